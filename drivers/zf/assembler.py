"""Profile reassembly from profiler datagrams, with loss/reorder/duplicate accounting.

:class:`ProfileAssembler` is sans-I/O: ``feed(datagram, host_ns) -> list[Profile]``. Profiles
are emitted in counter order: as soon as all their packets are in, or — incomplete, with the
points they have — once a profile ``window`` counters newer has been seen (so a packet reordered
across a profile boundary still finds its profile). ``feed_assembled``/``flush_assembled`` emit
the same profiles as :class:`AssembledProfile` (the packets, arrays not built yet: the daemon's
hot path builds them only when a consumer wants the points), and ``feed_batch`` a burst of
datagrams at once (the same profiles and counters, with array operations for the usual burst).
Counters (``stats``):

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
from collections.abc import Callable
from typing import cast

import numpy as np

from drivers.base import DecoderStats, DriverError
from drivers.zf.codec import FLAG_PPS_LOCKED, FLAG_TIME_VALID, Packet, Profile, ProfileCodec
from drivers.zf.zfp1 import RANGE_UNIT_M, ZFP1

_HALF = 1 << 31
_RESET_BACK = 1000  # a jump back by more than this many profiles is a restart, not reordering
_UDEG_TO_RAD = np.pi / 180e6
_SYNCED = FLAG_PPS_LOCKED | FLAG_TIME_VALID


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
        h = np.array(
            [(p.t0_ns, p.dt_ns, p.angle0_udeg, p.dangle_udeg, p.range_01mm.shape[0]) for p in packets],
            dtype=np.int64,
        )
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


def _summary(packets: list[Packet]) -> tuple[int, int | None]:
    """(AND of the packets' flags, t0 of the first packet with points: None when none has any)."""
    flags = 0xFFFF
    for p in packets:
        flags &= p.flags
    return flags, next((p.t0_ns for p in packets if p.range_01mm.shape[0]), None)


class AssembledProfile:
    """A profile's packets (in index order) before its per-point arrays are built: what the
    daemon needs of every profile (counter, flags, first time tag) at the cost of none of the
    arrays; :meth:`build` makes the :class:`Profile` for those who want the points.

    From the assembler's batch path the packets are still datagrams (``decode`` decodes them
    when :attr:`packets` is first read) and ``summary`` gives (the AND of their flags, the t0 of
    the first packet with points) without decoding them."""

    __slots__ = ("profile_counter", "packet_count", "host_ns", "_items", "_decode", "_summary")

    def __init__(
        self,
        counter: int,
        packets: list,
        packet_count: int,
        host_ns: int | None,
        decode: Callable[[bytes], Packet] | None = None,
        summary: tuple[int, int | None] | None = None,
    ) -> None:
        self.profile_counter = counter
        self.packet_count = packet_count
        self.host_ns = host_ns
        self._items = packets
        self._decode = decode
        self._summary = summary

    @property
    def packets(self) -> list[Packet]:
        if self._decode is not None:
            decode = self._decode
            self._items = [x if isinstance(x, Packet) else decode(x) for x in self._items]
            self._decode = None
        return self._items

    @property
    def packets_received(self) -> int:
        return len(self._items)

    @property
    def summary(self) -> tuple[int, int | None]:
        """(AND of the packets' flags, t0 of the first packet with points)."""
        if self._summary is None:
            self._summary = _summary(self.packets)
        return self._summary

    @property
    def t0_ns(self) -> int | None:
        """GPS ns of the first point received (None: no points), ``Profile.gps_ns[0]``."""
        return self.summary[1]

    @property
    def pps_locked(self) -> bool:
        return bool(self.summary[0] & FLAG_PPS_LOCKED)

    @property
    def time_valid(self) -> bool:
        return bool(self.summary[0] & FLAG_TIME_VALID)

    def build(self) -> Profile:
        return build_profile(self.profile_counter, self.packets, self.packet_count, self.host_ns)


class _Run:
    """The profile in flight on the batch path: its packets 0…n−1 so far, in order (datagrams,
    or Packets taken over from the one-by-one path), the AND of their flags and the t0 of the
    first one with points."""

    __slots__ = ("counter", "count", "host_ns", "items", "flags", "t0_ns")

    def __init__(
        self, counter: int, count: int, host_ns: int | None, items: list, flags: int, t0_ns: int | None
    ) -> None:
        self.counter, self.count, self.host_ns = counter, count, host_ns
        self.items, self.flags, self.t0_ns = items, flags, t0_ns


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
        self._scan = getattr(codec, "scan_packets", None)  # optional: a batch's headers at once
        self._run: _Run | None = None  # the profile in flight, when the batch path has it
        self.last_packet: Packet | None = None  # the last datagram fed, decoded (None: rejected)

    def feed(self, data: bytes, host_ns: int | None = None) -> list[Profile]:
        return [a.build() for a in self.feed_assembled(data, host_ns)]

    def flush(self) -> list[Profile]:
        """Emit every open profile (incomplete ones with what they have)."""
        return [a.build() for a in self.flush_assembled()]

    def feed_assembled(self, data: bytes, host_ns: int | None = None) -> list[AssembledProfile]:
        """:meth:`feed` without building the per-point arrays (:meth:`AssembledProfile.build`)."""
        if self._run is not None:
            self._take_back_run(self._run)
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
        if (
            part is not None
            and p.packet_index == part.max_index + 1
            and p.packet_count == part.count
            and len(self._open) == 1
        ):  # the usual case: the next packet of the one profile in flight
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
        if self._run is not None:
            self._take_back_run(self._run)
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
        newest = cast(int, self._newest)  # set by feed_assembled before it calls here
        while self._open:
            oldest = min(self._open, key=lambda k: _diff(k, newest))
            part = self._open[oldest]
            if len(part.packets) == part.count or _diff(newest, oldest) >= self.window:
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

    # -- the batch path --------------------------------------------------------------------------

    def feed_batch(
        self, datagrams: list[bytes], host_ns: list[int]
    ) -> tuple[list[AssembledProfile], list[int | None]]:
        """:meth:`feed_assembled` over a batch, in order, and each datagram's device time tag (its
        t0 when PPS-locked and time-valid; None otherwise or when rejected).

        The usual batch — every datagram a valid packet (the codec's ``scan_packets``), each the
        next packet of the profile in flight or the first of the next profile — is handled with
        a few array operations and no per-datagram decoding; the profiles, counters and
        :attr:`last_packet` are those of feeding the datagrams one by one, which is what any
        other batch gets."""
        heads = self._scan(datagrams) if self._scan is not None and datagrams else None
        done = self._feed_run(datagrams, host_ns, heads) if heads is not None else None
        if done is not None:
            return done
        profiles: list[AssembledProfile] = []
        tags: list[int | None] = []
        for data, t in zip(datagrams, host_ns, strict=False):
            profiles += self.feed_assembled(data, t)
            p = self.last_packet
            tags.append(p.t0_ns if p is not None and p.flags & _SYNCED == _SYNCED else None)
        return profiles, tags

    def _run_start(self) -> tuple[int, int | None, int] | None:
        """(counter, packet count or None for a new profile, index) the batch path expects next."""
        if self._run is not None:
            r = self._run
            return r.counter, r.count, len(r.items)
        if not self._open:
            if self._last is None or self._newest != self._last:
                return None
            return (self._last + 1) & 0xFFFFFFFF, None, 0
        if len(self._open) != 1:
            return None
        ((c, part),) = self._open.items()
        if part.max_index != len(part.packets) - 1:  # a hole: one by one
            return None
        return c, part.count, part.max_index + 1

    def _feed_run(self, datagrams: list[bytes], host_ns: list[int], h: np.ndarray):
        start = self._run_start()
        if start is None:
            return None
        c = h["profile_counter"].astype(np.int64)
        i = h["packet_index"].astype(np.int64)
        k = h["packet_count"].astype(np.int64)
        if c[0] != start[0] or i[0] != start[2] or (start[1] is not None and k[0] != start[1]):
            return None
        same = (c[1:] == c[:-1]) & (i[1:] == i[:-1] + 1) & (k[1:] == k[:-1])
        nxt = (i[:-1] == k[:-1] - 1) & (c[1:] == (c[:-1] + 1) & 0xFFFFFFFF) & (i[1:] == 0)
        if not (same | nxt).all():
            return None
        run = self._run
        if run is None and self._open:  # take the profile in flight over from the one-by-one path
            ((c0, part),) = self._open.items()
            del self._open[c0]
            packets = [part.packets[j] for j in range(len(part.packets))]
            run = _Run(c0, part.count, part.host_ns, packets, *_summary(packets))
        stats = self.stats
        stats.bytes_in += sum(map(len, datagrams))
        flags_l, t0_l = h["flags"].tolist(), h["t0_ns"].tolist()
        with_points = np.flatnonzero(h["n_points"]).tolist()
        ends = (np.flatnonzero(i == k - 1) + 1).tolist()
        if not ends or ends[-1] != len(datagrams):
            ends.append(len(datagrams))
        out: list[AssembledProfile] = []
        a, w = 0, 0
        for b in ends:
            if run is None:  # the next profile begins
                run = _Run(int(c[a]), int(k[a]), host_ns[a], [], 0xFFFF, None)
                self._newest = run.counter
            run.items += datagrams[a:b]
            for f in flags_l[a:b]:
                run.flags &= f
            while w < len(with_points) and with_points[w] < a:
                w += 1
            if run.t0_ns is None and w < len(with_points) and with_points[w] < b:
                run.t0_ns = t0_l[with_points[w]]
            if len(run.items) == run.count:
                self._last = run.counter
                self._complete_recent.append(run.counter)
                stats.records += 1
                out.append(
                    AssembledProfile(
                        run.counter, run.items, run.count, run.host_ns, self._decode, (run.flags, run.t0_ns)
                    )
                )
                run = None
            a = b
        self._run = run
        self.last_packet = self._decode(datagrams[-1])
        tags = [t if f & _SYNCED == _SYNCED else None for f, t in zip(flags_l, t0_l, strict=True)]
        return out, tags

    def _take_back_run(self, r: _Run) -> None:
        """The profile in flight (``r``, the batch path's ``_run``) goes back to the one-by-one
        path (decoded)."""
        self._run = None
        part = self._open[r.counter] = _Partial(r.count, r.host_ns)
        decode = self._decode
        part.packets = {j: x if isinstance(x, Packet) else decode(x) for j, x in enumerate(r.items)}
        part.max_index = len(r.items) - 1
