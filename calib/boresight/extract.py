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
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from scipy import sparse
from scipy.optimize import linear_sum_assignment
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from calib.core.geometry import Rectangle, fit_plane

MODES = ("seeded", "auto")


class ExtractionError(ValueError):
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


# -- building blocks ------------------------------------------------------------------------


@dataclass(frozen=True)
class RansacPlane:
    normal: np.ndarray  # unit, oriented like the hint when one is given
    d: float  # nᵀx + d = 0
    inliers: np.ndarray  # (n,) bool, within the inlier distance of the refined plane
    iterations: int  # hypotheses drawn

    @property
    def inlier_fraction(self) -> float:
        return float(self.inliers.mean()) if self.inliers.size else 0.0


_SCORE_POINTS = 20_000  # hypotheses are scored on at most this many points
_BATCH = 128  # hypotheses per vectorized batch


def ransac_plane(
    p_m,
    distance_m: float = 0.01,
    stop_fraction: float = 0.98,
    max_iterations: int = 2000,
    rng: np.random.Generator | None = None,
    normal_hint=None,
    max_tilt_rad: float | None = None,
    confidence: float = 0.999,
) -> RansacPlane | None:
    """RANSAC plane of points (n, 3), or None when no admissible plane has 3 inliers.

    Hypotheses from random triplets are scored by their inlier count (|distance| ≤
    ``distance_m``), in vectorized batches; sampling stops when a plane holds
    ``stop_fraction`` of the points, after the adaptive number of samples for ``confidence``,
    or at ``max_iterations``. With ``normal_hint`` and ``max_tilt_rad`` only planes whose
    normal is within that angle of the hint are admissible. The best plane is refined by
    least squares on its inliers.
    """
    p = np.asarray(p_m, float)
    n = p.shape[0]
    if n < 3:
        return None
    rng = rng if rng is not None else np.random.default_rng(0)
    score = p if n <= _SCORE_POINTS else p[rng.choice(n, _SCORE_POINTS, replace=False)]
    hint = None if normal_hint is None else np.asarray(normal_hint, float)
    cos_tilt = None if (hint is None or max_tilt_rad is None) else np.cos(max_tilt_rad)
    best_count, best = 0, None
    needed = max_iterations
    drawn = 0
    while drawn < min(needed, max_iterations):
        idx = rng.integers(0, n, (_BATCH, 3))
        a, b, c = p[idx[:, 0]], p[idx[:, 1]], p[idx[:, 2]]
        ab, ac = b - a, c - a
        nrm = np.cross(ab, ac)
        length = np.linalg.norm(nrm, axis=1)
        # near-collinear triples (points of one scan line) span no plane: sin(angle) ≥ 0.1
        ok = length > 0.1 * np.linalg.norm(ab, axis=1) * np.linalg.norm(ac, axis=1) + 1e-12
        nrm = nrm[ok] / length[ok, None]
        a = a[ok]
        drawn += _BATCH
        if cos_tilt is not None:
            keep = np.abs(nrm @ hint) >= cos_tilt
            nrm, a = nrm[keep], a[keep]
        if nrm.shape[0] == 0:
            continue
        d = -np.einsum("ij,ij->i", nrm, a)
        counts = np.count_nonzero(np.abs(score @ nrm.T + d) <= distance_m, axis=0)
        k = int(np.argmax(counts))
        if counts[k] > best_count:
            best_count, best = int(counts[k]), (nrm[k], d[k])
            w = best_count / score.shape[0]
            if w >= stop_fraction:
                break
            needed = int(np.ceil(np.log(1.0 - confidence) / np.log(max(1.0 - w**3, 1e-12))))
    if best is None or best_count < 3:
        return None
    normal, d = best
    inliers = np.abs(p @ normal + d) <= distance_m
    if inliers.sum() >= 3:  # least-squares refinement on the inliers
        fit = fit_plane(p[inliers], orient_like=normal)
        refined = np.abs(p @ fit.normal + fit.d) <= distance_m
        admissible = cos_tilt is None or abs(fit.normal @ hint) >= cos_tilt
        if admissible and refined.sum() >= inliers.sum():
            normal, d, inliers = fit.normal, fit.d, refined
    if hint is not None and normal @ hint < 0:
        normal, d = -normal, -d
    return RansacPlane(np.asarray(normal, float), float(d), inliers, drawn)


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


@dataclass(frozen=True)
class IntensitySplit:
    threshold: float | None  # None: no usable contrast
    contrast: float  # ratio of the geometric means of the two classes


def intensity_split(intensity, min_contrast: float = 2.0) -> IntensitySplit:
    """Otsu's two-class threshold of the log intensities; ``threshold`` is None when the
    classes' geometric means differ by less than ``min_contrast`` (one material only)."""
    x = np.log(np.maximum(np.asarray(intensity, float), 1e-9))
    if x.size < 4 or np.ptp(x) <= 0:
        return IntensitySplit(None, 1.0)
    hist, edges = np.histogram(x, bins=256)
    mids = 0.5 * (edges[1:] + edges[:-1])
    w0 = np.cumsum(hist)
    w1 = x.size - w0
    s0 = np.cumsum(hist * mids)
    m0 = s0 / np.maximum(w0, 1)
    m1 = (s0[-1] - s0) / np.maximum(w1, 1)
    between = w0 * w1 * (m0 - m1) ** 2
    k = int(np.argmax(between[:-1]))
    thr = float(edges[k + 1])
    lo, hi = x[x < thr], x[x >= thr]
    if lo.size == 0 or hi.size == 0:
        return IntensitySplit(None, 1.0)
    contrast = float(np.exp(hi.mean() - lo.mean()))
    return IntensitySplit(float(np.exp(thr)) if contrast >= min_contrast else None, contrast)


def local_normals(p_m, k: int = 12, max_points: int = 5000) -> np.ndarray:
    """(n, 3) unit normals of the least-squares planes of each point's k nearest neighbours.
    Beyond ``max_points`` the normals are computed on an even sample of that many points and
    each point takes the normal of its nearest sample point (dense clouds stay fast)."""
    p = np.asarray(p_m, float)
    n = p.shape[0]
    if n < 3:
        return np.tile([0.0, 0.0, 1.0], (n, 1))
    sample = p if n <= max_points else p[np.linspace(0, n - 1, max_points).astype(np.int64)]
    tree = cKDTree(sample)
    _, nb = tree.query(sample, k=min(k, sample.shape[0]))
    q = sample[nb] - sample[nb].mean(axis=1, keepdims=True)
    normals = np.linalg.eigh(np.einsum("nki,nkj->nij", q, q))[1][:, :, 0]
    if sample is p:
        return normals
    return normals[tree.query(p, k=1)[1]]


def incidence_corrected(p_m, intensity, origin_m, k: int = 12) -> np.ndarray:
    """Intensity divided by the cosine of the incidence angle (beam from ``origin_m`` against
    the local surface normal, cosine floored at 0.1): a Lambertian surface's reflectivity, so
    that a target seen obliquely still outshines the wall behind it."""
    p = np.asarray(p_m, float)
    beam = p - np.asarray(origin_m, float)
    beam /= np.maximum(np.linalg.norm(beam, axis=1, keepdims=True), 1e-9)
    cos = np.abs(np.einsum("ij,ij->i", local_normals(p, k), beam))
    return np.asarray(intensity, float) / np.maximum(cos, 0.1)


def link_radius(p_m, smallest_target_m: float) -> float:
    """Cluster link distance: 40 % of the smallest target dimension (a profiler samples a
    target in lines that an oblique pass spreads far apart, farther than the points within a
    line), at least three median nearest-neighbour spacings and 5 cm."""
    p = np.asarray(p_m, float)
    nn = 0.0
    if p.shape[0] >= 2:
        sample = p if p.shape[0] <= 5000 else p[:: p.shape[0] // 5000]
        dist, _ = cKDTree(p).query(sample, k=2)
        nn = 3.0 * float(np.median(dist[:, 1]))
    return max(0.05, nn, 0.4 * smallest_target_m)


def clusters(p_m, link_m: float) -> np.ndarray:
    """Connected-component label of each point. Points are gathered in cubic voxels of half
    the link distance, and voxels whose centres are within ``link_m`` are linked (the cost
    depends on the occupied volume, not on the point density)."""
    p = np.asarray(p_m, float)
    n = p.shape[0]
    if n == 0:
        return np.empty(0, np.int64)
    cell = np.floor(p / (0.5 * link_m)).astype(np.int64)
    cells, inverse = np.unique(cell, axis=0, return_inverse=True)
    m = cells.shape[0]
    pairs = cKDTree(cells * (0.5 * link_m)).query_pairs(link_m * (1 + 1e-9), output_type="ndarray")
    graph = sparse.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(m, m))
    return connected_components(graph, directed=False)[1][inverse.ravel()]


def in_plane_axes(normal, width_axis) -> tuple[np.ndarray, np.ndarray]:
    """The configured width axis projected into the plane, and the axis up the slope."""
    n = np.asarray(normal, float)
    u = np.asarray(width_axis, float) - (np.asarray(width_axis, float) @ n) * n
    u /= np.linalg.norm(u)
    return u, np.cross(u, n)


def _extent(ab: np.ndarray) -> np.ndarray:
    """Robust extent (width, height) of in-plane coordinates (n, 2): the 2–98 % span divided
    by 0.96 (exact for points spread uniformly over the rectangle; a few stray points do not
    count)."""
    lo, hi = np.percentile(ab, [2.0, 98.0], axis=0)
    return (hi - lo) / 0.96


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
        ext = _extent(ab[m])
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
    ext = _extent(ab[best])
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
        ext = _extent(np.column_stack([(inl - ctr) @ u, (inl - ctr) @ v]))
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
    out = []
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
