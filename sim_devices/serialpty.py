"""A serial device emulated on a pseudo-terminal behind a stable symlink.

The emulator writes to the pty's master side; the daemon opens the *link* (``<run dir>/ins``),
which points at the current slave (``/dev/pts/N``), like udev's ``/dev/serial/by-id/`` names.
:meth:`PtyPort.unplug` closes master and slave and removes the link (the reader sees end of
file / EIO); :meth:`PtyPort.plug` opens a new pty and moves the link to it atomically, so a
reader that reopens the same path reaches the new device.

Writes never block. A real device's UART sends whether or not anyone listens; here the kernel
buffers a few kB and then refuses: what it refuses is kept for ``backlog_s`` (a transmit FIFO)
and retried at the next write, then dropped and counted (``bytes_overrun``). Bytes written while
unplugged are counted as ``bytes_unplugged``. A pty has no baud rate: the stream is not paced by
the configured baud.
"""

from __future__ import annotations

import os
import time
import tty
from collections import deque
from pathlib import Path


class PtyPort:
    def __init__(self, link: str | Path, backlog_s: float = 0.05) -> None:
        self.link = Path(link)
        self.backlog_ns = round(backlog_s * 1e9)
        self.master: int | None = None
        self.slave: int | None = None
        self.slave_path: str | None = None
        self._backlog: deque[tuple[int, bytes]] = deque()
        self.stats = {"bytes_written": 0, "bytes_overrun": 0, "bytes_unplugged": 0, "plugs": 0, "unplugs": 0}

    @property
    def plugged(self) -> bool:
        return self.master is not None

    def plug(self) -> str:
        """Open a new pty and point the link at it; returns the slave's path."""
        if self.plugged:
            return self.slave_path
        master, slave = os.openpty()
        tty.setraw(slave)
        os.set_blocking(master, False)
        self.master, self.slave, self.slave_path = master, slave, os.ttyname(slave)
        tmp = self.link.with_name(f".{self.link.name}.{os.getpid()}.tmp")
        try:
            tmp.unlink()
        except FileNotFoundError:
            pass
        os.symlink(self.slave_path, tmp)
        os.replace(tmp, self.link)
        self.stats["plugs"] += 1
        return self.slave_path

    def unplug(self) -> None:
        """Remove the link and close the pty (both sides): the device is unplugged."""
        if self.plugged:
            self._release()
            self.stats["unplugs"] += 1

    def close(self) -> None:
        """The end of the run: like :meth:`unplug`, not counted as one."""
        if self.plugged:
            self._release()

    def _release(self) -> None:
        try:
            if self.link.is_symlink() and os.readlink(self.link) == self.slave_path:
                self.link.unlink()
        except OSError:
            pass
        for fd in (self.master, self.slave):
            try:
                os.close(fd)
            except OSError:
                pass
        self.master = self.slave = self.slave_path = None
        self._backlog.clear()

    def write(self, data: bytes, now_ns: int | None = None) -> None:
        if not self.plugged:
            self.stats["bytes_unplugged"] += len(data)
            return
        now = time.monotonic_ns() if now_ns is None else now_ns
        backlog = self._backlog
        while backlog and backlog[0][0] < now:  # older than the transmit FIFO holds
            self.stats["bytes_overrun"] += len(backlog.popleft()[1])
        if data:
            backlog.append((now + self.backlog_ns, data))
        while backlog:
            deadline, chunk = backlog[0]
            try:
                n = os.write(self.master, chunk)
            except BlockingIOError:
                n = 0
            except OSError:  # the pty is gone under us: count as overrun
                n = 0
            self.stats["bytes_written"] += n
            if n < len(chunk):
                backlog[0] = (deadline, chunk[n:])
                return
            backlog.popleft()
