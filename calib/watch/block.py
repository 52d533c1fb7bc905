"""One block of the mount watch: the boresight correction that best reconciles the tie patches
seen by a few consecutive survey lines of different headings.

A mount change does not move a surface seen from one heading alone (the surface's own plane
absorbs it); it moves the surface *differently* from opposite headings — a roll change tilts a
wall one way from a line sailed north and the other way from the line sailed back. So a block is
two or more consecutive lines whose headings differ (:func:`block_ready`); its points,
georeferenced with the **calibrated** mount, are cut into tie patches
(:func:`calib.extraction.patches.extract_candidates`: planar cells seen by lines of different
headings), the most informative are chosen (:func:`calib.boresight.scene_ties.choose`) and the
boresight alone is adjusted against them with the GLS estimator
(:func:`calib.boresight.adjust.adjust`, ``estimator="gls"``): the POS errors are Gauss–Markov
processes estimated jointly, so a drift of the INS between two lines is not read as a mount
change; every patch gets its own roughness variance, so a wavy wall widens its own σ instead of
bending the estimate.

**Moving things.** A moored hull rising in the swell is planar within a line and somewhere else
on the next one. After each solution the mean residual of every (patch, line) is compared with
the others (robustly: over 1.4826 × their median absolute deviation); a patch with a line beyond
:data:`MOVED_Z` is dropped and the block solved again (at most :data:`MOVED_ROUNDS` times).
A mount change does not survive this test as a "moving" patch: the residuals are taken *after*
the fit, which already contains the change.

**What comes out** (:class:`BlockEstimate`): the correction ``delta_rad`` (estimated boresight
minus the calibrated one, canonical roll, pitch, yaw) and its covariance, scaled up by the a
posteriori variance factor when that exceeds 1 (a misspecified model then widens the σ rather
than raising alarms); a block that observes nothing (no patch, one heading, a singular system)
has ``status`` saying why and no estimate — it carries no evidence either way.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from calib.boresight.adjust import adjust
from calib.boresight.errormodel import ErrorModel
from calib.boresight.observability import ObservabilityError
from calib.boresight.observations import AdjustmentError, AdjustOptions, build_observations
from calib.boresight.scene_ties import boresight_information, choose
from calib.core import frames
from calib.core.georef import Mount
from calib.core.trajectory import Trajectory
from calib.extraction.patches import PatchError, PatchOptions, extract_candidates, gather_members
from calib.extraction.points import georeference_passes, pass_headings
from calib.io.bundle import ScanPoints

MOVED_Z = 6.0  # robust z of a (patch, line) mean residual beyond which the patch moved
MOVED_ROUNDS = 2
MIN_MOVED_SCALE_M = 0.002  # the robust scale's floor (noise-free data)
HOLD_SIGMA_RAD = 1e-7  # the prior σ that holds an unobserved angle at the calibrated value
#: the selection's starting information: a (1°)⁻² prior per angle (a ranking device only)
SELECTION_PRIOR_RAD = np.radians(1.0)
MIN_PATCHES_PER_GROUP = 2  # a group of the group test holds at least this many patches


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
    min_heading_spread_deg: float = 90.0  # a block needs two lines this far apart in heading
    max_lines_per_block: int = 3  # … among at most this many consecutive lines
    min_range_m: float = 2.0  # returns nearer are the vessel's own rails
    max_range_m: float = 60.0  # farther returns are sparse and their footprint is wide
    max_points: int = 3_000_000  # a block's points are thinned evenly beyond this
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

    def __post_init__(self):
        if not 0 < self.min_range_m < self.max_range_m:
            raise ValueError(
                f"watch range window [{self.min_range_m}, {self.max_range_m}] m: expected 0 < min < max"
            )
        if self.max_patches < 1 or self.max_points < 1000 or self.max_lines_per_block < 2:
            raise ValueError("watch: max_patches ≥ 1, max_points ≥ 1000 and max_lines_per_block ≥ 2 expected")


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
    runtime_s: float = 0.0
    #: the group test (:func:`group_test`): χ² of the patch groups' estimates about the block's
    #: and its degrees of freedom (nan / 0: not run)
    group_chi2: float = float("nan")
    group_df: int = 0
    #: the link test (:func:`group_test`): the block's estimate against its groups' combination
    link_chi2: float = float("nan")
    link_df: int = 0
    #: the angles held at the calibrated value (not resolved to ``max_sigma_rad`` there)
    held: tuple[bool, ...] = (False, False, False)

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
            "group_chi2": None if not np.isfinite(self.group_chi2) else float(self.group_chi2),
            "group_df": self.group_df,
            "link_chi2": None if not np.isfinite(self.link_chi2) else float(self.link_chi2),
            "link_df": self.link_df,
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
    if idx.size > options.max_points:  # evenly in time: every k-th return
        idx = idx[:: int(np.ceil(idx.size / options.max_points))]
    return points.select(idx) if idx.size < len(points) else points


def estimate_block(
    points: ScanPoints,
    trajectory: Trajectory,
    mount: Mount,
    sigmas: dict,
    model: ErrorModel,
    wall_azimuth_rad: float,
    options: WatchOptions = WatchOptions(),
) -> BlockEstimate:
    """The boresight correction of one block (module docstring). ``points``: the block's lines
    (``pass_id`` = line id); ``trajectory``: the POS solution with its σ; ``mount``: the
    calibrated mount; ``sigmas``: :func:`site_sigmas`; ``model``: the POS error model (its
    correlation times)."""
    import time

    clock = time.perf_counter()
    pts = _thin(points, options)
    pids = tuple(int(p) for p in pts.pass_ids()) if len(pts) else ()
    base: dict[str, Any] = {
        "t_start_gps_s": float(points.t_gps_s.min()) if len(points) else float("nan"),
        "t_end_gps_s": float(points.t_gps_s.max()) if len(points) else float("nan"),
        "pass_ids": tuple(int(p) for p in np.unique(points.pass_id)),
    }
    if len(pts) == 0:
        return BlockEstimate(**base, headings_deg=(), status="no returns in the range window")
    yaw = trajectory.interpolate(pts.t_gps_s + mount.time_offset_s).rpy_rad[:, 2]
    headings = pass_headings(yaw, pts.pass_id, wall_azimuth_rad)
    hdeg = tuple(float(np.degrees(headings[p]) % 360.0) for p in pids)
    base["headings_deg"] = hdeg
    if not block_ready(headings.values(), options):
        return BlockEstimate(**base, status="lines of one heading")
    p_lgf, origin = georeference_passes(pts, trajectory, mount, None)
    opt = replace(options.patch, min_heading_spread_deg=options.min_heading_spread_deg)
    try:
        cands = extract_candidates(p_lgf, origin, pts.pass_id, headings, np.zeros(len(pts), bool), opt)
    except PatchError as e:
        return BlockEstimate(**base, status=f"no tie patch ({e})")
    if len(cands.names) == 0:
        return BlockEstimate(**base, status="no tie patch seen from two headings")
    cands = gather_members(cands, p_lgf, pts.pass_id, np.zeros(len(pts), bool), opt)
    max_rms_m = options.planar_noise_factor * float(sigmas["sigma_range_m"])
    curved = _curved(cands.labels, p_lgf, pts.pass_id, max_rms_m)
    cands.labels[np.isin(cands.labels, curved)] = -1
    idx = np.flatnonzero(cands.labels >= 0)
    if idx.size == 0:
        return BlockEstimate(
            **base, status="no tie patch planar from every line", n_candidates=len(cands.names)
        )
    obs = build_observations(
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
        **sigmas,
    )
    # knots on a uniform grid of min(τ)/knots_per_tau rather than at every INS epoch (100 Hz):
    # the same model to the bridge's approximation, a hundred times fewer unknowns
    obs.trajectory = None
    planes = [(n, d) for n, d in zip(cands.normals, cands.d_m)]
    info = boresight_information(obs, mount, planes)
    chosen, _ = choose(info, np.eye(3) / SELECTION_PRIOR_RAD**2, options.max_patches)
    if not chosen:
        return BlockEstimate(**base, status="no tie patch adds information", n_candidates=len(cands.names))
    moved: list[str] = []
    adj = AdjustOptions(
        estimate=(),
        error_model=model,
        jackknife=False,
        boresight_prior_rad=np.stack([mount.boresight_rad, np.full(3, options.prior_sigma_rad)]),
        estimator="gls",
        roughness="all",
        knots_per_tau=options.knots_per_tau,
    )
    for _ in range(MOVED_ROUNDS + 1):
        order = sorted(chosen)
        sub = _planes_subset(obs, order, cands.names)
        try:
            res = adjust(sub, mount, [planes[j] for j in order], adj)
        except (ObservabilityError, AdjustmentError, np.linalg.LinAlgError) as e:
            return BlockEstimate(**base, status=f"not observable ({e})", n_candidates=len(cands.names))
        bad = _moved(sub, res)
        if not bad.size:
            break
        moved += [sub.plane_names[j] for j in bad]
        chosen = [j for j in chosen if cands.names[j] not in moved]
        if not chosen:
            return BlockEstimate(**base, status="every tie patch moved", moved_patches=tuple(moved))
    plane_init = [planes[j] for j in order]
    nope: dict[str, Any] = {"n_candidates": len(cands.names), "moved_patches": tuple(moved)}
    try:
        sigma_cal_rad = sigma_at_calibrated(sub, mount, plane_init, adj)
    except (ObservabilityError, AdjustmentError, np.linalg.LinAlgError) as e:
        return BlockEstimate(**base, status=f"not observable ({e})", **nope)
    held = sigma_cal_rad > options.max_sigma_rad
    if held.all():
        return BlockEstimate(**base, status=f"no verdict: {_unresolved(sigma_cal_rad, options)}", **nope)
    groups = patch_groups(cands.centers_m[order], options)
    if groups is None:
        return BlockEstimate(
            **base, status=f"no verdict: {len(order)} tie patches, too few for the group test", **nope
        )
    pinned = replace(
        adj,
        boresight_prior_rad=np.stack(
            [mount.boresight_rad, np.where(held, HOLD_SIGMA_RAD, options.prior_sigma_rad)]
        ),
    )
    try:
        res = adjust(sub, mount, plane_init, pinned) if held.any() else res
    except (ObservabilityError, AdjustmentError, np.linalg.LinAlgError) as e:
        return BlockEstimate(**base, status=f"not observable ({e})", **nope)
    test = group_test(sub, mount, plane_init, pinned, groups, ~held, res, options)
    if test.failed is not None:
        return BlockEstimate(
            **base,
            status=f"no verdict: {test.failed}",
            group_chi2=test.chi2,
            group_df=test.df,
            link_chi2=test.link_chi2,
            link_df=test.link_df,
            **nope,
        )
    delta, cov = _pinned(res, mount, held, sigma_cal_rad, test.factor)
    uses = []
    for k, j in enumerate(order):
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
    return BlockEstimate(
        **base,
        status="ok",
        delta_rad=delta,
        cov_rad2=cov,
        sigma0_squared=float(res.sigma0_squared),
        n_points=res.n_points,
        n_candidates=len(cands.names),
        patches=tuple(uses),
        moved_patches=tuple(moved),
        runtime_s=time.perf_counter() - clock,
        group_chi2=test.chi2,
        group_df=test.df,
        link_chi2=test.link_chi2,
        link_df=test.link_df,
        held=tuple(bool(h) for h in held),
    )


def _curved(labels: np.ndarray, p_lgf_m: np.ndarray, pass_id: np.ndarray, max_rms_m: float) -> np.ndarray:
    """The patches (label values) that some line sees curved: the RMS of that line's points
    about their own best plane beyond ``max_rms_m``. Each line apart, so that a mount change —
    which tilts one line's points against the other's — does not make a patch look curved."""
    out = []
    for j in np.unique(labels[labels >= 0]):
        in_j = labels == j
        for k in np.unique(pass_id[in_j]):
            q = p_lgf_m[in_j & (pass_id == k)]
            if q.shape[0] < 3:
                continue
            smallest = np.linalg.eigvalsh(np.cov((q - q.mean(axis=0)).T))[0]
            if np.sqrt(max(smallest, 0.0)) > max_rms_m:
                out.append(int(j))
                break
    return np.asarray(out, np.int64)


def _planes_subset(obs, order: list[int], names) -> Any:
    """The observations of the planes ``order`` (indices into ``names``), renumbered."""
    sub = obs.select(np.isin(obs.plane_index, order))
    sub.plane_index = np.searchsorted(order, sub.plane_index)
    sub.plane_names = [names[j] for j in order]
    sub.patch_planes = tuple(range(len(order)))
    return sub


def patch_groups(centers_m: np.ndarray, options: WatchOptions) -> list[np.ndarray] | None:
    """The chosen patches (their centres, LGF) split into contiguous groups along the scene's
    longest horizontal extent — neighbours share a stretch of wall, its waviness, the moment
    each line passed it — or None when there are too few for two groups."""
    n = centers_m.shape[0]
    k = min(options.patch_groups, n // MIN_PATCHES_PER_GROUP)
    if k < 2:
        return None
    xy = centers_m[:, :2] - centers_m[:, :2].mean(axis=0)
    axis = np.linalg.svd(xy, full_matrices=False)[2][0]
    return np.array_split(np.argsort(xy @ axis, kind="stable"), k)


@dataclass(frozen=True)
class GroupTest:
    """The block's patches split into groups along the scene, each solved alone (the free
    angles; the held ones pinned as in the block's solution)."""

    chi2: float  # dispersion: the groups' estimates about their information-weighted mean
    df: int
    limit: float  # dispersion χ² beyond which the block is no verdict
    #: the block's estimate against the groups' combination (a Hausman test): what the block
    #: knows beyond its groups comes only from the POS processes linking them across time
    link_chi2: float = 0.0
    link_df: int = 0
    link_limit: float = float("inf")

    @property
    def factor(self) -> float:
        """The variance factor of the groups' dispersion (≥ 1)."""
        return max(1.0, self.chi2 / self.df) if self.df else 1.0

    @property
    def failed(self) -> str | None:
        """Why the block is no verdict, or None."""
        if self.chi2 > self.limit:
            return (
                f"its tie patch groups disagree (χ² = {self.chi2:.0f} over {self.df} degrees of "
                f"freedom, limit {self.limit:.0f})"
            )
        if self.link_chi2 > self.link_limit:
            return (
                f"its estimate is not its patch groups' (χ² = {self.link_chi2:.1f} over "
                f"{self.link_df} degrees of freedom, limit {self.link_limit:.1f}): it rests on the "
                "POS error model across the lines, not on the patches"
            )
        return None


def group_test(
    sub,
    mount: Mount,
    planes,
    adj: AdjustOptions,
    groups,
    free: np.ndarray,
    full,
    options: WatchOptions,
) -> GroupTest:
    """Each group of patches solved alone (the prior of ``adj`` on the correction).

    **Dispersion**: ``χ² = Σ_g (δ_g − δ̄)ᵀ C_g⁻¹ (δ_g − δ̄)`` about their information-weighted
    mean ``δ̄``, on ``n_free·(G − 1)`` degrees of freedom: a wall that bends, a patch that is not
    one plane from both lines, a hull that moved — each shows as groups that disagree beyond
    their σ. Its χ²/df scales the block's covariance; beyond
    :attr:`WatchOptions.max_group_factor` the block is no verdict.

    **Link**: ``χ² = (δ − δ̄)ᵀ (C̄ − C)⁺ (δ − δ̄)`` of the block's estimate ``δ`` (``full``)
    against the groups' combination (its covariance ``C̄`` with the prior counted once): under
    the model, the block's estimate is the more precise and their difference has covariance
    ``C̄ − C``. What the block knows beyond its groups comes from the POS processes linking
    the groups across time; on an oblique line the wall-normal position drift and yaw both
    grow with the range, and a block that leaned on that link gave yaw 4σ wrong with a flat
    wall and no POS error at all (the beam footprint's noise alone). Beyond the χ² quantile
    :attr:`WatchOptions.group_alpha` the block is no verdict."""
    from scipy import stats

    prior_info = np.diag(1.0 / adj.boresight_prior_rad[1][free] ** 2)  # type: ignore[index]
    deltas, infos = [], []
    for g in groups:
        order = sorted(int(j) for j in g)
        part = _planes_subset(sub, order, sub.plane_names)
        try:
            r = adjust(part, mount, [planes[j] for j in order], adj)
        except (ObservabilityError, AdjustmentError, np.linalg.LinAlgError):
            continue
        deltas.append((r.boresight_rad - mount.boresight_rad)[free])
        cov = r.cov_realistic * max(1.0, float(r.sigma0_squared))
        infos.append(np.linalg.inv(cov[np.ix_(free, free)]))
    n_free = int(np.count_nonzero(free))
    df = n_free * (len(deltas) - 1)
    if df <= 0:
        return GroupTest(float("inf"), 0, 0.0)
    mean = np.linalg.solve(sum(infos), sum(w @ d for w, d in zip(infos, deltas)))
    chi2 = sum(float((d - mean) @ w @ (d - mean)) for w, d in zip(infos, deltas))
    # the combination: each group's information holds the prior once; count it once
    info_comb = sum(infos) - (len(deltas) - 1) * prior_info
    cov_comb = np.linalg.inv(info_comb)
    comb = cov_comb @ sum(w @ d for w, d in zip(infos, deltas))
    cov_full = (full.cov_realistic * max(1.0, float(full.sigma0_squared)))[np.ix_(free, free)]
    diff = (full.boresight_rad - mount.boresight_rad)[free] - comb
    link = float(diff @ np.linalg.solve(cov_comb + cov_full, diff))
    link_df = n_free
    link_limit = float(stats.chi2.isf(options.group_alpha, link_df))
    return GroupTest(chi2, df, options.max_group_factor * df, link, link_df, link_limit)


def sigma_at_calibrated(sub, mount: Mount, planes, adj: AdjustOptions) -> np.ndarray:
    """The σ of each angle (with the correction's prior, scaled by the variance factor when
    above 1) linearized at the **calibrated** boresight — the hypothesis the watch tests.

    Judged at the solution instead, an angle the block barely sees looked resolved: on a pair
    sailed back along one oblique track (montreal seed 3, lines 3–4 and 5–6) yaw moves every
    point the same way from both lines and is not seen at first order; the solution wandered
    to +3.8° and −3.4°, where the second-order terms are large, and its σ there (0.4°) was a
    tenth of what the data say about yaw near the calibrated value. The nuisance unknowns
    (planes, roughness, POS processes) are solved with the boresight pinned; its information
    is the pinned covariance's inverse less the pin."""
    pin = np.full(3, HOLD_SIGMA_RAD)
    res = adjust(sub, mount, planes, replace(adj, boresight_prior_rad=np.stack([mount.boresight_rad, pin])))
    info_rad2 = np.linalg.inv(res.cov_realistic) - np.diag(1.0 / pin**2)
    info_rad2 = 0.5 * (info_rad2 + info_rad2.T) + np.eye(3) / adj.boresight_prior_rad[1] ** 2  # type: ignore[index]
    cov = np.linalg.inv(info_rad2) * max(1.0, float(res.sigma0_squared))
    return np.sqrt(np.clip(np.diag(cov), 0.0, None))


def _unresolved(sigma_rad: np.ndarray, options: WatchOptions) -> str:
    parts = ", ".join(f"{a} {np.degrees(s):.3f}°" for a, s in zip(("roll", "pitch", "yaw"), sigma_rad))
    return (
        f"no angle resolved to {np.degrees(options.max_sigma_rad):.3f}° at the calibrated mount (σ {parts})"
    )


def _pinned(res, mount: Mount, held: np.ndarray, sigma_cal_rad: np.ndarray, factor: float):
    """The correction and its covariance from the solution with the ``held`` angles pinned at
    the calibrated value: the covariance scaled by the variance factor when above 1 and by the
    group test's ``factor``; a held angle's correction is 0 with its σ at the calibrated mount,
    uncorrelated (no evidence)."""
    delta = np.where(held, 0.0, res.boresight_rad - mount.boresight_rad)
    cov = res.cov_realistic * max(1.0, float(res.sigma0_squared)) * factor
    cov[held, :] = 0.0
    cov[:, held] = 0.0
    cov[held, held] = sigma_cal_rad[held] ** 2
    return delta, cov


def _moved(obs, res) -> np.ndarray:
    """Indices of the planes of ``obs`` with a (plane, line) mean residual beyond
    :data:`MOVED_Z` robust σ of all such means."""
    used = np.isin(obs.point_ids, res.used_point_ids)
    plane, line = obs.plane_index[used], obs.pass_index[used]
    m = int(line.max()) + 1
    key = plane * m + line
    uniq, inv = np.unique(key, return_inverse=True)
    mean = np.bincount(inv, res.residual_m) / np.bincount(inv)
    dev = np.abs(mean - np.median(mean))
    scale = max(1.4826 * float(np.median(dev)), MIN_MOVED_SCALE_M)
    return np.unique(uniq[dev > MOVED_Z * scale] // m)
