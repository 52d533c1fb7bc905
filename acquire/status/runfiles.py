"""The files the daemon (often root) opens beside its status socket, and its session root: never
another user's.

The status socket and its lock (``<socket>.lock``, :mod:`acquire.daemon.pidlock`) live in a run
directory (``/run/mls``). Whoever can write that directory can put a symbolic link or a hard
link where the daemon will open, truncate or chmod a file, and have root do it to a file of
their choosing. So:

- :func:`check_run_dir`: the directory must be owned by this user or root and not writable by
  others (world-writable is accepted only with the sticky bit, as ``/tmp``: others cannot then
  remove or rename this user's files there);
- :func:`open_private`: the file is opened with ``O_NOFOLLOW | O_CLOEXEC`` (a symlink is refused,
  not followed) and refused unless it is a regular file of this user with one link;
- :func:`check_own_entry`: an entry found at the socket's path is a socket (or a stale plain
  file) of this user, not a symlink (it is then removed, never followed);
- :func:`check_session_root`: the directory of the sessions (``session.directory``), made if
  missing, must be owned by this user or root and not writable by others — the sticky bit is no
  excuse there: at start-up the daemon salvages every session it finds in it, and a session
  another user planted (with links to files of their choosing) would have it write there.

Each refusal is :class:`UnsafeRunFile`: one line naming the path and what to do.
"""

from __future__ import annotations

import errno
import os
import stat
from pathlib import Path

from acquire.errors import AcquireError


class UnsafeRunFile(AcquireError, PermissionError):
    """A run-directory file or directory others could have planted or may replace (the message
    names it and what to do)."""


def _owner_ok(uid: int) -> bool:
    return uid in (os.geteuid(), 0)


def check_private_dir(directory: str | Path, what: str, instead: str, *, sticky_ok: bool) -> None:
    """:class:`UnsafeRunFile` when ``directory`` is another user's (not this one's nor root's)
    or writable by every user (with ``sticky_ok``, unless it has the sticky bit, as ``/tmp``).
    The message names ``what`` it is, the owner and mode found, and the fix: chown, chmod, or
    ``instead``."""
    d = Path(directory)
    st = os.stat(d)
    mode = stat.S_IMODE(st.st_mode)
    if not _owner_ok(st.st_uid):
        raise UnsafeRunFile(
            f"{d}: the {what} belongs to uid {st.st_uid} (mode {mode:o}), not to this user (uid "
            f"{os.geteuid()}) or root: refused; give it to this user (chown {os.geteuid()} {d}) or {instead}"
        )
    if mode & stat.S_IWOTH and not (sticky_ok and mode & stat.S_ISVTX):
        sticky = "sticky bit, not enough here" if mode & stat.S_ISVTX else "no sticky bit"
        raise UnsafeRunFile(
            f"{d}: the {what} (owner uid {st.st_uid}) is writable by every user (mode {mode:o}, {sticky}): "
            f"refused; chmod o-w {d}{' (or +t)' if sticky_ok else ''}, or {instead}"
        )


def check_run_dir(directory: str | Path) -> None:
    """:class:`UnsafeRunFile` when ``directory`` is writable by others (without the sticky bit)
    or another user's."""
    check_private_dir(directory, "run directory", "choose another status.socket", sticky_ok=True)


def check_session_root(directory: str | Path) -> None:
    """Make the session root if it is missing (this user's, mode 755), then
    :class:`UnsafeRunFile` when it is another user's or writable by others (sticky or not)."""
    Path(directory).mkdir(mode=0o755, parents=True, exist_ok=True)
    check_private_dir(directory, "session root", "choose another session.directory", sticky_ok=False)


def open_private(path: str | Path, flags: int, mode: int = 0o644) -> int:
    """``os.open`` of a file of this user, never through a symlink (module docstring)."""
    p = Path(path)
    try:
        fd = os.open(p, flags | os.O_NOFOLLOW | os.O_CLOEXEC, mode)
    except OSError as e:
        if e.errno == errno.ELOOP:
            raise UnsafeRunFile(f"{p} is a symbolic link: refused (not followed); remove it") from None
        raise
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise UnsafeRunFile(f"{p} is not a regular file: refused; remove it")
        if st.st_uid != os.geteuid():
            raise UnsafeRunFile(
                f"{p} belongs to uid {st.st_uid}, not to this user (uid {os.geteuid()}): refused; remove it"
            )
        if st.st_nlink != 1:
            raise UnsafeRunFile(
                f"{p} has {st.st_nlink} hard links: refused (it may be another file); remove it"
            )
    except BaseException:
        os.close(fd)
        raise
    return fd


def check_own_entry(path: str | Path) -> bool:
    """Whether something is at ``path``; :class:`UnsafeRunFile` unless it is a socket or a plain
    file of this user (a symlink is refused, never followed)."""
    p = Path(path)
    try:
        st = os.lstat(p)
    except FileNotFoundError:
        return False
    if stat.S_ISLNK(st.st_mode):
        raise UnsafeRunFile(f"{p} is a symbolic link: refused (not followed); remove it")
    if not (stat.S_ISSOCK(st.st_mode) or stat.S_ISREG(st.st_mode)):  # (a stale file: removed)
        raise UnsafeRunFile(f"{p} exists and is not a socket: refused (not removed); remove it or move it")
    if not _owner_ok(st.st_uid):
        raise UnsafeRunFile(f"{p} belongs to uid {st.st_uid}, not to this user: refused; remove it")
    return True
