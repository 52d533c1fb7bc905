"""Profile reassembly from profiler datagrams, with loss/reorder/duplicate accounting.

:class:`ProfileAssembler` is sans-I/O: ``feed(datagram, host_ns) -> list[Profile]``. Profiles
are emitted in counter order: as soon as all their packets are in, or — incomplete, with the
points they have — once a profile ``window`` counters newer has been seen (so a packet reordered
across a profile boundary still finds its profile). Counters (``stats``):

- ``rejected[reason]``: datagrams the codec refused (``bad_crc``, ``bad_magic``, ``short``, ...)
  and ``inconsistent_count`` (a packet disagreeing with its profile's packet count);
- ``events['duplicate']``: a packet already received (same profile, same index);
- ``events['reordered']``: a packet that arrived after a later one (lower index in its profile,
  or an older profile than one already open);
- ``events['late']``: a packet for a profile already emitted incomplete (dropped);
- ``events['packets_lost']``: packets missing from emitted profiles;
- ``events['profiles_lost']``: profile counters never seen at all;
- ``events['counter_reset']``: the counter jumped back (a scanner restart): state is reset.

Profile counters are u32 and compared with serial-number arithmetic, so wrapping is fine.
"""

from __future__ import annotations

from collections import deque

import numpy as np

from drivers.base import DecoderStats, DriverError
from drivers.zf.codec import Packet, Profile, ProfileCodec
from drivers.zf.zfp1 import RANGE_UNIT_M, ZFP1

_HALF = 1 << 31
_RESET_BACK = 1000  # a jump back by more than this many profiles is a restart, not reordering
_UDEG_TO_RAD = np.pi / 180e6


def _diff(a: int, b: int) -> int:
    """a − b for u32 counters (serial-number arithmetic)."""
    return ((a - b + _HALF) & 0xFFFFFFFF) - _HALF


class _Partial:
    __slots__ = ("packets", "count", "host_ns", "max_index")

    def __init__(self, count: int, host_ns: int | None) -> None:
        self.packets: dict[int, Packet] = {}
        self.count = count
        self.host_ns = host_ns
        self.max_index = -1


def build_profile(counter: int, packets: list[Packet], packet_count: int, host_ns: int | None) -> Profile:
    """Concatenate packets (sorted by index) into one :class:`Profile` with per-point arrays."""
    first = packets[0]
    dt, da = first.dt_ns, first.dangle_udeg
    uniform = True
    start = 0
    for p in packets:  # the usual case: contiguous packets of one evenly spaced line
        if p.dt_ns != dt or p.dangle_udeg != da or p.t0_ns != first.t0_ns + start * dt or (
            p.angle0_udeg != first.angle0_udeg + start * da
        ):
            uniform = False
            break
        start += p.n_points
    if uniform:
        local = np.arange(start, dtype=np.int64)
        gps = first.t0_ns + local * dt
        ang = (first.angle0_udeg + local * da) * _UDEG_TO_RAD
    else:
        k = len(packets)
        ns = np.fromiter((p.n_points for p in packets), dtype=np.int64, count=k)
        local = np.arange(int(ns.sum()), dtype=np.int64) - np.repeat(np.cumsum(ns) - ns, ns)

        def per_point(attr: str) -> np.ndarray:
            return np.repeat(np.fromiter((getattr(p, attr) for p in packets), dtype=np.int64, count=k), ns)

        gps = per_point("t0_ns") + local * per_point("dt_ns")
        ang = (per_point("angle0_udeg") + local * per_point("dangle_udeg")) * _UDEG_TO_RAD
    if len(packets) == 1:
        r01, inten = first.range_01mm, first.intensity
    else:
        r01 = np.concatenate([p.range_01mm for p in packets])
        inten = np.concatenate([p.intensity for p in packets])
    rng = r01 * RANGE_UNIT_M
    rng[r01 == 0] = np.nan
    return Profile(
        profile_counter=counter,
        gps_ns=gps,
        scan_angle_rad=ang,
        range_m=rng,
        intensity=np.array(inten, dtype=np.uint16),
        pps_locked=all(p.pps_locked for p in packets),
        time_valid=all(p.time_valid for p in packets),
        packets_received=len(packets),
        packet_count=packet_count,
        host_ns=host_ns,
    )


class ProfileAssembler:
    """Datagrams → :class:`Profile` (see the module docstring). Never raises on bad datagrams."""

    def __init__(self, codec: ProfileCodec = ZFP1, window: int = 2) -> None:
        self.codec = codec
        self.window = max(1, int(window))
        self.stats = DecoderStats()
        self._open: dict[int, _Partial] = {}
        self._last: int | None = None  # counter of the last emitted profile
        self._newest: int | None = None
        self._complete_recent: deque[int] = deque(maxlen=8)

    def feed(self, data: bytes, host_ns: int | None = None) -> list[Profile]:
        stats = self.stats
        stats.bytes_in += len(data)
        try:
            p = self.codec.decode_packet(data)
        except DriverError as exc:
            stats.rejected[getattr(exc, "reason", "invalid")] += 1
            return []
        c = p.profile_counter
        out: list[Profile] = []
        if self._newest is not None and _diff(c, self._newest) < -_RESET_BACK:
            stats.events["counter_reset"] += 1
            out.extend(self.flush())
            self._last = self._newest = None
        if self._last is not None and _diff(c, self._last) <= 0:
            stats.events["duplicate" if c in self._complete_recent else "late"] += 1
            return out
        part = self._open.get(c)
        if part is None:
            if self._newest is not None and _diff(c, self._newest) < 0:
                stats.events["reordered"] += 1
            part = self._open[c] = _Partial(p.packet_count, host_ns)
        elif p.packet_count != part.count:
            stats.rejected["inconsistent_count"] += 1
            return out
        idx = p.packet_index
        if idx in part.packets:
            stats.events["duplicate"] += 1
            return out
        if idx < part.max_index:
            stats.events["reordered"] += 1
        else:
            part.max_index = idx
        part.packets[idx] = p
        if self._newest is None or _diff(c, self._newest) > 0:
            self._newest = c
        out.extend(self._emit_ready())
        return out

    def flush(self) -> list[Profile]:
        """Emit every open profile (incomplete ones with what they have)."""
        out = []
        for c in sorted(self._open, key=lambda k: _diff(k, self._newest if self._newest is not None else k)):
            out.append(self._emit(c))
        return out

    def _emit_ready(self) -> list[Profile]:
        if len(self._open) == 1:  # fast path: one profile in flight
            c, part = next(iter(self._open.items()))
            if len(part.packets) == part.count:
                return [self._emit(c)]
            return []
        out = []
        while self._open:
            oldest = min(self._open, key=lambda k: _diff(k, self._newest))
            part = self._open[oldest]
            if len(part.packets) == part.count or _diff(self._newest, oldest) >= self.window:
                out.append(self._emit(oldest))
            else:
                break
        return out

    def _emit(self, c: int) -> Profile:
        part = self._open.pop(c)
        stats = self.stats
        if self._last is not None and _diff(c, self._last) > 1:
            stats.events["profiles_lost"] += _diff(c, self._last) - 1
        self._last = c
        missing = part.count - len(part.packets)
        if missing:
            stats.events["packets_lost"] += missing
        else:
            self._complete_recent.append(c)
        packets = [part.packets[i] for i in sorted(part.packets)]
        stats.records += 1
        return build_profile(c, packets, part.count, part.host_ns)
