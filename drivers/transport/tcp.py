"""The ``tcp`` transport: a TCP client (e.g. an INS Ethernet output) that reconnects with the
same back-off after the peer goes away; a slow consumer stops its reading (TCP pushes back)."""

from __future__ import annotations

import asyncio
import time

from drivers.transport.base import Transport


class TcpTransport(Transport):
    """A TCP client (e.g. an INS Ethernet output); reconnects after the peer goes away."""

    kind = "tcp"

    def __init__(self, host: str, port: int, name: str | None = None, **kwargs) -> None:
        super().__init__(name or f"tcp:{host}:{port}", **kwargs)
        self.host, self.port = host, port
        self._writer: asyncio.StreamWriter | None = None
        self._task: asyncio.Task | None = None
        self._drained = asyncio.Event()

    def describe(self) -> str:
        return f"tcp {self.host}:{self.port}"

    def _resume(self) -> None:
        self._drained.set()

    async def _connect(self) -> None:
        reader, self._writer = await asyncio.open_connection(self.host, self.port)
        self._task = self._loop.create_task(self._pump(reader))

    async def _pump(self, reader: asyncio.StreamReader) -> None:
        while True:
            try:
                data = await reader.read(65536)
            except (ConnectionError, OSError) as exc:
                self._lost(f"read failed: {exc}")
                return
            host_ns = time.monotonic_ns()
            if not data:
                self._lost("connection closed by the peer")
                return
            if not self._push(data, host_ns):  # slow consumer: stop reading, TCP pushes back
                self._drained.clear()
                await self._drained.wait()

    async def _disconnect(self) -> None:
        task, writer = self._task, self._writer
        self._task = self._writer = None
        if task is not None and task is not asyncio.current_task():
            task.cancel()
        if writer is not None:
            writer.close()
            try:
                await writer.wait_closed()
            except (ConnectionError, OSError):
                pass
