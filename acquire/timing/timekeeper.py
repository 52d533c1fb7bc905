"""PPS edges and time messages → labelled pulses → the clock model, and the time alarms
(docs/architecture.md §5, §6).

:class:`TimeKeeper` owns the daemon's :class:`~drivers.pps.PpsLabeler` and
:class:`~acquire.timing.clock.ClockModel`. The PPS device hands it every pulse (:meth:`on_edge`); the
time device (the INS named by the PPS device's ``time_device``) hands it every time message of
the configured kinds as a whole GPS second (:meth:`on_time`), in whatever order the event loop
gets to them: the labeller matches them by their stamps. A labelled pulse goes into the clock
model, in host-time order.

Every pulse is logged once on ``/pps`` when its fate is known — labelled (and accepted or
rejected by the clock model, with the residual), or dropped by the labeller (``unlabelled``,
``ambiguous``: its time message came later than expected, ``duplicate``) — with ``host_ns`` =
the pulse's host stamp and, when labelled, the device time tag = the GPS second it marks.
``log_time − publish_time`` of a labelled pulse is then the clock model's error at that pulse.
Clock-state changes are reported through ``on_state`` (the supervisor logs and alarms them).

Alarms on ``clock`` (with an :class:`~acquire.alarms.AlarmBook`, evaluated by :meth:`tick`):

- ``time_ambiguous`` (warning): a time message later or earlier than its expected latency for
  every pulse — it could belong to two pulses — left its pulse unlabelled; clears 10 s after
  the last one;
- ``leap_table_stale`` (warning): the GPS date is past the leap-second table's expiry (a leap
  second may be missing from it); the table in use is the built-in one or, when given
  ``leap_list`` (the daemon: tzdata's ``/usr/share/zoneinfo/leap-seconds.list``), that file
  when it is a newer consistent one;
- ``leap_second_mismatch`` (warning): the INS announces a GPS − UTC (:meth:`on_gps_minus_utc`)
  other than the table's for now: its UTC tags are read with its own count (its GPS time stays
  exact), while UTC from the table — the system clock's seed, UTC shown to the operator — may be
  off by the difference;
- ``host_clock_offset`` (warning): once the PPS gives GPS time (LOCKED or HOLDOVER), the host's
  system clock (UTC + leap seconds) is off it by more than the clock params'
  ``host_offset_alarm_ns`` [1 s] — chrony or gpsd is not disciplining it; the message names the
  offset and ``chronyc tracking``; cleared once back within the limit (records stamped before the
  first PPS fit carry the host's time: the session log marks them, :mod:`acquire.log.schema`);
- ``host_clock_step`` (warning): ``CLOCK_REALTIME`` stepped by 10 ms or more (NTP, ``date -s``;
  seen by the time keeper's :class:`~drivers.timing.HostClock` (its step counter) at each tick's
  read of realtime − monotonic;
  smaller steps, a virtual machine's clock discipline, are handled alike and counted in the
  metrics' ``host_clock_steps``, without an alarm): the
  daemon's stamps are monotonic and do not move, the transports keep kernel stamps taken before
  the step on the old offset (:class:`drivers.timing.RealtimeStamps`), and the clock model's
  system-clock seed is refreshed; clears 10 s later.

:func:`coarse_gps_offset_ns` seeds the clock model before the first pulse: GPS − host
monotonic from the system clock (UTC + leap seconds).

The host clock is an object handed in (``host_clock``: the real one by default; the simulated
devices' :class:`~drivers.timing.FakeHostClock` when the daemon is told so), which owns the step
counts the status reports (``host_clock_steps``, ``host_clock_steps_alarmed``).
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from acquire.alarms import WARNING, AlarmBook
from acquire.timing.clock import ClockModel, ClockState
from calib.core.frames import leap_seconds_at_gps_ns, leap_seconds_at_utc
from calib.core.gpstime import GPS_EPOCH_UNIX_S, leap_table, parse_leap_seconds_list, use_leap_table
from drivers.pps import PpsEdge, PpsLabeler
from drivers.timing import STEP_ALARM_NS, HostClock

NS_PER_S = 1_000_000_000
UNIX_TO_GPS_EPOCH_S = 315_964_800  # 1980-01-06T00:00:00Z in Unix seconds
EVENT_CLEAR_NS = 10 * NS_PER_S  # an event alarm clears this long after the last event
SYSTEM_LEAP_SECONDS_LIST = "/usr/share/zoneinfo/leap-seconds.list"

Submit = Callable[..., Any]  # SessionWriter.submit-like: (topic, payload, host_ns=, device_ns=)


def coarse_gps_offset_ns(host_clock: HostClock | None = None) -> int:
    """GPS ns − ``time.monotonic_ns()`` from the system clock (UTC + the leap seconds), read
    through ``host_clock`` (default: the real one; the read counts toward its steps)."""
    import datetime as _dt

    offset = (host_clock if host_clock is not None else HostClock()).realtime_minus_monotonic_ns()
    real = time.monotonic_ns() + offset
    leap = leap_seconds_at_utc(_dt.datetime.fromtimestamp(real / NS_PER_S, _dt.UTC))
    return offset - UNIX_TO_GPS_EPOCH_S * NS_PER_S + leap * NS_PER_S


def load_leap_list(path: str | Path) -> str:
    """Install the leap-second table of an IERS ``leap-seconds.list`` when it is newer than the
    one in use; returns what happened (for the status)."""
    try:
        table = parse_leap_seconds_list(Path(path).read_text(encoding="ascii"), str(path))
        installed = use_leap_table(table)
    except (OSError, ValueError, UnicodeDecodeError) as e:
        return f"{path} not used: {e}"
    return f"{path} {'in use' if installed else 'not newer than the table in use'}"


class TimeKeeper:
    """Labels PPS pulses with time messages, feeds the clock model, watches the time (module
    docstring)."""

    def __init__(
        self,
        clock: ClockModel,
        submit: Submit | None = None,
        on_state: Callable[[ClockState, ClockState, int], None] | None = None,
        on_edge_added: Callable[[], None] | None = None,
        alarms: AlarmBook | None = None,
        leap_list: str | Path | None = None,
        host_gps_offset_ns: Callable[[], int] | None = None,
        host_clock: HostClock | None = None,
    ) -> None:
        """``host_clock``: the host's clock, read each tick for its steps (default: the real one;
        the simulated devices' :class:`~drivers.timing.FakeHostClock` when the daemon is given
        one). ``host_gps_offset_ns``: GPS − host monotonic as the host's system clock says it
        (default :func:`coarse_gps_offset_ns` through ``host_clock``; tests inject one)."""
        self.clock = clock
        self.host_clock = host_clock if host_clock is not None else HostClock()
        seed = functools.partial(coarse_gps_offset_ns, self.host_clock)
        self.host_gps_offset_ns = host_gps_offset_ns or seed
        self.host_clock_offset_ns: int | None = None  # system clock − GPS, once GPS time is known
        self.on_edge_added = on_edge_added
        self.labeler = PpsLabeler()
        self.submit = submit
        self.on_state = on_state
        self.alarms = alarms
        self.state = ClockState.UNLOCKED
        self.pulses = 0
        self.time_messages = 0
        self.last_edge_host_ns: int | None = None
        self.leap_note = "built-in table" if leap_list is None else load_leap_list(leap_list)
        self.gps_minus_utc_s: int | None = None  # as the time device announces it
        self._ambiguous = (0, 0)  # (events seen, host ns of the latest)
        # a first read: a step from here on is counted (steps seen, steps of >= STEP_ALARM_NS
        # seen, host ns of the latest of those)
        self.host_clock.realtime_minus_monotonic_ns()
        steps = self.host_clock.steps_seen
        self._host_steps = (steps.count, steps.large, 0)

    # -- inputs -----------------------------------------------------------------------------

    def on_edge(self, edge: PpsEdge) -> None:
        """A PPS pulse as its source saw it (host monotonic stamp)."""
        self.pulses += 1
        self.last_edge_host_ns = edge.host_ns
        self._labelled(self.labeler.add_edge(edge))

    def on_time(self, gps_s: int, host_ns: int) -> None:
        """A time message for GPS second ``gps_s`` received at ``host_ns``."""
        self.time_messages += 1
        self._labelled(self.labeler.add_time(int(gps_s), int(host_ns)))

    def on_gps_minus_utc(self, gps_minus_utc_s: int | None) -> None:
        """The GPS − UTC the time device announces (None: it stopped announcing)."""
        self.gps_minus_utc_s = gps_minus_utc_s

    def tick(self, now_host_ns: int) -> None:
        """Periodic: decide what the labeller can, log pulses that can no longer be labelled,
        report a clock-state change, evaluate the time alarms."""
        self._labelled(self.labeler.tick(now_host_ns))
        state = self.clock.state_at(now_host_ns)
        if state != self.state:
            old, self.state = self.state, state
            if self.on_state is not None:
                self.on_state(old, state, now_host_ns)
        if self.alarms is not None:
            self._alarms(now_host_ns)

    def flush(self) -> None:
        """Decide and log every pulse still waiting for a label (shutdown)."""
        self._labelled(self.labeler.flush())

    # -- internals --------------------------------------------------------------------------

    def _labelled(self, edges: list[PpsEdge]) -> None:
        for edge, reason in self.labeler.take_dropped():
            self._log(edge, None, reason)
        for edge in edges:
            assert edge.gps_s is not None, "the labeller hands over labelled edges only"
            result = self.clock.add_edge(edge.host_ns, edge.gps_s)
            if self.on_edge_added is not None:
                self.on_edge_added()
            self._log(edge, result, result.reason)

    def _alarms(self, now: int) -> None:
        al = self.alarms
        assert al is not None
        self._ambiguous_alarm(al, now)
        self._host_clock_step_alarm(al, now)
        self._leap_alarms(al, now)
        self._host_clock_offset_alarm(al, now)

    def _ambiguous_alarm(self, al: AlarmBook, now: int) -> None:
        """``time_ambiguous``: a time message that could belong to two pulses; cleared 10 s
        after the last one."""
        count, since = self._ambiguous
        n = self.labeler.stats.events["time_ambiguous"]
        if n > count:
            self._ambiguous = (n, now)
            a = self.labeler.last_ambiguous or {}
            al.raise_now(
                "time_ambiguous",
                "clock",
                now,
                severity=WARNING,
                message=f"the time message of GPS second {a.get('gps_s')} came "
                f"{a.get('latency_ns', 0) / 1e6:.1f} ms after the latest pulse, expected "
                f"{a.get('expected_ns', 0) / 1e6:.1f} ± {a.get('tolerance_ns', 0) / 1e6:.1f} ms: it could "
                f"belong to two pulses, none labelled ({n} so far)",
            )
        elif since and now - since > EVENT_CLEAR_NS and al.is_active("time_ambiguous", "clock"):
            al.clear_now("time_ambiguous", "clock", now, message="time messages on time again")

    def _host_clock_step_alarm(self, al: AlarmBook, now: int) -> None:
        """A step of the host's realtime clock: any step refreshes the system-clock seed, one of
        at least :data:`~drivers.timing.STEP_ALARM_NS` raises ``host_clock_step`` (cleared 10 s
        later)."""
        self.host_clock.realtime_minus_monotonic_ns()  # a read shows a step to the clock's counter
        steps = self.host_clock.steps_seen
        count, large, since = self._host_steps
        if steps.count > count:  # any step: the system-clock seed follows it
            self.clock.coarse_offset_ns = self.host_gps_offset_ns()
            self._host_steps = (steps.count, large, since)
        if steps.large > large:
            self._host_steps = (steps.count, steps.large, now)
            step_ns = steps.last[1] if steps.last else 0
            al.raise_now(
                "host_clock_step",
                "clock",
                now,
                severity=WARNING,
                message=f"the host's realtime clock stepped by {step_ns / 1e9:+.3f} s: stamps are "
                "monotonic, kernel stamps before the step kept their offset, the system-clock "
                f"seed refreshed ({steps.large} steps of ≥ {STEP_ALARM_NS / 1e6:.0f} ms so far, "
                f"{steps.count - steps.large} smaller)",
            )
        elif since and now - since > EVENT_CLEAR_NS and al.is_active("host_clock_step", "clock"):
            al.clear_now("host_clock_step", "clock", now, message="no host clock step for 10 s")

    def _leap_alarms(self, al: AlarmBook, now: int) -> None:
        """The leap-second table: ``leap_table_stale`` (expired) and ``leap_second_mismatch``
        (contradicted by the time device)."""
        table = leap_table()
        gps_ns = self.clock.gps_ns(now)
        leap = leap_seconds_at_gps_ns(gps_ns)
        stale = table.expired_at_unix_ns(gps_ns - leap * NS_PER_S + GPS_EPOCH_UNIX_S * NS_PER_S)
        al.update(
            "leap_table_stale",
            "clock",
            stale,
            now,
            severity=WARNING,
            message=f"the leap-second table expired on {table.expires} ({table.source}): a leap "
            "second announced since may be missing; install a newer IERS leap-seconds.list (tzdata)"
            if stale
            else f"leap-second table valid until {table.expires}",
        )
        announced = self.gps_minus_utc_s
        mismatch = announced is not None and announced != leap
        al.update(
            "leap_second_mismatch",
            "clock",
            mismatch,
            now,
            severity=WARNING,
            message=f"the time device applies GPS − UTC = {announced} s, the leap-second table "
            f"{leap} s (expires {table.expires}): its UTC tags are read with its own {announced} s; "
            "UTC from the table may be off by the difference (a leap second the table lacks, or a "
            "wrong device)"
            if mismatch
            else f"GPS − UTC {leap} s as the table says",
        )

    def _host_clock_offset_alarm(self, al: AlarmBook, now: int) -> None:
        """``host_clock_offset``: the system clock off GPS time by more than the clock params'
        ``host_offset_alarm_ns``, judged only while the PPS gives GPS time (LOCKED, HOLDOVER);
        cleared once back within it."""
        if self.clock.state_at(now) == ClockState.UNLOCKED:
            return  # GPS time not known: the alarm keeps its state
        offset = self.host_gps_offset_ns() - (self.clock.gps_ns(now) - now)
        self.host_clock_offset_ns = offset
        limit = self.clock.params.host_offset_alarm_ns
        off = abs(offset) > limit
        side = "ahead of" if offset > 0 else "behind"
        al.update(
            "host_clock_offset",
            "clock",
            off,
            now,
            severity=WARNING,
            message=f"host clock {abs(offset) / NS_PER_S:,.3f} s {side} GPS time (limit "
            f"{limit / NS_PER_S:g} s): is chrony (or gpsd) disciplining it? see `chronyc tracking`; "
            "records stamped before the PPS lock carry the host's time"
            if off
            else f"host clock within {limit / NS_PER_S:g} s of GPS time ({offset / NS_PER_S:+.3f} s)",
        )

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
        expected = self.labeler.expected_latency()
        return {
            "pulses": self.pulses,
            "labelled": self.labeler.stats.records,
            "time_messages": self.time_messages,
            "unlabelled": ev["unlabelled"],
            "duplicate_edges": ev["duplicate_edge"],
            "time_without_edge": ev["time_without_edge"],
            "time_ambiguous": ev["time_ambiguous"],
            "time_latency_ms": None if expected is None else round(expected[0] / 1e6, 3),
            "leap_table": {**leap_table().as_dict(), "note": self.leap_note},
            "gps_minus_utc_announced_s": self.gps_minus_utc_s,
            "host_clock_steps": self.host_clock.steps_seen.count,
            "host_clock_steps_alarmed": self.host_clock.steps_seen.large,
            "host_clock_offset_s": None
            if self.host_clock_offset_ns is None
            else round(self.host_clock_offset_ns / NS_PER_S, 6),
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
        """(GPS ns, clock state name) of a host monotonic stamp; the state is
        :data:`~acquire.timing.clock.HOST_TIME_STATE` before any PPS fit (host time)."""
        if not self._h0 <= host_ns <= self._until:
            a = self.clock.to_gps(host_ns)
            b = self.clock.to_gps(host_ns + NS_PER_S)
            self._h0, self._g0 = host_ns, a.gps_ns
            self._rate = (b.gps_ns - a.gps_ns) / NS_PER_S
            self._state = a.record_state
            self._until = host_ns + self.max_age_ns
            return a.gps_ns, self._state
        return self._g0 + round((host_ns - self._h0) * self._rate), self._state

    def gps_ns(self, host_ns: int) -> int:
        return self.estimate(host_ns)[0]
