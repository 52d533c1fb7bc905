"""Clock fit of device time tags against receive stamps: drift, offset, jitter, outlier gating."""

from __future__ import annotations

import numpy as np
import pytest

from drivers.timing import DAY_NS, fit_clock, unwrap_time_of_day_ns


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
