"""Scene tie patches: planar pieces of the quay wall, piles and other flat surfaces around the
targets, seen by several passes from different headings; each becomes one more unknown plane
(a nuisance) of the boresight adjustment.

:func:`extract_candidates` cuts the georeferenced points (LGF, NED, metres, with the current best
mount) into cubic cells and keeps the cells whose points make a plane:

1. Points on targets (``exclude``) and every point within ``exclusion_margin_m`` of one are
   left out (a KD-tree over the target points).
2. Cells: a 3-D grid of edge ``size_m`` anchored at the LGF origin (cell ``floor(p / size)``, so
   the grid does not move when the mount or the data extent changes). A surface that only clips
   a cell (a wall crossing it near a corner, diagonally) leaves too few points or a sliver there,
   so a second grid, shifted by half a cell along the three axes, is run over the points of the
   cells the first grid rejected: it sees those pieces in the middle of its cells. (A strip along
   a surface's own edge narrower than about half a cell stays a sliver in both: line-like.)
3. Per cell, in this order (the first rule that fails is the reason counted in ``rejected``):
   ``few points`` — fewer than ``min_passes`` passes hold ``min_points_per_pass`` points and the
   cell holds fewer than ``min_passes × min_points_per_pass`` points; ``few passes`` — enough
   points, but fewer than ``min_passes`` passes hold ``min_points_per_pass`` of them;
   ``same heading`` — no two of those passes differ in heading by ``min_heading_spread_deg``
   (mod 360°); ``near a target`` replaces any of these three when the cell would have passed
   them with its excluded points. Then the plane is fitted by PCA (centroid and the eigenvector
   of the smallest eigenvalue of the covariance, all cells in one batched ``eigh``), the points
   beyond 3 × RMS of it are dropped once (a bollard or hull edge clipping the cell) and the
   plane refitted. That RMS is estimated robustly, 1.4826 × the median absolute deviation of
   the distances (the RMS of Gaussian noise, which a clump of off-plane points barely moves, where
   it would inflate the plain RMS until the clump stayed in). On the refit's inliers the pass
   rules are checked again (a pass left with fewer than ``min_points_per_pass`` inliers no
   longer counts, and its points leave the patch), then ``line-like`` — the
   second eigenvalue is below ``min_extent_ratio`` × the first (a railing, a sliver) — and
   ``not planar`` — the RMS distance to the plane, about each pass's own offset (a pass's POS
   error moves its points as a whole), exceeds ``max_rms_m``.
4. A patch keeps the refit's inliers of the passes that count; above ``max_points_per_patch``
   they are subsampled round-robin over passes (each pass gets a point before any gets two) and,
   within a pass, round-robin over a 4 × 4 in-plane sub-grid of the cell (spread over space),
   ties broken by a fixed-seed permutation: deterministic.

With ``size_m = None`` the edge is chosen among 1.0, 1.5 and 2.0 m: the one that gives the
adjustment the most points, Σₖ min(nₖ, max_points_per_patch) over the accepted patches (number
of patches × their mean usable points), the smaller edge on a tie.

Everything is vectorized (cells grouped by sorting, moments by ``bincount``): O(n log n); a
million points take about a second at a given size, three at the automatic one.

The rules let small pieces through (a few dozen points over 0.2 m at a wall's end): their
normals are as noisy as their extent makes them; weighing that is the selection's business.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from scipy.spatial import cKDTree

from calib.core.errors import CalibError

REASONS = ("near a target", "few points", "few passes", "same heading", "line-like", "not planar")
AUTO_SIZES_M = (1.0, 1.5, 2.0)
GRID_SHIFTS = (0.0, 0.5)  # in cells: the grid, then the half-shifted one over its rejected cells
OUTLIER_FACTOR = 3.0  # the refit drops points beyond this × the robust RMS of the first fit
ROBUST_SCALE = 1.4826  # RMS of Gaussian noise / its median absolute deviation
SUBGRID = 4  # in-plane sub-cells per cell edge that the subsample spreads over
SUBSAMPLE_SEED = 0
_MIN_THRESHOLD_M = 1e-9  # the outlier threshold on a noise-free plane


class PatchError(CalibError, ValueError):
    """Tie patches cannot be extracted from this input (the message says why and what to do)."""


@dataclass(frozen=True)
class PatchOptions:
    size_m: float | None = None  # cell edge; None: chosen among AUTO_SIZES_M
    min_points_per_pass: int = 15  # a pass counts for a patch only with this many points in it
    min_passes: int = 2
    min_heading_spread_deg: float = 30.0  # two of its passes differ in heading by this (mod 360)
    max_rms_m: float = 0.02  # planarity: RMS distance to the plane, all passes combined
    min_extent_ratio: float = 0.3  # 2nd eigenvalue / 1st: the points spread over the cell
    max_points_per_patch: int = 400  # subsampled above this
    exclusion_margin_m: float = 0.2  # keep away from target points

    def __post_init__(self):
        if self.size_m is not None and not (np.isfinite(self.size_m) and self.size_m > 0):
            raise PatchError(f"patch option size_m = {self.size_m!r}: expected a positive size or None")
        if self.min_points_per_pass < 3:
            raise PatchError(
                f"patch option min_points_per_pass = {self.min_points_per_pass!r}: expected ≥ 3 (a plane)"
            )
        if self.min_passes < 1:
            raise PatchError(f"patch option min_passes = {self.min_passes!r}: expected ≥ 1")
        if not 0.0 <= self.min_heading_spread_deg <= 180.0:
            raise PatchError(
                f"patch option min_heading_spread_deg = {self.min_heading_spread_deg!r}: "
                "expected an angle in [0, 180]"
            )
        if not (np.isfinite(self.max_rms_m) and self.max_rms_m > 0):
            raise PatchError(f"patch option max_rms_m = {self.max_rms_m!r}: expected a positive number")
        if not 0.0 <= self.min_extent_ratio <= 1.0:
            raise PatchError(
                f"patch option min_extent_ratio = {self.min_extent_ratio!r}: expected a ratio in [0, 1]"
            )
        floor = self.min_passes * self.min_points_per_pass
        if self.max_points_per_patch < floor:
            raise PatchError(
                f"patch option max_points_per_patch = {self.max_points_per_patch!r}: expected ≥ "
                f"min_passes × min_points_per_pass = {floor}"
            )
        if not (np.isfinite(self.exclusion_margin_m) and self.exclusion_margin_m >= 0):
            raise PatchError(f"patch option exclusion_margin_m = {self.exclusion_margin_m!r}: expected ≥ 0")


@dataclass
class PatchCandidates:
    labels: np.ndarray  # (n,) int64: patch index per point, −1 not in a patch
    normals: np.ndarray  # (m, 3) unit, toward the mean scanner position of the patch's points
    d_m: np.ndarray  # (m,) plane n·x + d = 0 in the LGF
    centers_m: np.ndarray  # (m, 3) centroid of the patch's inliers (before subsampling)
    rms_m: np.ndarray  # (m,) RMS distance of the inliers to the plane
    n_points: np.ndarray  # (m,) points labelled (after subsampling)
    passes: list[tuple[int, ...]]  # pass ids that see each patch (min_points_per_pass inliers)
    size_m: float
    names: list[str]  # "patch001", ...
    rejected: dict[str, int]  # reason (REASONS) -> number of cells
    n_cells: int = 0  # non-empty cells of both grids: len(names) + sum(rejected.values())
    scores: dict[float, int] = field(default_factory=dict)  # automatic size: size_m -> Σ min(n, cap)

    def __len__(self) -> int:
        return len(self.names)


def extract_candidates(
    p_lgf_m,
    origin_lgf_m,
    pass_id,
    pass_heading_rad: dict[int, float],
    exclude,
    options: PatchOptions = PatchOptions(),
) -> PatchCandidates:
    """Tie-patch candidates among points ``p_lgf_m`` (n, 3) scanned from ``origin_lgf_m``
    (n, 3) in passes ``pass_id`` (n,) of headings ``pass_heading_rad``, away from the target
    points ``exclude`` (n,) bool; see the module docstring for the rules. :class:`PatchError`
    on inconsistent input."""
    p, origin, pass_index, pass_ids, exclude_b = _validated(p_lgf_m, origin_lgf_m, pass_id, exclude)
    missing = [int(i) for i in pass_ids if int(i) not in pass_heading_rad]
    if missing:
        raise PatchError(f"pass_heading_rad has no heading for pass ids {missing}")
    heading_rad = np.array([float(pass_heading_rad[int(i)]) for i in pass_ids])
    if not np.all(np.isfinite(heading_rad)):
        raise PatchError(
            f"pass_heading_rad: the heading of pass {int(pass_ids[~np.isfinite(heading_rad)][0])} is not finite"
        )
    diff = np.abs(np.angle(np.exp(1j * (heading_rad[:, None] - heading_rad[None, :]))))
    pair_ok = np.degrees(diff) >= options.min_heading_spread_deg - 1e-9
    excluded = near_excluded(p, exclude_b, options.exclusion_margin_m)
    sizes = AUTO_SIZES_M if options.size_m is None else (float(options.size_m),)
    best: _Found | None = None
    scores: dict[float, int] = {}
    for size in sizes:
        found = _extract_at(p, origin, pass_index, excluded, pair_ok, size, options)
        scores[size] = int(np.minimum(found.n_inliers, options.max_points_per_patch).sum())
        if best is None or scores[size] > scores[best.size_m]:
            best = found
    assert best is not None
    return _candidates(best, p, pass_index, pass_ids, options, scores if options.size_m is None else {})


def _candidates(found: _Found, p, pass_index, pass_ids, opt: PatchOptions, scores) -> PatchCandidates:
    m = found.normal.shape[0]
    keep = _subsample(found, p, pass_index, opt.max_points_per_patch)
    member, patch = found.member[keep], found.member_patch[keep]
    labels = np.full(p.shape[0], -1, np.int64)
    labels[member] = patch
    return PatchCandidates(
        labels=labels,
        normals=found.normal,
        d_m=-np.einsum("ij,ij->i", found.normal, found.center_m),
        centers_m=found.center_m,
        rms_m=found.rms_m,
        n_points=np.bincount(patch, minlength=m).astype(np.int64),
        passes=[tuple(int(pass_ids[j]) for j in np.flatnonzero(row)) for row in found.counted],
        size_m=found.size_m,
        names=[f"patch{k + 1:03d}" for k in range(m)],
        rejected=dict(found.rejected),
        n_cells=found.n_cells,
        scores=scores,
    )


# -- input -------------------------------------------------------------------------------------


def _validated(p_lgf_m, origin_lgf_m, pass_id, exclude):
    p = np.asarray(p_lgf_m, float)
    if p.ndim != 2 or p.shape[1] != 3:
        raise PatchError(f"p_lgf_m has shape {p.shape}: expected (n, 3)")
    n = p.shape[0]
    origin = np.asarray(origin_lgf_m, float)
    if origin.shape != (n, 3):
        raise PatchError(f"origin_lgf_m has shape {origin.shape}: expected ({n}, 3) like p_lgf_m")
    pid = np.asarray(pass_id)
    if pid.shape != (n,):
        raise PatchError(f"pass_id has shape {pid.shape}: expected ({n},) like p_lgf_m")
    if n and not np.issubdtype(pid.dtype, np.integer):
        raise PatchError(f"pass_id has dtype {pid.dtype}: expected integers")
    ex = np.asarray(exclude)
    if ex.shape != (n,) or (n and ex.dtype != bool):
        raise PatchError(f"exclude has shape {ex.shape} and dtype {ex.dtype}: expected ({n},) bool")
    for name, a in (("p_lgf_m", p), ("origin_lgf_m", origin)):
        bad = ~np.all(np.isfinite(a), axis=1)
        if bad.any():
            raise PatchError(
                f"{name}: {int(bad.sum())} points are not finite (the first is point "
                f"{int(np.flatnonzero(bad)[0])}); drop invalid returns before extracting patches"
            )
    pass_ids, pass_index = np.unique(pid.astype(np.int64), return_inverse=True)
    return p, origin, pass_index.astype(np.int64), pass_ids, ex.astype(bool)


def near_excluded(p: np.ndarray, exclude: np.ndarray, margin_m: float) -> np.ndarray:
    """The target points and every point within ``margin_m`` of one."""
    out = exclude.copy()
    if not exclude.any() or margin_m <= 0:
        return out
    tree = cKDTree(p[exclude])
    rest = np.flatnonzero(~exclude)
    dist, _ = tree.query(p[rest], k=1, distance_upper_bound=margin_m)
    out[rest[dist <= margin_m]] = True
    return out


# -- cells -------------------------------------------------------------------------------------


@dataclass
class _Found:
    """Patches found at one cell size, before subsampling (points as indices into the input)."""

    size_m: float
    member: np.ndarray  # (k,) point index of each inlier of an accepted patch
    member_patch: np.ndarray  # (k,) its patch
    normal: np.ndarray  # (m, 3)
    center_m: np.ndarray  # (m, 3)
    evecs: np.ndarray  # (m, 3, 3) columns: eigenvectors, ascending eigenvalues
    rms_m: np.ndarray  # (m,)
    n_inliers: np.ndarray  # (m,)
    counted: np.ndarray  # (m, P) bool: the passes that see the patch
    rejected: dict[str, int]
    n_cells: int


def _extract_at(p, origin, pass_index, excluded, pair_ok, size_m: float, opt: PatchOptions) -> _Found:
    """Both grids at one cell size: the second over the points of the cells the first rejected."""
    free = np.ones(p.shape[0], bool)
    parts: list[_Found] = []
    for shift in GRID_SHIFTS:
        idx = np.flatnonzero(free)
        part, taken = _grid(p[idx], origin[idx], pass_index[idx], excluded[idx], pair_ok, size_m, shift, opt)
        part.member = idx[part.member]
        free[idx[taken]] = False
        parts.append(part)
    offsets = np.cumsum([0] + [pt.normal.shape[0] for pt in parts])
    return _Found(
        size_m,
        np.concatenate([pt.member for pt in parts]),
        np.concatenate([pt.member_patch + o for pt, o in zip(parts, offsets, strict=False)]),
        np.concatenate([pt.normal for pt in parts]),
        np.concatenate([pt.center_m for pt in parts]),
        np.concatenate([pt.evecs for pt in parts]),
        np.concatenate([pt.rms_m for pt in parts]),
        np.concatenate([pt.n_inliers for pt in parts]),
        np.concatenate([pt.counted for pt in parts]),
        {r: sum(pt.rejected[r] for pt in parts) for r in REASONS},
        sum(pt.n_cells for pt in parts),
    )


@dataclass(frozen=True, kw_only=True)
class _GridCells:
    """One grid's cells that pass the pass rule with the targets' points left out."""

    cell_of: np.ndarray  # (n,) each point's cell
    n_cells: int
    cand: np.ndarray  # the cells with enough points in all (cell ids)
    go: np.ndarray  # the candidates that pass the rule (indices into ``cand``)
    pts: np.ndarray  # the points (not excluded) of those cells
    grp: np.ndarray  # each one's cell, as an index into ``go``


def _passing_cells(
    p, pass_index, excluded, pair_ok, size_m, shift, opt: PatchOptions, rejected
) -> _GridCells:
    """The cells of the grid whose points (the excluded ones, near the targets, left out) pass
    the pass rule; the others counted in ``rejected`` by reason."""
    cell_of, n_cells = _cells(p, size_m, shift)
    min_total = opt.min_passes * opt.min_points_per_pass
    n_all = np.bincount(cell_of, minlength=n_cells)
    # cells with too few points in all cannot pass the pass rule, with or without their targets
    rejected["few points"] += int(np.count_nonzero(n_all < min_total))
    cand = np.flatnonzero(n_all >= min_total)
    local = np.full(n_cells, -1, np.int64)
    local[cand] = np.arange(cand.size)
    pt = np.flatnonzero(local[cell_of] >= 0)
    c_of = local[cell_of[pt]]
    ok_all, _, _ = _pass_rule(c_of, pass_index[pt], cand.size, pair_ok, opt)
    kept = ~excluded[pt]
    ok_kept, why, _ = _pass_rule(c_of[kept], pass_index[pt][kept], cand.size, pair_ok, opt)
    near = ok_all & ~ok_kept
    rejected["near a target"] += int(np.count_nonzero(near))
    _count(rejected, why[~ok_kept & ~near])
    go = np.flatnonzero(ok_kept)
    local2 = np.full(cand.size, -1, np.int64)
    local2[go] = np.arange(go.size)
    sel = kept & (local2[c_of] >= 0)
    return _GridCells(cell_of=cell_of, n_cells=n_cells, cand=cand, go=go, pts=pt[sel], grp=local2[c_of[sel]])


def _inliers(q: np.ndarray, grp: np.ndarray, n_groups: int) -> np.ndarray:
    """The points within 3 × the robust RMS of their cell's first plane fit."""
    center, _, evecs = _pca(q, grp, n_groups)
    dist = np.einsum("ij,ij->i", q - center[grp], np.ascontiguousarray(evecs[:, :, 0])[grp])
    dist -= _group_median(dist, grp, n_groups)[grp]
    rms0 = ROBUST_SCALE * _group_median(np.abs(dist), grp, n_groups)
    return np.abs(dist) <= np.maximum(OUTLIER_FACTOR * rms0[grp], _MIN_THRESHOLD_M)


def _rms_within_passes(p, pts, grp, pass_index, center, evecs, n_groups: int) -> np.ndarray:
    """Each cell's RMS about its plane, within each pass: a pass's POS error shifts its points
    as a whole (the adjustment estimates that), so the spread is measured about each pass's own
    offset."""
    d = np.einsum("ij,ij->i", p[pts] - center[grp], np.ascontiguousarray(evecs[:, :, 0])[grp])
    n_pass = int(pass_index.max()) + 1 if pass_index.size else 1
    key = grp * n_pass + pass_index[pts]
    n_key = np.maximum(np.bincount(key, minlength=n_groups * n_pass), 1)
    d -= (np.bincount(key, d, minlength=n_groups * n_pass) / n_key)[key]
    return np.sqrt(
        np.bincount(grp, d * d, minlength=n_groups) / np.maximum(np.bincount(grp, minlength=n_groups), 1)
    )


def _grid(
    p, origin, pass_index, excluded, pair_ok, size_m, shift, opt: PatchOptions
) -> tuple[_Found, np.ndarray]:
    """One grid of edge ``size_m`` shifted by ``shift`` cells: cells, rules, fits; and which
    points lie in the cells of its patches (outliers included: no other grid gets them)."""
    rejected = dict.fromkeys(REASONS, 0)
    cells = _passing_cells(p, pass_index, excluded, pair_ok, size_m, shift, opt, rejected)
    go = cells.go
    # the cells that pass: fit, drop the points beyond 3 × RMS once, refit
    inl = _inliers(p[cells.pts], cells.grp, go.size)
    pts, grp = cells.pts[inl], cells.grp[inl]
    ok2, why2, counted = _pass_rule(grp, pass_index[pts], go.size, pair_ok, opt)
    # a patch holds the inliers of the passes that count: the refit is on exactly those
    in_counted = counted[grp, pass_index[pts]]
    pts, grp = pts[in_counted], grp[in_counted]
    center, evals, evecs = _pca(p[pts], grp, go.size)
    n_in = np.bincount(grp, minlength=go.size)
    line = evals[:, 1] < opt.min_extent_ratio * np.maximum(evals[:, 2], np.finfo(float).tiny)
    rms = _rms_within_passes(p, pts, grp, pass_index, center, evecs, go.size)
    flat = rms <= opt.max_rms_m
    _count(rejected, why2[~ok2])
    rejected["line-like"] += int(np.count_nonzero(ok2 & line))
    rejected["not planar"] += int(np.count_nonzero(ok2 & ~line & ~flat))
    acc = np.flatnonzero(ok2 & ~line & flat)
    patch_of = np.full(go.size, -1, np.int64)
    patch_of[acc] = np.arange(acc.size)
    member = patch_of[grp] >= 0
    pts, patch = pts[member], patch_of[grp[member]]
    normal = evecs[acc, :, 0].copy()
    toward = _group_mean(origin[pts], patch, acc.size) - center[acc]
    normal[np.einsum("ij,ij->i", normal, toward) < 0] *= -1.0
    taken_cell = np.zeros(cells.n_cells, bool)
    taken_cell[cells.cand[go[acc]]] = True
    found = _Found(
        size_m,
        pts,
        patch,
        normal,
        center[acc],
        evecs[acc],
        rms[acc],
        n_in[acc],
        counted[acc],
        rejected,
        cells.n_cells,
    )
    return found, taken_cell[cells.cell_of]


def _cells(p: np.ndarray, size_m: float, shift: float) -> tuple[np.ndarray, int]:
    """Cell index (0 … n_cells − 1, in the order of the cells' keys) of each point."""
    if p.shape[0] == 0:
        return np.empty(0, np.int64), 0
    ijk = np.floor(p / size_m + shift).astype(np.int64)
    ijk -= ijk.min(axis=0)
    dims = ijk.max(axis=0) + 1
    if float(np.prod(dims.astype(float))) >= 2.0**62:
        raise PatchError(
            f"the points span {dims.tolist()} cells of {size_m} m: too large a grid; "
            "give the points of the quay only"
        )
    key = (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]
    uniq, cell_of = np.unique(key, return_inverse=True)
    return cell_of.astype(np.int64), int(uniq.size)


def _pass_rule(cell, pass_index, n_cells, pair_ok, opt: PatchOptions):
    """Per cell (``cell`` and ``pass_index`` per point): whether ``min_passes`` passes hold
    ``min_points_per_pass`` points each and two of them differ in heading by
    ``min_heading_spread_deg``; the reason (index into REASONS) where not; the counted passes
    (n_cells, P)."""
    n_pass = pair_ok.shape[0]
    per_pass = np.bincount(cell * n_pass + pass_index, minlength=n_cells * n_pass).reshape(n_cells, n_pass)
    counted = per_pass >= opt.min_points_per_pass
    n_counted = counted.sum(axis=1)
    c = counted.astype(float)
    spread = np.einsum("ij,jk,ik->i", c, pair_ok.astype(float), c) > 0
    ok = (n_counted >= opt.min_passes) & spread
    few_points = per_pass.sum(axis=1) < opt.min_passes * opt.min_points_per_pass
    reason = np.where(
        n_counted >= opt.min_passes,
        REASONS.index("same heading"),
        np.where(few_points, REASONS.index("few points"), REASONS.index("few passes")),
    )
    return ok, reason, counted


def _count(rejected: dict[str, int], reason: np.ndarray) -> None:
    for i, r in enumerate(REASONS):
        rejected[r] += int(np.count_nonzero(reason == i))


def _group_mean(v: np.ndarray, grp: np.ndarray, m: int) -> np.ndarray:
    n = np.maximum(np.bincount(grp, minlength=m), 1)
    vt = np.ascontiguousarray(v.T)
    return np.stack([np.bincount(grp, vj, minlength=m) for vj in vt], axis=1) / n[:, None]


def _group_median(v: np.ndarray, grp: np.ndarray, m: int) -> np.ndarray:
    """The (lower) median of ``v`` in each of ``m`` groups; 0 for an empty group."""
    out = np.zeros(m)
    if v.size == 0:
        return out
    lo = float(v.min())
    span = float(v.max()) - lo + 1.0  # one sort on group + value, the values kept apart
    order = np.argsort(grp * span + (v - lo))
    n = np.bincount(grp, minlength=m)
    start = np.cumsum(n) - n
    has = n > 0
    out[has] = v[order[start[has] + (n[has] - 1) // 2]]
    return out


def _covariances(p: np.ndarray, grp: np.ndarray, m: int, center: np.ndarray) -> np.ndarray:
    """(m, 3, 3) population covariance of each group about ``center`` (two-pass: centred first)."""
    q = np.ascontiguousarray((p - center[grp]).T)
    n = np.maximum(np.bincount(grp, minlength=m), 1)
    cov = np.empty((m, 3, 3))
    for a in range(3):
        for b in range(a, 3):
            cov[:, a, b] = cov[:, b, a] = np.bincount(grp, q[a] * q[b], minlength=m) / n
    return cov


def _pca(p: np.ndarray, grp: np.ndarray, m: int):
    """Centroid (m, 3), eigenvalues (m, 3) ascending and eigenvectors (m, 3, 3) as columns."""
    center = _group_mean(p, grp, m)
    evals, evecs = np.linalg.eigh(_covariances(p, grp, m, center))
    return center, evals, evecs


# -- subsampling -------------------------------------------------------------------------------


def _subsample(found: _Found, p, pass_index, cap: int) -> np.ndarray:
    """Which members stay: all of a patch within ``cap``; else ``cap`` of them, round-robin over
    the passes, within a pass round-robin over the in-plane sub-cells (SUBGRID per cell edge),
    the order within a round and within a sub-cell from a fixed-seed permutation."""
    member, patch = found.member, found.member_patch
    keep = np.ones(member.size, bool)
    over = np.bincount(patch, minlength=found.normal.shape[0]) > cap
    sel = np.flatnonzero(over[patch])
    if sel.size == 0:
        return keep
    pt, k = member[sel], patch[sel]
    q = p[pt] - found.center_m[k]
    sub_m = found.size_m / SUBGRID
    u = np.floor(np.einsum("ij,ij->i", q, found.evecs[:, :, 2][k]) / sub_m).astype(np.int64)
    v = np.floor(np.einsum("ij,ij->i", q, found.evecs[:, :, 1][k]) / sub_m).astype(np.int64)
    u -= u.min()
    v -= v.min()
    sub = u * (int(v.max()) + 1) + v
    tie = np.random.default_rng(SUBSAMPLE_SEED).permutation(sel.size)
    pi = pass_index[pt]
    k_pass = k * found.counted.shape[1] + pi
    r_sub = rank_in_group(k_pass * (int(sub.max()) + 1) + sub, tie)  # rank within its sub-cell
    r_pass = rank_in_group(k_pass, r_sub, tie)  # round-robin over the sub-cells of its pass
    r_patch = rank_in_group(k, r_pass, tie)  # round-robin over the passes of its patch
    keep[sel] = r_patch < cap
    return keep


def rank_in_group(group: np.ndarray, *keys: np.ndarray) -> np.ndarray:
    """Rank (0, 1, …) of each element within its group, ordered by the non-negative integer
    ``keys`` (the first first); the last key must be unique within a group (a tie-break)."""
    combined = group.astype(np.int64)
    for key in keys:  # one int64 sort key while it fits, else a lexsort
        base = int(key.max()) + 1 if key.size else 1
        if int(combined.max(initial=0)) >= (2**62) // base:
            order = np.lexsort(tuple(reversed(keys)) + (group,))
            break
        combined = combined * base + key
    else:
        order = np.argsort(combined)
    g = group[order]
    start = np.ones(g.size, bool)
    start[1:] = g[1:] != g[:-1]
    first = np.maximum.accumulate(np.where(start, np.arange(g.size), 0))
    rank = np.empty(g.size, np.int64)
    rank[order] = np.arange(g.size) - first
    return rank


#: half-width (m) of the band about a patch's plane within which :func:`gather_members` takes
#: points: wide against a pass's POS position error, so that no pass is cut by its own error
GATHER_BAND_M = 0.15


def gather_members(
    cands: PatchCandidates,
    p_lgf_m: np.ndarray,
    pass_id: np.ndarray,
    exclude: np.ndarray,
    options: PatchOptions = PatchOptions(),
    band_m: float = GATHER_BAND_M,
) -> PatchCandidates:
    """The candidates with their points taken again, independently of each pass's offset.

    A cell's points depend on where each pass put them: a pass whose POS error moved the
    surface by 2 cm across a cell boundary, or beyond the refit's 3 × MAD of the combined
    plane, loses points for a reason correlated with its error, and the adjustment then sees a
    biased sample. Here every point not excluded within the disc of the patch (diameter the
    cell size) and within ``band_m`` of its plane belongs to it; outliers are judged within
    each pass about that pass's own median distance; the cap keeps every pass's share
    (deterministic order). Passes with fewer than ``min_points_per_pass`` points drop out."""
    p = np.asarray(p_lgf_m, float)
    pid = np.asarray(pass_id)
    free = ~near_excluded(p, np.asarray(exclude, bool), options.exclusion_margin_m)
    idx_free = np.flatnonzero(free)
    tree = cKDTree(p[idx_free])
    r = 0.5 * cands.size_m
    labels = np.full(p.shape[0], -1, np.int64)
    passes: list[tuple[int, ...]] = []
    order = np.random.default_rng(0).permutation(p.shape[0])
    rank_key = np.empty(p.shape[0], np.int64)
    rank_key[order] = np.arange(p.shape[0])
    for j, (c, n) in enumerate(zip(cands.centers_m, cands.normals, strict=False)):
        near = idx_free[tree.query_ball_point(c, float(np.hypot(r, band_m)))]
        near = near[labels[near] < 0]
        rel = p[near] - c
        dist = rel @ n
        radial = np.linalg.norm(rel - dist[:, None] * n, axis=1)
        inside = (radial <= r) & (np.abs(dist) <= band_m)
        near, dist = near[inside], dist[inside]
        keep_j, seen = [], []
        for k in np.unique(pid[near]):
            sel = pid[near] == k
            dk = dist[sel] - np.median(dist[sel])
            mad = 1.4826 * np.median(np.abs(dk))
            ok = np.abs(dk) <= max(4.0 * mad, _MIN_THRESHOLD_M)
            if np.count_nonzero(ok) >= options.min_points_per_pass:
                members = near[sel][ok]
                keep_j.append(members[np.argsort(rank_key[members])])
                seen.append(int(k))
        counts = np.array([m.size for m in keep_j], np.int64)
        quota = _quota(counts, options.max_points_per_patch)
        for members in keep_j:
            labels[members[:quota]] = j
        passes.append(tuple(seen))
    n_points = np.bincount(labels[labels >= 0], minlength=len(cands.names))
    return replace(cands, labels=labels, n_points=n_points, passes=passes)


def _quota(counts: np.ndarray, cap: int) -> int:
    """The largest q with Σ min(counts, q) ≤ cap (every pass keeps up to q points)."""
    if counts.size == 0 or counts.sum() <= cap:
        return int(counts.max()) if counts.size else 0
    lo, hi = 0, int(counts.max())
    while lo < hi:
        mid = (lo + hi + 1) // 2
        if np.minimum(counts, mid).sum() <= cap:
            lo = mid
        else:
            hi = mid - 1
    return lo
