"""Named alarms with raise/clear hysteresis, shared by the clock, latency and log monitors.

An alarm is keyed by ``(name, device)`` (``("latency_jump", "ins")``, ``("disk_write_failed",
"log")``). A monitor evaluates its condition and calls :meth:`AlarmBook.update`; the book raises
the alarm once the condition has held for ``raise_after_ns`` and clears it once it has been
false for ``clear_after_ns`` (time hysteresis; value hysteresis — a lower threshold to clear —
is the caller's, see :meth:`AlarmBook.is_active`). Each transition is an :class:`AlarmEvent`
(a raise, a clear, and a raise again when an active alarm's severity rises: warning →
critical is never silent), returned by ``update`` and queued for :meth:`AlarmBook.drain`, which the daemon publishes (socket,
MQTT ``alarms``) and logs (``/events``).

Besides the monitors' alarms (docs/architecture.md §6.4), the mount watch
(:mod:`acquire.watch`) raises ``mount_shift`` (:data:`MOUNT_SHIFT`, critical, device ``mount``)
when its sequential test finds the boresight moved since the calibration: the message names the
angle(s), the size with σ and since when; it is never cleared during the session (the mount
needs a new calibration).

Times: ``now_ns`` is the monitor's stream time (host monotonic ns); the book converts it to GPS
ns with ``to_gps`` (the clock model) for the alarm's ``first_gps_ns``/``last_gps_ns``.
The book is thread-safe (the log writer updates it from its own thread).
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from typing import Literal

INFO, WARNING, CRITICAL = "info", "warning", "critical"
MOUNT_SHIFT = ("mount_shift", "mount")  # (name, device) of the mount watch's alarm
SEVERITIES = (INFO, WARNING, CRITICAL)
_RANK = {CRITICAL: 0, WARNING: 1, INFO: 2}


@dataclass(frozen=True)
class Alarm:
    """One named alarm of one device (a snapshot; the book replaces it on each change)."""

    name: str  # "time_step", "latency_jump", ...
    device: str  # device name, or a subsystem: "clock", "log"
    severity: str  # info | warning | critical
    message: str  # why, with numbers: "latency 28.1 ms, baseline 8.0 ms (+20.1 ms > 5.0 ms)"
    first_host_ns: int  # stream time when (last) raised
    last_host_ns: int  # stream time of the latest update while active (or of the clear)
    first_gps_ns: int | None = None
    last_gps_ns: int | None = None
    active: bool = True
    raised_count: int = 1  # how many times this alarm has been raised

    @property
    def key(self) -> tuple[str, str]:
        return (self.name, self.device)

    def as_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class AlarmEvent:
    action: Literal["raise", "clear"]
    alarm: Alarm

    def as_dict(self) -> dict:
        return {"action": self.action, **self.alarm.as_dict()}


@dataclass
class _Pending:
    since_ns: int | None = None  # when the condition started to differ from the alarm's state


class AlarmBook:
    """The set of alarms of the daemon, with time hysteresis and a queue of transitions."""

    def __init__(self, to_gps: Callable[[int], int | None] | None = None):
        self._to_gps = to_gps
        self._alarms: dict[tuple[str, str], Alarm] = {}
        self._pending: dict[tuple[str, str], _Pending] = {}
        self._events: list[AlarmEvent] = []
        self._lock = threading.Lock()

    def _gps(self, host_ns: int) -> int | None:
        return self._to_gps(host_ns) if self._to_gps is not None else None

    def update(
        self,
        name: str,
        device: str,
        condition: bool,
        now_ns: int,
        *,
        message: str = "",
        severity: str = WARNING,
        raise_after_ns: int = 0,
        clear_after_ns: int = 0,
    ) -> AlarmEvent | None:
        """Feed the current truth of a condition; return the transition it caused, if any.

        ``message`` describes the condition *now*: it becomes the alarm's message on raise,
        refreshes it while active, and is the clear message when the alarm clears.
        """
        if severity not in SEVERITIES:
            raise ValueError(f"alarm severity {severity!r}: expected one of {SEVERITIES}")
        key = (name, device)
        with self._lock:
            alarm = self._alarms.get(key)
            active = alarm is not None and alarm.active
            pending = self._pending.setdefault(key, _Pending())
            if condition == active:
                pending.since_ns = None
                if active and alarm is not None:  # refresh the message and the last time
                    new = replace(
                        alarm,
                        message=message or alarm.message,
                        last_host_ns=now_ns,
                        last_gps_ns=self._gps(now_ns),
                        severity=severity,
                    )
                    self._alarms[key] = new
                    if _RANK[severity] < _RANK[alarm.severity]:  # escalated: raised again
                        event = AlarmEvent("raise", new)
                        self._events.append(event)
                        return event
                return None
            if pending.since_ns is None:
                pending.since_ns = now_ns
            wait_ns = raise_after_ns if condition else clear_after_ns
            if now_ns - pending.since_ns < wait_ns:
                return None
            pending.since_ns = None
            if condition:
                new = Alarm(
                    name=name,
                    device=device,
                    severity=severity,
                    message=message,
                    first_host_ns=now_ns,
                    last_host_ns=now_ns,
                    first_gps_ns=self._gps(now_ns),
                    last_gps_ns=self._gps(now_ns),
                    active=True,
                    raised_count=(alarm.raised_count + 1) if alarm is not None else 1,
                )
                event = AlarmEvent("raise", new)
            else:
                assert alarm is not None
                new = replace(
                    alarm,
                    active=False,
                    message=message or alarm.message,
                    last_host_ns=now_ns,
                    last_gps_ns=self._gps(now_ns),
                )
                event = AlarmEvent("clear", new)
            self._alarms[key] = new
            self._events.append(event)
            return event

    def raise_now(
        self, name: str, device: str, now_ns: int, *, message: str, severity: str = WARNING
    ) -> AlarmEvent | None:
        """Raise (or refresh) an alarm at once, for conditions that are events."""
        return self.update(name, device, True, now_ns, message=message, severity=severity)

    def clear_now(self, name: str, device: str, now_ns: int, *, message: str = "") -> AlarmEvent | None:
        return self.update(name, device, False, now_ns, message=message)

    def is_active(self, name: str, device: str) -> bool:
        with self._lock:
            alarm = self._alarms.get((name, device))
            return alarm is not None and alarm.active

    def get(self, name: str, device: str) -> Alarm | None:
        with self._lock:
            return self._alarms.get((name, device))

    def active(self) -> list[Alarm]:
        """The active alarms, most severe first, then oldest first."""
        with self._lock:
            alarms = [a for a in self._alarms.values() if a.active]
        return sorted(alarms, key=lambda a: (_RANK[a.severity], a.first_host_ns))

    def drain(self) -> list[AlarmEvent]:
        """Transitions since the last drain, oldest first."""
        with self._lock:
            events, self._events = self._events, []
        return events
