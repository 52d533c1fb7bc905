"""PPS labelling into the clock model (TimeKeeper), the cached clock estimate, the log batcher and
the CAN frame records — the daemon's record plumbing, without I/O."""

from __future__ import annotations

import asyncio
import time

import numpy as np
import pytest

from acquire.alarms import AlarmBook
from acquire.log.batch import LogBatcher
from acquire.timing.clock import HOST_TIME_STATE, ClockModel, ClockState
from acquire.timing.timekeeper import ClockCache, TimeKeeper, coarse_gps_offset_ns
from drivers.base import DriverError
from drivers.can import can_frame_bytes, parse_can_frame
from drivers.pps import PpsEdge
from tests.drivers.helpers import fake_host_clock, step_host_clock
from tests.waiting import wait_until_async

NS = 1_000_000_000
H0 = 5_000 * NS  # host monotonic of the first pulse
G0 = 1_400_000_000  # its GPS second


class Log:
    def __init__(self):
        self.rows = []

    def __call__(self, topic, payload, *, host_ns, device_ns=None):
        self.rows.append((topic, payload, host_ns, device_ns))
        return True


def test_pulses_are_labelled_by_time_messages_and_every_pulse_is_logged_once():
    clock, log, states = ClockModel(), Log(), []
    tk = TimeKeeper(clock, log, lambda old, new, t: states.append((old, new)))
    for k in range(8):
        edge = PpsEdge(H0 + k * NS + (k % 3) * 7_000, "pps", k + 1)
        tk.on_edge(edge)
        if k == 5:
            tk.on_edge(edge)  # the same pulse again (a duplicated datagram)
        if k != 6:  # no time message for the 7th pulse
            tk.on_time(G0 + k, H0 + k * NS + 50_000_000)
        tk.tick(H0 + k * NS + 100_000_000)
    tk.tick(H0 + 9 * NS)
    rows = [r[1] for r in log.rows]
    by_seq = {}
    for r in rows:
        by_seq.setdefault(r["sequence"], []).append(r["reason"])
    assert by_seq[6] == ["duplicate", "accepted"]  # logged at once / when labelled
    assert by_seq[7] == ["unlabelled"]
    assert all(by_seq[s] == ["accepted"] for s in (1, 2, 3, 4, 5, 8))
    labelled = [(p["gps_s"], h, d) for _, p, h, d in log.rows if p["gps_s"] is not None]
    assert [g for g, _, _ in labelled] == [G0 + k for k in (0, 1, 2, 3, 4, 5, 7)]
    assert all(d == g * NS and h // NS == H0 // NS + g - G0 for g, h, d in labelled)
    assert clock.edges_accepted == 7
    # locked at the 4th edge; 2 s after the last labelled pulse: holdover
    assert states == [(ClockState.UNLOCKED, ClockState.LOCKED), (ClockState.LOCKED, ClockState.HOLDOVER)]
    assert tk.status()["unlabelled"] == 1 and tk.status()["duplicate_edges"] == 1


def test_clock_cache_gives_the_models_estimate_and_refreshes_after_an_edge():
    clock = ClockModel(coarse_offset_ns=123 * NS)
    cache = ClockCache(clock)
    assert cache.estimate(H0) == (H0 + 123 * NS, HOST_TIME_STATE)  # no PPS fit: host time
    rng = np.random.default_rng(3)
    for k in range(10):  # host runs 35 ppm slow against GPS, 20 µs jitter
        clock.add_edge(H0 + round(k * NS / (1 + 35e-6)) + int(rng.normal(0, 20_000)), G0 + k)
        cache.invalidate()
    for h in H0 + 9 * NS + np.sort(rng.integers(0, 3 * NS // 2, 2000)):
        gps, state = cache.estimate(int(h))
        est = clock.to_gps(int(h))
        assert abs(gps - est.gps_ns) <= 1 and state == est.state.value
    assert abs(coarse_gps_offset_ns() - coarse_gps_offset_ns()) < 1_000_000


def test_log_batcher_keeps_the_order_stamps_the_clock_and_hands_over_in_batches():
    batches = []

    def submit_batch(records):
        batches.append(list(records))
        return len(records)

    clock = ClockModel(coarse_offset_ns=7 * NS)
    b = LogBatcher(submit_batch, ClockCache(clock), period_s=0.01, max_items=50)

    async def run():
        for i in range(120):
            b.submit("/lidar/raw" if i % 2 else "/ins/raw", bytes([i]), host_ns=H0 + i, device_ns=i or None)
        assert [len(x) for x in batches] == [50, 50]  # two full batches handed over at once
        await wait_until_async(lambda: len(batches) == 3, 10, "the rest after the period")

    asyncio.run(run())
    assert [len(x) for x in batches] == [50, 50, 20]
    calls = [r for x in batches for r in x]  # (topic, payload, host_ns, device_ns, log_time_ns, clock_state)
    assert [c[1] for c in calls] == [bytes([i]) for i in range(120)]
    assert [c[0] for c in calls[:2]] == ["/ins/raw", "/lidar/raw"] and all(
        c[2] == H0 + i for i, c in enumerate(calls)
    )
    assert all(c[4] == H0 + i + 7 * NS and c[5] == HOST_TIME_STATE for i, c in enumerate(calls))
    assert calls[0][3] is None and calls[5][3] == 5
    assert b.batches == 3 and b.records == 120


@pytest.mark.parametrize(
    ("arb", "data", "ext"),
    [
        (0x6E0, b"\xe1\x01\x03\x00\x01\x00\x00\x00", False),
        (0x1ABCDE, b"", True),
        (0x123, bytes(range(48)), False),
    ],
)
def test_can_frames_are_stored_as_socketcan_frames(arb, data, ext):
    raw = can_frame_bytes(arb, data, ext)
    assert len(raw) == (16 if len(data) <= 8 else 72)
    assert parse_can_frame(raw) == (arb, data, ext)
    with pytest.raises(DriverError, match="17 bytes: expected 16 or 72"):
        parse_can_frame(raw[:16] + b"x")


def test_log_batcher_submit_many_stamps_as_submit_does_one_by_one():
    one, many = [], []
    clock = ClockModel(coarse_offset_ns=7 * NS)
    a = LogBatcher(lambda r: one.extend(r) or len(r), ClockCache(clock), max_items=50)
    b = LogBatcher(lambda r: many.extend(r) or len(r), ClockCache(clock), max_items=50)
    payloads = [bytes([i]) for i in range(80)]
    hosts = [H0 + 3_000_000 * i for i in range(80)]  # 0.24 s: past the cache's 50 ms
    tags = [H0 + i if i % 3 else None for i in range(80)]
    for p, h, t in zip(payloads, hosts, tags):
        a.submit("/lidar/raw", p, host_ns=h, device_ns=t)
    for s in (slice(0, 30), slice(30, 31), slice(31, 80)):
        b.submit_many("/lidar/raw", payloads[s], hosts[s], tags[s])
    a.flush()
    b.flush()
    assert many == one and len(one) == 80 and one[4][3] == H0 + 4 and one[3][3] is None


def _keeper(alarms, log=None):
    return TimeKeeper(ClockModel(), log, alarms=alarms)


def _pulses(tk, g0: int, seconds, latency_ns=50_000_000, late: dict | None = None):
    """Pulses 1 s apart from H0 labelled from GPS second g0, their time message ``latency_ns``
    after them (``late``: k → another latency), a tick after each."""
    for k in seconds:
        tk.on_edge(PpsEdge(H0 + k * NS, "pps", k + 1))
        tk.on_time(g0 + k, H0 + k * NS + (late or {}).get(k, latency_ns))
        tk.tick(H0 + k * NS + 900_000_000)


def test_a_late_time_message_raises_time_ambiguous_and_its_pulse_is_logged_ambiguous():
    alarms, log = AlarmBook(), Log()
    tk = _keeper(alarms, log)
    _pulses(tk, G0, range(8), late={6: 850_000_000})
    a = alarms.get("time_ambiguous", "clock")
    assert a is not None and a.active and a.severity == "warning"
    assert f"GPS second {G0 + 6} came 850.0 ms after the latest pulse, expected 50.0 ± 50.0 ms" in a.message
    reasons = {p["sequence"]: p["reason"] for _, p, _, _ in log.rows}
    assert reasons[7] == "ambiguous" and reasons[8] == "accepted"
    assert tk.clock.edges_accepted == 7 and tk.status()["time_ambiguous"] == 1
    _pulses(tk, G0, range(8, 19))  # on time again: cleared 10 s after the last one
    assert not alarms.is_active("time_ambiguous", "clock")
    assert [e.action for e in alarms.drain() if e.alarm.name == "time_ambiguous"] == ["raise", "clear"]


@pytest.fixture
def builtin_leap_table():
    """The built-in leap-second table in use for the test, whatever another test left."""
    from calib.core import gpstime

    with gpstime.leap_table_scope():
        yield


@pytest.mark.usefixtures("builtin_leap_table")
def test_leap_table_stale_past_the_expiry_and_a_mismatching_announced_gps_minus_utc():
    from calib.core.frames import utc_fields_to_gps_ns

    alarms = AlarmBook()
    tk = _keeper(alarms)
    _pulses(tk, utc_fields_to_gps_ns(2026, 12, 27, 86_390 * NS) // NS, range(6))  # the table's last day
    assert not alarms.is_active("leap_table_stale", "clock")
    _pulses(tk, utc_fields_to_gps_ns(2026, 12, 27, 86_390 * NS) // NS, range(6, 12))  # 10 s on: 2026-12-28
    a = alarms.get("leap_table_stale", "clock")
    assert a.active and "the leap-second table expired on 2026-12-28" in a.message
    tk.on_gps_minus_utc(19)
    tk.tick(H0 + 12 * NS)
    m = alarms.get("leap_second_mismatch", "clock")
    assert m.active and "applies GPS − UTC = 19 s, the leap-second table 18 s" in m.message
    tk.on_gps_minus_utc(18)
    tk.tick(H0 + 12 * NS + 250_000_000)
    assert not alarms.is_active("leap_second_mismatch", "clock")
    assert tk.status()["leap_table"]["expires"] == "2026-12-28"


def test_a_step_of_the_host_clock_raises_host_clock_step_and_refreshes_the_seed(tmp_path):
    alarms = AlarmBook()
    now = time.monotonic_ns()
    path = tmp_path / "host_clock"
    fake = fake_host_clock(path, [])
    clock = ClockModel(coarse_offset_ns=coarse_gps_offset_ns(fake))
    tk = TimeKeeper(clock, alarms=alarms, host_clock=fake)
    seed = clock.coarse_offset_ns
    tk.tick(now)
    assert not alarms.is_active("host_clock_step", "clock")
    step_host_clock(path, time.monotonic_ns(), 5 * NS)  # the step, made now
    tk.tick(now + 250_000_000)
    a = alarms.get("host_clock_step", "clock")
    assert a.active and "the host's realtime clock stepped by +5.000 s" in a.message
    assert abs(clock.coarse_offset_ns - seed - 5 * NS) < 1_000_000
    tk.tick(now + 11 * NS)
    assert not alarms.is_active("host_clock_step", "clock")
    assert tk.status()["host_clock_steps"] == fake.steps_seen.count == 1


def test_a_few_milliseconds_step_is_counted_and_followed_without_an_alarm(tmp_path):
    """A virtual machine's clock discipline steps the realtime clock by a millisecond or two:
    the seed follows it, the metrics count it, nobody is alarmed; a 10-ms step alarms."""
    alarms = AlarmBook()
    now = time.monotonic_ns()
    path = tmp_path / "host_clock"
    fake = fake_host_clock(path, [])
    clock = ClockModel(coarse_offset_ns=coarse_gps_offset_ns(fake))
    tk = TimeKeeper(clock, alarms=alarms, host_clock=fake)
    seed, before = clock.coarse_offset_ns, tk.status()
    tk.tick(now)
    step_host_clock(path, time.monotonic_ns(), 3_000_000)  # each step made when the test says
    tk.tick(now + 250_000_000)
    assert not alarms.is_active("host_clock_step", "clock")
    assert abs(clock.coarse_offset_ns - seed - 3_000_000) < 1_000_000
    assert tk.status()["host_clock_steps"] == before["host_clock_steps"] + 1
    assert tk.status()["host_clock_steps_alarmed"] == before["host_clock_steps_alarmed"]
    step_host_clock(path, time.monotonic_ns(), 12_000_000)
    tk.tick(now + 500_000_000)
    a = alarms.get("host_clock_step", "clock")
    after = tk.status()
    assert after["host_clock_steps_alarmed"] == before["host_clock_steps_alarmed"] + 1
    small = after["host_clock_steps"] - after["host_clock_steps_alarmed"]
    assert a.active and "stepped by +0.012 s" in a.message and f"{small} smaller" in a.message


def test_the_daemon_takes_a_newer_iers_list_from_tzdata_and_names_what_it_did(tmp_path):
    import datetime as dt

    from calib.core import gpstime
    from drivers.hydrins.timeofday import resolve_gps_ns

    def ntp(d: dt.date) -> int:
        return (d - dt.date(1900, 1, 1)).days * 86_400

    rows = "".join(f"{ntp(d)}\t{n + 19}\n" for d, n in gpstime.BUILTIN.steps)
    newer = tmp_path / "leap-seconds.list"  # with a leap second on 2027-07-01, expiring later
    newer.write_text(
        f"#$\t{ntp(dt.date(2027, 1, 7))}\n#@\t{ntp(dt.date(2027, 12, 28))}\n{rows}{ntp(dt.date(2027, 7, 1))}\t38\n"
    )
    july_2027_unix_ns = 1_814_400_000 * NS
    noon_ns = 43_200 * NS
    in_use = gpstime.leap_table()
    with gpstime.leap_table_scope():  # from the built-in table; the table installed ends with the test
        # an INS time of day on 2027-07-01, dated by the built-in table (18 s; the decoder's cache filled)
        builtin_gps_ns = resolve_gps_ns(noon_ns, july_2027_unix_ns + noon_ns)
        tk = TimeKeeper(ClockModel(), leap_list=newer)
        assert tk.leap_note == f"{newer} in use"
        assert tk.status()["leap_table"]["expires"] == "2027-12-28"
        assert gpstime.leap_table().gps_minus_utc_at_unix_ns(july_2027_unix_ns) == 19
        # the decoders follow the table installed (their cache is keyed on it)
        assert resolve_gps_ns(noon_ns, july_2027_unix_ns + noon_ns) == builtin_gps_ns + NS
        assert TimeKeeper(ClockModel(), leap_list=newer).leap_note.endswith("not newer than the table in use")
        newer.write_text("#@ 1\n")
        assert "not used: " in TimeKeeper(ClockModel(), leap_list=newer).leap_note
    assert gpstime.leap_table() is in_use
