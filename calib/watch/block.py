"""One block of the mount watch: the boresight correction that best reconciles the tie patches
seen by a few consecutive survey lines of different headings.

A mount change does not move a surface seen from one heading alone (the surface's own plane
absorbs it); it moves the surface *differently* from opposite headings — a roll change tilts a
wall one way from a line sailed north and the other way from the line sailed back. So a block is
two or more consecutive lines whose headings differ (:func:`block_ready`); its points,
georeferenced with the **calibrated** mount, are cut into tie patches
(:func:`calib.extraction.patches.extract_candidates`: planar cells seen by lines of different
headings) and vertical cylinders (piles, posts: :func:`calib.boresight.scene_ties.tie_candidates`),
the most informative patches and every pile up to a budget of their own are chosen
(:func:`calib.boresight.scene_ties.choose`) and the
boresight alone is adjusted against them with the GLS estimator
(:func:`calib.boresight.adjust.adjust`, ``estimator="gls"``): the POS errors are Gauss–Markov
processes estimated jointly, so a drift of the INS between two lines is not read as a mount
change; every patch gets its own roughness variance, so a wavy wall widens its own σ instead of
bending the estimate.

**Moving things.** A moored hull rising in the swell is planar within a line and somewhere else
on the next one. After each solution the mean residual of every (patch, line) is compared with
the others (robustly: over 1.4826 × their median absolute deviation); a patch with a line beyond
:data:`~calib.watch.patchtests.MOVED_Z` is dropped and the block solved again (at most :data:`MOVED_ROUNDS` times).
A mount change does not survive this test as a "moving" patch: the residuals are taken *after*
the fit, which already contains the change.

**What comes out** (:class:`BlockEstimate`): the correction ``delta_rad`` (estimated boresight
minus the calibrated one, canonical roll, pitch, yaw) and its covariance, scaled up by the a
posteriori variance factor when that exceeds 1 (a misspecified model then widens the σ rather
than raising alarms); a block that observes nothing (no patch, one heading, a singular system)
has ``status`` saying why and no estimate — it carries no evidence either way.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from calib.boresight.adjust import AdjustmentResult, adjust
from calib.boresight.errormodel import ErrorModel
from calib.boresight.observability import ObservabilityError, SingularError
from calib.boresight.observations import AdjustmentError, AdjustOptions, Observations, build_observations
from calib.boresight.scene_ties import (
    MAX_CYLINDERS,
    TieCandidates,
    boresight_information,
    choose,
    tie_candidates,
)
from calib.core import frames
from calib.core.georef import Mount
from calib.core.sampling import random_subset
from calib.core.trajectory import Trajectory
from calib.extraction.cylinders import CylinderOptions
from calib.extraction.patches import PatchError, PatchOptions
from calib.extraction.points import georeference_passes, line_headings
from calib.io.bundle import ScanPoints
from calib.watch.patchtests import (
    HOLD_SIGMA_RAD,
    GroupTest,
    curved_patches,
    group_test,
    moved_planes,
    patch_groups,
    pinned_correction,
    sigma_at_calibrated,
    unresolved,
)

MOVED_ROUNDS = 2
#: features dropped as not determined by their own points before the block gives up
MAX_UNDETERMINED = 10
#: the selection's starting information: a (1°)⁻² prior per angle (a ranking device only)
SELECTION_PRIOR_RAD = np.radians(1.0)


@dataclass(frozen=True)
class WatchOptions:
    """How a block is cut into tie patches and solved."""

    patch: PatchOptions = PatchOptions(size_m=1.5, max_points_per_patch=300)
    #: a patch is used when every line sees it planar: the RMS of that line's points about their
    #: own plane within this multiple of the scanner's range σ. A surface curved by more — a
    #: hull, a pile, a fender — is sampled differently from each line and bends the angle only
    #: it observes (production lines: pitch z RMS 1.4–1.6 with the patches' 2 cm, all lines
    #: together, as the only planarity test)
    planar_noise_factor: float = 3.5
    max_patches: int = 60
    #: tie cylinders (piles) beside the patches: a budget of their own and no least gain, as in a
    #: calibration (:func:`calib.boresight.scene_ties.choose`): the white weights of the
    #: selection let a wall's patches look as if they fixed yaw, which only the piles do
    max_cylinders: int = MAX_CYLINDERS
    min_heading_spread_deg: float = 90.0  # a block needs two lines this far apart in heading
    max_lines_per_block: int = 3  # … among at most this many consecutive lines
    min_range_m: float = 2.0  # returns nearer are the vessel's own rails
    max_range_m: float = 60.0  # farther returns are sparse and their footprint is wide
    max_points: int = 3_000_000  # a block's points are thinned at random beyond this
    #: a pile leaning more than this (as georeferenced at the block's mount) is not a tie
    #: cylinder (calib.extraction.cylinders: the model is upright)
    max_lean_deg: float = CylinderOptions().max_lean_deg
    #: GLS knot spacing min(τ)/knots_per_tau (the trajectory's epochs when fewer). Between knots
    #: the POS error is the OU bridge, whose variance is added to each point as if white; but it
    #: is shared by every point of a patch seen within a fraction of a second, so a coarse grid
    #: (τ/20: 3 s at τ = 60 s, a 1.6 mm bridge σ) put a correlated error the model calls noise
    #: into every (patch, line) and gave yaw 7σ wrong on a tilted mount; at τ/200 it is ≤ 0.5 mm
    knots_per_tau: float = 200.0
    #: the prior of the correction: an angle the block barely sees stays near the calibrated
    #: value with about this σ (and so moves the test hardly at all)
    prior_sigma_rad: float = float(np.radians(0.5))
    #: an angle the block resolves no better than this is held at the calibrated value while
    #: the others are solved (and carries no evidence: the sequential test's same bound)
    max_sigma_rad: float = float(np.radians(0.1))
    #: the group test: the chosen patches are split along the scene into this many groups
    #: (fewer when there are less than :data:`MIN_PATCHES_PER_GROUP` patches per group)
    patch_groups: int = 6
    #: the groups' variance factor (χ²/df) beyond which the block is no verdict: its σ would
    #: be more than three times what the model says — the model does not describe its data
    max_group_factor: float = 9.0
    #: the link test's false-rejection rate under the model (:func:`group_test`)
    group_alpha: float = 1e-3
    #: a provisional estimate (a targetless round that is not the last: its features were cut at
    #: a mount still tenths of a degree off): a failed group test is recorded
    #: (:attr:`BlockEstimate.group_failed`) and the estimate kept, not a stop
    provisional: bool = False

    def __post_init__(self):
        if not 0 < self.min_range_m < self.max_range_m:
            raise ValueError(
                f"watch range window [{self.min_range_m}, {self.max_range_m}] m: expected 0 < min < max"
            )
        if (
            self.max_patches < 1
            or self.max_cylinders < 0
            or self.max_points < 1000
            or self.max_lines_per_block < 2
        ):
            raise ValueError(
                "watch: max_patches ≥ 1, max_cylinders ≥ 0, max_points ≥ 1000 and max_lines_per_block ≥ 2 expected"
            )


@dataclass(frozen=True)
class PatchUse:
    """A chosen patch and what it gave the block."""

    name: str
    center_lgf_m: tuple[float, ...]  # (3,)
    normal_lgf: tuple[float, ...]  # (3,)
    pass_ids: tuple[int, ...]
    n_points: int
    info_rad2: tuple[float, ...]  # (3,) its diagonal of the boresight information (white)


@dataclass(frozen=True)
class BlockEstimate:
    t_start_gps_s: float
    t_end_gps_s: float
    pass_ids: tuple[int, ...]
    headings_deg: tuple[float, ...]  # of the lines, relative to the wall direction
    status: str  # "ok", or why the block carries no estimate
    delta_rad: np.ndarray | None = None  # estimated − calibrated boresight (roll, pitch, yaw)
    cov_rad2: np.ndarray | None = None
    sigma0_squared: float = float("nan")
    n_points: int = 0  # points adjusted
    n_candidates: int = 0
    patches: tuple[PatchUse, ...] = ()
    moved_patches: tuple[str, ...] = ()  # dropped as moving between lines
    undetermined_features: tuple[str, ...] = ()  # dropped: their own parameters left free
    runtime_s: float = 0.0
    #: the group test (:func:`group_test`): χ² of the patch groups' estimates about the block's
    #: and its degrees of freedom (nan / 0: not run)
    group_chi2: float = float("nan")
    group_df: int = 0
    #: the link test (:func:`group_test`): the block's estimate against its groups' combination
    link_chi2: float = float("nan")
    link_df: int = 0
    #: why the group test failed, for a provisional block that kept its estimate; None otherwise
    group_failed: str | None = None
    #: the angles held at the calibrated value (not resolved to ``max_sigma_rad`` there)
    held: tuple[bool, ...] = (False, False, False)
    #: the adjustment behind the estimate, when asked for (``keep_result``; per-point arrays: the
    #: watch, which keeps its blocks, does not), not in :meth:`as_dict`
    result: AdjustmentResult | None = field(default=None, repr=False, compare=False)
    #: with ``result``: its observations and adjustment options
    observations: Observations | None = field(default=None, repr=False, compare=False)
    adjust_options: AdjustOptions | None = field(default=None, repr=False, compare=False)

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    @property
    def sigma_rad(self) -> np.ndarray:
        if self.cov_rad2 is None:
            return np.full(3, np.inf)
        return np.sqrt(np.clip(np.diag(self.cov_rad2), 0.0, None))

    def as_dict(self) -> dict:
        deg = lambda v: None if v is None else [float(x) for x in np.degrees(v)]  # noqa: E731
        return {
            "t_start_gps_s": self.t_start_gps_s,
            "t_end_gps_s": self.t_end_gps_s,
            "pass_ids": list(self.pass_ids),
            "headings_deg": list(self.headings_deg),
            "status": self.status,
            "delta_deg": deg(self.delta_rad),
            "sigma_deg": deg(self.sigma_rad) if self.ok else None,
            "correlation": None if self.cov_rad2 is None else _correlation(self.cov_rad2).tolist(),
            "sigma0_squared": None if not self.ok else float(self.sigma0_squared),
            "n_points": self.n_points,
            "n_candidates": self.n_candidates,
            "patches": [
                {
                    "name": p.name,
                    "center_lgf_m": list(p.center_lgf_m),
                    "normal_lgf": list(p.normal_lgf),
                    "pass_ids": list(p.pass_ids),
                    "n_points": p.n_points,
                    "info_deg2": [float(x) * (np.pi / 180) ** 2 for x in p.info_rad2],
                }
                for p in self.patches
            ],
            "moved_patches": list(self.moved_patches),
            "undetermined_features": list(self.undetermined_features),
            "group_chi2": None if not np.isfinite(self.group_chi2) else float(self.group_chi2),
            "group_df": self.group_df,
            "link_chi2": None if not np.isfinite(self.link_chi2) else float(self.link_chi2),
            "link_df": self.link_df,
            "group_failed": self.group_failed,
            "held": list(self.held),
            "runtime_s": self.runtime_s,
        }


def _correlation(cov: np.ndarray) -> np.ndarray:
    s = np.sqrt(np.clip(np.diag(cov), 1e-300, None))
    return cov / np.outer(s, s)


def heading_spread_deg(headings_rad) -> float:
    """The largest difference between two headings (mod 360°, 0…180°)."""
    h = np.asarray(list(headings_rad), float)
    if h.size < 2:
        return 0.0
    d = np.abs(frames.wrap_pi(h[:, None] - h[None, :]))
    return float(np.degrees(d.max()))


def block_ready(headings_rad, options: WatchOptions = WatchOptions()) -> bool:
    """Whether lines of these headings (relative, radians) make a block."""
    return heading_spread_deg(headings_rad) >= options.min_heading_spread_deg


def site_sigmas(site) -> dict:
    """The observation sigmas of a :class:`calib.io.site.Site` as :func:`build_observations`
    takes them."""
    return {
        "sigma_range_m": site.sigma_range_m,
        "sigma_range_per_m": site.sigma_range_per_m,
        "beam_divergence_rad": site.beam_divergence_rad,
        "sigma_scan_angle_rad": site.sigma_scan_angle_rad,
        "sigma_position_m": site.sigma_position_m,
        "sigma_attitude_rad": site.sigma_attitude_rad,
    }


def site_error_model(site) -> ErrorModel:
    """The Gauss–Markov POS error model of a site (its correlation times, else the default)."""
    from calib.boresight.pipeline import CalibrationOptions, error_model

    return error_model(CalibrationOptions(), site)[0]


def _thin(points: ScanPoints, options: WatchOptions) -> ScanPoints:
    keep = (points.range_m >= options.min_range_m) & (points.range_m <= options.max_range_m)
    idx = np.flatnonzero(keep)
    idx = random_subset(idx, options.max_points, seed=0)
    return points.select(idx) if idx.size < len(points) else points


def _block_span(points: ScanPoints) -> dict[str, Any]:
    """What every block estimate states, estimate or not: its time span and its lines."""
    return {
        "t_start_gps_s": float(points.t_gps_s.min()) if len(points) else float("nan"),
        "t_end_gps_s": float(points.t_gps_s.max()) if len(points) else float("nan"),
        "pass_ids": tuple(int(p) for p in np.unique(points.pass_id)),
    }


@dataclass(frozen=True)
class _Stop:
    """A block that carries no estimate: why (its ``status``) and what it found that far."""

    status: str
    extra: dict[str, Any] = field(default_factory=dict)


def _tie_candidates(
    pts: ScanPoints,
    trajectory: Trajectory,
    mount: Mount,
    headings,
    sigma_range_m: float,
    options: WatchOptions,
) -> TieCandidates | _Stop:
    """The tie patches and cylinders seen from two headings, the points of the patches that
    some line sees curved unlabelled (label −1)."""
    p_lgf, origin = georeference_passes(pts, trajectory, mount, None)
    opt = replace(options.patch, min_heading_spread_deg=options.min_heading_spread_deg)
    cyl_opt = CylinderOptions(
        min_heading_spread_deg=options.min_heading_spread_deg, max_lean_deg=options.max_lean_deg
    )
    none = np.zeros(len(pts), bool)
    try:
        found = tie_candidates(p_lgf, origin, pts.pass_id, headings, none, opt, np.inf, cyl_opt)
    except PatchError as e:
        return _Stop(f"no tie patch ({e})")
    if found is None:
        return _Stop("no tie patch seen from two headings")
    on_patch = np.where(found.labels < found.n_patches, found.labels, -1)
    curved = curved_patches(on_patch, p_lgf, pts.pass_id, options.planar_noise_factor * sigma_range_m)
    found.labels[np.isin(found.labels, curved)] = -1
    return found


def _patch_observations(
    pts: ScanPoints, idx: np.ndarray, trajectory: Trajectory, mount: Mount, cands, headings, sigmas: dict
) -> Observations:
    """The observations of the labelled points ``idx``, built without the trajectory: the GLS
    then puts its knots on a uniform grid of min(τ)/knots_per_tau rather than at every INS
    epoch (100 Hz): the same model to the bridge's approximation, a hundred times fewer
    unknowns."""
    return build_observations(
        trajectory,
        pts.t_gps_s[idx],
        pts.range_m[idx],
        pts.scan_angle_rad[idx],
        cands.labels[idx],
        pts.pass_id[idx],
        list(cands.names),
        point_ids=idx,
        time_offset_s=mount.time_offset_s,
        pass_headings_rad=headings,
        carry_trajectory=False,
        **sigmas,
    )


def _adjust_options(mount: Mount, model: ErrorModel, options: WatchOptions) -> AdjustOptions:
    """The block's GLS: the boresight alone, near the calibrated one (the correction's prior),
    every patch with its own roughness."""
    return AdjustOptions(
        estimate=(),
        error_model=model,
        jackknife=False,
        boresight_prior_rad=np.stack([mount.boresight_rad, np.full(3, options.prior_sigma_rad)]),
        estimator="gls",
        roughness="all",
        knots_per_tau=options.knots_per_tau,
    )


@dataclass(frozen=True)
class _Fit:
    """The block solved on its chosen patches, those that moved between lines dropped."""

    order: list[int]  # the patches solved, indices into the candidates
    sub: Observations  # their observations, the planes renumbered in ``order``
    res: AdjustmentResult
    moved: tuple[str, ...]  # the patches dropped as moving
    undetermined: tuple[str, ...] = ()  # the features dropped as not determined by their points


_NOT_SOLVED = (ObservabilityError, AdjustmentError, np.linalg.LinAlgError)


def _fit_without_moved(
    obs: Observations, mount: Mount, planes, chosen: list[int], names, adj
) -> _Fit | _Stop:
    """Solve on the chosen patches; drop those with a line whose mean residual stands out
    (:func:`~calib.watch.patchtests.moved_planes`) and solve again, at most
    :data:`MOVED_ROUNDS` times."""
    moved: list[str] = []
    rounds = 0
    while True:
        order = sorted(chosen)
        sub = obs.of_planes(order)
        try:
            res = adjust(sub, mount, [planes[j] for j in order], adj)
        except _NOT_SOLVED as e:
            return _not_solved(e, sub.plane_names)
        bad = moved_planes(sub, res)
        if not bad.size or rounds == MOVED_ROUNDS:
            break
        rounds += 1
        moved += [sub.plane_names[j] for j in bad]
        chosen = [j for j in chosen if names[j] not in moved]
        if not chosen:
            return _Stop("every tie patch moved", {"moved_patches": tuple(moved)})
    return _Fit(order=order, sub=sub, res=res, moved=tuple(moved))


def _not_solved(e: Exception, features: list[str]) -> _Stop:
    """A block the adjustment could not solve; a singular system names the feature it leaves
    free (``free_feature``), for the caller to drop."""
    extra = {"free_feature": _free_feature(e, features)} if isinstance(e, SingularError) else {}
    return _Stop(f"not observable ({e})", extra)


def _free_feature(e: SingularError, features: list[str]) -> str | None:
    """The feature a singular system leaves free: the first of its null direction's unknowns
    that is a feature's own (``NAME.d``, ``NAME.normal_t1``, …)."""
    for unknown in e.unknowns:
        name = unknown.rsplit(".", 1)[0]
        if "." in unknown and name in features:
            return name
    return None


@dataclass(frozen=True)
class _Judged:
    """The block's solution with the unresolved angles held, and its group test."""

    res: AdjustmentResult
    held: np.ndarray  # (3,) bool: the angles held at the calibrated value
    sigma_cal_rad: np.ndarray  # (3,) each angle's σ at the calibrated mount
    test: GroupTest


def _judged(
    fit: _Fit, mount: Mount, centers_m: np.ndarray, planes, adj, options: WatchOptions
) -> _Judged | _Stop:
    """Hold the angles not resolved at the calibrated mount, solve again and run the group
    test on the patches split along the scene (``centers_m``: the solved patches')."""
    plane_init = [planes[j] for j in fit.order]
    try:
        sigma_cal_rad = sigma_at_calibrated(fit.sub, mount, plane_init, adj)
    except _NOT_SOLVED as e:  # e.g. a feature determined at the solution but free at the calibrated mount
        return _not_solved(e, fit.sub.plane_names)
    held = sigma_cal_rad > options.max_sigma_rad
    if held.all():
        return _Stop(f"no verdict: {unresolved(sigma_cal_rad, options.max_sigma_rad)}")
    groups = patch_groups(centers_m, options.patch_groups)
    if groups is None:
        return _Stop(f"no verdict: {len(fit.order)} tie patches, too few for the group test")
    pinned = replace(
        adj,
        boresight_prior_rad=np.stack(
            [mount.boresight_rad, np.where(held, HOLD_SIGMA_RAD, options.prior_sigma_rad)]
        ),
    )
    try:
        res = adjust(fit.sub, mount, plane_init, pinned) if held.any() else fit.res
    except _NOT_SOLVED as e:
        return _not_solved(e, fit.sub.plane_names)
    test = group_test(
        fit.sub, mount, plane_init, pinned, groups, ~held, res, options.group_alpha, options.max_group_factor
    )
    if test.failed is not None and not options.provisional:
        return _Stop(
            f"no verdict: {test.failed}",
            {
                "group_chi2": test.chi2,
                "group_df": test.df,
                "link_chi2": test.link_chi2,
                "link_df": test.link_df,
            },
        )
    return _Judged(res=res, held=held, sigma_cal_rad=sigma_cal_rad, test=test)


def _fit_and_judge(obs, mount, planes, chosen, cands, adj, options) -> tuple[_Fit, _Judged] | _Stop:
    """:func:`_fit_without_moved` and :func:`_judged`. A feature whose own parameters the data
    leave free (a pile seen on too narrow an arc: the normal equations singular along it, at the
    solution or at the calibrated mount) is dropped and the block solved again, at most
    :data:`MAX_UNDETERMINED` of them."""
    dropped: list[str] = []
    while True:
        fit = _fit_without_moved(obs, mount, planes, chosen, cands.names, adj)
        if isinstance(fit, _Stop):
            stop = fit
        else:
            fit = replace(fit, undetermined=tuple(dropped))
            judged = _judged(fit, mount, cands.centers_m[fit.order], planes, adj, options)
            if not isinstance(judged, _Stop):
                return fit, judged
            stop = _Stop(judged.status, {"moved_patches": fit.moved, **judged.extra})
        free = stop.extra.pop("free_feature", None)
        if free is None or len(dropped) >= MAX_UNDETERMINED or len(chosen) <= 1:
            return stop
        dropped.append(free)
        chosen = [j for j in chosen if cands.names[j] != free]


def _patch_uses(fit: _Fit, res: AdjustmentResult, cands, info) -> tuple[PatchUse, ...]:
    """What each solved patch gave the block."""
    uses = []
    sub = fit.sub
    for k, j in enumerate(fit.order):
        in_p = sub.plane_index == k
        uses.append(
            PatchUse(
                cands.names[j],
                tuple(float(x) for x in cands.centers_m[j]),
                tuple(float(x) for x in res.state.normals[k]),
                tuple(int(sub.pass_ids[i]) for i in np.unique(sub.pass_index[in_p])),
                int(np.count_nonzero(in_p)),
                tuple(float(x) for x in np.diag(info[j])),
            )
        )
    return tuple(uses)


def estimate_block(
    points: ScanPoints,
    trajectory: Trajectory,
    mount: Mount,
    sigmas: dict,
    model: ErrorModel,
    wall_azimuth_rad: float,
    options: WatchOptions = WatchOptions(),
    keep_result: bool = False,
) -> BlockEstimate:
    """The boresight correction of one block (module docstring). ``points``: the block's lines
    (``pass_id`` = line id); ``trajectory``: the POS solution with its σ; ``mount``: the
    calibrated mount; ``sigmas``: :func:`site_sigmas`; ``model``: the POS error model (its
    correlation times); ``keep_result``: the estimate keeps the adjustment behind it."""
    clock = time.perf_counter()
    pts = _thin(points, options)
    base = _block_span(points)
    if len(pts) == 0:
        return BlockEstimate(**base, headings_deg=(), status="no returns in the range window")
    headings = line_headings(pts, trajectory, wall_azimuth_rad, mount.time_offset_s)
    base["headings_deg"] = tuple(float(np.degrees(headings[int(p)]) % 360.0) for p in pts.pass_ids())
    if not block_ready(headings.values(), options):
        return BlockEstimate(**base, status="lines of one heading")
    cands = _tie_candidates(pts, trajectory, mount, headings, float(sigmas["sigma_range_m"]), options)
    if isinstance(cands, _Stop):
        return BlockEstimate(**base, status=cands.status, **cands.extra)
    idx = np.flatnonzero(cands.labels >= 0)
    n_candidates = len(cands.names)
    if idx.size == 0:
        return BlockEstimate(**base, status="no tie patch planar from every line", n_candidates=n_candidates)
    obs = _patch_observations(pts, idx, trajectory, mount, cands, headings, sigmas)
    planes = cands.features
    info = boresight_information(obs, mount, planes)
    counts = np.bincount(obs.plane_index, minlength=len(cands.names))
    prior = np.eye(3) / SELECTION_PRIOR_RAD**2
    chosen, _ = choose(info, prior, options.max_patches, cands.is_cylinder, options.max_cylinders, counts)
    if not chosen:
        return BlockEstimate(**base, status="no tie patch adds information", n_candidates=n_candidates)
    adj = _adjust_options(mount, model, options)
    solved = _fit_and_judge(obs, mount, planes, chosen, cands, adj, options)
    if isinstance(solved, _Stop):
        return BlockEstimate(**base, status=solved.status, n_candidates=n_candidates, **solved.extra)
    fit, judged = solved
    delta, cov = pinned_correction(judged.res, mount, judged.held, judged.sigma_cal_rad, judged.test.factor)
    return BlockEstimate(
        **base,
        status="ok",
        delta_rad=delta,
        cov_rad2=cov,
        sigma0_squared=float(judged.res.sigma0_squared),
        n_points=judged.res.n_points,
        n_candidates=n_candidates,
        patches=_patch_uses(fit, judged.res, cands, info),
        moved_patches=fit.moved,
        undetermined_features=fit.undetermined,
        runtime_s=time.perf_counter() - clock,
        group_chi2=judged.test.chi2,
        group_df=judged.test.df,
        link_chi2=judged.test.link_chi2,
        link_df=judged.test.link_df,
        group_failed=judged.test.failed,
        held=tuple(bool(h) for h in judged.held),
        result=judged.res if keep_result else None,
        observations=fit.sub if keep_result else None,
        adjust_options=adj if keep_result else None,
    )
