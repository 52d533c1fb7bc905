"""The surfaces an assessment compares and their returns: the returns of a pass on a validation
plane (candidates near the rectangle, trimmed to their own plane), the part of them within the
reference's coverage, how many local planes rest on collinear neighbours, and the planar patches
two clouds both see (when the site lists no validation planes).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from calib.assess.results import DEFAULT_ASSESS_OPTIONS, AssessOptions
from calib.core.geometry import Rectangle, fit_plane


def plane_candidates(p_m: np.ndarray, rect: Rectangle, gate_m: float, margin_m: float = 0.0) -> np.ndarray:
    """Mask of points inside the rectangle (grown by ``margin_m``) within ``gate_m`` of its
    plane."""
    return (np.abs(rect.signed_distance(p_m)) <= gate_m) & rect.contains(p_m, margin_m)


def clean_patch(
    p_m: np.ndarray, mask: np.ndarray, n_sigma: float = 4.0, floor_m: float = 0.02, iterations: int = 8
) -> np.ndarray:
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


def collinear_fraction(q_m: np.ndarray, ref_m: np.ndarray, normal, k: int, ratio: float = 0.1) -> float:
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


@dataclass(frozen=True, kw_only=True)
class _Cells:
    """Both clouds binned in cubic cells: per cell its points of each cloud and the sums of
    their coordinates (relative to the clouds' lowest corner) and of their products."""

    key: np.ndarray  # (m, 3) the cells' integer coordinates
    inv: np.ndarray  # (n,) each point's cell
    cnt_a: np.ndarray  # (m,) points of the first cloud
    cnt_b: np.ndarray  # (m,) … of the second
    s1: np.ndarray  # (m, 3) Σ x
    s2: np.ndarray  # (m, 3, 3) Σ x xᵀ

    @property
    def cnt(self) -> np.ndarray:
        return self.cnt_a + self.cnt_b


def _cells(pts: np.ndarray, which: np.ndarray, cell_m: float) -> _Cells:
    origin = pts.min(axis=0)
    key = np.floor((pts - origin) / cell_m).astype(np.int64)
    cells, inv, _ = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    inv = inv.ravel()
    m = len(cells)
    rel = pts - origin
    s1 = np.stack([np.bincount(inv, rel[:, j], m) for j in range(3)], axis=1)
    s2 = np.empty((m, 3, 3))
    for i in range(3):
        for j in range(i, 3):
            s2[:, i, j] = s2[:, j, i] = np.bincount(inv, rel[:, i] * rel[:, j], m)
    return _Cells(
        key=cells,
        inv=inv,
        cnt_a=np.bincount(inv[which == 0], minlength=m),
        cnt_b=np.bincount(inv[which == 1], minlength=m),
        s1=s1,
        s2=s2,
    )


def _plane_of(s1_, s2_, n_):
    """Centroid, normal and eigenvalues (ascending) of points from their sums."""
    c = s1_ / n_
    cov = s2_ / n_ - np.outer(c, c)
    w, v = np.linalg.eigh(cov)
    return c, v[:, 0], w


def _flat_cells(cs: _Cells, ok_cells: np.ndarray, options: AssessOptions):
    """The cells planar (thin) and not a line (spread in two directions): their centroids,
    normals and smallest eigenvalues, by cell."""
    cnt = cs.cnt
    cent, normal, flat = {}, {}, {}
    for ci in ok_cells:
        c, nv, w = _plane_of(cs.s1[ci], cs.s2[ci], cnt[ci])
        if (
            np.sqrt(max(w[0], 0.0)) <= options.auto_max_rms_m
            and np.sqrt(max(w[1], 0.0)) > options.auto_cell_m / 20
        ):
            cent[ci], normal[ci], flat[ci] = c, nv, float(w[0])
    return cent, normal, flat


def _grown_regions(cs: _Cells, cent: dict, normal: dict, flat: dict, options: AssessOptions) -> list[list]:
    """Regions of neighbouring flat cells that agree with the region's plane, grown from the
    flattest cells first; each a list of cell indices."""
    cnt = cs.cnt
    index = {tuple(cs.key[ci]): ci for ci in cent}
    offsets = [np.array(o) for o in np.ndindex(3, 3, 3) if o != (1, 1, 1)]
    cos_max = np.cos(np.radians(options.auto_max_angle_deg))
    tol = 3.0 * options.auto_max_rms_m
    region = {}
    regions: list[list[np.intp]] = []  # cell indices of each region
    for seed in sorted(cent, key=lambda c: flat[c]):  # flattest cells seed first
        if seed in region:
            continue
        members = [seed]
        region[seed] = len(regions)
        S1, S2, N = cs.s1[seed].copy(), cs.s2[seed].copy(), int(cnt[seed])
        c, nv, _ = _plane_of(S1, S2, N)
        queue = [seed]
        while queue:
            ci = queue.pop()
            for o in offsets:
                nb = index.get(tuple(cs.key[ci] + o - 1))
                if nb is None or nb in region:
                    continue
                if abs(normal[nb] @ nv) < cos_max or abs((cent[nb] - c) @ nv) > tol:
                    continue
                region[nb] = len(regions)
                members.append(nb)
                queue.append(nb)
                S1 += cs.s1[nb]
                S2 += cs.s2[nb]
                N += int(cnt[nb])
                c, nv, _ = _plane_of(S1, S2, N)
        regions.append(members)
    return regions


def extract_common_patches(
    p_a: np.ndarray, p_b: np.ndarray, toward_m: np.ndarray, options: AssessOptions = DEFAULT_ASSESS_OPTIONS
) -> list[Rectangle]:
    """Planar patches seen by both clouds: cells of ``auto_cell_m`` whose points of both clouds
    lie on one plane (RMS ≤ ``auto_max_rms_m``, not a line), grown into regions of neighbouring
    cells that agree with the region's plane (normal within ``auto_max_angle_deg``, centroid
    within 3 × ``auto_max_rms_m``). Returns the regions' bounding rectangles (normals toward
    ``toward_m``), the largest first, named P1, P2, …"""
    pts = np.concatenate([p_a, p_b])
    which = np.concatenate([np.zeros(len(p_a), np.int8), np.ones(len(p_b), np.int8)])
    cs = _cells(pts, which, options.auto_cell_m)
    min_cell = max(options.k, 8)
    ok_cells = np.flatnonzero((cs.cnt_a >= min_cell) & (cs.cnt_b >= min_cell))
    if ok_cells.size == 0:
        return []
    cent, normal, flat = _flat_cells(cs, ok_cells, options)
    regions = _grown_regions(cs, cent, normal, flat, options)
    cell_region = np.full(len(cs.key), -1)
    for r, members in enumerate(regions):
        cell_region[members] = r
    point_region = cell_region[cs.inv]
    out = []
    for r in range(len(regions)):
        sel = point_region == r
        if (
            np.count_nonzero(sel & (which == 0)) < options.min_points
            or np.count_nonzero(sel & (which == 1)) < options.min_points
        ):
            continue
        rp = pts[sel]
        f = fit_plane(rp)
        toward = np.asarray(toward_m, float) - f.centroid_m
        out.append((int(sel.sum()), _rectangle_of(rp, f.normal if f.normal @ toward >= 0 else -f.normal, "")))
    out.sort(key=lambda x: -x[0])
    return [replace(r, name=f"P{i + 1}") for i, (_, r) in enumerate(out[: options.auto_max_patches])]
