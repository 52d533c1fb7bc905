"""``host_clock_offset`` (issue 26): the host's system clock off GPS time by more than the
configured limit once the PPS gives GPS time — raised with the offset and a hint at chrony,
cleared when back within the limit; never judged before the lock. Injected host clock, no sleeps."""

from __future__ import annotations

import pytest

from acquire.alarms import AlarmBook
from acquire.daemon.config import VesselConfigError, parse_vessel_config
from acquire.timing.clock import ClockModel, ClockParams
from acquire.timing.timekeeper import TimeKeeper
from drivers.pps import PpsEdge

NS = 1_000_000_000
H0 = 5_000 * NS  # host monotonic of the first pulse
G0 = 1_400_000_000  # its GPS second
TRUE_OFFSET_NS = G0 * NS - H0  # GPS − host monotonic, as the pulses say
DAYS_41_S = 41 * 86_400


class HostClock:
    """GPS − host monotonic as the host's system clock says it: the truth + ``error_ns``."""

    def __init__(self, error_ns: int) -> None:
        self.error_ns = error_ns

    def __call__(self) -> int:
        return TRUE_OFFSET_NS + self.error_ns


def _keeper(host: HostClock, params: ClockParams | None = None) -> tuple[TimeKeeper, AlarmBook]:
    alarms = AlarmBook()
    clock = ClockModel(params, coarse_offset_ns=host())
    return TimeKeeper(clock, alarms=alarms, host_gps_offset_ns=host), alarms


def _pulse(tk: TimeKeeper, k: int) -> None:
    """Pulse k (1 s apart from H0), its time message 50 ms later, a tick 0.9 s after it."""
    tk.on_edge(PpsEdge(H0 + k * NS, "pps", k + 1))
    tk.on_time(G0 + k, H0 + k * NS + 50_000_000)
    tk.tick(H0 + k * NS + 900_000_000)


def test_a_host_clock_41_days_behind_is_alarmed_once_locked_and_cleared_when_fixed():
    host = HostClock(-DAYS_41_S * NS)
    tk, alarms = _keeper(host)
    for k in range(3):  # fewer edges than min_edges: GPS time not known yet, nothing judged
        _pulse(tk, k)
        assert alarms.get("host_clock_offset", "clock") is None
    _pulse(tk, 3)  # the 4th edge: LOCKED
    a = alarms.get("host_clock_offset", "clock")
    assert a is not None and a.active and a.severity == "warning"
    assert a.message.startswith("host clock 3,542,400.000 s behind GPS time (limit 1 s)"), a.message
    assert "chrony (or gpsd)" in a.message and "chronyc tracking" in a.message
    assert tk.status()["host_clock_offset_s"] == -3_542_400.0
    host.error_ns = 2_000_000  # chrony stepped it: 2 ms ahead
    _pulse(tk, 4)
    assert not alarms.is_active("host_clock_offset", "clock")
    assert [(e.action, e.alarm.name) for e in alarms.drain()] == [
        ("raise", "host_clock_offset"),
        ("clear", "host_clock_offset"),
    ]
    assert alarms.get("host_clock_offset", "clock").message == "host clock within 1 s of GPS time (+0.002 s)"


def test_ahead_of_gps_and_the_configured_limit():
    tk, alarms = _keeper(HostClock(3 * NS), ClockParams(host_offset_alarm_ns=5 * NS))
    for k in range(6):
        _pulse(tk, k)
    assert not alarms.is_active("host_clock_offset", "clock")
    tk, alarms = _keeper(HostClock(1_500_000_000))
    for k in range(6):
        _pulse(tk, k)
    assert (
        "host clock 1.500 s ahead of GPS time (limit 1 s)" in alarms.get("host_clock_offset", "clock").message
    )


def test_while_unlocked_again_the_alarm_keeps_its_state():
    host = HostClock(-DAYS_41_S * NS)
    tk, alarms = _keeper(host)
    for k in range(5):
        _pulse(tk, k)
    assert alarms.is_active("host_clock_offset", "clock")
    host.error_ns = 0
    tk.tick(H0 + 3600 * NS)  # no pulse for an hour: past holdover, UNLOCKED — not judged
    assert tk.state.value == "UNLOCKED" and alarms.is_active("host_clock_offset", "clock")


def _vessel(clock: str) -> str:
    return (
        "vessel: v\ndevices:\n  - {name: ins, kind: ins, protocol: stdbin, "
        f"transport: {{type: tcp, host: 10.0.0.2, port: 8110}}}}\nsession: {{directory: logs}}\n{clock}"
    )


def test_the_limit_is_the_clock_sections_host_offset_alarm_s():
    assert parse_vessel_config(_vessel("")).clock.host_offset_alarm_ns == NS
    cfg = parse_vessel_config(_vessel("clock: {host_offset_alarm_s: 0.25}\n"))
    assert cfg.clock.host_offset_alarm_ns == 250_000_000
    with pytest.raises(VesselConfigError) as exc:
        parse_vessel_config(_vessel("clock: {host_offset_alarm_s: 0}\n"), source="v.yaml")
    (err,) = exc.value.errors
    assert err.startswith("v.yaml:5:") and "clock.host_offset_alarm_s: got 0" in err
