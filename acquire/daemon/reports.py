"""The daemon's status reports: the watchdog's check of the device tasks, the devices that are
not connected (the critical alarm ``device_unavailable``, the watchdog's ``STATUS=`` line), the
retained ``status``, ``sensors/<name>``, ``clock`` and ``metrics`` documents, the pre-survey
checks (the ``presurvey`` section of the checklist), and their copies in the session log
(``/status``, ``/clock``, ``/latency``).

:class:`~acquire.daemon.supervisor.Supervisor` holds one of each: :class:`DeviceHealth` (its
device tasks and its record of the devices that are down), :class:`Outlets` (what its start-up
opens) and :class:`StatusReporter` (the documents, built from those and the daemon's clock,
monitors, alarms and status bus)."""

from __future__ import annotations

import asyncio
import datetime as _dt
import os
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, NamedTuple

from acquire.alarms import CRITICAL, AlarmBook
from acquire.daemon.configschema import VesselConfig
from acquire.daemon.consumers import ChecklistPublisher, ConsumerHub
from acquire.daemon.devices import DaemonContext, Device, InsDevice, ProfilerDevice
from acquire.status.bus import StatusBus, StatusServer
from acquire.timing.clock import ClockModel, ClockState
from acquire.timing.latency import LatencyMonitor
from acquire.timing.timekeeper import TimeKeeper

if TYPE_CHECKING:  # MQTT is imported when the config enables it
    from acquire.log.sessionlog import SessionWriter
    from acquire.status.mqtt import MqttPublisher

NS_PER_S = 1_000_000_000
MIN_RCVBUF_BYTES = 8 * 2**20  # profiler socket buffer: ~0.8 s of the full Z+F rate
MIN_FREE_BYTES = 2 * 2**30  # the disk_space check
#: the alarms that fail the pre-survey ``latency_in_band`` check
LATENCY_ALARMS = (
    "latency_out_of_band",
    "latency_jump",
    "time_step",
    "clock_drift",
    "pps_flag_lost",
    "latency_jitter",
)


@dataclass
class DeviceHealth:
    """How the devices fare: the supervisor's device tasks (filled as it spawns them) and its
    record of the devices that are down (kept by its device loops)."""

    devices: dict[str, Device]
    tasks: dict[str, asyncio.Task] = field(default_factory=dict)  # device → its task
    crashed: dict[str, str] = field(default_factory=dict)  # device → the error while down after a driver bug
    unavailable: dict[str, str] = field(default_factory=dict)  # device → the error while not opened/read

    def drivers_health(self) -> tuple[bool, str]:
        """Watchdog check: every device task is running and none is down after a crash."""
        dead = [n for n, t in self.tasks.items() if t.done()]
        if dead:
            return False, f"device task ended: {', '.join(dead)}"
        if self.crashed:
            return False, "; ".join(f"{n}: {e}" for n, e in self.crashed.items())
        return True, f"{len(self.tasks)}/{len(self.devices)} device tasks alive"

    def device_error(self, dev: Device) -> str | None:
        """Why ``dev`` is not connected: its open raised (the supervisor's record), or its
        transport's last attempt failed (the OS error text); None when it is connected."""
        if dev.name in self.crashed:
            return None  # driver_failed says it
        return self.unavailable.get(dev.name) or dev.connection_error()

    def unavailable_devices(self) -> dict[str, str]:
        """Device → why it is not connected, for the devices that are not."""
        errors = {n: self.device_error(d) for n, d in self.devices.items()}
        return {n: e for n, e in errors.items() if e is not None}

    def devices_availability(self) -> tuple[bool, str]:
        """The watchdog's advisory (named in ``STATUS=``, never withholding the ping: restarting
        the daemon brings no device back and would stop the others' recording)."""
        down = self.unavailable_devices()
        if not down:
            return True, f"{len(self.devices)} devices connected"
        return False, "; ".join(f"{n} not connected: {e}" for n, e in down.items())

    def update_alarms(self, alarms: AlarmBook, now: int) -> None:
        """Raise, refresh or clear the critical alarm ``device_unavailable`` of every device."""
        for dev in self.devices.values():
            error = self.device_error(dev)
            alarms.update(
                "device_unavailable",
                dev.name,
                error is not None,
                now,
                severity=CRITICAL,
                message=f"{dev.name} ({dev.kind}) not connected: {error}; retrying"
                if error is not None
                else f"{dev.name} connected",
            )

    def device_state(self, dev: Device) -> str:
        """``failed`` (driver bug), ``unavailable``, ``connected`` or ``disconnected``."""
        if dev.name in self.crashed:
            return "failed"
        if self.device_error(dev) is not None:
            return "unavailable"
        return "connected" if dev.connected else "disconnected"


@dataclass
class Outlets:
    """Where the daemon's records and status go, opened by its start-up (None before, and for
    MQTT when the config has no ``mqtt`` section)."""

    writer: SessionWriter | None = None  # the session log
    server: StatusServer | None = None  # the status socket
    mqtt: MqttPublisher | None = None


class PresurveyCheck(NamedTuple):
    """One pre-survey check: its name, whether it passes, what it saw."""

    name: str
    ok: bool
    detail: str


@dataclass(kw_only=True, eq=False)
class StatusReporter:
    """Builds and publishes the status documents of one daemon (see the module docstring).

    ``ctx.submit`` is the session log's submit (the supervisor points it at the log's batcher
    once the session is open); ``loop_lag_ns`` is the monitor loop's worst lateness since the
    last status round (kept by the supervisor's loops, reported in ``metrics``)."""

    config: VesselConfig
    health: DeviceHealth
    outlets: Outlets
    clock: ClockModel
    timekeeper: TimeKeeper
    monitor: LatencyMonitor
    alarms: AlarmBook
    hub: ConsumerHub
    bus: StatusBus
    checklist: ChecklistPublisher
    ctx: DaemonContext
    started_utc: _dt.datetime
    started_mono_ns: int
    loop_lag_ns: int = 0

    @property
    def devices(self) -> dict[str, Device]:
        return self.health.devices

    def status_doc(self, state: str) -> dict:
        """The retained ``status`` document, the daemon being in ``state``."""
        now = time.monotonic_ns()
        writer, mqtt = self.outlets.writer, self.outlets.mqtt
        w = writer.stats() if writer is not None else None
        doc = {
            "state": state,
            "vessel": self.config.vessel,
            "session": writer.session_dir.name if writer and writer.session_dir else None,
            "pid": os.getpid(),
            "started_utc": self.started_utc.isoformat(timespec="seconds"),
            "uptime_s": round((now - self.started_mono_ns) / NS_PER_S, 1),
            "clock": self.clock.state_at(now).value,
            "devices": {n: self.health.device_state(d) for n, d in self.devices.items()},
            "log": None
            if w is None
            else {
                "state": w.state,
                "segment": w.segment,
                "messages": w.messages_written,
                "dropped": sum(w.dropped.values()),
                "lost": sum(w.lost.values()),
                "free_mb": None if w.free_bytes is None else round(w.free_bytes / 2**20, 1),
            },
            "mqtt": None if mqtt is None else ("connected" if mqtt.connected else "disconnected"),
            "alarms": [a.as_dict() for a in self.alarms.active()],
        }
        return doc

    def publish_status(self, state: str) -> None:
        """The ``status`` document to the status bus (socket and MQTT)."""
        self.bus.publish("status", self.status_doc(state))

    def _sensor(self, name: str, dev: Device) -> dict:
        """The retained ``sensors/<name>`` summary (the details are in ``metrics``)."""
        out = {"state": self.health.device_state(dev), "kind": dev.kind, "records": dev.records}
        if (error := self.health.device_error(dev)) is not None:
            out["error"] = error
        if name in self.monitor.devices:
            st = self.monitor.stats(name)
            out.update(
                rate_hz=None if st.rate_hz is None else round(st.rate_hz, 1),
                sync=st.sync,
                latency_ms=None if st.mean_ns is None else round(st.mean_ns / 1e6, 3),
                latency_p99_ms=None if st.p99_ns is None else round(st.p99_ns / 1e6, 3),
                pps_flag=st.pps_flag,
            )
        out.update(reconnects=dev.reconnects, gaps=dev.gaps, lost=dev.losses())
        return out

    def clock_doc(self, now: int) -> dict:
        """The ``clock`` document at ``now`` (:func:`clock_doc`)."""
        return clock_doc(self.clock, self.timekeeper, now)

    def publish_details(self, now: int) -> None:
        """``sensors/<name>``, ``clock``, ``metrics`` and the checklist's ``presurvey``."""
        bus = self.bus
        for name, dev in self.devices.items():
            bus.publish(f"sensors/{name}", self._sensor(name, dev))
        bus.publish("clock", self.clock_doc(now))
        bus.publish("metrics", self.metrics_doc())
        self.checklist.publish("presurvey", self.presurvey(now))

    def metrics_doc(self) -> dict:
        """The ``metrics`` document: latency, log, socket, MQTT, devices, consumers, loop, CPU."""
        cpu = time.process_time()
        writer, server, mqtt = self.outlets.writer, self.outlets.server, self.outlets.mqtt
        return {
            "latency": self.monitor.snapshot(),
            "log": writer.stats().as_dict() if writer is not None else None,
            "status_socket": None
            if server is None
            else {
                "clients": server.clients,
                "served": server.clients_served,
                "dropped": server.clients_dropped,
            },
            "mqtt": None if mqtt is None else mqtt.metrics(),
            "devices": {n: d.status() for n, d in self.devices.items()},
            "consumers": self.hub.status(),
            "loop_lag_ms": round(self.loop_lag_ns / 1e6, 3),
            "cpu_s": round(cpu, 3),
        }

    def presurvey(self, now: int) -> dict:
        """docs/architecture.md §8's pre-survey checks: ``{check: {"ok": bool, "detail": str}}``."""
        checks = [
            self._devices_connected(),
            *(c for dev in self.devices.values() for c in self._device_checks(dev)),
            self._clock_locked(now),
            self._latency_in_band(),
            self._disk_space(),
            self._mount_configured(),
        ]
        return {c.name: {"ok": c.ok, "detail": c.detail} for c in checks}

    def _devices_connected(self) -> PresurveyCheck:
        down = self.health.unavailable_devices()
        return PresurveyCheck(
            "devices_connected",
            not down,
            "; ".join(f"{n}: {e}" for n, e in down.items()) or f"{len(self.devices)} devices connected",
        )

    def _device_checks(self, dev: Device) -> list[PresurveyCheck]:
        """The INS's navigation, GNSS and PPS; the profiler's data and socket buffer."""
        if isinstance(dev, InsDevice):
            return _ins_checks(dev.last_nav or {})
        if isinstance(dev, ProfilerDevice):
            rate = self.monitor.stats(dev.name).rate_hz
            return [
                PresurveyCheck("profiler_data", bool(rate), f"{rate or 0:.0f} profiles/s"),
                _receive_buffer_check(getattr(dev.transport, "rcvbuf_bytes_granted", 0)),
            ]
        return []

    def _clock_locked(self, now: int) -> PresurveyCheck:
        state = self.clock.state_at(now)
        return PresurveyCheck("clock_locked", state == ClockState.LOCKED, f"clock {state.value}")

    def _latency_in_band(self) -> PresurveyCheck:
        bad = [a for a in self.alarms.active() if a.name in LATENCY_ALARMS]
        return PresurveyCheck(
            "latency_in_band", not bad, "; ".join(f"{a.device}: {a.name}" for a in bad) or "ok"
        )

    def _disk_space(self) -> PresurveyCheck:
        writer = self.outlets.writer
        w = writer.stats() if writer is not None else None
        free = w.free_bytes if w is not None else None
        return PresurveyCheck(
            "disk_space",
            free is not None and free > MIN_FREE_BYTES,
            "unknown" if free is None else f"{free / 2**30:.1f} GiB free",
        )

    def _mount_configured(self) -> PresurveyCheck:
        mount = self.config.mount
        return PresurveyCheck(
            "mount_configured",
            mount is not None,
            "mount in the vessel config" if mount else "no mount in the vessel config",
        )

    def log_status(self, now: int, state: str) -> None:
        """``/status``, ``/clock`` and ``/latency`` to the session log (once it is open)."""
        if self.outlets.writer is None:
            return
        submit = self.ctx.submit
        submit("/status", self.status_doc(state), host_ns=now)
        submit("/clock", self.clock_doc(now), host_ns=now)
        submit("/latency", self.monitor.snapshot(), host_ns=now)


def clock_doc(clock: ClockModel, timekeeper: TimeKeeper, now: int) -> dict:
    """The ``clock`` document: the clock model's status and estimate at ``now``, the PPS labels."""
    est = clock.to_gps(now)
    return {
        **clock.status(now).as_dict(),
        "gps_ns": est.gps_ns,
        "host_ns": now,
        "pps": timekeeper.status(),
    }


def _ins_checks(nav: dict) -> list[PresurveyCheck]:
    """``ins_navigating``, ``gnss_fix``, ``ins_pps`` of the INS's last navigation record."""
    navigating = bool(nav.get("navigation") and nav.get("fine_alignment"))
    if navigating:
        state = "navigating, fine aligned"
    else:
        state = "no navigation record yet" if not nav else "aligning / not navigating"
    return [
        PresurveyCheck("ins_navigating", navigating, state),
        PresurveyCheck(
            "gnss_fix", bool(nav.get("gps_valid")), "GNSS valid" if nav.get("gps_valid") else "no valid GNSS"
        ),
        PresurveyCheck(
            "ins_pps",
            bool(nav.get("pps_detected") and nav.get("utc_detected")),
            f"INS time source: {nav.get('time_source', 'none')}",
        ),
    ]


def _receive_buffer_check(buf: int) -> PresurveyCheck:
    """``receive_buffer``: the profiler socket's buffer, at least :data:`MIN_RCVBUF_BYTES`."""
    return PresurveyCheck(
        "receive_buffer",
        buf >= MIN_RCVBUF_BYTES,
        f"profiler socket buffer {buf / 2**20:.1f} MiB"
        + ("" if buf >= MIN_RCVBUF_BYTES else " (raise the sysctl net.core.rmem_max to 33554432)"),
    )
