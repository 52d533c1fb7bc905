"""Scene tie cylinders: vertical piles, posts and dolphins around the targets, seen by several
passes from different headings; each becomes one more unknown vertical cylinder (axis point c,
radius r; condition |(x − c)_horizontal| − r = 0) of the boresight adjustment.

:func:`extract_cylinders` finds them among the georeferenced points (LGF, NED, metres, with the
current best mount; "up" is −z):

1. Points on targets (``exclude``) and every point within ``exclusion_margin_m`` of one are
   left out (a KD-tree over the target points): they never enter a cylinder.
2. Columns: a horizontal grid of edge ``cell_m`` anchored at the LGF origin (column
   ``floor((x, y) / cell_m)``). A column is *vertical* when its points occupy at least
   ``min_column_height_m`` of height, counted in height bins of ``cell_m`` (the ground, a deck,
   a rope over the ground occupy a bin or two; a pile, a wall, a hull many).
3. Vertical columns joined through their 8 neighbours make components. A component whose
   extent along north or east exceeds 2 × ``max_radius_m`` + 2 cells is rejected as
   ``too wide`` (a wall, a hull, a long fender); the others are candidates, with every kept
   point of their columns (the column at a pile's foot holds some ground too: the fit's outlier
   drop takes it out).
4. Per candidate, in this order (the first rule that fails is the reason counted in
   ``rejected``): ``few points``, ``few passes``, ``same heading`` — the pass rule of
   :mod:`calib.extraction.patches` (``min_passes`` passes hold ``min_points_per_pass`` points
   and two of them differ in heading by ``min_heading_spread_deg``, mod 360°; the points of the
   passes that do not count leave the candidate). Then the circle is fitted: algebraically
   (Kåsa) for a start, then a few Gauss–Newton steps of the geometric fit in which every pass
   has its own centre and all share one radius (a pass's POS error moves its points as a
   whole: the offsets are the adjustment's business, not the shape's); ``radius`` — the radius
   is outside [``min_radius_m``, ``max_radius_m``] (a flat face fits only a huge circle). The
   points beyond 3 × RMS of the circle are dropped once (the ground at the foot, a ladder, a
   rope), that RMS estimated robustly as 1.4826 × the median absolute deviation, and the
   circle refitted on the inliers of the passes that still count (the pass rule again). On the
   refit: ``radius`` again, ``short`` — the members span less than ``min_height_m`` of height,
   ``narrow arc`` — the largest gap between the members' bearings about the axis leaves less
   than ``min_arc_deg`` seen, ``not circular`` — the RMS distance to the circle, about each
   pass's own centre, exceeds ``max_rms_m`` (a box, a corner), ``leaning`` — the axis's lean
   fitted to the members' heights (the circle residuals against the radial direction × height,
   linearized about the upright fit) exceeds ``max_lean_deg`` and the members show it clearly
   (:data:`LEAN_Z`; a lean across a narrow arc's line of sight shows as nothing, and does no
   harm): the adjustment models upright cylinders, and piles leaning 0.3–1° (installation
   tolerances) biased roll by 1σ.
5. A cylinder's axis is the mean of its passes' centres (each pass weighs the same: the mean
   offset of its passes is the datum), at the members' mid height; its height is the span of
   the members. Above ``max_points_per_cylinder`` the members are subsampled round-robin over
   the passes (each pass gets a point before any gets two) and, within a pass, round-robin over
   HEIGHT_BINS height bins, ties broken by a fixed-seed permutation: deterministic.

Everything is vectorized (columns grouped by sorting, components by a sparse graph, all circles
fitted at once by ``bincount``): O(n log n); a million points take one to three seconds (the
more small clusters of clutter, the longer).

Known limit: a pile standing within a cell or two of a wall (or of another vertical surface)
joins the wall's component and is lost with it as ``too wide``; so do piles braced together
closer than that.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from calib.core.errors import CalibError
from calib.core.geometry import VerticalCylinder
from calib.extraction.circlefit import Circles, fit_circles, lean, sums
from calib.extraction.patches import near_excluded, rank_in_group

REASONS: tuple[str, ...] = ("too wide", "few points", "few passes", "same heading")  # pass rule
REASONS += ("radius", "short", "narrow arc", "not circular", "leaning")  # the shape
OUTLIER_FACTOR = 3.0  # the refit drops points beyond this × the robust RMS of the first fit
ROBUST_SCALE = 1.4826  # RMS of Gaussian noise / its median absolute deviation
HEIGHT_BINS = 8  # height bins per cylinder that the subsample spreads over
SUBSAMPLE_SEED = 0
_MIN_THRESHOLD_M = 1e-9  # the outlier threshold on a noise-free circle
_TINY_M = 1e-12
#: a lean counts when its points show it this clearly (√(sᵀNs)/σ, a χ with 2 degrees of freedom
#: for an upright pile: beyond 4 once in 3,000)
LEAN_Z = 4.0
_NEIGHBOURS = ((0, 1), (1, -1), (1, 0), (1, 1))  # half of the 8: each pair of columns once


class CylinderError(CalibError, ValueError):
    """Tie cylinders cannot be extracted from this input (the message says why and what to do)."""


def _at_least(v: float, lo: float, strict: bool = False) -> bool:
    return bool(np.isfinite(v) and (v > lo if strict else v >= lo))


@dataclass(frozen=True, kw_only=True)
class CylinderOptions:
    cell_m: float = 0.1  # horizontal grid (and height bin) edge
    min_column_height_m: float = 0.5  # a column is vertical with this much height occupied
    min_radius_m: float = 0.1
    max_radius_m: float = 0.8  # piles of 0.2–1.6 m diameter by default
    min_height_m: float = 1.0  # height span of the visible part
    max_rms_m: float = 0.02  # RMS distance to the circle, about each pass's own centre
    #: the axis's lean from vertical the adjustment's upright model tolerates (the lean fitted
    #: to the members' heights); piles leaning 0.3–1° biased roll by 1σ on montreal_piles
    max_lean_deg: float = 0.1
    min_arc_deg: float = 60.0  # arc seen around the axis, all passes together
    min_passes: int = 2
    min_points_per_pass: int = 15  # a pass counts for a cylinder only with this many points on it
    min_heading_spread_deg: float = 30.0  # two of its passes differ in heading by this (mod 360)
    max_points_per_cylinder: int = 400  # subsampled above this
    exclusion_margin_m: float = 0.2  # keep away from target points

    def __post_init__(self) -> None:
        floor = self.min_passes * self.min_points_per_pass
        r0, cap = self.min_radius_m, self.max_points_per_cylinder
        checks = (
            ("cell_m", _at_least(self.cell_m, 0.0, strict=True), "a positive size"),
            ("min_column_height_m", _at_least(self.min_column_height_m, 0.0), "≥ 0"),
            ("min_radius_m", _at_least(r0, 0.0), "≥ 0"),
            ("max_radius_m", _at_least(self.max_radius_m, r0, strict=True), f"> min_radius_m = {r0!r}"),
            ("min_height_m", _at_least(self.min_height_m, 0.0), "≥ 0"),
            ("max_rms_m", _at_least(self.max_rms_m, 0.0, strict=True), "a positive number"),
            ("max_lean_deg", 0.0 < self.max_lean_deg <= 90.0, "an angle in (0, 90]"),
            ("min_arc_deg", 0.0 <= self.min_arc_deg <= 360.0, "an angle in [0, 360]"),
            ("min_passes", self.min_passes >= 1, "≥ 1"),
            ("min_points_per_pass", self.min_points_per_pass >= 3, "≥ 3 (a circle)"),
            ("min_heading_spread_deg", 0.0 <= self.min_heading_spread_deg <= 180.0, "an angle in [0, 180]"),
            ("max_points_per_cylinder", cap >= floor, f"≥ min_passes × min_points_per_pass = {floor}"),
            ("exclusion_margin_m", _at_least(self.exclusion_margin_m, 0.0), "≥ 0"),
        )
        for name, ok, expected in checks:
            if not ok:
                raise CylinderError(f"cylinder option {name} = {getattr(self, name)!r}: expected {expected}")


@dataclass(frozen=True, kw_only=True)
class CylinderCandidates:
    labels: np.ndarray  # (n,) int64: cylinder index per point, −1 not in a cylinder
    centers_m: np.ndarray  # (m, 3) the axis at the members' mid height (mean of the passes' centres)
    radius_m: np.ndarray  # (m,)
    height_m: np.ndarray  # (m,) height span of the members
    rms_m: np.ndarray  # (m,) RMS distance to the circle, about each pass's own centre
    arc_deg: np.ndarray  # (m,) arc seen around the axis, all passes together
    n_points: np.ndarray  # (m,) points labelled (after subsampling)
    passes: list[tuple[int, ...]]  # pass ids that see each cylinder (min_points_per_pass inliers)
    names: list[str]  # "cyl_001", ...
    rejected: dict[str, int]  # reason (REASONS) -> number of components
    n_components: int  # components of vertical columns: len(names) + sum(rejected.values())
    #: (n,) bool: the points of piles rejected as ``leaning`` only: round, not planar (no tie
    #: patch may be cut on them)
    leaning_points: np.ndarray

    def __len__(self) -> int:
        return len(self.names)

    def cylinders(self, reflectivity: float = 0.3) -> list[VerticalCylinder]:
        """The candidates as :class:`VerticalCylinder` (axis at mid height, in the LGF)."""
        return [
            VerticalCylinder(
                name=name,
                center_m=self.centers_m[k].copy(),
                radius_m=float(self.radius_m[k]),
                height_m=float(self.height_m[k]),
                reflectivity=reflectivity,
            )
            for k, name in enumerate(self.names)
        ]


def extract_cylinders(
    p_lgf_m,
    pass_id,
    pass_heading_rad: dict[int, float],
    exclude,
    options: CylinderOptions = CylinderOptions(),
) -> CylinderCandidates:
    """Tie-cylinder candidates among points ``p_lgf_m`` (n, 3) of passes ``pass_id`` (n,) of
    headings ``pass_heading_rad``, away from the target points ``exclude`` (n,) bool; see the
    module docstring for the rules. :class:`CylinderError` on inconsistent input."""
    p, pass_index, pass_ids, exclude_b = _validated(p_lgf_m, pass_id, exclude)
    pair_ok = _heading_pairs(pass_ids, pass_heading_rad, options.min_heading_spread_deg)
    kept = np.flatnonzero(~near_excluded(p, exclude_b, options.exclusion_margin_m))
    rejected = dict.fromkeys(REASONS, 0)
    members, n_components = _candidate_members(p, kept, options, rejected)
    members, summary, leaning_pts = _fit_and_judge(p, pass_index, members, pair_ok, options, rejected)
    keep = _subsample(members, p[members.pts, 2], pass_index[members.pts], summary, options)
    labels = np.full(p.shape[0], -1, np.int64)
    labels[members.pts[keep]] = members.cand[keep]
    m = members.m
    return CylinderCandidates(
        labels=labels,
        centers_m=summary.center_m,
        radius_m=summary.radius_m,
        height_m=summary.height_m,
        rms_m=summary.rms_m,
        arc_deg=summary.arc_deg,
        n_points=np.bincount(members.cand[keep], minlength=m).astype(np.int64),
        passes=[tuple(int(pass_ids[j]) for j in np.flatnonzero(row)) for row in summary.seen],
        names=[f"cyl_{k + 1:03d}" for k in range(m)],
        rejected=rejected,
        n_components=n_components,
        leaning_points=_mask(p.shape[0], leaning_pts),
    )


def _mask(n: int, idx: np.ndarray) -> np.ndarray:
    out = np.zeros(n, bool)
    out[idx] = True
    return out


# -- input -------------------------------------------------------------------------------------


def _validated(p_lgf_m, pass_id, exclude):
    p = np.asarray(p_lgf_m, float)
    if p.ndim != 2 or p.shape[1] != 3:
        raise CylinderError(f"p_lgf_m has shape {p.shape}: expected (n, 3)")
    n = p.shape[0]
    pid = np.asarray(pass_id)
    if pid.shape != (n,):
        raise CylinderError(f"pass_id has shape {pid.shape}: expected ({n},) like p_lgf_m")
    if n and not np.issubdtype(pid.dtype, np.integer):
        raise CylinderError(f"pass_id has dtype {pid.dtype}: expected integers")
    ex = np.asarray(exclude)
    if ex.shape != (n,) or (n and ex.dtype != bool):
        raise CylinderError(f"exclude has shape {ex.shape} and dtype {ex.dtype}: expected ({n},) bool")
    bad = ~np.all(np.isfinite(p), axis=1)
    if bad.any():
        raise CylinderError(
            f"p_lgf_m: {int(bad.sum())} points are not finite (the first is point "
            f"{int(np.flatnonzero(bad)[0])}); drop invalid returns before extracting cylinders"
        )
    pass_ids, pass_index = np.unique(pid.astype(np.int64), return_inverse=True)
    return p, pass_index.astype(np.int64), pass_ids, ex.astype(bool)


def _heading_pairs(pass_ids: np.ndarray, pass_heading_rad: dict[int, float], spread_deg: float):
    """(P, P) bool: which two passes differ in heading by ``spread_deg`` (mod 360°)."""
    missing = [int(i) for i in pass_ids if int(i) not in pass_heading_rad]
    if missing:
        raise CylinderError(f"pass_heading_rad has no heading for pass ids {missing}")
    heading_rad = np.array([float(pass_heading_rad[int(i)]) for i in pass_ids])
    if not np.all(np.isfinite(heading_rad)):
        raise CylinderError(
            f"pass_heading_rad: the heading of pass {int(pass_ids[~np.isfinite(heading_rad)][0])} is not finite"
        )
    diff = np.abs(np.angle(np.exp(1j * (heading_rad[:, None] - heading_rad[None, :]))))
    return np.degrees(diff) >= spread_deg - 1e-9


# -- columns and components --------------------------------------------------------------------


@dataclass(frozen=True, kw_only=True)
class _Members:
    """The points of the candidates (indices into the input) and each one's candidate."""

    pts: np.ndarray  # (k,)
    cand: np.ndarray  # (k,) 0 … m − 1
    m: int

    def restricted(self, keep_point: np.ndarray, keep_cand: np.ndarray) -> _Members:
        """The kept points of the kept candidates, the candidates renumbered in their order."""
        new = np.full(self.m, -1, np.int64)
        new[keep_cand] = np.arange(int(np.count_nonzero(keep_cand)))
        sel = keep_point & keep_cand[self.cand]
        return _Members(pts=self.pts[sel], cand=new[self.cand[sel]], m=int(np.count_nonzero(keep_cand)))


@dataclass(frozen=True, kw_only=True)
class _Columns:
    """The occupied columns of the horizontal grid (keys sorted) and each point's column."""

    column_of: np.ndarray  # (n,) index into ``key``
    key: np.ndarray  # (C,) i × stride + j, sorted
    stride: int


def _columns(xy: np.ndarray, cell_m: float) -> _Columns:
    """The grid's columns; indices start at 1 with a free row and column on each side, so that
    the neighbours of a column never wrap to another row."""
    ij = np.floor(xy / cell_m).astype(np.int64)
    ij -= ij.min(axis=0) - 1
    dims = ij.max(axis=0) + 2
    if float(dims[0]) * float(dims[1]) >= 2.0**62:
        raise CylinderError(
            f"the points span {dims.tolist()} columns of {cell_m} m: too large a grid; "
            "give the points of the quay only"
        )
    key, column_of = np.unique(ij[:, 0] * dims[1] + ij[:, 1], return_inverse=True)
    return _Columns(column_of=column_of.astype(np.int64), key=key, stride=int(dims[1]))


def _vertical(z: np.ndarray, column_of: np.ndarray, n_columns: int, opt: CylinderOptions) -> np.ndarray:
    """(C,) bool: the columns whose points occupy ``min_column_height_m`` of height (in bins of
    ``cell_m``)."""
    k = np.floor(z / opt.cell_m).astype(np.int64)
    k -= k.min()
    n_bins = int(k.max()) + 1
    if float(n_columns) * n_bins >= 2.0**62:
        raise CylinderError(f"the points span {n_bins} height bins of {opt.cell_m} m: too tall a scene")
    occupied = np.bincount(np.unique(column_of * n_bins + k) // n_bins, minlength=n_columns)
    need = max(1, int(np.ceil(opt.min_column_height_m / opt.cell_m - 1e-9)))
    return occupied >= need


def _components(cols: _Columns, vertical: np.ndarray) -> tuple[np.ndarray, int]:
    """(C,) the component of each vertical column (8-neighbour), −1 for the others; and their
    number."""
    idx = np.flatnonzero(vertical)
    comp = np.full(cols.key.size, -1, np.int64)
    if idx.size == 0:
        return comp, 0
    vkey = cols.key[idx]
    src, dst = [np.arange(idx.size)], [np.arange(idx.size)]
    for di, dj in _NEIGHBOURS:
        other = vkey + di * cols.stride + dj
        pos = np.minimum(np.searchsorted(vkey, other), idx.size - 1)
        hit = np.flatnonzero(vkey[pos] == other)
        src.append(hit)
        dst.append(pos[hit])
    a, b = np.concatenate(src), np.concatenate(dst)
    graph = coo_matrix((np.ones(a.size, np.int8), (a, b)), shape=(idx.size, idx.size))
    n_comp, label = connected_components(graph, directed=False)
    comp[idx] = label
    return comp, int(n_comp)


def _compact(comp: np.ndarray, cols: _Columns, n_comp: int, opt: CylinderOptions) -> np.ndarray:
    """(n_comp,) bool: the components that fit 2 × ``max_radius_m`` + 2 cells along north and east."""
    if n_comp == 0:
        return np.zeros(0, bool)
    idx = np.flatnonzero(comp >= 0)
    order = idx[np.argsort(comp[idx], kind="stable")]
    ij = np.column_stack([cols.key // cols.stride, cols.key % cols.stride])
    starts = np.flatnonzero(np.r_[True, np.diff(comp[order]) != 0])
    lo = np.minimum.reduceat(ij[order], starts, axis=0)
    hi = np.maximum.reduceat(ij[order], starts, axis=0)
    max_cells = int(np.floor(2.0 * opt.max_radius_m / opt.cell_m + 1e-9)) + 2
    return np.all(hi - lo + 1 <= max_cells, axis=1)


def _candidate_members(p, kept: np.ndarray, opt: CylinderOptions, rejected) -> tuple[_Members, int]:
    """The kept points of the columns of compact components of vertical columns; and the number
    of components (the wide ones counted in ``rejected``)."""
    if kept.size == 0:
        return _Members(pts=kept, cand=kept.copy(), m=0), 0
    q = p[kept]
    cols = _columns(q[:, :2], opt.cell_m)
    comp, n_comp = _components(cols, _vertical(q[:, 2], cols.column_of, cols.key.size, opt))
    compact = _compact(comp, cols, n_comp, opt)
    rejected["too wide"] += int(np.count_nonzero(~compact))
    comp_of = comp[cols.column_of]
    sel = comp_of >= 0
    every = _Members(pts=kept[sel], cand=comp_of[sel], m=n_comp)
    return every.restricted(np.ones(every.pts.size, bool), compact), n_comp


# -- the pass rule -----------------------------------------------------------------------------


def _apply_pass_rule(members: _Members, pass_index, pair_ok, opt: CylinderOptions, rejected) -> _Members:
    """The candidates in which ``min_passes`` passes hold ``min_points_per_pass`` points each and
    two of those differ in heading by ``min_heading_spread_deg``, with the points of those
    passes only; the others counted in ``rejected`` by reason."""
    m, n_pass, pi = members.m, pair_ok.shape[0], pass_index[members.pts]
    per_pass = np.bincount(members.cand * n_pass + pi, minlength=m * n_pass).reshape(m, n_pass)
    counted = per_pass >= opt.min_points_per_pass
    enough = counted.sum(axis=1) >= opt.min_passes
    c = counted.astype(float)
    spread = np.einsum("ij,jk,ik->i", c, pair_ok.astype(float), c) > 0
    few_points = per_pass.sum(axis=1) < opt.min_passes * opt.min_points_per_pass
    rejected["few points"] += int(np.count_nonzero(~enough & few_points))
    rejected["few passes"] += int(np.count_nonzero(~enough & ~few_points))
    rejected["same heading"] += int(np.count_nonzero(enough & ~spread))
    return members.restricted(counted[members.cand, pi], enough & spread)


# -- circles -----------------------------------------------------------------------------------


def _group_median(v: np.ndarray, grp: np.ndarray, m: int) -> np.ndarray:
    """The (lower) median of ``v`` in each of ``m`` groups; 0 for an empty group."""
    out = np.zeros(m)
    order = np.lexsort((v, grp))
    n = np.bincount(grp, minlength=m)
    start = np.cumsum(n) - n
    has = n > 0
    out[has] = v[order[start[has] + (n[has] - 1) // 2]]
    return out


def _inliers(residual: np.ndarray, cand: np.ndarray, m: int) -> np.ndarray:
    """The points within 3 × the robust RMS (1.4826 × MAD) of their candidate's circle."""
    dev = residual - _group_median(residual, cand, m)[cand]
    rms0 = ROBUST_SCALE * _group_median(np.abs(dev), cand, m)
    return np.abs(dev) <= np.maximum(OUTLIER_FACTOR * rms0[cand], _MIN_THRESHOLD_M)


def _radius_ok(radius_m: np.ndarray, opt: CylinderOptions) -> np.ndarray:
    return np.isfinite(radius_m) & (radius_m >= opt.min_radius_m) & (radius_m <= opt.max_radius_m)


# -- the candidates' rules ---------------------------------------------------------------------


@dataclass(frozen=True, kw_only=True)
class _Summary:
    """Per candidate, what the rules judge and the result reports."""

    center_m: np.ndarray  # (m, 3)
    radius_m: np.ndarray
    height_m: np.ndarray
    top_m: np.ndarray  # the smallest z (NED: the top) of the members
    rms_m: np.ndarray
    arc_deg: np.ndarray
    lean_deg: np.ndarray  # the axis's lean fitted to the members' heights
    lean_z: np.ndarray  # how clearly the members show it (circlefit.lean)
    seen: np.ndarray  # (m, P) bool: the passes with members

    def take(self, k: np.ndarray) -> _Summary:
        return _Summary(**{name: getattr(self, name)[k] for name in self.__dataclass_fields__})


def _arc_deg(angle: np.ndarray, cand: np.ndarray, m: int) -> np.ndarray:
    """(m,) 360° minus the largest gap between the bearings ``angle`` (rad) of each candidate."""
    out = np.zeros(m)
    if angle.size == 0:
        return out
    order = np.lexsort((angle, cand))
    a, c = angle[order], cand[order]
    starts = np.flatnonzero(np.r_[True, c[1:] != c[:-1]])
    ends = np.r_[starts[1:], a.size] - 1
    gap = np.r_[0.0, np.diff(a)]
    gap[starts] = a[starts] + 2.0 * np.pi - a[ends]  # across ±180°
    out[c[starts]] = 360.0 - np.degrees(np.maximum.reduceat(gap, starts))
    return out


def _summarize(p, members: _Members, circles: Circles, pass_index, n_pass: int) -> _Summary:
    """Axis (the mean of the passes' centres at the members' mid height), radius, height, RMS
    about each pass's own centre, arc seen and passes of each candidate."""
    m, cand = members.m, members.cand
    n_groups = np.maximum(np.bincount(circles.group_cand, minlength=m), 1)
    axis = np.column_stack(sums(circles.group_cand, m, *circles.center_m.T)) / n_groups[:, None]
    z = p[members.pts, 2]
    top = np.full(m, np.inf)
    bottom = np.full(m, -np.inf)
    np.minimum.at(top, cand, z)
    np.maximum.at(bottom, cand, z)
    n = np.maximum(np.bincount(cand, minlength=m), 1)
    d = p[members.pts, :2] - circles.center_m[circles.group]
    seen = np.zeros((m, n_pass), bool)
    seen[cand, pass_index[members.pts]] = True
    lean_deg, lean_z = lean(d, z, circles, m)
    return _Summary(
        center_m=np.column_stack([axis, 0.5 * (top + bottom)]),
        radius_m=circles.radius_m,
        height_m=bottom - top,
        top_m=top,
        rms_m=np.sqrt(np.bincount(cand, circles.residual_m**2, minlength=m) / n),
        arc_deg=_arc_deg(np.arctan2(d[:, 1], d[:, 0]), cand, m),
        lean_deg=lean_deg,
        lean_z=lean_z,
        seen=seen,
    )


def _judge(s: _Summary, opt: CylinderOptions, rejected: dict[str, int]) -> tuple[np.ndarray, np.ndarray]:
    """(m,) bool each: the refitted candidates that pass the shape rules, and those that fail
    only the last, ``leaning``; the others counted by their first failed rule."""
    ok = np.ones(s.radius_m.size, bool)
    with np.errstate(invalid="ignore"):
        rules = (
            ("radius", _radius_ok(s.radius_m, opt)),
            ("short", s.height_m >= opt.min_height_m),
            ("narrow arc", s.arc_deg >= opt.min_arc_deg),
            ("not circular", s.rms_m <= opt.max_rms_m),
            ("leaning", ~((s.lean_deg > opt.max_lean_deg) & (s.lean_z > LEAN_Z))),  # NaN: upright
        )
    failed = ok
    for reason, passed in rules:
        failed = ok & ~passed
        rejected[reason] += int(np.count_nonzero(failed))
        ok &= passed
    return ok, failed


def _fit_and_judge(p, pass_index, members: _Members, pair_ok, opt: CylinderOptions, rejected):
    """Pass rule, fit, radius, outlier drop, pass rule, refit, shape rules: the accepted
    candidates' members and their summary, and the member points of those rejected only as
    leaning."""
    n_pass = pair_ok.shape[0]
    members = _apply_pass_rule(members, pass_index, pair_ok, opt, rejected)
    first = fit_circles(p[members.pts, :2], members.cand, pass_index[members.pts], members.m, n_pass)
    fits = _radius_ok(first.radius_m, opt)
    rejected["radius"] += int(np.count_nonzero(~fits))
    members = members.restricted(_inliers(first.residual_m, members.cand, members.m), fits)
    members = _apply_pass_rule(members, pass_index, pair_ok, opt, rejected)
    circles = fit_circles(p[members.pts, :2], members.cand, pass_index[members.pts], members.m, n_pass)
    summary = _summarize(p, members, circles, pass_index, n_pass)
    ok, leaning = _judge(summary, opt, rejected)
    leaning_pts = members.pts[leaning[members.cand]]
    return (
        members.restricted(np.ones(members.pts.size, bool), ok),
        summary.take(np.flatnonzero(ok)),
        leaning_pts,
    )


# -- subsampling -------------------------------------------------------------------------------


def _subsample(members: _Members, z, pass_index, s: _Summary, opt: CylinderOptions) -> np.ndarray:
    """Which members stay: all of a cylinder within the cap; else the cap of them, round-robin
    over the passes, within a pass round-robin over HEIGHT_BINS height bins, the order within
    a round and within a bin from a fixed-seed permutation."""
    cand = members.cand
    if cand.size == 0:
        return np.ones(0, bool)
    rel = (z - s.top_m[cand]) / np.maximum(s.height_m[cand], _TINY_M)
    height_bin = np.clip(np.floor(rel * HEIGHT_BINS), 0, HEIGHT_BINS - 1).astype(np.int64)
    tie = np.random.default_rng(SUBSAMPLE_SEED).permutation(cand.size)
    n_pass = int(pass_index.max()) + 1
    cand_pass = cand * n_pass + pass_index
    r_bin = rank_in_group(cand_pass * HEIGHT_BINS + height_bin, tie)  # rank within its bin
    r_pass = rank_in_group(cand_pass, r_bin, tie)  # round-robin over the bins of its pass
    r_cand = rank_in_group(cand, r_pass, tie)  # round-robin over the passes of its cylinder
    return r_cand < opt.max_points_per_cylinder
