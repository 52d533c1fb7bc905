"""Each serial device of the config present, a character device, and openable by the daemon's
user: its mode bits for ``mls`` (with the unit's ``dialout``), and a real open by this process
(``O_NONBLOCK``, no settings changed) unless the running daemon has it."""

from __future__ import annotations

import errno
import os
import stat

from acquire.doctor.access import READ, WRITE, DaemonUser, describe, may
from acquire.doctor.result import CheckResult, fail, ok

FIND_PORT = "ls -l /dev/serial/by-id/ names the adapters plugged in"


def serial_devices(cfg) -> list[tuple[str, str]]:
    """``(device name, port)`` of every serial port the daemon opens: serial transports and
    serial-line PPS sources."""
    out = []
    for d in cfg.devices:
        if d.transport is not None and getattr(d.transport, "type", "") == "serial":
            out.append((d.name, d.transport.port))
        elif d.source is not None and d.source.type == "serial-line" and d.source.port:
            out.append((d.name, d.source.port))
    return out


def serial_check(device: str, port: str, user: DaemonUser, daemon_running: bool) -> CheckResult:
    """One serial port: present, a character device, readable and writable by ``user``, and
    opened once here."""
    data = {"port": port, "daemon_user": user.name}
    try:
        st = os.stat(port)
    except OSError as e:
        return fail(
            "serial",
            f"{port}: {e.strerror}",
            f"plug the device in, or set the config's port to where it is ({FIND_PORT})",
            device=device,
            data=data,
        )
    data["mode"] = describe(st)
    if not stat.S_ISCHR(st.st_mode):
        return fail(
            "serial",
            f"{port}: not a character device ({data['mode']})",
            f"set the config's port to the serial device ({FIND_PORT})",
            device=device,
            data=data,
        )
    if not may(st, user, READ | WRITE):
        return fail(
            "serial",
            f"{port} ({data['mode']}): {user.described} may not read and write it",
            'give the port to group dialout (a udev rule GROUP="dialout", MODE="0660"): the '
            "unit runs the daemon with SupplementaryGroups=dialout",
            device=device,
            data=data,
        )
    if daemon_running:
        return ok(
            "serial", f"{port} ({data['mode']}) present; the running daemon has it", device=device, data=data
        )
    return _open_once(device, port, data)


def _open_once(device: str, port: str, data: dict) -> CheckResult:
    try:
        fd = os.open(port, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    except OSError as e:
        held = e.errno == errno.EBUSY
        return fail(
            "serial",
            f"{port} ({data['mode']}) cannot be opened: [Errno {e.errno}] {e.strerror}",
            "another program holds it: `fuser -v "
            + port
            + "` names it; stop it (gpsd, ModemManager, a terminal)"
            if held
            else "check the adapter (dmesg) and the port's permissions",
            device=device,
            data=data,
        )
    os.close(fd)
    return ok("serial", f"{port} ({data['mode']}) present and openable", device=device, data=data)
