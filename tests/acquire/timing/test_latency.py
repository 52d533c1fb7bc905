"""Latency monitor and sync check on synthetic streams (and one real capture)."""

from __future__ import annotations

import datetime as dt

import numpy as np
import pytest

from acquire.alarms import AlarmBook
from acquire.timing.clock import ClockModel, ClockState, GpsEstimate
from acquire.timing.latency import LatencyLimits, LatencyMonitor, MonitorParams
from tests.drivers.helpers import REAL

NS = 1_000_000_000
MS = 1_000_000
HOST0_NS = 5_000 * NS
OFFSET_NS = 1_400_000_000 * NS  # GPS − host of the stub clock


class StubClock:
    """A locked clock with a known offset (the monitor is tested apart from the clock model)."""

    def __init__(self, state=ClockState.LOCKED):
        self.state = state

    def to_gps(self, host_ns: int) -> GpsEstimate:
        return GpsEstimate(host_ns + OFFSET_NS, self.state, 1000)


def stream(
    monitor,
    device,
    rate_hz,
    t_end_s,
    latency_ns,
    *,
    t_start_s=0.0,
    tag_offset_ns=None,
    pps_flag=None,
    rng=None,
    skip=None,
    tick_s=0.25,
):
    """Run a device stream through the monitor; return [(t_s, event)] in stream order.

    The device measures at true GPS times on a grid; the record is received ``latency_ns(t)``
    later; its time tag is the true time + ``tag_offset_ns(t)`` (a device clock error).
    """
    rng = rng or np.random.default_rng(1)
    events = []
    next_tick = t_start_s
    for t in np.arange(t_start_s, t_end_s, 1.0 / rate_hz):
        if skip is not None and skip(t):
            continue
        while next_tick <= t:
            events += [(next_tick, e) for e in monitor.tick(HOST0_NS + int(next_tick * NS))]
            next_tick += tick_s
        true_gps = OFFSET_NS + HOST0_NS + int(t * NS)
        host = true_gps - OFFSET_NS + int(latency_ns(t) + rng.normal(0.0, 0.3 * MS))
        tag = true_gps + (int(tag_offset_ns(t)) if tag_offset_ns else 0)
        flag = pps_flag(t) if pps_flag else None
        events += [(t, e) for e in monitor.observe(device, host, tag, pps_flag=flag)]
    return events


def raised(events, name=None):
    return [(t, e.alarm.name) for t, e in events if e.action == "raise" and name in (None, e.alarm.name)]


def monitor_with(device="ins", **limits):
    m = LatencyMonitor(StubClock(), AlarmBook(to_gps=lambda host_ns: host_ns + OFFSET_NS))
    defaults = dict(
        band_ns=(0, 30 * MS),
        jump_ns=5 * MS,
        max_sigma_ns=2 * MS,
        max_drift_ppm=10.0,
        rate_hz=200.0,
        gap_ns=NS,
    )
    m.add_device(device, LatencyLimits(**{**defaults, **limits}))
    return m


def test_steady_stream_gives_correct_statistics_and_no_alarm():
    m = monitor_with()
    events = stream(m, "ins", 200, 75.0, lambda t: 8 * MS + 0.05 * MS * np.sin(t))
    assert events == []
    s = m.stats("ins")
    assert s.sync == "ok" and s.n == pytest.approx(2000, abs=60)  # 10 s window at 200 Hz
    assert s.mean_ns == pytest.approx(8 * MS, abs=0.05 * MS)
    assert s.sigma_ns == pytest.approx(0.3 * MS, rel=0.1)
    assert s.p99_ns == pytest.approx(8 * MS + 2.33 * 0.3 * MS, abs=0.15 * MS)
    assert s.max_ns > s.p99_ns > s.mean_ns
    assert s.rate_hz == pytest.approx(200.0, abs=1.0)
    assert abs(s.drift_ppm) < 2.0
    d = m.snapshot()["ins"]
    assert d["latency_mean_ms"] == pytest.approx(8.0, abs=0.05) and d["sync"] == "ok"


def test_20ms_ins_latency_jump_raises_latency_jump_within_2s_and_clears_when_back():
    m = monitor_with()
    events = stream(m, "ins", 200, 80.0, lambda t: 8 * MS + (20 * MS if 40.0 <= t < 60.0 else 0))
    r = raised(events)
    assert [name for _, name in r] == ["latency_jump"], r
    assert 40.0 <= r[0][0] <= 42.0
    alarm = m.alarms.get("latency_jump", "ins")
    assert not alarm.active and alarm.severity == "warning"
    cleared = [t for t, e in events if e.action == "clear" and e.alarm.name == "latency_jump"]
    assert len(cleared) == 1 and 60.0 <= cleared[0] <= 63.0
    raise_event = next(e for _, e in events if e.action == "raise")
    assert (
        "(+19.99" in raise_event.alarm.message
        or "(+20.00" in raise_event.alarm.message
        and raise_event.alarm.device == "ins"
    )
    assert raise_event.alarm.first_gps_ns == raise_event.alarm.first_host_ns + OFFSET_NS


def test_1s_profiler_offset_raises_time_step_within_2s_and_not_a_jump():
    m = monitor_with("profiler", band_ns=(0, 20 * MS))
    events = stream(
        m, "profiler", 200, 50.0, lambda t: 3 * MS, tag_offset_ns=lambda t: -NS if t >= 30.0 else 0
    )
    r = raised(events)
    assert [name for _, name in r] == ["time_step"], r
    assert 30.0 <= r[0][0] <= 32.0
    a = m.alarms.get("time_step", "profiler")
    assert a.active and a.severity == "critical" and "+1.00" in a.message


def test_a_device_one_second_off_from_the_start_is_a_time_step():
    m = monitor_with("profiler", band_ns=(0, 20 * MS))
    events = stream(m, "profiler", 200, 5.0, lambda t: 3 * MS, tag_offset_ns=lambda t: NS)
    assert raised(events) == [(pytest.approx(0.0, abs=0.3), "time_step")]


def test_isolated_outliers_do_not_raise_and_hysteresis_holds_near_the_threshold():
    m = monitor_with()

    def latency(t):
        base = 8 * MS
        if abs(t % 2.0) < 1e-9:
            return base + 60 * MS  # one wild sample every 2 s
        if 20.0 <= t < 30.0:
            return base + 6 * MS  # above the 5 ms threshold: raise
        if 30.0 <= t < 40.0:
            return base + 3 * MS  # below it but above half of it: stays raised
        return base  # back: clears

    events = stream(m, "ins", 200, 50.0, latency)
    jumps = [(t, e.action) for t, e in events if e.alarm.name == "latency_jump"]
    assert [a for _, a in jumps] == ["raise", "clear"], jumps
    assert 20.0 <= jumps[0][0] <= 22.0 and 40.0 <= jumps[1][0] <= 43.0


def test_a_persistent_jump_is_relearned_as_the_new_baseline():
    m = LatencyMonitor(StubClock(), AlarmBook(), MonitorParams(relearn_ns=30 * NS))
    m.add_device("ins", LatencyLimits(band_ns=(0, 50 * MS), jump_ns=5 * MS, rate_hz=200.0))
    events = stream(m, "ins", 200, 90.0, lambda t: 8 * MS + (20 * MS if t >= 20.0 else 0))
    jumps = [(t, e.action) for t, e in events if e.alarm.name == "latency_jump"]
    assert [a for _, a in jumps] == ["raise", "clear"]
    assert 50.0 <= jumps[1][0] <= 55.0
    assert m.stats("ins").baseline_ns == pytest.approx(28 * MS, abs=0.2 * MS)


def test_drifting_device_clock_raises_clock_drift_and_a_small_drift_does_not():
    m = monitor_with()
    events = stream(
        m, "ins", 200, 80.0, lambda t: 8 * MS, tag_offset_ns=lambda t: -20e-6 * t * NS
    )  # device clock 20 ppm slow
    r = raised(events)
    assert [n for _, n in r] == ["clock_drift"]
    assert 60.0 <= r[0][0] <= 70.0  # 60 s of 1-s medians, then 5 s to confirm
    assert m.stats("ins").drift_ppm == pytest.approx(20.0, abs=1.0)
    m2 = monitor_with()
    assert stream(m2, "ins", 200, 80.0, lambda t: 8 * MS, tag_offset_ns=lambda t: -3e-6 * t * NS) == []
    assert m2.stats("ins").drift_ppm == pytest.approx(3.0, abs=1.0)


def test_pps_flag_lost_raises_at_once_and_clears_after_it_is_back():
    m = monitor_with()
    events = stream(m, "ins", 200, 30.0, lambda t: 8 * MS, pps_flag=lambda t: not (10.0 <= t < 15.0))
    flags = [(t, e.action) for t, e in events if e.alarm.name == "pps_flag_lost"]
    assert [a for _, a in flags] == ["raise", "clear"]
    assert 10.0 <= flags[0][0] <= 10.3 and 15.0 <= flags[1][0] <= 17.5
    assert m.alarms.get("pps_flag_lost", "ins").severity == "critical"


def test_data_gap_and_rate_drop():
    m = monitor_with()
    # a 3 s hole at 20 s, then half the rate from 40 s
    events = stream(
        m,
        "ins",
        200,
        60.0,
        lambda t: 8 * MS,
        skip=lambda t: 20.0 <= t < 23.0 or (t >= 40.0 and round(t * 200) % 2 == 1),
    )
    names = [(t, e.alarm.name, e.action) for t, e in events]
    gap = [x for x in names if x[1] == "data_gap"]
    assert [a for *_, a in gap] == ["raise", "clear"]
    assert 21.0 <= gap[0][0] <= 21.3 and gap[1][0] == pytest.approx(23.0, abs=0.01)
    assert m.alarms.get("data_gap", "ins").message.startswith("records again after 3.0")  # 3.005 s
    drops = [x for x in names if x[1] == "rate_drop"]
    assert drops[0][2] == "raise" and 40.0 <= drops[0][0] <= 44.0
    assert all(not (20.0 <= t < 24.0) for t, *_ in drops)  # the gap is not also a rate drop
    assert m.stats("ins").rate_hz == pytest.approx(100.0, abs=2.0)


def test_a_device_that_never_delivers_is_a_data_gap_from_the_first_look():
    """A device silent since the monitor first looked at it (the daemon's start: a port that
    cannot be opened, a cable never plugged) raises the critical data_gap after ``gap``."""
    m = monitor_with()
    ticks = [m.tick(HOST0_NS + k * NS // 4) for k in range(13)]  # 0 … 3 s, no record
    raises = [(k / 4, e.alarm.name) for k, evs in enumerate(ticks) for e in evs if e.action == "raise"]
    assert raises == [(1.25, "data_gap")]  # > 1 s of silence
    alarm = m.alarms.get("data_gap", "ins")
    assert alarm.severity == "critical" and alarm.message == "no record for 3.00 s (none since start)"
    assert m.stats("ins").last_age_ns is None and m.stats("ins").records == 0
    events = m.observe("ins", HOST0_NS + 3 * NS + NS // 10, OFFSET_NS + HOST0_NS + 3 * NS)
    assert [(e.action, e.alarm.name) for e in events] == [("clear", "data_gap")]
    assert m.alarms.get("data_gap", "ins").message == "first record after 3.10 s"
    # a device whose first record comes within ``gap`` of the first look raises nothing
    m2 = monitor_with()
    m2.tick(HOST0_NS)
    events = stream(m2, "ins", 200, 5.0, lambda t: 8 * MS, t_start_s=0.9)
    assert raised(events) == []


def test_no_sync_check_without_a_locked_clock_or_a_time_tag():
    m = LatencyMonitor(StubClock(ClockState.UNLOCKED))
    m.add_device("ins", LatencyLimits(rate_hz=200.0))
    events = stream(m, "ins", 200, 10.0, lambda t: 8 * MS, tag_offset_ns=lambda t: NS)
    assert raised(events) == []
    assert m.stats("ins").sync == "no_clock"
    m.add_device("can", LatencyLimits())
    m.observe("can", HOST0_NS, None)
    m.tick(HOST0_NS + NS // 2)
    assert m.stats("can").sync == "no_time_tag"


def _drifting_clock():
    """A real clock model, the GPS time of the first sample, and host(GPS) for a host 35 ppm fast."""
    rate = 1 + 35e-6  # GPS ns per host ns
    gps0 = OFFSET_NS + HOST0_NS

    def host_of(gps_ns):
        return HOST0_NS + round((gps_ns - gps0) / rate)

    return ClockModel(), gps0, host_of


def test_with_the_real_clock_model_fed_by_pps_edges():
    """Latency through the clock model itself: host drifts 35 ppm, PPS jitter 20 µs."""
    rng = np.random.default_rng(2)
    clock, gps0, host_of = _drifting_clock()
    m = LatencyMonitor(clock, AlarmBook(to_gps=clock.gps_ns))
    m.add_device("ins", LatencyLimits(band_ns=(0, 30 * MS), rate_hz=200.0))
    events, next_edge = [], 1
    for k in range(200 * 40):
        true_gps = gps0 + k * 5 * MS
        while gps0 + next_edge * NS + 300 * MS <= true_gps:  # labelled 0.3 s after the pulse
            clock.add_edge(
                host_of(gps0 + next_edge * NS) + round(rng.normal(0, 20_000)), gps0 // NS + next_edge
            )
            next_edge += 1
        host = host_of(true_gps) + 8 * MS + (20 * MS if k >= 200 * 30 else 0)
        events += m.observe("ins", host, true_gps)
    s = m.stats("ins")
    assert [e.alarm.name for e in events if e.action == "raise"] == ["latency_jump"]
    jump = m.alarms.get("latency_jump", "ins")
    assert abs(jump.first_gps_ns - (gps0 + 30 * NS)) <= 2 * NS
    assert s.sigma_ns < 0.1 * MS  # only the clock model's own error remains


def test_a_relock_after_unlabelled_pulses_does_not_move_the_latency():
    """The fault campaign's late ZDAs: three pulses go unlabelled (HOLDOVER), then the next
    labelled pulse relocks the clock model; the samples before, during and after are on one
    line (host drifts 35 ppm, PPS jitter 20 µs), so a jitter or jump alarm would be the device's."""
    rng = np.random.default_rng(5)
    clock, gps0, host_of = _drifting_clock()
    m = LatencyMonitor(clock, AlarmBook(to_gps=clock.gps_ns))
    m.add_device("ins", LatencyLimits(band_ns=(0, 30 * MS), rate_hz=100.0))
    events, states, next_edge, lat = [], [], 1, []
    for k in range(100 * 40):
        true_gps = gps0 + k * 10 * MS
        while gps0 + next_edge * NS + 300 * MS <= true_gps:  # labelled 0.3 s after the pulse
            if next_edge not in (20, 21, 22):  # their time messages came too late: unlabelled
                clock.add_edge(
                    host_of(gps0 + next_edge * NS) + round(rng.normal(0, 20_000)), gps0 // NS + next_edge
                )
            next_edge += 1
        host = host_of(true_gps) + 3 * MS + round(rng.uniform(0, 0.5 * MS))
        events += m.observe("ins", host, true_gps)
        states.append(clock.state_at(host))
        lat.append(clock.to_gps(host).gps_ns - true_gps)
    assert states[100 * 22] == ClockState.HOLDOVER and states[-1] == ClockState.LOCKED
    assert not [e.alarm.name for e in events if e.action == "raise"]
    # the latency through the relock: the device's own 3–3.5 ms, the clock model's error aside
    lat_ms = np.array(lat[100 * 10 :]) / MS
    assert 3.0 - 0.1 <= lat_ms.min() and lat_ms.max() <= 3.5 + 0.1
    assert m.stats("ins").sigma_ns < 0.2 * MS


def test_real_capture_nbp1406_zda_latency_115ms():
    """Seapath 330 ZDA on a ship's logger: host receive − ZDA time tag ≈ 115 ms, σ ≈ 0.35 ms."""
    path = REAL / "openrvdas-nbp1406" / "NBP1406_s330-2014-08-01"
    assert path.exists(), f"real capture missing: {path}"
    m = LatencyMonitor(StubClock(), AlarmBook())
    m.add_device(
        "s330",
        LatencyLimits(
            band_ns=(50 * MS, 200 * MS), jump_ns=5 * MS, max_sigma_ns=2 * MS, rate_hz=1.0, gap_ns=3 * NS
        ),
    )
    epoch = dt.datetime(1970, 1, 1, tzinfo=dt.UTC)
    events, n, lat_ms = [], 0, []
    for line in path.read_text().splitlines():
        stamp, _, sentence = line.partition(" ")
        if not sentence.startswith("$INZDA"):
            continue
        f = sentence.split(",")
        host = dt.datetime.fromisoformat(stamp.replace("Z", "+00:00"))
        tag = dt.datetime(int(f[4]), int(f[3]), int(f[2]), tzinfo=dt.UTC) + dt.timedelta(
            hours=int(f[1][0:2]), minutes=int(f[1][2:4]), seconds=float(f[1][4:])
        )
        host_ns = (host - epoch) // dt.timedelta(microseconds=1) * 1000 - OFFSET_NS
        tag_ns = (tag - epoch) // dt.timedelta(microseconds=1) * 1000
        events += m.observe("s330", host_ns, tag_ns)
        lat_ms.append((host - tag).total_seconds() * 1e3)
        n += 1
    assert n == 625
    assert events == []
    s = m.stats("s330")
    assert s.mean_ns / MS == pytest.approx(115.0, abs=1.0)
    assert s.sigma_ns / MS < 1.0
    assert s.mean_ns / MS == pytest.approx(np.mean(lat_ms[-10:]), abs=0.5)
    assert s.rate_hz == pytest.approx(1.0, abs=0.5)
