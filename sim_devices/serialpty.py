"""A serial device emulated on a pseudo-terminal behind a stable symlink.

The emulator writes to the pty's master side; the daemon opens the *link* (``<run dir>/ins``),
which points at the current slave (``/dev/pts/N``), like udev's ``/dev/serial/by-id/`` names.
:meth:`PtyPort.unplug` closes master and slave and removes the link (the reader sees end of
file / EIO); :meth:`PtyPort.plug` opens a new pty and moves the link to it atomically, so a
reader that reopens the same path reaches the new device.

Writes never block. A real device's UART sends whether or not anyone listens; here the kernel
buffers a few kB and then refuses: what it refuses is kept for ``backlog_s`` (a transmit FIFO)
and retried at each write, then — still refused at a write after ``backlog_s`` — dropped and
counted (``bytes_overrun``; :attr:`PtyPort.overruns`: when). Bytes written while
unplugged are counted as ``bytes_unplugged``; those in flight when the device is unplugged (still
in the transmit FIFO, or in the pty where nobody read them yet: closing it discards them) as
``bytes_in_flight`` — the unplug's loss, not the reader's. A pty has no baud rate: the stream is
not paced by the configured baud.
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
        self.accepted = 0  # bytes handed to write() while plugged, since the start
        self.overruns: list[list[int]] = []  # [first, last host ns, bytes] of each overrun episode
        self.stats = {
            "bytes_written": 0,
            "bytes_overrun": 0,
            "bytes_unplugged": 0,
            "bytes_in_flight": 0,
            "plugs": 0,
            "unplugs": 0,
        }

    @property
    def plugged(self) -> bool:
        return self.master is not None

    def plug(self) -> str:
        """Open a new pty and point the link at it; returns the slave's path."""
        if self.plugged:
            assert self.slave_path is not None  # opened with the pty
            return self.slave_path
        master, slave = os.openpty()
        tty.setraw(slave)
        os.set_blocking(master, False)
        os.set_blocking(slave, False)  # (our own descriptor: read only to count what is unplugged)
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

    def unplug(self) -> int:
        """Remove the link and close the pty (both sides): the device is unplugged. Returns the
        bytes in flight it loses (the last of those written), counted in ``bytes_in_flight``."""
        if not self.plugged:
            return 0
        lost = sum(len(chunk) for _, chunk in self._backlog) + self._unread()
        self._release()
        self.stats["unplugs"] += 1
        self.stats["bytes_in_flight"] += lost
        return lost

    def _unread(self) -> int:
        """Bytes waiting in the pty that no reader took: taken here, as the close would drop them."""
        slave = self.slave
        assert slave is not None  # plugged
        n = 0
        while True:
            try:
                data = os.read(slave, 65536)
            except OSError:  # BlockingIOError: nothing more
                return n
            if not data:
                return n
            n += len(data)

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
            assert fd is not None  # plugged: both sides open
            try:
                os.close(fd)
            except OSError:
                pass
        self.master = self.slave = self.slave_path = None
        self._backlog.clear()

    def _overrun(self, now_ns: int, n: int) -> None:
        """Count dropped bytes; drops less than 0.1 s apart are one episode (the first 100 kept)."""
        self.stats["bytes_overrun"] += n
        last = self.overruns[-1] if self.overruns else None
        if last is not None and now_ns - last[1] < 100_000_000:
            last[1], last[2] = now_ns, last[2] + n
        elif len(self.overruns) < 100:
            self.overruns.append([now_ns, now_ns, n])

    def write(self, data: bytes, now_ns: int | None = None) -> None:
        if not self.plugged:
            self.stats["bytes_unplugged"] += len(data)
            return
        self.accepted += len(data)
        now = time.monotonic_ns() if now_ns is None else now_ns
        backlog = self._backlog
        if data:
            backlog.append((now + self.backlog_ns, data))
        self._send()
        # refused again, and older than the transmit FIFO holds: lost (tried first, so that the
        # emulator's own delay between writes does not drop what the reader has made room for)
        while backlog and backlog[0][0] < now:
            self._overrun(now, len(backlog.popleft()[1]))

    def _send(self) -> None:
        """Write the backlog, oldest first, as far as the pty takes it."""
        backlog, master = self._backlog, self.master
        assert master is not None  # plugged
        while backlog:
            deadline, chunk = backlog[0]
            try:
                n = os.write(master, chunk)
            except OSError:  # full (BlockingIOError), or the pty gone under us: kept, then overrun
                n = 0
            self.stats["bytes_written"] += n
            if n < len(chunk):
                backlog[0] = (deadline, chunk[n:])
                return
            backlog.popleft()
