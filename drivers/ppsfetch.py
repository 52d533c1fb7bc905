"""The RFC 2783 kernel PPS ABI (``<linux/pps.h>``, 64-bit): the ``PPS_FETCH`` ioctl's request
number and its ``struct pps_fdata`` buffer, packed and unpacked (used by
:class:`drivers.pps.KernelPpsSource` and ``mls doctor``)."""

from __future__ import annotations

import struct
from dataclasses import dataclass

NS_PER_S = 1_000_000_000


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
