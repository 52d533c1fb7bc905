"""Profile reassembly from profiler datagrams, with loss/reorder/duplicate accounting.

:class:`ProfileAssembler` is sans-I/O: ``feed(datagram, host_ns) -> list[Profile]``. Profiles
are emitted in counter order: as soon as all their packets are in, or — incomplete, with the
points they have — once a profile ``window`` counters newer has been seen (so a packet reordered
across a profile boundary still finds its profile). ``feed_assembled``/``flush_assembled`` emit
the same profiles as :class:`AssembledProfile` (the packets, arrays not built yet: the daemon's
hot path builds them only when a consumer wants the points). Counters (``stats``):

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
    k = len(packets)
    if k == 1:
        n = first.n_points
        local = np.arange(n, dtype=np.int64)
        gps = first.t0_ns + local * first.dt_ns
        ang = (first.angle0_udeg + local * first.dangle_udeg) * _UDEG_TO_RAD
        r01, inten = first.range_01mm, first.intensity
    else:
        # per packet: t0, dt, angle0, dangle, n (a scanner's dt is fractional, so each packet
        # carries its own rounded t0 and the points of a profile are not one arithmetic series)
        h = np.array([(p.t0_ns, p.dt_ns, p.angle0_udeg, p.dangle_udeg, p.range_01mm.shape[0]) for p in packets],
                     dtype=np.int64)  # fmt: skip
        ns = h[:, 4]
        local = np.arange(int(ns.sum()), dtype=np.int64) - np.repeat(np.cumsum(ns) - ns, ns)
        if (h[:, 1] == h[0, 1]).all() and (h[:, 3] == h[0, 3]).all():  # one dt, one angle step
            gps = np.repeat(h[:, 0], ns) + local * h[0, 1]
            ang = (np.repeat(h[:, 2], ns) + local * h[0, 3]) * _UDEG_TO_RAD
        else:
            gps = np.repeat(h[:, 0], ns) + local * np.repeat(h[:, 1], ns)
            ang = (np.repeat(h[:, 2], ns) + local * np.repeat(h[:, 3], ns)) * _UDEG_TO_RAD
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
        packets_received=k,
        packet_count=packet_count,
        host_ns=host_ns,
    )


class AssembledProfile:
    """A profile's packets (in index order) before its per-point arrays are built: what the
    daemon needs of every profile (counter, flags, first time tag) at the cost of none of the
    arrays; :meth:`build` makes the :class:`Profile` for those who want the points."""

    __slots__ = ("profile_counter", "packets", "packet_count", "host_ns")

    def __init__(self, counter: int, packets: list[Packet], packet_count: int, host_ns: int | None) -> None:
        self.profile_counter = counter
        self.packets = packets
        self.packet_count = packet_count
        self.host_ns = host_ns

    @property
    def packets_received(self) -> int:
        return len(self.packets)

    @property
    def t0_ns(self) -> int | None:
        """GPS ns of the first point received (None: no points), ``Profile.gps_ns[0]``."""
        return next((p.t0_ns for p in self.packets if p.range_01mm.shape[0]), None)

    @property
    def pps_locked(self) -> bool:
        return all(p.pps_locked for p in self.packets)

    @property
    def time_valid(self) -> bool:
        return all(p.time_valid for p in self.packets)

    def build(self) -> Profile:
        return build_profile(self.profile_counter, self.packets, self.packet_count, self.host_ns)


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
        self._decode = codec.decode_packet
        self.last_packet: Packet | None = None  # the last datagram fed, decoded (None: rejected)

    def feed(self, data: bytes, host_ns: int | None = None) -> list[Profile]:
        return [a.build() for a in self.feed_assembled(data, host_ns)]

    def flush(self) -> list[Profile]:
        """Emit every open profile (incomplete ones with what they have)."""
        return [a.build() for a in self.flush_assembled()]

    def feed_assembled(self, data: bytes, host_ns: int | None = None) -> list[AssembledProfile]:
        """:meth:`feed` without building the per-point arrays (:meth:`AssembledProfile.build`)."""
        stats = self.stats
        stats.bytes_in += len(data)
        try:
            p = self._decode(data)
        except DriverError as exc:
            self.last_packet = None
            stats.rejected[getattr(exc, "reason", "invalid")] += 1
            return []
        self.last_packet = p
        c = p.profile_counter
        part = self._open.get(c)
        if part is not None and p.packet_index == part.max_index + 1 and p.packet_count == part.count \
                and len(self._open) == 1:  # the usual case: the next packet of the one profile in flight
            part.max_index = p.packet_index
            part.packets[p.packet_index] = p
            return [self._emit(c)] if len(part.packets) == part.count else []
        out: list[AssembledProfile] = []
        if self._newest is not None and _diff(c, self._newest) < -_RESET_BACK:
            stats.events["counter_reset"] += 1
            out.extend(self.flush_assembled())
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

    def flush_assembled(self) -> list[AssembledProfile]:
        out = []
        for c in sorted(self._open, key=lambda k: _diff(k, self._newest if self._newest is not None else k)):
            out.append(self._emit(c))
        return out

    def _emit_ready(self) -> list[AssembledProfile]:
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

    def _emit(self, c: int) -> AssembledProfile:
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
        return AssembledProfile(c, packets, part.count, part.host_ns)
