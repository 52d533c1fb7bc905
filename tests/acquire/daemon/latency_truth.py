"""The fault campaign's latency alarms judged against the truth (not a test module).

:func:`replay_latency_alarms` feeds the latency monitor (:class:`acquire.timing.latency.
LatencyMonitor`, the daemon's own code and limits) the records the daemon logged — each INS
epoch and each profile, with the daemon's host stamp and the device's time tag — and evaluates
it at the daemon's monitor rounds (``/latency``), with one difference: the GPS time of a stamp
comes from the emulators' truth clock instead of the daemon's PPS clock model. An alarm the
replay raises too is a fact about the latency the devices were received with on this host (on a
loaded machine the emulators send late and the reader stamps late); one it does not raise comes
from the daemon's clock model (a re-anchor, a wrong label), which is what the campaign must catch.
"""

from __future__ import annotations

from pathlib import Path

from acquire.alarms import AlarmBook
from acquire.daemon.config import load_vessel_config
from acquire.log.read import iter_messages
from acquire.timing.clock import ClockState, GpsEstimate
from acquire.timing.latency import ALARM_DELAYS_S, LatencyMonitor
from drivers.zf.assembler import ProfileAssembler

#: the alarms drawn from the latency samples (the monitor's others watch the data flow)
LATENCY_ALARMS = ("time_step", "latency_jump", "latency_out_of_band", "latency_jitter", "clock_drift")
assert set(LATENCY_ALARMS) <= set(ALARM_DELAYS_S)


class _TruthClock:
    """The truth clock, in the daemon's clock states (from its ``clock_state`` events: a sample
    the daemon did not take, while UNLOCKED, is not taken either)."""

    def __init__(self, truth, states: list[tuple[int, str]]):
        self.truth, self.states = truth, states

    def to_gps(self, host_ns: int) -> GpsEstimate:
        state = next((to for h, to in reversed(self.states) if h <= host_ns), "UNLOCKED")
        return GpsEstimate(self.truth.gps_ns(host_ns), ClockState(state), 0)


def replay_latency_alarms(session: Path, truth, vessel_yaml: Path) -> list[tuple[str, str, int, int | None]]:
    """``(alarm name, device, raised at, cleared at or None)`` of the latency alarms of the
    replay (module docstring), in host monotonic ns."""
    events = [m.payload | {"h": m.host_ns} for m in iter_messages(session, {"/events"})]
    states = [(e["h"], e["to"]) for e in events if e["event"] == "clock_state"]
    config = load_vessel_config(vessel_yaml)
    monitor = LatencyMonitor(_TruthClock(truth, states), AlarmBook())
    for d in config.devices:
        if d.kind in ("ins", "profiler"):
            monitor.add_device(d.name, d.latency)
    assert {d.name: d.kind for d in config.devices if d.kind in ("ins", "profiler")} == {
        "ins": "ins",
        "profiler": "profiler",
    }, "the campaign's vessel: one INS (/ins/nav) and one profiler (/lidar/raw)"
    inputs: list[tuple[int, int, str | None, int | None, bool | None]] = []  # (host, 0, device, tag, pps)
    for m in iter_messages(session, {"/ins/nav"}):
        p = m.payload  # the daemon passes the tag when the INS says it is on UTC
        inputs.append((m.host_ns, 0, "ins", p["gps_ns"] if p["utc_detected"] else None, p["pps_detected"]))
    assembler = ProfileAssembler()  # the profiles of the datagrams, as the daemon assembled them
    for m in iter_messages(session, {"/lidar/raw"}):
        for prof in assembler.feed_assembled(m.payload, m.host_ns):
            inputs.append(
                (prof.host_ns, 0, "profiler", prof.t0_ns if prof.time_valid else None, prof.pps_locked)
            )
    ticks = [(m.host_ns, 1, None, None, None) for m in iter_messages(session, {"/latency"})]
    raised: dict[tuple[str, str], int] = {}
    out = []
    for host, is_tick, device, tag, pps in sorted(inputs + ticks, key=lambda x: (x[0], x[1])):
        evs = monitor.tick(host) if is_tick else monitor.observe(device, host, tag, pps_flag=pps)
        for ev in evs:
            a = ev.alarm
            if a.name not in LATENCY_ALARMS:
                continue
            if ev.action == "raise":
                raised[a.name, a.device] = a.first_host_ns
            elif (a.name, a.device) in raised:
                out.append((a.name, a.device, raised.pop((a.name, a.device)), a.last_host_ns))
    out += [(n, d, h, None) for (n, d), h in raised.items()]
    return sorted(out, key=lambda x: x[2])
