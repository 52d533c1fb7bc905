"""Async byte transports: what every transport shares — :class:`Transport`, :class:`Chunk`,
:class:`TransportEvent`.

Every transport yields :class:`Chunk` ``(data, host_ns)`` tuples, ``host_ns`` being
``time.monotonic_ns()`` taken when the bytes were seen ready (before the read: by the event loop,
or by the serial port's reader thread), and is used the same way (aiomqtt style)::

    async with create_transport({"kind": "serial", "port": "/run/mls/ins", "baudrate": 115200}) as t:
        async for data, host_ns in t:
            records = decoder.feed(data, host_ns)

(:func:`drivers.transport.registry.create_transport` builds one from a config.) A subclass
implements ``_connect`` / ``_disconnect``; the base class queues the chunks, and when the device
goes away (``_lost``) reports it and reconnects in the background with a back-off
(``reconnect_min_s`` doubling to ``reconnect_max_s``; a subclass may wait for its device to
appear instead, ``_wait_retry``: the serial port watches its path).

State changes are reported as :class:`TransportEvent` to the ``on_event`` callback and kept in
``transport.events``; ``transport.connected`` and ``transport.reconnects`` give the state, and
``transport.last_error`` why it is not connected: the OS error of the last failed open (``[Errno 2]
... No such file or directory: '/dev/ttyUSB9'``, ``[Errno 98] Address already in use``) or the
reason the device went away, None while connected.
"""

from __future__ import annotations

import asyncio
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import ClassVar, NamedTuple

from drivers.base import DecoderStats


class Chunk(NamedTuple):
    data: bytes
    host_ns: int


@dataclass(frozen=True, slots=True)
class TransportEvent:
    transport: str  # the transport's name
    kind: str  # 'connected' | 'disconnected' | 'reconnect_failed'
    detail: str
    host_ns: int


class Transport:
    """Base class (python-can ``BusABC`` style): subclasses implement ``_connect``/``_disconnect``."""

    kind: ClassVar[str] = ""

    def __init__(
        self,
        name: str | None = None,
        on_event: Callable[[TransportEvent], None] | None = None,
        max_chunks: int = 1024,
        reconnect_min_s: float = 0.1,
        reconnect_max_s: float = 5.0,
    ) -> None:
        self.name = name or self.kind
        self.on_event = on_event
        self.max_chunks = max_chunks
        self.reconnect_min_s = reconnect_min_s
        self.reconnect_max_s = reconnect_max_s
        self.stats = DecoderStats()
        self.events: deque[TransportEvent] = deque(maxlen=100)
        self.connected = False
        self.reconnects = 0
        self.last_error: str | None = None  # why not connected (None while connected)
        self._chunks: deque[Chunk] = deque()
        self._ready = asyncio.Event()  # replaced by open(), bound to its loop
        self._closing = False
        self._reconnect_task: asyncio.Task | None = None
        self._loop: asyncio.AbstractEventLoop  # set by open(): subclasses use it once connected

    # -- lifecycle -----------------------------------------------------------------------------
    async def open(self) -> None:
        """Connect; if the device is not there yet, report it and keep trying in the background."""
        self._loop = asyncio.get_running_loop()
        self._ready = asyncio.Event()
        self._closing = False
        try:
            await self._connect()
        except OSError as exc:
            self.last_error = str(exc)
            self._report("disconnected", f"cannot open: {exc}")
            self._schedule_reconnect()
            return
        self._set_connected(first=True)

    async def close(self) -> None:
        self._closing = True
        if self._reconnect_task is not None:
            self._reconnect_task.cancel()
            try:
                await self._reconnect_task
            except (asyncio.CancelledError, Exception):
                pass
            self._reconnect_task = None
        await self._disconnect()
        self.connected = False
        self._ready.set()

    async def __aenter__(self):
        await self.open()
        return self

    async def __aexit__(self, *exc) -> None:
        await self.close()

    # -- reading -------------------------------------------------------------------------------
    async def read(self) -> Chunk:
        """The next chunk; raises EOFError once the transport is closed and drained."""
        await self._wait_chunks()
        chunk = self._chunks.popleft()
        if len(self._chunks) < self.max_chunks // 2:
            self._resume()
        return chunk

    async def read_batch(self, max_chunks: int = 4096) -> list[Chunk]:
        """Every chunk waiting (at most ``max_chunks``, at least one): a high-rate consumer takes
        a burst in one await. Raises EOFError once the transport is closed and drained."""
        await self._wait_chunks()
        chunks = self._chunks
        if len(chunks) <= max_chunks:
            out = list(chunks)
            chunks.clear()
        else:
            out = [chunks.popleft() for _ in range(max_chunks)]
        if len(chunks) < self.max_chunks // 2:
            self._resume()
        return out

    async def _wait_chunks(self) -> None:
        while not self._chunks:
            if self._closing:
                raise EOFError(f"transport {self.name} closed")
            self._ready.clear()
            await self._ready.wait()

    def __aiter__(self):
        return self._iter()

    async def _iter(self):
        while True:
            try:
                yield await self.read()
            except EOFError:
                return

    def _push(self, data: bytes, host_ns: int) -> bool:
        """Queue a chunk; returns False when the queue is full (caller pauses or drops)."""
        self._chunks.append(Chunk(data, host_ns))
        self.stats.bytes_in += len(data)
        self.stats.records += 1
        self._ready.set()
        return len(self._chunks) < self.max_chunks

    def _resume(self) -> None:  # override where reading can be paused
        pass

    # -- connection state ----------------------------------------------------------------------
    def _report(self, kind: str, detail: str) -> None:
        event = TransportEvent(self.name, kind, detail, time.monotonic_ns())
        self.events.append(event)
        if self.on_event is not None:
            self.on_event(event)

    def _set_connected(self, first: bool = False) -> None:
        self.connected = True
        self.last_error = None
        if not first:
            self.reconnects += 1
        self._report("connected", self.describe())

    def _lost(self, reason: str) -> None:
        """The device went away: report, release, and reconnect in the background."""
        if not self.connected or self._closing:
            return
        self.connected = False
        self.last_error = reason
        self._report("disconnected", reason)
        self._loop.create_task(self._disconnect())
        self._schedule_reconnect()

    def _schedule_reconnect(self) -> None:
        if self._closing or (self._reconnect_task is not None and not self._reconnect_task.done()):
            return
        self._reconnect_task = self._loop.create_task(self._reconnect())

    async def _reconnect(self) -> None:
        delay = self.reconnect_min_s
        failures = 0
        while not self._closing:
            appeared = await self._wait_retry(delay)
            try:
                await self._connect()
            except OSError as exc:
                self.last_error = str(exc)
                failures += 1
                if failures in (1, 10) or failures % 100 == 0:
                    self._report("reconnect_failed", f"attempt {failures}: {exc}")
                delay = self.reconnect_min_s if appeared else min(delay * 2.0, self.reconnect_max_s)
                continue
            self._set_connected()
            return

    async def _wait_retry(self, delay_s: float) -> bool:
        """Wait before the next attempt to connect; True when the device has just appeared (the
        back-off then starts over). Here: sleep ``delay_s``; the serial port waits for its path."""
        await asyncio.sleep(delay_s)
        return False

    def describe(self) -> str:
        return self.kind

    async def _connect(self) -> None:
        raise NotImplementedError

    async def _disconnect(self) -> None:
        raise NotImplementedError
