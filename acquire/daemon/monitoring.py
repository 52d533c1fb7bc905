"""The alarms of the daemon's monitor loop (docs/architecture.md §6, §8), apart from the latency
monitor's and the time keeper's own: ``time_step`` (the clock model restarted on stepped PPS
labels), ``packet_loss`` per device, ``consumer_overflow`` per consumer tap, the clock-state
alarms ``clock_holdover`` / ``clock_unlocked`` (with a ``clock_state`` event on every change),
and the drain of every alarm transition to the ``alarms`` status topic and ``/events``.

:class:`MonitorAlarms` is what :class:`~acquire.daemon.supervisor.Supervisor` runs each round of
its 4 Hz monitor loop (:meth:`MonitorAlarms.step`) and hands to the time keeper as its
clock-state callback (:meth:`MonitorAlarms.clock_state`)."""

from __future__ import annotations

import logging
from collections.abc import Callable

from acquire.alarms import CRITICAL, WARNING, AlarmBook
from acquire.daemon.consumers import ConsumerHub
from acquire.daemon.devices import Device
from acquire.status.bus import StatusBus
from acquire.timing.clock import ClockModel, ClockState

log = logging.getLogger("mls.acquire")
NS_PER_S = 1_000_000_000
LOSS_CLEAR_S = 5.0  # packet_loss clears after this long without a new loss
STEP_CLEAR_S = 10.0


class MonitorAlarms:
    """Raises and clears the monitor loop's alarms and publishes every alarm transition.

    ``log_event(data, host_ns)`` writes an ``/events`` entry (the supervisor's
    :meth:`~acquire.daemon.supervisor.Supervisor.log_event`)."""

    def __init__(
        self,
        *,
        clock: ClockModel,
        alarms: AlarmBook,
        devices: dict[str, Device],
        hub: ConsumerHub,
        bus: StatusBus,
        log_event: Callable[[dict, int | None], None],
    ) -> None:
        self.clock = clock
        self.alarms = alarms
        self.devices = devices
        self.hub = hub
        self.bus = bus
        self.log_event = log_event
        self._losses: dict[str, tuple[int, int]] = {}  # device → (count, host_ns of last increase)
        self._tap_drops: dict[str, int] = {}  # tap → records it had dropped at the last round
        self._steps = 0  # the clock model's steps already alarmed
        self._step_ns: int | None = None  # host ns of the last step while time_step is raised
        self._was_locked = False  # the clock has been LOCKED once (UNLOCKED after it is an alarm)

    def step(self, now: int) -> bool:
        """One monitor round's alarms, then the drain: whether any alarm changed."""
        self._check_time_step(now)
        self._check_packet_loss(now)
        self._check_consumer_overflow(now)
        return self.drain()

    def _check_time_step(self, now: int) -> None:
        """``time_step`` on ``clock``: raised when the clock model restarted, cleared after
        :data:`STEP_CLEAR_S` without another."""
        clock, al = self.clock, self.alarms
        if clock.steps > self._steps:
            self._steps, self._step_ns = clock.steps, now
            al.raise_now(
                "time_step",
                "clock",
                now,
                severity=CRITICAL,
                message=f"PPS labels stepped: the clock model restarted ({clock.steps} steps so far)",
            )
        elif self._step_ns is not None and now - self._step_ns > STEP_CLEAR_S * NS_PER_S:
            self._step_ns = None
            al.clear_now("time_step", "clock", now, message="clock model steady since the step")

    def _check_packet_loss(self, now: int) -> None:
        """``packet_loss`` per device: raised when its loss count grew, cleared after
        :data:`LOSS_CLEAR_S` without a new loss."""
        al = self.alarms
        for name, dev in self.devices.items():
            lost = dev.losses()
            count, since = self._losses.get(name, (0, 0))
            if lost > count:
                self._losses[name] = (lost, now)
                al.raise_now(
                    "packet_loss",
                    name,
                    now,
                    severity=WARNING,
                    message=f"{lost - count} packets lost (total {lost})",
                )
            elif al.is_active("packet_loss", name) and now - since > LOSS_CLEAR_S * NS_PER_S:
                al.clear_now(
                    "packet_loss", name, now, message=f"no loss for {LOSS_CLEAR_S:g} s (total {lost})"
                )

    def _check_consumer_overflow(self, now: int) -> None:
        """``consumer_overflow`` per tap: raised while its drop count grows."""
        for tap in self.hub.taps:
            before = self._tap_drops.get(tap.name, 0)
            self._tap_drops[tap.name] = tap.dropped
            self.alarms.update(
                "consumer_overflow",
                tap.name,
                tap.dropped > before,
                now,
                severity=WARNING,
                message=f"{tap.name} does not keep up: {tap.dropped} records dropped",
                clear_after_ns=int(LOSS_CLEAR_S * NS_PER_S),
            )

    def clock_state(self, old: ClockState, new: ClockState, now: int) -> None:
        """The time keeper's clock-state change: a ``clock_state`` event, and ``clock_holdover``
        / ``clock_unlocked`` raised or cleared."""
        st = self.clock.status(now)
        bound = st.as_dict()["error_bound_us"]
        self.log_event(
            {
                "event": "clock_state",
                "from": old.value,
                "to": new.value,
                "error_bound_us": bound,
                "edges_in_window": st.edges_in_window,
            },
            now,
        )
        al = self.alarms
        if new == ClockState.LOCKED:
            self._was_locked = True
            al.clear_now("clock_holdover", "clock", now, message="PPS back: LOCKED")
            al.clear_now("clock_unlocked", "clock", now, message="PPS back: LOCKED")
        elif new == ClockState.HOLDOVER:
            al.raise_now(
                "clock_holdover",
                "clock",
                now,
                severity=WARNING,
                message=f"no PPS for {st.as_dict()['last_edge_age_s']} s: holding over, "
                f"error bound {bound} µs",
            )
        elif self._was_locked:
            al.clear_now("clock_holdover", "clock", now)
            al.raise_now(
                "clock_unlocked",
                "clock",
                now,
                severity=CRITICAL,
                message="clock UNLOCKED: holdover bound exceeded or PPS labels lost; "
                "GPS times come from the devices' tags or the system clock",
            )

    def drain(self) -> bool:
        """Every alarm transition since the last drain to the ``alarms`` topic, ``/events`` and
        the log: whether there was any."""
        events = self.alarms.drain()
        for ev in events:
            d = ev.as_dict()
            self.bus.publish("alarms", d)
            self.log_event({"event": "alarm", **d}, ev.alarm.last_host_ns)
            log.warning("alarm %s %s/%s: %s", ev.action, ev.alarm.name, ev.alarm.device, ev.alarm.message)
        return bool(events)
