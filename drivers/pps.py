"""PPS sources and the labelling of pulses with GPS seconds (docs/architecture.md §5).

Records: a :class:`PpsEdge` is one pulse as the host saw it — ``host_ns`` on the host's
``CLOCK_MONOTONIC`` (the time base of every transport stamp), ``source`` (the source's name),
``sequence`` (the source's pulse counter) and, once labelled, ``gps_s`` (the whole GPS second
the pulse marks). ``realtime_ns`` keeps the raw ``CLOCK_REALTIME`` stamp of a kernel pulse.

Labelling (:class:`PpsLabeler`, gpsd's rule): a pulse is labelled with GPS second S only when a
time message for S — a sentence/frame whose time tag lies in [S, S+1) — arrives within 1.1 s
after the pulse; the latest pending pulse before the message takes the label. Pulses that never
get a label within 1.1 s, duplicate pulses (same sequence again, or a second pulse less than
``min_interval_ns`` after the previous one) and second labels for one GPS second are dropped and
counted (``stats.events``: ``unlabelled``, ``duplicate_edge``, ``duplicate_label``,
``time_without_edge``, ``non_monotonic``).

Sources — one small async interface (:class:`PpsSource`: ``async with source:`` then
``async for edge in source``), a registry keyed by the config's ``kind``
(:func:`create_pps_source`):

- ``kernel``: ``/dev/ppsN`` through the RFC 2783 ``PPS_FETCH`` ioctl, in a thread (blocking call
  with a timeout). The kernel stamps are CLOCK_REALTIME; they are moved to CLOCK_MONOTONIC with
  the realtime − monotonic offset sampled right after each fetch.
- ``serial-line``: the DCD line of a serial port through ``TIOCMIWAIT`` in a thread; a rising
  DCD is a pulse, stamped with CLOCK_MONOTONIC as the ioctl returns.
- ``udp``: datagrams from an emulator (:func:`encode_pps_datagram`), each carrying the edge's
  own host monotonic stamp. Format (little-endian, 20 bytes)::

      magic b'PPS1' | sequence u64 | host_monotonic_ns i64
"""

from __future__ import annotations

import asyncio
import errno
import fcntl
import os
import socket
import struct
import termios
import threading
import time
from collections.abc import AsyncIterator
from dataclasses import dataclass, replace

from drivers.base import DecoderStats, DriverError, Registry
from drivers.timing import realtime_minus_monotonic_ns

NS_PER_S = 1_000_000_000
LABEL_WINDOW_NS = 1_100_000_000

# ---------------------------------------------------------------------------------------------
# Records and labelling.
# ---------------------------------------------------------------------------------------------


@dataclass(slots=True, frozen=True)
class PpsEdge:
    host_ns: int  # CLOCK_MONOTONIC ns of the pulse
    source: str
    sequence: int
    gps_s: int | None = None  # the GPS second the pulse marks, once labelled
    realtime_ns: int | None = None  # raw CLOCK_REALTIME stamp (kernel source)


class PpsLabeler:
    """gpsd's rule for naming pulses (see the module docstring). Sans-I/O, never raises."""

    def __init__(self, window_ns: int = LABEL_WINDOW_NS, min_interval_ns: int = 500_000_000) -> None:
        self.window_ns = window_ns
        self.min_interval_ns = min_interval_ns
        self.stats = DecoderStats()
        self._pending: list[PpsEdge] = []
        self._last_edge: PpsEdge | None = None
        self._last_label: int | None = None
        self._seen: set[tuple[str, int]] = set()
        self._seen_order: list[tuple[str, int]] = []

    def add_edge(self, edge: PpsEdge) -> list[PpsEdge]:
        """Register a pulse; returns nothing (pulses are returned when labelled)."""
        key = (edge.source, edge.sequence)
        last = self._last_edge
        if key in self._seen or (
            last is not None
            and last.source == edge.source
            and 0 <= edge.host_ns - last.host_ns < self.min_interval_ns
        ):
            self.stats.events["duplicate_edge"] += 1
            return []
        self._seen.add(key)
        self._seen_order.append(key)
        if len(self._seen_order) > 64:
            self._seen.discard(self._seen_order.pop(0))
        self._expire(edge.host_ns)
        self._pending.append(edge)
        self._last_edge = edge
        return []

    def add_time(self, gps_s: int, host_ns: int) -> list[PpsEdge]:
        """A time message for GPS second ``gps_s`` received at ``host_ns`` → labelled pulse(s)."""
        self._expire(host_ns)
        gps_s = int(gps_s)
        candidates = [e for e in self._pending if 0 <= host_ns - e.host_ns <= self.window_ns]
        if not candidates:
            if self._last_label != gps_s:
                self.stats.events["time_without_edge"] += 1
            return []
        edge = max(candidates, key=lambda e: e.host_ns)
        if self._last_label is not None and gps_s <= self._last_label:
            self.stats.events["duplicate_label" if gps_s == self._last_label else "non_monotonic"] += 1
            return []
        older = sum(1 for e in self._pending if e.host_ns < edge.host_ns)
        if older:
            self.stats.events["unlabelled"] += older
        self._pending = [e for e in self._pending if e.host_ns > edge.host_ns]
        self._last_label = gps_s
        self.stats.records += 1
        return [replace(edge, gps_s=gps_s)]

    def _expire(self, now_ns: int) -> None:
        keep = [e for e in self._pending if now_ns - e.host_ns <= self.window_ns]
        if len(keep) != len(self._pending):
            self.stats.events["unlabelled"] += len(self._pending) - len(keep)
            self._pending = keep


# ---------------------------------------------------------------------------------------------
# UDP datagram format (emulators).
# ---------------------------------------------------------------------------------------------

PPS_MAGIC = b"PPS1"
_PPS_DATAGRAM = struct.Struct("<4sQq")
PPS_DATAGRAM_SIZE = _PPS_DATAGRAM.size


def encode_pps_datagram(sequence: int, host_ns: int) -> bytes:
    return _PPS_DATAGRAM.pack(PPS_MAGIC, sequence & 0xFFFFFFFFFFFFFFFF, host_ns)


def decode_pps_datagram(data: bytes, source: str = "udp") -> PpsEdge:
    """Raises :class:`DriverError` naming what is wrong with the datagram."""
    if len(data) != PPS_DATAGRAM_SIZE:
        raise DriverError(f"PPS datagram of {len(data)} bytes: expected {PPS_DATAGRAM_SIZE}")
    magic, seq, host_ns = _PPS_DATAGRAM.unpack(data)
    if magic != PPS_MAGIC:
        raise DriverError(f"PPS datagram magic {magic!r}: expected {PPS_MAGIC!r}")
    return PpsEdge(host_ns, source, seq)


# ---------------------------------------------------------------------------------------------
# RFC 2783 kernel PPS (Linux ABI of <linux/pps.h>, 64-bit).
# ---------------------------------------------------------------------------------------------

# struct pps_ktime { __s64 sec; __s32 nsec; __u32 flags; }                       16 bytes
# struct pps_kinfo { __u32 assert_sequence, clear_sequence; struct pps_ktime assert_tu,
#                    clear_tu; int current_mode; }                   44 bytes + 4 padding = 48
# struct pps_fdata { struct pps_kinfo info; struct pps_ktime timeout; }           64 bytes
PPS_KTIME = struct.Struct("=qiI")
PPS_FDATA = struct.Struct("=II16s16si4x16s")
PPS_TIME_INVALID = 1 << 0
# _IOWR('p', 0xa4, struct pps_fdata *): the size field is that of a pointer (8 on 64-bit).
PPS_FETCH = (3 << 30) | (8 << 16) | (ord("p") << 8) | 0xA4  # 0xC00870A4


@dataclass(frozen=True, slots=True)
class PpsFetch:
    assert_sequence: int
    clear_sequence: int
    assert_realtime_ns: int
    clear_realtime_ns: int
    current_mode: int


def pack_pps_fdata(timeout_s: float | None) -> bytearray:
    """The ``struct pps_fdata`` buffer for ``PPS_FETCH``; None waits forever."""
    if timeout_s is None:
        tmo = PPS_KTIME.pack(0, 0, PPS_TIME_INVALID)
    else:
        sec = int(timeout_s)
        tmo = PPS_KTIME.pack(sec, int(round((timeout_s - sec) * 1e9)), 0)
    return bytearray(PPS_FDATA.pack(0, 0, bytes(16), bytes(16), 0, tmo))


def unpack_pps_fdata(buf: bytes | bytearray) -> PpsFetch:
    a_seq, c_seq, a_tu, c_tu, mode, _tmo = PPS_FDATA.unpack(bytes(buf))
    a_sec, a_nsec, _ = PPS_KTIME.unpack(a_tu)
    c_sec, c_nsec, _ = PPS_KTIME.unpack(c_tu)
    return PpsFetch(a_seq, c_seq, a_sec * NS_PER_S + a_nsec, c_sec * NS_PER_S + c_nsec, mode)


# ---------------------------------------------------------------------------------------------
# Sources.
# ---------------------------------------------------------------------------------------------

PPS_SOURCES = Registry("pps")
register_pps_source = PPS_SOURCES.register


def create_pps_source(config: dict) -> PpsSource:
    """``{'kind': 'kernel'|'serial-line'|'udp', ...}`` → a PPS source (not yet opened)."""
    return PPS_SOURCES.create(config)


class PpsSource:
    """``async with source:`` then ``async for edge in source`` (or ``await source.get()``)."""

    kind = ""

    def __init__(self, name: str | None = None, queue_size: int = 64) -> None:
        self.name = name or self.kind
        self.stats = DecoderStats()
        self._queue: asyncio.Queue = asyncio.Queue(queue_size)
        self._loop: asyncio.AbstractEventLoop | None = None

    async def open(self) -> None:
        self._loop = asyncio.get_running_loop()

    async def close(self) -> None:
        pass

    async def __aenter__(self):
        await self.open()
        return self

    async def __aexit__(self, *exc) -> None:
        await self.close()

    async def get(self) -> PpsEdge:
        item = await self._queue.get()
        if isinstance(item, BaseException):
            raise item
        return item

    def __aiter__(self) -> AsyncIterator[PpsEdge]:
        return self._iter()

    async def _iter(self):
        while True:
            yield await self.get()

    def _put(self, item) -> None:  # on the loop thread
        if self._queue.full():
            self.stats.events["dropped"] += 1
            return
        if isinstance(item, PpsEdge):
            self.stats.records += 1
        self._queue.put_nowait(item)

    def _put_threadsafe(self, item) -> None:
        if self._loop is not None and not self._loop.is_closed():
            self._loop.call_soon_threadsafe(self._put, item)


class _ThreadedSource(PpsSource):
    """A source whose blocking wait runs in a daemon thread."""

    def __init__(self, name: str | None = None) -> None:
        super().__init__(name)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    async def open(self) -> None:
        await super().open()
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name=f"pps-{self.name}", daemon=True)
        self._thread.start()

    async def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            await asyncio.to_thread(self._thread.join, 3.0)
            self._thread = None

    def _run(self) -> None:
        raise NotImplementedError


@register_pps_source("kernel")
class KernelPpsSource(_ThreadedSource):
    """``/dev/ppsN`` via ``PPS_FETCH`` (assert edges). ``ioctl`` is injectable for tests."""

    def __init__(
        self, device: str = "/dev/pps0", name: str | None = None, timeout_s: float = 1.5, ioctl=fcntl.ioctl
    ):
        super().__init__(name or device)
        self.device = device
        self.timeout_s = timeout_s
        self._ioctl = ioctl

    def _run(self) -> None:
        try:
            fd = os.open(self.device, os.O_RDONLY)
        except OSError as exc:
            self._put_threadsafe(DriverError(f"PPS device {self.device}: {exc.strerror}"))
            return
        last_seq = None
        try:
            while not self._stop.is_set():
                buf = pack_pps_fdata(self.timeout_s)
                try:
                    self._ioctl(fd, PPS_FETCH, buf, True)
                except OSError as exc:
                    if exc.errno in (errno.ETIMEDOUT, errno.EINTR):
                        continue
                    self._put_threadsafe(DriverError(f"PPS_FETCH on {self.device}: {exc.strerror}"))
                    return
                offset = realtime_minus_monotonic_ns()
                f = unpack_pps_fdata(buf)
                if f.assert_sequence == last_seq or f.assert_realtime_ns == 0:
                    continue
                last_seq = f.assert_sequence
                self._put_threadsafe(
                    PpsEdge(
                        f.assert_realtime_ns - offset,
                        self.name,
                        f.assert_sequence,
                        None,
                        f.assert_realtime_ns,
                    )
                )
        finally:
            os.close(fd)


@register_pps_source("serial-line")
class SerialLinePpsSource(_ThreadedSource):
    """A pulse on a serial port's DCD line, via ``TIOCMIWAIT`` (real UARTs only: a pty refuses it).

    ``ioctl`` is injectable so the edge logic can be tested without a UART.
    """

    LINES = {
        "dcd": termios.TIOCM_CD,
        "cts": termios.TIOCM_CTS,
        "dsr": termios.TIOCM_DSR,
        "ri": termios.TIOCM_RI,
    }

    def __init__(self, port: str, line: str = "dcd", name: str | None = None, ioctl=fcntl.ioctl):
        super().__init__(name or f"{port}:{line}")
        if line not in self.LINES:
            raise DriverError(f"pps.line {line!r}: expected one of {sorted(self.LINES)}")
        self.port = port
        self.mask = self.LINES[line]
        self._ioctl = ioctl

    def _run(self) -> None:
        try:
            fd = os.open(self.port, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        except OSError as exc:
            self._put_threadsafe(DriverError(f"PPS serial port {self.port}: {exc.strerror}"))
            return
        seq = 0
        try:
            level = self._level(fd)
            while not self._stop.is_set():
                try:
                    self._ioctl(fd, termios.TIOCMIWAIT, self.mask)
                except InterruptedError:
                    continue
                now = time.monotonic_ns()
                new_level = self._level(fd)
                if new_level and not level:  # rising edge = assert
                    seq += 1
                    self._put_threadsafe(PpsEdge(now, self.name, seq))
                level = new_level
        except OSError as exc:
            self._put_threadsafe(
                DriverError(
                    f"TIOCMIWAIT/TIOCMGET on {self.port}: {exc.strerror or exc} (not a UART with modem lines?)"
                )
            )
        finally:
            os.close(fd)

    def _level(self, fd: int) -> bool:
        buf = self._ioctl(fd, termios.TIOCMGET, struct.pack("i", 0))
        return bool(struct.unpack("i", buf)[0] & self.mask)


@register_pps_source("udp")
class UdpPpsSource(PpsSource):
    """Pulses from an emulator: one :func:`encode_pps_datagram` per pulse on a UDP port."""

    def __init__(self, host: str = "127.0.0.1", port: int = 0, name: str | None = None):
        super().__init__(name or "udp")
        self.host, self.port = host, port
        self._transport: asyncio.DatagramTransport | None = None

    async def open(self) -> None:
        await super().open()
        source = self

        class _Proto(asyncio.DatagramProtocol):
            def datagram_received(self, data, addr):
                try:
                    source._put(decode_pps_datagram(data, source.name))
                except DriverError:
                    source.stats.rejected["bad_datagram"] += 1

        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.bind((self.host, self.port))
        self.port = sock.getsockname()[1]
        loop = asyncio.get_running_loop()  # the loop super().open() kept
        self._transport, _ = await loop.create_datagram_endpoint(_Proto, sock=sock)

    async def close(self) -> None:
        if self._transport is not None:
            self._transport.close()
            self._transport = None


def gps_second_of(gps_ns: int) -> int:
    """The GPS second a time message belongs to (for :meth:`PpsLabeler.add_time`)."""
    return int(gps_ns) // NS_PER_S


__all__ = [
    "PpsEdge",
    "PpsLabeler",
    "PpsSource",
    "KernelPpsSource",
    "SerialLinePpsSource",
    "UdpPpsSource",
    "PPS_SOURCES",
    "create_pps_source",
    "register_pps_source",
    "encode_pps_datagram",
    "decode_pps_datagram",
    "pack_pps_fdata",
    "unpack_pps_fdata",
    "PPS_FETCH",
    "gps_second_of",
]
