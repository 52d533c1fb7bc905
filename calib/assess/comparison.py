"""Relative accuracy assessment of a calibration (thesis §4.4.6, §4.5.4; DESIGN §7 "Assessment").

The same raw returns of two passes (reciprocal ones by default: 0°/180°, 45°/225°, …) are
georeferenced twice, with the a-priori mount of the site config (*before*) and with the mount
of a calibration result (*after*), and compared with cloud-to-cloud distances to local
least-squares planes (:mod:`calib.assess.c2c`, CloudCompare's C2C ``-MODEL LS KNN k``): the first pass
of a pair is the compared cloud, the second the reference. A boresight error moves the two
passes of a reciprocal pair in opposite directions by an amount that grows with the range, so
the distances before the calibration grow with the height of the surface above the water, and
after a good calibration they fall to what the sensors' noise allows.

**Surfaces compared.** (1) The validation planes of the site config (approximate rectangles,
e.g. the tower patches V1–V5 of the thesis's Fig. 4.22) or, when the site lists none (or on
request), planar patches extracted automatically from the pair's calibrated clouds: cells of
``auto_cell_m`` whose points of *both* passes lie on one plane, grown into regions of coplanar
neighbouring cells. (2) The whole overlap of the two passes (points of each pass within
``overlap_radius_m`` of the other pass).

**Which returns.** The returns of a surface are chosen once, in the *after* geometry (the best
estimate of where each return lies): inside the rectangle (grown by ``margin_m``), within
``gate_m`` of its plane, and then per pass on its own least-squares plane (iterative trimming at
``clean_sigma`` robust σ, never closer than ``clean_floor_m``). Compared returns outside the
reference's coverage in either geometry are left out (:func:`within_coverage`: C2C would
extrapolate the reference's edge there). The same returns are compared before and after, so the
two figures differ only by the mount.

**Expected level after the calibration.** With a perfect mount the distance of a compared
return q to the local plane of the reference is its own noise along the normal minus the error
of the local plane at q:

    d = e_q − Σ_j w_j e_j,    w_j = 1/k + (x_q − c)ᵀ S⁻¹ (x_j − c)

(the least-squares plane through the k neighbours j with in-plane coordinates x_j, centroid c
and scatter S, evaluated at q), so ``var d = σ_q² + Σ_j w_j² σ_j²`` and, for equal σ,
``Σ_j w_j² = h(q) = 1/k + (x_q − c)ᵀ S⁻¹ (x_q − c)``, the leverage of q in the local fit.
The median of |d| over a patch is then the median of a mixture of half-normals of variances
``σ²(1 + h)``: for an evenly sampled plane 0.87 σ with k = 6 and 0.73 σ with k = 12 (the
leverage has a heavy tail: neighbourhoods whose centroid lies off the compared point).
A profiler's sampling is anisotropic (scan lines), so some neighbourhoods are nearly collinear,
their planes tilt freely about the line and the distances grow (:func:`collinear_fraction`
counts them; above 10 % a note suggests a larger k); the expected level is therefore computed
with C2C itself on the real sampling (:func:`expected_c2c`: both patches put on one
plane, synthetic normal errors with each return's σ). The σ along the normal comes from the
site's scanner sigmas and the geometry, ``σ_ρ² (n·∂x/∂ρ)² + σ_α² (n·∂x/∂α)²``. POS errors
are correlated in time (DESIGN §7): during the few seconds a pass sees a surface they act as one
offset per pass, of variance ``Σ σ_c² n_c²`` (position) plus ``Σ σ_k² ((r × n)·a_k)²``
(attitude; r from the INS to the return, a_k the axes of roll, pitch and heading), independent
between passes; *expected* adds the two passes' offsets to the scanner noise, *expected
(scanner)* leaves them out. One pair of passes draws one offset, so its median scatters: the
95th percentile of the median over the draws is the *upper* bound the verdict uses; a second
bound adds the relative offset the result's own boresight σ allows, ``(J_A − J_B)·δb`` with J
the derivative of each return along the normal by the boresight angles and δb ~ N(0, Σ_b)
(realistic σ and correlation of result.json). Beside the prediction the *floor* is measured:
the C2C median once the reference patch is moved onto the compared patch's plane (its own
scatter kept) — what the two patches give when they agree exactly.

**Against the truth** (a simulated bundle, ``truth.json``): the signed distance of each
selected return to the true plane it lies on (by name for the site's validation planes, else
the true rectangle holding most of the patch's returns), georeferenced before, after and with
the true mount; and the C2C with the true mount: what a perfect calibration would leave, given
the bundle's POS errors.

Heights are "above the water": above the scanner's mean height during the pair, plus
``scanner_height_m`` (the scanner's height above the water line; 0 by default, i.e. heights
relative to the platform as in the thesis's figures).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from calib.assess.c2c import DistanceStats, c2c, distance_stats
from calib.core.geometry import Rectangle, fit_plane
from calib.core.georef import Mount, georeference

STATES = ("before", "after")
ANGLES = ("roll", "pitch", "yaw")
#: Passes are reciprocal when their sailed headings differ by 180° within this tolerance.
RECIPROCAL_TOLERANCE_DEG = 20.0
_ALPHA_STEP_RAD = 1e-6


class AssessError(ValueError):
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


# -- results --------------------------------------------------------------------------------


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
            "name": self.name, "source": self.source, "pair": list(self.pair),
            "height_m": self.height_m, "n_compared": self.after.count,
            "n_reference": self.n_reference, "collinear_fraction": self.collinear_fraction,
            "before": self.before.as_dict(), "after": self.after.as_dict(),
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
        }  # fmt: skip
        if self.rectangle is not None:
            r = self.rectangle
            d["rectangle"] = {"center_lgf_m": r.center_m.tolist(), "normal": r.normal.tolist(),
                              "width_m": r.width_m, "height_m": r.height_m}  # fmt: skip
        if self.truth is not None:
            d["truth"] = {s: {str(p): st.as_dict() for p, st in v.items()}
                          for s, v in self.truth.items()}  # fmt: skip
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
        return {"pair": list(self.pair), "state": self.state, "slope_m_per_m": self.slope_m_per_m,
                "intercept_m": self.intercept_m, "n": self.n,
                "height_span_m": list(self.height_span_m)}  # fmt: skip


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
        out = [c for c in self.comparisons if c.source != "overlap"
               and (pair is None or c.pair == tuple(pair))]  # fmt: skip
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


# -- mounts and pairs -----------------------------------------------------------------------


def _angles_deg(v_rad) -> dict[str, float]:
    return {a: float(x) for a, x in zip(ANGLES, np.degrees(v_rad))}


def mount_from_result(apriori: Mount, result: dict, source: str = "result"
                      ) -> tuple[Mount, list[str]]:  # fmt: skip
    """The mount a calibration result describes: the a-priori one with the estimated boresight
    and the estimated extras (range offset, lever arm x/y, latency) applied; plus notes on what
    was not applied (per-pass trajectory offsets correct the trajectory, not the mount)."""
    from calib.assess.history import validate_result

    bs = validate_result(result, source)["boresight_deg"]
    mount = apriori.with_boresight(np.radians([bs[a] for a in ANGLES]))
    notes = []
    extras = result.get("extras") or {}
    if not isinstance(extras, dict):
        raise AssessError(f"{source}: extras is {extras!r}, expected an object")

    def value(key):
        e = extras[key]
        v = e.get("value") if isinstance(e, dict) else None
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise AssessError(f"{source}: extras.{key}.value is {v!r}, expected a finite number")
        return float(v)

    lever = mount.lever_arm_m.copy()
    kw = {}
    for key in extras:
        if key == "range_offset_m":
            kw["range_offset_m"] = value(key)
        elif key == "scan_angle_offset_deg":
            kw["scan_angle_offset_rad"] = float(np.radians(value(key)))
        elif key == "lever_arm_x_m":
            lever[0] = value(key)
        elif key == "lever_arm_y_m":
            lever[1] = value(key)
        elif key == "latency_s":
            kw["time_offset_s"] = value(key)
        elif not (key.startswith("pass") and key.endswith("_offset_m")):
            notes.append(f"{source}: extra {key!r} is not a mount parameter; not applied")
    if any(k.startswith("pass") and k.endswith("_offset_m") for k in extras):
        notes.append("the result's per-pass trajectory offsets are not applied (they correct "
                     "the calibration passes' trajectory, not the mount)")  # fmt: skip
    return replace(mount, lever_arm_m=lever, **kw), notes


def pass_headings_deg(bundle) -> dict[int, float]:
    """Sailed heading of each pass (circular mean of the trajectory at its returns' times)."""
    pts, traj = bundle.points, bundle.trajectory
    out = {}
    for pid in pts.pass_ids():
        t = pts.t_gps_s[pts.pass_id == pid]
        t = t[~traj.uncovered(t)]
        if t.size == 0:
            continue
        t = t[:: max(1, t.size // 2000)]
        h = traj.interpolate(t).rpy_rad[:, 2]
        out[pid] = float(np.degrees(np.arctan2(np.sin(h).mean(), np.cos(h).mean())) % 360.0)
    return out


def _heading_gap_deg(a: float, b: float) -> float:
    """How far two headings are from opposite: |((a − b) mod 360°) − 180°|."""
    return abs((a - b) % 360.0 - 180.0)


def reciprocal_pairs(headings_deg: dict[int, float],
                     tolerance_deg: float = RECIPROCAL_TOLERANCE_DEG) -> list[tuple[int, int]]:  # fmt: skip
    """Pairs of passes sailed in opposite directions (each pass in at most one pair, the closest
    to 180° first), lower pass id first."""
    ids = sorted(headings_deg)
    cands = sorted((_heading_gap_deg(headings_deg[a], headings_deg[b]), a, b)
                   for i, a in enumerate(ids) for b in ids[i + 1:])  # fmt: skip
    used, pairs = set(), []
    for gap, a, b in cands:
        if gap <= tolerance_deg and a not in used and b not in used:
            pairs.append((a, b))
            used |= {a, b}
    return sorted(pairs)


def parse_pairs(text: str) -> list[tuple[int, int]]:
    """``"1:2,5:6"`` → [(1, 2), (5, 6)] (compared pass first, reference second)."""
    out = []
    for item in text.split(","):
        item = item.strip()
        a, sep, b = item.partition(":")
        if not sep or not a.strip().isdigit() or not b.strip().isdigit():
            raise AssessError(f"pair {item!r}: expected two pass ids A:B, e.g. 1:2")
        pa, pb = int(a), int(b)
        if pa == pb:
            raise AssessError(f"pair {item!r}: a pass cannot be compared with itself")
        out.append((pa, pb))
    if not out:
        raise AssessError(f"pairs {text!r}: expected A:B[,C:D…]")
    return out


# -- selecting the returns of a surface -----------------------------------------------------


def plane_candidates(p_m: np.ndarray, rect: Rectangle, gate_m: float, margin_m: float = 0.0
                     ) -> np.ndarray:  # fmt: skip
    """Mask of points inside the rectangle (grown by ``margin_m``) within ``gate_m`` of its
    plane."""
    return (np.abs(rect.signed_distance(p_m)) <= gate_m) & rect.contains(p_m, margin_m)


def clean_patch(p_m: np.ndarray, mask: np.ndarray, n_sigma: float = 4.0, floor_m: float = 0.02,
                iterations: int = 8) -> np.ndarray:  # fmt: skip
    """The points of ``mask`` on their own least-squares plane: refit and drop those farther than
    ``max(n_sigma · σ, floor_m)`` (σ = 1.4826 × the median distance) until nothing changes."""
    keep = np.asarray(mask, bool).copy()
    for _ in range(iterations):
        if keep.sum() < 3:
            break
        f = fit_plane(p_m[keep])
        r = np.abs((p_m - f.centroid_m) @ f.normal)
        rk = r[keep]
        thr = max(n_sigma * 1.4826 * float(np.median(rk)), floor_m)
        new = mask & (r <= thr)
        if np.array_equal(new, keep):
            break
        keep = new
    return keep


def within_coverage(q_m: np.ndarray, ref_m: np.ndarray, normal, factor: float = 2.0) -> np.ndarray:
    """Mask of the compared points that lie within the reference's coverage on the plane: their
    in-plane distance to the nearest reference point is at most ``factor`` times the reference's
    median in-plane point spacing. Beyond it the local planes would be extrapolated from the
    reference's edge (often one scan line, whose plane is arbitrary)."""
    from scipy.spatial import cKDTree

    basis = _plane_basis(normal)
    q2, r2 = q_m @ basis, ref_m @ basis
    tree = cKDTree(r2)
    spacing = float(np.median(tree.query(r2, k=2)[0][:, 1])) if len(r2) > 1 else 0.0
    return tree.query(q2, k=1)[0] <= factor * spacing


def collinear_fraction(q_m: np.ndarray, ref_m: np.ndarray, normal, k: int,
                       ratio: float = 0.1) -> float:  # fmt: skip
    """Fraction of the compared points whose local plane rests on nearly collinear neighbours:
    the k neighbours of the nearest reference point spread less than ``ratio`` times as much
    across as along (in the plane). A profiler samples along scan lines, so with a small k the
    neighbours can all lie on one line across the profiles; the tilt of their plane about that
    line is then set by the noise, and a large offset between the clouds is understated."""
    from scipy.spatial import cKDTree

    basis = _plane_basis(normal)
    r2 = ref_m @ basis
    tree = cKDTree(r2)
    nearest = tree.query(q_m @ basis, k=1)[1]
    k = min(k, len(ref_m))
    nb = tree.query(r2[nearest], k=k)[1].reshape(len(q_m), k)
    x = r2[nb] - r2[nb].mean(axis=1, keepdims=True)
    cov = np.einsum("nki,nkj->nij", x, x)
    tr = cov[:, 0, 0] + cov[:, 1, 1]
    det = cov[:, 0, 0] * cov[:, 1, 1] - cov[:, 0, 1] ** 2
    disc = np.sqrt(np.maximum(tr * tr / 4 - det, 0.0))
    lam_min, lam_max = tr / 2 - disc, tr / 2 + disc
    return float(np.mean(np.sqrt(np.maximum(lam_min, 0.0)) < ratio * np.sqrt(lam_max)))


def _plane_basis(normal) -> np.ndarray:
    """(3, 2) orthonormal in-plane axes of a plane with this normal."""
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    e1 = np.cross(n, [0.0, 0.0, 1.0] if abs(n[2]) < 0.9 else [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    return np.stack([e1, np.cross(n, e1)], axis=1)


def _rectangle_of(points: np.ndarray, normal: np.ndarray, name: str) -> Rectangle:
    """The bounding rectangle of points on a plane (width axis horizontal where possible)."""
    f = fit_plane(points, orient_like=normal)
    n = f.normal
    u = np.cross([0.0, 0.0, 1.0], n)
    if np.linalg.norm(u) < 0.3:  # a nearly horizontal plane: the major axis
        u = np.linalg.eigh(np.cov((points - f.centroid_m).T))[1][:, 2]
        u = u - n * (u @ n)
    u /= np.linalg.norm(u)
    v = np.cross(u, n)
    q = points - f.centroid_m
    cu, cv = q @ u, q @ v
    center = f.centroid_m + u * 0.5 * (cu.min() + cu.max()) + v * 0.5 * (cv.min() + cv.max())
    return Rectangle(name, center, n, u, v, float(np.ptp(cu)), float(np.ptp(cv)))


def extract_common_patches(p_a: np.ndarray, p_b: np.ndarray, toward_m: np.ndarray,
                           options: AssessOptions = AssessOptions()) -> list[Rectangle]:  # fmt: skip
    """Planar patches seen by both clouds: cells of ``auto_cell_m`` whose points of both clouds
    lie on one plane (RMS ≤ ``auto_max_rms_m``, not a line), grown into regions of neighbouring
    cells that agree with the region's plane (normal within ``auto_max_angle_deg``, centroid
    within 3 × ``auto_max_rms_m``). Returns the regions' bounding rectangles (normals toward
    ``toward_m``), the largest first, named P1, P2, …"""
    cell = options.auto_cell_m
    pts = np.concatenate([p_a, p_b])
    which = np.concatenate([np.zeros(len(p_a), np.int8), np.ones(len(p_b), np.int8)])
    origin = pts.min(axis=0)
    key = np.floor((pts - origin) / cell).astype(np.int64)
    cells, inv, _ = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    inv = inv.ravel()
    m = len(cells)
    min_cell = max(options.k, 8)
    cnt_a = np.bincount(inv[which == 0], minlength=m)
    cnt_b = np.bincount(inv[which == 1], minlength=m)
    cnt = cnt_a + cnt_b
    rel = pts - origin
    s1 = np.stack([np.bincount(inv, rel[:, j], m) for j in range(3)], axis=1)
    s2 = np.empty((m, 3, 3))
    for i in range(3):
        for j in range(i, 3):
            s2[:, i, j] = s2[:, j, i] = np.bincount(inv, rel[:, i] * rel[:, j], m)
    ok_cells = np.flatnonzero((cnt_a >= min_cell) & (cnt_b >= min_cell))
    if ok_cells.size == 0:
        return []

    def plane_of(s1_, s2_, n_):
        c = s1_ / n_
        cov = s2_ / n_ - np.outer(c, c)
        w, v = np.linalg.eigh(cov)
        return c, v[:, 0], w

    cent, normal, flat = {}, {}, {}
    for ci in ok_cells:
        c, nv, w = plane_of(s1[ci], s2[ci], cnt[ci])
        # planar (thin) and not a line (spread in two directions)
        if np.sqrt(max(w[0], 0.0)) <= options.auto_max_rms_m and np.sqrt(max(w[1], 0.0)) > cell / 20:
            cent[ci], normal[ci], flat[ci] = c, nv, float(w[0])
    index = {tuple(cells[ci]): ci for ci in cent}
    offsets = [np.array(o) for o in np.ndindex(3, 3, 3) if o != (1, 1, 1)]
    cos_max = np.cos(np.radians(options.auto_max_angle_deg))
    tol = 3.0 * options.auto_max_rms_m
    region = {}
    regions = []
    for seed in sorted(cent, key=lambda c: flat[c]):  # flattest cells seed first
        if seed in region:
            continue
        members = [seed]
        region[seed] = len(regions)
        S1, S2, N = s1[seed].copy(), s2[seed].copy(), int(cnt[seed])
        c, nv, _ = plane_of(S1, S2, N)
        queue = [seed]
        while queue:
            ci = queue.pop()
            for o in offsets:
                nb = index.get(tuple(cells[ci] + o - 1))
                if nb is None or nb in region:
                    continue
                if abs(normal[nb] @ nv) < cos_max or abs((cent[nb] - c) @ nv) > tol:
                    continue
                region[nb] = len(regions)
                members.append(nb)
                queue.append(nb)
                S1 += s1[nb]
                S2 += s2[nb]
                N += int(cnt[nb])
                c, nv, _ = plane_of(S1, S2, N)
        regions.append(members)
    cell_region = np.full(m, -1)
    for r, members in enumerate(regions):
        cell_region[members] = r
    point_region = cell_region[inv]
    out = []
    for r, members in enumerate(regions):
        sel = point_region == r
        if np.count_nonzero(sel & (which == 0)) < options.min_points or \
                np.count_nonzero(sel & (which == 1)) < options.min_points:
            continue
        rp = pts[sel]
        f = fit_plane(rp)
        toward = np.asarray(toward_m, float) - f.centroid_m
        out.append((int(sel.sum()), _rectangle_of(rp, f.normal if f.normal @ toward >= 0
                                                  else -f.normal, "")))  # fmt: skip
    out.sort(key=lambda x: -x[0])
    return [replace(r, name=f"P{i + 1}") for i, (_, r) in enumerate(out[: options.auto_max_patches])]


# -- expected level -------------------------------------------------------------------------


def expected_c2c(q_m: np.ndarray, ref_m: np.ndarray, normal, var_q_m2: np.ndarray,
                 var_ref_m2: np.ndarray, k: int, offset_basis_m: np.ndarray | None = None,
                 draws: int = 8, offset_draws: int = 256, seed: int = 0) -> tuple[float, float]:  # fmt: skip
    """(median, 95th percentile of the patch's median) of the C2C of two patches that agree
    exactly but for their errors.

    Both patches are put on one plane (their in-plane positions kept, so the sampling and C2C's
    local planes are the real ones) and each return gets a normal error N(0, var); C2C gives
    the signed distances e of ``draws`` such draws. Offsets of the compared returns
    ``o = offset_basis_m @ z``, z ~ N(0, I) (a POS offset common to a pass, the effect of the
    boresight's σ), are then added to e for ``offset_draws`` draws of z (each with one of the
    noise draws) — what C2C gives for offsets small against the patch. The 95th percentile of
    the per-draw medians bounds the median one pair of passes can show."""
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    c = q_m.mean(axis=0)
    base_q = q_m - np.outer((q_m - c) @ n, n)
    base_r = ref_m - np.outer((ref_m - c) @ n, n)
    rng = np.random.default_rng(seed)
    sq, sr = np.sqrt(var_q_m2), np.sqrt(var_ref_m2)
    e = []
    for _ in range(draws):
        q = base_q + np.outer(rng.standard_normal(len(q_m)) * sq, n)
        r = base_r + np.outer(rng.standard_normal(len(ref_m)) * sr, n)
        e.append(c2c(q, r, k, orient_direction=n).signed_distance_m)
    if offset_basis_m is None:
        d = np.abs(np.stack(e, axis=1))
    else:
        m = int(np.clip(4_000_000 // max(len(q_m), 1), 32, offset_draws))
        z = rng.standard_normal((offset_basis_m.shape[1], m))
        d = np.abs(np.stack([e[i % draws] for i in range(m)], axis=1) + offset_basis_m @ z)
    return float(np.median(d)), float(np.percentile(np.median(d, axis=0), 95.0))


def boresight_covariance(result: dict) -> tuple[np.ndarray, str]:
    """(3, 3) covariance (rad²) of a result's boresight from its realistic σ (else the scaled
    σ) and its correlation matrix; and which σ it used."""
    from calib.assess.history import validate_result

    v = validate_result(result)
    kind = "realistic" if v["sigma_realistic_deg"] is not None else "scaled"
    sig = np.radians([v[f"sigma_{kind}_deg"][a] for a in ANGLES])
    return np.asarray(v["correlation"]) * np.outer(sig, sig), kind


def boresight_normal_jacobian(t_gps_s, range_m, scan_angle_rad, traj, mount: Mount, normal,
                              step_rad: float = 1e-6) -> np.ndarray:  # fmt: skip
    """(n, 3) derivative of each return's position along ``normal`` by the boresight roll,
    pitch and yaw (central differences)."""
    n = np.asarray(normal, float)
    out = np.empty((len(t_gps_s), 3))
    for j in range(3):
        e = np.zeros(3)
        e[j] = step_rad
        hi = georeference(t_gps_s, range_m, scan_angle_rad, traj,
                          mount.with_boresight(mount.boresight_rad + e))  # fmt: skip
        lo = georeference(t_gps_s, range_m, scan_angle_rad, traj,
                          mount.with_boresight(mount.boresight_rad - e))  # fmt: skip
        out[:, j] = ((hi - lo) @ n) / (2.0 * step_rad)
    return out


def scanner_normal_variance(t_gps_s, range_m, scan_angle_rad, traj, mount: Mount, normal,
                            sigma_range_m: float, sigma_scan_angle_rad: float) -> np.ndarray:  # fmt: skip
    """Variance of each return along ``normal`` from the range and scan-angle noise:
    ``σ_ρ² (n·∂x/∂ρ)² + σ_α² (n·∂x/∂α)²`` (the derivatives by georeferencing)."""
    n = np.asarray(normal, float)
    x = georeference(t_gps_s, range_m, scan_angle_rad, traj, mount)
    dx_rho = x - georeference(t_gps_s, np.zeros_like(range_m), scan_angle_rad, traj, mount)
    dx_rho /= np.maximum(np.asarray(range_m, float), 1e-9)[:, None]
    dx_alpha = (georeference(t_gps_s, range_m, np.asarray(scan_angle_rad) + _ALPHA_STEP_RAD, traj,
                             mount) - x) / _ALPHA_STEP_RAD  # fmt: skip
    return (sigma_range_m * (dx_rho @ n)) ** 2 + (sigma_scan_angle_rad * (dx_alpha @ n)) ** 2


def pos_normal_variance(t_gps_s, p_m, traj, mount: Mount, normal, sigma_position_m,
                        sigma_attitude_rad) -> np.ndarray:  # fmt: skip
    """Variance along ``normal`` of each return's displacement by the POS errors (position
    N, E, D and roll, pitch, heading; the trajectory's per-epoch σ when it has them, else the
    given ones)."""
    n = np.asarray(normal, float)
    poses = traj.interpolate(np.asarray(t_gps_s, float) + mount.time_offset_s)
    shape = (len(p_m), 3)
    sp = poses.sigma_p_m if poses.sigma_p_m is not None else np.broadcast_to(sigma_position_m, shape)
    sa = poses.sigma_rpy_rad if poses.sigma_rpy_rad is not None else \
        np.broadcast_to(sigma_attitude_rad, shape)
    var = (sp**2) @ (n**2)
    rxn = np.cross(np.asarray(p_m, float) - poses.p_lgf_m, n)
    h, pitch = poses.rpy_rad[:, 2], poses.rpy_rad[:, 1]
    a_head = np.broadcast_to([0.0, 0.0, 1.0], rxn.shape)
    a_pitch = np.stack([-np.sin(h), np.cos(h), np.zeros_like(h)], axis=1)  # Rz(ψ)·e_y
    a_roll = np.stack([np.cos(h) * np.cos(pitch), np.sin(h) * np.cos(pitch), -np.sin(pitch)],
                      axis=1)  # Rz(ψ)·Ry(θ)·e_x
    for j, a in enumerate((a_roll, a_pitch, a_head)):
        var = var + (sa[:, j] * np.einsum("ij,ij->i", rxn, a)) ** 2
    return var


# -- the assessment -------------------------------------------------------------------------


@dataclass
class _Pass:
    """One pass's returns (indices into the bundle's points) georeferenced with each mount."""

    idx: np.ndarray
    geo: dict[str, np.ndarray]  # state → (n, 3) LGF
    scanner_m: np.ndarray  # mean scanner position (LGF)

    @property
    def after(self) -> np.ndarray:
        return self.geo["after"]


def mount_from_truth(truth: dict, apriori: Mount) -> Mount:
    """The true mount of a simulated bundle (truth.json, DESIGN §4)."""
    try:
        bs = truth["boresight_deg"]
        return Mount(
            lever_arm_m=np.asarray(truth.get("lever_arm_m", apriori.lever_arm_m), float),
            nominal_rad=np.radians(truth.get("nominal_deg", np.degrees(apriori.nominal_rad))),
            boresight_rad=np.radians([float(bs[a]) for a in ANGLES]),
            range_offset_m=float(truth.get("range_offset_m", 0.0)),
            scan_angle_offset_rad=float(np.radians(truth.get("scan_angle_offset_deg", 0.0))),
            time_offset_s=float(truth.get("time_offset_s", 0.0)),
        )  # fmt: skip
    except (KeyError, TypeError, ValueError) as e:
        raise AssessError(f"truth.json: no usable true mount ({e!r})") from None


def _truth_rectangles(truth: dict) -> list[tuple[str, Rectangle]]:
    out = []
    for kind in ("validation_planes", "targets", "background"):
        for t in truth.get(kind, []) or []:
            n = np.asarray(t["normal"], float)
            incl = np.arccos(np.clip(-n[2], -1.0, 1.0))
            az = np.arctan2(n[1], n[0]) if np.hypot(n[0], n[1]) > 1e-9 else 0.0
            r = Rectangle.from_orientation(t["name"], t["center_lgf_m"], t["width_m"],
                                           t["height_m"], incl, az)  # fmt: skip
            out.append((t["name"], r))
    return out


def _match_truth(name: str, source: str, p_m: np.ndarray, truth_rects) -> Rectangle | None:
    if source == "site":
        for tn, r in truth_rects:
            if tn == name:
                return r
    best, best_frac = None, 0.8
    for _, r in truth_rects:
        frac = float(np.mean((np.abs(r.signed_distance(p_m)) < 0.25) & r.contains(p_m, 0.25)))
        if frac > best_frac:
            best, best_frac = r, frac
    return best


def _height_fit(pair, state, h, d, bin_m: float = 2.0) -> HeightFit:
    slope, intercept = np.polyfit(h, d, 1) if np.ptp(h) > 0 else (0.0, float(np.mean(d)))
    b = np.floor(h / bin_m).astype(np.int64)
    centres, medians = [], []
    for v in np.unique(b):
        sel = b == v
        if sel.sum() >= 5:
            centres.append((v + 0.5) * bin_m)
            medians.append(float(np.median(d[sel])))
    return HeightFit(tuple(pair), state, float(slope), float(intercept), int(h.size),
                     (float(h.min()), float(h.max())), np.array(centres), np.array(medians))  # fmt: skip


def assess(bundle, result: dict, pairs: Sequence[tuple[int, int]] | None = None,
           options: AssessOptions = AssessOptions(), truth: dict | None | str = "auto",
           progress: Callable[[str], None] | None = None) -> Assessment:  # fmt: skip
    """Compare passes before and after a calibration (see the module docstring).

    ``bundle``: a :class:`calib.io.bundle.Bundle` or its directory; ``result``: the result.json
    document (or its path); ``pairs``: (compared, reference) pass ids, default the reciprocal
    pairs; ``truth``: the truth.json document, None for none, "auto" to read the bundle's.
    ``progress(message)`` is called before each step.
    """
    from calib.io.bundle import read_bundle, read_truth

    say = progress or (lambda message: None)
    if not hasattr(bundle, "points"):
        say("reading the bundle")
        bundle = read_bundle(bundle)
    if not isinstance(result, dict):
        from calib.assess.history import load_result

        result = load_result(result)
    if isinstance(truth, str):
        truth = read_truth(bundle.path) if (Path(bundle.path) / "truth.json").exists() else None
    site, traj, pts = bundle.site, bundle.trajectory, bundle.points
    mounts = {"before": site.mount}
    mounts["after"], notes = mount_from_result(site.mount, result)
    if truth:
        try:
            mounts["true"] = mount_from_truth(truth, site.mount)
        except AssessError as e:
            notes.append(f"{e}; compared without the true mount")
    cov_bs, _ = boresight_covariance(result)
    apriori = result.get("apriori_deg")
    if isinstance(apriori, dict):
        site_deg = _angles_deg(site.mount.boresight_rad)
        if any(abs(float(apriori.get(a, site_deg[a])) - site_deg[a]) > 1e-6 for a in ANGLES):
            notes.append("the result's a-priori boresight differs from site.yaml's; 'before' "
                         "uses site.yaml's")  # fmt: skip
    headings = pass_headings_deg(bundle)
    if pairs is None:
        pairs = reciprocal_pairs(headings)
        if not pairs:
            raise AssessError(
                "no reciprocal passes (headings 180° ± 20° apart) in the bundle; sailed "
                "headings: " + ", ".join(f"{k}: {v:.0f}°" for k, v in sorted(headings.items()))
                + "; name the pairs to compare (e.g. --pairs 1:2)")  # fmt: skip
    pairs = [(int(a), int(b)) for a, b in pairs]
    for p in pairs:
        for pid in p:
            if pid not in headings:
                raise AssessError(f"pass {pid} (pair {p[0]}:{p[1]}) has no returns covered by the "
                                  f"trajectory; passes: {', '.join(map(str, sorted(headings)))}")  # fmt: skip
    rng = np.random.default_rng(options.seed)
    cache: dict[int, _Pass] = {}

    def get_pass(pid: int) -> _Pass:
        if pid in cache:
            return cache[pid]
        say(f"georeferencing pass {pid}")
        idx = np.flatnonzero(pts.pass_id == pid)
        bad = np.zeros(idx.size, bool)
        for m in mounts.values():
            bad |= traj.uncovered(pts.t_gps_s[idx] + m.time_offset_s)
        if bad.any():
            notes.append(f"pass {pid}: {int(bad.sum())} returns outside the trajectory left out")
            idx = idx[~bad]
        if idx.size > options.max_points_per_pass:
            notes.append(f"pass {pid}: a random {options.max_points_per_pass:,} of its "
                         f"{idx.size:,} returns used")  # fmt: skip
            idx = np.sort(rng.choice(idx, options.max_points_per_pass, replace=False))
        t, rho, alpha = pts.t_gps_s[idx], pts.range_m[idx], pts.scan_angle_rad[idx]
        geo = {s: np.ascontiguousarray(georeference(t, rho, alpha, traj, m))
               for s, m in mounts.items()}  # fmt: skip
        sub = slice(None, None, max(1, idx.size // 5000))
        origin = georeference(t[sub], np.zeros(t[sub].size), alpha[sub], traj, mounts["after"])
        cache[pid] = _Pass(idx, geo, origin.mean(axis=0))
        return cache[pid]

    use_auto = options.auto_planes or not site.validation_planes
    site_rects = [] if use_auto else [v.rectangle(bundle.frame) for v in site.validation_planes]
    truth_rects = []
    if truth:
        try:
            truth_rects = _truth_rectangles(truth)
        except (KeyError, TypeError, ValueError) as e:
            notes.append(f"truth.json: planes unreadable ({e!r}); no comparison with the truth")
    comparisons: list[Comparison] = []
    fits: list[HeightFit] = []
    for pair in pairs:
        A, B = get_pass(pair[0]), get_pass(pair[1])
        scanner_down = 0.5 * (A.scanner_m[2] + B.scanner_m[2])
        if use_auto:
            say(f"extracting planar patches seen by passes {pair[0]} and {pair[1]}")
            toward = 0.5 * (A.scanner_m + B.scanner_m)
            rects, source = extract_common_patches(A.after, B.after, toward, options), "auto"
            if not rects:
                notes.append(f"passes {pair[0]}:{pair[1]}: no planar patch seen by both")
        else:
            rects, source = site_rects, "site"
        pair_cmp = []
        for rect in rects:
            say(f"passes {pair[0]}:{pair[1]}: {rect.name}")
            c = _compare_surface(rect, source, pair, A, B, scanner_down, bundle, mounts["after"],
                                 cov_bs, options, truth_rects, notes)  # fmt: skip
            if c is not None:
                pair_cmp.append(c)
        if pair_cmp:
            h = np.concatenate([c.heights_m for c in pair_cmp])
            for state in STATES:
                d = np.concatenate([getattr(c, f"d_{state}_m") for c in pair_cmp])
                fits.append(_height_fit(pair, state, h, d))
        comparisons += pair_cmp
        if options.overlap:
            say(f"passes {pair[0]}:{pair[1]}: whole overlap")
            c = _compare_overlap(pair, A, B, scanner_down, options, rng, notes)
            if c is not None:
                comparisons.append(c)
    return Assessment(
        bundle_path=Path(bundle.path), pairs=tuple(pairs), headings_deg=headings,
        boresight_before_deg=_angles_deg(mounts["before"].boresight_rad),
        boresight_after_deg=_angles_deg(mounts["after"].boresight_rad),
        truth_boresight_deg=_angles_deg(mounts["true"].boresight_rad) if "true" in mounts
        else None,
        plane_source="auto" if use_auto else "site", comparisons=tuple(comparisons),
        height_fits=tuple(fits), notes=tuple(notes), options=options,
    )  # fmt: skip


def _covering(traj, t_gps_s: np.ndarray):
    """The part of the trajectory whose intervals cover the times (georeferencing a few returns
    then costs no more than their own intervals)."""
    tt = traj.t_gps_s
    i0 = max(int(np.searchsorted(tt, t_gps_s.min(), "right")) - 1, 0)
    i1 = min(int(np.searchsorted(tt, t_gps_s.max(), "left")) + 1, tt.size)
    return traj.select(slice(i0, max(i1, i0 + 2)))


def _heights(p_m: np.ndarray, scanner_down_m: float, options: AssessOptions) -> np.ndarray:
    return scanner_down_m - p_m[:, 2] + options.scanner_height_m


def _c2c_states(A: _Pass, B: _Pass, ia, ib, k, normal=None) -> dict:
    """C2C of the selected returns of A to those of B, for every georeferencing state."""
    return {s: c2c(A.geo[s][ia], B.geo[s][ib], k, orient_direction=normal) for s in A.geo}


def _compare_surface(rect, source, pair, A: _Pass, B: _Pass, scanner_down, bundle, after_mount,
                     cov_bs_rad2, options: AssessOptions, truth_rects, notes) -> Comparison | None:  # fmt: skip
    sel = {}
    for pid, P in zip(pair, (A, B)):
        cand = plane_candidates(P.after, rect, options.gate_m, options.margin_m)
        keep = clean_patch(P.after, cand, options.clean_sigma, options.clean_floor_m)
        if keep.sum() < options.min_points:
            notes.append(f"{rect.name}: pass {pid} has {int(keep.sum())} returns on it (fewer "
                         f"than {options.min_points}); not compared for passes {pair[0]}:{pair[1]}")  # fmt: skip
            return None
        sel[pid] = np.flatnonzero(keep)
    ia, ib = sel[pair[0]], sel[pair[1]]
    # compared returns beyond the reference's coverage (in any state) would meet local planes
    # extrapolated from its edge: left out, the same for every state
    inside = np.ones(ia.size, bool)
    for s in A.geo:
        inside &= within_coverage(A.geo[s][ia], B.geo[s][ib], rect.normal)
    if inside.sum() < options.min_points:
        notes.append(f"{rect.name}: passes {pair[0]}:{pair[1]} overlap on {int(inside.sum())} "
                     f"returns (fewer than {options.min_points}); not compared")  # fmt: skip
        return None
    ia = ia[inside]
    qa, qb = A.after[ia], B.after[ib]
    k = options.k
    collinear = collinear_fraction(qa, qb, rect.normal, k)
    if collinear > 0.1:
        notes.append(f"{rect.name} (passes {pair[0]}:{pair[1]}): {collinear:.0%} of the local "
                     f"planes (k = {k}) rest on nearly collinear neighbours (scan lines); C2C "
                     f"understates large offsets there: compare with a larger --knn (e.g. 12)")  # fmt: skip
    fa = fit_plane(qa, orient_like=rect.normal)
    fb = fit_plane(qb, orient_like=rect.normal)
    res = _c2c_states(A, B, ia, ib, k, rect.normal)
    # floor: the reference patch moved onto the compared patch's plane, its scatter kept
    r_b = (qb - fb.centroid_m) @ fb.normal
    on_b = qb - np.outer(r_b, fb.normal)
    on_a = on_b - np.outer((on_b - fa.centroid_m) @ fa.normal, fa.normal)
    floor = c2c(qa, on_a + np.outer(r_b, fa.normal), k).stats().median_m
    # expected level (module docstring)
    site, traj, pts = bundle.site, bundle.trajectory, bundle.points

    def errors(P, idx, q):
        """Scanner variance per return, mean POS variance, boresight Jacobian (all along n)."""
        j = P.idx[idx]
        t = pts.t_gps_s[j]
        sub = _covering(traj, t + after_mount.time_offset_s)
        obs = (t, pts.range_m[j], pts.scan_angle_rad[j], sub, after_mount, fa.normal)
        scan = scanner_normal_variance(*obs, site.sigma_range_m, site.sigma_scan_angle_rad)
        pos = pos_normal_variance(t, q, sub, after_mount, fa.normal, site.sigma_position_m,
                                  site.sigma_attitude_rad)  # fmt: skip
        return scan, float(np.mean(pos)), boresight_normal_jacobian(*obs)

    var_a, pos_a, jac_a = errors(A, ia, qa)
    var_b, pos_b, jac_b = errors(B, ib, qb)
    # the boresight's own uncertainty moves the two passes differently: (J_A − J_B)·δb
    from scipy.spatial import cKDTree

    jac_rel = jac_a - jac_b[cKDTree(qb).query(qa, k=1)[1]]
    w, v = np.linalg.eigh(cov_bs_rad2)
    bs_basis = jac_rel @ (v * np.sqrt(np.clip(w, 0.0, None)))
    pos_basis = np.full((len(qa), 1), math.sqrt(pos_a + pos_b))
    expect = lambda basis=None: expected_c2c(qa, qb, fa.normal, var_a, var_b, k, basis,  # noqa: E731
                                             seed=options.seed)  # fmt: skip
    exp_scan = expect()[0]
    exp_total, upper = expect(pos_basis)
    upper_cal = max(expect(np.column_stack([pos_basis, bs_basis]))[1], upper)
    truth_stats, truth_name = None, None
    if truth_rects:
        tr = _match_truth(rect.name, source, np.concatenate([qa, qb]), truth_rects)
        if tr is not None:
            truth_name = tr.name
            truth_stats = {s: {pid: distance_stats(tr.signed_distance(P.geo[s][idx]))
                               for pid, P, idx in ((pair[0], A, ia), (pair[1], B, ib))}
                           for s in A.geo}  # fmt: skip
    heights = _heights(qa, scanner_down, options)
    return Comparison(
        name=rect.name, source=source, pair=tuple(pair), height_m=float(np.median(heights)),
        n_reference=int(ib.size), collinear_fraction=collinear, before=res["before"].stats(),
        after=res["after"].stats(), true_mount=res["true"].stats() if "true" in res else None,
        before_signed_mean_m=res["before"].stats(signed=True).mean_m,
        after_signed_mean_m=res["after"].stats(signed=True).mean_m, floor_median_m=floor,
        expected_scanner_median_m=exp_scan, expected_median_m=exp_total, expected_upper_m=upper,
        expected_upper_calibration_m=upper_cal, pos_offset_sigma_m=math.sqrt(pos_a + pos_b),
        boresight_offset_sigma_m=float(np.sqrt(np.mean(np.sum(bs_basis**2, axis=1)))),
        rectangle=rect,
        truth_plane=truth_name, truth=truth_stats, d_before_m=res["before"].distance_m,
        d_after_m=res["after"].distance_m, heights_m=heights,
    )  # fmt: skip


def _compare_overlap(pair, A: _Pass, B: _Pass, scanner_down, options: AssessOptions, rng,
                     notes) -> Comparison | None:  # fmt: skip
    from scipy.spatial import cKDTree

    def subsample(n):
        if n <= options.max_overlap_points:
            return np.arange(n)
        return np.sort(rng.choice(n, options.max_overlap_points, replace=False))

    ia, ib = subsample(len(A.after)), subsample(len(B.after))
    r = options.overlap_radius_m
    da, _ = cKDTree(B.after[ib]).query(A.after[ia], k=1, distance_upper_bound=r)
    db, _ = cKDTree(A.after[ia]).query(B.after[ib], k=1, distance_upper_bound=r)
    ia, ib = ia[np.isfinite(da)], ib[np.isfinite(db)]
    if ia.size < options.min_points or ib.size < options.min_points:
        notes.append(f"passes {pair[0]}:{pair[1]}: overlap too small ({ia.size} and {ib.size} "
                     f"returns within {r:g} m of the other pass)")  # fmt: skip
        return None
    res = _c2c_states(A, B, ia, ib, options.k)
    heights = _heights(A.after[ia], scanner_down, options)
    return Comparison(
        name="overlap", source="overlap", pair=tuple(pair), height_m=float(np.median(heights)),
        n_reference=int(ib.size), collinear_fraction=None, before=res["before"].stats(),
        after=res["after"].stats(), true_mount=res["true"].stats() if "true" in res else None,
        before_signed_mean_m=None, after_signed_mean_m=None, floor_median_m=None,
        expected_scanner_median_m=None, expected_median_m=None, expected_upper_m=None,
        expected_upper_calibration_m=None, pos_offset_sigma_m=None,
        boresight_offset_sigma_m=None, rectangle=None, truth_plane=None, truth=None,
        d_before_m=res["before"].distance_m, d_after_m=res["after"].distance_m, heights_m=heights,
    )  # fmt: skip


# -- reporting ------------------------------------------------------------------------------


def fmt_length(x_m: float | None) -> str:
    """A distance as a surveyor reads it: 1.38 m, 48 mm, 3.2 mm, 0.41 mm."""
    if x_m is None or not math.isfinite(x_m):
        return "—"
    a = abs(x_m)
    if a >= 1.0:
        return f"{x_m:.2f} m"
    if a >= 0.01:
        return f"{x_m * 1e3:.0f} mm"
    if a >= 0.001:
        return f"{x_m * 1e3:.1f} mm"
    return f"{x_m * 1e3:.2f} mm"


def fmt_ratio(r: float) -> str:
    if not math.isfinite(r):
        return "∞"
    return f"{r:.0f}×" if r >= 10 else f"{r:.1f}×"


def verdict(c: Comparison) -> str:
    """One phrase on the distance after the calibration (surface comparisons)."""
    after = c.after.median_m
    if after > c.before.median_m:
        return "WORSE than before: check the result and the site's mount"
    if c.expected_upper_m is None:
        return ""
    if after <= c.expected_upper_m:
        return (f"at the noise level of the scanner and the POS (expected "
                f"{fmt_length(c.expected_median_m)}, 95 % bound {fmt_length(c.expected_upper_m)})")
    if after <= c.expected_upper_calibration_m:
        return (f"above the sensors' noise level ({fmt_length(c.expected_upper_m)}) but within "
                f"what the calibration's own σ allows ({fmt_length(c.expected_upper_calibration_m)})")
    return (f"larger than the sensors' noise ({fmt_length(c.expected_upper_m)}) and the "
            f"calibration's σ ({fmt_length(c.expected_upper_calibration_m)}) explain")


def _pair_label(a: Assessment, pair) -> str:
    h = a.headings_deg
    return f"{pair[0]} ({h[pair[0]]:.0f}°) ↔ {pair[1]} ({h[pair[1]]:.0f}°)"


def plot_histograms(a: Assessment, out_dir: Path) -> list[Path]:
    """Overlaid histograms of the C2C before and after, one PNG per surface and pair
    (log-spaced bins: before and after differ by orders of magnitude)."""
    from matplotlib.figure import Figure

    paths = []
    for c in a.comparisons:
        d0, d1 = c.d_before_m * 1e3, c.d_after_m * 1e3
        pos = np.concatenate([d0[d0 > 0], d1[d1 > 0]])
        if pos.size == 0:
            continue
        lo = max(float(np.percentile(pos, 0.5)), 1e-3)
        hi = max(float(pos.max()), lo * 10)
        bins = np.geomspace(lo, hi, 60)
        fig = Figure(figsize=(7.5, 4.2))
        ax = fig.subplots()
        where = "whole overlap" if c.source == "overlap" else f"{c.name} ({c.height_m:.0f} m)"
        for d, label, color in ((d0, "before (a-priori mount)", "tab:blue"),
                                (d1, "after (estimated mount)", "tab:brown")):  # fmt: skip
            med = float(np.median(d))
            ax.hist(np.clip(d, lo, hi), bins=bins, histtype="stepfilled", alpha=0.45, color=color,
                    label=f"{label}: median {fmt_length(med / 1e3)}")  # fmt: skip
            ax.axvline(med, color=color, lw=1.5, ls="--")
        if c.expected_median_m:
            ax.axvline(c.expected_median_m * 1e3, color="k", lw=1.0, ls=":",
                       label=f"expected (scanner + POS): {fmt_length(c.expected_median_m)}")  # fmt: skip
        ax.set_xscale("log")
        ax.set_xlabel("cloud-to-cloud distance (mm, local LS plane, k = %d)" % a.options.k)
        ax.set_ylabel("returns")
        ax.set_title(f"{where} — passes {_pair_label(a, c.pair)}")
        ax.legend(fontsize=8)
        fig.subplots_adjust(left=0.09, right=0.98, bottom=0.12, top=0.92)
        p = Path(out_dir) / f"hist_{c.pair[0]}-{c.pair[1]}_{c.name}.png"
        fig.savefig(p, dpi=110)
        paths.append(p)
    return paths


def plot_heights(a: Assessment, out_dir: Path, max_points: int = 20000) -> list[Path]:
    """Distance against the height above the water, before and after, with the binned medians
    and the fitted line; one PNG per pair."""
    from matplotlib.figure import Figure

    rng = np.random.default_rng(0)
    paths = []
    for pair in a.pairs:
        planes = a.planes(pair)
        if not planes:
            continue
        h = np.concatenate([c.heights_m for c in planes])
        fig = Figure(figsize=(9.0, 5.0))
        axes = fig.subplots(1, 2, sharey=True)
        sub = rng.choice(h.size, min(h.size, max_points), replace=False)
        for ax, state, color in zip(axes, STATES, ("tab:blue", "tab:brown")):
            d = np.concatenate([getattr(c, f"d_{state}_m") for c in planes]) * 1e3
            fit = a.height_fit(pair, state)
            ax.scatter(d[sub], h[sub], s=2, alpha=0.25, color=color, lw=0)
            ax.plot(fit.bin_medians_m * 1e3, fit.bin_heights_m, "o-", color="k", ms=3, lw=1,
                    label="median per 2 m of height")  # fmt: skip
            hh = np.linspace(*fit.height_span_m, 20)
            ax.plot((fit.intercept_m + fit.slope_m_per_m * hh) * 1e3, hh, "--", color="tab:red",
                    label=f"fit: {fit.slope_m_per_m * 1e3:.1f} mm per m of height")  # fmt: skip
            ax.set_xlabel(f"C2C distance {state} (mm)")
            ax.set_title(f"{state} the calibration")
            ax.set_xlim(left=0)
            ax.legend(fontsize=8, loc="lower right")
        axes[0].set_ylabel("height above the water (m)")
        fig.suptitle(f"Distance against height — passes {_pair_label(a, pair)}")
        fig.subplots_adjust(left=0.07, right=0.98, bottom=0.1, top=0.87, wspace=0.06)
        p = Path(out_dir) / f"height_{pair[0]}-{pair[1]}.png"
        fig.savefig(p, dpi=110)
        paths.append(p)
    return paths


def summary_lines(a: Assessment) -> list[str]:
    """The improvement in words, one sentence per line."""
    lines = []
    for pair in a.pairs:
        label = _pair_label(a, pair)
        planes = sorted(a.planes(pair), key=lambda c: -c.height_m)
        for c in planes:
            lines.append(f"Passes {label}: median C2C on {c.name} ({c.height_m:.0f} m) went from "
                         f"{fmt_length(c.before.median_m)} to {fmt_length(c.after.median_m)} "
                         f"({fmt_ratio(c.improvement)} smaller); {verdict(c)}.")  # fmt: skip
        for c in a.comparisons:
            if c.source == "overlap" and c.pair == pair:
                lines.append(f"Passes {label}, whole overlap ({c.after.count:,} returns): median "
                             f"from {fmt_length(c.before.median_m)} to "
                             f"{fmt_length(c.after.median_m)}.")  # fmt: skip
        try:
            b, f = a.height_fit(pair, "before"), a.height_fit(pair, "after")
        except KeyError:
            continue
        if b.height_span_m[1] - b.height_span_m[0] >= 5.0:
            grow = "grew" if b.slope_m_per_m > 0 else "changed"
            lines.append(
                f"Passes {label}: before the calibration the distances {grow} by "
                f"{b.slope_m_per_m * 1e3:.1f} mm per metre of height ({b.height_span_m[0]:.0f}–"
                f"{b.height_span_m[1]:.0f} m), after by {f.slope_m_per_m * 1e3:.1f} mm per metre"
                + ("; a boresight error moves reciprocal passes apart in proportion to the range, "
                   "so this growth is its signature." if b.slope_m_per_m > 2e-3 else "."))  # fmt: skip
            if abs(f.slope_m_per_m) > max(2e-3, 0.2 * abs(b.slope_m_per_m)):
                lines.append(f"Passes {label}: the distances after still change with height: a "
                             f"boresight error remains.")  # fmt: skip
    if a.truth_boresight_deg is not None:
        err = {k: a.boresight_after_deg[k] - a.truth_boresight_deg[k] for k in ANGLES}
        lines.append("Simulated bundle: the estimate differs from the true boresight by " +
                     ", ".join(f"{k} {err[k]:+.4f}°" for k in ANGLES) + ".")  # fmt: skip
    return lines


def _stats_cells(s: DistanceStats) -> list[str]:
    return [fmt_length(s.mean_m), fmt_length(s.median_m), fmt_length(s.rms_m), fmt_length(s.p95_m)]


def assessment_markdown(a: Assessment, figures: Sequence[Path] = ()) -> str:
    """``assessment.md``: the summary in words, the tables and the figures."""
    name = a.bundle_path.name
    b0, b1 = a.boresight_before_deg, a.boresight_after_deg
    out = [f"# Relative accuracy assessment — {name}", ""]
    out += [
        f"Boresight before (site.yaml a priori): roll {b0['roll']:.4f}°, pitch {b0['pitch']:.4f}°, "
        f"yaw {b0['yaw']:.4f}°; after (calibration result): roll {b1['roll']:.4f}°, pitch "
        f"{b1['pitch']:.4f}°, yaw {b1['yaw']:.4f}° (canonical convention).",
        "",
        f"Method: the same returns of two passes are georeferenced with each mount and compared "
        f"with cloud-to-cloud distances to local least-squares planes (k = {a.options.k}; "
        f"CloudCompare's C2C `-MODEL LS KNN {a.options.k}`), the first pass of a pair against "
        f"the second. Surfaces: "
        + ("the site's validation planes" if a.plane_source == "site"
           else "planar patches found automatically in both passes (the site lists no "
                "validation planes, or --auto-planes)")
        + f", and the whole overlap of the passes. Heights are above the water line "
          f"(the scanner's mean height + {a.options.scanner_height_m:g} m).",
        "", "## Summary", "",
    ]  # fmt: skip
    out += [f"- {line}" for line in summary_lines(a)]
    out += ["", "*Expected*: the median C2C the scanner sigmas and the POS sigmas of site.yaml "
            "give for these very returns and C2C's local planes (POS errors as one offset per "
            "pass); *floor*: the median once the two patches' planes coincide (their own scatter "
            "kept); *calib. σ*: the σ of the relative offset the result's own boresight σ "
            "allows.", ""]  # fmt: skip
    for pair in a.pairs:
        rows = [c for c in a.comparisons if c.pair == pair]
        if not rows:
            continue
        out += [f"## Passes {_pair_label(a, pair)}", ""]
        head = ["surface", "height", "returns", "before mean", "before median", "before RMS",
                "before p95", "after mean", "after median", "after RMS", "after p95", "×",
                "expected", "floor", "calib. σ"]  # fmt: skip
        truth_col = any(c.true_mount is not None for c in rows)
        if truth_col:
            head.append("true mount median")
        out += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        for c in sorted(rows, key=lambda c: (c.source == "overlap", -c.height_m)):
            cells = [c.name if c.source != "overlap" else "whole overlap", f"{c.height_m:.1f} m",
                     f"{c.after.count:,}", *_stats_cells(c.before), *_stats_cells(c.after),
                     fmt_ratio(c.improvement), fmt_length(c.expected_median_m),
                     fmt_length(c.floor_median_m), fmt_length(c.boresight_offset_sigma_m)]  # fmt: skip
            if truth_col:
                cells.append(fmt_length(c.true_mount.median_m if c.true_mount else None))
            out.append("| " + " | ".join(cells) + " |")
        out.append("")
        truth_rows = [c for c in rows if c.truth]
        if truth_rows:
            out += ["Against the true planes (simulated bundle): signed distance of each pass's "
                    "returns, mean ± standard deviation.", "",
                    "| surface | true plane | pass | before | after | true mount |",
                    "|---|---|---|---|---|---|"]  # fmt: skip
            for c in sorted(truth_rows, key=lambda c: -c.height_m):
                for pid in c.pair:
                    cells = [f"{fmt_length(c.truth[s][pid].mean_m)} ± {fmt_length(c.truth[s][pid].std_m)}"
                             if s in c.truth else "—" for s in ("before", "after", "true")]  # fmt: skip
                    out.append(f"| {c.name} | {c.truth_plane} | {pid} | " + " | ".join(cells) + " |")
            out.append("")
    if a.notes:
        out += ["## Notes", ""] + [f"- {n}" for n in a.notes] + [""]
    if figures:
        out += ["## Figures", ""] + [f"![{p.stem}]({p.name})" for p in figures] + [""]
    return "\n".join(out)


def write_assessment(a: Assessment, out_dir) -> dict[str, list[Path]]:
    """Write ``assessment.md``, ``assessment.json`` and the PNG figures into ``out_dir``."""
    d = Path(out_dir)
    d.mkdir(parents=True, exist_ok=True)
    figures = plot_heights(a, d) + plot_histograms(a, d)
    md = d / "assessment.md"
    md.write_text(assessment_markdown(a, figures), encoding="utf-8")
    js = d / "assessment.json"
    js.write_text(json.dumps(a.to_dict(), indent=2) + "\n", encoding="utf-8")
    return {"markdown": [md], "json": [js], "figures": figures}
