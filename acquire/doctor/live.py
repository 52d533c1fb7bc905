"""The running daemon's own view of the same things, when it runs: its lock beside the status
socket names it (:mod:`acquire.daemon.pidlock`) and its socket gives the snapshot ``mls status``
shows (:func:`acquire.status.bus.read_snapshot`): state, clock, devices, log disk, MQTT, the
pre-survey checks (the receive buffer it was granted among them) and the active alarms."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from acquire.daemon.pidlock import lock_path_for, read_holder
from acquire.status.bus import read_snapshot


def _pid_alive(pid: int | None) -> bool:
    if pid is None:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def summary(snap: dict[str, Any]) -> dict[str, Any]:
    """The part of the snapshot ``mls doctor`` shows (docs/doctor.md ``live``)."""
    st = snap.get("status", {})
    log = st.get("log") or {}
    clock = snap.get("clock", {})
    presurvey = (snap.get("checklist") or {}).get("presurvey") or {}
    return {
        "state": st.get("state"),
        "pid": st.get("pid"),
        "session": st.get("session"),
        "uptime_s": st.get("uptime_s"),
        "clock": st.get("clock"),
        "clock_error_bound_us": clock.get("error_bound_us"),
        "devices": st.get("devices") or {},
        "log_free_mb": log.get("free_mb"),
        "mqtt": st.get("mqtt"),
        "presurvey": {k: v for k, v in presurvey.items() if isinstance(v, dict)},
        "alarms": [
            {k: a.get(k) for k in ("severity", "name", "device", "message")} for a in st.get("alarms") or []
        ],
    }


def live_view(socket: Path, timeout_s: float = 2.0) -> dict[str, Any] | None:
    """None when no daemon runs on this config; else its view, or why it cannot be read."""
    holder = read_holder(lock_path_for(socket))
    pid = holder.pid if holder is not None else None
    try:
        snap = read_snapshot(socket, timeout_s)
    except PermissionError as e:
        return {
            "socket": str(socket),
            "pid": pid,
            "error": f"{e.strerror}: run as root or as a member of group mls",
        }
    except (OSError, ValueError) as e:
        if not _pid_alive(pid):
            return None
        return {"socket": str(socket), "pid": pid, "error": f"the daemon (pid {pid}) does not answer: {e}"}
    return {"socket": str(socket), **summary(snap), "pid": (snap.get("status") or {}).get("pid", pid)}
