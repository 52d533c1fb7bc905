"""One target in one pass (steps 1–4 of :mod:`calib.extraction.extract`): the candidates near
its seed, their intensity classes, planes of its orientation (a dominant plane of another
orientation set aside, parallel planes one after another), the cluster of its size — or the
reason it is missing or rejected. The options and the error of the extraction live here too."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

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
    #: "found"; "missing" (too few points, no plane of its orientation); "rejected" (points
    #: of its orientation there, but no cluster of its size: the wall or a neighbour)
    status: str = "found"

    @property
    def n_points(self) -> int:
        return int(self.indices.size)


def missing_target(target, pass_id, n_cand, n_class, contrast, note, status="missing") -> TargetPass:
    """Nothing kept of a target in a pass, and why (``status`` missing or rejected)."""
    return TargetPass(
        target,
        pass_id,
        np.empty(0, np.int64),
        n_cand,
        n_class,
        contrast,
        None,
        float("nan"),
        None,
        note,
        status,
    )


@dataclass(frozen=True)
class _Class:
    """The candidates of the target's reflectivity class."""

    indices: np.ndarray
    contrast: float
    note: str


def _target_classes(p_m, intensity, cand, rect: Rectangle, opts: ExtractOptions, origin_m) -> list[_Class]:
    """Step 2: the candidates split by intensity, in the order they are tried. The split is
    made on the incidence-corrected intensities when the beam origins are given; when those
    show no contrast the raw ones are tried (a scanner whose intensity does not fall with
    incidence shows a grazing wall brighter than the target once corrected). With contrast:
    the class the configured reflectivity expects (bright from 0.5 up), then the other (the
    configured value is a guess; what matters is the target against *its* wall), then every
    candidate by geometry alone; without contrast: every candidate."""
    tries = [] if origin_m is None else [incidence_corrected(p_m[cand], intensity[cand], origin_m[cand])]
    tries.append(intensity[cand])
    splits = [(refl, intensity_split(refl, opts.min_contrast)) for refl in tries]
    usable = [s for s in splits if s[1].threshold is not None]
    refl, split = usable[0] if usable else max(splits, key=lambda s: s[1].contrast)
    geometry = (
        f"no reflectivity contrast around it (ratio {split.contrast:.2f} < "
        f"{opts.min_contrast:g}): separated from its surroundings by geometry only"
    )
    if split.threshold is None:
        return [_Class(cand, split.contrast, geometry)]
    bright = refl >= split.threshold
    expected, other = ("brighter", "darker") if rect.reflectivity >= 0.5 else ("darker", "brighter")
    first = bright if expected == "brighter" else ~bright
    return [
        _Class(cand[first], split.contrast, ""),
        _Class(
            cand[~first],
            split.contrast,
            f"found among the {other} points around it (its configured reflectivity "
            f"{rect.reflectivity:g} expected the {expected})",
        ),
        _Class(
            cand,
            split.contrast,
            f"in neither intensity class (ratio {split.contrast:.2f}): separated from its surroundings by "
            f"geometry only",
        ),
    ]


#: parallel planes tried per target and pass (the target, the wall behind it, a ledge)
MAX_PARALLEL_PLANES = 3


def _refined_band(q, keep, normal, rect: Rectangle, opts: ExtractOptions):
    """Step 3's refinement: least squares on the band, then a band of five robust σ (three
    rounds); None when the points are not a plane of the target's orientation."""
    cos_tilt = np.cos(opts.max_tilt_rad)
    d = 0.0
    for _ in range(3):
        fit = fit_plane(q[keep], orient_like=normal)
        if abs(fit.normal @ rect.normal) < cos_tilt:
            return None
        normal, d = fit.normal, fit.d
        dist = q @ normal + d
        sigma = 1.4826 * np.median(np.abs(dist[keep] - np.median(dist[keep])))
        band = max(3.0 * opts.ransac_distance_m, 5.0 * sigma)
        keep = np.abs(dist) <= band
    return normal, d, keep


def _ransac(q, left, rect: Rectangle, opts: ExtractOptions, rng, oriented: bool):
    """A RANSAC plane among the points ``left`` (of the target's orientation when ``oriented``),
    its inliers as a mask over ``q``; None when there is none."""
    idx = np.flatnonzero(left)
    if idx.size < opts.min_points_per_pass:
        return None
    plane = ransac_plane(
        q[idx],
        opts.ransac_distance_m,
        opts.ransac_stop_fraction,
        opts.ransac_max_iterations,
        rng,
        rect.normal if oriented else None,
        opts.max_tilt_rad if oriented else None,
        local_radius_m=0.5 * min(rect.width_m, rect.height_m),
    )
    if plane is None or plane.inliers.sum() < opts.min_points_per_pass:
        return None
    keep = np.zeros(q.shape[0], bool)
    keep[idx[plane.inliers]] = True
    return plane.normal, keep


def _without_other_surface(q, rect: Rectangle, opts: ExtractOptions, rng) -> np.ndarray:
    """The points left once the dominant plane is set aside when its orientation is not the
    target's (the wall behind an inclined target: a plane of the target's orientation would
    otherwise be a slice across it, holding more points than the target itself)."""
    left = np.ones(q.shape[0], bool)
    found = _ransac(q, left, rect, opts, rng, oriented=False)
    if found is None:
        return left
    normal, keep = found
    fit = fit_plane(q[keep], orient_like=normal)
    if abs(fit.normal @ rect.normal) >= np.cos(opts.max_tilt_rad):
        return left  # the dominant plane may be the target's own (or its wall's): the search decides
    dist = q @ fit.normal + fit.d
    sigma = 1.4826 * np.median(np.abs(dist[keep] - np.median(dist[keep])))
    return np.abs(dist) > max(3.0 * opts.ransac_distance_m, 5.0 * sigma)


def _parallel_planes(q, rect: Rectangle, opts: ExtractOptions, rng):
    """Step 3: up to :data:`MAX_PARALLEL_PLANES` planes of the target's orientation, the
    largest first, once a dominant plane of another orientation is set aside
    (:func:`_without_other_surface`); each plane's band is taken out before the next is sought
    (a target proud of a wall of its own orientation is the second plane when it is not the
    first). A RANSAC plane whose refit leaves the orientation (its inliers were a slice across
    another surface) is skipped, its inliers set aside."""
    left = _without_other_surface(q, rect, opts, rng)
    out: list[tuple[np.ndarray, float, np.ndarray]] = []
    for _ in range(2 * MAX_PARALLEL_PLANES):
        if len(out) == MAX_PARALLEL_PLANES:
            break
        found = _ransac(q, left, rect, opts, rng, oriented=True)
        if found is None:
            break
        normal, keep = found
        refined = _refined_band(q, keep, normal, rect, opts)
        band = None if refined is None else refined[2] & left
        if band is None or band.sum() < opts.min_points_per_pass:
            left &= ~keep
            continue
        out.append((refined[0], refined[1], band))
        left &= ~band
    return out


@dataclass(frozen=True)
class _Cluster:
    mask: np.ndarray  # over the class points
    extent_m: np.ndarray  # (width, height)
    ab_m: np.ndarray  # in-plane coordinates of every class point about the seed centre
    normal: np.ndarray
    d: float
    mismatch: float  # Σ |log(extent / size)|


def _clusters_on(q, band, normal, d, rect: Rectangle, centre, opts: ExtractOptions) -> list[_Cluster]:
    """Step 4: the connected clusters of one plane's band with their extents."""
    u, v = in_plane_axes(normal, rect.u_axis)
    ab = np.column_stack([(q - centre) @ u, (q - centre) @ v])
    size = np.array([rect.width_m, rect.height_m])
    on = np.flatnonzero(band)
    labels = clusters(q[on], link_radius(q[on], min(rect.width_m, rect.height_m)))
    out = []
    for lab in np.unique(labels):
        mask = np.zeros(q.shape[0], bool)
        mask[on[labels == lab]] = True
        if mask.sum() < opts.min_points_per_pass:
            continue
        ext = robust_extent(ab[mask])
        out.append(
            _Cluster(mask, ext, ab, normal, d, float(np.sum(np.abs(np.log(np.maximum(ext, 1e-3) / size)))))
        )
    return out


def _fits(c: _Cluster, rect: Rectangle, opts: ExtractOptions) -> bool:
    """No larger than the target (a partial view may be smaller)."""
    size = np.array([rect.width_m, rect.height_m])
    return bool(np.all(c.extent_m <= size * (1.0 + opts.size_tolerance) + 0.05))


def _offset_from_seed_m(c: _Cluster, centre) -> float:
    """How far the cluster's plane lies from the seed centre along its normal."""
    return abs(float(c.normal @ centre + c.d))


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
    origins ``origin_m`` (n, 3) the intensities are corrected for incidence first.

    A cluster larger than the target (the wall around it, a neighbour touching it) is never
    trimmed to the target's size: the target is *rejected* in that pass with the reason."""
    centre = rect.center_m if seed_m is None else np.asarray(seed_m, float)
    radius = opts.search_radius_m + 0.5 * np.hypot(rect.width_m, rect.height_m)
    near = np.sum((p_m[idx] - centre) ** 2, axis=1) <= radius**2
    cand = idx[near]
    n_cand = cand.size
    if n_cand < opts.min_points_per_pass:
        return missing_target(
            rect.name, pass_id, n_cand, 0, 1.0, f"{n_cand} points within {radius:.1f} m of its centre"
        )
    tried = []  # the classes in turn, up to the first that holds the target
    for cls in _target_classes(p_m, intensity, cand, rect, opts, origin_m):
        tried.append(_find_in_class(p_m, cls, rect, centre, pass_id, n_cand, opts, rng))
        if tried[-1].status == "found":
            return tried[-1]
    return next((t for t in tried if t.status == "rejected"), tried[0])


def _find_in_class(
    p_m, cls: _Class, rect: Rectangle, centre, pass_id: int, n_cand: int, opts, rng
) -> TargetPass:
    """Steps 3–4 among one intensity class of the candidates."""
    n_cls = cls.indices.size
    if n_cls < opts.min_points_per_pass:
        return missing_target(
            rect.name,
            pass_id,
            n_cand,
            n_cls,
            cls.contrast,
            f"{n_cls} of {n_cand} nearby points have its reflectivity",
        )
    q = p_m[cls.indices]
    planes = _parallel_planes(q, rect, opts, rng)
    if not planes:
        return missing_target(
            rect.name, pass_id, n_cand, n_cls, cls.contrast, "no plane with its orientation among its points"
        )
    found = [c for normal, d, band in planes for c in _clusters_on(q, band, normal, d, rect, centre, opts)]
    fitting = [c for c in found if _fits(c, rect, opts)]
    if not fitting:
        return _rejected(rect, pass_id, n_cand, cls, found)
    # the best size match; near-equal matches: nearer the seed along the normal, then larger
    best = min(
        fitting,
        key=lambda c: (round(c.mismatch, 1), round(_offset_from_seed_m(c, centre), 1), -int(c.mask.sum())),
    )
    # the middle of the robust span (stray points do not pull it); on a partial view
    # (extent below the size) the box still holds the whole cluster
    mid = np.percentile(best.ab_m[best.mask], [2.0, 98.0], axis=0).mean(axis=0)
    half = 0.5 * np.array([rect.width_m, rect.height_m]) - opts.edge_margin_m
    inside = np.all(np.abs(best.ab_m - mid) <= half, axis=1) & best.mask
    sel = cls.indices[inside]
    if sel.size < opts.min_points_per_pass:
        return missing_target(
            rect.name, pass_id, n_cand, n_cls, cls.contrast, f"only {sel.size} points inside its rectangle"
        )
    rms = float(np.sqrt(np.mean((p_m[sel] @ best.normal + best.d) ** 2)))
    return TargetPass(
        rect.name,
        pass_id,
        np.sort(sel),
        n_cand,
        n_cls,
        cls.contrast,
        best.normal,
        rms,
        best.extent_m,
        cls.note,
    )


def _rejected(rect: Rectangle, pass_id: int, n_cand: int, cls: _Class, found: list[_Cluster]) -> TargetPass:
    """No cluster of the target's size: the reason names the nearest miss."""
    size = np.array([rect.width_m, rect.height_m])
    if not found:
        why = "its plane's points form no cluster of at least the minimum size"
    else:
        c = min(found, key=lambda c: c.mismatch)
        why = (
            f"the nearest cluster of its orientation measures {c.extent_m[0]:.2f} × {c.extent_m[1]:.2f} m "
            f"against the configured {size[0]:.2f} × {size[1]:.2f} m: more than the target alone (the wall "
            f"or a neighbour joined to it), not used"
        )
    note = "; ".join(filter(None, [cls.note, why]))
    return missing_target(rect.name, pass_id, n_cand, cls.indices.size, cls.contrast, note, status="rejected")
