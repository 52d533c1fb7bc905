"""What the boresight adjustment takes in: the per-point observations, their checks, the options.

:class:`Observations` holds, per point, the eight observations (position N, E, D; roll, pitch,
heading; range; scan angle) and their sigmas, built from the trajectory by
:func:`build_observations`; :func:`validate_input` refuses targets the adjustment cannot use;
:class:`AdjustOptions` says what to estimate and how; :class:`AdjustmentError` is raised for any
input the adjustment cannot run on (its message says why and what to do).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from calib.boresight.errormodel import ErrorModel
from calib.boresight.ghmodel import EXTRA_NAMES
from calib.core.errors import CalibError
from calib.core.trajectory import Trajectory, TrajectoryError

ESTIMABLE = EXTRA_NAMES + ("pass_offsets",)
MIN_POINTS_PER_PLANE = 10
#: adjustment-level estimators (``pass_offsets`` is the thesis estimator with pass offsets)
ESTIMATORS = ("gls", "thesis")


class AdjustmentError(CalibError, ValueError):
    """The adjustment cannot run on this input (the message says why and what to do)."""


@dataclass
class Observations:
    """Everything the adjustment needs, per point (n points)."""

    t_gps_s: np.ndarray  # (n,)
    l: np.ndarray  # (n, 8) N, E, D, roll, pitch, heading, range, scan angle
    sigma_l: np.ndarray  # (n, 8) standard deviations of l
    plane_index: np.ndarray  # (n,) int, into plane_names
    pass_index: np.ndarray  # (n,) int, into pass_ids
    plane_names: list[str]
    pass_ids: list[int]
    point_ids: np.ndarray  # (n,) indices into the source point set (for outlier lists)
    trajectory: Trajectory | None = None  # needed to estimate a latency
    pass_headings_rad: dict[int, float] = field(default_factory=dict)  # relative to the wall
    #: planes that are scene tie patches (the rest are targets), indices into plane_names
    patch_planes: tuple[int, ...] = ()
    #: half the beam divergence: the GLS adds ρ·this·tan(incidence) to each point's range σ
    beam_half_divergence_rad: float = 0.0

    def __len__(self) -> int:
        return self.t_gps_s.shape[0]

    def latency_trajectory(self) -> Trajectory:
        """The trajectory, which estimating a latency needs (:class:`AdjustmentError` without)."""
        if self.trajectory is None:
            raise AdjustmentError("estimating the latency needs the trajectory")
        return self.trajectory

    def select(self, mask: np.ndarray) -> Observations:
        return Observations(
            self.t_gps_s[mask],
            self.l[mask],
            self.sigma_l[mask],
            self.plane_index[mask],
            self.pass_index[mask],
            self.plane_names,
            self.pass_ids,
            self.point_ids[mask],
            self.trajectory,
            self.pass_headings_rad,
            self.patch_planes,
            self.beam_half_divergence_rad,
        )

    def of_planes(self, order: list[int]) -> Observations:
        """The observations of the planes ``order`` (sorted indices into ``plane_names``),
        renumbered, every one of them a tie patch."""
        sub = self.select(np.isin(self.plane_index, order))
        sub.plane_index = np.searchsorted(order, sub.plane_index)
        sub.plane_names = [self.plane_names[j] for j in order]
        sub.patch_planes = tuple(range(len(order)))
        return sub


def build_observations(
    trajectory: Trajectory,
    t_gps_s: np.ndarray,
    range_m: np.ndarray,
    scan_angle_rad: np.ndarray,
    plane_index: np.ndarray,
    pass_id: np.ndarray,
    plane_names: list[str],
    sigma_range_m: float,
    sigma_scan_angle_rad: float,
    sigma_position_m: np.ndarray,
    sigma_attitude_rad: np.ndarray,
    point_ids: np.ndarray | None = None,
    time_offset_s: float = 0.0,
    pass_headings_rad: dict[int, float] | None = None,
    sigma_range_per_m: float = 0.0,
    beam_divergence_rad: float = 0.0,
    *,
    carry_trajectory: bool = True,
) -> Observations:
    """Interpolate the trajectory at the point times and attach the sigmas.

    The trajectory's per-epoch sigmas are used when present, else the site's constant ones.
    ``carry_trajectory=False`` builds observations that do not carry the trajectory: the GLS
    then puts its knots on a uniform grid of min(τ)/``knots_per_tau`` instead of at every INS
    epoch (:func:`calib.boresight.gls.frame_for`; the same model to the bridge's approximation,
    far fewer unknowns), and no latency can be estimated from them.
    """
    t = np.asarray(t_gps_s, float)
    n = t.size
    if n == 0:
        raise AdjustmentError("no points to adjust")
    if not np.all(np.isfinite(t)):
        raise AdjustmentError(f"{int(np.sum(~np.isfinite(t)))} point time(s) are NaN or infinite")
    pid = np.asarray(pass_id)
    same = pid[1:] == pid[:-1]
    back = same & (np.diff(t) < 0)
    if back.any():
        i = int(np.argmax(back)) + 1
        raise AdjustmentError(
            f"point times go backwards within pass {int(pid[i])} at point {i} "
            f"({t[i]:.6f} s after {t[i - 1]:.6f} s)"
        )
    for name, arr in (("range", range_m), ("scan angle", scan_angle_rad)):
        if not np.all(np.isfinite(arr)):
            raise AdjustmentError(f"{name} is NaN or infinite for {int(np.sum(~np.isfinite(arr)))} point(s)")
    try:
        poses = trajectory.interpolate(t + time_offset_s)
    except TrajectoryError as e:
        raise AdjustmentError(f"the trajectory does not cover the points: {e}") from None
    l = np.empty((n, 8))
    l[:, 0:3] = poses.p_lgf_m
    l[:, 3:6] = poses.rpy_rad
    l[:, 6] = range_m
    l[:, 7] = scan_angle_rad
    sig = np.empty((n, 8))
    sig[:, 0:3] = poses.sigma_p_m if poses.sigma_p_m is not None else sigma_position_m
    sig[:, 3:6] = poses.sigma_rpy_rad if poses.sigma_rpy_rad is not None else sigma_attitude_rad
    sig[:, 6] = sigma_range_m + sigma_range_per_m * np.asarray(range_m, float)
    sig[:, 7] = sigma_scan_angle_rad
    pass_ids = sorted(int(p) for p in np.unique(pid))
    pass_index = np.searchsorted(pass_ids, pid)
    return Observations(
        t,
        l,
        sig,
        np.asarray(plane_index, int),
        pass_index,
        list(plane_names),
        pass_ids,
        np.arange(n) if point_ids is None else np.asarray(point_ids),
        trajectory if carry_trajectory else None,
        dict(pass_headings_rad or {}),
        (),
        0.5 * beam_divergence_rad,
    )


def validate_input(obs: Observations) -> None:
    counts = np.bincount(obs.plane_index, minlength=len(obs.plane_names))
    few = [
        f"{name} ({c} points)"
        for name, c in zip(obs.plane_names, counts, strict=False)
        if c < MIN_POINTS_PER_PLANE
    ]
    if few:
        raise AdjustmentError(
            f"target(s) with fewer than {MIN_POINTS_PER_PLANE} points: "
            f"{', '.join(few)}; re-extract them or remove them from the site"
        )
    if len(obs.plane_names) < 2:
        raise AdjustmentError(
            f"only one target ({obs.plane_names[0]}) has points: a single plane cannot separate "
            f"the boresight from POS and plane errors (thesis §4.4.1.2); use at least two targets "
            f"with different inclinations (e.g. vertical and 45°)"
        )


#: the largest iteration cap an adjustment accepts (it converges in 3–8 on any sane input)
MAX_ITERATIONS = 1000


@dataclass(frozen=True)
class AdjustOptions:
    estimate: tuple[str, ...] = ()
    tol_angle_rad: float = 1e-9  # ≈ 6e-8°
    tol_m: float = 1e-7
    #: also converged when every step is below this fraction of its formal σ (0: off)
    rel_tol: float = 1e-3
    max_iterations: int = 20
    outliers: str = "snooping"  # or "none"
    outlier_alpha: float = 0.05  # family-wise error rate of the data-snooping tests
    max_outlier_rounds: int = 10
    error_model: ErrorModel = ErrorModel()
    jackknife: bool = True
    max_sigma_rad: float = float(np.radians(0.05))  # observability limit for a boresight angle
    pass_offset_sigma_m: np.ndarray | None = None  # prior; default: the trajectory's σ
    #: "gls": the POS errors as Gauss–Markov processes estimated jointly (calib.boresight.gls),
    #: its σ is its realistic σ; "thesis": white weights, realistic σ by propagation
    estimator: str = "gls"
    knots_per_tau: float = 100.0  # GLS: knot spacing = the shortest τ over this
    #: GLS: which planes get a roughness variance estimated from their residuals
    roughness: str = "all"  # or "patches", "none"
    #: GLS: a Gaussian prior on the boresight, (2, 3): its mean and σ per angle (the mount
    #: watch: a block that barely sees an angle must not wander off on it); None: none
    boresight_prior_rad: np.ndarray | None = None

    def __post_init__(self):
        unknown = [e for e in self.estimate if e not in ESTIMABLE]
        if unknown:
            raise AdjustmentError(
                f"unknown extra unknown(s) {', '.join(unknown)}; choose from {', '.join(ESTIMABLE)}"
            )
        if "scan_angle_offset" in self.estimate:
            raise AdjustmentError(
                "scan_angle_offset cannot be estimated with the boresight: a scan-angle offset "
                "is a rotation about the scanner's own x axis, which the boresight rotation "
                "already contains for any mount (thesis §3.5.2 finds them correlated; here they "
                "are identical), so the estimated boresight absorbs it"
            )
        if self.estimator not in ESTIMATORS:
            raise AdjustmentError(f"estimator {self.estimator!r}: expected one of {', '.join(ESTIMATORS)}")
        if self.roughness not in ("patches", "all", "none"):
            raise AdjustmentError(f"roughness={self.roughness!r}: expected 'patches', 'all' or 'none'")
        if self.outliers not in ("snooping", "none"):
            raise AdjustmentError(f"outliers={self.outliers!r}: expected 'snooping' or 'none'")
        if not (isinstance(self.max_iterations, int) and 1 <= self.max_iterations <= MAX_ITERATIONS):
            raise AdjustmentError(
                f"max_iterations={self.max_iterations!r}: expected a whole number from 1 to {MAX_ITERATIONS}"
            )
