"""ZFP1: the project's documented stand-in for the Z+F profiler packet format (docs/architecture.md §5).

The vendor's format is not public; until its interface document is at hand, profiles travel as
ZFP1 packets, one per UDP datagram, little-endian::

    offset size field
         0    4 magic            b'ZFP1'
         4    2 header_size      u16 = 40
         6    2 flags            u16: bit0 PPS locked, bit1 time valid, bit2 last packet of profile
         8    4 profile_counter  u32 (wraps)
        12    2 packet_index     u16 (0-based within the profile)
        14    2 packet_count     u16 (packets in this profile)
        16    8 t0_ns            i64 GPS ns of this packet's first point
        24    4 dt_ns            u32 point period
        28    4 angle0_udeg      i32 scan angle of the first point, micro-degrees
        32    4 dangle_udeg      i32 angle step per point, micro-degrees
        36    2 n_points         u16
        38    2 reserved         u16 = 0
        40  6·n points           n × (range u32 in 0.1 mm, 0 = no return; intensity u16)
    40+6n   4 crc32            zlib CRC-32 of everything before it

Point i of a packet was measured at ``t0_ns + i·dt_ns`` at scan angle
``angle0_udeg + i·dangle_udeg``. :func:`decode_packet` returns a :class:`Packet` whose point
arrays are numpy views made with ``numpy.frombuffer`` (no copy); :func:`encode_profile` splits a
profile into packets whose payload fits ``max_payload`` bytes (default 1400, below an Ethernet
MTU). :data:`ZFP1` bundles both as a :class:`~drivers.zf.codec.ProfileCodec`, the seam where the
vendor's format will plug in; its ``encode_profile`` takes a :class:`~drivers.zf.codec.Profile`
(points evenly spaced in time and angle, as the scanner produces them).
"""

from __future__ import annotations

import struct
import zlib

import numpy as np

from drivers.base import DriverError
from drivers.zf.codec import FLAG_LAST, FLAG_PPS_LOCKED, FLAG_TIME_VALID, Packet, Profile

MAGIC = b"ZFP1"
HEADER = struct.Struct("<4sHHIHHqIiiHH")
HEADER_SIZE = HEADER.size  # 40
POINT_DTYPE = np.dtype([("range_01mm", "<u4"), ("intensity", "<u2")])
POINT_SIZE = POINT_DTYPE.itemsize  # 6
CRC_SIZE = 4
DEFAULT_MAX_PAYLOAD = 1400
RANGE_UNIT_M = 1e-4
MAX_RANGE_01MM = 0xFFFFFFFF


class ZfpError(DriverError):
    """A datagram that is not a valid ZFP1 packet; ``reason`` is the counter key."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


def parse_header(data: bytes) -> tuple:
    """Validate a datagram and return its raw header tuple (the assembler's fast path).

    Raises :class:`ZfpError` with a reason: ``short``, ``bad_magic``, ``bad_header_size``,
    ``size_mismatch``, ``bad_crc``, ``bad_index``.
    """
    n = len(data)
    if n < HEADER_SIZE + CRC_SIZE:
        raise ZfpError(
            "short", f"ZFP1 datagram of {n} bytes: a packet needs at least {HEADER_SIZE + CRC_SIZE}"
        )
    h = HEADER.unpack_from(data, 0)
    if h[0] != MAGIC:
        raise ZfpError("bad_magic", f"ZFP1 magic {h[0]!r}: expected {MAGIC!r}")
    if h[1] != HEADER_SIZE:
        raise ZfpError("bad_header_size", f"ZFP1 header_size {h[1]}: expected {HEADER_SIZE}")
    if n != HEADER_SIZE + POINT_SIZE * h[10] + CRC_SIZE:
        raise ZfpError(
            "size_mismatch",
            f"ZFP1 n_points {h[10]} needs {HEADER_SIZE + POINT_SIZE * h[10] + CRC_SIZE} bytes, datagram has {n}",
        )
    if zlib.crc32(memoryview(data)[: n - CRC_SIZE]) != int.from_bytes(data[n - CRC_SIZE :], "little"):
        raise ZfpError("bad_crc", "ZFP1 CRC-32 mismatch")
    if h[5] == 0 or h[4] >= h[5]:
        raise ZfpError("bad_index", f"ZFP1 packet_index {h[4]} of packet_count {h[5]}")
    return h


HEADER_DTYPE = np.dtype(
    [
        ("magic", "S4"),
        ("header_size", "<u2"),
        ("flags", "<u2"),
        ("profile_counter", "<u4"),
        ("packet_index", "<u2"),
        ("packet_count", "<u2"),
        ("t0_ns", "<i8"),
        ("dt_ns", "<u4"),
        ("angle0_udeg", "<i4"),
        ("dangle_udeg", "<i4"),
        ("n_points", "<u2"),
        ("reserved", "<u2"),
    ]
)
#: zlib.crc32 of a packet *with* its little-endian CRC-32 appended, whatever the packet: the check
#: needs no slicing
CRC_RESIDUE = 0x2144DF1C


def scan_packets(datagrams: list[bytes]) -> np.ndarray | None:
    """The headers of a batch of datagrams as one :data:`HEADER_DTYPE` array when every one is a
    valid packet (what :func:`parse_header` accepts), None as soon as one is not (decode them one
    by one to learn which and why): the assembler's batch path, a few numpy operations instead
    of a header parse per datagram."""
    n = len(datagrams)
    if n == 0:
        return None
    lens = np.fromiter(map(len, datagrams), np.int64, n)
    if lens.min() < HEADER_SIZE + CRC_SIZE:
        return None
    if (np.fromiter(map(zlib.crc32, datagrams), np.uint32, n) != CRC_RESIDUE).any():
        return None
    h = np.frombuffer(b"".join([d[:HEADER_SIZE] for d in datagrams]), HEADER_DTYPE)
    ok = (h["magic"] == MAGIC) & (h["header_size"] == HEADER_SIZE) & (h["packet_index"] < h["packet_count"])
    ok &= lens == HEADER_SIZE + CRC_SIZE + POINT_SIZE * h["n_points"].astype(np.int64)
    return h if ok.all() else None


def decode_packet(data: bytes) -> Packet:
    """One datagram → :class:`Packet` (raises :class:`ZfpError` on anything invalid)."""
    h = parse_header(data)
    pts = np.frombuffer(data, dtype=POINT_DTYPE, count=h[10], offset=HEADER_SIZE)
    return Packet(h[2], h[3], h[4], h[5], h[6], h[7], h[8], h[9], pts["range_01mm"], pts["intensity"])


def encode_packet(
    *,
    flags: int,
    profile_counter: int,
    packet_index: int,
    packet_count: int,
    t0_ns: int,
    dt_ns: int,
    angle0_udeg: int,
    dangle_udeg: int,
    range_01mm: np.ndarray,
    intensity: np.ndarray,
) -> bytes:
    n = len(range_01mm)
    if n != len(intensity) or n > 0xFFFF:
        raise DriverError(
            f"ZFP1 packet: {n} ranges and {len(intensity)} intensities (expected equal, <= 65535)"
        )
    pts = np.empty(n, dtype=POINT_DTYPE)
    pts["range_01mm"] = range_01mm
    pts["intensity"] = intensity
    return pack_packet(
        flags, profile_counter, packet_index, packet_count, t0_ns, dt_ns, angle0_udeg, dangle_udeg, pts
    )


def pack_packet(
    flags: int,
    profile_counter: int,
    packet_index: int,
    packet_count: int,
    t0_ns: int,
    dt_ns: int,
    angle0_udeg: int,
    dangle_udeg: int,
    points: np.ndarray,
) -> bytes:
    """:func:`encode_packet` for points already in :data:`POINT_DTYPE` (at most 65535; an
    emulator slices one profile-long array instead of building one per packet)."""
    head = HEADER.pack(
        MAGIC,
        HEADER_SIZE,
        flags & 0xFFFF,
        profile_counter & 0xFFFFFFFF,
        packet_index,
        packet_count,
        t0_ns,
        dt_ns,
        angle0_udeg,
        dangle_udeg,
        len(points),
        0,
    )
    body = head + points.tobytes()
    return body + zlib.crc32(body).to_bytes(4, "little")


def points_per_packet(max_payload: int = DEFAULT_MAX_PAYLOAD) -> int:
    n = (max_payload - HEADER_SIZE - CRC_SIZE) // POINT_SIZE
    if n < 1:
        raise DriverError(
            f"ZFP1 max_payload {max_payload}: must be at least {HEADER_SIZE + CRC_SIZE + POINT_SIZE} bytes"
        )
    return min(n, 0xFFFF)


def encode_profile(
    profile_counter: int,
    t0_ns: int,
    dt_ns: int,
    angle0_udeg: int,
    dangle_udeg: int,
    range_01mm,
    intensity,
    *,
    pps_locked: bool = True,
    time_valid: bool = True,
    max_payload: int = DEFAULT_MAX_PAYLOAD,
) -> list[bytes]:
    """Split one profile (points evenly spaced in time and angle) into ZFP1 datagrams.

    ``range_01mm`` (uint32, 0.1 mm, 0 = no return) and ``intensity`` (uint16) are per point;
    each packet's ``t0_ns``/``angle0_udeg`` are those of its own first point.
    """
    ranges = np.asarray(range_01mm, dtype=np.uint32)
    inten = np.asarray(intensity, dtype=np.uint16)
    if ranges.shape != inten.shape or ranges.ndim != 1:
        raise DriverError(
            f"ZFP1 profile: ranges {ranges.shape} and intensities {inten.shape} must be equal 1-D arrays"
        )
    per = points_per_packet(max_payload)
    count = max(1, -(-ranges.size // per))
    if count > 0xFFFF:
        raise DriverError(f"ZFP1 profile of {ranges.size} points needs {count} packets (max 65535)")
    base = (FLAG_PPS_LOCKED if pps_locked else 0) | (FLAG_TIME_VALID if time_valid else 0)
    out = []
    for k in range(count):
        i = k * per
        out.append(
            encode_packet(
                flags=base | (FLAG_LAST if k == count - 1 else 0),
                profile_counter=profile_counter,
                packet_index=k,
                packet_count=count,
                t0_ns=t0_ns + i * dt_ns,
                dt_ns=dt_ns,
                angle0_udeg=angle0_udeg + i * dangle_udeg,
                dangle_udeg=dangle_udeg,
                range_01mm=ranges[i : i + per],
                intensity=inten[i : i + per],
            )
        )
    return out


class Zfp1Codec:
    """ZFP1 behind the :class:`~drivers.zf.codec.ProfileCodec` interface."""

    name = "zfp1"

    def decode_packet(self, data: bytes) -> Packet:
        return decode_packet(data)

    def scan_packets(self, datagrams: list[bytes]) -> np.ndarray | None:
        return scan_packets(datagrams)

    def encode_profile(self, profile: Profile, max_payload: int = DEFAULT_MAX_PAYLOAD) -> list[bytes]:
        """A Profile whose points are evenly spaced in time and angle → datagrams.

        Raises :class:`DriverError` when the spacing is not uniform (within 1 ns and 1 µdeg).
        """
        t = np.asarray(profile.gps_ns, dtype=np.int64)
        a_udeg = np.rint(np.degrees(np.asarray(profile.scan_angle_rad, dtype=np.float64)) * 1e6).astype(
            np.int64
        )
        n = t.size
        dt = int(t[1] - t[0]) if n > 1 else 0
        da = int(a_udeg[1] - a_udeg[0]) if n > 1 else 0
        idx = np.arange(n, dtype=np.int64)
        if n and (
            np.any(np.abs(t - (t[0] + idx * dt)) > 1) or np.any(np.abs(a_udeg - (a_udeg[0] + idx * da)) > 1)
        ):
            raise DriverError(
                f"ZFP1 profile {profile.profile_counter}: points are not evenly spaced in time and angle"
            )
        rng = np.asarray(profile.range_m, dtype=np.float64)
        r01 = np.where(np.isfinite(rng), np.rint(np.nan_to_num(rng) / RANGE_UNIT_M), 0)
        if np.any((r01 < 0) | (r01 > MAX_RANGE_01MM)):
            raise DriverError(
                f"ZFP1 profile {profile.profile_counter}: range outside 0..{MAX_RANGE_01MM * RANGE_UNIT_M:.0f} m"
            )
        return encode_profile(
            profile.profile_counter,
            int(t[0]) if n else 0,
            dt,
            int(a_udeg[0]) if n else 0,
            da,
            r01.astype(np.uint32),
            profile.intensity,
            pps_locked=profile.pps_locked,
            time_valid=profile.time_valid,
            max_payload=max_payload,
        )


ZFP1 = Zfp1Codec()
