"""Two settings of the host: the UDP receive buffer the kernel allows (``net.core.rmem_max``,
read from a path: the seam) and the leap-second table the daemon will use (the built-in one, or
tzdata's ``leap-seconds.list`` when it is newer, as :class:`acquire.timing.timekeeper.TimeKeeper`
decides)."""

from __future__ import annotations

import datetime as _dt
from pathlib import Path

from acquire.daemon.reports import MIN_RCVBUF_BYTES
from acquire.doctor.result import CheckResult, fail, ok, warn
from acquire.timing.timekeeper import SYSTEM_LEAP_SECONDS_LIST
from calib.core.gpstime import LeapTable, leap_table, parse_leap_seconds_list

RMEM_MAX_PATH = Path("/proc/sys/net/core/rmem_max")
#: what the profiler's socket asks for (drivers/transport/udp_batch.py), and systemd/90-mls-net.conf
RMEM_MAX_WANTED_BYTES = 32 * 2**20
LEAP_WARN_DAYS = 30  # a table expiring this soon: update tzdata before the survey
SYSCTL_ADVICE = (
    "install systemd/90-mls-net.conf in /etc/sysctl.d/ (install.py does) and run `sysctl --system`"
)


def udp_buffer_check(path: Path = RMEM_MAX_PATH) -> CheckResult:
    """``net.core.rmem_max`` against the 32 MiB the profiler's socket asks for; below half the
    daemon's own pre-survey minimum (the kernel grants twice the cap) it is not ready."""
    try:
        rmem_max = int(path.read_text().split()[0])
    except (OSError, ValueError, IndexError) as e:
        return warn("udp_buffer", f"{path}: cannot be read ({e})", SYSCTL_ADVICE, data={"path": str(path)})
    data = {"path": str(path), "rmem_max_bytes": rmem_max, "wanted_bytes": RMEM_MAX_WANTED_BYTES}
    text = f"net.core.rmem_max {rmem_max / 2**20:.2f} MiB"
    if rmem_max >= RMEM_MAX_WANTED_BYTES:
        return ok("udp_buffer", f"{text} (≥ 32 MiB)", data=data)
    if 2 * rmem_max >= MIN_RCVBUF_BYTES:
        return warn(
            "udp_buffer",
            f"{text}, below 32 MiB: a stall of the PC may drop profiler packets",
            SYSCTL_ADVICE,
            data=data,
        )
    return fail(
        "udp_buffer",
        f"{text}: the profiler socket gets {2 * rmem_max / 2**20:.2f} MiB, less than "
        f"{MIN_RCVBUF_BYTES / 2**20:.0f} MiB (packets will be lost at the full rate)",
        SYSCTL_ADVICE,
        data=data,
    )


def effective_leap_table(system_list: Path = Path(SYSTEM_LEAP_SECONDS_LIST)) -> tuple[LeapTable, str]:
    """The table the daemon would use, and a note on the system file (never installed here)."""
    table = leap_table()
    try:
        other = parse_leap_seconds_list(system_list.read_text(encoding="ascii"), str(system_list))
    except (OSError, ValueError, UnicodeDecodeError) as e:
        return table, f"{system_list} not used: {e}"
    if other.expires > table.expires and other.extends(table):
        return other, f"{system_list} newer than the built-in table"
    return table, f"{system_list} not newer (expires {other.expires})"


def leap_check(today: _dt.date, system_list: Path = Path(SYSTEM_LEAP_SECONDS_LIST)) -> CheckResult:
    table, note = effective_leap_table(system_list)
    days_left = (table.expires - today).days
    data = {**table.as_dict(), "days_left": days_left, "system_list": note}
    advice = "update tzdata (apt-get install tzdata; its leap-seconds.list) or marine-mls"
    if days_left <= 0:
        return warn(
            "leap_table",
            f"the leap-second table expired on {table.expires} ({table.source}): "
            "the daemon will raise leap_table_stale",
            advice,
            data=data,
        )
    if days_left <= LEAP_WARN_DAYS:
        return warn(
            "leap_table",
            f"the leap-second table expires in {days_left} days ({table.expires})",
            advice,
            data=data,
        )
    return ok("leap_table", f"valid until {table.expires} (GPS − UTC {data['gps_minus_utc_s']} s)", data=data)
