"""The capture reader on synthetic captures (both byte orders, time resolutions, link types) and errors."""

from __future__ import annotations

import struct

import pytest

from drivers.capture.pcapng import CaptureReader, PcapError, udp_datagrams
from tests.drivers.helpers import real_file


def _block(e: str, btype: int, body: bytes) -> bytes:
    body += b"\0" * (-len(body) % 4)
    n = len(body) + 12
    return struct.pack(e + "II", btype, n) + body + struct.pack(e + "I", n)


def _shb(e: str) -> bytes:
    return _block(e, 0x0A0D0D0A, struct.pack(e + "IHHq", 0x1A2B3C4D, 1, 0, -1))


def _idb(e: str, linktype: int, tsresol: int | None = None, tsoffset: int | None = None) -> bytes:
    opts = b""
    if tsresol is not None:
        opts += struct.pack(e + "HH", 9, 1) + bytes([tsresol]) + b"\0\0\0"
    if tsoffset is not None:
        opts += struct.pack(e + "HHq", 14, 8, tsoffset)
    opts += struct.pack(e + "HH", 0, 0)
    return _block(e, 1, struct.pack(e + "HHI", linktype, 0, 65535) + opts)


def _epb(e: str, iface: int, ticks: int, data: bytes) -> bytes:
    return _block(
        e, 6, struct.pack(e + "IIIII", iface, ticks >> 32, ticks & 0xFFFFFFFF, len(data), len(data)) + data
    )


def _udp_ipv4(payload: bytes, sport=5000, dport=8200, frag=0) -> bytes:
    udp = struct.pack(">HHHH", sport, dport, 8 + len(payload), 0) + payload
    return (
        struct.pack(
            ">BBHHHBBH4s4s",
            0x45,
            0,
            20 + len(udp),
            1,
            frag,
            64,
            17,
            0,
            bytes([192, 168, 1, 2]),
            bytes([192, 168, 1, 9]),
        )
        + udp
    )


def _udp_ipv6(payload: bytes, dport=8200) -> bytes:
    udp = struct.pack(">HHHH", 7, dport, 8 + len(payload), 0) + payload
    return struct.pack(">IHBB16s16s", 6 << 28, len(udp), 17, 64, b"\0" * 15 + b"\1", b"\0" * 15 + b"\1") + udp


def _eth(ip: bytes, etype=0x0800, vlan=False) -> bytes:
    head = b"\x11" * 6 + b"\x22" * 6
    if vlan:
        head += struct.pack(">HH", 0x8100, 5)
    return head + struct.pack(">H", etype) + ip


@pytest.mark.parametrize("e", ["<", ">"])
def test_pcapng_both_byte_orders_resolutions_and_link_types(e):
    cap = (
        _shb(e)
        + _idb(e, 1)  # Ethernet, default µs
        + _idb(e, 113, tsresol=9, tsoffset=10)  # Linux SLL, ns, +10 s
        + _idb(e, 101, tsresol=0x80 | 10)  # raw IP, 2^-10 s
        + _epb(e, 0, 1_500_000_000_123_456, _eth(_udp_ipv4(b"one"), vlan=True))
        + _epb(e, 1, 1_500_000_000_123_456_789, b"\0" * 14 + struct.pack(">H", 0x86DD) + _udp_ipv6(b"two"))
        + _epb(e, 2, 1024 * 7 + 512, _udp_ipv4(b"three"))
        + _epb(e, 0, 1, _eth(_udp_ipv4(b"frag", frag=0x2000)))
        + _epb(e, 0, 2, _eth(b"\0" * 28, etype=0x0806))  # ARP
        + _epb(e, 0, 3, _eth(_udp_ipv4(b"other", dport=9999)))
    )
    reader = CaptureReader(cap)
    pkts = list(reader)
    assert len(pkts) == 6 and [p.linktype for p in pkts[:3]] == [1, 113, 101]
    assert pkts[0].timestamp_ns == 1_500_000_000_123_456_000
    assert pkts[1].timestamp_ns == 1_500_000_010_123_456_789
    assert pkts[2].timestamp_ns == 7_500_000_000
    from drivers.base import DecoderStats

    stats = DecoderStats()
    grams = list(udp_datagrams(pkts, port=8200, stats=stats))
    assert [g.payload for g in grams] == [b"one", b"two", b"three"]
    assert grams[0].src == ("192.168.1.2", 5000) and grams[0].dst == ("192.168.1.9", 8200)
    assert grams[1].src == ("::1", 7)
    assert dict(stats.events) == {"ip_fragment": 1, "not_ip": 1, "other_port": 1}


def test_classic_pcap_with_nanosecond_stamps():
    head = struct.pack("<IHHiIII", 0xA1B23C4D, 2, 4, 0, 0, 65535, 1)
    pkt = _eth(_udp_ipv4(b"ns"))
    cap = head + struct.pack("<IIII", 1_600_000_000, 999_999_999, len(pkt), len(pkt)) + pkt
    (g,) = udp_datagrams(CaptureReader(cap))
    assert g.payload == b"ns" and g.timestamp_ns == 1_600_000_000_999_999_999


def test_truncated_capture_ends_iteration_and_is_counted():
    cap = (
        _shb("<")
        + _idb("<", 1)
        + _epb("<", 0, 5, _eth(_udp_ipv4(b"ok")))
        + _epb("<", 0, 6, _eth(_udp_ipv4(b"cut")))[:-9]
    )
    reader = CaptureReader(cap)
    assert len(list(reader)) == 1 and reader.stats.rejected["truncated"] == 1


def test_not_a_capture_is_a_clear_error(tmp_path):
    bad = tmp_path / "notes.txt"
    bad.write_bytes(b"hello world")
    with pytest.raises(PcapError, match=r"notes.txt: offset 0: magic 68656c6c is neither pcapng nor pcap"):
        list(CaptureReader(bad))
    with pytest.raises(PcapError, match="block length 7"):
        list(CaptureReader(_shb("<")[:4] + struct.pack("<I", 7) + _shb("<")[8:]))


def test_real_capture_packets_and_stamps():
    reader = CaptureReader(real_file("ixblue-stdbin", "stdbin_V2_2Hz.pcapng"))
    grams = list(udp_datagrams(reader, port=8200))
    assert len(grams) == 26 and not reader.stats.rejected
    assert all(g.dst[1] == 8200 and g.payload[:2] == b"IX" for g in grams)
    steps = [b.timestamp_ns - a.timestamp_ns for a, b in zip(grams, grams[1:])]
    assert all(abs(s - 500_000_000) < 1_000_000 for s in steps)  # 2 Hz
    assert 1_550_000_000 < grams[0].timestamp_ns / 1e9 < 1_560_000_000  # February 2019


def test_blocks_are_read_one_at_a_time_and_oversized_ones_skipped_unread(monkeypatch, tmp_path):
    import drivers.capture.pcapng as pcapng

    monkeypatch.setattr(pcapng, "MAX_BLOCK", 200)
    cap = (
        _shb("<")
        + _idb("<", 1)
        + _epb("<", 0, 1, _eth(_udp_ipv4(b"first")))
        + _block("<", 5, b"\0" * 400)  # interface statistics: not read, whatever its size
        + _epb("<", 0, 2, _eth(_udp_ipv4(b"x" * 300)))  # a body longer than MAX_BLOCK
        + _epb("<", 0, 3, _eth(_udp_ipv4(b"last")))
    )
    path = tmp_path / "cap.pcapng"
    path.write_bytes(cap)
    reader = CaptureReader(path)
    offsets = []
    payloads = []
    for g in udp_datagrams(reader):
        payloads.append(g.payload)
        offsets.append(reader.offset)
    assert payloads == [b"first", b"last"]
    assert dict(reader.stats.rejected) == {"oversized_block": 1}
    assert offsets[-1] == reader.size == len(cap) and 0 < offsets[0] < offsets[-1]
