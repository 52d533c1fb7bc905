"""Free space of the log's file system, watched while segments are written: the ``disk_low``
alarm comes before a full disk stops the writer (docs/architecture.md §4.5, §6.4).

:func:`free_bytes` is the one place the writer asks the file system (a segment opening, each
fsync, each check). :class:`DiskWatch` runs on the writer thread every ``disk_check_s`` and
every :data:`CHECK_BYTES` written: below ``disk_warning_bytes`` free it raises ``disk_low``
(device ``log``) as a warning, below ``disk_critical_bytes`` as critical (raised again: an
escalation is an alarm event), with the free space and the minutes left at the write rate of
the last :data:`RATE_WINDOW_S` in its message. It drops back a level, or clears, only once the
free space is :data:`HYSTERESIS` above the threshold it crossed (value hysteresis).
"""

from __future__ import annotations

import os
from collections import deque
from pathlib import Path

from acquire.alarms import CRITICAL, WARNING, AlarmBook

NS_PER_S = 1_000_000_000
CHECK_BYTES = 64 * 2**20  # also check after this many bytes written since the last check
RATE_WINDOW_S = 30.0  # the write rate is taken over this long
HYSTERESIS = 0.10  # back a level once free space is 10 % above the threshold crossed
ALARM, DEVICE = "disk_low", "log"


def free_bytes(path: str | Path) -> int | None:
    """Bytes an unprivileged writer may still use on ``path``'s file system (statvfs
    ``f_bavail · f_frsize``); None when it cannot be read."""
    try:
        st = os.statvfs(path)
    except OSError:
        return None
    return st.f_bavail * st.f_frsize


def size_text(n: float) -> str:
    return f"{n / 2**30:.2f} GiB" if abs(n) >= 2**30 else f"{n / 2**20:.1f} MiB"


class DiskWatch:
    """The ``disk_low`` alarm of one session writer (see the module docstring)."""

    def __init__(self, warning_bytes: int, critical_bytes: int, check_s: float, alarms: AlarmBook):
        self.warning_bytes, self.critical_bytes = warning_bytes, critical_bytes
        self.check_ns = int(check_s * NS_PER_S)
        self.alarms = alarms
        self.level: str | None = None  # None | warning | critical
        self.free: int | None = None
        self.rate_bps: float | None = None  # bytes written per second, over RATE_WINDOW_S
        self.minutes_left: float | None = None  # free / rate (None: nothing being written)
        self._samples: deque[tuple[int, int]] = deque()  # (now_ns, bytes written)
        self._next_ns: int | None = None
        self._next_bytes = 0

    def due(self, now_ns: int, written: int) -> bool:
        return self._next_ns is None or now_ns >= self._next_ns or written >= self._next_bytes

    def update(self, now_ns: int, written: int, free: int | None, where: str | Path = "") -> None:
        """One check: ``written`` = bytes the writer has written so far, ``free`` = what
        :func:`free_bytes` says now (None: unknown, the alarm stays as it is)."""
        self._next_ns, self._next_bytes = now_ns + self.check_ns, written + CHECK_BYTES
        s = self._samples
        s.append((now_ns, written))
        while len(s) > 2 and now_ns - s[1][0] >= RATE_WINDOW_S * NS_PER_S:
            s.popleft()
        (t0, b0), (t1, b1) = s[0], s[-1]
        if t1 - t0 >= NS_PER_S:
            self.rate_bps = max(b1 - b0, 0) * NS_PER_S / (t1 - t0)
        if free is None:
            return
        self.free = free
        self.minutes_left = free / self.rate_bps / 60.0 if self.rate_bps else None
        if self.warning_bytes <= 0:
            return
        level = self._level(free)
        if level is None:
            if self.level is not None:
                self.alarms.clear_now(
                    ALARM,
                    DEVICE,
                    now_ns,
                    message=f"{size_text(free)} free on the log file system{_at(where)} again "
                    f"(warning below {size_text(self.warning_bytes)})",
                )
        else:
            threshold = self.critical_bytes if level == CRITICAL else self.warning_bytes
            self.alarms.raise_now(
                ALARM,
                DEVICE,
                now_ns,
                severity=level,
                message=f"{size_text(free)} free on the log file system{_at(where)}, below "
                f"{size_text(threshold)}: {self._eta()}; make room, or writing stops when "
                f"the disk is full",
            )
        self.level = level

    def _level(self, free: int) -> str | None:
        crit, warn, lvl, up = self.critical_bytes, self.warning_bytes, self.level, 1.0 + HYSTERESIS
        if crit > 0 and (free < crit or (lvl == CRITICAL and free < crit * up)):
            return CRITICAL
        if free < warn or (lvl is not None and free < warn * up):
            return WARNING
        return None

    def _eta(self) -> str:
        if self.rate_bps is None:
            return "write rate not known yet"
        if self.minutes_left is None:
            return "nothing being written"
        return f"about {self.minutes_left:.0f} min left at {self.rate_bps / 2**20:.2f} MiB/s"


def _at(where: str | Path) -> str:
    return f" ({where})" if str(where) else ""
