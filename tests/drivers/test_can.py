"""CAN via python-can: virtual and udp_multicast buses, host stamps, decoder hooks, event markers."""

from __future__ import annotations

import asyncio
import socket
import time

import can
import pytest

from drivers.base import DriverError
from drivers.can import (
    EVENT_MARKER_ID,
    CanFrame,
    CanReader,
    EventMarker,
    decode_event_marker,
    encode_event_marker,
    event_marker_message,
    open_can_bus,
    pin_multicast_to_loopback,
)


def test_event_marker_encoding():
    data = encode_event_marker("pass_start", 3, 17)
    assert data == bytes([0xE1, 1, 3, 0, 17, 0, 0, 0])
    frame = CanFrame(EVENT_MARKER_ID, data, 123, 0.0)
    assert decode_event_marker(frame) == EventMarker("pass_start", 3, 17, 123)
    for bad, msg in [
        (data[:7], "7 data bytes"),
        (b"\x00" + data[1:], "format byte"),
        (data[:1] + b"\x09" + data[2:], "kind code"),
    ]:
        with pytest.raises(DriverError, match=msg):
            decode_event_marker(CanFrame(EVENT_MARKER_ID, bad, 0, 0.0))
    with pytest.raises(DriverError, match="kind 'start'"):
        encode_event_marker("start", 1, 1)


def test_open_can_bus_names_config_errors():
    with pytest.raises(DriverError, match="can.interface: missing"):
        open_can_bus({"channel": "x"})
    with pytest.raises(DriverError, match="can \\(no_such_interface\\)"):
        open_can_bus({"interface": "no_such_interface"})


def _exchange(rx_config: dict, tx_config: dict):
    async def run():
        rx_bus = open_can_bus(rx_config)
        tx_bus = open_can_bus(tx_config)
        try:
            # (the receiving bus exists before the first send: it keeps the frames until read)
            async with CanReader(rx_bus, {EVENT_MARKER_ID: decode_event_marker}) as reader:
                before = time.monotonic_ns()
                tx_bus.send(event_marker_message("pass_start", 2, 1))
                tx_bus.send(can.Message(arbitration_id=0x123, data=b"\x01\x02", is_extended_id=False))
                tx_bus.send(can.Message(arbitration_id=EVENT_MARKER_ID, data=b"\x00", is_extended_id=False))
                tx_bus.send(event_marker_message("pass_end", 2, 2))
                frames = [await asyncio.wait_for(reader.get(), 3) for _ in range(4)]
                return before, frames, reader.stats
        finally:
            rx_bus.shutdown()
            tx_bus.shutdown()

    return asyncio.run(run())


def test_virtual_bus_frames_are_stamped_and_decoded_per_arbitration_id():
    before, frames, stats = _exchange(
        {"interface": "virtual", "channel": "mls-test"}, {"interface": "virtual", "channel": "mls-test"}
    )
    start, other, broken, end = frames
    assert start.decoded == EventMarker("pass_start", 2, 1, start.host_ns)
    assert end.decoded.kind == "pass_end" and end.decoded.sequence == 2
    assert other.arbitration_id == 0x123 and other.data == b"\x01\x02" and other.decoded is None
    assert broken.decoded is None and stats.rejected[f"0x{EVENT_MARKER_ID:x}"] == 1
    assert before <= start.host_ns <= other.host_ns <= end.host_ns <= time.monotonic_ns()
    assert stats.records == 4


def test_udp_multicast_bus_between_two_buses_on_loopback():
    """Across processes the emulators use python-can's udp_multicast; it needs msgpack."""
    try:
        import msgpack  # noqa: F401
    except ImportError:
        pytest.fail(
            "python-can's udp_multicast interface needs msgpack: add python-can[multicast] to the dependencies"
        )
    cfg = {"interface": "udp_multicast", "channel": "239.74.163.2", "port": 43117}
    _, frames, stats = _exchange(cfg, cfg)
    assert [f.decoded.kind if f.decoded else None for f in frames] == ["pass_start", None, None, "pass_end"]


def test_multicast_socket_is_pinned_to_loopback():
    """The loopback pinning used for udp_multicast, on a socket joined the way python-can joins."""
    group, port = "239.74.163.9", 43119
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    rx.bind(("", port))
    rx.setsockopt(
        socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, socket.inet_aton(group) + socket.inet_aton("0.0.0.0")
    )
    pin_multicast_to_loopback(rx, group)
    assert rx.getsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, 4) == socket.inet_aton("127.0.0.1")
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    tx.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton("127.0.0.1"))
    tx.sendto(b"marker", (group, port))
    rx.settimeout(2)
    data, addr = rx.recvfrom(100)
    assert data == b"marker" and addr[0] == "127.0.0.1"
    rx.close()
    tx.close()
