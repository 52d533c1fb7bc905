"""Waiting for a missing device path to appear without polling: an inotify watch (Linux, through
ctypes) on the deepest directory of the path that exists.

A serial device comes back as a path: ``/dev/ttyUSB0`` made by the kernel, then the stable link
``/dev/serial/by-id/usb-…`` made by udev (its directory too, when it is the only adapter), or an
emulator's ``<run dir>/ins`` moved into place. :func:`wait_for_path` returns as soon as the path
exists, or something was created, moved in or changed in that directory (the caller looks
again: a deeper directory may now exist), or after ``timeout_s`` in any case — a link whose
target comes later, or a file system whose changes inotify does not see, is found at the
caller's next look. While nothing happens it costs nothing (no wake-up before ``timeout_s``);
without inotify (another OS, the per-user limit of instances reached) it sleeps ``timeout_s``.
"""

from __future__ import annotations

import asyncio
import ctypes
import functools
import os
from pathlib import Path

_IN_ATTRIB, _IN_MOVED_TO, _IN_CREATE = 0x004, 0x080, 0x100
_IN_DELETE_SELF, _IN_MOVE_SELF, _IN_ONLYDIR = 0x400, 0x800, 0x01000000
_MASK = _IN_ATTRIB | _IN_MOVED_TO | _IN_CREATE | _IN_DELETE_SELF | _IN_MOVE_SELF | _IN_ONLYDIR


@functools.cache
def _libc() -> ctypes.CDLL | None:
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        _ = (libc.inotify_init1, libc.inotify_add_watch)  # present: Linux
    except (OSError, AttributeError):
        return None
    return libc


def nearest_directory(path: str | os.PathLike) -> Path:
    """The deepest existing directory on the way to ``path`` (its parent, or one above)."""
    d = Path(os.path.abspath(path)).parent
    while not d.is_dir() and d != d.parent:
        d = d.parent
    return d


def _watch(directory: Path) -> int | None:
    """An inotify descriptor watching ``directory`` for new or changed entries, or None."""
    libc = _libc()
    if libc is None:
        return None
    fd = libc.inotify_init1(os.O_NONBLOCK | os.O_CLOEXEC)
    if fd < 0:
        return None
    if libc.inotify_add_watch(fd, os.fsencode(directory), _MASK) < 0:
        os.close(fd)
        return None
    return fd


async def wait_for_path(path: str | os.PathLike, timeout_s: float) -> bool:
    """Wait until ``path`` exists, the deepest existing directory on the way to it changes, or
    ``timeout_s`` passes (module docstring); returns whether the path exists."""
    fd = _watch(nearest_directory(path))
    if fd is None:
        await asyncio.sleep(timeout_s)
        return os.path.exists(path)  # noqa: ASYNC240 (a stat of a device path: no disk, no wait)
    loop = asyncio.get_running_loop()
    changed = loop.create_future()

    def readable() -> None:
        if not changed.done():
            changed.set_result(None)

    loop.add_reader(fd, readable)
    try:
        # (it may have come before the watch was in place; a stat of a device path does not block)
        if not os.path.exists(path):  # noqa: ASYNC240
            await asyncio.wait({changed}, timeout=timeout_s)
    finally:
        loop.remove_reader(fd)
        os.close(fd)
        changed.cancel()
    return os.path.exists(path)  # noqa: ASYNC240 (a stat of a device path: no disk, no wait)
