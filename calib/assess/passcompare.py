"""Two passes of a pair compared (:mod:`calib.assess.comparison`): on one surface
(:func:`compare_surface`: C2C before and after, its floor, the level the sensors' errors allow,
the distances to the true plane) or on their whole overlap (:func:`compare_overlap`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from calib.assess.c2c import c2c, distance_stats
from calib.assess.expected import (
    boresight_normal_jacobian,
    expected_c2c,
    pos_normal_variance,
    scanner_normal_variance,
)
from calib.assess.results import AssessOptions, Comparison
from calib.assess.surfaces import clean_patch, collinear_fraction, plane_candidates, within_coverage
from calib.core.geometry import Rectangle, fit_plane
from calib.core.georef import Mount

if TYPE_CHECKING:  # (an annotation: the bundle is read by the caller)
    from calib.io.bundle import Bundle


@dataclass
class PassClouds:
    """One pass's returns (indices into the bundle's points) georeferenced with each mount."""

    idx: np.ndarray
    geo: dict[str, np.ndarray]  # state → (n, 3) LGF
    scanner_m: np.ndarray  # mean scanner position (LGF)

    @property
    def after(self) -> np.ndarray:
        return self.geo["after"]


@dataclass(frozen=True, kw_only=True)
class SurfaceContext:
    """What comparing any surface of an assessment needs beyond the two passes."""

    bundle: Bundle
    after_mount: Mount  # the result's
    cov_bs_rad2: np.ndarray  # the result's boresight covariance
    options: AssessOptions
    truth_rects: list[tuple[str, Rectangle]]
    notes: list[str]


def match_truth(name: str, source: str, p_m: np.ndarray, truth_rects) -> Rectangle | None:
    """The true plane of a surface: by name for the site's, else the true rectangle holding
    more than 80 % of its returns."""
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


def _covering(traj, t_gps_s: np.ndarray):
    """The part of the trajectory whose intervals cover the times (georeferencing a few returns
    then costs no more than their own intervals)."""
    tt = traj.t_gps_s
    i0 = max(int(np.searchsorted(tt, t_gps_s.min(), "right")) - 1, 0)
    i1 = min(int(np.searchsorted(tt, t_gps_s.max(), "left")) + 1, tt.size)
    return traj.select(slice(i0, max(i1, i0 + 2)))


def _heights(p_m: np.ndarray, scanner_down_m: float, options: AssessOptions) -> np.ndarray:
    return scanner_down_m - p_m[:, 2] + options.scanner_height_m


def _c2c_states(A: PassClouds, B: PassClouds, ia, ib, k, normal=None) -> dict:
    """C2C of the selected returns of A to those of B, for every georeferencing state."""
    return {s: c2c(A.geo[s][ia], B.geo[s][ib], k, orient_direction=normal) for s in A.geo}


def _surface_returns(rect, pair, A: PassClouds, B: PassClouds, options: AssessOptions, notes):
    """The returns of each pass on the surface (indices into the passes' clouds), the compared
    ones within the reference's coverage; None (a note says why) when too few."""
    sel = {}
    for pid, P in zip(pair, (A, B), strict=False):
        cand = plane_candidates(P.after, rect, options.gate_m, options.margin_m)
        keep = clean_patch(P.after, cand, options.clean_sigma, options.clean_floor_m)
        if keep.sum() < options.min_points:
            notes.append(
                f"{rect.name}: pass {pid} has {int(keep.sum())} returns on it (fewer "
                f"than {options.min_points}); not compared for passes {pair[0]}:{pair[1]}"
            )
            return None
        sel[pid] = np.flatnonzero(keep)
    ia, ib = sel[pair[0]], sel[pair[1]]
    # compared returns beyond the reference's coverage (in any state) would meet local planes
    # extrapolated from its edge: left out, the same for every state
    inside = np.ones(ia.size, bool)
    for s in A.geo:
        inside &= within_coverage(A.geo[s][ia], B.geo[s][ib], rect.normal)
    if inside.sum() < options.min_points:
        notes.append(
            f"{rect.name}: passes {pair[0]}:{pair[1]} overlap on {int(inside.sum())} "
            f"returns (fewer than {options.min_points}); not compared"
        )
        return None
    return ia[inside], ib


def _floor_median_m(qa: np.ndarray, qb: np.ndarray, fa, fb, k: int) -> float:
    """The floor: the C2C median once the reference patch is moved onto the compared patch's
    plane, its scatter kept."""
    r_b = (qb - fb.centroid_m) @ fb.normal
    on_b = qb - np.outer(r_b, fb.normal)
    on_a = on_b - np.outer((on_b - fa.centroid_m) @ fa.normal, fa.normal)
    return c2c(qa, on_a + np.outer(r_b, fa.normal), k).stats().median_m


def _return_errors(P: PassClouds, idx, q, ctx: SurfaceContext, normal):
    """Scanner variance per return, mean POS variance, boresight Jacobian (all along
    ``normal``) of the returns ``idx`` of a pass."""
    site, traj, pts = ctx.bundle.site, ctx.bundle.trajectory, ctx.bundle.points
    mount = ctx.after_mount
    j = P.idx[idx]
    t = pts.t_gps_s[j]
    sub = _covering(traj, t + mount.time_offset_s)
    obs = (t, pts.range_m[j], pts.scan_angle_rad[j], sub, mount, normal)
    scan = scanner_normal_variance(*obs, site.sigma_range_m, site.sigma_scan_angle_rad)
    pos = pos_normal_variance(t, q, sub, mount, normal, site.sigma_position_m, site.sigma_attitude_rad)
    return scan, float(np.mean(pos)), boresight_normal_jacobian(*obs)


@dataclass(frozen=True, kw_only=True)
class _Expected:
    """The C2C median the sensors' errors allow (calib.assess.expected)."""

    scanner_median_m: float  # the scanner's noise alone
    median_m: float  # with the POS errors as one offset per pass
    upper_m: float  # the upper bound one pair can show
    upper_calibration_m: float  # … with the result's own boresight σ
    pos_offset_sigma_m: float
    boresight_offset_sigma_m: float


def _expected(A, B, ia, ib, qa, qb, normal, ctx: SurfaceContext) -> _Expected:
    """The expected level after the calibration (:mod:`calib.assess.expected`)."""
    var_a, pos_a, jac_a = _return_errors(A, ia, qa, ctx, normal)
    var_b, pos_b, jac_b = _return_errors(B, ib, qb, ctx, normal)
    # the boresight's own uncertainty moves the two passes differently: (J_A − J_B)·δb
    from scipy.spatial import cKDTree

    jac_rel = jac_a - jac_b[cKDTree(qb).query(qa, k=1)[1]]
    w, v = np.linalg.eigh(ctx.cov_bs_rad2)
    bs_basis = jac_rel @ (v * np.sqrt(np.clip(w, 0.0, None)))
    pos_basis = np.full((len(qa), 1), math.sqrt(pos_a + pos_b))
    k, seed = ctx.options.k, ctx.options.seed

    def expect(basis=None):
        return expected_c2c(qa, qb, normal, var_a, var_b, k, basis, seed=seed)

    exp_scan = expect()[0]
    exp_total, upper = expect(pos_basis)
    upper_cal = max(expect(np.column_stack([pos_basis, bs_basis]))[1], upper)
    return _Expected(
        scanner_median_m=exp_scan,
        median_m=exp_total,
        upper_m=upper,
        upper_calibration_m=upper_cal,
        pos_offset_sigma_m=math.sqrt(pos_a + pos_b),
        boresight_offset_sigma_m=float(np.sqrt(np.mean(np.sum(bs_basis**2, axis=1)))),
    )


def _against_truth(rect, source, pair, A, B, ia, ib, qa, qb, truth_rects):
    """The true plane's name and the signed distances' statistics to it, per state and pass
    (None, None: no true plane)."""
    if not truth_rects:
        return None, None
    tr = match_truth(rect.name, source, np.concatenate([qa, qb]), truth_rects)
    if tr is None:
        return None, None
    stats = {
        s: {
            pid: distance_stats(tr.signed_distance(P.geo[s][idx]))
            for pid, P, idx in ((pair[0], A, ia), (pair[1], B, ib))
        }
        for s in A.geo
    }
    return tr.name, stats


def compare_surface(
    rect, source, pair, A: PassClouds, B: PassClouds, scanner_down, ctx: SurfaceContext
) -> Comparison | None:
    """The pair compared on one surface (``source``: "site" or "auto"); None (a note says why)
    when either pass has too few returns on it."""
    options, notes = ctx.options, ctx.notes
    chosen = _surface_returns(rect, pair, A, B, options, notes)
    if chosen is None:
        return None
    ia, ib = chosen
    qa, qb = A.after[ia], B.after[ib]
    k = options.k
    collinear = collinear_fraction(qa, qb, rect.normal, k)
    if collinear > 0.1:
        notes.append(
            f"{rect.name} (passes {pair[0]}:{pair[1]}): {collinear:.0%} of the local "
            f"planes (k = {k}) rest on nearly collinear neighbours (scan lines); C2C "
            f"understates large offsets there: compare with a larger --knn (e.g. 12)"
        )
    fa = fit_plane(qa, orient_like=rect.normal)
    fb = fit_plane(qb, orient_like=rect.normal)
    res = _c2c_states(A, B, ia, ib, k, rect.normal)
    floor = _floor_median_m(qa, qb, fa, fb, k)
    exp = _expected(A, B, ia, ib, qa, qb, fa.normal, ctx)
    truth_name, truth_stats = _against_truth(rect, source, pair, A, B, ia, ib, qa, qb, ctx.truth_rects)
    heights = _heights(qa, scanner_down, options)
    return Comparison(
        name=rect.name,
        source=source,
        pair=tuple(pair),
        height_m=float(np.median(heights)),
        n_reference=int(ib.size),
        collinear_fraction=collinear,
        before=res["before"].stats(),
        after=res["after"].stats(),
        true_mount=res["true"].stats() if "true" in res else None,
        before_signed_mean_m=res["before"].stats(signed=True).mean_m,
        after_signed_mean_m=res["after"].stats(signed=True).mean_m,
        floor_median_m=floor,
        expected_scanner_median_m=exp.scanner_median_m,
        expected_median_m=exp.median_m,
        expected_upper_m=exp.upper_m,
        expected_upper_calibration_m=exp.upper_calibration_m,
        pos_offset_sigma_m=exp.pos_offset_sigma_m,
        boresight_offset_sigma_m=exp.boresight_offset_sigma_m,
        rectangle=rect,
        truth_plane=truth_name,
        truth=truth_stats,
        d_before_m=res["before"].distance_m,
        d_after_m=res["after"].distance_m,
        heights_m=heights,
    )


def compare_overlap(
    pair, A: PassClouds, B: PassClouds, scanner_down, options: AssessOptions, rng, notes
) -> Comparison | None:
    """The pair compared on their whole overlap: the returns of each pass within
    ``overlap_radius_m`` of the other's (at most ``max_overlap_points`` of each, drawn with
    ``rng``); None (a note says why) when the overlap is too small."""
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
        notes.append(
            f"passes {pair[0]}:{pair[1]}: overlap too small ({ia.size} and {ib.size} "
            f"returns within {r:g} m of the other pass)"
        )
        return None
    res = _c2c_states(A, B, ia, ib, options.k)
    heights = _heights(A.after[ia], scanner_down, options)
    return Comparison(
        name="overlap",
        source="overlap",
        pair=tuple(pair),
        height_m=float(np.median(heights)),
        n_reference=int(ib.size),
        collinear_fraction=None,
        before=res["before"].stats(),
        after=res["after"].stats(),
        true_mount=res["true"].stats() if "true" in res else None,
        before_signed_mean_m=None,
        after_signed_mean_m=None,
        floor_median_m=None,
        expected_scanner_median_m=None,
        expected_median_m=None,
        expected_upper_m=None,
        expected_upper_calibration_m=None,
        pos_offset_sigma_m=None,
        boresight_offset_sigma_m=None,
        rectangle=None,
        truth_plane=None,
        truth=None,
        d_before_m=res["before"].distance_m,
        d_after_m=res["after"].distance_m,
        heights_m=heights,
    )
