"""Async byte transports: serial, UDP, TCP — they move bytes and stamp the host receive time.

Every transport yields :class:`Chunk` ``(data, host_ns)`` tuples, ``host_ns`` being
``time.monotonic_ns()`` taken when the bytes were seen ready (before the read: by the event loop,
or by the serial port's reader thread), and is used the same way (aiomqtt style)::

    async with create_transport({"kind": "serial", "port": "/run/mls/ins", "baudrate": 115200}) as t:
        async for data, host_ns in t:
            records = decoder.feed(data, host_ns)

The registry (:data:`TRANSPORTS`, :func:`register_transport`, :func:`create_transport`) is keyed
by the config's ``kind``, after python-can's interface registry; a new transport is one class
with ``@register_transport("name")``.

- ``serial`` (:class:`SerialTransport`): pyserial opens and configures the port; a thread of its
  own reads it (:class:`_PortReader`: ``poll`` and ``os.read``, the GIL released while it waits)
  and stamps the bytes when they are ready, so a busy event loop delays their decoding but
  neither their stamp nor their reading (a pty or UART buffers only a few kB). When the port
  vanishes (EIO/EOF: a USB adapter unplugged, an emulator's pty closed) the transport reports
  ``disconnected``, backs off (``reconnect_min_s`` doubling to ``reconnect_max_s``, 0.5 s for
  a serial port: trying to open a missing path costs nothing, and every second waited after
  the INS is back is a second of navigation lost) and reopens the same path — a stable symlink
  such as ``/dev/serial/by-id/...`` or an emulator's ``<run dir>/ins`` then reaches the new
  device — and reports ``connected``. A slow consumer pauses reading (the kernel buffers)
  instead of losing bytes.
- ``udp`` (:class:`UdpTransport`): one datagram per chunk; a large ``SO_RCVBUF`` (asked
  ``rcvbuf_bytes``, granted ``rcvbuf_bytes_granted``); optional multicast ``group`` joined on
  ``interface``; when the consumer lags, datagrams are dropped and counted (``stats``).
- ``tcp`` (:class:`TcpTransport`): a client that reconnects with the same back-off.
- ``udp-batch`` (:mod:`drivers.transport.udp_batch`): UDP for high datagram rates (the profiler at the
  full Z+F rate): kernel receive stamps, every waiting datagram drained per wake-up.

State changes are reported as :class:`TransportEvent` to the ``on_event`` callback and kept in
``transport.events``; ``transport.connected`` and ``transport.reconnects`` give the state.
"""

from __future__ import annotations

import asyncio
import os
import select
import socket
import struct
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, ClassVar, NamedTuple

from drivers.base import DecoderStats, DriverError, Registry


class Chunk(NamedTuple):
    data: bytes
    host_ns: int


@dataclass(frozen=True, slots=True)
class TransportEvent:
    transport: str  # the transport's name
    kind: str  # 'connected' | 'disconnected' | 'reconnect_failed'
    detail: str
    host_ns: int


TRANSPORTS = Registry("transport")
register_transport = TRANSPORTS.register


def create_transport(config: dict[str, Any], on_event: Callable[[TransportEvent], None] | None = None) -> Transport:
    """A config mapping with ``kind`` and that transport's keyword arguments → a transport."""
    return TRANSPORTS.create(config, on_event=on_event)


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
        self._chunks: deque[Chunk] = deque()
        self._ready: asyncio.Event | None = None
        self._closing = False
        self._reconnect_task: asyncio.Task | None = None
        self._loop: asyncio.AbstractEventLoop | None = None

    # -- lifecycle -----------------------------------------------------------------------------
    async def open(self) -> None:
        """Connect; if the device is not there yet, report it and keep trying in the background."""
        self._loop = asyncio.get_running_loop()
        self._ready = asyncio.Event()
        self._closing = False
        try:
            await self._connect()
        except OSError as exc:
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
        if self._ready is not None:
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
        if not first:
            self.reconnects += 1
        self._report("connected", self.describe())

    def _lost(self, reason: str) -> None:
        """The device went away: report, release, and reconnect in the background."""
        if not self.connected or self._closing:
            return
        self.connected = False
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
            await asyncio.sleep(delay)
            try:
                await self._connect()
            except OSError as exc:
                failures += 1
                if failures in (1, 10) or failures % 100 == 0:
                    self._report("reconnect_failed", f"attempt {failures}: {exc}")
                delay = min(delay * 2.0, self.reconnect_max_s)
                continue
            self._set_connected()
            return

    def describe(self) -> str:
        return self.kind

    async def _connect(self) -> None:
        raise NotImplementedError

    async def _disconnect(self) -> None:
        raise NotImplementedError


class _PortReader:
    """The thread that reads one open serial fd: it waits in ``poll`` (the GIL released), stamps
    the host time as soon as the bytes are ready and hands them to the event loop. A busy loop
    (a burst of profiler datagrams, the log writer holding the GIL) then delays only the
    *decoding* of serial bytes, never their reading: a UART's or pty's kernel buffer holds a few
    kB, which at 100 kB/s is tens of milliseconds. At most ``max_waiting`` chunks wait for the
    consumer; beyond that the thread stops reading (the kernel buffers) until :meth:`resume`."""

    def __init__(self, fd: int, loop: asyncio.AbstractEventLoop, deliver: Callable[[Chunk | str], None],
                 waiting: Callable[[], int], max_waiting: int, name: str) -> None:  # fmt: skip
        self.fd, self.loop, self.deliver = fd, loop, deliver
        self.waiting, self.max_waiting = waiting, max_waiting
        self.incoming: deque[Chunk | str] = deque()  # appended here, taken in the loop (deque ops are atomic)
        self._wake_r, self._wake_w = os.pipe()
        self._room = threading.Event()
        self._room.set()
        self._stop = False
        self.thread = threading.Thread(target=self._run, name=f"mls-serial-{name}"[:15], daemon=True)
        self.thread.start()

    def _hand_over(self, item: Chunk | str) -> None:
        self.incoming.append(item)
        try:
            self.loop.call_soon_threadsafe(self._in_loop)
        except RuntimeError:  # the loop is closed: nobody reads any more
            self._stop = True

    def _in_loop(self) -> None:
        incoming, deliver = self.incoming, self.deliver
        while incoming:
            deliver(incoming.popleft())

    def _run(self) -> None:
        poller = select.poll()
        poller.register(self.fd, select.POLLIN | select.POLLPRI)
        poller.register(self._wake_r, select.POLLIN)
        while not self._stop:
            if self.waiting() + len(self.incoming) >= self.max_waiting:  # the consumer lags
                self._room.clear()
                if self.waiting() + len(self.incoming) >= self.max_waiting:
                    self._room.wait(0.05)
                continue
            try:
                ready = poller.poll()
            except InterruptedError:
                continue
            if self._stop:
                return
            host_ns = time.monotonic_ns()
            if not any(fd == self.fd for fd, _ in ready):
                continue
            try:
                data = os.read(self.fd, 65536)
            except BlockingIOError:
                continue
            except OSError as exc:
                self._hand_over(f"read failed: {exc.strerror or exc}")
                return
            if not data:
                self._hand_over("end of file (port closed by the other side)")
                return
            self._hand_over(Chunk(data, host_ns))

    def resume(self) -> None:
        self._room.set()

    def stop(self) -> None:
        """End the thread (it returns from ``poll`` at once) and wait for it."""
        self._stop = True
        self._room.set()
        os.write(self._wake_w, b"x")
        if self.thread is not threading.current_thread():
            self.thread.join(2.0)
        os.close(self._wake_r)
        os.close(self._wake_w)


@register_transport("serial")
class SerialTransport(Transport):
    """A serial port (or pty) read by a thread of its own; reopens the same path after a loss."""

    def __init__(
        self,
        port: str,
        baudrate: int = 115200,
        bytesize: int = 8,
        parity: str = "N",
        stopbits: float = 1,
        name: str | None = None,
        **kwargs,
    ) -> None:
        kwargs.setdefault("reconnect_max_s", 0.5)
        super().__init__(name or port, **kwargs)
        self.port = port
        self.settings = {"baudrate": baudrate, "bytesize": bytesize, "parity": parity, "stopbits": stopbits}
        self._serial = None
        self._reader: _PortReader | None = None

    def describe(self) -> str:
        s = self.settings
        return f"serial {self.port} {s['baudrate']} {s['bytesize']}{s['parity']}{s['stopbits']}"

    async def _connect(self) -> None:
        import serial  # pyserial

        try:
            ser = serial.Serial(self.port, timeout=0, exclusive=True, **self.settings)
        except serial.SerialException as exc:
            raise OSError(str(exc)) from exc
        except ValueError as exc:  # a bad setting is a configuration error, not a missing device
            raise DriverError(f"serial {self.port}: {exc}") from exc
        os.set_blocking(ser.fileno(), False)
        self._serial = ser
        reader: _PortReader | None = None

        def deliver(item: Chunk | str) -> None:
            if self._reader is not reader:
                return  # from a reader already stopped (a loss raced the thread's last read)
            if isinstance(item, str):
                self._lost(item)
            else:
                self._push(item.data, item.host_ns)

        reader = self._reader = _PortReader(ser.fileno(), self._loop, deliver, self._chunks.__len__,
                                            self.max_chunks, self.name)  # fmt: skip

    async def _disconnect(self) -> None:
        ser, reader = self._serial, self._reader
        self._serial = self._reader = None
        if reader is not None:
            reader.stop()
        if ser is not None:
            try:
                ser.close()
            except Exception:  # the device is gone; closing it can fail, that is fine
                pass

    def _resume(self) -> None:
        if self._reader is not None:
            self._reader.resume()


@register_transport("udp")
class UdpTransport(Transport):
    """Datagrams on a UDP port (optionally a multicast group), one chunk per datagram."""

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
        self._transport = None

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


@register_transport("tcp")
class TcpTransport(Transport):
    """A TCP client (e.g. an INS Ethernet output); reconnects after the peer goes away."""

    def __init__(self, host: str, port: int, name: str | None = None, **kwargs) -> None:
        super().__init__(name or f"tcp:{host}:{port}", **kwargs)
        self.host, self.port = host, port
        self._writer = None
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


from drivers.transport import udp_batch as udpbatch  # noqa: E402,F401  (files the udp-batch transport; it imports this module)
