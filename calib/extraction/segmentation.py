"""Point-cloud building blocks of the target extraction (:mod:`calib.extraction.extract`): a RANSAC
plane among admissible orientations, Otsu's two-class split of log intensities, intensities
corrected for incidence, connected clusters, and a plane's in-plane axes and a cluster's robust
extent on them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from calib.core.geometry import fit_plane


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
    local_radius_m: float | None = None,
) -> RansacPlane | None:
    """RANSAC plane of points (n, 3), or None when no admissible plane has 3 inliers.

    Hypotheses from random triplets are scored by their inlier count (|distance| ≤
    ``distance_m``), in vectorized batches; sampling stops when a plane holds
    ``stop_fraction`` of the points, after the adaptive number of samples for ``confidence``,
    or at ``max_iterations``. With ``normal_hint`` and ``max_tilt_rad`` only planes whose
    normal is within that angle of the hint are admissible. The best plane is refined by
    least squares on its inliers.

    With ``local_radius_m`` every other batch draws its triplets locally: the first point at
    random, the other two among its neighbours within that radius. A small target among a
    wall's points (3 % of them, say) is then sampled whole about 3 % of the time instead of
    0.003 % — a global draw of three would almost never find it within ``max_iterations``.
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
    local = None if local_radius_m is None else (cKDTree(p), float(local_radius_m))
    batch = 0
    while drawn < min(needed, max_iterations):
        batch += 1
        if local is not None and batch % 2 == 0:
            idx = _local_triplets(p, local[0], local[1], rng)
        else:
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


def _local_triplets(p: np.ndarray, tree: cKDTree, radius_m: float, rng: np.random.Generator) -> np.ndarray:
    """(_BATCH, 3) indices: a random first point and two of its neighbours within the radius
    (the first point thrice where it has fewer than two: a degenerate triplet, dropped)."""
    first = rng.integers(0, p.shape[0], _BATCH)
    out = np.repeat(first[:, None], 3, axis=1)
    for row, near in enumerate(tree.query_ball_point(p[first], radius_m)):
        if len(near) >= 3:
            out[row, 1:] = rng.choice(near, 2, replace=False)
    return out


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


def robust_extent(ab: np.ndarray) -> np.ndarray:
    """Robust extent (width, height) of in-plane coordinates (n, 2): the 2–98 % span divided
    by 0.96 (exact for points spread uniformly over the rectangle; a few stray points do not
    count)."""
    lo, hi = np.percentile(ab, [2.0, 98.0], axis=0)
    return (hi - lo) / 0.96
