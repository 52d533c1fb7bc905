"""A UDP transport for high datagram rates (the profiler: ~4600 datagrams/s at the full Z+F rate),
filed in the drivers' transport registry as ``udp-batch``.

asyncio's datagram transport reads one datagram per event-loop iteration, so every datagram
costs a wake-up of the loop (an ``epoll_wait``, the callbacks, a task step) — most of the
daemon's CPU at the full Z+F rate. This transport instead:

- stamps each datagram with the **kernel's** receive time (``SO_TIMESTAMPNS``, moved from
  ``CLOCK_REALTIME`` to ``CLOCK_MONOTONIC`` with the offset sampled at each read), so a stamp
  does not depend on when the loop gets to the socket (the kernel switches stamping on a few
  milliseconds after the first socket asks; datagrams before that carry their read time);
- drains every datagram waiting (``recvmsg`` until ``EAGAIN``, at most ``burst`` per round),
  then stops watching the socket for ``coalesce_s`` (5 ms): at most ~200 loop wake-ups per
  second, whatever the rate, while the socket buffer holds what arrives meanwhile. The buffer
  asked is 32 MiB (``SO_RCVBUFFORCE`` when the process may, else ``SO_RCVBUF``, which the
  kernel caps at twice ``net.core.rmem_max``: raise that sysctl on the vessel PC, e.g. to
  33554432): ~14 000 full ZFP1 datagrams, 3 s at the full Z+F rate, to ride out a stall of the
  daemon (another process hogging the CPU, a slow disk).

When ``max_chunks`` datagrams wait for the consumer, reading pauses (they wait in the socket
buffer; the kernel drops what overflows it, counted in ``/proc/net/udp``) until the consumer has
taken half of them. Truncated datagrams are counted (``rejected['truncated']``).
:mod:`drivers.transport` imports this module, so ``create_transport({"kind": "udp-batch", ...})``
works wherever the transports do.
"""

from __future__ import annotations

import socket
import struct
import time

from drivers.timing import realtime_minus_monotonic_ns
from drivers.transport import Transport, register_transport

_TIMESPEC = struct.Struct("@qq")
_SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)  # Linux values where Python lacks the name
_SO_RCVBUFFORCE = getattr(socket, "SO_RCVBUFFORCE", 33)
_SCM_TIMESTAMPNS = _SO_TIMESTAMPNS
MAX_DATAGRAM = 65535


@register_transport("udp-batch")
class BatchUdpTransport(Transport):
    def __init__(self, port: int, host: str = "0.0.0.0", rcvbuf_bytes: int = 32 * 1024 * 1024,
                 coalesce_s: float = 0.005, burst: int = 4096, name: str | None = None, **kwargs) -> None:  # fmt: skip
        kwargs.setdefault("max_chunks", 16384)
        super().__init__(name or f"udp:{port}", **kwargs)
        self.host, self.port = host, port
        self.rcvbuf_bytes = rcvbuf_bytes
        self.rcvbuf_bytes_granted = 0
        self.coalesce_s = coalesce_s
        self.burst = burst
        self.kernel_stamps = False
        self._sock: socket.socket | None = None
        self._timer = None
        self._paused = False

    def describe(self) -> str:
        return (f"udp {self.host}:{self.port} (SO_RCVBUF {self.rcvbuf_bytes_granted} bytes, "
                f"{'kernel' if self.kernel_stamps else 'loop'} receive stamps)")  # fmt: skip

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
        self._loop.add_reader(sock.fileno(), self._on_readable)

    async def _disconnect(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        sock, self._sock = self._sock, None
        if sock is not None:
            try:
                self._loop.remove_reader(sock.fileno())
            except (ValueError, OSError):
                pass
            sock.close()

    def _on_readable(self) -> None:
        sock = self._sock
        if sock is None:
            return
        mono = time.monotonic_ns()
        offset = realtime_minus_monotonic_ns()
        recvmsg, chunks, stats = sock.recvmsg, self._chunks, self.stats
        anc_size = socket.CMSG_SPACE(_TIMESPEC.size)
        got = 0
        for _ in range(min(self.burst, self.max_chunks - len(chunks))):
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
                    host_ns = sec * 1_000_000_000 + nsec - offset
            if flags & socket.MSG_TRUNC:
                stats.rejected["truncated"] += 1
                continue
            self._push(data, host_ns)
            got += 1
        if got and self.coalesce_s > 0:  # let the next datagrams gather in the socket buffer
            self._loop.remove_reader(sock.fileno())
            self._timer = self._loop.call_later(self.coalesce_s, self._rearm)
        elif len(chunks) >= self.max_chunks:  # the consumer lags: leave them in the kernel's
            self._loop.remove_reader(sock.fileno())  # buffer until it has caught up
            self._paused = True

    def _resume(self) -> None:
        if self._paused and self._sock is not None and self._timer is None:
            self._paused = False
            self._loop.add_reader(self._sock.fileno(), self._on_readable)

    def _rearm(self) -> None:
        self._timer = None
        if self._sock is not None:
            self._loop.add_reader(self._sock.fileno(), self._on_readable)
