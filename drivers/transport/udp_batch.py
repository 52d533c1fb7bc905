"""A UDP transport for high datagram rates (the profiler: ~4600 datagrams/s at the full Z+F rate),
filed in the drivers' transport table (:mod:`drivers.transport.registry`) as ``udp-batch``.

asyncio's datagram transport reads one datagram per event-loop iteration, so every datagram
costs a wake-up of the loop (an ``epoll_wait``, the callbacks, a task step) — most of the
daemon's CPU at the full Z+F rate. This transport instead:

- stamps each datagram with the **kernel's** receive time (``SO_TIMESTAMPNS``, moved from
  ``CLOCK_REALTIME`` to ``CLOCK_MONOTONIC`` with the offset sampled at each read, through
  :class:`drivers.timing.RealtimeStamps`: a step of the realtime clock between a datagram's
  arrival and its read does not shift its stamp), so a stamp does not depend on when the loop
  gets to the socket (the kernel switches stamping on a few milliseconds after the first socket
  asks; datagrams before that carry their read time);
- drains every datagram waiting (``recvmmsg``, 64 datagrams per system call, through
  :mod:`drivers.transport.recvmmsg`; one ``recvmsg`` each where the C library lacks it; until
  ``EAGAIN``, at most ``burst`` per round),
  then stops watching the socket and polls it again after ``coalesce_s`` (5 ms): at most ~200
  loop wake-ups per second, whatever the rate, while the socket buffer holds what arrives
  meanwhile; only a poll that finds nothing goes back to watching the socket. The buffer
  asked is 32 MiB (``SO_RCVBUFFORCE`` when the process may, else ``SO_RCVBUF``, which the
  kernel caps at twice ``net.core.rmem_max``: raise that sysctl on the vessel PC, e.g. to
  33554432): ~14 000 full ZFP1 datagrams, 3 s at the full Z+F rate, to ride out a stall of the
  daemon (another process hogging the CPU, a slow disk).

When ``max_chunks`` datagrams wait for the consumer, reading pauses (they wait in the socket
buffer; the kernel drops what overflows it, counted in ``/proc/net/udp``) until the consumer has
taken half of them. Truncated datagrams are counted (``rejected['truncated']``).
"""

from __future__ import annotations

import asyncio
import socket
import struct
import time
from typing import TYPE_CHECKING

from drivers.timing import RealtimeStamps
from drivers.transport import recvmmsg
from drivers.transport.base import Transport

if TYPE_CHECKING:
    from drivers.timing import HostClock

_TIMESPEC = struct.Struct("@qq")
_SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)  # Linux values where Python lacks the name
_SO_RCVBUFFORCE = getattr(socket, "SO_RCVBUFFORCE", 33)
_SCM_TIMESTAMPNS = _SO_TIMESTAMPNS
_MSG_TRUNC = int(socket.MSG_TRUNC)  # a plain int: the IntFlag's & costs a microsecond
MAX_DATAGRAM = 65535


class BatchUdpTransport(Transport):
    kind = "udp-batch"

    def __init__(
        self,
        port: int,
        host: str = "0.0.0.0",
        rcvbuf_bytes: int = 32 * 1024 * 1024,
        coalesce_s: float = 0.005,
        burst: int = 4096,
        name: str | None = None,
        use_recvmmsg: bool = True,
        host_clock: HostClock | None = None,
        **kwargs,
    ) -> None:
        kwargs.setdefault("max_chunks", 16384)
        super().__init__(name or f"udp:{port}", **kwargs)
        self.host, self.port = host, port
        self.rcvbuf_bytes = rcvbuf_bytes
        self.rcvbuf_bytes_granted = 0
        self.coalesce_s = coalesce_s
        self.burst = burst
        self.kernel_stamps = False
        self.use_recvmmsg = use_recvmmsg and recvmmsg.available()
        self._sock: socket.socket | None = None
        self._mmsg: recvmmsg.MmsgReceiver | None = None
        self._timer: asyncio.TimerHandle | None = None
        self._paused = False
        self._watching = False  # the socket is registered with the loop's selector
        # the kernel's realtime stamps moved to monotonic time through ``host_clock`` (the real
        # clock by default; the simulated devices' fake one where it is handed over)
        self.stamps = RealtimeStamps() if host_clock is None else RealtimeStamps(clock=host_clock)

    def describe(self) -> str:
        return (
            f"udp {self.host}:{self.port} (SO_RCVBUF {self.rcvbuf_bytes_granted} bytes, "
            f"{'kernel' if self.kernel_stamps else 'loop'} receive stamps)"
        )

    async def _connect(self) -> None:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            try:  # beyond net.core.rmem_max: needs CAP_NET_ADMIN, else the capped size
                sock.setsockopt(socket.SOL_SOCKET, _SO_RCVBUFFORCE, self.rcvbuf_bytes)
            except OSError:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, self.rcvbuf_bytes)
            self.rcvbuf_bytes_granted = sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)
            try:
                sock.setsockopt(socket.SOL_SOCKET, _SO_TIMESTAMPNS, 1)
                self.kernel_stamps = True
            except OSError:
                self.kernel_stamps = False
            sock.bind((self.host, self.port))
            sock.setblocking(False)
            self.port = sock.getsockname()[1]
        except OSError:
            sock.close()
            raise
        self._sock = sock
        if self.use_recvmmsg:
            self._mmsg = recvmmsg.MmsgReceiver(sock)
        self._watching = False
        self._watch(True)

    async def _disconnect(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        if self._sock is not None:
            try:
                self._watch(False)
            except (ValueError, OSError):
                pass
            self._sock.close()
            self._sock = None

    def _on_readable(self) -> None:
        sock = self._sock
        if sock is None:
            return
        mono = time.monotonic_ns()
        offset = self.stamps.begin()
        chunks = self._chunks
        room = min(self.burst, self.max_chunks - len(chunks))
        mmsg = self._mmsg
        got = (
            self._read_many(mmsg, room, mono, offset)
            if mmsg is not None
            else self._read_each(sock, room, mono, offset)
        )
        if got and self.coalesce_s > 0:  # let the next datagrams gather in the socket buffer:
            self._watch(False)  # while they flow, a timer polls (no epoll_ctl per round)
            self._timer = self._loop.call_later(self.coalesce_s, self._poll)
        elif len(chunks) >= self.max_chunks:  # the consumer lags: leave them in the kernel's
            self._watch(False)  # buffer until it has caught up
            self._paused = True
        else:  # nothing came: sleep until the socket is readable
            self._watch(True)

    def _watch(self, on: bool) -> None:
        if on != self._watching and self._sock is not None:
            if on:
                self._loop.add_reader(self._sock.fileno(), self._on_readable)
            else:
                self._loop.remove_reader(self._sock.fileno())
            self._watching = on

    def _read_many(self, mmsg: recvmmsg.MmsgReceiver, room: int, mono: int, offset: int) -> int:
        push, stats, conv = self._push, self.stats, self.stamps
        got = 0
        while got < room:
            want = min(mmsg.slots, room - got)
            try:
                datagrams, stamps, truncated = mmsg.receive(want)
            except BlockingIOError:
                break
            except OSError:
                stats.events["socket_errors"] += 1
                break
            if truncated:
                stats.rejected["truncated"] += truncated
            if conv.exact:
                for data, t in zip(datagrams, stamps, strict=True):  # (one stamp per datagram)
                    push(data, mono if t is None else t - offset)
                if stamps and stamps[-1] is not None:
                    conv.last_ns = stamps[-1] - offset
            else:  # the realtime clock stepped: stamps on either side of the step
                for data, t in zip(datagrams, stamps, strict=True):  # (one stamp per datagram)
                    push(data, mono if t is None else conv.convert(t, mono))
            k = len(datagrams) + truncated
            got += k
            if k < want:
                break  # the socket is empty
        return got

    def _read_each(self, sock: socket.socket, room: int, mono: int, offset: int) -> int:
        recvmsg, stats, conv = sock.recvmsg, self.stats, self.stamps
        anc_size = socket.CMSG_SPACE(_TIMESPEC.size)
        got = 0
        for _ in range(room):
            try:
                data, anc, flags, _addr = recvmsg(MAX_DATAGRAM, anc_size)
            except BlockingIOError:
                break
            except OSError:
                stats.events["socket_errors"] += 1
                break
            host_ns = mono
            for level, kind, value in anc:
                if level == socket.SOL_SOCKET and kind == _SCM_TIMESTAMPNS and len(value) >= 16:
                    sec, nsec = _TIMESPEC.unpack_from(value)
                    t = sec * 1_000_000_000 + nsec
                    if conv.exact:
                        host_ns = conv.last_ns = t - offset
                    else:
                        host_ns = conv.convert(t, mono)
            if flags & _MSG_TRUNC:
                stats.rejected["truncated"] += 1
                continue
            self._push(data, host_ns)
            got += 1
        return got

    def _resume(self) -> None:
        if self._paused and self._sock is not None and self._timer is None:
            self._paused = False
            self._watch(True)

    def _poll(self) -> None:
        self._timer = None
        if self._sock is not None and not self._paused:
            self._on_readable()
