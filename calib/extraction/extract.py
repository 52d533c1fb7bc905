"""Planar target extraction from georeferenced passes (thesis §4.4.4, §4.5.3 and Appendix B.2).

Per pass and per target (``seeded`` mode, the thesis's semi-automatic procedure with the
operator's click replaced by the approximate centre in site.yaml):

1. **candidates**: the pass's points within ``search_radius_m`` + the target's half-diagonal of
   its configured centre (the centre is approximate, and an a-priori boresight that is wrong by
   2° moves a target at 16 m by about 0.6 m);
2. **reflectivity**: a white target on a concrete wall is several times brighter. The
   intensities are divided by the cosine of incidence (when the beam origins are given: a 45°
   target seen from below is otherwise hardly brighter than the wall), then a two-class split
   of their logarithms (Otsu's threshold) is used when the two classes differ by at least
   ``min_contrast``; when the corrected intensities show no contrast the raw ones are tried (a
   scanner whose intensity does not fall with incidence). The target is the bright class (the
   dark one when its configured reflectivity is below 0.5). Without contrast every candidate is
   kept and a warning says so;
3. **RANSAC planes** on those points (thesis defaults: inlier distance 0.01 m, stop as soon as
   a plane holds 98 % of the points; otherwise the adaptive number of samples for a 99.9 %
   chance of one all-inlier sample), among planes within ``max_tilt_rad`` of the configured
   normal; each plane is refined by least squares and its points kept within a band of five
   robust σ of it (at least three inlier distances: the band removes gross outliers only, so
   the noise of the kept points is not truncated, which would bias σ̂0²). The band is taken out
   and the next plane sought, up to :data:`MAX_PARALLEL_PLANES`: without contrast, a target
   standing proud of a wall of its own orientation is the second plane, the wall the first;
4. **the target's own rectangle**: each plane's points fall into connected clusters; among the
   clusters no larger than the configured size (a partial view may be smaller) the best size
   match is the target (near-equal matches: the one nearer the seed along the normal, then the
   larger); a box of the configured size around it, shrunk by ``edge_margin_m`` (mixed returns
   on the edges), keeps the target and nothing of its surroundings. When every cluster is
   larger than the target (the wall beside it, a neighbour touching it) the target is
   **rejected** in that pass with the nearest cluster's size: it is never trimmed to a box
   around a median point, which would hand the adjustment a piece of wall as the target.

A target with fewer than ``min_points_per_pass`` points in a pass is *missing* from that pass
(*rejected* as above when points of its orientation were there): a warning names both, its few
points are dropped, and the run continues (a target with too few points over all passes is the
adjustment's error, not the extraction's; one lost in two passes or more makes the calibration's
verdict questionable, :mod:`calib.boresight.checks.verdict`).

``auto`` mode finds the seeds itself: per pass, the bright points (the same two-class split
over the whole pass) are grouped into connected clusters, each gets a RANSAC plane and its
extent, and clusters are matched to the configured targets by size and inclination (an
optimal assignment; targets that look alike are told apart by their configured centres). The
matched clusters then seed step 1–4.

:func:`voxel_subsample` keeps one point per cubic voxel: the point nearest the voxel's centre
(ties: the earliest), in the original order.

One target in one pass (steps 1–4, the options and the error) is :mod:`calib.extraction.target`;
the point-cloud building blocks (RANSAC plane, intensity split, incidence correction, clusters,
extents) are in :mod:`calib.extraction.segmentation`.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from scipy.optimize import linear_sum_assignment

from calib.core.geometry import Rectangle, fit_plane
from calib.extraction.segmentation import (
    clusters,
    in_plane_axes,
    incidence_corrected,
    intensity_split,
    link_radius,
    ransac_plane,
    robust_extent,
)
from calib.extraction.target import (  # noqa: F401  (MODES, extract_target: the package's interface)
    MODES,
    ExtractionError,
    ExtractOptions,
    TargetPass,
    extract_target,
    missing_target,
)

# -- automatic seeds -----------------------------------------------------------------------


def auto_seeds(
    p_m: np.ndarray,
    intensity: np.ndarray,
    idx: np.ndarray,
    rects: list[Rectangle],
    opts: ExtractOptions,
    rng: np.random.Generator,
    origin_m: np.ndarray | None = None,
) -> dict[str, np.ndarray]:
    """Seeds (cluster centres) of the configured targets found without their centres in one
    pass: bright planar clusters matched to the targets by size and inclination."""
    refl = (
        intensity[idx] if origin_m is None else incidence_corrected(p_m[idx], intensity[idx], origin_m[idx])
    )
    split = intensity_split(refl, opts.min_contrast)
    if split.threshold is None:
        return {}
    bright = idx[refl >= split.threshold]
    if bright.size < opts.min_points_per_pass:
        return {}
    q = p_m[bright]
    labels = clusters(q, link_radius(q, min(min(r.width_m, r.height_m) for r in rects)))
    found = []  # (centre, inclination, extent along the horizontal and up the slope)
    for lab in np.unique(labels):
        m = labels == lab
        if m.sum() < opts.min_points_per_pass:
            continue
        c = q[m]
        plane = ransac_plane(
            c, max(opts.ransac_distance_m, 0.02), opts.ransac_stop_fraction, opts.ransac_max_iterations, rng
        )
        if plane is None or plane.inliers.sum() < opts.min_points_per_pass:
            continue
        n = plane.normal if plane.normal[2] <= 0 else -plane.normal  # up-facing (NED)
        incl = float(np.arccos(np.clip(-n[2], -1.0, 1.0)))
        horiz = np.cross([0.0, 0.0, 1.0], n)
        horiz = horiz / np.linalg.norm(horiz) if np.linalg.norm(horiz) > 1e-6 else np.array([1.0, 0.0, 0.0])
        u, v = in_plane_axes(n, horiz)
        inl = c[plane.inliers]
        ctr = inl.mean(axis=0)
        ext = robust_extent(np.column_stack([(inl - ctr) @ u, (inl - ctr) @ v]))
        found.append((ctr, incl, ext))
    if not found:
        return {}
    cost = np.full((len(rects), len(found)), 1e6)
    for i, r in enumerate(rects):
        size = np.array([r.width_m, r.height_m])
        for j, (ctr, incl, ext) in enumerate(found):
            size_err = np.abs(np.log(np.maximum(ext, 1e-3) / size))
            incl_err = abs(incl - abs(r.inclination_rad))
            if np.all(size_err <= np.log(1.0 + opts.size_tolerance) + 0.1) and incl_err <= np.radians(15.0):
                # alike targets are told apart by their configured centres (the 1e-4 weight
                # keeps distance a tie-breaker only)
                cost[i, j] = size_err.sum() + incl_err + 1e-4 * np.linalg.norm(ctr - r.center_m)
    rows, cols = linear_sum_assignment(cost)
    return {rects[i].name: found[j][0] for i, j in zip(rows, cols, strict=False) if cost[i, j] < 1e6}


# -- all targets in all passes -------------------------------------------------------------


@dataclass
class Extraction:
    target_names: list[str]
    pass_ids: list[int]
    found: list[TargetPass]  # one per (pass, target), pass-major
    subsample_m: float | None = None
    warnings: list[str] = field(default_factory=list)

    def indices(self) -> tuple[np.ndarray, np.ndarray]:
        """(point indices ascending, target index of each)."""
        idx = [f.indices for f in self.found]
        tgt = [np.full(f.n_points, self.target_names.index(f.target)) for f in self.found]
        if not idx:
            return np.empty(0, np.int64), np.empty(0, np.int64)
        i, t = np.concatenate(idx), np.concatenate(tgt)
        order = np.argsort(i, kind="stable")
        return i[order], t[order]

    def counts(self) -> dict[int, dict[str, int]]:
        """Points per pass and per target."""
        out = {pid: dict.fromkeys(self.target_names, 0) for pid in self.pass_ids}
        for f in self.found:
            out[f.pass_id][f.target] += f.n_points
        return out

    def without(self, names: list[str]) -> Extraction:
        """The extraction with the targets ``names`` left out (their warnings stay)."""
        keep = [n for n in self.target_names if n not in names]
        found = [f for f in self.found if f.target in keep]
        return Extraction(keep, self.pass_ids, found, self.subsample_m, list(self.warnings))

    def lost_passes(self) -> dict[str, list[int]]:
        """Per target, the passes it is missing from or rejected in."""
        out: dict[str, list[int]] = {}
        for f in self.found:
            if f.n_points == 0:
                out.setdefault(f.target, []).append(f.pass_id)
        return out

    def totals(self) -> dict[str, int]:
        out = dict.fromkeys(self.target_names, 0)
        for f in self.found:
            out[f.target] += f.n_points
        return out


#: the extraction's options when the caller gives none (frozen, shared)
_DEFAULT_OPTIONS = ExtractOptions()


def extract(
    p_lgf_m,
    intensity,
    pass_id,
    rects: list[Rectangle],
    options: ExtractOptions = _DEFAULT_OPTIONS,
    origin_lgf_m=None,
    progress=None,
) -> Extraction:
    """Extract every target (``rects``: configured size, orientation, approximate centre in
    the LGF) from every pass of georeferenced points ``p_lgf_m`` (n, 3) with their
    ``intensity`` and ``pass_id``; ``origin_lgf_m`` (n, 3), the scanner's position at each
    return, lets the intensities be corrected for incidence (recommended: a target seen
    obliquely is otherwise hardly brighter than the wall). ``progress(done, total)`` is called
    after each pass."""
    p = np.asarray(p_lgf_m, float)
    origin = None if origin_lgf_m is None else np.asarray(origin_lgf_m, float)
    inten = np.asarray(intensity, float)
    pid = np.asarray(pass_id)
    if not rects:
        raise ExtractionError("the site configures no targets")
    rng = np.random.default_rng(options.seed)
    pass_ids = [int(x) for x in np.unique(pid)]
    out = Extraction([r.name for r in rects], pass_ids, [])
    for k, pass_no in enumerate(pass_ids):
        idx = np.flatnonzero(pid == pass_no)
        seeds = {}
        if options.mode == "auto":
            seeds = auto_seeds(p, inten, idx, rects, options, rng, origin)
        for r in rects:
            if options.mode == "auto" and r.name not in seeds:
                tp = missing_target(
                    r.name, pass_no, 0, 0, 1.0, "no bright planar cluster of its size and inclination"
                )
            else:
                tp = extract_target(p, inten, idx, r, pass_no, options, rng, seeds.get(r.name), origin)
            out.found.append(tp)
            if tp.status == "rejected":
                out.warnings.append(f"target {r.name} is rejected in pass {pass_no}: {tp.note}")
            elif tp.n_points == 0:
                out.warnings.append(f"target {r.name} is missing from pass {pass_no}: {tp.note}")
            elif tp.note:
                out.warnings.append(f"target {r.name} in pass {pass_no}: {tp.note}")
        if progress is not None:
            progress(k + 1, len(pass_ids))
    return out


def voxel_subsample(p_m, voxel_m: float) -> np.ndarray:
    """Indices (ascending) of one point per cubic voxel of edge ``voxel_m``: the point nearest
    the voxel's centre, the earliest on a tie. The grid is anchored at the LGF origin."""
    p = np.asarray(p_m, float)
    if not (np.isfinite(voxel_m) and voxel_m > 0):
        raise ExtractionError(f"subsampling voxel {voxel_m!r} m: expected a positive size")
    if p.shape[0] == 0:
        return np.empty(0, np.int64)
    cell = np.floor(p / voxel_m)
    dist = np.sum((p - (cell + 0.5) * voxel_m) ** 2, axis=1)
    cell = (cell - cell.min(axis=0)).astype(np.int64)
    dims = cell.max(axis=0) + 1
    key = (cell[:, 0] * dims[1] + cell[:, 1]) * dims[2] + cell[:, 2]
    order = np.lexsort((np.arange(p.shape[0]), dist, key))
    first = np.ones(order.size, bool)
    first[1:] = key[order][1:] != key[order][:-1]
    return np.sort(order[first])


def subsample(ext: Extraction, p_lgf_m, voxel_m: float) -> Extraction:
    """The extraction with each target's points of each pass thinned by
    :func:`voxel_subsample` (passes are thinned separately: each keeps its own view)."""
    p = np.asarray(p_lgf_m, float)
    found = [replace(f, indices=f.indices[voxel_subsample(p[f.indices], voxel_m)]) for f in ext.found]
    return Extraction(ext.target_names, ext.pass_ids, found, voxel_m, list(ext.warnings))


def from_labels(target_index, pass_id, target_names: list[str]) -> Extraction:
    """An extraction from known labels (per point: index into ``target_names``, −1 none),
    e.g. a simulator's truth, for tests and comparisons."""
    ti = np.asarray(target_index)
    pid = np.asarray(pass_id)
    pass_ids = [int(x) for x in np.unique(pid)]
    found = []
    for pass_no in pass_ids:
        for j, name in enumerate(target_names):
            sel = np.flatnonzero((pid == pass_no) & (ti == j))
            found.append(
                TargetPass(name, pass_no, sel, sel.size, sel.size, 1.0, None, float("nan"), None, "labelled")
            )
    warnings = [
        f"target {f.target} is missing from pass {f.pass_id}: no labelled point"
        for f in found
        if f.n_points == 0
    ]
    return Extraction(list(target_names), pass_ids, found, None, warnings)


def initial_planes(ext: Extraction, p_lgf_m, rects: list[Rectangle]) -> list[tuple[np.ndarray, float] | None]:
    """A-priori plane of each target (normal, d; None with < 3 points), from its points over
    all passes: the centroid of the combined points (thesis §4.4.4) and the mean of the
    per-pass least-squares normals (oriented like the configured one). The thesis fits the
    combined data; but with an a-priori boresight off by a degree or two the passes' copies of
    a target no longer overlap, and the combined cloud of a small target is a thick slab whose
    fitted normal can be off by tens of degrees, while every pass on its own is a clean plane
    tilted by about the boresight error."""
    p = np.asarray(p_lgf_m, float)
    out: list[tuple[np.ndarray, float] | None] = []
    for r in rects:
        parts = [f.indices for f in ext.found if f.target == r.name and f.n_points >= 3]
        if not parts:
            out.append(None)
            continue
        normals, weights = [], []
        for sel in parts:
            fit = fit_plane(p[sel], orient_like=r.normal)
            normals.append(fit.normal)
            weights.append(sel.size)
        n = np.average(np.array(normals), axis=0, weights=weights)
        n /= np.linalg.norm(n)
        centroid = p[np.concatenate(parts)].mean(axis=0)
        out.append((n, -float(n @ centroid)))
    return out
