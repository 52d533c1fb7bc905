"""Room on the session disk for the hours the operator plans, at the rates the config states,
and the daemon's user allowed to write there.

The log's rate is the daemon's own estimate (the guidance's :func:`disk_needed_bytes`, with
``acquire/guidance/prechecks.py``'s ``DEFAULT_LOG_RATE_BYTES_S`` at the defaults): each profiler
at its profile rate × ``guidance.points_per_360`` points of 6 bytes plus 10 % framing, each INS
at its record rate × about 300 bytes (NMEA). The free space comes from
:func:`acquire.log.diskspace.free_bytes` (the writer's own reading; the seam). After the planned
hours the disk must keep ``session.disk_warning_mb`` free (else ``disk_low`` would be raised
during the survey: a warning) and ``session.disk_critical_mb`` (else: not ready).
"""

from __future__ import annotations

import errno
import os
import tempfile
from collections.abc import Callable
from pathlib import Path

from acquire.doctor.access import WRITE, DaemonUser, describe, may
from acquire.doctor.result import CheckResult, fail, ok, warn
from acquire.log.diskspace import free_bytes, size_text

POINT_BYTES = 6  # ZFP1: range u32 + intensity u16
FRAMING = 1.1  # packet headers and the log's records
INS_RECORD_BYTES = 300  # one INS epoch in NMEA
INS_DEFAULT_HZ = 200.0


def log_rate_bytes_per_s(cfg) -> float:
    """Bytes per second the session log grows by at the config's rates."""
    g = cfg.guidance
    rate = 0.0
    for d in cfg.devices:
        if d.kind == "profiler":
            rate += (d.latency.rate_hz or g.profile_rate_hz) * g.points_per_360 * POINT_BYTES * FRAMING
        elif d.kind == "ins":
            rate += (d.latency.rate_hz or INS_DEFAULT_HZ) * INS_RECORD_BYTES
    return rate


def existing_dir(path: Path) -> Path:
    """``path``, or its nearest existing parent (the daemon makes the session root)."""
    p = path
    while not p.exists() and p != p.parent:
        p = p.parent
    return p


def _unwritable(where: Path, user: DaemonUser) -> CheckResult | None:
    st = os.stat(where)
    if not may(st, user, WRITE | 1):  # write and search
        return fail(
            "disk",
            f"{where} ({describe(st)}): {user.described} may not write there",
            f"chown {user.name}:{user.name} {where} (install.py makes /var/lib/mls/sessions) "
            "or choose another session.directory",
            data={"directory": str(where)},
        )
    try:  # a read-only or full file system: whoever runs doctor sees it too
        tempfile.TemporaryFile(dir=where).close()
    except OSError as e:
        if e.errno in (errno.EROFS, errno.ENOSPC, errno.EDQUOT):
            return fail(
                "disk",
                f"{where}: cannot write: {e.strerror}",
                "remount it read-write or free space",
                data={"directory": str(where)},
            )
    return None


def disk_check(
    cfg, hours: float, user: DaemonUser, free: Callable[[Path], int | None] = free_bytes
) -> CheckResult:
    where = existing_dir(cfg.session_dir)
    if (bad := _unwritable(where, user)) is not None:
        return bad
    rate = log_rate_bytes_per_s(cfg)
    have = free(where)
    data = {
        "directory": str(cfg.session_dir),
        "hours": hours,
        "rate_bytes_per_s": round(rate),
        "free_bytes": have,
    }
    if have is None:
        return warn("disk", f"{where}: free space unknown", "check the mount (df -h)", data=data)
    opts = cfg.session
    need = int(hours * 3600 * rate)
    left = have - need
    hours_possible = max(have - opts.disk_critical_bytes, 0) / rate / 3600 if rate else None
    data.update(
        need_bytes=need,
        left_bytes=left,
        hours_possible=None if hours_possible is None else round(hours_possible, 1),
    )
    text = (
        f"{size_text(have)} free in {where}; {hours:g} h at {rate / 2**20:.2f} MiB/s need {size_text(need)}"
    )
    advice = "free space (older sessions to the office disk), or plan fewer hours"
    if left < max(opts.disk_critical_bytes, opts.min_free_bytes):
        return fail(
            "disk", f"{text}: not enough (about {hours_possible or 0:.1f} h possible)", advice, data=data
        )
    if left < opts.disk_warning_bytes:
        return warn("disk", f"{text}: disk_low would be raised during the survey", advice, data=data)
    return ok("disk", f"{text}; {size_text(left)} left after", data=data)
