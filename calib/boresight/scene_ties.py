"""Scene tie patches: planar pieces of the wall, piles and other surfaces around the targets,
added to the adjustment as nuisance planes (with their own roughness variance).

After a first solution on the targets, every point is georeferenced with that boresight (the
passes then agree to millimetres, so a patch is one surface and not one per pass), candidate
patches are cut (:func:`calib.extraction.patches.extract_candidates`: planar, seen by two or more
passes of different headings, away from the targets) and chosen like a designer would: greedily
by how much each adds to the boresight's information (the log-determinant gain of its 3 × 3
contribution after its own plane is eliminated), until a patch adds less than
:data:`MIN_GAIN` or :data:`MAX_PATCHES` are chosen. The chosen patches' points join the
targets' observations with ``patch_planes`` naming them, so the GLS estimator gives each a
roughness variance estimated from its residuals: a wall that is not flat widens its own σ
instead of bending the boresight.

Vertical cylinders (piles, posts: :func:`calib.extraction.cylinders.extract_cylinders`) are
candidates beside the patches, chosen by the same gain: a yaw moves a point along the track,
which a wall parallel to it barely sees and a cylinder sees as a change of its distance from
the axis (:mod:`calib.boresight.ghmodel`). The cylinders are found first and no patch is cut
on one (a large pile's face is flat to 1–2 cm over a patch's width).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from scipy import stats
from scipy.spatial import cKDTree

from calib.boresight.adjust import AdjustmentResult, adjust
from calib.boresight.gausshelmert import initial_state, plane_centers
from calib.boresight.ghmodel import State, linearize
from calib.boresight.gls import gls_information
from calib.boresight.observations import (
    MIN_POINTS_PER_PLANE,
    AdjustOptions,
    Observations,
    build_observations,
)
from calib.core import frames
from calib.core.georef import Mount
from calib.core.trajectory import Poses, Trajectory
from calib.extraction.cylinders import CylinderCandidates, CylinderOptions, extract_cylinders
from calib.extraction.patches import PatchCandidates, PatchOptions, extract_candidates, gather_members
from calib.extraction.points import georeference_passes, pass_headings
from calib.io.bundle import ScanPoints
from calib.io.site import Site

MAX_PATCHES = 30
MAX_CYLINDERS = 10  # tie cylinders (piles) beside the patches, their own budget (:func:`choose`)
#: patches farther than this from every target point are not used: the scene *around* the
#: targets, seen at nearly the same instants and geometry. Far surfaces (a tower 20–40 m up and
#: along, tested) gave σ that covered the truth at 2σ only 80 % of the time — a mismatch between
#: such data and the model that is not understood yet, so they are left out.
MAX_DISTANCE_M = 10.0
MIN_GAIN = 0.01  # log-det gain below which a patch is not worth its plane


@dataclass
class TiePatches:
    observations: Observations  # targets and the chosen features together
    planes: list  # a-priori features: the targets' planes (normal, d), then the chosen ties'
    chosen: list[int]  # indices into the candidates: the patches', then the cylinders' after them
    candidates: PatchCandidates | None
    gain: list[float]  # log-det gain of each chosen feature (when it was chosen)
    cylinders: CylinderCandidates | None = None

    @property
    def n_patch_candidates(self) -> int:
        return 0 if self.candidates is None else len(self.candidates.names)


def concat(a: Observations, b: Observations) -> Observations:
    """``a`` then ``b`` (plane indices of ``b`` after ``a``'s; pass indices over the union)."""
    pass_ids = sorted(set(a.pass_ids) | set(b.pass_ids))
    remap = [np.searchsorted(pass_ids, o.pass_ids) for o in (a, b)]
    return Observations(
        np.concatenate([a.t_gps_s, b.t_gps_s]),
        np.concatenate([a.l, b.l]),
        np.concatenate([a.sigma_l, b.sigma_l]),
        np.concatenate([a.plane_index, b.plane_index + len(a.plane_names)]),
        np.concatenate([remap[0][a.pass_index], remap[1][b.pass_index]]),
        a.plane_names + b.plane_names,
        pass_ids,
        np.concatenate([a.point_ids, b.point_ids]),
        a.trajectory,
        {**b.pass_headings_rad, **a.pass_headings_rad},
        tuple(a.patch_planes) + tuple(len(a.plane_names) + j for j in b.patch_planes),
        a.beam_half_divergence_rad,
    )


def _near_targets(
    cands: PatchCandidates, target_points_m: np.ndarray, max_distance_m: float
) -> PatchCandidates:
    """The candidates whose centre lies within ``max_distance_m`` of a target point."""
    return _kept_near(
        cands, target_points_m, max_distance_m, ("normals", "d_m", "centers_m", "rms_m", "n_points")
    )


def _cylinders_near_targets(
    cyl: CylinderCandidates, target_points_m: np.ndarray, max_distance_m: float
) -> CylinderCandidates:
    """The cylinder candidates whose axis lies within ``max_distance_m`` of a target point
    (measured at the axis's mid height, like a patch's centre)."""
    fields = ("centers_m", "radius_m", "height_m", "rms_m", "arc_deg", "n_points")
    return _kept_near(cyl, target_points_m, max_distance_m, fields)


def _kept_near(
    cands: Any, target_points_m: np.ndarray, max_distance_m: float, arrays: tuple[str, ...]
) -> Any:
    """Patch or cylinder candidates (``arrays``: their per-candidate array fields; ``passes`` and
    ``names`` are lists) with only those centred within ``max_distance_m`` of a target point,
    the points' labels renumbered."""
    n = len(cands.names)
    if target_points_m.shape[0] == 0 or n == 0:
        return cands
    d, _ = cKDTree(target_points_m).query(cands.centers_m)
    keep = np.flatnonzero(d <= max_distance_m)
    remap = np.full(n, -1, np.int64)
    remap[keep] = np.arange(keep.size)
    kept: dict[str, Any] = {f: getattr(cands, f)[keep] for f in arrays}
    kept.update({f: [getattr(cands, f)[j] for j in keep] for f in ("passes", "names")})
    return replace(cands, labels=np.where(cands.labels >= 0, remap[np.maximum(cands.labels, 0)], -1), **kept)


def boresight_information(obs: Observations, mount, planes) -> np.ndarray:
    """(m, 3, 3): each plane's contribution to the boresight information with its own plane
    eliminated, under white weights (a ranking, not a σ)."""
    r_nom = frames.rotation_zyx(*mount.nominal_rad)
    state = initial_state(mount, planes, len(obs.pass_ids), plane_centers(obs, mount, r_nom))
    lin = linearize(state, r_nom, obs.plane_index, obs.pass_index, obs.l)
    w = 1.0 / np.einsum("ij,ij->i", lin.B**2, obs.sigma_l**2)
    m = len(obs.plane_names)
    a, p = lin.A_boresight, lin.A_plane

    def per_plane(x, y):
        prod = np.einsum("ni,nj->nij", x * w[:, None], y).reshape(len(obs), -1)
        out = np.stack(
            [np.bincount(obs.plane_index, prod[:, k], minlength=m) for k in range(prod.shape[1])], 1
        )
        return out.reshape(m, x.shape[1], y.shape[1])

    I_bb, I_bp, I_pp = per_plane(a, a), per_plane(a, p), per_plane(p, p)
    return I_bb - I_bp @ np.linalg.solve(I_pp + 1e-12 * np.eye(3), np.transpose(I_bp, (0, 2, 1)))


def choose(
    info: np.ndarray,
    base: np.ndarray,
    max_patches: int = MAX_PATCHES,
    is_cylinder: np.ndarray | None = None,
    max_cylinders: int = MAX_CYLINDERS,
    n_points: np.ndarray | None = None,
) -> tuple[list[int], list[float]]:
    """Greedy log-det selection over the candidates' ``info`` starting from ``base``, each
    adding at least :data:`MIN_GAIN`: at most ``max_patches`` of them. With ``is_cylinder``
    (per candidate) the cylinders have a budget of their own, ``max_cylinders``, and no least
    gain: the white weights of ``info`` let a hundred wall patches look as if they fixed yaw,
    which the GLS with the POS errors' correlation says they do not — on a harbour calibration
    site three piles valued at a gain of 0.01 took the yaw bound from 44 to 28 mdeg.
    ``n_points`` (per candidate): one with fewer than the adjustment takes
    (:data:`~calib.boresight.observations.MIN_POINTS_PER_PLANE`) is never chosen — without a
    least gain, a pile whose points a block's range window or thinning left out would be."""
    cyl = np.zeros(len(info), bool) if is_cylinder is None else np.asarray(is_cylinder, bool)
    budget = {False: max_patches, True: max_cylinders if is_cylinder is not None else 0}
    least = np.where(cyl, 0.0, MIN_GAIN)
    chosen: list[int] = []
    gains: list[float] = []
    current = base.copy()
    _, ld = np.linalg.slogdet(current)
    left = np.array([budget[bool(c)] > 0 for c in cyl], bool)
    if n_points is not None:
        left &= np.asarray(n_points) >= MIN_POINTS_PER_PLANE
    while left.any():
        scores = np.linalg.slogdet(current[None] + info)[1] - ld  # every candidate at once
        left &= scores >= least
        if not left.any():
            break
        scores[~left] = -np.inf
        j = int(np.argmax(scores))  # the first of equal scores, as before
        chosen.append(j)
        gains.append(float(scores[j]))
        current = current + info[j]
        ld += scores[j]
        left[j] = False
        kind = bool(cyl[j])
        budget[kind] -= 1
        if budget[kind] <= 0:
            left &= cyl != kind
    return chosen, gains


#: the patch and cylinder searches' options when the caller gives none (frozen, shared)
_DEFAULT_PATCH_OPTIONS = PatchOptions()
_DEFAULT_CYLINDER_OPTIONS = CylinderOptions()


def add_tie_patches(
    targets: Observations,
    target_planes,
    cov_boresight: np.ndarray,
    mount_est,
    p_lgf_m: np.ndarray,
    origin_lgf_m: np.ndarray,
    t_gps_s: np.ndarray,
    range_m: np.ndarray,
    scan_angle_rad: np.ndarray,
    pass_id: np.ndarray,
    on_target: np.ndarray,
    trajectory,
    sigmas: dict,
    poses=None,
    options: PatchOptions = _DEFAULT_PATCH_OPTIONS,
    pass_heading_rad: dict[int, float] | None = None,
    max_distance_m: float = MAX_DISTANCE_M,
) -> TiePatches | None:
    """The targets' observations with the chosen tie patches added (None: no patch found).

    ``p_lgf_m``/``origin_lgf_m``: every point georeferenced with ``mount_est`` (the first
    solution); ``on_target``: the points the targets use; ``cov_boresight``: the first
    solution's covariance (the information the patches must add to); ``sigmas``: the site's
    ``sigma_range_m``, ``sigma_scan_angle_rad``, ``sigma_position_m``, ``sigma_attitude_rad``;
    ``poses``: per-point POS observations replacing the trajectory's (a simulator's)."""
    headings = {**(pass_heading_rad or {}), **targets.pass_headings_rad}
    found = tie_candidates(p_lgf_m, origin_lgf_m, pass_id, headings, on_target, options, max_distance_m)
    if found is None:
        return None
    idx = np.flatnonzero(found.labels >= 0)
    obs = build_observations(
        trajectory,
        t_gps_s[idx],
        range_m[idx],
        scan_angle_rad[idx],
        found.labels[idx],
        pass_id[idx],
        list(found.names),
        point_ids=idx,
        time_offset_s=mount_est.time_offset_s,
        pass_headings_rad=headings,
        **sigmas,
    )
    if poses is not None:
        obs.l[:, 0:6] = np.column_stack([poses.p_lgf_m[idx], poses.rpy_rad[idx]])
    info = boresight_information(obs, mount_est, found.features)
    counts = np.bincount(obs.plane_index, minlength=len(found.names))
    chosen, gains = choose(info, np.linalg.inv(cov_boresight), is_cylinder=found.is_cylinder, n_points=counts)
    if not chosen:
        return None
    order = sorted(chosen)
    sub = obs.of_planes(order)
    gain = [gains[chosen.index(j)] for j in order]
    return TiePatches(
        concat(targets, sub),
        list(target_planes) + [found.features[j] for j in order],
        order,
        found.patches,
        gain,
        found.cylinders,
    )


@dataclass(frozen=True, kw_only=True)
class TieCandidates:
    """The scene's tie features found around the targets: planar patches, then cylinders."""

    patches: PatchCandidates | None
    cylinders: CylinderCandidates | None
    labels: np.ndarray  # (n,) per point its feature (patches first, then cylinders), −1 none
    features: list  # (normal, d) per patch, a VerticalCylinder per cylinder
    names: list[str]

    @property
    def n_patches(self) -> int:
        return 0 if self.patches is None else len(self.patches.names)

    @property
    def is_cylinder(self) -> np.ndarray:
        """(m,) bool: which features are cylinders (they follow the patches)."""
        return np.arange(len(self.names)) >= self.n_patches

    @property
    def centers_m(self) -> np.ndarray:
        """(m, 3): the patches' centres, then the cylinders' axis points at mid height."""
        parts = [c.centers_m for c in (self.patches, self.cylinders) if c is not None]
        return np.concatenate(parts) if parts else np.empty((0, 3))


def tie_candidates(
    p_lgf_m,
    origin_lgf_m,
    pass_id,
    headings,
    on_target,
    options: PatchOptions,
    max_distance_m: float,
    cylinder_options: CylinderOptions = _DEFAULT_CYLINDER_OPTIONS,
) -> TieCandidates | None:
    """The vertical cylinders (piles, posts) and the planar patches seen from two headings within
    ``max_distance_m`` of the targets (none: every one); no patch is cut on a cylinder found
    (None: neither was found).

    The cylinders come first: a 1.2 m pile's face is flat to 1–2 cm over a patch's width, and
    such patches passed the planarity rule and biased yaw by 1.5 σ on average on montreal_piles
    (each pass samples a curved face differently)."""
    cyl = extract_cylinders(p_lgf_m, pass_id, headings, on_target, cylinder_options)
    cyl = _cylinders_near_targets(cyl, p_lgf_m[on_target], max_distance_m)
    not_patch = on_target | on_cylinders(p_lgf_m, cyl) | cyl.leaning_points
    patches = _patch_candidates(
        p_lgf_m, origin_lgf_m, pass_id, headings, on_target, not_patch, options, max_distance_m
    )
    n_patches = 0 if patches is None else len(patches.names)
    if n_patches == 0 and len(cyl) == 0:
        return None
    labels = np.full(p_lgf_m.shape[0], -1, np.int64) if patches is None else patches.labels.copy()
    on_cylinder = (cyl.labels >= 0) & (labels < 0)
    on_cylinder[on_cylinder] = facing_cylinder(
        p_lgf_m[on_cylinder], origin_lgf_m[on_cylinder], cyl.centers_m[cyl.labels[on_cylinder]]
    )
    labels[on_cylinder] = cyl.labels[on_cylinder] + n_patches
    planes = [] if patches is None else [(n, d) for n, d in zip(patches.normals, patches.d_m, strict=True)]
    return TieCandidates(
        patches=patches,
        cylinders=cyl if cyl.n_components else None,  # none kept: what was rejected, and why
        labels=labels,
        features=planes + cyl.cylinders(),
        names=([] if patches is None else list(patches.names)) + list(cyl.names),
    )


#: a point within this of a cylinder's surface (and within its height) belongs to the cylinder
CYLINDER_SHELL_M = 0.05


def on_cylinders(p_lgf_m: np.ndarray, cyl: CylinderCandidates) -> np.ndarray:
    """(n,) bool: the points on the surface of a found cylinder (within :data:`CYLINDER_SHELL_M`
    and its height), whether or not the cylinder's subsample holds them."""
    out = np.zeros(p_lgf_m.shape[0], bool)
    for c, r, h in zip(cyl.centers_m, cyl.radius_m, cyl.height_m, strict=True):
        near = np.flatnonzero(
            (np.abs(p_lgf_m[:, 0] - c[0]) <= r + CYLINDER_SHELL_M)
            & (np.abs(p_lgf_m[:, 1] - c[1]) <= r + CYLINDER_SHELL_M)
            & (np.abs(p_lgf_m[:, 2] - c[2]) <= 0.5 * h + CYLINDER_SHELL_M)
        )
        radial = np.hypot(p_lgf_m[near, 0] - c[0], p_lgf_m[near, 1] - c[1])
        out[near[np.abs(radial - r) <= CYLINDER_SHELL_M]] = True
    return out


#: a cylinder's points are used where the beam meets the surface within 60° of head-on. Near
#: the silhouette a range residual moves the point along the surface, off the cylinder by its
#: square over the diameter: the linearization fails there (the roughness estimate of a 0.3 m
#: pile jumped between 8 and 22 mm from one iteration to the next and the adjustment did not
#: converge), and a real beam there half hits the pile and half what is behind it.
MIN_COS_INCIDENCE_CYLINDER = 0.5


def facing_cylinder(p_lgf_m: np.ndarray, origin_lgf_m: np.ndarray, axis_m: np.ndarray) -> np.ndarray:
    """(k,) bool: the points on vertical cylinders (axis points ``axis_m`` (k, 3)) whose beam
    from ``origin_lgf_m`` meets the surface within :data:`MIN_COS_INCIDENCE_CYLINDER`."""
    radial = p_lgf_m[:, :2] - axis_m[:, :2]
    beam = p_lgf_m - origin_lgf_m
    dot = np.einsum("ij,ij->i", radial, beam[:, :2])
    cos = np.abs(dot) / (np.linalg.norm(radial, axis=1) * np.linalg.norm(beam, axis=1))
    return cos >= MIN_COS_INCIDENCE_CYLINDER


def _patch_candidates(
    p_lgf_m, origin_lgf_m, pass_id, headings, on_target, exclude, options: PatchOptions, max_distance_m: float
) -> PatchCandidates | None:
    """The planar tie patches within ``max_distance_m`` of the targets (``on_target``) with
    their members, none of the points ``exclude`` (the targets' and the cylinders'); None: none
    found."""
    cands = extract_candidates(p_lgf_m, origin_lgf_m, pass_id, headings, exclude, options)
    if len(cands.names) == 0:
        return None
    cands = _near_targets(cands, p_lgf_m[on_target], max_distance_m)
    if len(cands.names) == 0:
        return None
    return gather_members(cands, p_lgf_m, pass_id, exclude, options)


def tie_patches_from_points(
    obs, planes, res, site, mount, trajectory, points, poses, idx
) -> TiePatches | None:
    """What the pipeline calls: :func:`add_tie_patches` on every point of the bundle
    (``points``, georeferenced with the first solution ``res``), the targets' points (``idx``)
    excluded, with the ``site``'s sigmas."""
    est = mount.with_boresight(res.boresight_rad)
    p, origin = georeference_passes(points, trajectory, est, poses)
    # the heading of every pass relative to the wall, as the targets' (a pass may see the scene
    # and no target)
    yaw = poses.rpy_rad[:, 2] if poses is not None else trajectory.interpolate(points.t_gps_s).rpy_rad[:, 2]
    headings = pass_headings(yaw, points.pass_id, site.wall_azimuth_rad)
    on_target = np.zeros(len(points), bool)
    on_target[idx] = True
    sigmas = {
        "sigma_range_per_m": site.sigma_range_per_m,
        "beam_divergence_rad": site.beam_divergence_rad,
        "sigma_range_m": site.sigma_range_m,
        "sigma_scan_angle_rad": site.sigma_scan_angle_rad,
        "sigma_position_m": site.sigma_position_m,
        "sigma_attitude_rad": site.sigma_attitude_rad,
    }
    return add_tie_patches(
        obs,
        planes,
        res.cov_realistic,
        est,
        p,
        origin,
        points.t_gps_s,
        points.range_m,
        points.scan_angle_rad,
        points.pass_id,
        on_target,
        trajectory,
        sigmas,
        poses,
        pass_heading_rad=headings,
    )


#: the kinds of feature :func:`crlb_by_features` adds one at a time, in this order
FEATURE_KINDS = ("targets", "planar patches", "cylinders")


def crlb_by_features(
    obs: Observations, state: State, mount: Mount, options: AdjustOptions
) -> dict[str, list[float]]:
    """The Cramér–Rao σ (deg) of roll, pitch and yaw at the solution ``state`` with the first
    kind of feature present (:data:`FEATURE_KINDS`: the targets, or without targets the planar
    tie patches), then with each further kind added (``"+ cylinders"``): what each kind adds,
    against the limit (the GLS information, equal to the dense oracle's; flat features: the
    roughness variances are left out)."""
    r_nom = frames.rotation_zyx(*mount.nominal_rad)
    is_tie = np.isin(np.arange(len(obs.plane_names)), obs.patch_planes)
    cylinder = state.is_cylinder
    kinds = (~is_tie & ~cylinder, is_tie & ~cylinder, cylinder)
    out: dict[str, list[float]] = {}
    keep = np.zeros_like(is_tie)
    for kind, members in zip(FEATURE_KINDS, kinds, strict=True):
        if not members.any():
            continue
        keep = keep | members
        sub_obs, sub_state = _features_subset(obs, state, keep)
        _, cov, _ = gls_information(sub_obs, sub_state, r_nom, options.estimate, options.error_model)
        out[f"+ {kind}" if out else kind] = [float(x) for x in np.degrees(np.sqrt(np.diag(cov)[:3]))]
    return out


def _features_subset(obs: Observations, state: State, keep: np.ndarray) -> tuple[Observations, State]:
    """The observations of the features ``keep`` (m,) bool and the state of those features."""
    new_index = np.cumsum(keep) - 1
    sub = obs.select(keep[obs.plane_index])
    sub.plane_index = new_index[sub.plane_index]
    sub.plane_names = [n for n, k in zip(obs.plane_names, keep, strict=True) if k]
    sub.patch_planes = tuple(int(new_index[j]) for j in obs.patch_planes if keep[j])
    st = state.copy()
    st.normals, st.d_m, st.centers_m = st.normals[keep], st.d_m[keep], st.centers_m[keep]
    st.cylinders = None if st.cylinders is None or not st.cylinders[keep].any() else st.cylinders[keep]
    return sub, st


#: the level of :func:`patches_agree`'s test: one false refusal in this many good runs
PATCH_TEST_ALPHA = 0.01


def patches_agree(targets_only, with_patches, alpha: float = PATCH_TEST_ALPHA) -> dict:
    """Whether adding the tie patches moved the boresight by more than the data allow.

    Both estimates are efficient under the model and the targets-only one uses a subset of the
    data, so their difference has covariance ``Σ_targets − Σ_patches`` (a Hausman test): a
    χ² (3 degrees of freedom) beyond the ``1 − alpha`` quantile says the patches carry a bias
    the model does not explain (a surface that is not planar at the scale of the patches,
    something moving) — patches may not buy precision with bias."""
    d = with_patches.boresight_rad - targets_only.boresight_rad
    V = targets_only.cov_realistic - with_patches.cov_realistic
    w, U = np.linalg.eigh(0.5 * (V + V.T))
    keep = w > 1e-12 * max(float(w.max()), 1e-300)
    chi2 = float(np.sum((U[:, keep].T @ d) ** 2 / w[keep]))
    dof = int(np.count_nonzero(keep))
    p = float(stats.chi2.sf(chi2, dof)) if dof else 1.0
    return {"chi2": chi2, "dof": dof, "p_value": p, "alpha": alpha, "agree": p >= alpha}


def targets_without_exposed_groups(obs, mount, planes, adjust_opts, targets_only, with_ties, check):
    """Disagreement resolved by evidence: target groups the adjustment with the tie patches
    removed as gross errors (the patches' evidence exposed them) but the targets alone kept are
    taken out of the targets' solution too, and the two are compared again. Returns the
    (targets-only result, check) to use: the new ones when any group was taken out."""
    kept = {(g["plane"], g["pass_id"]) for g in targets_only.removed_groups if g["removed"]}
    exposed = [
        (g["plane"], g["pass_id"])
        for g in with_ties.removed_groups
        if g["removed"] and (g["plane"], g["pass_id"]) not in kept and g["plane"] in obs.plane_names
    ]
    if not exposed:
        return targets_only, check
    keep = np.ones(len(obs), bool)
    for plane, pass_id in exposed:
        keep &= ~(
            (obs.plane_index == obs.plane_names.index(plane))
            & (obs.pass_index == obs.pass_ids.index(pass_id))
        )
    again = adjust(obs.select(keep), mount, planes, replace(adjust_opts, jackknife=False))
    again = replace(
        again,
        removed_groups=[g for g in with_ties.removed_groups if (g["plane"], g["pass_id"]) in exposed]
        + again.removed_groups,
    )
    return again, patches_agree(again, with_ties)


@dataclass(frozen=True, kw_only=True)
class TieSearch:
    """Where a calibration looks for tie patches: every point of the survey, not only the
    targets'."""

    site: Site
    mount: Mount  # the a-priori mount
    trajectory: Trajectory
    points: ScanPoints
    poses: Poses | None
    target_rows: np.ndarray  # the extracted targets' point indices
    point_rows: np.ndarray | None  # per point its row in the source file (None: its index)


@dataclass(frozen=True, kw_only=True)
class TiedSolution:
    """The solution to use after trying the tie patches, and what the try found."""

    obs: Observations
    planes: list[tuple[np.ndarray, float]]
    result: AdjustmentResult
    check: dict | None = None  # :func:`patches_agree` (None: no patch found)
    ties: TiePatches | None = None  # the patches, when accepted
    targets_only: AdjustmentResult | None = None  # the targets' solution, when they were accepted


def with_tie_patches(
    search: TieSearch,
    obs: Observations,
    planes,
    res: AdjustmentResult,
    adjust_opts: AdjustOptions,
    warnings: list[str],
    notes: list[str],
) -> TiedSolution:
    """The targets' solution ``res`` with the scene's tie patches added, kept when they agree
    with the targets. When they do not, the result is the targets alone with its σ widened to
    cover the other solution (a warning; the verdict says so)."""
    mount = search.mount
    ties = tie_patches_from_points(
        obs,
        planes,
        res,
        search.site,
        mount,
        search.trajectory,
        search.points,
        search.poses,
        search.target_rows,
    )
    if ties is None:
        notes.append(
            "tie patches: no planar patch or cylinder of the scene seen from two headings; targets only"
        )
        return TiedSolution(obs=obs, planes=planes, result=res)
    if search.point_rows is not None:  # outlier ids name rows of the file
        n_t = len(obs)
        ties.observations.point_ids[n_t:] = np.asarray(search.point_rows)[ties.observations.point_ids[n_t:]]
    with_ties = adjust(ties.observations, mount.with_boresight(res.boresight_rad), ties.planes, adjust_opts)
    check = patches_agree(res, with_ties)
    if not check["agree"]:  # a target group the patches exposed: judge the targets without it
        res, check = targets_without_exposed_groups(obs, mount, planes, adjust_opts, res, with_ties, check)
    if check["agree"]:
        return TiedSolution(
            obs=ties.observations,
            planes=ties.planes,
            result=with_ties,
            check=check,
            ties=ties,
            targets_only=res,
        )
    d = with_ties.boresight_rad - res.boresight_rad
    warnings.append(
        f"tie patches disagree with the targets (χ² = {check['chi2']:.1f} on 3 degrees of "
        f"freedom, p = {check['p_value']:.2g}): the result uses the targets alone, its σ "
        f"widened by the difference (roll/pitch/yaw "
        f"{', '.join(f'{x:+.3f}' for x in np.degrees(d))}°)"
    )
    widened = replace(res, cov_realistic=res.cov_realistic + np.diag(d**2))
    return TiedSolution(obs=obs, planes=planes, result=widened, check=check)
