"""The options and the results of a relative accuracy assessment: what one comparison of a
surface, one fit of the distances against height and the whole assessment hold (and how they
go into ``assessment.json``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from calib.assess.c2c import DistanceStats
from calib.core.errors import CalibError
from calib.core.geometry import Rectangle

STATES = ("before", "after")
ANGLES = ("roll", "pitch", "yaw")


class AssessError(CalibError, ValueError):
    """The assessment cannot run on this input (the message says what and why)."""


@dataclass(frozen=True)
class AssessOptions:
    k: int = 6  # neighbours of the local least-squares plane (CloudCompare's KNN)
    gate_m: float = 1.0  # returns within this distance of a validation plane are candidates
    margin_m: float = 0.0  # grow the validation rectangles by this much
    min_points: int = 30  # per pass and surface
    clean_sigma: float = 4.0  # per-pass plane trimming, in robust σ
    clean_floor_m: float = 0.02  # ... never closer than this
    auto_planes: bool = False  # extract patches even when the site lists validation planes
    auto_cell_m: float = 1.5
    auto_max_rms_m: float = 0.05  # planarity of a cell (both passes, after the calibration)
    auto_max_angle_deg: float = 10.0  # between a cell's normal and its region's
    auto_max_patches: int = 12
    overlap: bool = True
    overlap_radius_m: float = 0.5
    max_overlap_points: int = 500_000  # per pass (a random subsample beyond this)
    max_points_per_pass: int = 5_000_000  # a random subsample beyond this
    scanner_height_m: float = 0.0  # scanner above the water line
    seed: int = 0

    def __post_init__(self):
        if int(self.k) != self.k or self.k < 3:
            raise AssessError(f"k = {self.k!r}: a local plane needs k ≥ 3 neighbours")
        for name in ("gate_m", "clean_sigma", "auto_cell_m", "auto_max_rms_m", "overlap_radius_m"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise AssessError(f"{name} = {v!r}: expected a positive number")
        for name in ("margin_m", "clean_floor_m"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise AssessError(f"{name} = {v!r}: expected a number ≥ 0")
        if int(self.min_points) != self.min_points or self.min_points < 3:
            raise AssessError(f"min_points = {self.min_points!r}: expected an integer ≥ 3")


#: the assessment's options when the caller gives none (frozen, shared)
DEFAULT_ASSESS_OPTIONS = AssessOptions()


@dataclass(frozen=True)
class Comparison:
    """C2C of one surface (or the whole overlap) between the two passes of a pair."""

    name: str
    source: str  # "site", "auto" or "overlap"
    pair: tuple[int, int]  # (compared pass, reference pass)
    height_m: float  # median height of the compared returns above the water
    n_reference: int
    collinear_fraction: float | None  # of the local planes (see collinear_fraction)
    before: DistanceStats  # unsigned C2C (CloudCompare's value)
    after: DistanceStats
    true_mount: DistanceStats | None  # with the true mount (simulated bundles)
    before_signed_mean_m: float | None  # mean signed C2C (+ along the surface's normal)
    after_signed_mean_m: float | None
    floor_median_m: float | None  # C2C median once the two patches' planes coincide
    expected_scanner_median_m: float | None  # from the scanner sigmas and the local-plane model
    expected_median_m: float | None  # ... plus the POS offsets of the two passes
    expected_upper_m: float | None  # 95 % bound of the median one pair can show (scanner + POS)
    expected_upper_calibration_m: float | None  # ... with the result's boresight σ as well
    pos_offset_sigma_m: float | None  # σ of the relative POS offset of the passes (normal)
    boresight_offset_sigma_m: float | None  # RMS σ of the relative offset the result's σ allows
    rectangle: Rectangle | None
    truth_plane: str | None
    truth: dict | None  # {state: {pass_id: DistanceStats (signed, to the true plane)}}
    d_before_m: np.ndarray = field(repr=False)  # unsigned, per compared return
    d_after_m: np.ndarray = field(repr=False)
    heights_m: np.ndarray = field(repr=False)

    @property
    def improvement(self) -> float:
        """Ratio of the median before to the median after."""
        a = self.after.median_m
        return self.before.median_m / a if a > 0 else math.inf

    def to_dict(self) -> dict:
        d = {
            "name": self.name,
            "source": self.source,
            "pair": list(self.pair),
            "height_m": self.height_m,
            "n_compared": self.after.count,
            "n_reference": self.n_reference,
            "collinear_fraction": self.collinear_fraction,
            "before": self.before.as_dict(),
            "after": self.after.as_dict(),
            "true_mount": None if self.true_mount is None else self.true_mount.as_dict(),
            "before_signed_mean_m": self.before_signed_mean_m,
            "after_signed_mean_m": self.after_signed_mean_m,
            "improvement": self.improvement if math.isfinite(self.improvement) else None,
            "floor_median_m": self.floor_median_m,
            "expected_scanner_median_m": self.expected_scanner_median_m,
            "expected_median_m": self.expected_median_m,
            "expected_upper_m": self.expected_upper_m,
            "expected_upper_calibration_m": self.expected_upper_calibration_m,
            "pos_offset_sigma_m": self.pos_offset_sigma_m,
            "boresight_offset_sigma_m": self.boresight_offset_sigma_m,
            "truth_plane": self.truth_plane,
        }
        if self.rectangle is not None:
            r = self.rectangle
            d["rectangle"] = {
                "center_lgf_m": r.center_m.tolist(),
                "normal": r.normal.tolist(),
                "width_m": r.width_m,
                "height_m": r.height_m,
            }
        if self.truth is not None:
            d["truth"] = {s: {str(p): st.as_dict() for p, st in v.items()} for s, v in self.truth.items()}
        return d


@dataclass(frozen=True)
class HeightFit:
    """Least-squares line of the unsigned C2C against the height above the water."""

    pair: tuple[int, int]
    state: str
    slope_m_per_m: float
    intercept_m: float
    n: int
    height_span_m: tuple[float, float]
    bin_heights_m: np.ndarray = field(repr=False)  # centres of height bins with points
    bin_medians_m: np.ndarray = field(repr=False)

    def to_dict(self) -> dict:
        return {
            "pair": list(self.pair),
            "state": self.state,
            "slope_m_per_m": self.slope_m_per_m,
            "intercept_m": self.intercept_m,
            "n": self.n,
            "height_span_m": list(self.height_span_m),
        }


@dataclass(frozen=True)
class Assessment:
    bundle_path: Path
    pairs: tuple[tuple[int, int], ...]
    headings_deg: dict[int, float]  # sailed heading of each pass
    boresight_before_deg: dict[str, float]
    boresight_after_deg: dict[str, float]
    truth_boresight_deg: dict[str, float] | None
    plane_source: str  # "site" or "auto"
    comparisons: tuple[Comparison, ...]
    height_fits: tuple[HeightFit, ...]
    notes: tuple[str, ...]
    options: AssessOptions

    def comparison(self, name: str, pair: tuple[int, int]) -> Comparison:
        for c in self.comparisons:
            if c.name == name and c.pair == tuple(pair):
                return c
        raise KeyError(f"no comparison of {name!r} for passes {pair[0]}:{pair[1]}")

    def planes(self, pair: tuple[int, int] | None = None) -> list[Comparison]:
        """The surface comparisons (not the overlaps), lowest first."""
        out = [
            c for c in self.comparisons if c.source != "overlap" and (pair is None or c.pair == tuple(pair))
        ]
        return sorted(out, key=lambda c: (c.pair, c.height_m))

    def height_fit(self, pair: tuple[int, int], state: str) -> HeightFit:
        for h in self.height_fits:
            if h.pair == tuple(pair) and h.state == state:
                return h
        raise KeyError(f"no height fit for passes {pair[0]}:{pair[1]} {state}")

    def to_dict(self) -> dict:
        return {
            "bundle": str(self.bundle_path),
            "pairs": [list(p) for p in self.pairs],
            "headings_deg": {str(k): v for k, v in self.headings_deg.items()},
            "boresight_before_deg": self.boresight_before_deg,
            "boresight_after_deg": self.boresight_after_deg,
            "truth_boresight_deg": self.truth_boresight_deg,
            "plane_source": self.plane_source,
            "k": self.options.k,
            "scanner_height_m": self.options.scanner_height_m,
            "comparisons": [c.to_dict() for c in self.comparisons],
            "height_fits": [h.to_dict() for h in self.height_fits],
            "notes": list(self.notes),
        }
