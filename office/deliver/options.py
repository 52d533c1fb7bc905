"""What ``mls georef`` is asked for: tiling, output CRS, chunking and the surveyor's filters."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

from acquire.errors import AcquireError

TILINGS = ("line", "square")


class GeorefError(AcquireError, ValueError):
    """A survey cannot be georeferenced as asked (the message says why and what to do)."""


def _window(name: str, w, lo: float = -math.inf, hi: float = math.inf) -> tuple[float, float] | None:
    if w is None:
        return None
    a, b = (float(v) for v in w)
    if not (math.isfinite(a) and math.isfinite(b)) or not (lo <= a < b <= hi):
        raise GeorefError(f"{name} {a:g} {b:g}: expected MIN < MAX within [{lo:g}, {hi:g}]")
    return a, b


@dataclass(frozen=True)
class Filters:
    """Which returns go into the deliverable.

    ``range_m``: the range window (m); the default's 1 m floor drops the vessel's own rails and
    mast right in front of the scanner. ``scan_angle_deg``: a window of the scanner's own angle
    (as ``points.csv`` and ``mls decode`` give it, [0, 360)). ``intensity_min``: the floor of the
    scanner's 16-bit count. ``time_gps_s``: a GPS-time window. ``vessel_box_m``: a box in the
    body frame (x forward, y starboard, z down, from the INS reference point: x_min, x_max,
    y_min, y_max, z_min, z_max) whose returns are the vessel itself."""

    range_m: tuple[float, float] = (1.0, 119.0)
    scan_angle_deg: tuple[float, float] | None = None
    intensity_min: int = 0
    time_gps_s: tuple[float, float] | None = None
    vessel_box_m: tuple[float, float, float, float, float, float] | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "range_m", _window("--range-m", self.range_m, 0.0, 1e4))
        object.__setattr__(self, "scan_angle_deg", _window("--scan-angle-deg", self.scan_angle_deg, 0, 360))
        object.__setattr__(self, "time_gps_s", _window("--time-gps-s", self.time_gps_s, 0.0))
        if not 0 <= int(self.intensity_min) <= 65535:
            raise GeorefError(f"--intensity-min {self.intensity_min}: expected 0…65535")
        if self.vessel_box_m is not None:
            b = tuple(float(v) for v in self.vessel_box_m)
            if (
                len(b) != 6
                or not all(math.isfinite(v) for v in b)
                or not all(b[2 * i] < b[2 * i + 1] for i in range(3))
            ):
                raise GeorefError(
                    f"--vessel-box-m {self.vessel_box_m}: expected X_MIN X_MAX Y_MIN Y_MAX Z_MIN Z_MAX "
                    f"(metres, body frame), each MIN < MAX"
                )
            object.__setattr__(self, "vessel_box_m", b)


@dataclass(frozen=True)
class GeorefOptions:
    """``tiling``: ``line`` (one tile per pass / survey line; returns outside every line are
    left out, or go to the tile ``transit`` with ``keep_transits``) or ``square`` (squares of
    ``tile_m`` in the output CRS). A tile of more than ``max_tile_points`` is written as
    several files (``-p01``, ``-p02``… in time order). ``chunk_s``: the time chunk one task
    georeferences; it bounds a worker's memory (at the full Z+F rate, 2 s — 2 M points — took
    0.5 GB per worker, 5 s took 1.1 GB)."""

    crs: str = "utm"
    tiling: str = "line"
    tile_m: float | None = None
    keep_transits: bool = False
    chunk_s: float = 2.0
    max_tile_points: int = 20_000_000
    compress: bool = True
    filters: Filters = field(default_factory=Filters)

    def __post_init__(self) -> None:
        if self.tiling not in TILINGS:
            raise GeorefError(f"tiling {self.tiling!r}: expected one of {', '.join(TILINGS)}")
        if self.tiling == "square" and not (self.tile_m and self.tile_m > 0 and math.isfinite(self.tile_m)):
            raise GeorefError(f"--tile-m {self.tile_m}: square tiles need a positive size")
        if not 0.5 <= self.chunk_s <= 600:
            raise GeorefError(f"--chunk-s {self.chunk_s:g}: expected 0.5…600 s")
        if self.max_tile_points < 1000:
            raise GeorefError(f"--max-tile-points {self.max_tile_points}: expected at least 1000")

    def as_dict(self) -> dict:
        return asdict(self)
