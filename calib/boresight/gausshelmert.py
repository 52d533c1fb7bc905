"""One iterated Gauss–Helmert solution of the plane-based boresight adjustment, docs/architecture.md §7.

One condition per point, ``F_i = n_jᵀ x_i(l_i, unknowns) + d_j = 0`` (see :mod:`calib.boresight.ghmodel`),
eight observations per point with their own sigmas (position, attitude, range, scan angle).
Because each point has one condition, ``M_i = B_i Q_i B_iᵀ`` is a scalar and the normal
equations assemble in O(n): never a dense n × n or 8n × 8n matrix.

The solution is the iterated Gauss–Helmert model with the linearization at the adjusted
observations (``w = F(l̂) + B (l − l̂)``), unit normals kept exactly unit by a minimal
(tangent-space) parameterization, optional extra unknowns and per-pass trajectory translations
with a prior from the trajectory's σ.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np

from calib.boresight.ghmodel import EXTRA_NAMES, Linearization, State, georeferenced, linearize, tangent_bases
from calib.boresight.observability import ANGLE_NAMES, SingularError
from calib.boresight.observations import AdjustOptions, Observations
from calib.core import frames
from calib.core.geometry import VerticalCylinder
from calib.core.trajectory import Trajectory

#: Boresight steps above this linearize at the observations (see solve).
_FAR_RAD = 1e-4


# ---------------------------------------------------------------------------------------------
# Parameter layout
# ---------------------------------------------------------------------------------------------


class Layout:
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


def _design_rows(lin, layout: Layout, plane_index, pass_index, sl) -> np.ndarray:
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


def normal_equations(lin, layout, obs, w, M):
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
    dp = dx[layout.i_plane : layout.i_offset].reshape(-1, 3)[obs.plane_index]
    out += np.einsum("ij,ij->i", lin.A_plane, dp)
    if layout.offsets:
        do = dx[layout.i_offset :].reshape(-1, 3)[obs.pass_index]
        out += np.einsum("ij,ij->i", lin.A_offset, do)
    return out


def leverage(sol: Solution, obs: Observations) -> np.ndarray:
    """A_i N⁻¹ A_iᵀ for every point (chunked; O(n·u²))."""
    out = np.empty(len(obs))
    for lo in range(0, len(obs), _CHUNK):
        sl = slice(lo, min(lo + _CHUNK, len(obs)))
        A = _design_rows(sol.lin, sol.layout, obs.plane_index, obs.pass_index, sl)
        out[sl] = np.einsum("ij,ij->i", A @ sol.Ninv, A)
    return out


# ---------------------------------------------------------------------------------------------
# Solver
# ---------------------------------------------------------------------------------------------


def pose_rates(traj: Trajectory, t: np.ndarray, h: float = 0.005) -> tuple[np.ndarray, np.ndarray]:
    """Velocity (LGF) and body angular rate at times t, by central differences."""
    lo = np.maximum(t - h, traj.t_gps_s[0])
    hi = np.minimum(t + h, traj.t_gps_s[-1])
    a, b = traj.interpolate(lo), traj.interpolate(hi)
    dt = (hi - lo)[:, None]
    vel = (b.p_lgf_m - a.p_lgf_m) / dt
    rel = np.einsum("nji,njk->nik", a.r_b_n, b.r_b_n)
    omega = frames.vector_from_rotation(rel) / dt
    return vel, omega


def initial_state(mount, planes_init, n_passes, centers=None) -> State:
    """``planes_init``: per feature a plane (normal, d) in the LGF or a
    :class:`~calib.core.geometry.VerticalCylinder`; ``centers`` the features' reference points
    near their points (default: a plane's foot of the perpendicular from the LGF origin, a
    cylinder's own centre; a cylinder's is moved along its axis to the given point's height)."""
    cylinders = np.array([isinstance(f, VerticalCylinder) for f in planes_init], bool)
    normals = np.array([_feature_normal(f) for f in planes_init]).reshape(-1, 3)
    d_lgf = np.array(
        [0.0 if isinstance(f, VerticalCylinder) else float(f[1]) / np.linalg.norm(f[0]) for f in planes_init]
    )
    if centers is None:
        centers = -d_lgf[:, None] * normals
    centers = np.asarray(centers, float).copy()
    d_rel = d_lgf + np.einsum("ij,ij->i", normals, centers)
    for j in np.flatnonzero(cylinders):
        cyl = planes_init[j]
        centers[j, :2] = cyl.center_m[:2]
        d_rel[j] = -float(cyl.radius_m)
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
        cylinders=cylinders if cylinders.any() else None,
    )


def _feature_normal(feature) -> np.ndarray:
    """A plane's unit normal, a vertical cylinder's axis (down: the LGF's z)."""
    if isinstance(feature, VerticalCylinder):
        return np.array([0.0, 0.0, 1.0])
    n = np.asarray(feature[0], float)
    return n / np.linalg.norm(n)


def plane_centers(obs: Observations, mount, r_nom) -> np.ndarray:
    """Centroid of each plane's points georeferenced with the a-priori mount."""
    _, x_lgf_m = georeferenced(
        initial_state(mount, [(np.array([0.0, 0.0, 1.0]), 0.0)] * len(obs.plane_names), len(obs.pass_ids)),
        r_nom,
        obs.plane_index,
        obs.pass_index,
        obs.l,
    )
    cnt = np.bincount(obs.plane_index, minlength=len(obs.plane_names))[:, None]
    sums = np.stack(
        [np.bincount(obs.plane_index, x_lgf_m[:, c], minlength=len(obs.plane_names)) for c in range(3)], 1
    )
    return sums / np.maximum(cnt, 1)


def _apply(state: State, dx: np.ndarray, layout: Layout, bases) -> State:
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
    dp = dx[layout.i_plane : layout.i_offset].reshape(-1, 3)
    tangent_step = np.einsum("mij,mj->mi", bases, dp[:, 0:2])
    if s.cylinders is not None:  # a cylinder's axis moves, its direction stays
        s.centers_m = s.centers_m + np.where(s.cylinders[:, None], tangent_step, 0.0)
        tangent_step[s.cylinders] = 0.0
    n_new = s.normals + tangent_step
    s.normals = n_new / np.linalg.norm(n_new, axis=1, keepdims=True)
    s.d_m = s.d_m + dp[:, 2]
    if layout.offsets:
        s.pass_offsets_m = s.pass_offsets_m + dx[layout.i_offset :].reshape(-1, 3)
    return s


@dataclass
class Solution:
    state: State
    N: np.ndarray
    Ninv: np.ndarray
    lin: Linearization
    M: np.ndarray
    e: np.ndarray  # adjusted misclosure A·dx + w per point (its square / M is vᵀPv)
    vtpv: float
    df: int
    iterations: int
    converged: bool
    layout: Layout


def offset_prior_sigma(obs: Observations, options: AdjustOptions) -> np.ndarray:
    """(K, 3) prior σ of the per-pass translations: the mean position σ of each pass."""
    if options.pass_offset_sigma_m is not None:
        return np.broadcast_to(np.asarray(options.pass_offset_sigma_m, float), (len(obs.pass_ids), 3))
    out = np.empty((len(obs.pass_ids), 3))
    for k in range(len(obs.pass_ids)):
        out[k] = obs.sigma_l[obs.pass_index == k, 0:3].mean(axis=0)
    return out


def linearize_at_state(obs: Observations, state: State, r_nom: np.ndarray, layout: Layout) -> Linearization:
    """One linearization at ``state`` and the observations as given (predictions, judgements)."""
    rates = (
        pose_rates(obs.latency_trajectory(), obs.t_gps_s + state.latency_s)
        if "latency" in layout.extras
        else None
    )
    bases = tangent_bases(state.normals)
    return linearize(state, r_nom, obs.plane_index, obs.pass_index, obs.l, rates, bases)


def observations_at(obs: Observations, state: State, estimate_latency: bool) -> np.ndarray:
    """The observation vector; with latency estimated the poses move with Δt."""
    if not estimate_latency or state.latency_s == 0.0:
        return obs.l
    poses = obs.latency_trajectory().interpolate(obs.t_gps_s + state.latency_s)
    l = obs.l.copy()
    l[:, 0:3] = poses.p_lgf_m
    l[:, 3:6] = poses.rpy_rad
    return l


def solve(obs: Observations, state: State, r_nom: np.ndarray, options: AdjustOptions) -> Solution:
    layout = Layout(len(obs.plane_names), len(obs.pass_ids), options.estimate)
    est_latency = "latency" in layout.extras
    Q = obs.sigma_l**2
    prior_sigma = offset_prior_sigma(obs, options) if layout.offsets else None
    v = np.zeros_like(obs.l)  # residuals of the observations
    converged = False
    it = 0
    rates = None
    for it in range(1, options.max_iterations + 1):
        l_obs = observations_at(obs, state, est_latency)
        l0 = l_obs + v
        if est_latency:
            rates = pose_rates(obs.latency_trajectory(), obs.t_gps_s + state.latency_s)
        bases = tangent_bases(state.normals)
        lin = linearize(state, r_nom, obs.plane_index, obs.pass_index, l0, rates, bases)
        w = lin.F - np.einsum("ij,ij->i", lin.B, v)
        M = np.einsum("ij,ij->i", lin.B**2, Q)
        N, g = normal_equations(lin, layout, obs, w, M)
        if prior_sigma is not None:  # layout.offsets
            o = state.pass_offsets_m.reshape(-1)
            wt = 1.0 / prior_sigma.reshape(-1) ** 2
            idx = np.arange(layout.i_offset, layout.n)
            N[idx, idx] += wt
            g[idx] += wt * o
        dx = solve_normal(N, -g, obs, layout)
        e = _a_times(lin, layout, obs, dx) + w
        k = e / M
        v = -Q * lin.B * k[:, None]
        state = _apply(state, dx, layout, bases)
        angle_step = np.max(np.abs(dx[0:3]))
        if angle_step > _FAR_RAD:
            # far from the solution the residuals of a linear step are not residuals of the
            # solution: keep linearizing at the observations until the boresight settles
            v[:] = 0.0
        if step_converged(dx, layout, options, N, it):
            converged = True
            break
    vtpv = float(np.sum(v**2 / Q))
    df = len(obs) - layout.n
    if prior_sigma is not None:  # layout.offsets
        o = state.pass_offsets_m.reshape(-1)
        vtpv += float(np.sum(o**2 / prior_sigma.reshape(-1) ** 2))
        df += 3 * len(obs.pass_ids)
    Ninv = np.linalg.inv(N)
    return Solution(state, N, Ninv, lin, M, e, vtpv, df, it, converged, layout)


def step_converged(
    dx: np.ndarray,
    layout: Layout,
    options: AdjustOptions,
    N: np.ndarray,
    it: int,
    inverse: Callable[[], np.ndarray] | None = None,
) -> bool:
    """Every step below the absolute tolerances, or (after the first iteration) below
    ``options.rel_tol`` of its formal σ from the normal matrix ``N`` (``inverse``: gives
    ``N⁻¹`` when the caller has a cheaper way than inverting ``N``)."""
    plane_steps = dx[layout.i_plane : layout.i_offset].reshape(-1, 3)
    metric_step = float(np.max(np.abs(plane_steps[:, 2])))
    angle_step = max(float(np.max(np.abs(dx[0:3]))), float(np.max(np.abs(plane_steps[:, 0:2]))))
    for i, name in enumerate(layout.extras):
        step = abs(dx[layout.i_extra + i])
        if name == "scan_angle_offset":
            angle_step = max(angle_step, step)
        elif name == "latency":
            metric_step = max(metric_step, step * 10.0)  # ~10 m/s: seconds → metres
        else:
            metric_step = max(metric_step, step)
    if layout.offsets:
        metric_step = max(metric_step, float(np.max(np.abs(dx[layout.i_offset :]))))
    if angle_step < options.tol_angle_rad and metric_step < options.tol_m:
        return True
    if options.rel_tol > 0 and it > 1:
        # steps that no longer matter against the unknowns' own σ (noisy data converge only
        # linearly in the last digits: see the iteration scheme above)
        sd = np.sqrt(np.diag(np.linalg.inv(N) if inverse is None else inverse()))
        return bool(np.all(np.abs(dx) <= options.rel_tol * sd))
    return False


def solve_normal(N, rhs, obs, layout):
    """Solve N dx = rhs; a singular N is an observability error naming the cause."""
    try:
        c = np.linalg.cholesky(N)
    except np.linalg.LinAlgError:
        raise singular_error(N, obs, layout) from None
    y = np.linalg.solve(c, rhs)
    return np.linalg.solve(c.T, y)


def singular_error(N, obs, layout) -> SingularError:
    """The error of a singular normal matrix, naming its null direction's largest unknowns."""
    names = layout.names(obs.plane_names, obs.pass_ids)
    vals, vecs = np.linalg.eigh(N)
    v = vecs[:, 0]
    top = [int(i) for i in np.argsort(-np.abs(v))[:3] if abs(v[i]) > 0.1]
    combo = " + ".join(f"{v[i]:.2f}·{names[i]}" for i in top)
    return SingularError(
        f"the normal equations are singular: the data do not determine {combo}. "
        f"Check that every plane has points from several passes and that extra unknowns "
        f"({', '.join(layout.extras) or 'none'}) are observable with this geometry.",
        tuple(names[i] for i in top),
    )
