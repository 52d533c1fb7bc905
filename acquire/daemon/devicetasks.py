"""The daemon's device tasks: :class:`DeviceRunner` keeps each device open and running for
:class:`~acquire.daemon.supervisor.Supervisor` — one :meth:`DeviceRunner.run` per device task,
reopening a device after a failure with a doubling back-off, and every failure recorded in the
:class:`~acquire.daemon.reports.DeviceHealth`, alarmed (``device_unavailable`` for a device
error, ``driver_failed`` for a bug) and logged to ``/events``."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
import traceback
from collections.abc import Callable

from acquire.alarms import CRITICAL, AlarmBook
from acquire.daemon.devices import Device
from acquire.daemon.reports import DeviceHealth
from drivers.base import DriverError

log = logging.getLogger("mls.acquire")
DRIVER_BACKOFF_S = (0.5, 30.0)  # the first and the longest wait before reopening a device


class DeviceRunner:
    """Runs the devices (see the module docstring); ``log_event(data, host_ns)`` writes an
    ``/events`` entry (the supervisor's :meth:`~acquire.daemon.supervisor.Supervisor.log_event`)."""

    def __init__(
        self, *, health: DeviceHealth, alarms: AlarmBook, log_event: Callable[[dict, int | None], None]
    ) -> None:
        self.health = health
        self.alarms = alarms
        self.log_event = log_event

    async def run(self, dev: Device) -> None:
        """Open and run a device for ever; after a failure close it, wait (doubling back-off)
        and open it again. A device error (:class:`~drivers.base.DriverError`, ``OSError``: the
        device is absent or went away) makes it *unavailable* (alarm ``device_unavailable``);
        anything else is a bug in a driver (alarm ``driver_failed``), which also withholds the
        systemd watchdog until the device runs again."""
        backoff = DRIVER_BACKOFF_S[0]
        while True:
            try:
                if not dev.opened:
                    await dev.open()
                self.health.crashed.pop(dev.name, None)
                self.health.unavailable.pop(dev.name, None)
                now = time.monotonic_ns()
                if self.alarms.is_active("driver_failed", dev.name):
                    self.alarms.clear_now("driver_failed", dev.name, now, message=f"{dev.name} running again")
                self.health.update_alarms(self.alarms, now)  # cleared once its transport is connected
                await dev.run()
                raise EOFError(f"{dev.name}: the device stream ended")
            except asyncio.CancelledError:
                raise
            except Exception as e:
                self.failed(dev, e, "open" if not dev.opened else "run")
                with contextlib.suppress(Exception):
                    await dev.close()
                dev.opened = False
                await asyncio.sleep(backoff)
                backoff = min(backoff * 2, DRIVER_BACKOFF_S[1])

    def failed(self, dev: Device, e: BaseException, when: str) -> None:
        """A failure of ``dev`` (in its ``open`` or ``run``): recorded, alarmed and logged."""
        text = f"{type(e).__name__}: {e}"
        now = time.monotonic_ns()
        if isinstance(e, (DriverError, OSError, EOFError)):
            self.health.unavailable[dev.name] = text
            name, what = "device_unavailable", "not connected"
        else:
            self.health.crashed[dev.name] = text
            name, what = "driver_failed", "driver failed"
        message = f"{dev.name} ({dev.kind}) {what}: {text}; retrying"
        self.alarms.raise_now(name, dev.name, now, severity=CRITICAL, message=message)
        self.log_event(
            {
                "event": name,
                "device": dev.name,
                "when": when,
                "error": text,
                "traceback": traceback.format_exception(e)[-3:],
            },
            now,
        )
        log.error("device %s: %s (%s): %s", dev.name, what, when, text)
