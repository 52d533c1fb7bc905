"""One writer per output directory: an exclusive flock on ``<dir>/.mls-lock``.

Every command that writes a directory (``mls georef``, ``mls calib run``, ``mls export``,
``mls design``, ``mls watch``, ``mls sim dataset``) holds :class:`DirLock` on it while it writes
(:func:`calib.io.outputs.lock_output_dir`). The lock file holds one JSON line naming the holder
(``pid``, ``host``, ``command``, ``started_utc``); a second writer is refused with one line naming
it (:class:`OutputLocked`), whatever its options (``--force`` and ``--resume`` included).

- The kernel releases a flock when its holder dies, so a lock file left by a killed process is
  no obstacle: the next writer takes it over.
- An orderly release unlinks the file while still holding the lock, so a finished deliverable
  holds no lock file. A taker therefore checks, once it holds the flock, that the path still
  names the file it locked (else it locked an unlinked file: it tries again).
- The file is opened with ``O_NOFOLLOW | O_CLOEXEC``: a symlink there is refused, never followed,
  and a child process (a Dask worker, an exporter) does not inherit the lock.
- A CLI command keeps its lock with :func:`hold` until the command ends: the ``mls`` group
  (``cli/app.py``) calls :func:`release_held` once the command returns or fails (and so does the
  interpreter's exit).
"""

from __future__ import annotations

import atexit
import datetime as _dt
import errno
import fcntl
import json
import os
import shlex
import socket
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from calib.core.errors import CalibError

LOCK_NAME = ".mls-lock"
_OPEN_FLAGS = os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC


class OutputLocked(CalibError, RuntimeError):
    """An output directory is held by another writer, or its lock file cannot be used (the
    message names the directory and the holder)."""


@dataclass(frozen=True)
class LockHolder:
    """What a lock file says about its holder (``None``: not written): an output directory's
    writer (its ``command``) or the acquisition daemon (its ``config``)."""

    pid: int | None
    host: str | None
    started_utc: str | None
    config: str | None = None
    command: str | None = None

    def describe(self) -> str:
        who = f"pid {self.pid}" if self.pid is not None else "a process whose pid is not written yet"
        if self.host:
            who += f" on {self.host}"
        if self.command:
            who += f" ({self.command})"
        if self.started_utc:
            who += f", started {self.started_utc}"
        if self.config:
            who += f", config {self.config}"
        return who

    def running_here(self) -> bool:
        """The PID is a live process of this host."""
        if self.pid is None or (self.host and self.host != socket.gethostname()):
            return False
        try:
            os.kill(self.pid, 0)
        except ProcessLookupError:
            return False
        except PermissionError:  # alive, another user's
            return True
        return True


def _parse_holder(data: bytes) -> LockHolder | None:
    try:
        d = json.loads(data.decode("utf-8"))
        pid = d.get("pid")
        return LockHolder(
            pid if isinstance(pid, int) else None,
            d.get("host") or None,
            d.get("started_utc") or None,
            command=d.get("command") or None,
        )
    except (ValueError, AttributeError, UnicodeDecodeError):
        return None


def _read_holder(fd: int) -> LockHolder:
    """The holder written in the open lock file ``fd``; a holder that has just taken the lock
    writes itself at once, so an empty file is read again for a moment."""
    for _ in range(25):
        holder = _parse_holder(os.pread(fd, 4096, 0))
        if holder is not None:
            return holder
        time.sleep(0.02)
    return LockHolder(None, None, None)


def default_command() -> str:
    """This process's command line, as the lock records it."""
    argv = [Path(sys.argv[0]).name, *sys.argv[1:]] if sys.argv else ["?"]
    text = shlex.join(argv)
    return text if len(text) <= 200 else text[:199] + "…"


class DirLock:
    """The writer lock of ``directory`` (module docstring); the directory must exist."""

    def __init__(self, directory: str | Path, command: str | None = None):
        self.directory = Path(directory)
        self.path = self.directory / LOCK_NAME
        self.command = command or default_command()
        self.remove_dir_if_empty = False  # set by the caller that created the directory
        self._fd: int | None = None

    @property
    def held(self) -> bool:
        return self._fd is not None

    def _open(self) -> int:
        try:
            return os.open(self.path, _OPEN_FLAGS, 0o644)
        except OSError as e:
            if e.errno == errno.ELOOP:
                raise OutputLocked(
                    f"{self.directory}: its writer lock {self.path} is a symbolic link; remove it"
                ) from None
            raise OutputLocked(
                f"{self.directory}: cannot create the writer lock {self.path} ({e.strerror or e})"
            ) from None

    def _same_file(self, fd: int) -> bool:
        """The path still names the file ``fd`` locked (a releasing holder unlinks it)."""
        try:
            st = os.lstat(self.path)
        except FileNotFoundError:
            return False
        own = os.fstat(fd)
        return (st.st_dev, st.st_ino) == (own.st_dev, own.st_ino)

    def acquire(self) -> None:
        """Take the lock and write this process into it; :class:`OutputLocked` when another
        process holds it."""
        if self._fd is not None:
            return
        while True:
            fd = self._open()
            try:
                try:
                    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                except BlockingIOError:
                    holder = _read_holder(fd)
                    raise OutputLocked(
                        f"{self.directory}: another writer holds it: {holder.describe()}; wait for "
                        f"it to end or choose another directory"
                    ) from None
                if not self._same_file(fd):
                    os.close(fd)
                    continue
                self._write_holder(fd)
            except BaseException:
                os.close(fd)  # releases the flock if it was taken
                raise
            self._fd = fd
            return

    def _write_holder(self, fd: int) -> None:
        record = {
            "pid": os.getpid(),
            "host": socket.gethostname(),
            "command": self.command,
            "started_utc": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        }
        os.ftruncate(fd, 0)
        os.pwrite(fd, (json.dumps(record) + "\n").encode(), 0)

    def release(self) -> None:
        """Unlink the lock file (it is still ours) and release the lock; then remove the
        directory if it was made for this writer and nothing was written into it."""
        fd, self._fd = self._fd, None
        if fd is None:
            return
        try:
            if self._same_file(fd):
                self.path.unlink()
        except OSError:
            pass
        finally:
            os.close(fd)
        if self.remove_dir_if_empty:
            try:
                self.directory.rmdir()
            except OSError:
                pass

    def __enter__(self) -> DirLock:
        self.acquire()
        return self

    def __exit__(self, *exc) -> None:
        self.release()


_HELD: list[DirLock] = []


def hold(lock: DirLock) -> DirLock:
    """Keep ``lock`` until :func:`release_held` (the end of the CLI command, or of the process)."""
    _HELD.append(lock)
    return lock


def release_held() -> None:
    """Release every lock :func:`hold` keeps, the last taken first."""
    while _HELD:
        _HELD.pop().release()


atexit.register(release_held)
