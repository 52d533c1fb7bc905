"""The PPS emulator: one UDP datagram per GNSS pulse, carrying the edge's host monotonic stamp.

At every whole GPS second S of the run the pulse happens at ``host(S)`` on the truth clock; its
stamp is that instant plus a Gaussian jitter of σ ``jitter_s`` (clipped at ±4σ), as a kernel
interrupt stamp would be, and the datagram (:func:`drivers.pps.encode_pps_datagram`, the
drivers' ``udp`` PPS source) leaves at the stamp. The pulse counter starts at 1 and advances per
pulse sent; a ``pps_loss`` fault suppresses the pulses in its window (the counter does not
advance), the ``udp_*`` faults act on the datagrams.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from drivers.pps import encode_pps_datagram
from sim_devices.faults import Fault, Timeline
from sim_devices.udp import DatagramSender, UdpLink

NS_PER_S = 1_000_000_000


@dataclass(frozen=True)
class PpsSettings:
    host: str = "127.0.0.1"
    port: int = 0
    jitter_s: float = 20e-6

    def __post_init__(self) -> None:
        if not 0 <= self.jitter_s < 0.05:
            raise ValueError(f"PPS jitter_s {self.jitter_s!r}: expected 0 ≤ jitter < 0.05 s")


class PpsEmulator:
    name = "pps"
    spin_ns = 200_000

    def __init__(
        self, settings: PpsSettings, faults: list[Fault], start_gps_ns: int, end_gps_ns: int, seed: int = 0
    ) -> None:
        self.s = settings
        self.timeline = Timeline(faults, start_gps_ns)
        self.start_gps_ns, self.end_gps_ns = start_gps_ns, end_gps_ns
        self.seed = seed
        self.rng = np.random.default_rng([seed, 3])
        self.link: DatagramSender | None = None
        self.counts = {"pulses": 0, "suppressed": 0}
        self.edges: list[tuple[int, int, int]] = []  # (sequence, GPS second, host stamp ns)

    def seconds(self) -> np.ndarray:
        return np.arange(-(-self.start_gps_ns // NS_PER_S), -(-self.end_gps_ns // NS_PER_S), dtype=np.int64)

    def prepare(self) -> dict:
        self.link = UdpLink((self.s.host, self.s.port), self.timeline, self.seed + 1)
        return {"address": [self.s.host, self.s.port], "format": "PPS1", "jitter_s": self.s.jitter_s}

    def run(self, clock, pacer, timing) -> bool:
        sigma = self.s.jitter_s * NS_PER_S
        seq = 1
        for sec in self.seconds().tolist():
            g = sec * NS_PER_S
            if self.timeline.active("pps_loss", g) is not None:
                self.counts["suppressed"] += 1
                continue
            jitter = round(float(np.clip(self.rng.normal(0.0, sigma), -4 * sigma, 4 * sigma))) if sigma else 0
            stamp = clock.host_ns(g) + jitter
            if not pacer.wait_until(stamp):
                return False
            assert self.link is not None  # opened by prepare() (or set by the caller)
            self.link.send(encode_pps_datagram(seq, stamp), g)
            timing.record(stamp, time.monotonic_ns())
            self.edges.append((seq, sec, stamp))
            self.counts["pulses"] += 1
            seq += 1
        return True

    def close(self) -> None:
        if self.link is not None:
            self.link.close()

    def stats(self) -> dict:
        return {
            **self.counts,
            **(self.link.stats if self.link else {}),
            "edges": [{"sequence": q, "gps_s": s, "host_ns": h} for q, s, h in self.edges],
        }
