"""The profiler of ``mls sim session`` (:mod:`office.simsession.record`): the survey's returns cast by the
simulator chunk by chunk and sent as the ZFP1 datagrams the profiler emulator would send.

One profile grid runs through the whole session (the scanner never stops, as on a survey): profile
p starts at ``origin_ns + rint(p·period_ns)``, its slot s is measured at ``+ rint(s·dt_ns)`` at
scan angle ``s·Δα`` (``Δα = 360°/K``), the conventions of :class:`sim_devices.feed.ProfileGrid`.
:class:`LidarStream` casts the rays of about a second of profiles at a time with the simulator's
own :func:`calib.sim.simulate.scan` (the true trajectory and mount; memory stays bounded whatever
the session's length), adds the scanner noise and keeps the measured ranges inside the range
window as :func:`calib.sim.simulate.simulate` does, quantizes as the feed does (0.1 mm, intensity
× 65535) and packs every profile of the chunk into ZFP1 datagrams with a few numpy operations
(:func:`pack_profiles`): the bytes, emission times and host stamps of
:meth:`sim_devices.profiler.ProfilerEmulator.packets` for the same profiles (``tests/cli/
test_sim_session.py`` compares them), without a ``struct.pack`` per packet. Every slot of the
recorded windows is sent (range 0: no return), as a running scanner does.
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field

import numpy as np

from calib.core.frames import gps_ns_to_seconds
from drivers.zf.codec import FLAG_LAST, FLAG_PPS_LOCKED, FLAG_TIME_VALID
from drivers.zf.zfp1 import (
    CRC_SIZE,
    DEFAULT_MAX_PAYLOAD,
    HEADER_DTYPE,
    HEADER_SIZE,
    MAGIC,
    POINT_DTYPE,
    RANGE_UNIT_M,
)
from sim_devices.feed import INTENSITY_FULL_SCALE, NS_PER_S
from sim_devices.profiler import packet_layout

#: profiles cast per chunk: about this many seconds of the scanner
CHUNK_S = 1.0


@dataclass(frozen=True)
class Datagrams:
    """ZFP1 datagrams in emission order and, per profile, its first packet's stamps."""

    payloads: list  # memoryviews of the packed packets (one datagram each)
    host_ns: np.ndarray  # (m,) int64 host receive stamp (truth clock: emission + latency)
    t0_ns: np.ndarray  # (m,) int64 each packet's first point time: the device time tag
    first_packet: np.ndarray  # (P,) index of each profile's first packet
    profile_host_ns: np.ndarray  # (P,) host stamp of each profile's first packet
    profile_t0_ns: np.ndarray  # (P,) time of each profile's first point sent

    def __len__(self) -> int:
        return len(self.payloads)


def _packet_dtype(n_points: int) -> np.dtype:
    return np.dtype([("head", HEADER_DTYPE), ("pts", POINT_DTYPE, (n_points,)), ("crc", "<u4")])


def pack_profiles(
    start_ns: np.ndarray,
    counters: np.ndarray,
    range_01mm: np.ndarray,
    intensity: np.ndarray,
    layout: list[tuple[int, int]],
    dt_ns: float,
    dangle_udeg: float,
    clock,
    latency_ns: int,
) -> Datagrams:
    """ZFP1 datagrams of P profiles (``range_01mm``, ``intensity``: (P, K), 0 = no return),
    profile p starting at ``start_ns[p]`` with counter ``counters[p]``, split as ``layout``
    ((first slot, n points) per packet, :func:`sim_devices.profiler.packet_layout`): the same bytes
    and stamps as :meth:`sim_devices.profiler.ProfilerEmulator.packets` (PPS-locked, time-valid,
    no clock fault), packed per group of equal-length packets with numpy; only the CRC is one
    ``zlib.crc32`` call per packet."""
    start_ns = np.asarray(start_ns, np.int64)
    P, count = start_ns.size, len(layout)
    dt_int, da_int = round(dt_ns), round(dangle_udeg)
    flags = FLAG_TIME_VALID | FLAG_PPS_LOCKED
    views: list = [None] * (P * count)
    t0 = np.empty((P, count), np.int64)
    emit = np.empty((P, count), np.int64)
    groups: dict[int, list[int]] = {}
    for k, (_, n) in enumerate(layout):
        groups.setdefault(n, []).append(k)
    for n, ks in groups.items():
        s0 = np.array([layout[k][0] for k in ks], np.int64)
        arr = np.zeros((P, len(ks)), _packet_dtype(n))
        h = arr["head"]
        h["magic"] = MAGIC
        h["header_size"] = HEADER_SIZE
        h["flags"] = flags | np.where(np.array(ks) == count - 1, FLAG_LAST, 0)[None, :]
        h["profile_counter"] = (np.asarray(counters, np.int64) & 0xFFFFFFFF)[:, None]
        h["packet_index"] = np.array(ks)[None, :]
        h["packet_count"] = count
        first = np.array([round(s * dt_ns) for s in s0.tolist()], np.int64)
        h["t0_ns"] = start_ns[:, None] + first[None, :]
        h["dt_ns"] = dt_int
        h["angle0_udeg"] = np.array([round(s * dangle_udeg) for s in s0.tolist()], np.int64)[None, :]
        h["dangle_udeg"] = da_int
        h["n_points"] = n
        slots = s0[:, None] + np.arange(n)[None, :]
        arr["pts"]["range_01mm"] = range_01mm[:, slots]
        arr["pts"]["intensity"] = intensity[:, slots]
        size = arr.itemsize
        mv = arr.reshape(-1).view(np.uint8).data  # the packets' bytes, as a memoryview
        body = size - CRC_SIZE
        arr["crc"] = np.fromiter(
            (zlib.crc32(mv[i : i + body]) for i in range(0, P * len(ks) * size, size)), np.uint32, P * len(ks)
        ).reshape(P, len(ks))
        ends = np.array([round((layout[k][0] + layout[k][1]) * dt_ns) for k in ks], np.int64)
        t0[:, ks] = h["t0_ns"]
        emit[:, ks] = start_ns[:, None] + ends[None, :]
        for j, k in enumerate(ks):
            for p in range(P):
                off = (p * len(ks) + j) * size
                views[p * count + k] = mv[off : off + size]
    host = clock.host_ns_array(emit.reshape(-1)) + latency_ns
    first_packet = np.arange(P, dtype=np.int64) * count
    return Datagrams(views, host, t0.reshape(-1), first_packet, host[first_packet], t0[:, 0].copy())


@dataclass
class LidarCounts:
    """What the stream sent so far."""

    profiles: int = 0
    packets: int = 0
    points: int = 0  # slots sent (returns and no-returns)
    returns: int = 0  # slots with a range
    per_pass: dict[int, int] = field(default_factory=dict)  # returns inside each pass window
    per_pass_surface: dict[int, np.ndarray] = field(default_factory=dict)  # by scene surface
    per_surface: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # (R,) by scene surface


class LidarStream:
    """The profiler of a session window: ``chunks()`` yields the :class:`Datagrams` of about
    :data:`CHUNK_S` of profiles at a time, in emission order (see the module docstring).

    ``passes``: (pass id, start ns, end ns) windows; the returns whose wire time lies in one
    (ends included, as ``mls export`` counts them) are counted per pass."""

    def __init__(
        self,
        scenario,
        scene,
        trajectory_true,
        mount_true,
        start_ns: int,
        end_ns: int,
        clock,
        seed: int,
        passes: Sequence[tuple[int, int, int]] = (),
        latency_s: float = 0.0005,
        max_payload: int = DEFAULT_MAX_PAYLOAD,
    ) -> None:
        sc = self.scanner = scenario.scanner
        self.noise = scenario.scanner_noise
        self.scene, self.traj, self.mount = scene, trajectory_true, mount_true
        self.clock = clock
        self.rate_hz = float(sc.effective_profile_rate_hz)
        self.K = int(sc.effective_points_per_360)
        self.period_ns = NS_PER_S / self.rate_hz
        self.dt_ns = self.period_ns / self.K
        self.dangle_udeg = 360e6 / self.K
        self.origin_ns = int(start_ns)
        # the profiles wholly inside the window (a float margin keeps the last one honest)
        self.n_profiles = max(math.floor((end_ns - start_ns) / self.period_ns + 1e-9), 0)
        mask = sc.window_mask()
        padded = np.concatenate([[False], mask, [False]]).astype(np.int8)
        edges = np.flatnonzero(np.diff(padded))
        self.runs = tuple((int(a), int(b)) for a, b in zip(edges[::2], edges[1::2], strict=True))
        self.layout = packet_layout(self.runs, max_payload)
        self.first_slot = np.zeros(self.K, np.int64)  # the first slot of the packet of each slot
        for s0, n in self.layout:
            self.first_slot[s0 : s0 + n] = s0
        self.latency_ns = round(latency_s * NS_PER_S)
        self.rng = np.random.default_rng([seed, 5])
        self.passes = sorted(passes, key=lambda w: w[1])
        self.chunk_profiles = max(1, round(CHUNK_S * self.rate_hz))
        self.counts = LidarCounts(per_surface=np.zeros(len(scene), np.int64))
        for pid, _, _ in self.passes:
            self.counts.per_pass[pid] = 0
            self.counts.per_pass_surface[pid] = np.zeros(len(scene), np.int64)

    @property
    def points_per_profile(self) -> int:
        return sum(n for _, n in self.layout)

    @property
    def end_ns(self) -> int:
        """The time the last profile ends."""
        return self.origin_ns + round(self.n_profiles * self.period_ns)

    def start_ns(self, profiles: np.ndarray) -> np.ndarray:
        return self.origin_ns + np.rint(np.asarray(profiles, np.int64) * self.period_ns).astype(np.int64)

    def chunks(self) -> Iterator[Datagrams]:
        for pa in range(0, self.n_profiles, self.chunk_profiles):
            yield self.chunk(pa, min(pa + self.chunk_profiles, self.n_profiles))

    def chunk(self, pa: int, pb: int) -> Datagrams:
        """The datagrams of profiles [pa, pb)."""
        from calib.sim.simulate import scan

        n, K = pb - pa, self.K
        p_idx = np.arange(pa, pb, dtype=np.int64)
        start = self.start_ns(p_idx)
        t_a = float(gps_ns_to_seconds(int(start[0])))
        rate = self.rate_hz
        ret = scan(self.scanner, self.scene, self.traj, self.mount, t_a, t_a + (n + 0.5) / rate)
        # the grid position of each return: its slot from the encoder angle, its profile from its time
        d_alpha = 2.0 * np.pi / K
        slot = np.rint(ret.alpha_rad / d_alpha).astype(np.int64) % K
        j = (ret.t_gps_s - t_a) * (rate * K)
        prof = np.rint((j - slot) / K).astype(np.int64)
        # the noise and the recording window, as calib.sim.simulate.simulate applies them
        d_range, _ = self.noise.draw(ret.range_true_m, ret.cos_incidence, self.rng)
        measured_m = ret.range_true_m - self.mount.range_offset_m + d_range
        sc = self.scanner
        keep = (measured_m >= sc.min_range_m) & (measured_m <= sc.max_range_m) & (prof >= 0) & (prof < n)
        slot, prof, measured_m, surface = slot[keep], prof[keep], measured_m[keep], ret.surface[keep]
        intensity = self.scene.reflectivity[surface] * ret.cos_incidence[keep]
        ranges = np.zeros((n, K), np.uint32)
        inten = np.zeros((n, K), np.uint16)
        ranges[prof, slot] = np.maximum(np.rint(measured_m / RANGE_UNIT_M), 1).astype(np.uint32)
        inten[prof, slot] = np.rint(np.clip(intensity, 0.0, 1.0) * INTENSITY_FULL_SCALE).astype(np.uint16)
        self._count(n, prof, slot, surface, start)
        return pack_profiles(
            start,
            p_idx,
            ranges,
            inten,
            self.layout,
            self.dt_ns,
            self.dangle_udeg,
            self.clock,
            self.latency_ns,
        )

    def _count(self, n: int, prof, slot, surface, start) -> None:
        c = self.counts
        c.profiles += n
        c.packets += n * len(self.layout)
        c.points += n * self.points_per_profile
        c.returns += int(prof.size)
        c.per_surface += np.bincount(surface, minlength=len(self.scene))
        if not self.passes or prof.size == 0:
            return
        # the time each return has on the wire: its packet's t0 + i·dt (what a decoder gives)
        s0 = self.first_slot[slot]
        first = np.rint(s0 * self.dt_ns).astype(np.int64)
        t_ns = start[prof] + first + (slot - s0) * round(self.dt_ns)
        for pid, a, b in self.passes:
            inside = (t_ns >= a) & (t_ns <= b)
            if inside.any():
                c.per_pass[pid] += int(inside.sum())
                c.per_pass_surface[pid] += np.bincount(surface[inside], minlength=len(self.scene))
