"""A session log's directory and settings, shared by the writer and the salvage: the names of
the session directory, its segments, lock and reserve files, :class:`SessionOptions`,
:class:`LogError` and :func:`fsync_dir`."""

from __future__ import annotations

import datetime as _dt
import os
import re
from dataclasses import dataclass
from pathlib import Path

from mcap.writer import CompressionType

from acquire.errors import AcquireError

SEGMENT_RE = re.compile(r"^seg-(\d{6})\.mcap$")
SESSION_RE = re.compile(r"^\d{8}T\d{6}Z_[A-Za-z0-9][A-Za-z0-9_.-]*$")
LOCK_NAME = "session.lock"
RESERVE_NAME = ".reserve"
COMPRESSIONS = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}


class LogError(AcquireError, RuntimeError):
    """A session directory that cannot be used (locked by another writer, not creatable)."""


@dataclass(frozen=True)
class SessionOptions:
    rotate_s: float = 600.0
    rotate_bytes: int = 512 * 1024 * 1024
    flush_s: float = 0.5  # chunk flush period (≤ 1 s)
    fsync_s: float = 2.0
    queue_size: int = 50_000
    compression: str = "zstd"  # zstd | lz4 | none
    chunk_bytes: int = 1024 * 1024
    retry_s: float = 1.0  # after a write failure, try a new segment this often
    reserve_bytes: int = 64 * 1024  # released to close a segment on a full disk
    min_free_bytes: int = 16 * 1024 * 1024  # no new segment on a file system with less free
    disk_warning_bytes: int = 10 * 2**30  # disk_low warning below this much free (0: no alarm)
    disk_critical_bytes: int = 2 * 2**30  # disk_low critical below this (0: never critical)
    disk_check_s: float = 1.0  # free space checked this often (and every 64 MiB written)
    stall_s: float = 10.0  # writer loop silent this long → unhealthy (watchdog)

    def __post_init__(self) -> None:
        if not 0 < self.flush_s <= 1.0:
            raise ValueError(f"flush_s={self.flush_s}: expected 0 < flush_s ≤ 1 s")
        if self.fsync_s <= 0 or self.rotate_s <= 0 or self.rotate_bytes <= 0:
            raise ValueError("fsync_s, rotate_s and rotate_bytes must be positive")
        if not 0 <= self.disk_critical_bytes <= self.disk_warning_bytes or self.disk_check_s <= 0:
            raise ValueError(
                f"disk_critical_bytes={self.disk_critical_bytes}, disk_warning_bytes="
                f"{self.disk_warning_bytes}, disk_check_s={self.disk_check_s}: expected "
                f"0 ≤ critical ≤ warning and a positive check period"
            )
        if self.compression not in COMPRESSIONS:
            raise ValueError(f"compression {self.compression!r}: expected one of {sorted(COMPRESSIONS)}")


def fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def session_name(vessel: str, start_utc: _dt.datetime) -> str:
    return f"{start_utc.astimezone(_dt.UTC):%Y%m%dT%H%M%SZ}_{vessel}"
