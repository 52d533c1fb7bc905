"""systemd notification protocol (``sd_notify``) with the standard library, and a health watchdog.

``Type=notify`` services tell systemd ``READY=1`` when they serve, ``WATCHDOG=1`` at least every
``WatchdogSec`` while healthy, ``STATUS=...`` (shown by ``systemctl status``) and ``STOPPING=1``.
Messages are datagrams to the AF_UNIX socket named by ``$NOTIFY_SOCKET`` (a path, or an abstract
name written ``@name``). Outside systemd (no ``$NOTIFY_SOCKET``) every call is a no-op.

:class:`HealthWatchdog` ties the pings to real health: it sends ``WATCHDOG=1`` only when every
registered check passes (drivers alive, the log writer progressing); otherwise it withholds the
ping and says why in ``STATUS=``, so systemd restarts a daemon that is hung, not one that is
merely busy. Advisories (a device that is not connected) are named in ``STATUS=`` (``running,
degraded: devices: ins not connected: [Errno 2] ...``, shown by ``systemctl status``) but never
withhold the ping: a restart would not bring the device back.
"""

from __future__ import annotations

import asyncio
import os
import socket
from collections.abc import Callable

Check = Callable[[], "tuple[bool, str]"]


def _address(value: str) -> str | bytes:
    if value.startswith("@"):
        return b"\0" + value[1:].encode()  # abstract namespace
    return value


def notify(message: str, env: dict[str, str] | None = None) -> bool:
    """Send one notification; True when it was sent (False outside systemd)."""
    target = (env if env is not None else os.environ).get("NOTIFY_SOCKET")
    if not target or not (target.startswith("/") or target.startswith("@")):
        return False
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC) as s:
        s.connect(_address(target))
        s.sendall(message.encode())
    return True


def ready(status: str | None = None) -> bool:
    return notify("READY=1" + (f"\nSTATUS={status}" if status else ""))


def stopping(status: str | None = None) -> bool:
    return notify("STOPPING=1" + (f"\nSTATUS={status}" if status else ""))


def status(text: str) -> bool:
    return notify(f"STATUS={text}")


def watchdog_period_s(env: dict[str, str] | None = None) -> float | None:
    """The ``WatchdogSec`` systemd asks of this process (``$WATCHDOG_USEC`` / ``$WATCHDOG_PID``),
    or None when no watchdog is armed for it."""
    env = env if env is not None else dict(os.environ)
    usec = env.get("WATCHDOG_USEC")
    pid = env.get("WATCHDOG_PID")
    if not usec or not usec.isdigit() or int(usec) == 0:
        return None
    if pid and pid.isdigit() and int(pid) != os.getpid():
        return None
    return int(usec) / 1e6


class HealthWatchdog:
    """Pings the systemd watchdog only while every named check passes."""

    def __init__(
        self,
        checks: dict[str, Check] | None = None,
        env: dict[str, str] | None = None,
        advisories: dict[str, Check] | None = None,
    ):
        self.checks: dict[str, Check] = dict(checks or {})
        self.advisories: dict[str, Check] = dict(advisories or {})  # in STATUS=, never withholding
        self.env = env
        self.last_failures: list[str] | None = None  # None: nothing reported yet
        self.last_status: str | None = None
        self.pings = 0

    def add_check(self, name: str, check: Check) -> None:
        self.checks[name] = check

    def evaluate(self, checks: dict[str, Check] | None = None) -> list[str]:
        """The failing checks (default: the health checks) as ``"name: reason"`` (a check that
        raises fails)."""
        failures = []
        for name, check in (self.checks if checks is None else checks).items():
            try:
                ok, reason = check()
            except Exception as e:
                ok, reason = False, f"check raised {type(e).__name__}: {e}"
            if not ok:
                failures.append(f"{name}: {reason}")
        return failures

    def beat(self) -> bool:
        """One watchdog round: ping if healthy, else report why not. Returns health."""
        failures = self.evaluate()
        notes = self.evaluate(self.advisories)
        if failures:
            text = "unhealthy: " + "; ".join(failures + notes)
        else:
            text = "running" + (", degraded: " + "; ".join(notes) if notes else "")
        if text != self.last_status:
            notify("STATUS=" + text, self.env)
        self.last_failures, self.last_status = failures, text
        if failures:
            return False
        if notify("WATCHDOG=1", self.env):
            self.pings += 1
        return True

    async def run(self, period_s: float | None = None) -> None:
        """Beat every half watchdog period (or ``period_s``) until cancelled."""
        interval = period_s or (watchdog_period_s(self.env) or 20.0) / 2.0
        while True:
            self.beat()
            await asyncio.sleep(interval)
