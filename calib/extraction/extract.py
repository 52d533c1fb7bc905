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
   ``min_contrast``; the target is the bright class (the dark one when its configured
   reflectivity is below 0.5). Without contrast every candidate is kept and a warning says so;
3. **RANSAC plane** on those points (thesis defaults: inlier distance 0.01 m, stop as soon as
   a plane holds 98 % of the points; otherwise the adaptive number of samples for a 99.9 %
   chance of one all-inlier sample), among planes within ``max_tilt_rad`` of the configured
   normal; the plane is refined by least squares and the points kept within a band of five
   robust σ of it (at least three inlier distances): the band removes gross outliers only, so
   the noise of the kept points is not truncated (truncating it would bias σ̂0²);
4. **the target's own rectangle**: the kept points fall into connected clusters; the cluster
   whose extent (along the target's width axis and up its slope) best matches the configured
   size is the target; then a box of the configured size around it, shrunk by
   ``edge_margin_m`` (mixed returns on the edges), keeps the target and nothing of its
   surroundings.

A target with fewer than ``min_points_per_pass`` points in a pass is *missing* from that pass:
a warning names both, its few points are dropped, and the run continues (a target with too few
points over all passes is the adjustment's error, not the extraction's).

``auto`` mode finds the seeds itself: per pass, the bright points (the same two-class split
over the whole pass) are grouped into connected clusters, each gets a RANSAC plane and its
extent, and clusters are matched to the configured targets by size and inclination (an
optimal assignment; targets that look alike are told apart by their configured centres). The
matched clusters then seed step 1–4.

:func:`voxel_subsample` keeps one point per cubic voxel: the point nearest the voxel's centre
(ties: the earliest), in the original order.

The point-cloud building blocks (RANSAC plane, intensity split, incidence correction, clusters,
extents) are in :mod:`calib.extraction.segmentation`.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from scipy.optimize import linear_sum_assignment

from calib.core.errors import CalibError
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

MODES = ("seeded", "auto")


class ExtractionError(CalibError, ValueError):
    """The extraction cannot run on this input (the message says why and what to do)."""


@dataclass(frozen=True)
class ExtractOptions:
    mode: str = "seeded"
    search_radius_m: float = 2.0  # plus each target's half-diagonal
    ransac_distance_m: float = 0.01
    ransac_stop_fraction: float = 0.98
    ransac_max_iterations: int = 2000
    max_tilt_rad: float = float(np.radians(30.0))  # RANSAC planes vs the configured normal
    min_contrast: float = 2.0  # intensity ratio (geometric means) target / surroundings
    edge_margin_m: float = 0.02
    size_tolerance: float = 0.25  # relative; beyond it the cluster is not the target alone
    min_points_per_pass: int = 10
    seed: int = 0  # RANSAC's random generator

    def __post_init__(self):
        if self.mode not in MODES:
            raise ExtractionError(f"extraction mode {self.mode!r}: expected seeded or auto")
        for name in ("search_radius_m", "ransac_distance_m", "min_contrast"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ExtractionError(f"extraction option {name} = {v!r}: expected a positive number")
        if not 0.0 < self.ransac_stop_fraction <= 1.0:
            raise ExtractionError(
                f"ransac_stop_fraction = {self.ransac_stop_fraction!r}: expected a fraction in (0, 1]"
            )
        if self.edge_margin_m < 0:
            raise ExtractionError(f"edge_margin_m = {self.edge_margin_m!r}: expected ≥ 0")


# -- one target in one pass ----------------------------------------------------------------


@dataclass(frozen=True)
class TargetPass:
    """What the extraction found of one target in one pass."""

    target: str
    pass_id: int
    indices: np.ndarray  # into the points given to the extraction
    n_candidates: int  # within the search radius
    n_target_class: int  # of those, in the target's intensity class
    contrast: float  # intensity ratio of the two classes (1 when none)
    normal: np.ndarray | None  # RANSAC plane of the pass
    rms_m: float  # of the kept points about that plane
    extent_m: np.ndarray | None  # (width, height) of the chosen cluster
    note: str = ""  # why nothing (or something doubtful) was kept

    @property
    def n_points(self) -> int:
        return int(self.indices.size)


def _missing(target, pass_id, n_cand, n_class, contrast, note) -> TargetPass:
    return TargetPass(
        target, pass_id, np.empty(0, np.int64), n_cand, n_class, contrast, None, float("nan"), None, note
    )


def extract_target(
    p_m: np.ndarray,
    intensity: np.ndarray,
    idx: np.ndarray,
    rect: Rectangle,
    pass_id: int,
    opts: ExtractOptions,
    rng: np.random.Generator,
    seed_m=None,
    origin_m: np.ndarray | None = None,
) -> TargetPass:
    """Steps 1–4 of the module docstring for one target (``rect``: configured size,
    orientation and approximate centre) among the points ``idx`` of one pass. With the beam
    origins ``origin_m`` (n, 3) the intensities are corrected for incidence first."""
    centre = rect.center_m if seed_m is None else np.asarray(seed_m, float)
    radius = opts.search_radius_m + 0.5 * np.hypot(rect.width_m, rect.height_m)
    pts = p_m[idx]
    near = np.sum((pts - centre) ** 2, axis=1) <= radius**2
    cand = idx[near]
    n_cand = cand.size
    if n_cand < opts.min_points_per_pass:
        return _missing(
            rect.name, pass_id, n_cand, 0, 1.0, f"{n_cand} points within {radius:.1f} m of its centre"
        )
    refl = (
        intensity[cand]
        if origin_m is None
        else incidence_corrected(p_m[cand], intensity[cand], origin_m[cand])
    )
    split = intensity_split(refl, opts.min_contrast)
    note = ""
    if split.threshold is None:
        cls = cand
        note = (
            f"no reflectivity contrast around it (ratio {split.contrast:.2f} < "
            f"{opts.min_contrast:g}): separated from its surroundings by geometry only"
        )
    elif rect.reflectivity >= 0.5:
        cls = cand[refl >= split.threshold]
    else:
        cls = cand[refl < split.threshold]
    if cls.size < opts.min_points_per_pass:
        return _missing(
            rect.name,
            pass_id,
            n_cand,
            cls.size,
            split.contrast,
            f"{cls.size} of {n_cand} nearby points have its reflectivity",
        )
    q = p_m[cls]
    plane = ransac_plane(
        q,
        opts.ransac_distance_m,
        opts.ransac_stop_fraction,
        opts.ransac_max_iterations,
        rng,
        rect.normal,
        opts.max_tilt_rad,
    )
    if plane is None or plane.inliers.sum() < opts.min_points_per_pass:
        return _missing(
            rect.name,
            pass_id,
            n_cand,
            cls.size,
            split.contrast,
            "no plane with its orientation among its points",
        )
    normal, d = plane.normal, plane.d
    keep = plane.inliers
    cos_tilt = np.cos(opts.max_tilt_rad)
    for _ in range(3):  # least squares on the band, then a band of five robust σ
        fit = fit_plane(q[keep], orient_like=normal)
        if abs(fit.normal @ rect.normal) < cos_tilt:  # the points are not a plane of that
            return _missing(
                rect.name,
                pass_id,
                n_cand,
                cls.size,
                split.contrast,  # tilt
                "no plane with its orientation among its points",
            )
        normal, d = fit.normal, fit.d
        dist = q @ normal + d
        sigma = 1.4826 * np.median(np.abs(dist[keep] - np.median(dist[keep])))
        band = max(3.0 * opts.ransac_distance_m, 5.0 * sigma)
        keep = np.abs(dist) <= band
    q, sel = q[keep], cls[keep]
    # clusters of the kept points; the one whose extent matches the configured size
    u, v = in_plane_axes(normal, rect.u_axis)
    ab = np.column_stack([(q - centre) @ u, (q - centre) @ v])
    size = np.array([rect.width_m, rect.height_m])
    labels = clusters(q, link_radius(q, min(rect.width_m, rect.height_m)))
    best, best_key = None, None
    for lab in np.unique(labels):
        m = labels == lab
        if m.sum() < opts.min_points_per_pass:
            continue
        ext = robust_extent(ab[m])
        mismatch = float(np.sum(np.abs(np.log(np.maximum(ext, 1e-3) / size))))
        key = (round(mismatch, 1), -int(m.sum()))  # near-equal matches: the larger cluster
        if best_key is None or key < best_key:
            best, best_key = m, key
    if best is None:
        return _missing(
            rect.name,
            pass_id,
            n_cand,
            cls.size,
            split.contrast,
            f"its points form no cluster of at least {opts.min_points_per_pass} points",
        )
    ext = robust_extent(ab[best])
    too_big = np.any(ext > size * (1.0 + opts.size_tolerance) + 0.05)
    if too_big:
        # the cluster is more than the target (no contrast, or a bright neighbour touching
        # it): centre a target-sized box on the cluster's median point
        mid = np.median(ab[best], axis=0)
        note = "; ".join(
            filter(
                None,
                [
                    note,
                    (
                        f"its cluster measures {ext[0]:.2f} × {ext[1]:.2f} m against the configured "
                        f"{size[0]:.2f} × {size[1]:.2f} m: a box of the configured size around its median "
                        f"point was kept"
                    ),
                ],
            )
        )
    else:
        # the middle of the robust span (stray points do not pull it); on a partial view
        # (extent below the size) the box still holds the whole cluster
        mid = np.percentile(ab[best], [2.0, 98.0], axis=0).mean(axis=0)
    half = 0.5 * size - opts.edge_margin_m
    inside = np.all(np.abs(ab - mid) <= half, axis=1) & best
    sel = sel[inside]
    if sel.size < opts.min_points_per_pass:
        return _missing(
            rect.name,
            pass_id,
            n_cand,
            cls.size,
            split.contrast,
            f"only {sel.size} points inside its rectangle",
        )
    rms = float(np.sqrt(np.mean((p_m[sel] @ normal + d) ** 2)))
    return TargetPass(
        rect.name, pass_id, np.sort(sel), n_cand, cls.size, split.contrast, normal, rms, ext, note
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
    return {rects[i].name: found[j][0] for i, j in zip(rows, cols) if cost[i, j] < 1e6}


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

    def totals(self) -> dict[str, int]:
        out = dict.fromkeys(self.target_names, 0)
        for f in self.found:
            out[f.target] += f.n_points
        return out


def extract(
    p_lgf_m,
    intensity,
    pass_id,
    rects: list[Rectangle],
    options: ExtractOptions = ExtractOptions(),
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
                tp = _missing(
                    r.name, pass_no, 0, 0, 1.0, "no bright planar cluster of its size and inclination"
                )
            else:
                tp = extract_target(p, inten, idx, r, pass_no, options, rng, seeds.get(r.name), origin)
            out.found.append(tp)
            if tp.n_points == 0:
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
