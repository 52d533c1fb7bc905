"""The truth clock: one mapping host ``CLOCK_MONOTONIC`` → GPS time shared by every emulator.

    gps_ns = gps_anchor_ns + (host_ns − host_anchor_ns) · rate,   rate = speed · (1 + drift_ppm·1e-6)

``host_anchor_ns`` is the host instant at which the emulated world's GPS time is
``gps_anchor_ns`` (the start of the scenario window). ``drift_ppm`` is how much faster GPS time
runs than the host clock — the same sign as the daemon's clock model (``acquire.timing.clock``:
``drift_ppm`` = (GPS ns per host ns − 1)·1e6), so a daemon tracking this clock perfectly
reports ``drift_ppm`` (at speed 1). ``speed`` > 1 runs the scenario faster than real time: the
daemon then sees a clock rate of ``speed``.

The run directory holds it as ``truth_clock.json`` (:meth:`TruthClock.write`,
:meth:`TruthClock.read`) so tests can score the daemon's clock estimate against it, and the
simulated steps of the host's realtime clock (``host_clock_step`` faults) as ``host_clock``
(:func:`write_host_clock_steps`, read by :class:`drivers.timing.FakeHostClock`).
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

NS_PER_S = 1_000_000_000
FORMAT = "marine-mls truth clock v1"
HOST_CLOCK_FILE = "host_clock"  # the simulated host-clock steps (drivers.timing.FakeHostClock)


@dataclass(frozen=True)
class TruthClock:
    host_anchor_ns: int  # host CLOCK_MONOTONIC at the anchor
    gps_anchor_ns: int  # GPS ns (since 1980-01-06) at the anchor
    drift_ppm: float = 0.0
    speed: float = 1.0

    def __post_init__(self) -> None:
        if not self.speed > 0:
            raise ValueError(f"truth clock speed {self.speed!r}: expected > 0")
        if not abs(self.drift_ppm) < 1e5:
            raise ValueError(f"truth clock drift_ppm {self.drift_ppm!r}: expected |drift| < 1e5 ppm")

    @classmethod
    def starting_in(
        cls, lead_s: float, gps_anchor_ns: int, drift_ppm: float = 0.0, speed: float = 1.0
    ) -> TruthClock:
        """A clock whose GPS time is ``gps_anchor_ns`` ``lead_s`` seconds from now."""
        return cls(
            time.monotonic_ns() + round(lead_s * NS_PER_S), int(gps_anchor_ns), float(drift_ppm), float(speed)
        )

    @property
    def rate(self) -> float:
        """GPS ns per host ns."""
        return self.speed * (1.0 + self.drift_ppm * 1e-6)

    def gps_ns(self, host_ns: int) -> int:
        return self.gps_anchor_ns + round((int(host_ns) - self.host_anchor_ns) * self.rate)

    def host_ns(self, gps_ns: int) -> int:
        return self.host_anchor_ns + round((int(gps_ns) - self.gps_anchor_ns) / self.rate)

    def host_ns_array(self, gps_ns: np.ndarray) -> np.ndarray:
        """Vectorized :meth:`host_ns` (int64 in, int64 out; the same rounding)."""
        d = (np.asarray(gps_ns, dtype=np.int64) - self.gps_anchor_ns).astype(np.float64)
        return self.host_anchor_ns + np.rint(d / self.rate).astype(np.int64)

    def gps_ns_array(self, host_ns: np.ndarray) -> np.ndarray:
        d = (np.asarray(host_ns, dtype=np.int64) - self.host_anchor_ns).astype(np.float64)
        return self.gps_anchor_ns + np.rint(d * self.rate).astype(np.int64)

    def now_gps_ns(self) -> int:
        return self.gps_ns(time.monotonic_ns())

    # -- file -----------------------------------------------------------------------------------

    def to_dict(self) -> dict:
        d = asdict(self)
        d.update(
            format=FORMAT,
            rate=self.rate,
            gps_minus_host_at_anchor_ns=self.gps_anchor_ns - self.host_anchor_ns,
            formula="gps_ns = gps_anchor_ns + (host_ns - host_anchor_ns) * rate; "
            "rate = speed * (1 + drift_ppm * 1e-6); host_ns is time.monotonic_ns()",
        )
        return d

    def write(self, path: str | Path, **extra) -> Path:
        """Write ``truth_clock.json`` (atomically); ``extra`` keys are added (e.g. the window)."""
        path = Path(path)
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_text(json.dumps({**self.to_dict(), **extra}, indent=2) + "\n", encoding="utf-8")
        tmp.replace(path)
        return path

    @classmethod
    def read(cls, path: str | Path) -> TruthClock:
        d = json.loads(Path(path).read_text(encoding="utf-8"))
        if d.get("format") != FORMAT:
            raise ValueError(f"{path}: format {d.get('format')!r}, expected {FORMAT!r}")
        return cls(
            int(d["host_anchor_ns"]), int(d["gps_anchor_ns"]), float(d["drift_ppm"]), float(d["speed"])
        )


def write_host_clock_steps(path: str | Path, steps: list[tuple[int, int]]) -> Path:
    """The steps the ``host_clock_step`` faults would make to the host's realtime clock —
    ``(host monotonic ns of the step, step ns)`` — for :class:`drivers.timing.FakeHostClock`
    (the emulators cannot step this machine's clock; a daemon given this file,
    ``mls acquire --sim-host-clock FILE``, sees the steps instead). Written atomically."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    lines = ["# marine-mls simulated host clock steps: host_monotonic_ns step_ns"]
    lines += [f"{int(t)} {int(step)}" for t, step in sorted(steps)]
    tmp.write_text("\n".join(lines) + "\n", encoding="utf-8")
    tmp.replace(path)
    return path
