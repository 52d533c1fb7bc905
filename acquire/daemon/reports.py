"""The daemon's status reports: the watchdog's check of the device tasks, the devices that are
not connected (the critical alarm ``device_unavailable``, the watchdog's ``STATUS=`` line), the
retained ``status``, ``sensors/<name>``, ``clock`` and ``metrics`` documents, the pre-survey
checks (the ``presurvey`` section of the checklist), and their copies in the session log
(``/status``, ``/clock``, ``/latency``)."""

from __future__ import annotations

import os
import time

from acquire.alarms import CRITICAL
from acquire.daemon.devices import Device
from acquire.timing.clock import ClockState

NS_PER_S = 1_000_000_000
MIN_RCVBUF_BYTES = 8 * 2**20  # profiler socket buffer: ~0.8 s of the full Z+F rate


class StatusReports:
    """The status part of :class:`~acquire.daemon.supervisor.Supervisor` (a mixin: it reads the
    supervisor's config, devices and their tasks, clock, monitors, alarms, session writer,
    status bus, socket server and MQTT publisher)."""

    def drivers_health(self) -> tuple[bool, str]:
        """Watchdog check: every device task is running and none is down after a crash."""
        dead = [n for n, t in self._device_tasks.items() if t.done()]
        if dead:
            return False, f"device task ended: {', '.join(dead)}"
        if self.crashed:
            return False, "; ".join(f"{n}: {e}" for n, e in self.crashed.items())
        return True, f"{len(self._device_tasks)}/{len(self.devices)} device tasks alive"

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

    def update_device_alarms(self, now: int) -> None:
        """Raise, refresh or clear the critical alarm ``device_unavailable`` of every device."""
        for dev in self.devices.values():
            error = self.device_error(dev)
            self.alarms.update(
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
        if dev.name in self.crashed:
            return "failed"
        if self.device_error(dev) is not None:
            return "unavailable"
        return "connected" if dev.connected else "disconnected"

    def status_doc(self, state: str | None = None) -> dict:
        now = time.monotonic_ns()
        w = self.writer.stats() if self.writer is not None else None
        doc = {
            "state": state or self.state,
            "vessel": self.config.vessel,
            "session": self.writer.session_dir.name if self.writer and self.writer.session_dir else None,
            "pid": os.getpid(),
            "started_utc": self.started_utc.isoformat(timespec="seconds"),
            "uptime_s": round((now - self.started_mono_ns) / NS_PER_S, 1),
            "clock": self.clock.state_at(now).value,
            "devices": {n: self.device_state(d) for n, d in self.devices.items()},
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
            "mqtt": None if self.mqtt is None else ("connected" if self.mqtt.connected else "disconnected"),
            "alarms": [a.as_dict() for a in self.alarms.active()],
        }
        return doc

    def _publish_status(self) -> None:
        self.bus.publish("status", self.status_doc())

    def _sensor(self, name: str, dev: Device) -> dict:
        """The retained ``sensors/<name>`` summary (the details are in ``metrics``)."""
        out = {"state": self.device_state(dev), "kind": dev.kind, "records": dev.records}
        if (error := self.device_error(dev)) is not None:
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
        est = self.clock.to_gps(now)
        return {
            **self.clock.status(now).as_dict(),
            "gps_ns": est.gps_ns,
            "host_ns": now,
            "pps": self.timekeeper.status(),
        }

    def _publish_details(self, now: int) -> None:
        bus = self.bus
        for name, dev in self.devices.items():
            bus.publish(f"sensors/{name}", self._sensor(name, dev))
        bus.publish("clock", self.clock_doc(now))
        bus.publish("metrics", self.metrics_doc())
        self.checklist.publish("presurvey", self.presurvey(now))

    def metrics_doc(self) -> dict:
        cpu = time.process_time()
        return {
            "latency": self.monitor.snapshot(),
            "log": self.writer.stats().as_dict() if self.writer is not None else None,
            "status_socket": None
            if self.server is None
            else {
                "clients": self.server.clients,
                "served": self.server.clients_served,
                "dropped": self.server.clients_dropped,
            },
            "mqtt": None if self.mqtt is None else self.mqtt.metrics(),
            "devices": {n: d.status() for n, d in self.devices.items()},
            "consumers": self.hub.status(),
            "loop_lag_ms": round(self.loop_lag_ns / 1e6, 3),
            "cpu_s": round(cpu, 3),
        }

    def presurvey(self, now: int) -> dict:
        """docs/architecture.md §8's pre-survey checks: ``{check: {"ok": bool, "detail": str}}``."""
        checks: dict[str, dict] = {}

        def check(name: str, ok: bool, detail: str) -> None:
            checks[name] = {"ok": bool(ok), "detail": detail}

        down = self.unavailable_devices()
        check(
            "devices_connected",
            not down,
            "; ".join(f"{n}: {e}" for n, e in down.items()) or f"{len(self.devices)} devices connected",
        )

        for dev in self.devices.values():
            if dev.kind == "ins":
                nav = getattr(dev, "last_nav", None) or {}
                check(
                    "ins_navigating",
                    nav.get("navigation") and nav.get("fine_alignment"),
                    "navigating, fine aligned"
                    if nav.get("navigation") and nav.get("fine_alignment")
                    else "no navigation record yet"
                    if not nav
                    else "aligning / not navigating",
                )
                check(
                    "gnss_fix",
                    nav.get("gps_valid"),
                    "GNSS valid" if nav.get("gps_valid") else "no valid GNSS",
                )
                check(
                    "ins_pps",
                    nav.get("pps_detected") and nav.get("utc_detected"),
                    f"INS time source: {nav.get('time_source', 'none')}",
                )
            elif dev.kind == "profiler":
                rate = self.monitor.stats(dev.name).rate_hz
                check("profiler_data", bool(rate), f"{rate or 0:.0f} profiles/s")
                buf = getattr(dev.transport, "rcvbuf_bytes_granted", 0)
                check(
                    "receive_buffer",
                    buf >= MIN_RCVBUF_BYTES,
                    f"profiler socket buffer {buf / 2**20:.1f} MiB"
                    + (
                        "" if buf >= MIN_RCVBUF_BYTES else " (raise the sysctl net.core.rmem_max to 33554432)"
                    ),
                )
        state = self.clock.state_at(now)
        check("clock_locked", state == ClockState.LOCKED, f"clock {state.value}")
        bad = [
            a
            for a in self.alarms.active()
            if a.name
            in (
                "latency_out_of_band",
                "latency_jump",
                "time_step",
                "clock_drift",
                "pps_flag_lost",
                "latency_jitter",
            )
        ]
        check("latency_in_band", not bad, "; ".join(f"{a.device}: {a.name}" for a in bad) or "ok")
        w = self.writer.stats() if self.writer is not None else None
        free = w.free_bytes if w is not None else None
        check(
            "disk_space",
            free is not None and free > 2 * 2**30,
            "unknown" if free is None else f"{free / 2**30:.1f} GiB free",
        )
        check(
            "mount_configured",
            self.config.mount is not None,
            "mount in the vessel config" if self.config.mount else "no mount in the vessel config",
        )
        return checks

    def _log_status(self, now: int) -> None:
        if self.writer is None:
            return
        submit = self.ctx.submit
        submit("/status", self.status_doc(), host_ns=now)
        submit("/clock", self.clock_doc(now), host_ns=now)
        submit("/latency", self.monitor.snapshot(), host_ns=now)
