"""Relative accuracy assessment of a calibration (thesis §4.4.6, §4.5.4; docs/architecture.md §7 "Assessment").

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
reference's coverage in either geometry are left out
(:func:`calib.assess.surfaces.within_coverage`: C2C would extrapolate the reference's edge
there). The same returns are compared before and after, so the two figures differ only
by the mount.

**Expected level after the calibration** (:mod:`calib.assess.expected`): from the scanner sigmas
and the geometry, the POS errors as one offset per pass, and the result's own boresight σ; the
*upper* bound of the median one pair can show is what the verdict uses. Beside the prediction
the *floor* is measured: the C2C median once the reference patch is moved onto the compared
patch's plane (its own scatter kept) — what the two patches give when they agree exactly.

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

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from calib.assess.c2c import c2c, distance_stats
from calib.assess.expected import (
    boresight_covariance,
    boresight_normal_jacobian,
    expected_c2c,
    pos_normal_variance,
    scanner_normal_variance,
)
from calib.assess.mounts import mount_from_result, mount_from_truth
from calib.assess.pairs import pass_headings_deg, reciprocal_pairs
from calib.assess.results import ANGLES, STATES, AssessError, Assessment, AssessOptions, Comparison, HeightFit
from calib.assess.surfaces import (
    clean_patch,
    collinear_fraction,
    extract_common_patches,
    plane_candidates,
    within_coverage,
)
from calib.core.geometry import Rectangle, fit_plane
from calib.core.georef import georeference


def _angles_deg(v_rad) -> dict[str, float]:
    return {a: float(x) for a, x in zip(ANGLES, np.degrees(v_rad))}


@dataclass
class _Pass:
    """One pass's returns (indices into the bundle's points) georeferenced with each mount."""

    idx: np.ndarray
    geo: dict[str, np.ndarray]  # state → (n, 3) LGF
    scanner_m: np.ndarray  # mean scanner position (LGF)

    @property
    def after(self) -> np.ndarray:
        return self.geo["after"]


def _truth_rectangles(truth: dict) -> list[tuple[str, Rectangle]]:
    out = []
    for kind in ("validation_planes", "targets", "background"):
        for t in truth.get(kind, []) or []:
            n = np.asarray(t["normal"], float)
            incl = np.arccos(np.clip(-n[2], -1.0, 1.0))
            az = np.arctan2(n[1], n[0]) if np.hypot(n[0], n[1]) > 1e-9 else 0.0
            r = Rectangle.from_orientation(
                t["name"], t["center_lgf_m"], t["width_m"], t["height_m"], incl, az
            )
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
    return HeightFit(
        tuple(pair),
        state,
        float(slope),
        float(intercept),
        int(h.size),
        (float(h.min()), float(h.max())),
        np.array(centres),
        np.array(medians),
    )


def assess(
    bundle,
    result: dict,
    pairs: Sequence[tuple[int, int]] | None = None,
    options: AssessOptions = AssessOptions(),
    truth: dict | None | str = "auto",
    progress: Callable[[str], None] | None = None,
) -> Assessment:
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
            notes.append(
                "the result's a-priori boresight differs from site.yaml's; 'before' uses site.yaml's"
            )
    headings = pass_headings_deg(bundle)
    if pairs is None:
        pairs = reciprocal_pairs(headings)
        if not pairs:
            raise AssessError(
                "no reciprocal passes (headings 180° ± 20° apart) in the bundle; sailed "
                "headings: "
                + ", ".join(f"{k}: {v:.0f}°" for k, v in sorted(headings.items()))
                + "; name the pairs to compare (e.g. --pairs 1:2)"
            )
    pairs = [(int(a), int(b)) for a, b in pairs]
    for p in pairs:
        for pid in p:
            if pid not in headings:
                raise AssessError(
                    f"pass {pid} (pair {p[0]}:{p[1]}) has no returns covered by the "
                    f"trajectory; passes: {', '.join(map(str, sorted(headings)))}"
                )
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
            notes.append(
                f"pass {pid}: a random {options.max_points_per_pass:,} of its {idx.size:,} returns used"
            )
            idx = np.sort(rng.choice(idx, options.max_points_per_pass, replace=False))
        t, rho, alpha = pts.t_gps_s[idx], pts.range_m[idx], pts.scan_angle_rad[idx]
        geo = {s: np.ascontiguousarray(georeference(t, rho, alpha, traj, m)) for s, m in mounts.items()}
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
            c = _compare_surface(
                rect,
                source,
                pair,
                A,
                B,
                scanner_down,
                bundle,
                mounts["after"],
                cov_bs,
                options,
                truth_rects,
                notes,
            )
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
        bundle_path=Path(bundle.path),
        pairs=tuple(pairs),
        headings_deg=headings,
        boresight_before_deg=_angles_deg(mounts["before"].boresight_rad),
        boresight_after_deg=_angles_deg(mounts["after"].boresight_rad),
        truth_boresight_deg=_angles_deg(mounts["true"].boresight_rad) if "true" in mounts else None,
        plane_source="auto" if use_auto else "site",
        comparisons=tuple(comparisons),
        height_fits=tuple(fits),
        notes=tuple(notes),
        options=options,
    )


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


def _compare_surface(
    rect,
    source,
    pair,
    A: _Pass,
    B: _Pass,
    scanner_down,
    bundle,
    after_mount,
    cov_bs_rad2,
    options: AssessOptions,
    truth_rects,
    notes,
) -> Comparison | None:
    sel = {}
    for pid, P in zip(pair, (A, B)):
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
    ia = ia[inside]
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
    # floor: the reference patch moved onto the compared patch's plane, its scatter kept
    r_b = (qb - fb.centroid_m) @ fb.normal
    on_b = qb - np.outer(r_b, fb.normal)
    on_a = on_b - np.outer((on_b - fa.centroid_m) @ fa.normal, fa.normal)
    floor = c2c(qa, on_a + np.outer(r_b, fa.normal), k).stats().median_m
    # expected level (calib.assess.expected)
    site, traj, pts = bundle.site, bundle.trajectory, bundle.points

    def errors(P, idx, q):
        """Scanner variance per return, mean POS variance, boresight Jacobian (all along n)."""
        j = P.idx[idx]
        t = pts.t_gps_s[j]
        sub = _covering(traj, t + after_mount.time_offset_s)
        obs = (t, pts.range_m[j], pts.scan_angle_rad[j], sub, after_mount, fa.normal)
        scan = scanner_normal_variance(*obs, site.sigma_range_m, site.sigma_scan_angle_rad)
        pos = pos_normal_variance(
            t, q, sub, after_mount, fa.normal, site.sigma_position_m, site.sigma_attitude_rad
        )
        return scan, float(np.mean(pos)), boresight_normal_jacobian(*obs)

    var_a, pos_a, jac_a = errors(A, ia, qa)
    var_b, pos_b, jac_b = errors(B, ib, qb)
    # the boresight's own uncertainty moves the two passes differently: (J_A − J_B)·δb
    from scipy.spatial import cKDTree

    jac_rel = jac_a - jac_b[cKDTree(qb).query(qa, k=1)[1]]
    w, v = np.linalg.eigh(cov_bs_rad2)
    bs_basis = jac_rel @ (v * np.sqrt(np.clip(w, 0.0, None)))
    pos_basis = np.full((len(qa), 1), math.sqrt(pos_a + pos_b))

    def expect(basis=None):
        return expected_c2c(qa, qb, fa.normal, var_a, var_b, k, basis, seed=options.seed)

    exp_scan = expect()[0]
    exp_total, upper = expect(pos_basis)
    upper_cal = max(expect(np.column_stack([pos_basis, bs_basis]))[1], upper)
    truth_stats, truth_name = None, None
    if truth_rects:
        tr = _match_truth(rect.name, source, np.concatenate([qa, qb]), truth_rects)
        if tr is not None:
            truth_name = tr.name
            truth_stats = {
                s: {
                    pid: distance_stats(tr.signed_distance(P.geo[s][idx]))
                    for pid, P, idx in ((pair[0], A, ia), (pair[1], B, ib))
                }
                for s in A.geo
            }
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
        expected_scanner_median_m=exp_scan,
        expected_median_m=exp_total,
        expected_upper_m=upper,
        expected_upper_calibration_m=upper_cal,
        pos_offset_sigma_m=math.sqrt(pos_a + pos_b),
        boresight_offset_sigma_m=float(np.sqrt(np.mean(np.sum(bs_basis**2, axis=1)))),
        rectangle=rect,
        truth_plane=truth_name,
        truth=truth_stats,
        d_before_m=res["before"].distance_m,
        d_after_m=res["after"].distance_m,
        heights_m=heights,
    )


def _compare_overlap(
    pair, A: _Pass, B: _Pass, scanner_down, options: AssessOptions, rng, notes
) -> Comparison | None:
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
