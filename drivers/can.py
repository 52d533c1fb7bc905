"""CAN through python-can: a bus from config, host-stamped frames, decoders per arbitration id.

Config (the vessel config's CAN device; keys other than these go to ``can.Bus`` as is)::

    {"interface": "virtual", "channel": "mls"}                 # inside one process (tests)
    {"interface": "udp_multicast", "channel": "239.74.163.2",  # across processes (emulators)
     "port": 43113, "loopback_only": true}

``loopback_only`` (udp_multicast only, default True) keeps the multicast traffic on the
loopback interface: python-can joins the group on the default interface and sends through the
default route; the emulators and the daemon run on one host, so the socket is re-joined on
``lo`` and its outgoing interface pinned to it. python-can's ``udp_multicast`` interface needs
the ``msgpack`` package (``python-can[multicast]``); without it :func:`open_can_bus` raises
:class:`~drivers.base.DriverError` saying so.

:class:`CanReader` (``async with CanReader(bus) as r: async for frame in r``) receives in
python-can's notifier thread, stamps each frame with the host ``CLOCK_MONOTONIC`` there, and
hands :class:`CanFrame` records to the event loop through a bounded queue (overflow is counted,
never blocking). A decoder registered for an arbitration id (:meth:`CanReader.register`) turns
the frame's payload into a record, stored in ``frame.decoded``; a decoder raising
:class:`DriverError` counts the frame as rejected.

Event markers (pass start/end, operator marks), sent by the CAN emulator and decoded here, are
8-byte frames on :data:`EVENT_MARKER_ID` (0x6E0), little-endian::

    byte 0   format  0xE1
    byte 1   kind    1 pass_start, 2 pass_end, 3 mark
    bytes 2–3 pass_id u16
    bytes 4–7 sequence u32 (the emitter's marker counter)

The marker's time is the frame's host stamp.
"""

from __future__ import annotations

import asyncio
import socket
import struct
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any, cast

from drivers.base import DecoderStats, DriverError

if TYPE_CHECKING:
    from can import Notifier
    from can.interfaces.udp_multicast import UdpMulticastBus

EVENT_MARKER_ID = 0x6E0
EVENT_MARKER_FORMAT = 0xE1
EVENT_KINDS = {1: "pass_start", 2: "pass_end", 3: "mark"}
EVENT_CODES = {v: k for k, v in EVENT_KINDS.items()}
_MARKER = struct.Struct("<BBHI")


@dataclass(frozen=True, slots=True)
class CanFrame:
    arbitration_id: int
    data: bytes
    host_ns: int  # CLOCK_MONOTONIC when the frame was received
    device_timestamp_s: float  # the interface's own stamp (python-can Message.timestamp)
    is_extended_id: bool = False
    channel: str | None = None
    decoded: Any = None  # what the registered decoder made of it


@dataclass(frozen=True, slots=True)
class EventMarker:
    kind: str  # 'pass_start' | 'pass_end' | 'mark'
    pass_id: int
    sequence: int
    host_ns: int | None = None


def encode_event_marker(kind: str, pass_id: int, sequence: int) -> bytes:
    if kind not in EVENT_CODES:
        raise DriverError(f"event marker kind {kind!r}: expected one of {sorted(EVENT_CODES)}")
    if not 0 <= pass_id <= 0xFFFF:
        raise DriverError(f"event marker pass_id {pass_id}: expected 0..65535")
    return _MARKER.pack(EVENT_MARKER_FORMAT, EVENT_CODES[kind], pass_id, sequence & 0xFFFFFFFF)


def decode_event_marker(frame: CanFrame) -> EventMarker:
    """Raises :class:`DriverError` naming what is wrong with the payload."""
    if len(frame.data) != _MARKER.size:
        raise DriverError(f"event marker: {len(frame.data)} data bytes, expected {_MARKER.size}")
    fmt, code, pass_id, seq = _MARKER.unpack(frame.data)
    if fmt != EVENT_MARKER_FORMAT:
        raise DriverError(f"event marker format byte 0x{fmt:02x}: expected 0x{EVENT_MARKER_FORMAT:02x}")
    if code not in EVENT_KINDS:
        raise DriverError(f"event marker kind code {code}: expected one of {sorted(EVENT_KINDS)}")
    return EventMarker(EVENT_KINDS[code], pass_id, seq, frame.host_ns)


def event_marker_message(kind: str, pass_id: int, sequence: int, arbitration_id: int = EVENT_MARKER_ID):
    """A ``can.Message`` carrying an event marker (for the CAN emulator)."""
    import can

    return can.Message(
        arbitration_id=arbitration_id, data=encode_event_marker(kind, pass_id, sequence), is_extended_id=False
    )


def open_can_bus(config: dict[str, Any]):
    """A python-can bus from a config mapping (see the module docstring)."""
    import can

    cfg = dict(config)
    interface = cfg.pop("interface", None)
    if not interface:
        raise DriverError("can.interface: missing (e.g. 'virtual', 'udp_multicast', 'socketcan')")
    loopback_only = cfg.pop("loopback_only", True)
    if interface == "udp_multicast":
        from can.interfaces.udp_multicast.utils import is_msgpack_installed

        if not is_msgpack_installed(raise_exception=False):
            raise DriverError(
                "can.interface 'udp_multicast' needs the msgpack package (install python-can[multicast])"
            )
    try:
        bus = can.Bus(interface=interface, **cfg)
    except (can.CanError, ValueError, TypeError, NotImplementedError) as exc:
        raise DriverError(f"can ({interface}): {exc}") from exc
    if interface == "udp_multicast" and loopback_only:
        multicast = cast("UdpMulticastBus", bus)._multicast  # python-can 4.6 internals
        pin_multicast_to_loopback(multicast._socket, multicast.group)
    return bus


def pin_multicast_to_loopback(sock: socket.socket, group: str) -> None:
    """Move a multicast socket's membership and outgoing interface to the loopback interface."""
    if sock.family == socket.AF_INET:
        grp = socket.inet_aton(group)
        try:
            sock.setsockopt(
                socket.IPPROTO_IP, socket.IP_DROP_MEMBERSHIP, grp + struct.pack("@I", socket.INADDR_ANY)
            )
        except OSError:
            pass
        lo = socket.inet_aton("127.0.0.1")
        sock.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, grp + lo)
        sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, lo)
        sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP, 1)
    else:
        grp = socket.inet_pton(socket.AF_INET6, group)
        lo_index = socket.if_nametoindex("lo")
        try:
            sock.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_LEAVE_GROUP, grp + struct.pack("@I", 0))
        except OSError:
            pass
        sock.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_JOIN_GROUP, grp + struct.pack("@I", lo_index))
        sock.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_MULTICAST_IF, lo_index)
        sock.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_MULTICAST_LOOP, 1)


class CanReader:
    """Async reader of a python-can bus with per-arbitration-id decoders (see module docstring)."""

    def __init__(
        self,
        bus,
        decoders: dict[int, Callable[[CanFrame], Any]] | None = None,
        queue_size: int = 1024,
        close_bus: bool = False,
    ) -> None:
        self.bus = bus
        self.decoders: dict[int, Callable[[CanFrame], Any]] = dict(decoders or {})
        self.stats = DecoderStats()
        self.close_bus = close_bus
        self._queue: asyncio.Queue[CanFrame] = asyncio.Queue(queue_size)
        self._notifier: Notifier | None = None
        self._loop: asyncio.AbstractEventLoop | None = None

    def register(self, arbitration_id: int, decoder: Callable[[CanFrame], Any]) -> None:
        self.decoders[arbitration_id] = decoder

    async def __aenter__(self):
        import can

        loop = self._loop = asyncio.get_running_loop()
        reader = self

        class _Listener(can.Listener):
            def on_message_received(self, msg) -> None:  # notifier thread
                frame = CanFrame(
                    msg.arbitration_id,
                    bytes(msg.data),
                    time.monotonic_ns(),
                    msg.timestamp,
                    msg.is_extended_id,
                    None if msg.channel is None else str(msg.channel),
                )
                loop.call_soon_threadsafe(reader._deliver, frame)  # the loop that entered the reader

        self._notifier = can.Notifier(self.bus, [_Listener()], timeout=0.1)
        return self

    async def __aexit__(self, *exc) -> None:
        if self._notifier is not None:
            await asyncio.to_thread(self._notifier.stop)
            self._notifier = None
        if self.close_bus:
            self.bus.shutdown()

    def decode(self, frame: CanFrame) -> CanFrame:
        """Apply the registered decoder, if any; a DriverError counts the frame as rejected."""
        decoder = self.decoders.get(frame.arbitration_id)
        if decoder is None:
            return frame
        try:
            return replace(frame, decoded=decoder(frame))
        except DriverError:
            self.stats.rejected[f"0x{frame.arbitration_id:x}"] += 1
            return frame

    def _deliver(self, frame: CanFrame) -> None:
        self.stats.bytes_in += len(frame.data)
        if self._queue.full():
            self.stats.events["dropped_frames"] += 1
            return
        self.stats.records += 1
        self._queue.put_nowait(self.decode(frame))

    async def get(self) -> CanFrame:
        return await self._queue.get()

    def __aiter__(self):
        return self._iter()

    async def _iter(self):
        while True:
            yield await self._queue.get()


# ---------------------------------------------------------------------------------------------
# SocketCAN frame layout: how a frame is kept as bytes (the session's /can/<name> channels).
# ---------------------------------------------------------------------------------------------

_CAN_FRAME = struct.Struct("<IB3x8s")
_CANFD_FRAME = struct.Struct("<IBB2x64s")
CAN_EFF_FLAG = 0x80000000


def can_frame_bytes(arbitration_id: int, data: bytes, extended: bool = False) -> bytes:
    """SocketCAN ``struct can_frame`` (or ``canfd_frame`` beyond 8 data bytes), little-endian."""
    can_id = arbitration_id | (CAN_EFF_FLAG if extended else 0)
    if len(data) <= 8:
        return _CAN_FRAME.pack(can_id, len(data), bytes(data))
    return _CANFD_FRAME.pack(can_id, len(data), 0, bytes(data))


def parse_can_frame(raw: bytes) -> tuple[int, bytes, bool]:
    """(arbitration id, data, extended) of :func:`can_frame_bytes`' output."""
    if len(raw) == _CAN_FRAME.size:
        can_id, n, data = _CAN_FRAME.unpack(raw)
    elif len(raw) == _CANFD_FRAME.size:
        can_id, n, _, data = _CANFD_FRAME.unpack(raw)
    else:
        raise DriverError(f"CAN frame record of {len(raw)} bytes: expected 16 or 72")
    if n > len(data):  # a damaged length byte: the data would be cut silently
        raise DriverError(f"CAN frame record of {len(raw)} bytes says {n} data bytes: at most {len(data)}")
    extended = bool(can_id & CAN_EFF_FLAG)
    arbitration_id = can_id & 0x1FFFFFFF
    if not extended and arbitration_id > 0x7FF:
        raise DriverError(f"CAN frame record: standard (11-bit) id 0x{arbitration_id:x} exceeds 0x7ff")
    return arbitration_id, data[:n], extended
