"""The Z+F profiler emulator: the scenario's profiles as ZFP1 datagrams over UDP, in real time.

Every profile of the :class:`~sim_devices.feed.ProfileGrid` is sent as ZFP1 packets
(:func:`drivers.zf.zfp1.pack_packet`): each recorded angular run of the profile is split into
packets of at most ``max_payload`` bytes (226 points at 1400), a packet carries its first point's
time and angle, and is due ``latency_s`` (host seconds) after its last point was measured (on
the truth clock). The profile counter is the profile's index in the run (from 0). Datagrams go
out in bursts: the emulator sleeps until the last of the datagrams due within ``burst_s`` (host
seconds, default 1 ms: about 5 datagrams at the full rate, 23 at ×5) is due and sends them
together, so a datagram leaves at most ``burst_s`` late (the timing log records each one's
delay) and the emulator wakes once per burst instead of once per datagram (at ×5 a wake-up
every 43 µs would take most of a core).

The time stamps come from the profiler's own clock: the truth (PPS-locked flag set) unless a
``profiler_clock_offset`` fault adds its ``offset_s`` or a ``profiler_clock_drift`` fault lets
the clock run ``drift_ppm`` fast from the fault's start; both act on the profiles measured in
their window and set the PPS-locked flag as the fault says. ``udp_loss``, ``udp_reorder`` and
``udp_duplicate`` act on the datagrams (:class:`~sim_devices.udp.UdpLink`).
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from drivers.zf.codec import FLAG_LAST, FLAG_PPS_LOCKED, FLAG_TIME_VALID
from drivers.zf.zfp1 import DEFAULT_MAX_PAYLOAD, POINT_DTYPE, pack_packet, points_per_packet
from sim_devices.faults import Fault, Timeline
from sim_devices.feed import ProfileGrid
from sim_devices.udp import UdpLink


@dataclass(frozen=True)
class ProfilerSettings:
    host: str = "127.0.0.1"
    port: int = 0  # 0: a free port is chosen at start
    latency_s: float = 0.0005
    max_payload: int = DEFAULT_MAX_PAYLOAD
    burst_s: float = 0.001

    def __post_init__(self) -> None:
        if not 0 <= self.latency_s < 1:
            raise ValueError(f"profiler latency_s {self.latency_s!r}: expected 0 ≤ latency < 1 s")
        if not 0 <= self.burst_s <= 0.05:
            raise ValueError(f"profiler burst_s {self.burst_s!r}: expected 0 ≤ burst ≤ 0.05 s")
        points_per_packet(self.max_payload)  # raises DriverError naming the value


def packet_layout(runs, max_payload: int = DEFAULT_MAX_PAYLOAD) -> list[tuple[int, int]]:
    """The (first slot, n points) of each packet of a profile, in time order."""
    per = points_per_packet(max_payload)
    return [(s, min(per, end - s)) for a, end in runs for s in range(a, end, per)]


class ProfilerEmulator:
    name = "profiler"
    spin_ns = 0  # thousands of datagrams per second: sleep only

    def __init__(
        self,
        grid: ProfileGrid,
        settings: ProfilerSettings,
        faults: list[Fault],
        start_gps_ns: int,
        seed: int = 0,
    ) -> None:
        self.grid = grid
        self.s = settings
        self.timeline = Timeline(faults, start_gps_ns)
        self.layout = packet_layout(grid.runs, settings.max_payload)
        self.seed = seed
        self.link: UdpLink | None = None
        self.counts = {"profiles": 0, "packets": 0}

    def clock_error(self, t_gps_ns: int) -> tuple[int, bool]:
        """(profiler clock − truth in ns, PPS-locked flag) for a profile measured at ``t_gps_ns``."""
        err, locked = 0, True
        f = self.timeline.active("profiler_clock_offset", t_gps_ns)
        if f is not None:
            err += round(f.params["offset_s"] * 1e9)
            locked &= f.params["pps_locked"]
        f = self.timeline.active("profiler_clock_drift", t_gps_ns)
        if f is not None:
            started = self.timeline.started_at("profiler_clock_drift", t_gps_ns)
            assert started is not None  # an active drift has started
            err += round(f.params["drift_ppm"] * 1e-6 * (t_gps_ns - started))
            locked &= f.params["pps_locked"]
        return err, locked

    def packets(self, clock) -> Iterator[tuple[int, int, bytes]]:
        """(scheduled host ns, truth GPS ns of the emission, datagram), in emission order."""
        g = self.grid
        K, dt_ns, da_udeg = g.points_per_360, g.dt_ns, g.dangle_udeg
        dt_int, da_int = round(dt_ns), round(da_udeg)
        latency_ns = round(self.s.latency_s * 1e9)
        points = np.zeros(K, POINT_DTYPE)
        ranges, inten = points["range_01mm"], points["intensity"]
        count = len(self.layout)
        layout = [
            (s0, n, round(s0 * dt_ns), round((s0 + n) * dt_ns), round(s0 * da_udeg)) for s0, n in self.layout
        ]
        for p in range(len(g)):
            start = int(g.start_ns[p])
            err, locked = self.clock_error(start)
            flags = FLAG_TIME_VALID | (FLAG_PPS_LOCKED if locked else 0)
            slots, r01, i16 = g.profile_returns(p)
            ranges[slots] = r01
            inten[slots] = i16
            for k, (s0, n, t_first, t_end, a0) in enumerate(layout):
                emit_gps = start + t_end
                payload = pack_packet(
                    flags | (FLAG_LAST if k == count - 1 else 0),
                    p,
                    k,
                    count,
                    start + t_first + err,
                    dt_int,
                    a0,
                    da_int,
                    points[s0 : s0 + n],
                )
                yield clock.host_ns(emit_gps) + latency_ns, emit_gps, payload
            ranges[slots] = 0
            inten[slots] = 0

    def prepare(self) -> dict:
        self.link = UdpLink((self.s.host, self.s.port), self.timeline, self.seed)
        g = self.grid
        return {
            "address": [self.s.host, self.s.port],
            "protocol": "zfp1",
            "profile_rate_hz": g.profile_rate_hz,
            "points_per_360": g.points_per_360,
            "profiles": len(g),
            "packets_per_profile": len(self.layout),
            "points_per_profile": sum(n for _, n in self.layout),
        }

    def run(self, clock, pacer, timing) -> bool:
        link, mono, wait, record = self.link, time.monotonic_ns, pacer.wait_until, timing.record
        burst_ns = round(self.s.burst_s * 1e9)
        burst: list[tuple[int, int, bytes]] = []
        self.counts["packets"] = 0

        def send() -> bool:  # at the last one's instant
            if not wait(burst[-1][0]):
                return False
            assert link is not None  # opened by prepare()
            for host, emit_gps, payload in burst:
                link.send(payload, emit_gps)
                record(host, mono())
            self.counts["packets"] += len(burst)
            burst.clear()
            return True

        for item in self.packets(clock):
            if burst and item[0] - burst[0][0] > burst_ns and not send():
                return False
            burst.append(item)
        return not burst or send()

    def close(self) -> None:
        if self.link is not None:
            self.link.close()

    def stats(self) -> dict:
        self.counts["profiles"] = self.counts["packets"] // max(len(self.layout), 1)
        return {**self.counts, **(self.link.stats if self.link else {})}
