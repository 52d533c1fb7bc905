"""The ``udp`` transport: datagrams on a UDP port (optionally a multicast group), one chunk each.

A large ``SO_RCVBUF`` (asked ``rcvbuf_bytes``, granted ``rcvbuf_bytes_granted``); optional
multicast ``group`` joined on ``interface``; when the consumer lags, datagrams are dropped and
counted (``stats``). For high datagram rates see :mod:`drivers.transport.udp_batch`.
"""

from __future__ import annotations

import asyncio
import socket
import struct
import time

from drivers.transport.base import Transport


class UdpTransport(Transport):
    """Datagrams on a UDP port (optionally a multicast group), one chunk per datagram."""

    kind = "udp"

    def __init__(
        self,
        port: int,
        host: str = "0.0.0.0",
        group: str | None = None,
        interface: str = "0.0.0.0",
        rcvbuf_bytes: int = 8 * 1024 * 1024,
        name: str | None = None,
        **kwargs,
    ) -> None:
        super().__init__(name or f"udp:{port}", **kwargs)
        self.host, self.port, self.group, self.interface = host, port, group, interface
        self.rcvbuf_bytes = rcvbuf_bytes
        self.rcvbuf_bytes_granted = 0
        self._transport: asyncio.DatagramTransport | None = None

    def describe(self) -> str:
        where = f"{self.group} on {self.interface}" if self.group else self.host
        return f"udp {where}:{self.port} (SO_RCVBUF {self.rcvbuf_bytes_granted} bytes)"

    async def _connect(self) -> None:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, self.rcvbuf_bytes)
            self.rcvbuf_bytes_granted = sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)
            if self.group:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                sock.bind(("", self.port))
                mreq = struct.pack("4s4s", socket.inet_aton(self.group), socket.inet_aton(self.interface))
                sock.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, mreq)
            else:
                sock.bind((self.host, self.port))
            self.port = sock.getsockname()[1]
        except OSError:
            sock.close()
            raise
        owner = self

        class _Proto(asyncio.DatagramProtocol):
            def datagram_received(self, data, addr):
                host_ns = time.monotonic_ns()
                if len(owner._chunks) >= owner.max_chunks:
                    owner.stats.events["dropped_datagrams"] += 1
                    return
                owner._push(data, host_ns)

            def error_received(self, exc):
                owner.stats.events["socket_errors"] += 1

        self._transport, _ = await self._loop.create_datagram_endpoint(_Proto, sock=sock)

    async def _disconnect(self) -> None:
        if self._transport is not None:
            self._transport.close()
            self._transport = None
