"""Rigorous plane-based boresight adjustment (Gauss–Helmert), DESIGN §7.

One condition per point, ``F_i = n_jᵀ x_i(l_i, unknowns) + d_j = 0`` (see :mod:`calib.boresight.ghmodel`),
eight observations per point with their own sigmas (position, attitude, range, scan angle).
Because each point has one condition, ``M_i = B_i Q_i B_iᵀ`` is a scalar and the normal
equations assemble in O(n): never a dense n × n or 8n × 8n matrix.

The solution is the iterated Gauss–Helmert model with the linearization at the adjusted
observations (``w = F(l̂) + B (l − l̂)``), unit normals kept exactly unit by a minimal
(tangent-space) parameterization, optional extra unknowns and per-pass trajectory translations
with a prior from the trajectory's σ.

Uncertainty:
- formal: ``Q_xx = N⁻¹`` (σ0 = 1), and scaled by σ̂0;
- realistic: POS errors are correlated in time, so within a pass they act nearly as biases.
  ``sigma_realistic`` propagates the observation errors through the estimator with a
  first-order Gauss–Markov correlation of the POS channels (σ from the trajectory, correlation
  time from the site or the caller), ``Cov = N⁻¹ (Σ_ij g_i g_jᵀ ρ(t_i − t_j)) N⁻¹`` — evaluated
  in O(n) with decayed cumulative sums; for the boresight and every extra unknown (each
  extra is reported with its formal and realistic σ and its correlation with the boresight);
- a delete-one-pass jackknife is reported beside it as an empirical check.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Iterable

import numpy as np
from scipy import stats

from calib.core import frames
from calib.boresight.errormodel import (  # noqa: F401  (re-exported: part of the adjustment's API)
    DEFAULT_POS_CORRELATION_S,
    ErrorModel,
    correlated_sum,
)
from calib.boresight.ghmodel import EXTRA_NAMES, State, linearize, tangent_basis
from calib.boresight.observability import (  # noqa: F401  (re-exported)
    ANGLE_NAMES,
    OBSERVING_PAIRS,
    AdjustmentError,
    ObservabilityError,
    check_observability,
    sailed_headings,
)
from calib.core.trajectory import Trajectory, TrajectoryError

ESTIMABLE = EXTRA_NAMES + ("pass_offsets",)
MIN_POINTS_PER_PLANE = 10
#: Boresight steps above this linearize at the observations (see _solve).
_FAR_RAD = 1e-4


# ---------------------------------------------------------------------------------------------
# Input
# ---------------------------------------------------------------------------------------------


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

    def __len__(self) -> int:
        return self.t_gps_s.shape[0]

    def select(self, mask: np.ndarray) -> "Observations":
        return Observations(self.t_gps_s[mask], self.l[mask], self.sigma_l[mask],
                            self.plane_index[mask], self.pass_index[mask], self.plane_names,
                            self.pass_ids, self.point_ids[mask], self.trajectory,
                            self.pass_headings_rad)  # fmt: skip


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
) -> Observations:
    """Interpolate the trajectory at the point times and attach the sigmas.

    The trajectory's per-epoch sigmas are used when present, else the site's constant ones.
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
        raise AdjustmentError(f"point times go backwards within pass {int(pid[i])} at point {i} "
                              f"({t[i]:.6f} s after {t[i - 1]:.6f} s)")  # fmt: skip
    for name, arr in (("range", range_m), ("scan angle", scan_angle_rad)):
        if not np.all(np.isfinite(arr)):
            raise AdjustmentError(f"{name} is NaN or infinite for {int(np.sum(~np.isfinite(arr)))} "
                                  f"point(s)")  # fmt: skip
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
    sig[:, 6] = sigma_range_m
    sig[:, 7] = sigma_scan_angle_rad
    pass_ids = sorted(int(p) for p in np.unique(pid))
    pass_index = np.searchsorted(pass_ids, pid)
    return Observations(
        t, l, sig, np.asarray(plane_index, int), pass_index, list(plane_names), pass_ids,
        np.arange(n) if point_ids is None else np.asarray(point_ids), trajectory,
        dict(pass_headings_rad or {}),
    )  # fmt: skip


# ---------------------------------------------------------------------------------------------
# Options and results
# ---------------------------------------------------------------------------------------------


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

    def __post_init__(self):
        unknown = [e for e in self.estimate if e not in ESTIMABLE]
        if unknown:
            raise AdjustmentError(f"unknown extra unknown(s) {', '.join(unknown)}; choose from "
                                  f"{', '.join(ESTIMABLE)}")  # fmt: skip
        if "scan_angle_offset" in self.estimate:
            raise AdjustmentError(
                "scan_angle_offset cannot be estimated with the boresight: a scan-angle offset "
                "is a rotation about the scanner's own x axis, which the boresight rotation "
                "already contains for any mount (thesis §3.5.2 finds them correlated; here they "
                "are identical), so the estimated boresight absorbs it")
        if self.outliers not in ("snooping", "none"):
            raise AdjustmentError(f"outliers={self.outliers!r}: expected 'snooping' or 'none'")


@dataclass
class AdjustmentResult:
    boresight_rad: np.ndarray
    cov_formal: np.ndarray  # (3, 3), σ0 = 1
    sigma0_squared: float
    cov_realistic: np.ndarray  # (3, 3)
    cov_jackknife: np.ndarray | None
    df: int
    iterations: int
    converged: bool
    state: State
    #: name -> {"value", "sigma" (formal), "sigma_realistic" (``error_model`` propagated, as
    #: ``cov_realistic``), "correlation_with_boresight" (formal; [roll, pitch, yaw])}; for
    #: ``pass<id>_offset_m`` value and σ are [north, east, down] and the correlation is 3 × 3
    #: (rows north, east, down; columns roll, pitch, yaw)
    extras: dict
    plane_stats: list[dict]
    pass_stats: list[dict]
    n_points: int
    outlier_point_ids: np.ndarray
    residual_m: np.ndarray  # (n_used,) signed distance of each used point to its plane
    used_point_ids: np.ndarray
    runtime_s: float
    error_model: ErrorModel
    names: list[str]  # names of all unknowns (for cov_all)
    cov_all: np.ndarray  # formal covariance of all unknowns (σ0 = 1)

    @property
    def sigma_formal_rad(self) -> np.ndarray:
        return np.sqrt(np.diag(self.cov_formal))

    @property
    def sigma_scaled_rad(self) -> np.ndarray:
        return self.sigma_formal_rad * np.sqrt(self.sigma0_squared)

    @property
    def sigma_realistic_rad(self) -> np.ndarray:
        return np.sqrt(np.diag(self.cov_realistic))

    @property
    def correlation(self) -> np.ndarray:
        s = self.sigma_formal_rad
        return self.cov_formal / np.outer(s, s)

    def chi2_test(self, alpha: float = 0.05) -> dict:
        lo = float(stats.chi2.ppf(alpha / 2, self.df) / self.df)
        hi = float(stats.chi2.ppf(1 - alpha / 2, self.df) / self.df)
        return {"df": int(self.df), "lower": lo, "upper": hi,
                "passed": bool(lo <= self.sigma0_squared <= hi)}  # fmt: skip


# ---------------------------------------------------------------------------------------------
# Parameter layout
# ---------------------------------------------------------------------------------------------


class _Layout:
    def __init__(self, n_planes: int, n_passes: int, estimate: Iterable[str]):
        est = set(estimate)
        self.extras = [e for e in EXTRA_NAMES if e in est]
        self.offsets = "pass_offsets" in est
        self.i_extra = 3
        self.i_plane = 3 + len(self.extras)
        self.i_offset = self.i_plane + 3 * n_planes
        self.n = self.i_offset + (3 * n_passes if self.offsets else 0)
        self.n_planes, self.n_passes = n_planes, n_passes

    def names(self, plane_names, pass_ids) -> list[str]:
        out = [f"boresight_{a}" for a in ANGLE_NAMES] + list(self.extras)
        for p in plane_names:
            out += [f"{p}.normal_t1", f"{p}.normal_t2", f"{p}.d"]
        if self.offsets:
            for k in pass_ids:
                out += [f"pass{k}.offset_{c}" for c in ("north", "east", "down")]
        return out


def _design_rows(lin, layout: _Layout, plane_index, pass_index, sl) -> np.ndarray:
    """Dense rows of A for the points in slice ``sl`` (a chunk)."""
    m = sl.stop - sl.start
    A = np.zeros((m, layout.n))
    A[:, 0:3] = lin.A_boresight[sl]
    for i, name in enumerate(layout.extras):
        A[:, layout.i_extra + i] = lin.A_extra[name][sl]
    rows = np.arange(m)
    base = layout.i_plane + 3 * plane_index[sl]
    for c in range(3):
        A[rows, base + c] = lin.A_plane[sl, c]
    if layout.offsets:
        base = layout.i_offset + 3 * pass_index[sl]
        for c in range(3):
            A[rows, base + c] = lin.A_offset[sl, c]
    return A


_CHUNK = 1 << 16


def _normal_equations(lin, layout, obs, w, M):
    N = np.zeros((layout.n, layout.n))
    g = np.zeros(layout.n)
    for lo in range(0, len(obs), _CHUNK):
        sl = slice(lo, min(lo + _CHUNK, len(obs)))
        A = _design_rows(lin, layout, obs.plane_index, obs.pass_index, sl)
        sw = 1.0 / np.sqrt(M[sl])
        Aw = A * sw[:, None]
        N += Aw.T @ Aw
        g += Aw.T @ (w[sl] * sw)
    return N, g


def _a_times(lin, layout, obs, dx) -> np.ndarray:
    """A · dx for all points, without forming A."""
    out = lin.A_boresight @ dx[0:3]
    for i, name in enumerate(layout.extras):
        out += lin.A_extra[name] * dx[layout.i_extra + i]
    dp = dx[layout.i_plane: layout.i_offset].reshape(-1, 3)[obs.plane_index]
    out += np.einsum("ij,ij->i", lin.A_plane, dp)
    if layout.offsets:
        do = dx[layout.i_offset:].reshape(-1, 3)[obs.pass_index]
        out += np.einsum("ij,ij->i", lin.A_offset, do)
    return out


def _rows_of_inverse(lin, layout, obs, Ninv_rows, M) -> np.ndarray:
    """(n, r) = (Ninv_rows · A_iᵀ) / M_i for every point, without forming A."""
    r = Ninv_rows.shape[0]
    out = lin.A_boresight @ Ninv_rows[:, 0:3].T
    for i, name in enumerate(layout.extras):
        out += lin.A_extra[name][:, None] * Ninv_rows[:, layout.i_extra + i][None, :]
    P = Ninv_rows[:, layout.i_plane: layout.i_offset].T.reshape(-1, 3, r)  # (planes, 3, r)
    out += np.einsum("ic,icr->ir", lin.A_plane, P[obs.plane_index])
    if layout.offsets:
        O = Ninv_rows[:, layout.i_offset:].T.reshape(-1, 3, r)
        out += np.einsum("ic,icr->ir", lin.A_offset, O[obs.pass_index])
    return out / M[:, None]


# ---------------------------------------------------------------------------------------------
# Solver
# ---------------------------------------------------------------------------------------------


def _rates(traj: Trajectory, t: np.ndarray, h: float = 0.005) -> tuple[np.ndarray, np.ndarray]:
    """Velocity (LGF) and body angular rate at times t, by central differences."""
    lo = np.maximum(t - h, traj.t_gps_s[0])
    hi = np.minimum(t + h, traj.t_gps_s[-1])
    a, b = traj.interpolate(lo), traj.interpolate(hi)
    dt = (hi - lo)[:, None]
    vel = (b.p_lgf_m - a.p_lgf_m) / dt
    rel = np.einsum("nji,njk->nik", a.r_b_n, b.r_b_n)
    omega = frames.vector_from_rotation(rel) / dt
    return vel, omega


def _initial_state(mount, planes_init, n_passes, centers=None) -> State:
    """``planes_init``: (normal, d) in the LGF per plane; ``centers`` the planes' reference
    points (default: the foot of the perpendicular from the LGF origin)."""
    normals = np.array([np.asarray(n, float) / np.linalg.norm(n) for n, _ in planes_init])
    d_lgf = np.array([float(dd) / np.linalg.norm(n) for n, dd in planes_init])
    if centers is None:
        centers = -d_lgf[:, None] * normals
    centers = np.asarray(centers, float)
    d_rel = d_lgf + np.einsum("ij,ij->i", normals, centers)
    return State(
        boresight_rad=np.asarray(mount.boresight_rad, float).copy(),
        normals=normals,
        d_m=d_rel,
        centers_m=centers,
        pass_offsets_m=np.zeros((n_passes, 3)),
        lever_arm_m=np.asarray(mount.lever_arm_m, float).copy(),
        range_offset_m=float(mount.range_offset_m),
        scan_angle_offset_rad=float(mount.scan_angle_offset_rad),
        latency_s=float(mount.time_offset_s),
    )


def _plane_centers(obs: Observations, mount, r_nom) -> np.ndarray:
    """Centroid of each plane's points georeferenced with the a-priori mount."""
    lin = linearize(_initial_state(mount, [(np.array([0.0, 0.0, 1.0]), 0.0)] *
                                   len(obs.plane_names), len(obs.pass_ids)),
                    r_nom, obs.plane_index, obs.pass_index, obs.l)  # fmt: skip
    cnt = np.bincount(obs.plane_index, minlength=len(obs.plane_names))[:, None]
    sums = np.stack([np.bincount(obs.plane_index, lin.x_lgf_m[:, c],
                                 minlength=len(obs.plane_names)) for c in range(3)], 1)  # fmt: skip
    return sums / np.maximum(cnt, 1)


def _apply(state: State, dx: np.ndarray, layout: _Layout, bases) -> State:
    s = state.copy()
    s.boresight_rad = s.boresight_rad + dx[0:3]
    for i, name in enumerate(layout.extras):
        v = dx[layout.i_extra + i]
        if name == "range_offset":
            s.range_offset_m += v
        elif name == "scan_angle_offset":
            s.scan_angle_offset_rad += v
        elif name == "lever_arm_x":
            s.lever_arm_m[0] += v
        elif name == "lever_arm_y":
            s.lever_arm_m[1] += v
        elif name == "latency":
            s.latency_s += v
    dp = dx[layout.i_plane: layout.i_offset].reshape(-1, 3)
    n_new = s.normals + np.einsum("mij,mj->mi", bases, dp[:, 0:2])
    s.normals = n_new / np.linalg.norm(n_new, axis=1, keepdims=True)
    s.d_m = s.d_m + dp[:, 2]
    if layout.offsets:
        s.pass_offsets_m = s.pass_offsets_m + dx[layout.i_offset:].reshape(-1, 3)
    return s


@dataclass
class _Solution:
    state: State
    N: np.ndarray
    Ninv: np.ndarray
    lin: object
    M: np.ndarray
    e: np.ndarray  # adjusted misclosure A·dx + w per point (its square / M is vᵀPv)
    vtpv: float
    df: int
    iterations: int
    converged: bool
    layout: _Layout


def _offset_prior_sigma(obs: Observations, options: AdjustOptions) -> np.ndarray:
    """(K, 3) prior σ of the per-pass translations: the mean position σ of each pass."""
    if options.pass_offset_sigma_m is not None:
        return np.broadcast_to(np.asarray(options.pass_offset_sigma_m, float),
                               (len(obs.pass_ids), 3))  # fmt: skip
    out = np.empty((len(obs.pass_ids), 3))
    for k in range(len(obs.pass_ids)):
        out[k] = obs.sigma_l[obs.pass_index == k, 0:3].mean(axis=0)
    return out


def _observations_at(obs: Observations, state: State, estimate_latency: bool) -> np.ndarray:
    """The observation vector; with latency estimated the poses move with Δt."""
    if not estimate_latency or state.latency_s == 0.0:
        return obs.l
    if obs.trajectory is None:
        raise AdjustmentError("estimating the latency needs the trajectory")
    poses = obs.trajectory.interpolate(obs.t_gps_s + state.latency_s)
    l = obs.l.copy()
    l[:, 0:3] = poses.p_lgf_m
    l[:, 3:6] = poses.rpy_rad
    return l


def _solve(obs: Observations, state: State, r_nom: np.ndarray, options: AdjustOptions
           ) -> _Solution:  # fmt: skip
    layout = _Layout(len(obs.plane_names), len(obs.pass_ids), options.estimate)
    est_latency = "latency" in layout.extras
    Q = obs.sigma_l**2
    prior_sigma = _offset_prior_sigma(obs, options) if layout.offsets else None
    v = np.zeros_like(obs.l)  # residuals of the observations
    converged = False
    it = 0
    rates = None
    for it in range(1, options.max_iterations + 1):
        l_obs = _observations_at(obs, state, est_latency)
        l0 = l_obs + v
        if est_latency:
            rates = _rates(obs.trajectory, obs.t_gps_s + state.latency_s)
        bases = np.stack([tangent_basis(n) for n in state.normals])
        lin = linearize(state, r_nom, obs.plane_index, obs.pass_index, l0, rates, bases)
        w = lin.F - np.einsum("ij,ij->i", lin.B, v)
        M = np.einsum("ij,ij->i", lin.B**2, Q)
        N, g = _normal_equations(lin, layout, obs, w, M)
        if layout.offsets:
            o = state.pass_offsets_m.reshape(-1)
            wt = 1.0 / prior_sigma.reshape(-1) ** 2
            idx = np.arange(layout.i_offset, layout.n)
            N[idx, idx] += wt
            g[idx] += wt * o
        dx = _solve_normal(N, -g, obs, layout)
        e = _a_times(lin, layout, obs, dx) + w
        k = e / M
        v = -Q * lin.B * k[:, None]
        state = _apply(state, dx, layout, bases)
        angle_step = np.max(np.abs(dx[0:3]))
        if angle_step > _FAR_RAD:
            # far from the solution the residuals of a linear step are not residuals of the
            # solution: keep linearizing at the observations until the boresight settles
            v[:] = 0.0
        plane_steps = dx[layout.i_plane: layout.i_offset].reshape(-1, 3)
        metric_step = np.max(np.abs(plane_steps[:, 2]))
        angle_step = max(angle_step, np.max(np.abs(plane_steps[:, 0:2])))
        for i, name in enumerate(layout.extras):
            step = abs(dx[layout.i_extra + i])
            if name in ("scan_angle_offset",):
                angle_step = max(angle_step, step)
            elif name == "latency":
                metric_step = max(metric_step, step * 10.0)  # ~10 m/s: seconds → metres
            else:
                metric_step = max(metric_step, step)
        if layout.offsets:
            metric_step = max(metric_step, np.max(np.abs(dx[layout.i_offset:])))
        if angle_step < options.tol_angle_rad and metric_step < options.tol_m:
            converged = True
            break
        if options.rel_tol > 0 and it > 1:
            # steps that no longer matter against the unknowns' own σ (noisy data converge
            # only linearly in the last digits: see the iteration scheme above)
            sd = np.sqrt(np.diag(np.linalg.inv(N)))
            if np.all(np.abs(dx) <= options.rel_tol * sd):
                converged = True
                break
    vtpv = float(np.sum(v**2 / Q))
    df = len(obs) - layout.n
    if layout.offsets:
        o = state.pass_offsets_m.reshape(-1)
        vtpv += float(np.sum(o**2 / prior_sigma.reshape(-1) ** 2))
        df += 3 * len(obs.pass_ids)
    Ninv = np.linalg.inv(N)
    return _Solution(state, N, Ninv, lin, M, e, vtpv, df, it, converged, layout)


def _solve_normal(N, rhs, obs, layout):
    """Solve N dx = rhs; a singular N is an observability error naming the cause."""
    try:
        c = np.linalg.cholesky(N)
    except np.linalg.LinAlgError:
        raise ObservabilityError(_singular_message(N, obs, layout)) from None
    y = np.linalg.solve(c, rhs)
    return np.linalg.solve(c.T, y)


def _singular_message(N, obs, layout) -> str:
    names = layout.names(obs.plane_names, obs.pass_ids)
    vals, vecs = np.linalg.eigh(N)
    v = vecs[:, 0]
    top = np.argsort(-np.abs(v))[:3]
    combo = " + ".join(f"{v[i]:.2f}·{names[i]}" for i in top if abs(v[i]) > 0.1)
    return (f"the normal equations are singular: the data do not determine {combo}. "
            f"Check that every plane has points from several passes and that extra unknowns "
            f"({', '.join(layout.extras) or 'none'}) are observable with this geometry.")


# ---------------------------------------------------------------------------------------------
# Realistic covariance: propagation of time-correlated POS errors
# ---------------------------------------------------------------------------------------------


def _reported_rows(layout: _Layout) -> np.ndarray:
    """Indices of the boresight, the extras and the pass offsets (the unknowns reported with a
    realistic σ; the planes are not): just the boresight when nothing extra is estimated."""
    idx = np.arange(layout.i_plane)
    if layout.offsets:
        idx = np.concatenate([idx, np.arange(layout.i_offset, layout.n)])
    return idx


def propagated_covariance(sol: _Solution, obs: Observations, model: ErrorModel,
                          rows: slice | np.ndarray = slice(0, 3)) -> np.ndarray:  # fmt: skip
    """Covariance of the unknowns in ``rows`` (a slice or an index array) when the POS channels
    (0–5) follow ``model`` and range and scan angle are white: ``N⁻¹ H N⁻¹`` with
    H = Σ_c Σ_ij g_ic g_jcᵀ ρ_c(i, j). O(n·r²) for r rows."""
    Ninv_rows = sol.Ninv[rows]
    G = _rows_of_inverse(sol.lin, sol.layout, obs, Ninv_rows, sol.M)  # (n, r)
    r = G.shape[1]
    cov = np.zeros((r, r))
    # The prior on the pass offsets (offset = 0 ± σ) shapes N but adds no error of its own
    # here: under this model a pass's translation IS its POS position error, which the
    # position channels below already carry; counting it again would double it.
    for c in range(8):
        q = G * (sol.lin.B[:, c] * obs.sigma_l[:, c])[:, None]
        if c < 6:
            cov += correlated_sum(obs.t_gps_s, q, model, obs.pass_index, model.tau_s(c))
        else:
            cov += q.T @ q
    return cov


# ---------------------------------------------------------------------------------------------
# Observability
# ---------------------------------------------------------------------------------------------

def validate_input(obs: Observations) -> None:
    counts = np.bincount(obs.plane_index, minlength=len(obs.plane_names))
    few = [f"{name} ({c} points)" for name, c in zip(obs.plane_names, counts)
           if c < MIN_POINTS_PER_PLANE]  # fmt: skip
    if few:
        raise AdjustmentError(f"target(s) with fewer than {MIN_POINTS_PER_PLANE} points: "
                              f"{', '.join(few)}; re-extract them or remove them from the site")  # fmt: skip
    if len(obs.plane_names) < 2:
        raise AdjustmentError(
            f"only one target ({obs.plane_names[0]}) has points: a single plane cannot separate "
            f"the boresight from POS and plane errors (thesis §4.4.1.2); use at least two targets "
            f"with different inclinations (e.g. vertical and 45°)"
        )


# ---------------------------------------------------------------------------------------------
# Public entry points
# ---------------------------------------------------------------------------------------------


def _plane_pass_stats(obs: Observations, residual: np.ndarray, state: State):
    planes, passes = [], []
    for j, name in enumerate(obs.plane_names):
        r = residual[obs.plane_index == j]
        planes.append({"name": name, "normal": [float(x) for x in state.normals[j]],
                       "d": float(state.d_lgf_m[j]), "n_points": int(r.size),
                       "rms_m": float(np.sqrt(np.mean(r**2))) if r.size else float("nan")})  # fmt: skip
    for k, pid in enumerate(obs.pass_ids):
        r = residual[obs.pass_index == k]
        h = obs.pass_headings_rad.get(pid)
        passes.append({"id": int(pid),
                       "heading_deg": None if h is None else float(np.degrees(h) % 360.0),
                       "n_points": int(r.size),
                       "rms_m": float(np.sqrt(np.mean(r**2))) if r.size else float("nan")})  # fmt: skip
    return planes, passes


def _snooping_threshold(n: int, alpha: float) -> float:
    """Two-sided normal quantile for n tests at family-wise level alpha (Šidák), ≥ 3.29."""
    per_test = 1.0 - (1.0 - alpha) ** (1.0 / max(n, 1))
    return max(float(stats.norm.isf(per_test / 2.0)), 3.29)


def adjust(obs: Observations, mount, planes_init, options: AdjustOptions = AdjustOptions()
           ) -> AdjustmentResult:  # fmt: skip
    """Estimate the boresight (and the requested extras) from plane observations.

    ``mount`` is the a-priori :class:`calib.core.georef.Mount`; ``planes_init`` a list of
    (normal, d) per plane in ``obs.plane_names`` order (from the extraction's plane fits).
    """
    t_start = time.perf_counter()
    validate_input(obs)
    r_nom = frames.rotation_zyx(*mount.nominal_rad)
    state0 = _initial_state(mount, planes_init, len(obs.pass_ids),
                            _plane_centers(obs, mount, r_nom))  # fmt: skip
    active = np.ones(len(obs), bool)
    # observability is judged on the geometry at the a-priori values: an unobservable angle
    # would otherwise wander during the iterations and make the verdict arbitrary
    prior_info = _information(obs, state0, r_nom, options.estimate)
    if np.linalg.matrix_rank(prior_info.N) < prior_info.N.shape[0]:
        raise ObservabilityError(_singular_message(prior_info.N, obs, prior_info.layout))
    check_observability(prior_info.Ninv[0:3, 0:3], obs, options.max_sigma_rad, options.estimate)
    sol = _solve(obs, state0, r_nom, options)
    if not np.all(np.isfinite(sol.state.boresight_rad)):
        raise AdjustmentError("the adjustment diverged (non-finite estimates)")
    used = obs
    if options.outliers == "snooping":
        for _ in range(options.max_outlier_rounds):
            s0 = np.sqrt(sol.vtpv / sol.df)
            # normalized residual of each condition: e_i / sqrt(M_i − A_i N⁻¹ A_iᵀ) / σ̂0
            wn = sol.e / np.sqrt(np.maximum(sol.M - _leverage(sol, used), 1e-12 * sol.M)) / s0
            bad = np.abs(wn) > _snooping_threshold(len(used), options.outlier_alpha)
            if not bad.any():
                break
            idx_used = np.flatnonzero(active)
            active[idx_used[bad]] = False
            used = obs.select(active)
            validate_input(used)
            sol = _solve(used, sol.state, r_nom, options)
    # signed distances of the points georeferenced from the raw observations
    lin_raw = linearize(sol.state, r_nom, used.plane_index, used.pass_index,
                        _observations_at(used, sol.state, "latency" in sol.layout.extras))  # fmt: skip
    residual = lin_raw.F
    cov_formal_all = sol.Ninv
    # the realistic covariance of the boresight and of every extra unknown (not the planes):
    # an extra's formal σ is as optimistic as the boresight's under time-correlated POS errors
    rows = _reported_rows(sol.layout)
    cov_real_rows = (propagated_covariance(sol, used, options.error_model, rows)
                     if options.error_model.kind != "white"
                     else sol.Ninv[np.ix_(rows, rows)])  # fmt: skip
    cov_real = cov_real_rows[0:3, 0:3].copy()
    sd_real = np.sqrt(np.diag(cov_real_rows))  # in the order of ``rows``
    cov_jack = _jackknife(used, sol.state, r_nom, options) if options.jackknife else None
    names = sol.layout.names(used.plane_names, used.pass_ids)
    extras = {}
    sd = np.sqrt(np.diag(cov_formal_all))

    def corr_with_boresight(j: int) -> list[float]:
        return [float(cov_formal_all[j, a] / (sd[j] * sd[a])) for a in range(3)]

    for i, name in enumerate(sol.layout.extras):
        j = sol.layout.i_extra + i
        value = {"range_offset": sol.state.range_offset_m,
                 "scan_angle_offset": sol.state.scan_angle_offset_rad,
                 "lever_arm_x": sol.state.lever_arm_m[0], "lever_arm_y": sol.state.lever_arm_m[1],
                 "latency": sol.state.latency_s}[name]  # fmt: skip
        extras[name] = {"value": float(value), "sigma": float(sd[j]),
                        "sigma_realistic": float(sd_real[3 + i]),
                        "correlation_with_boresight": corr_with_boresight(j)}  # fmt: skip
    if sol.layout.offsets:
        r0 = 3 + len(sol.layout.extras)  # first pass offset in ``rows``
        for k, pid in enumerate(used.pass_ids):
            j = sol.layout.i_offset + 3 * k
            extras[f"pass{pid}_offset_m"] = {
                "value": [float(x) for x in sol.state.pass_offsets_m[k]],
                "sigma": [float(x) for x in sd[j: j + 3]],
                "sigma_realistic": [float(x) for x in sd_real[r0 + 3 * k: r0 + 3 * k + 3]],
                # rows north, east, down; columns roll, pitch, yaw
                "correlation_with_boresight": [corr_with_boresight(j + c) for c in range(3)],
            }
    planes, passes = _plane_pass_stats(used, residual, sol.state)
    return AdjustmentResult(
        boresight_rad=sol.state.boresight_rad.copy(),
        cov_formal=cov_formal_all[0:3, 0:3].copy(),
        sigma0_squared=sol.vtpv / sol.df,
        cov_realistic=cov_real,
        cov_jackknife=cov_jack,
        df=sol.df,
        iterations=sol.iterations,
        converged=sol.converged,
        state=sol.state,
        extras=extras,
        plane_stats=planes,
        pass_stats=passes,
        n_points=len(used),
        outlier_point_ids=obs.point_ids[~active],
        residual_m=residual,
        used_point_ids=used.point_ids,
        runtime_s=time.perf_counter() - t_start,
        error_model=options.error_model,
        names=names,
        cov_all=cov_formal_all,
    )


def _leverage(sol: _Solution, obs: Observations) -> np.ndarray:
    """A_i N⁻¹ A_iᵀ for every point (chunked; O(n·u²))."""
    out = np.empty(len(obs))
    for lo in range(0, len(obs), _CHUNK):
        sl = slice(lo, min(lo + _CHUNK, len(obs)))
        A = _design_rows(sol.lin, sol.layout, obs.plane_index, obs.pass_index, sl)
        out[sl] = np.einsum("ij,ij->i", A @ sol.Ninv, A)
    return out


def _jackknife(obs: Observations, state: State, r_nom, options: AdjustOptions):
    """Delete-one-pass jackknife covariance of the boresight (None with < 3 usable passes)."""
    est = []
    quick = AdjustOptions(estimate=options.estimate, tol_angle_rad=1e-9, tol_m=1e-7,
                          max_iterations=options.max_iterations)  # fmt: skip
    for k in range(len(obs.pass_ids)):
        sub = obs.select(obs.pass_index != k)
        keep = np.unique(sub.pass_index)
        sub.pass_index = np.searchsorted(keep, sub.pass_index)
        sub.pass_ids = [obs.pass_ids[i] for i in keep]
        if np.any(np.bincount(sub.plane_index, minlength=len(obs.plane_names)) < 3):
            continue
        s = state.copy()
        s.pass_offsets_m = s.pass_offsets_m[keep]
        try:
            sol = _solve(sub, s, r_nom, quick)
        except ObservabilityError:
            continue
        if np.all(np.sqrt(np.diag(sol.Ninv[0:3, 0:3])) < np.radians(1.0)):
            est.append(sol.state.boresight_rad)
    g = len(est)
    if g < 3:
        return None
    est = np.array(est)
    dev = est - est.mean(axis=0)
    return (g - 1) / g * dev.T @ dev


def _information(obs: Observations, state: State, r_nom, estimate) -> _Solution:
    """One linearization at ``state`` and the normal matrix (with the offset prior), wrapped as
    a solution so that the covariance machinery applies to it."""
    layout = _Layout(len(obs.plane_names), len(obs.pass_ids), estimate)
    rates = _rates(obs.trajectory, obs.t_gps_s + state.latency_s) \
        if "latency" in layout.extras else None
    bases = np.stack([tangent_basis(n) for n in state.normals])
    lin = linearize(state, r_nom, obs.plane_index, obs.pass_index, obs.l, rates, bases)
    M = np.einsum("ij,ij->i", lin.B**2, obs.sigma_l**2)
    N, _ = _normal_equations(lin, layout, obs, np.zeros(len(obs)), M)
    if layout.offsets:
        prior = _offset_prior_sigma(obs, AdjustOptions(estimate=tuple(estimate)))
        idx = np.arange(layout.i_offset, layout.n)
        N[idx, idx] += 1.0 / prior.reshape(-1) ** 2
    try:
        Ninv = np.linalg.inv(N)
    except np.linalg.LinAlgError:
        Ninv = np.linalg.pinv(N)
    return _Solution(state, N, Ninv, lin, M, np.zeros(len(obs)), 0.0, len(obs) - layout.n, 0,
                     True, layout)  # fmt: skip


def predict_covariance(obs: Observations, mount, planes, estimate: tuple[str, ...] = (),
                       model: ErrorModel = ErrorModel("white")) -> dict:  # fmt: skip
    """Boresight covariance the geometry in ``obs`` would give, without adjusting.

    ``obs`` holds noise-free observations (e.g. simulated for hypothetical passes and targets)
    with the sigmas to assume; ``planes`` the true (normal, d) per plane. Returns
    ``{"formal": 3×3, "realistic": 3×3 under ``model``, "correlation": 3×3}`` in radians².
    """
    r_nom = frames.rotation_zyx(*mount.nominal_rad)
    state = _initial_state(mount, planes, len(obs.pass_ids), _plane_centers(obs, mount, r_nom))
    sol = _information(obs, state, r_nom, estimate)
    formal = sol.Ninv[0:3, 0:3]
    realistic = formal if model.kind == "white" else propagated_covariance(sol, obs, model)
    s = np.sqrt(np.diag(formal))
    return {"formal": formal, "realistic": realistic, "correlation": formal / np.outer(s, s)}
