"""PPS edges and time messages → labelled pulses → the clock model (docs/architecture.md §5, §6).

:class:`TimeKeeper` owns the daemon's :class:`~drivers.pps.PpsLabeler` (gpsd's rule) and
:class:`~acquire.timing.clock.ClockModel`. The PPS device hands it every pulse (:meth:`on_edge`); the
time device (the INS named by the PPS device's ``time_device``) hands it every time message of
the configured kinds as a whole GPS second (:meth:`on_time`). A labelled pulse goes into the
clock model, in host-time order.

Every pulse is logged once on ``/pps`` when its fate is known — labelled (and accepted or
rejected by the clock model, with the residual), or dropped by the labeller (``unlabelled``
after 1.1 s without a time message, ``duplicate``) — with ``host_ns`` = the pulse's host stamp
and, when labelled, the device time tag = the GPS second it marks. ``log_time − publish_time``
of a labelled pulse is then the clock model's error at that pulse. Clock-state changes are
reported through ``on_state`` (the supervisor logs and alarms them).

:func:`coarse_gps_offset_ns` seeds the clock model before the first pulse: GPS − host
monotonic from the system clock (UTC + leap seconds).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

from acquire.timing.clock import ClockModel, ClockState
from calib.core.frames import leap_seconds_at_utc
from drivers.pps import LABEL_WINDOW_NS, PpsEdge, PpsLabeler
from drivers.timing import realtime_minus_monotonic_ns

NS_PER_S = 1_000_000_000
UNIX_TO_GPS_EPOCH_S = 315_964_800  # 1980-01-06T00:00:00Z in Unix seconds

Submit = Callable[..., Any]  # SessionWriter.submit-like: (topic, payload, host_ns=, device_ns=)


def coarse_gps_offset_ns() -> int:
    """GPS ns − ``time.monotonic_ns()`` from the system clock (UTC + the leap seconds)."""
    import datetime as _dt

    offset = realtime_minus_monotonic_ns()
    real = time.monotonic_ns() + offset
    leap = leap_seconds_at_utc(_dt.datetime.fromtimestamp(real / NS_PER_S, _dt.UTC))
    return offset - UNIX_TO_GPS_EPOCH_S * NS_PER_S + leap * NS_PER_S


class TimeKeeper:
    """Labels PPS pulses with time messages and feeds the clock model (module docstring)."""

    def __init__(
        self,
        clock: ClockModel,
        submit: Submit | None = None,
        on_state: Callable[[ClockState, ClockState, int], None] | None = None,
        on_edge_added: Callable[[], None] | None = None,
    ) -> None:
        self.clock = clock
        self.on_edge_added = on_edge_added
        self.labeler = PpsLabeler()
        self.submit = submit
        self.on_state = on_state
        self.state = ClockState.UNLOCKED
        self._pending: dict[tuple[str, int], PpsEdge] = {}  # pulses waiting for a label
        self.pulses = 0
        self.time_messages = 0
        self.last_edge_host_ns: int | None = None

    # -- inputs -----------------------------------------------------------------------------

    def on_edge(self, edge: PpsEdge) -> None:
        """A PPS pulse as its source saw it (host monotonic stamp)."""
        self.pulses += 1
        self.last_edge_host_ns = edge.host_ns
        dup = self.labeler.stats.events["duplicate_edge"]
        self.labeler.add_edge(edge)
        if self.labeler.stats.events["duplicate_edge"] > dup:
            self._log(edge, None, "duplicate")
            return
        self._pending[(edge.source, edge.sequence)] = edge
        self._expire(edge.host_ns)

    def on_time(self, gps_s: int, host_ns: int) -> None:
        """A time message for GPS second ``gps_s`` received at ``host_ns``."""
        self.time_messages += 1
        for edge in self.labeler.add_time(int(gps_s), int(host_ns)):
            self._pending.pop((edge.source, edge.sequence), None)
            self._expire(edge.host_ns, before=True)
            result = self.clock.add_edge(edge.host_ns, edge.gps_s)
            if self.on_edge_added is not None:
                self.on_edge_added()
            self._log(edge, result, result.reason)
        self._expire(host_ns)

    def tick(self, now_host_ns: int) -> None:
        """Periodic: log pulses that can no longer be labelled; report a clock-state change."""
        self._expire(now_host_ns)
        state = self.clock.state_at(now_host_ns)
        if state != self.state:
            old, self.state = self.state, state
            if self.on_state is not None:
                self.on_state(old, state, now_host_ns)

    def flush(self) -> None:
        """Log every pulse still waiting for a label as unlabelled (shutdown)."""
        for key, e in list(self._pending.items()):
            del self._pending[key]
            self._log(e, None, "unlabelled")

    # -- internals --------------------------------------------------------------------------

    def _expire(self, now_ns: int, before: bool = False) -> None:
        """Log pending pulses older than the labelling window (``before``: every pulse older
        than ``now_ns`` — the labeller drops them once a later pulse takes the label)."""
        for key, e in list(self._pending.items()):
            if (e.host_ns < now_ns) if before else (now_ns - e.host_ns > LABEL_WINDOW_NS):
                del self._pending[key]
                self._log(e, None, "unlabelled")

    def _log(self, edge: PpsEdge, result, reason: str) -> None:
        if self.submit is None:
            return
        data = {
            "source": edge.source,
            "sequence": edge.sequence,
            "host_ns": edge.host_ns,
            "gps_s": edge.gps_s,
            "reason": reason,
            "accepted": bool(result.accepted) if result is not None else False,
            "residual_ns": None if result is None else result.residual_ns,
            "step_ns": None if result is None else result.step_ns,
        }
        if edge.realtime_ns is not None:
            data["realtime_ns"] = edge.realtime_ns
        device_ns = None if edge.gps_s is None else edge.gps_s * NS_PER_S
        self.submit("/pps", data, host_ns=edge.host_ns, device_ns=device_ns)

    def status(self) -> dict:
        ev = self.labeler.stats.events
        return {
            "pulses": self.pulses,
            "labelled": self.labeler.stats.records,
            "time_messages": self.time_messages,
            "unlabelled": ev["unlabelled"],
            "duplicate_edges": ev["duplicate_edge"],
            "time_without_edge": ev["time_without_edge"],
        }


class ClockCache:
    """The clock model's estimate at ~0.3 µs a call, for the record hot path.

    The model is a straight line between PPS edges, so :meth:`estimate` reads it once (two
    :meth:`ClockModel.to_gps` calls 1 s apart give the offset and the rate) and extrapolates;
    the line and the state are read again after ``max_age_ns`` of host time (a state change
    — LOCKED → HOLDOVER — is seen that late at most) and after every labelled pulse
    (:meth:`invalidate`, called by the :class:`TimeKeeper`).
    """

    def __init__(self, clock: ClockModel, max_age_ns: int = 50_000_000) -> None:
        self.clock = clock
        self.max_age_ns = max_age_ns
        self._h0 = self._g0 = 0
        self._rate = 1.0
        self._state = ClockState.UNLOCKED.value
        self._until = -1  # host ns after which the line is read again

    def invalidate(self) -> None:
        self._until = -1

    def estimate(self, host_ns: int) -> tuple[int, str]:
        """(GPS ns, clock state name) of a host monotonic stamp."""
        if not self._h0 <= host_ns <= self._until:
            a = self.clock.to_gps(host_ns)
            b = self.clock.to_gps(host_ns + NS_PER_S)
            self._h0, self._g0 = host_ns, a.gps_ns
            self._rate = (b.gps_ns - a.gps_ns) / NS_PER_S
            self._state = a.state.value
            self._until = host_ns + self.max_age_ns
            return a.gps_ns, self._state
        return self._g0 + round((host_ns - self._h0) * self._rate), self._state

    def gps_ns(self, host_ns: int) -> int:
        return self.estimate(host_ns)[0]
