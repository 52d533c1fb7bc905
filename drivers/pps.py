"""PPS sources and the labelling of pulses with GPS seconds (docs/architecture.md §5).

Records: a :class:`PpsEdge` is one pulse as the host saw it — ``host_ns`` on the host's
``CLOCK_MONOTONIC`` (the time base of every transport stamp), ``source`` (the source's name),
``sequence`` (the source's pulse counter) and, once labelled, ``gps_s`` (the whole GPS second
the pulse marks). ``realtime_ns`` keeps the raw ``CLOCK_REALTIME`` stamp of a kernel pulse.

Labelling (:class:`PpsLabeler`): a pulse stamped ``h`` marks GPS second S when a time message
tagged S (its time tag in [S, S+1)) has a host receive stamp ``r`` with ``0 ≤ r − h ≤ 1.1 s``
(gpsd's window), judged on the stamps alone, **whatever order pulses and messages are fed in**
(a stalled loop hands over a backlog of both in any interleaving; each stream is in order):

- the **expected latency** ``r − h`` is learnt from the last 16 labelled pairs (mean μ, σ: the
  latency the clock model sees, GPS(receive) − tag, as the pulse marks the tag). From 4 pairs
  on, a message labels the one pulse with ``|r − h − μ| ≤ tol = min(max(50 ms, 6σ), 240 ms)``;
- a message off μ by more than ``tol`` for every pulse of its window is **ambiguous** — a late
  message of one pulse or an early one of the next, 1 s apart — and labels nothing
  (``time_ambiguous``, numbers in :attr:`PpsLabeler.last_ambiguous`): unlabelled, never 1 s
  wrong. Eight in a row with one latency restart the statistics (``latency_relearned``). A
  message a whole second late looks on time for the next pulse: the clock model's gate sees it;
- before 4 pairs, gpsd's rule: the latest pulse before the message.

Messages are decided in stamp order, as soon as the pulse they expect is here (before 4 pairs: a
pulse less than ``min_interval_ns`` before them — any other would be a duplicate), else once every
pulse up to them must have been fed (a later pulse was, or the previous :meth:`PpsLabeler.tick`
came 0.5 s after them). Pulses no message can label any more, pulses older than a labelled one,
duplicate pulses (same sequence, or less than ``min_interval_ns`` after the previous) and second
messages for one GPS second are dropped and counted (``stats.events``: ``unlabelled``,
``duplicate_edge``, ``duplicate_label``, ``time_without_edge``, ``non_monotonic``,
``time_ambiguous``).

Sources — one small async interface (:class:`PpsSource`: ``async with source:`` then
``async for edge in source``), a registry keyed by the config's ``kind``
(:func:`create_pps_source`):

- ``kernel``: ``/dev/ppsN`` through the RFC 2783 ``PPS_FETCH`` ioctl, in a thread (blocking call
  with a timeout). The kernel stamps are CLOCK_REALTIME; they are moved to CLOCK_MONOTONIC with
  the realtime − monotonic offset sampled right after each fetch (through
  :class:`drivers.timing.RealtimeStamps`: a step of the realtime clock is seen, not applied to
  a pulse stamped before it).
- ``serial-line``: the DCD line of a serial port through ``TIOCMIWAIT`` in a thread; a rising
  DCD is a pulse, stamped with CLOCK_MONOTONIC as the ioctl returns.
- ``udp``: datagrams from an emulator (:func:`encode_pps_datagram`), each carrying the edge's
  own host monotonic stamp. Format (little-endian, 20 bytes)::

      magic b'PPS1' | sequence u64 | host_monotonic_ns i64
"""

from __future__ import annotations

import asyncio
import bisect
import errno
import fcntl
import math
import os
import socket
import struct
import termios
import threading
import time
from collections import deque
from collections.abc import AsyncIterator
from dataclasses import dataclass, replace

from drivers.base import DecoderStats, DriverError, Registry
from drivers.ppsfetch import PPS_FETCH, pack_pps_fdata, unpack_pps_fdata
from drivers.timing import HostClock, RealtimeStamps

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


@dataclass(frozen=True)
class LabelParams:
    window_ns: int = LABEL_WINDOW_NS  # gpsd: a time message labels a pulse at most this long after it
    min_interval_ns: int = 500_000_000  # a pulse sooner than this after the previous: a duplicate
    settle_ns: int = 500_000_000  # a pulse comes this soon after its stamp (tick's rule)
    latency_pairs: int = 16  # labelled pairs of the latency statistics
    min_pairs: int = 4  # before that many, gpsd's rule alone
    tol_floor_ns: int = 50_000_000  # the expected latency's tolerance: at least this,
    tol_sigmas: float = 6.0  # this many σ of the latencies,
    tol_max_ns: int = 240_000_000  # at most this (below half the 0.5-s duplicate interval)
    relearn_after: int = 8  # ambiguous messages in a row with one latency: it changed


class PpsLabeler:
    """The labelling rule of the module docstring; sans-I/O, never raises. Each input returns
    the pulses it labelled (host order); dropped ones wait in :meth:`take_dropped`."""

    def __init__(
        self,
        window_ns: int = LABEL_WINDOW_NS,
        min_interval_ns: int = 500_000_000,
        params: LabelParams | None = None,
    ) -> None:
        self.params = params or LabelParams(window_ns=window_ns, min_interval_ns=min_interval_ns)
        self.window_ns = self.params.window_ns
        self.stats = DecoderStats()
        self.last_ambiguous: dict | None = None  # the latest ambiguous time message, for the alarm
        self._pulses: list[PpsEdge] = []  # pending, in host order
        self._pulse_time: int | None = None  # the latest pulse stamp fed
        self._messages: deque[tuple[int, int]] = deque()  # pending (host ns, GPS second)
        self._last_tag: int | None = None
        self._last_label_ns: int | None = None  # host stamp of the latest labelled pulse
        self._last_edge: PpsEdge | None = None
        self._latencies: deque[int] = deque(maxlen=self.params.latency_pairs)
        self._ambiguous_run: list[int] = []
        self._ambiguous_keys: set[tuple[str, int]] = set()
        self._dropped: list[tuple[PpsEdge, str]] = []
        self._seen: set[tuple[str, int]] = set()
        self._seen_order: deque[tuple[str, int]] = deque()
        self._prev_tick: int | None = None

    # -- inputs -------------------------------------------------------------------------------

    def add_edge(self, edge: PpsEdge) -> list[PpsEdge]:
        """A pulse; returns the pulses a pending time message labels now that it is here."""
        key = (edge.source, edge.sequence)
        last = self._last_edge
        if key in self._seen or (
            last is not None
            and last.source == edge.source
            and 0 <= edge.host_ns - last.host_ns < self.params.min_interval_ns
        ):
            self.stats.events["duplicate_edge"] += 1
            self._dropped.append((edge, "duplicate"))
            return []
        self._seen.add(key)
        self._seen_order.append(key)
        if len(self._seen_order) > 64:
            self._seen.discard(self._seen_order.popleft())
        self._last_edge = edge
        if self._last_label_ns is not None and edge.host_ns <= self._last_label_ns:
            self._drop(edge)  # older than a labelled pulse (a reordered datagram): too late
            return []
        pulses = self._pulses
        if not pulses or pulses[-1].host_ns < edge.host_ns:
            pulses.append(edge)
        else:
            pulses.insert(bisect.bisect([p.host_ns for p in pulses], edge.host_ns), edge)
        if self._pulse_time is None or edge.host_ns > self._pulse_time:
            self._pulse_time = edge.host_ns
        return self._resolve(None) if self._messages else []

    def add_time(self, gps_s: int, host_ns: int) -> list[PpsEdge]:
        """A time message for GPS second ``gps_s`` received at ``host_ns``."""
        gps_s = int(gps_s)
        last = self._last_tag
        if last is not None and gps_s <= last:  # the 2nd message of a second (TIME__ at 100 Hz)
            self.stats.events["duplicate_label" if gps_s == last else "non_monotonic"] += 1
            return []
        self._last_tag = gps_s
        self._messages.append((int(host_ns), gps_s))
        return self._resolve(None)

    def tick(self, now_ns: int) -> list[PpsEdge]:
        """Periodic: decide what no input can change any more, judged at the *previous* tick's
        time (after a stalled loop, what was stamped during the stall may not be fed yet)."""
        ref, self._prev_tick = self._prev_tick, int(now_ns)
        if ref is None:
            return []
        out = self._resolve(ref - self.params.settle_ns)
        first = self._messages[0][0] if self._messages else None
        while self._pulses and ref - self._pulses[0].host_ns > self.params.window_ns:
            if first is not None and first - self._pulses[0].host_ns <= self.params.window_ns:
                break  # a pending time message may still label it
            self._drop(self._pulses.pop(0))
        return out

    def flush(self) -> list[PpsEdge]:
        """Decide everything pending (the end of the streams)."""
        out = self._resolve(None, final=True)
        while self._pulses:
            self._drop(self._pulses.pop(0))
        return out

    def take_dropped(self) -> list[tuple[PpsEdge, str]]:
        """The pulses dropped since the last call, with the reason."""
        out, self._dropped = self._dropped, []
        return out

    def expected_latency(self) -> tuple[float, float] | None:
        """(mean, tolerance) in ns of time message − its pulse, once known (see the module docstring)."""
        lat, p = self._latencies, self.params
        if len(lat) < p.min_pairs:
            return None
        mean = sum(lat) / len(lat)
        sigma = math.sqrt(sum((x - mean) ** 2 for x in lat) / len(lat))
        return mean, min(max(p.tol_floor_ns, p.tol_sigmas * sigma), p.tol_max_ns)

    # -- decisions ----------------------------------------------------------------------------

    def _resolve(self, horizon_ns: int | None, final: bool = False) -> list[PpsEdge]:
        """Decide the pending messages, oldest first, while decidable (module docstring)."""
        out: list[PpsEdge] = []
        messages, window = self._messages, self.params.window_ns
        while messages:
            r, gps_s = messages[0]
            expected = self.expected_latency()
            pick = None
            if expected is not None:
                mean, tol = expected
                for p in reversed(self._pulses):
                    if r - p.host_ns > window:
                        break
                    if 0 <= r - p.host_ns and abs(r - p.host_ns - mean) <= tol:
                        pick = p
                        break
            elif self._pulses and 0 <= r - self._pulses[-1].host_ns < self.params.min_interval_ns:
                pick = self._pulses[-1]  # gpsd's pick: no other pulse can come between (duplicate)
            complete = (
                final
                or (self._pulse_time is not None and self._pulse_time >= r)
                or (horizon_ns is not None and r < horizon_ns)
            )
            if pick is None and not complete:
                break
            messages.popleft()
            labelled = self._decide(r, gps_s, expected, pick)
            if labelled is not None:
                out.append(labelled)
        return out

    def _decide(self, r: int, gps_s: int, expected, pick: PpsEdge | None) -> PpsEdge | None:
        window = self.params.window_ns
        candidates = [p for p in self._pulses if 0 <= r - p.host_ns <= window]
        if not candidates:
            self.stats.events["time_without_edge"] += 1
            return None
        if pick is None and expected is None:
            pick = candidates[-1]  # gpsd: the latest pulse before the message
        if pick is None:  # later or earlier than expected for every pulse: it could be either's
            mean, tol = expected
            latency = r - candidates[-1].host_ns
            self.stats.events["time_ambiguous"] += 1
            self.last_ambiguous = {
                "gps_s": gps_s,
                "host_ns": r,
                "latency_ns": latency,
                "expected_ns": round(mean),
                "tolerance_ns": round(tol),
            }
            self._ambiguous_keys.update((p.source, p.sequence) for p in candidates)
            run = self._ambiguous_run
            if run and abs(latency - sum(run) / len(run)) > tol:
                run.clear()
            run.append(latency)
            if len(run) >= self.params.relearn_after:  # the time messages' latency changed
                self._latencies.clear()
                self._latencies.extend(run)
                run.clear()
                self.stats.events["latency_relearned"] += 1
            return None
        while self._pulses and self._pulses[0].host_ns < pick.host_ns:
            self._drop(self._pulses.pop(0))
        self._pulses.pop(0)
        self._ambiguous_keys.discard((pick.source, pick.sequence))
        self._last_label_ns = pick.host_ns
        self._latencies.append(r - pick.host_ns)
        self._ambiguous_run.clear()
        self.stats.records += 1
        return replace(pick, gps_s=gps_s)

    def _drop(self, edge: PpsEdge) -> None:
        key = (edge.source, edge.sequence)
        self.stats.events["unlabelled"] += 1
        if key in self._ambiguous_keys:
            self._ambiguous_keys.discard(key)
            self._dropped.append((edge, "ambiguous"))
        else:
            self._dropped.append((edge, "unlabelled"))


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
    """``/dev/ppsN`` via ``PPS_FETCH`` (assert edges). ``ioctl`` is injectable for tests;
    ``host_clock`` moves the realtime stamps (default: the real clock)."""

    def __init__(
        self,
        device: str = "/dev/pps0",
        name: str | None = None,
        timeout_s: float = 1.5,
        ioctl=fcntl.ioctl,
        host_clock: HostClock | None = None,
    ):
        super().__init__(name or device)
        self.host_clock = host_clock
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
        stamps = RealtimeStamps(clock=self.host_clock)
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
                offset = stamps.begin()
                f = unpack_pps_fdata(buf)
                if f.assert_sequence == last_seq or f.assert_realtime_ns == 0:
                    continue
                last_seq = f.assert_sequence
                if stamps.exact:
                    host_ns = stamps.last_ns = f.assert_realtime_ns - offset
                else:  # the realtime clock stepped around this pulse
                    host_ns = stamps.convert(f.assert_realtime_ns, time.monotonic_ns())
                self._put_threadsafe(
                    PpsEdge(
                        host_ns,
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
        try:
            sock.bind((self.host, self.port))
            self.port = sock.getsockname()[1]
            loop = asyncio.get_running_loop()  # the loop super().open() kept
            self._transport, _ = await loop.create_datagram_endpoint(_Proto, sock=sock)
        except BaseException:
            sock.close()  # a port taken (or a cancelled open) leaves no socket behind
            raise

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
    "gps_second_of",
]
