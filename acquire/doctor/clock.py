"""Is the host clock disciplined? chrony (``chronyc -n tracking``: synchronised, reference, offset),
else systemd-timesyncd or another NTP client through ``timedatectl`` (synchronised or not, no
offset), else unknown. gpsd disciplines nothing itself: it feeds chrony (SHM or SOCK refclock),
so chrony's reference names it. The commands run through a :data:`Runner` (the seam)."""

from __future__ import annotations

import re
import shutil
import subprocess
from collections.abc import Callable

from acquire.doctor.result import CheckResult, fail, ok, warn

#: runs a command: (exit status, stdout + stderr), or None when the program is not installed
Runner = Callable[[list[str]], tuple[int, str] | None]
WELL_WITHIN_S = 0.010  # a disciplined clock is within milliseconds; beyond this, a warning
INSTALL_CHRONY = (
    "install chrony and give it the GNSS time: `refclock PPS /dev/pps0 lock NMEA` with gpsd's "
    "`refclock SHM 0 refid NMEA noselect` (chrony.conf(5)), then `chronyc tracking`"
)


def run_command(cmd: list[str], timeout_s: float = 5.0) -> tuple[int, str] | None:
    """The real :data:`Runner`."""
    if shutil.which(cmd[0]) is None:
        return None
    try:
        r = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s)
    except (OSError, subprocess.TimeoutExpired) as e:
        return 1, str(e)
    return r.returncode, r.stdout + r.stderr


def parse_tracking(text: str) -> dict:
    """``chronyc tracking``'s fields: ``reference``, ``stratum``, ``offset_s`` (system time
    minus true time: positive when fast), ``leap_status``."""
    fields = {k.strip(): v.strip() for k, _, v in (ln.partition(":") for ln in text.splitlines()) if v}
    out: dict = {"leap_status": fields.get("Leap status")}
    ref = fields.get("Reference ID", "")
    m = re.search(r"\((.*)\)", ref)
    out["reference"] = m.group(1) if m else ref or None
    out["stratum"] = int(fields["Stratum"]) if fields.get("Stratum", "").isdigit() else None
    m = re.match(r"([0-9.]+) seconds (fast|slow)", fields.get("System time", ""))
    out["offset_s"] = None if m is None else float(m.group(1)) * (1 if m.group(2) == "fast" else -1)
    return out


def _chrony(text: str, limit_s: float) -> CheckResult:
    t = parse_tracking(text)
    data = {"source": "chrony", **t}
    off = t["offset_s"]
    where = f"chrony, reference {t['reference']}, stratum {t['stratum']}"
    if t["leap_status"] != "Normal" or off is None:
        return warn(
            "clock",
            f"{where}: not synchronised (leap status {t['leap_status']})",
            "wait for chrony to lock (`chronyc sources`), check its refclocks",
            data=data,
        )
    if abs(off) >= limit_s:
        return fail(
            "clock",
            f"{where}: system clock {off:+.3f} s off (limit {limit_s:g} s)",
            "chrony is not correcting the clock: `chronyc makestep`, then check chrony.conf",
            data=data,
        )
    if abs(off) >= WELL_WITHIN_S:
        return warn(
            "clock",
            f"{where}: offset {off * 1e3:+.1f} ms",
            "let chrony settle (`chronyc tracking`)",
            data=data,
        )
    return ok("clock", f"{where}: synchronised, offset {off * 1e6:+.0f} µs", data=data)


def _timedatectl(run: Runner) -> CheckResult | None:
    got = run(["timedatectl", "show", "--property=NTP", "--property=NTPSynchronized"])
    if got is None or got[0] != 0:
        return None  # not installed, or no systemd
    props = dict(ln.split("=", 1) for ln in got[1].splitlines() if "=" in ln)
    data = {
        "source": "timedatectl",
        "ntp": props.get("NTP"),
        "synchronised": props.get("NTPSynchronized") == "yes",
    }
    if data["synchronised"]:
        return ok("clock", "synchronised (timedatectl: NTPSynchronized=yes; offset not reported)", data=data)
    return warn("clock", "not synchronised (timedatectl: NTPSynchronized=no)", INSTALL_CHRONY, data=data)


def clock_check(run: Runner = run_command, offset_limit_s: float = 1.0) -> CheckResult:
    """``offset_limit_s``: the config's ``clock.host_offset_alarm_s`` (the daemon's alarm)."""
    got = run(["chronyc", "-n", "tracking"])
    if got is not None:
        if got[0] == 0:
            return _chrony(got[1], offset_limit_s)
        return warn(
            "clock",
            f"chronyc tracking failed: {got[1].strip()[:120]}",
            "start chrony: systemctl enable --now chrony",
            data={"source": "chrony"},
        )
    other = _timedatectl(run)
    if other is not None:
        return other
    return warn(
        "clock", "unknown: neither chrony nor timedatectl answers", INSTALL_CHRONY, data={"source": None}
    )
