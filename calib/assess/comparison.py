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

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from calib.assess.expected import boresight_covariance
from calib.assess.mounts import mount_from_result, mount_from_truth
from calib.assess.pairs import pass_headings_deg, reciprocal_pairs
from calib.assess.passcompare import PassClouds, SurfaceContext, compare_overlap, compare_surface
from calib.assess.results import (
    ANGLES,
    DEFAULT_ASSESS_OPTIONS,
    STATES,
    AssessError,
    Assessment,
    AssessOptions,
    Comparison,
    HeightFit,
)
from calib.assess.surfaces import extract_common_patches
from calib.core.geometry import Rectangle
from calib.core.georef import georeference

if TYPE_CHECKING:  # (an annotation: the bundle is read when needed)
    from calib.io.bundle import Bundle


def _angles_deg(v_rad) -> dict[str, float]:
    return {a: float(x) for a, x in zip(ANGLES, np.degrees(v_rad), strict=False)}


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


def _read_inputs(bundle, result, truth: dict | None | str, say) -> tuple[Bundle, dict, dict | None]:
    """The bundle, the result document and the truth document (or None) from what was given."""
    from calib.io.bundle import read_bundle, read_truth

    if not hasattr(bundle, "points"):
        say("reading the bundle")
        bundle = read_bundle(bundle)
    if not isinstance(result, dict):
        from calib.assess.history import load_result

        result = load_result(result)
    if isinstance(truth, str):
        truth = read_truth(bundle.path) if (Path(bundle.path) / "truth.json").exists() else None
    return bundle, result, truth


def _mounts(site, result: dict, truth: dict | None) -> tuple[dict, list[str]]:
    """The mounts compared: "before" (site.yaml's), "after" (the result's) and, with a truth,
    "true"; and the notes about them."""
    mounts = {"before": site.mount}
    mounts["after"], notes = mount_from_result(site.mount, result)
    if truth:
        try:
            mounts["true"] = mount_from_truth(truth, site.mount)
        except AssessError as e:
            notes.append(f"{e}; compared without the true mount")
    apriori = result.get("apriori_deg")
    if isinstance(apriori, dict):
        site_deg = _angles_deg(site.mount.boresight_rad)
        if any(abs(float(apriori.get(a, site_deg[a])) - site_deg[a]) > 1e-6 for a in ANGLES):
            notes.append(
                "the result's a-priori boresight differs from site.yaml's; 'before' uses site.yaml's"
            )
    return mounts, notes


def _checked_pairs(pairs, headings: dict[int, float]) -> list[tuple[int, int]]:
    """The pairs to compare (default the reciprocal ones), each pass with covered returns."""
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
    return pairs


class _Passes:
    """Each pass's returns georeferenced with every mount, once (on first use)."""

    def __init__(self, bundle, mounts: dict, options: AssessOptions, rng, notes: list[str], say):
        self.bundle, self.mounts, self.options = bundle, mounts, options
        self.rng, self.notes, self.say = rng, notes, say
        self.cache: dict[int, PassClouds] = {}

    def get(self, pid: int) -> PassClouds:
        if pid not in self.cache:
            self.cache[pid] = self._georeferenced(pid)
        return self.cache[pid]

    def _georeferenced(self, pid: int) -> PassClouds:
        """The pass's returns covered by the trajectory (a random ``max_points_per_pass`` of
        them at most) georeferenced with each mount."""
        self.say(f"georeferencing pass {pid}")
        traj, pts, options = self.bundle.trajectory, self.bundle.points, self.options
        idx = np.flatnonzero(pts.pass_id == pid)
        bad = np.zeros(idx.size, bool)
        for m in self.mounts.values():
            bad |= traj.uncovered(pts.t_gps_s[idx] + m.time_offset_s)
        if bad.any():
            self.notes.append(f"pass {pid}: {int(bad.sum())} returns outside the trajectory left out")
            idx = idx[~bad]
        if idx.size > options.max_points_per_pass:
            self.notes.append(
                f"pass {pid}: a random {options.max_points_per_pass:,} of its {idx.size:,} returns used"
            )
            idx = np.sort(self.rng.choice(idx, options.max_points_per_pass, replace=False))
        t, rho, alpha = pts.t_gps_s[idx], pts.range_m[idx], pts.scan_angle_rad[idx]
        geo = {s: np.ascontiguousarray(georeference(t, rho, alpha, traj, m)) for s, m in self.mounts.items()}
        sub = slice(None, None, max(1, idx.size // 5000))
        origin = georeference(t[sub], np.zeros(t[sub].size), alpha[sub], traj, self.mounts["after"])
        return PassClouds(idx, geo, origin.mean(axis=0))


def _truth_planes(truth: dict | None, notes: list[str]) -> list[tuple[str, Rectangle]]:
    """The true planes of a simulated bundle (none without a truth, or an unreadable one)."""
    if not truth:
        return []
    try:
        return _truth_rectangles(truth)
    except (KeyError, TypeError, ValueError) as e:
        notes.append(f"truth.json: planes unreadable ({e!r}); no comparison with the truth")
        return []


def _compare_pair(pair, passes: _Passes, site_rects, ctx: SurfaceContext, say):
    """One pair compared on its surfaces (the site's, else extracted from both passes): the
    comparisons and the fits of the distances against the height."""
    A, B = passes.get(pair[0]), passes.get(pair[1])
    scanner_down = 0.5 * (A.scanner_m[2] + B.scanner_m[2])
    if site_rects is None:
        say(f"extracting planar patches seen by passes {pair[0]} and {pair[1]}")
        toward = 0.5 * (A.scanner_m + B.scanner_m)
        rects, source = extract_common_patches(A.after, B.after, toward, ctx.options), "auto"
        if not rects:
            ctx.notes.append(f"passes {pair[0]}:{pair[1]}: no planar patch seen by both")
    else:
        rects, source = site_rects, "site"
    pair_cmp = []
    for rect in rects:
        say(f"passes {pair[0]}:{pair[1]}: {rect.name}")
        c = compare_surface(rect, source, pair, A, B, scanner_down, ctx)
        if c is not None:
            pair_cmp.append(c)
    fits = []
    if pair_cmp:
        h = np.concatenate([c.heights_m for c in pair_cmp])
        for state in STATES:
            d = np.concatenate([getattr(c, f"d_{state}_m") for c in pair_cmp])
            fits.append(_height_fit(pair, state, h, d))
    return pair_cmp, fits


def assess(
    bundle,
    result: dict,
    pairs: Sequence[tuple[int, int]] | None = None,
    options: AssessOptions = DEFAULT_ASSESS_OPTIONS,
    truth: dict | None | str = "auto",
    progress: Callable[[str], None] | None = None,
) -> Assessment:
    """Compare passes before and after a calibration (see the module docstring).

    ``bundle``: a :class:`calib.io.bundle.Bundle` or its directory; ``result``: the result.json
    document (or its path); ``pairs``: (compared, reference) pass ids, default the reciprocal
    pairs; ``truth``: the truth.json document, None for none, "auto" to read the bundle's.
    ``progress(message)`` is called before each step.
    """
    say = progress or (lambda message: None)
    bundle, result, truth = _read_inputs(bundle, result, truth, say)
    site = bundle.site
    mounts, notes = _mounts(site, result, truth)
    cov_bs, _ = boresight_covariance(result)
    headings = pass_headings_deg(bundle)
    pairs = _checked_pairs(pairs, headings)
    rng = np.random.default_rng(options.seed)
    passes = _Passes(bundle, mounts, options, rng, notes, say)
    use_auto = options.auto_planes or not site.validation_planes
    site_rects = None if use_auto else [v.rectangle(bundle.frame) for v in site.validation_planes]
    ctx = SurfaceContext(
        bundle=bundle,
        after_mount=mounts["after"],
        cov_bs_rad2=cov_bs,
        options=options,
        truth_rects=_truth_planes(truth, notes),
        notes=notes,
    )
    comparisons: list[Comparison] = []
    fits: list[HeightFit] = []
    for pair in pairs:
        pair_cmp, pair_fits = _compare_pair(pair, passes, site_rects, ctx, say)
        comparisons += pair_cmp
        fits += pair_fits
        if options.overlap:
            say(f"passes {pair[0]}:{pair[1]}: whole overlap")
            A, B = passes.get(pair[0]), passes.get(pair[1])
            c = compare_overlap(pair, A, B, 0.5 * (A.scanner_m[2] + B.scanner_m[2]), options, rng, notes)
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
