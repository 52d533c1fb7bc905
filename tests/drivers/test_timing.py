"""Clock fit of device time tags against receive stamps: drift, offset, jitter, outlier gating;
the host's realtime clock: steps counted, kernel stamps converted across a step, the fake."""

from __future__ import annotations

import time

import numpy as np
import pytest

from drivers import timing
from drivers.timing import DAY_NS, fit_clock, unwrap_time_of_day_ns
from tests.drivers.helpers import fake_host_clock, realtime_offset_bounds_ns, step_host_clock


def test_fit_recovers_drift_offset_and_jitter_and_gates_outliers():
    rng = np.random.default_rng(3)
    device = np.arange(400, dtype=np.int64) * 500_000_000  # 2 Hz for 200 s
    jitter = rng.normal(0.0, 80e-6, device.size)
    host = 1_000_000_000_000 + 12_345_678 + device + np.round(device * -35e-6 + jitter * 1e9).astype(np.int64)
    host[[50, 200]] += 30_000_000  # two datagrams delayed by 30 ms
    fit = fit_clock(host, device)
    assert fit.n == 398 and fit.n_outliers == 2
    assert fit.drift_ppm == pytest.approx(-35.0, abs=0.5)
    assert fit.offset_s == pytest.approx(1000.012345678, abs=30e-6)
    assert fit.jitter_rms_s == pytest.approx(80e-6, rel=0.15)
    assert fit.jitter_max_s < 5 * 80e-6 and fit.span_s == pytest.approx(199.5)


def test_millisecond_stamps_are_not_gated_as_outliers():
    device = np.arange(600, dtype=np.int64) * 1_000_000_000 + 170_000_000
    host = device + 115_000_000 + np.where(np.arange(600) % 7 == 0, 1_000_000, 0)
    fit = fit_clock(host, device)
    assert fit.n_outliers == 0 and fit.offset_s == pytest.approx(0.1151, abs=0.0005)


def test_unwrap_time_of_day_across_midnight():
    tod = np.array([DAY_NS - 2_000_000_000, DAY_NS - 1_000_000_000, 0, 1_000_000_000])
    assert np.array_equal(np.diff(unwrap_time_of_day_ns(tod)), [1_000_000_000] * 3)


def test_fit_needs_three_samples():
    with pytest.raises(ValueError, match="length >= 3"):
        fit_clock([1, 2], [1, 2])


def test_a_step_of_the_realtime_clock_is_counted_by_any_read_of_the_offset(tmp_path):
    path = tmp_path / "host_clock"
    fake = fake_host_clock(path, [])
    before = fake.realtime_minus_monotonic_ns()
    count = fake.steps_seen.count
    lo, hi = realtime_offset_bounds_ns()
    assert lo - 1_000_000 < before < hi + 1_000_000  # no step yet: the real offset
    at = time.monotonic_ns()  # the step, made now: every read from here on sees it
    step_host_clock(path, at, -3_600 * 10**9)
    after = fake.realtime_minus_monotonic_ns()
    assert abs(after - before + 3_600 * 10**9) < 1_000_000
    assert fake.steps_seen.count == count + 1
    assert fake.steps_seen.last is not None
    t, step = fake.steps_seen.last
    assert step == pytest.approx(-3_600 * 10**9, abs=1_000_000)
    assert t >= at
    fake.realtime_minus_monotonic_ns()  # no second step
    assert fake.steps_seen.count == count + 1
    # kernel stamps taken after the step move with it, those before do not
    real_now = time.clock_gettime_ns(time.CLOCK_REALTIME)
    assert fake.kernel_stamp(real_now) == real_now - 3_600 * 10**9
    real_before = at + before - 10**9  # a realtime stamp 1 s before the step
    assert fake.kernel_stamp(real_before) == real_before


def test_each_host_clock_counts_its_own_steps_and_the_real_one_reads_the_kernel(tmp_path):
    """No process-wide counter: a fake's steps are its own, a real clock (the default of
    whoever reads one) sees none of them, and a transport's stamps on the real clock stay exact."""
    path = tmp_path / "host_clock"
    fake, real = fake_host_clock(path, []), timing.HostClock()
    assert not real.fake
    assert fake.fake
    fake.realtime_minus_monotonic_ns()
    real.realtime_minus_monotonic_ns()
    step_host_clock(path, time.monotonic_ns(), 5 * 10**9)
    fake.realtime_minus_monotonic_ns()
    offset = real.realtime_minus_monotonic_ns()
    assert (fake.steps_seen.count, fake.steps_seen.large) == (1, 1)
    assert (real.steps_seen.count, real.steps_seen.large) == (0, 0)
    lo, hi = realtime_offset_bounds_ns()
    assert lo - 1_000_000 < offset < hi + 1_000_000
    assert real.kernel_stamp(12345) == 12345
    stamps = timing.RealtimeStamps()
    stamps.begin()
    assert stamps.exact
    assert stamps.steps == 0
    on_fake = timing.RealtimeStamps(clock=fake)
    on_fake.begin()
    assert not on_fake.exact


@pytest.mark.parametrize("step_s", [-3600.0, 2.0])
def test_realtime_stamps_taken_before_a_step_keep_their_offset(tmp_path, step_s):
    """Kernel stamps of datagrams that arrived before the step and are read after it: converted
    with the new offset they would move by the step; they keep the old one. (The raw stamps are
    the real kernel's: ``convert`` moves those taken after the step, as the faked clock would.)
    The step is written when the first read is done, its instant 50 ms back: the arrivals lie
    before it, and a stamp after it, whatever the machine's pace."""
    path = tmp_path / "host_clock"
    stamps = timing.RealtimeStamps(clock=fake_host_clock(path, []))
    stamps.begin()  # the read before the step
    at = time.monotonic_ns() - 50_000_000
    before = [at - k * 10_000_000 for k in range(4, 0, -1)]  # monotonic arrivals before the step
    step_host_clock(path, at, round(step_s * 10**9))
    lo, hi = realtime_offset_bounds_ns()
    real_off = (lo + hi) // 2
    stamps.begin()  # the read, after the step
    assert stamps.steps == 1 and not stamps.exact
    read = time.monotonic_ns()
    got = [stamps.convert(m + real_off, read) for m in before]
    after = at + 25_000_000
    got.append(stamps.convert(after + real_off, read))  # a stamp after the step (faked by convert)
    assert max(abs(g - m) for g, m in zip(got, before + [after])) < 500_000
    assert (stamps.repaired, stamps.unknown) == (4, 0)
