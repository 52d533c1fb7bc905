"""One daemon per status socket: a lock file that says who holds it.

``mls acquire`` takes :class:`PidLock` on ``<status socket>.lock`` (e.g.
``/run/mls/status.sock.lock``, beside the socket in the run directory) before it salvages,
creates a session directory or touches the socket. The lock is an ``fcntl.flock`` on the file,
which holds one JSON line ``{"pid", "host", "started_utc", "config"}`` of the holder: a second
daemon on the same config is refused with the holder's PID and the lock's path, and leaves
everything as it found it.

The kernel releases a flock when its holder dies, so a lock that can be taken but still names a
holder was left by a daemon that ended without releasing it (``kill -9``, power cut): it is taken
over, and :meth:`PidLock.acquire` returns the old holder for the caller's warning. An orderly
release empties the file and keeps it (unlinking a lock file races with the next taker).

The daemon often runs as root: the lock file is opened with ``O_NOFOLLOW`` and refused when it is
a symlink, another user's file or a hard link, or when its directory is writable by others
(:mod:`acquire.status.runfiles`), so that nobody can have it truncate a file of their choosing.
"""

from __future__ import annotations

import datetime as _dt
import fcntl
import json
import logging
import os
import socket
import time
from dataclasses import asdict
from pathlib import Path

from acquire.errors import AcquireError
from acquire.status.runfiles import check_run_dir, open_private
from calib.io.dirlock import LockHolder


class LockHeld(AcquireError, RuntimeError):
    """The lock is held by another process (the message names its PID and the lock file)."""


def lock_path_for(socket_path: str | Path) -> Path:
    """The daemon lock of a status socket: ``<socket>.lock`` beside it."""
    p = Path(socket_path)
    return p.with_name(p.name + ".lock")


def read_holder(path: Path) -> LockHolder | None:
    """The holder a lock file names; None for an empty or missing file. An old-style file holding
    only a PID is read too."""
    try:
        text = Path(path).read_text(encoding="utf-8").strip()
    except (OSError, UnicodeDecodeError):
        return None
    if not text:
        return None
    try:
        d = json.loads(text)
        if isinstance(d, int):
            return LockHolder(d, None, None)
        pid = d.get("pid")
        return LockHolder(
            int(pid) if isinstance(pid, int) else None,
            d.get("host") or None,
            d.get("started_utc") or None,
            d.get("config") or None,
        )
    except (ValueError, AttributeError):
        return LockHolder(None, None, None, f"unreadable lock content {text[:80]!r}")


class PidLock:
    """An exclusive flock on ``path`` naming its holder (see the module docstring)."""

    def __init__(self, path: str | Path, config: str | None = None):
        self.path = Path(path)
        self.config = config
        self._fd: int | None = None

    @property
    def held(self) -> bool:
        return self._fd is not None

    def acquire(self) -> LockHolder | None:
        """Take the lock, write this process into it. Returns the previous holder when a stale
        lock (its holder gone without releasing it) was taken over, else None. Raises
        :class:`LockHeld` when another process holds it, :class:`UnsafeRunFile` (an OSError) when
        the file is a symlink, another user's, or in a directory others may write
        (:mod:`acquire.status.runfiles`), OSError when the file cannot be made."""
        if self._fd is not None:
            return None
        self.path.parent.mkdir(parents=True, exist_ok=True)
        check_run_dir(self.path.parent)
        fd = open_private(self.path, os.O_RDWR | os.O_CREAT)
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = None
                for _ in range(10):  # a holder that has just taken it writes itself at once
                    holder = read_holder(self.path)
                    if holder is not None:
                        break
                    time.sleep(0.02)
                holder = holder or LockHolder(None, None, None)
                raise LockHeld(
                    f"{self.path} is held by {holder.describe()}: another mls acquire runs on this "
                    f"status socket; stop it first (systemctl stop mls-acquire, or kill {holder.pid})"
                    if holder.pid is not None
                    else f"{self.path} is held by {holder.describe()}: another mls acquire runs on "
                    f"this status socket; stop it first"
                ) from None
            stale = read_holder(self.path)
            record = {
                "pid": os.getpid(),
                "host": socket.gethostname(),
                "started_utc": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
                "config": self.config,
            }
            os.ftruncate(fd, 0)
            os.pwrite(fd, (json.dumps(record) + "\n").encode(), 0)
            os.fsync(fd)
        except BaseException:
            os.close(fd)  # releases the flock if it was taken
            raise
        self._fd = fd
        return stale

    def take(self, log: logging.Logger) -> dict | None:
        """:meth:`acquire` for the daemon: a stale lock taken over is logged as a warning and
        returned as a dict (for the ``session_start`` event), else None."""
        stale = self.acquire()
        if stale is None:
            return None
        gone = "is now another process" if stale.running_here() else "is no longer running"
        log.warning(
            "took over the stale lock %s of %s: that daemon ended without releasing it (pid %s %s)",
            self.path,
            stale.describe(),
            stale.pid,
            gone,
        )
        return {"path": str(self.path), **asdict(stale)}

    def release(self) -> None:
        """Empty the file (an orderly end leaves no stale holder) and release the lock."""
        fd, self._fd = self._fd, None
        if fd is None:
            return
        try:
            os.ftruncate(fd, 0)
        except OSError:
            pass
        finally:
            os.close(fd)
