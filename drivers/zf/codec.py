"""The seam between the profiler's packet format and everything else.

:class:`Packet` is one decoded datagram (points evenly spaced in time and angle),
:class:`Profile` one reassembled scan line with per-point arrays, and :class:`ProfileCodec` the
small interface a packet format implements: ``decode_packet(bytes) -> Packet`` (raising
:class:`~drivers.base.DriverError` with a ``reason`` attribute on invalid input) and
``encode_profile(profile, max_payload) -> list[bytes]``, and optionally
``scan_packets(datagrams) -> headers | None`` (a batch's headers as one structured array with the
fields of ZFP1's ``HEADER_DTYPE`` — counter, index, count, flags, t0, n_points —, None when one
datagram is not valid: the assembler's batch path). The project's ZFP1 stand-in
(:mod:`drivers.zf.zfp1`) is one implementation; the vendor's format becomes another, and
:class:`~drivers.zf.assembler.ProfileAssembler` takes either.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

FLAG_PPS_LOCKED, FLAG_TIME_VALID, FLAG_LAST = 1, 2, 4


@dataclass(slots=True)
class Packet:
    flags: int  # bit0 PPS locked, bit1 time valid, bit2 last packet of the profile
    profile_counter: int
    packet_index: int
    packet_count: int
    t0_ns: int  # GPS ns of the first point
    dt_ns: int  # point period
    angle0_udeg: int  # scan angle of the first point, micro-degrees
    dangle_udeg: int  # angle step per point, micro-degrees
    range_01mm: np.ndarray  # uint32, 0.1 mm, 0 = no return
    intensity: np.ndarray  # uint16

    @property
    def n_points(self) -> int:
        return int(self.range_01mm.shape[0])

    @property
    def pps_locked(self) -> bool:
        return bool(self.flags & FLAG_PPS_LOCKED)

    @property
    def time_valid(self) -> bool:
        return bool(self.flags & FLAG_TIME_VALID)

    @property
    def last(self) -> bool:
        return bool(self.flags & FLAG_LAST)


@dataclass(slots=True)
class Profile:
    """One scan line. Arrays are per point, in packet order; a missing packet leaves a gap.

    ``range_m`` is NaN where the scanner had no return; ``scan_angle_rad`` is the raw scanner
    angle α of docs/architecture.md §3 (from +y_S toward +z_S).
    """

    profile_counter: int
    gps_ns: np.ndarray  # int64, GPS ns per point
    scan_angle_rad: np.ndarray  # float64
    range_m: np.ndarray  # float64, NaN = no return
    intensity: np.ndarray  # uint16
    pps_locked: bool = True
    time_valid: bool = True
    packets_received: int = 0
    packet_count: int = 0
    host_ns: int | None = None  # host receive stamp of the first packet received

    @property
    def complete(self) -> bool:
        return self.packets_received == self.packet_count

    @property
    def n_points(self) -> int:
        return int(self.gps_ns.shape[0])


class ProfileCodec(Protocol):
    """A profiler packet format (ZFP1 today, the vendor's format later)."""

    name: str

    def decode_packet(self, data: bytes) -> Packet: ...

    def encode_profile(self, profile: Profile, max_payload: int = 1400) -> list[bytes]: ...
