"""A small reader for packet captures (pcapng and classic pcap) and their UDP payloads.

Enough of the formats to replay device traffic captured with Wireshark/dumpcap/tcpdump: the
section header (either byte order), interface descriptions (link type, ``if_tsresol``,
``if_tsoffset``), enhanced, simple and obsolete packet blocks; classic pcap with micro- or
nanosecond stamps. Link types: Ethernet (with 802.1Q/802.1ad tags), raw IPv4/IPv6, BSD
loopback (NULL/LOOP), Linux cooked capture v1 and v2. UDP over IPv4 (unfragmented) and IPv6
(no extension headers).

The file is read block by block (record by record for pcap) through a buffered reader, never
whole: a capture of any size is read in bounded memory, and ``reader.offset`` says how far the
iteration got. Blocks the reader has no use for are skipped without being read.

Capture stamps are kept as ``timestamp_ns`` (ns since the Unix epoch, the capture host's
clock). A file that is not a capture raises :class:`PcapError` naming the file offset; a capture
cut short (the last block incomplete) ends the iteration and is counted in
``reader.stats.rejected['truncated']``; a block too short for its type's fixed fields (a damaged
length) is skipped and counted in ``rejected['short_block']``, one longer than
:data:`MAX_BLOCK` in ``rejected['oversized_block']``; packets that are not UDP are counted by
reason.
"""

from __future__ import annotations

import io
import ipaddress
import os
import socket
import struct
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

from drivers.base import DecoderStats, DriverError

#: a section header block starts with this block type, the same in either byte order
SHB_MAGIC = b"\x0a\x0d\x0d\x0a"
IDB, PB, SPB, EPB = 1, 2, 3, 6
#: the section header's byte-order magic 0x1A2B3C4D as written little- and big-endian
BYTE_ORDER_LE, BYTE_ORDER_BE = b"\x4d\x3c\x2b\x1a", b"\x1a\x2b\x3c\x4d"
LINKTYPE_NULL, LINKTYPE_ETHERNET, LINKTYPE_RAW = 0, 1, 101
LINKTYPE_LOOP, LINKTYPE_LINUX_SLL, LINKTYPE_IPV4, LINKTYPE_IPV6, LINKTYPE_LINUX_SLL2 = 108, 113, 228, 229, 276


#: the fixed part of each block type's body (IDB: linktype, reserved, snaplen; EPB/PB: 20 bytes);
#: the blocks of other types are skipped unread
_MIN_BODY = {IDB: 8, PB: 20, EPB: 20, SPB: 4}
#: the longest block (pcapng) or packet record (pcap) read; a longer one is a damaged length or
#: nothing a device sends: skipped unread, counted in ``rejected['oversized_block']``
MAX_BLOCK = 64 << 20
READ_BUFFER = 1 << 20
#: capture stamps are int64 ns since the Unix epoch (1677-09-21 to 2262-04-11)
MAX_TIMESTAMP_NS, MIN_TIMESTAMP_NS = 2**63 - 1, -(2**63)
_PCAP_MAGICS = (b"\xd4\xc3\xb2\xa1", b"\xa1\xb2\xc3\xd4", b"\x4d\x3c\xb2\xa1", b"\xa1\xb2\x3c\x4d")
_U32X2 = {"<": struct.Struct("<II"), ">": struct.Struct(">II")}
#: a packet block's interface id, timestamp (high, low) and captured length, by byte order and
#: block type (EPB: interface id u32; PB: interface id u16, then the drops count, not kept)
_PACKET_HEADS = {e: {EPB: struct.Struct(e + "IIII"), PB: struct.Struct(e + "HxxIII")} for e in ("<", ">")}
_IP_VERSIONS = {0x0800: 4, 0x86DD: 6}  # by EtherType
_ntop, _AF_INET = socket.inet_ntop, socket.AF_INET


class PcapError(DriverError):
    """The bytes are not a packet capture this reader understands."""


@dataclass(slots=True)
class CapturedPacket:
    timestamp_ns: int  # capture host clock, ns since the Unix epoch
    interface: int
    linktype: int
    data: bytes


@dataclass(slots=True)
class UdpDatagram:
    timestamp_ns: int
    src: tuple[str, int]
    dst: tuple[str, int]
    payload: bytes


class CaptureReader:
    """Iterate the packets of a pcapng or pcap capture: ``for pkt in CaptureReader(path)``.

    Reads the file block by block (bounded memory, whatever its size); ``offset`` is the file
    offset the iteration has reached (progress), ``size`` the size of the capture."""

    def __init__(self, source: str | Path | bytes) -> None:
        self._bytes: bytes | None = None
        if isinstance(source, (bytes, bytearray, memoryview)):
            self.name, self._bytes = "<bytes>", bytes(source)
            self.size = len(self._bytes)
        else:
            self.name, self._path = str(source), Path(source)
            self.size = self._path.stat().st_size
        self.offset = 0
        self.stats = DecoderStats(bytes_in=self.size)

    def _open(self) -> BinaryIO:
        if self._bytes is not None:
            return io.BytesIO(self._bytes)
        f = open(self._path, "rb", buffering=READ_BUFFER)  # closed by __iter__
        self.size = self.stats.bytes_in = os.fstat(f.fileno()).st_size  # what there is now
        return f

    def __iter__(self) -> Iterator[CapturedPacket]:
        with self._open() as f:
            magic = f.read(4)
            if len(magic) < 4:
                raise PcapError(f"{self.name}: {self.size} bytes is too short for a packet capture")
            if magic == SHB_MAGIC:
                f.seek(0)
                yield from self._pcapng(f)
            elif magic in _PCAP_MAGICS:
                yield from self._pcap(f, magic)
            else:
                raise PcapError(f"{self.name}: offset 0: magic {magic.hex()} is neither pcapng nor pcap")

    def _skip_to(self, f: BinaryIO, pos: int) -> None:
        f.seek(pos)
        self.offset = pos

    # -- pcapng --------------------------------------------------------------------------------
    def _pcapng(self, f: BinaryIO) -> Iterator[CapturedPacket]:
        size, pos, e = self.size, 0, "<"
        interfaces: list[tuple[int, int, int]] = []  # (linktype, units per second, offset_s)
        while pos + 12 <= size:
            head = f.read(8)
            if len(head) < 8:  # the file shrank under us
                break
            if head[:4] == SHB_MAGIC:
                e = self._byte_order(f.read(4), pos)
                interfaces = []  # interface ids restart in each section
            btype, blen = _U32X2[e].unpack(head)
            n = blen - 12  # the body, without the two length words
            min_body = _MIN_BODY.get(btype)
            if (
                blen < 12
                or blen % 4
                or pos + blen > size
                or min_body is None
                or n < min_body
                or n > MAX_BLOCK
            ):
                pos = self._unread_block(f, pos, blen, min_body)
                continue
            body = f.read(blen - 8)  # the body and the trailing length word
            if len(body) < blen - 8:
                break
            pos += blen
            self.offset = pos
            packet_head = _PACKET_HEADS[e].get(btype)
            if packet_head is not None:  # EPB, PB (per packet: kept inline, the replay's loop)
                iface, hi, lo, caplen = packet_head.unpack_from(body, 0)
                if iface >= len(interfaces):
                    self.stats.rejected["unknown_interface"] += 1
                    continue
                linktype, units, offset = interfaces[iface]
                ticks = (hi << 32) | lo
                ts_ns = ticks * 1_000_000_000 // units + offset * 1_000_000_000
                if not MIN_TIMESTAMP_NS <= ts_ns <= MAX_TIMESTAMP_NS:
                    raise PcapError(
                        _overflow(self.name, self.stats.records + 1, pos - blen, ticks, units, offset)
                    )
                self.stats.records += 1
                yield CapturedPacket(ts_ns, iface, linktype, body[20 : min(20 + caplen, n)])
            elif btype == IDB:
                interfaces.append(_interface(body, n, e))
            elif not interfaces:  # SPB
                self.stats.rejected["unknown_interface"] += 1
            else:
                self.stats.events["no_timestamp"] += 1
                self.stats.records += 1
                yield CapturedPacket(0, 0, interfaces[0][0], body[4:n])
        if pos != size:
            self._truncated_tail(f, pos)

    def _byte_order(self, bom: bytes, pos: int) -> str:
        """The struct byte order (``<`` or ``>``) of the section whose header is at ``pos``."""
        if bom == BYTE_ORDER_LE:
            return "<"
        if bom == BYTE_ORDER_BE:
            return ">"
        raise PcapError(f"{self.name}: offset {pos}: bad byte-order magic {bom.hex()}")

    def _unread_block(self, f: BinaryIO, pos: int, blen: int, min_body: int | None) -> int:
        """A block at ``pos`` not read: a malformed length (:class:`PcapError`), one past the end
        of the file (the capture was cut short: counted, skipped to the end), a type the reader
        has no use for, or a damaged length (counted); returns where the next block starts (the
        end of the file after a cut)."""
        if blen < 12 or blen % 4:
            raise PcapError(
                f"{self.name}: offset {pos}: block length {blen} (expected a multiple of 4, >= 12)"
            )
        if pos + blen > self.size:
            self._truncated_tail(f, pos)
            return self.size
        n = blen - 12
        if min_body is not None:  # a damaged length: skip the block, count it
            self.stats.rejected["short_block" if n < min_body else "oversized_block"] += 1
        self._skip_to(f, pos + blen)
        return pos + blen

    def _truncated_tail(self, f: BinaryIO, pos: int) -> None:
        """The capture ends with an incomplete block or record at ``pos``: counted, skipped."""
        self.stats.rejected["truncated"] += 1
        self.stats.skipped_bytes += self.size - pos
        self._skip_to(f, self.size)

    # -- classic pcap --------------------------------------------------------------------------
    def _pcap(self, f: BinaryIO, magic: bytes) -> Iterator[CapturedPacket]:
        size = self.size
        if size < 24:
            raise PcapError(f"{self.name}: pcap header needs 24 bytes, file has {size}")
        e = "<" if magic in (b"\xd4\xc3\xb2\xa1", b"\x4d\x3c\xb2\xa1") else ">"
        nano = magic in (b"\x4d\x3c\xb2\xa1", b"\xa1\xb2\x3c\x4d")
        linktype = struct.unpack_from(e + "I", f.read(20), 16)[0] & 0x0FFFFFFF
        record = struct.Struct(e + "IIII")
        pos = self.offset = 24
        while pos + 16 <= size:
            head = f.read(16)
            if len(head) < 16:  # the file shrank under us
                break
            sec, frac, caplen, _orig = record.unpack(head)
            if pos + 16 + caplen > size:
                break
            pos += 16 + caplen
            if caplen > MAX_BLOCK:
                self.stats.rejected["oversized_block"] += 1
                self._skip_to(f, pos)
                continue
            data = f.read(caplen)
            if len(data) < caplen:
                pos -= 16 + caplen
                break
            self.offset = pos
            ts = sec * 1_000_000_000 + (frac if nano else frac * 1000)
            self.stats.records += 1
            yield CapturedPacket(ts, 0, linktype, data)
        if pos != size:
            self._truncated_tail(f, pos)


def _interface(body: bytes, n: int, e: str) -> tuple[int, int, int]:
    """An interface description block's (link type, timestamp units per second, offset in s):
    ``if_tsresol`` (a power of 10, or of 2 with the high bit) and ``if_tsoffset`` options."""
    linktype = struct.unpack_from(e + "H", body, 0)[0]
    units, offset = 1_000_000, 0
    for code, value in _options(body[8:n], e):
        if code == 9 and value:
            v = value[0]
            units = 2 ** (v & 0x7F) if v & 0x80 else 10**v
        elif code == 14 and len(value) == 8:
            offset = struct.unpack(e + "q", value)[0]
    return linktype, units, offset


def _overflow(name: str, packet: int, offset: int, ticks: int, units: int, offset_s: int) -> str:
    """The one-line reason a pcapng packet's timestamp cannot be a 64-bit ns stamp."""
    tail = f" + if_tsoffset {offset_s} s" if offset_s else ""
    return (
        f"{name}: packet {packet} at offset {offset}: timestamp {ticks} ticks at {units} per s{tail} "
        f"is {ticks // units + offset_s} s since 1970, beyond 64-bit nanoseconds (year 2262): "
        "a damaged block or a wrong if_tsresol"
    )


def _options(raw: bytes, e: str) -> Iterator[tuple[int, bytes]]:
    pos = 0
    while pos + 4 <= len(raw):
        code, length = struct.unpack_from(e + "HH", raw, pos)
        if code == 0:
            return
        yield code, raw[pos + 4 : pos + 4 + length]
        pos += 4 + ((length + 3) & ~3)


def _ip_payload(pkt: CapturedPacket) -> tuple[int, bytes] | str:
    """(IP version, IP packet) or a reason string."""
    d, lt = pkt.data, pkt.linktype
    if lt == LINKTYPE_ETHERNET:
        if len(d) < 14:
            return "short_frame"
        etype, pos = struct.unpack_from(">H", d, 12)[0], 14
        while etype in (0x8100, 0x88A8) and len(d) >= pos + 4:
            etype, pos = struct.unpack_from(">H", d, pos + 2)[0], pos + 4
    elif lt in (LINKTYPE_NULL, LINKTYPE_LOOP):
        if len(d) < 4:
            return "short_frame"
        fam = struct.unpack_from("<I" if lt == LINKTYPE_NULL and d[0] else ">I", d, 0)[0]
        etype, pos = (0x0800 if fam == 2 else 0x86DD if fam in (10, 24, 28, 30) else 0), 4
    elif lt == LINKTYPE_LINUX_SLL:
        if len(d) < 16:
            return "short_frame"
        etype, pos = struct.unpack_from(">H", d, 14)[0], 16
    elif lt == LINKTYPE_LINUX_SLL2:
        if len(d) < 20:
            return "short_frame"
        etype, pos = struct.unpack_from(">H", d, 0)[0], 20
    elif lt in (LINKTYPE_RAW, LINKTYPE_IPV4, LINKTYPE_IPV6):
        etype, pos = (0x0800 if d[:1] and d[0] >> 4 == 4 else 0x86DD), 0
    else:
        return f"linktype_{lt}"
    version = _IP_VERSIONS.get(etype)
    return "not_ip" if version is None else (version, d[pos:])


def udp_datagrams(
    packets: Iterable[CapturedPacket], port: int | None = None, stats: DecoderStats | None = None
) -> Iterator[UdpDatagram]:
    """The UDP datagrams among ``packets`` (to or from ``port`` when given), capture stamps kept.

    Packets that are not UDP are counted in ``stats.events`` by reason.
    """
    stats = stats if stats is not None else DecoderStats()
    for pkt in packets:
        ip = _ip_payload(pkt)
        if isinstance(ip, str):
            stats.events[ip] += 1
            continue
        version, d = ip
        if version == 4:
            if len(d) < 20:
                stats.events["short_ip"] += 1
                continue
            ihl = (d[0] & 0x0F) * 4
            total, frag, proto = struct.unpack_from(">H", d, 2)[0], struct.unpack_from(">H", d, 6)[0], d[9]
            if frag & 0x3FFF:  # more-fragments flag or a fragment offset
                stats.events["ip_fragment"] += 1
                continue
            src, dst = _ntop(_AF_INET, d[12:16]), _ntop(_AF_INET, d[16:20])  # as IPv4Address's str
            udp = d[ihl:total] if total else d[ihl:]
        else:
            if len(d) < 40:
                stats.events["short_ip"] += 1
                continue
            proto = d[6]
            src, dst = str(ipaddress.IPv6Address(d[8:24])), str(ipaddress.IPv6Address(d[24:40]))
            plen = struct.unpack_from(">H", d, 4)[0]
            udp = d[40 : 40 + plen]
        if proto != 17:
            stats.events["not_udp"] += 1
            continue
        if len(udp) < 8:
            stats.events["short_udp"] += 1
            continue
        sport, dport, ulen = struct.unpack_from(">HHH", udp, 0)
        if port is not None and port not in (sport, dport):
            stats.events["other_port"] += 1
            continue
        payload = udp[8:ulen] if 8 <= ulen <= len(udp) else udp[8:]
        stats.records += 1
        yield UdpDatagram(pkt.timestamp_ns, (src, sport), (dst, dport), payload)
