"""The GLS boresight estimator: plane conditions with the POS errors as Gauss–Markov processes.

The thesis model weighs every point as if its POS errors were independent; they are not (they
drift with correlation times of tens of seconds), so within a pass they act as biases and a
white-weighted adjustment wastes most of the information. Here the POS error of each channel
is an unknown process on a knot grid (below) estimated jointly with the
boresight, the planes and the extras, with its exact AR(1) prior. Linearized at the adjusted
scanner observations (Gauss–Helmert, below)::

    F_i + A_i·dx + J_i·z + ε_i = 0,      z ~ N(0, P⁻¹),   ε_i ~ N(0, m_i)

``J_i`` carries ``B_ic·σ_ic`` times the bridge weights of channel c, ``m_i`` the range and
scan-angle noise, the bridge variance of the POS channels and the roughness of the point's
plane (a variance component estimated from the residuals at every iteration). The knots are
eliminated with a banded Cholesky factor (bandwidth 11) and the unknowns solved from the
Schur complement ``S = N_xx − N_xa N_aa⁻¹ N_ax`` (by blocks of knot rows: :mod:`.work.schur`):
time and memory O(n) in the points (O(K·p) in the K knots and p unknowns), never an n × n
matrix. ``S⁻¹`` is the covariance of the estimate under the model (the Cramér–Rao bound at the
solution): its formal σ is its realistic σ.

**Linearized at the adjusted range and scan angle, not the measured ones.** ``A_i`` depends on
the range: a yaw moves a point by its horizontal range times the angle. Evaluated at the
*measured* range, the range noise sits in both ``F_i`` and ``A_i``, and the estimating equation
``Σ w_i F_i A_i = 0`` has the expectation ``Σ w_i σ_ρ² B_ρ ∂B_ρ/∂b ≠ 0`` at the truth: the
solution leans towards the angle that makes the beams more grazing (the errors-in-variables
bias). On a line oblique to a wall, where a yaw shows only through the range's change along the
line, the mount watch's blocks came out 4–6σ wrong on a flat wall with no POS error at all,
as soon as the scanner had noise. So, as the thesis estimator does (:mod:`.gausshelmert`), each
iteration linearizes at ``l + v`` with the scanner residuals ``v = −Q B_scannerᵀ ε/m`` of the
previous one and the misclosure ``F(l + v) − B v`` (:func:`scanner_residuals`, each residual
within a few σ: far from the solution a misclosure is not the scanner's noise), and the
solution is not converged before a step has been taken from there. (Resetting ``v`` after a
large step, as the thesis estimator does, made the watch's blocks oscillate: the correction's
own step — 0.03° in yaw on a 45° line — counted as large.)

**The POS error processes on a knot grid** (the state-space half of the estimator).
Each POS channel c (north, east, down, roll, pitch, heading) carries an error
``a_c(t) = σ_c(t) · z_c(t)`` where ``σ_c(t)`` is the trajectory's own σ at t and ``z_c`` a unit
first-order Gauss–Markov (Ornstein–Uhlenbeck) process with correlation time ``τ_c``. The
unknowns are ``z_c`` at knots ``t_0 < t_1 < … < t_{K−1}``; the prior of the knot values is the
exact AR(1) chain, ``z_0 ~ N(0, 1)``, ``z_k | z_{k−1} ~ N(φ_k z_{k−1}, 1 − φ_k²)``: a tridiagonal
precision per channel, stored as one banded matrix over the six channels (index ``6·k + c``),
so that everything here is O(K) and the normal equations of the knots are banded (bandwidth 11:
a point touches two knots × six channels).

Where the knots come from:

- **the trajectory's epochs** (the usual case): the points' poses are linear interpolations of
  the trajectory, so their POS errors are exactly the same linear interpolation of the errors
  at the two epochs around them. The knots are the epochs that bracket a point; the model is
  exact, whatever the spacing.
- **a uniform grid** (no trajectory, or so many epochs that the knots would exceed
  :data:`MAX_KNOTS`): knots every ``min(τ)/100`` (or wider); between two knots the process is an
  OU bridge, ``z(t) = a·z_k + b·z_{k+1} + r(t)`` with ``a = φ₁(1 − φ₂²)/(1 − φ²)``,
  ``b = φ₂(1 − φ₁²)/(1 − φ²)`` and ``Var r = 1 − a·φ₁ − b·φ₂``; the bridge residual enters the
  estimator as white noise (an approximation: its correlation within one interval is neglected,
  which costs a little information, never adds any).

Knots cover only the time spans that hold points (a gap gets no knots of its own: the AR(1)
transition across it is exact), so passes separated by turns stay as correlated as the process
says.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import scipy.sparse as sp
from scipy.linalg.lapack import dpbtrf, dtbtrs

from calib.boresight.errormodel import ErrorModel
from calib.boresight.gausshelmert import (
    Layout,
    Solution,
    _apply,
    linearize_at_state,
    observations_at,
    offset_prior_sigma,
    pose_rates,
    singular_error,
    step_converged,
)
from calib.boresight.ghmodel import Linearization, State, linearize, tangent_bases
from calib.boresight.observability import ObservabilityError
from calib.boresight.observations import AdjustOptions, Observations
from calib.boresight.work.dense import CholeskyFactor
from calib.boresight.work.linearization import LinearizationBuffers
from calib.boresight.work.normals import (
    POINT_BLOCK,
    WRITE_BLOCK,
    GramPlan,
    KnotWeights,
    gls_row_values,
    knot_weights,
    layout_columns,
    white_misclosure,
    x_groups,
)
from calib.boresight.work.schur import DenseSchur, KnotSchur, knot_schur
from calib.boresight.work.sparse import design_matrix, knot_matrix

CHANNELS = 6
#: the knot normal equations have this lower bandwidth: two knots × six channels, minus one
BANDWIDTH = 2 * CHANNELS - 1
#: default knot spacing: the shortest correlation time over this
KNOTS_PER_TAU = 100.0
#: the spacing grows when the points span so long a time that more knots would be needed
MAX_KNOTS = 20000


@dataclass(frozen=True)
class KnotGrid:
    t_s: np.ndarray  # (K,) knot times, increasing
    exact: bool  # the knots are trajectory epochs and points interpolate them linearly
    spacing_s: float  # the median knot spacing within spans

    @property
    def n(self) -> int:
        return int(self.t_s.size)


def knot_grid(
    t_s: np.ndarray,
    tau_s: np.ndarray,
    epochs_s: np.ndarray | None = None,
    knots_per_tau: float = KNOTS_PER_TAU,
) -> KnotGrid:
    """The knots for points at ``t_s``: the trajectory ``epochs_s`` that bracket them when
    given and few enough, else a uniform grid (see the module docstring)."""
    ts = np.unique(np.asarray(t_s, float))
    if epochs_s is not None and epochs_s.size >= 2:
        ep = np.asarray(epochs_s, float)
        k = np.clip(np.searchsorted(ep, ts, side="right") - 1, 0, ep.size - 2)
        used = np.unique(np.concatenate([k, k + 1]))
        if used.size <= MAX_KNOTS:
            knots = ep[used]
            return KnotGrid(knots, True, float(np.median(np.diff(knots))))
    h = float(np.min(tau_s)) / knots_per_tau
    for _ in range(8):
        starts, ends = _spans(ts, h)
        count = int(np.sum(np.ceil((ends - starts) / h) + 1))
        if count <= MAX_KNOTS:
            break
        h *= count / MAX_KNOTS * 1.05
    starts, ends = _spans(ts, h)
    pieces = [a + h * np.arange(int(np.ceil((b - a) / h)) + 1) for a, b in zip(starts, ends, strict=False)]
    knots = np.concatenate(pieces)
    if knots.size < 2:  # every point at one instant
        knots = np.array([ts[0], ts[0] + h])
    return KnotGrid(knots, False, h)


def _spans(ts: np.ndarray, h: float) -> tuple[np.ndarray, np.ndarray]:
    gap = np.flatnonzero(np.diff(ts) > h)
    return ts[np.r_[0, gap + 1]], ts[np.r_[gap, ts.size - 1]]


@dataclass(frozen=True)
class Bridge:
    """Where each point sits between knots, per channel."""

    k: np.ndarray  # (n,) left knot
    a: np.ndarray  # (n, 6) weight of knot k
    b: np.ndarray  # (n, 6) weight of knot k + 1
    var: np.ndarray  # (n, 6) bridge variance (unit process); zero on exact knots


def bridge(grid: KnotGrid, t_s: np.ndarray, tau_s: np.ndarray) -> Bridge:
    """Linear interpolation weights on exact knots, else the OU bridge (module docstring)."""
    tk = grid.t_s
    k = np.clip(np.searchsorted(tk, t_s, side="right") - 1, 0, tk.size - 2)
    d1 = np.clip(t_s - tk[k], 0.0, None)[:, None]
    d2 = np.clip(tk[k + 1] - t_s, 0.0, None)[:, None]
    if grid.exact:
        w = np.broadcast_to(d1 / (d1 + d2), (t_s.size, CHANNELS))
        return Bridge(k, 1.0 - w, w.copy(), np.zeros((t_s.size, CHANNELS)))
    # once per distinct τ (channels that share one share their columns)
    taus, column = np.unique(np.asarray(tau_s, float), return_inverse=True)
    tau = taus[None, :]
    p1, p2 = np.exp(-d1 / tau), np.exp(-d2 / tau)
    den = -np.expm1(-2.0 * (d1 + d2) / tau)  # 1 − φ², accurate for short intervals
    a = p1 * -np.expm1(-2.0 * d2 / tau) / den
    b = p2 * -np.expm1(-2.0 * d1 / tau) / den
    var = np.clip(1.0 - a * p1 - b * p2, 0.0, None)
    return Bridge(k, a[:, column], b[:, column], var[:, column])


def prior_banded(grid: KnotGrid, tau_s: np.ndarray) -> np.ndarray:
    """The precision of the knot values in lower banded form ``(BANDWIDTH + 1, 6K)``
    (``ab[i − j, j] = P[i, j]``), for ``scipy.linalg.cholesky_banded(lower=True)``."""
    K = grid.n
    tau = np.asarray(tau_s, float)
    phi = np.exp(-np.diff(grid.t_s)[:, None] / tau[None, :])  # (K − 1, 6): transition k → k+1
    q = -np.expm1(-2.0 * np.diff(grid.t_s)[:, None] / tau[None, :])  # 1 − φ²
    diag = np.zeros((K, CHANNELS))
    diag[0] = 1.0
    diag[1:] += 1.0 / q
    diag[:-1] += phi**2 / q
    ab = np.zeros((BANDWIDTH + 1, CHANNELS * K))
    ab[0] = diag.reshape(-1)
    off = np.zeros((K, CHANNELS))
    off[:-1] = -phi / q  # P[6(k+1)+c, 6k+c], stored at column 6k + c
    ab[CHANNELS] = off.reshape(-1)
    return ab


def log_det_prior(grid: KnotGrid, tau_s: np.ndarray) -> float:
    """log det of the prior precision (the AR(1) chain: −Σ log(1 − φ_k²))."""
    q = -np.expm1(-2.0 * np.diff(grid.t_s)[:, None] / np.asarray(tau_s, float)[None, :])
    return float(-np.sum(np.log(q)))


def channel_taus(model: ErrorModel) -> np.ndarray:
    """(6,) correlation times of the POS channels (north, east, down, roll, pitch, heading)."""
    return np.array([model.tau_s(c) for c in range(CHANNELS)], float)


@dataclass
class GlsSolution(Solution):
    z: np.ndarray  # (6K,) estimated unit POS error processes at the knots
    grid: KnotGrid
    plane_var_m2: np.ndarray  # (m,) roughness variance of each plane used
    neg2_log_lik: float  # −2 log of the restricted likelihood (up to a constant), for τ
    system: _System  # the last iteration's normal equations (the group tests reuse them)


@dataclass
class _Frame:
    """What does not change between iterations: the knots, the bridge, the prior."""

    grid: KnotGrid
    br: Bridge
    prior: np.ndarray
    log_det_prior: float


def frame_for(obs: Observations, model: ErrorModel, knots_per_tau: float) -> _Frame:
    tau = channel_taus(model)
    epochs = obs.trajectory.t_gps_s if obs.trajectory is not None else None
    grid = knot_grid(obs.t_gps_s, tau, epochs, knots_per_tau)
    return _Frame(grid, bridge(grid, obs.t_gps_s, tau), prior_banded(grid, tau), log_det_prior(grid, tau))


#: a scanner residual of the Gauss–Helmert linearization is clipped to this many σ
MAX_RESIDUAL_SIGMA = 5.0

#: the footprint term is capped at this incidence (tan 89° ≈ 57)
COS_GRAZING = float(np.cos(np.radians(89.0)))


def range_sigma_m(lin, obs: Observations) -> np.ndarray:
    """Each point's range σ: the observations' (constant and range-proportional parts) plus the
    beam footprint on a surface at incidence θ, ρ·(divergence/2)·tan θ (``|B_range|`` is cos θ:
    the plane normal against the unit beam direction); θ is capped at 89°."""
    return _range_sigma_rows(lin.B[:, 6], obs.sigma_l[:, 6], obs.l[:, 6], obs.beam_half_divergence_rad)


def _range_sigma_rows(b_range, sigma_range_m, range_m, beam_half_divergence_rad: float) -> np.ndarray:
    if beam_half_divergence_rad == 0.0:
        return sigma_range_m
    c = np.clip(np.abs(b_range), COS_GRAZING, 1.0)
    return sigma_range_m + range_m * beam_half_divergence_rad * np.sqrt(1.0 - c * c) / c


def white_variance(
    lin, obs: Observations, fr: _Frame, plane_var_m2: np.ndarray, out: np.ndarray | None = None
) -> np.ndarray:
    """m_i: range and scan-angle noise, the POS bridge variance and the plane's roughness
    (in blocks of points, into ``out`` when given)."""
    n = len(obs)
    out = np.empty(n) if out is None else out
    has_bridge = bool(np.any(fr.br.var))
    for lo in range(0, n, POINT_BLOCK):
        sl = slice(lo, min(lo + POINT_BLOCK, n))
        out[sl] = _white_variance_rows(lin, obs, fr, plane_var_m2, sl, has_bridge)
    return out


def _white_variance_rows(lin, obs: Observations, fr: _Frame, plane_var_m2, sl: slice, has_bridge: bool):
    """:func:`white_variance` of the points in ``sl`` (``has_bridge``: any bridge variance)."""
    B, sig = lin.B[sl], obs.sigma_l[sl]
    rs = _range_sigma_rows(B[:, 6], sig[:, 6], obs.l[sl, 6], obs.beam_half_divergence_rad)
    m = (B[:, 6] * rs) ** 2 + (B[:, 7] * sig[:, 7]) ** 2
    if has_bridge:
        m += np.einsum("ij,ij->i", (B[:, :CHANNELS] * sig[:, :CHANNELS]) ** 2, fr.br.var[sl])
    return m + plane_var_m2[obs.plane_index[sl]]


def _write_rows(work: _Work, lin, layout: Layout, obs: Observations, fr: _Frame, plane_var_m2) -> np.ndarray:
    """Each point's white variance (into ``work.m``, returned) and its weighted row into the
    plan's buffer (the rows in smaller blocks: a block of rows stays in L2)."""
    n = len(obs)
    m = white_variance(lin, obs, fr, plane_var_m2, out=work.m)
    for lo in range(0, n, WRITE_BLOCK):
        sl = slice(lo, min(lo + WRITE_BLOCK, n))
        work.plan.write_rows(lo, sl.stop, gls_row_values(lin, layout, work.knots, sl), 1.0 / np.sqrt(m[sl]))
    return m


def scanner_residuals(lin, obs: Observations, k: np.ndarray, plane_var_m2: np.ndarray, cylinder_rows=None):
    """v (n, 2): the range and scan-angle residuals of the Gauss–Helmert adjustment for the
    correlates ``k`` (``C⁻¹`` times the misclosures after the fit: ``ε/m`` here), ``−Q Bᵀ k``.
    The range's ``Q`` holds the plane's roughness as well, at ``σ²/cos²θ`` (incidence θ): a
    surface standing off its plane by s moves the return along the beam by s/cos θ, exactly as
    range noise does, and biases the angles the same way (the foreign bundles' wavy walls: yaw
    0.25° → 0.08° on a 45° line). Each residual is kept within ±:data:`MAX_RESIDUAL_SIGMA` of
    its σ: far from the solution, or at an outlier, a misclosure is not noise and must not move
    the linearization far. The points of ``cylinder_rows`` (on piles) keep v = 0: linearized
    at the adjusted points the iteration could cycle (docs/architecture.md §7.3)."""
    n = len(obs)
    out = np.empty((n, 2))
    for lo in range(0, n, POINT_BLOCK):
        sl = slice(lo, min(lo + POINT_BLOCK, n))
        B = lin.B[sl]
        cos_incidence = np.clip(np.abs(B[:, 6]), COS_GRAZING, 1.0)
        rs = _range_sigma_rows(B[:, 6], obs.sigma_l[sl, 6], obs.l[sl, 6], obs.beam_half_divergence_rad)
        q_range = rs**2 + plane_var_m2[obs.plane_index[sl]] / cos_incidence**2
        sigma = np.stack([np.sqrt(q_range), obs.sigma_l[sl, 7]], axis=1)
        v = -(sigma**2) * B[:, 6:8] * k[sl, None]
        np.clip(v, -MAX_RESIDUAL_SIGMA * sigma, MAX_RESIDUAL_SIGMA * sigma, out=out[sl])
    if cylinder_rows is not None:
        out[cylinder_rows] = 0.0
    return out


def linearize_adjusted(
    obs: Observations,
    state: State,
    r_nom,
    v: np.ndarray,
    latency: bool,
    bases,
    buffers: LinearizationBuffers | None = None,
    pos_correction: np.ndarray | None = None,
):
    """The linearization at the observations with the scanner residuals ``v`` (n, 2) added,
    its misclosure ``F(l + v) − B v`` (module docstring); into ``buffers`` when given.
    ``pos_correction`` (n, 6): the POS errors' estimate to add to the poses as well (cylinders:
    below)."""
    l_at = observations_at(obs, state, latency)
    if pos_correction is not None:
        l_at = l_at.copy()
        l_at[:, :CHANNELS] += pos_correction
    rates = pose_rates(obs.latency_trajectory(), obs.t_gps_s + state.latency_s) if latency else None
    if buffers is None:
        l_obs = l_at.copy()
        l_obs[:, 6:8] += v
        lin = linearize(state, r_nom, obs.plane_index, obs.pass_index, l_obs, rates, bases)
    else:
        buffers.observations(l_at, v)
        lin = buffers.linearize(state, r_nom, obs.plane_index, obs.pass_index, rates, bases)
    for lo in range(0, len(obs), POINT_BLOCK):  # in blocks: no full-size temporaries
        sl = slice(lo, min(lo + POINT_BLOCK, len(obs)))
        lin.F[sl] -= lin.B[sl, 6] * v[sl, 0] + lin.B[sl, 7] * v[sl, 1]
        if pos_correction is not None:
            lin.F[sl] -= np.einsum("ij,ij->i", lin.B[sl, :CHANNELS], pos_correction[sl])
    return lin


def pos_errors(knots: KnotWeights, z: np.ndarray) -> np.ndarray:
    """(n, 6): each point's POS correction ``c = σ_c (a_c z_k,c + b_c z_k+1,c)`` from the knot
    values ``z`` (``J z = B c``: ``F(l) + J z ≈ F(l + c)``). With cylinders the iterations
    linearize at the poses corrected by it: a cylinder's gradient is the radial unit vector at
    the point, which a POS position error moves (docs/architecture.md §7.4b)."""
    zk = z.reshape(-1, CHANNELS)
    return knots.sa * zk[knots.k] + knots.sb * zk[knots.k + 1]


@dataclass
class _Work:
    """What one solution reuses across its iterations: the sorted, chunked layout of the
    points and its buffers (:class:`GramPlan`), the knot weights ``σ·a`` and ``σ·b``, the
    knots' Schur complement (:func:`knot_schur`: by blocks, or dense) and the buffers of the white
    variances and the misclosures."""

    plan: GramPlan
    knots: KnotWeights
    schur: KnotSchur | DenseSchur
    m: np.ndarray  # (n,) white variance, rewritten every iteration
    e: np.ndarray  # (n,) the white misclosures after the step
    k: np.ndarray  # (n,) their correlates e / m


def work_for(obs: Observations, layout: Layout, fr: _Frame) -> _Work:
    columns, n_groups = layout_columns(layout, len(obs.pass_ids))
    plan = GramPlan(x_groups(obs, layout), fr.br.k, fr.grid.n, columns, n_groups)
    schur = knot_schur(plan.cross_at, CHANNELS * fr.grid.n, layout.n, BANDWIDTH)
    n = len(obs)
    return _Work(plan, knot_weights(obs.sigma_l, fr.br), schur, np.empty(n), np.empty(n), np.empty(n))


@dataclass
class _System:
    S: np.ndarray  # Schur complement (p × p), offset prior included
    r: np.ndarray  # its right-hand side (S dx = −r)
    chol: np.ndarray  # L in lower banded form, N_aa = L Lᵀ
    m: np.ndarray
    schur: KnotSchur | DenseSchur  # N_ax reduced (the work's: overwritten by the next iteration)
    _lin: Linearization
    _layout: Layout
    _obs: Observations
    _fr: _Frame

    @cached_property
    def W(self) -> np.ndarray:
        """L⁻¹ N_ax (6K × p), made when asked (the group tests)."""
        return self.schur.W(self.chol)

    @cached_property
    def A(self) -> sp.csr_matrix:
        """The design matrix (n × p), built when asked (the group tests)."""
        return design_matrix(self._lin, self._layout, self._obs)

    @cached_property
    def J(self) -> sp.csr_matrix:
        """The knot matrix (n × 6K), built when asked (the group tests)."""
        return knot_matrix(self._lin, self._obs, self._fr)


def assemble(
    lin,
    layout,
    obs,
    fr: _Frame,
    plane_var_m2,
    state: State,
    prior_sigma,
    boresight_prior=None,
    work: _Work | None = None,
) -> _System:
    """The normal equations of one iteration reduced to the unknowns (the Schur complement over
    the knots), in the work arrays of ``work`` (made here when not given)."""
    work = work if work is not None else work_for(obs, layout, fr)
    m = _write_rows(work, lin, layout, obs, fr, plane_var_m2)
    nb = work.plan.normals(dense_cross=False)  # N_ax's entries only: work.schur places them
    nb.ab += fr.prior
    if not np.all(np.isfinite(nb.ab)):  # as cholesky_banded checks
        raise ValueError("array must not contain infs or NaNs")
    chol, info = dpbtrf(nb.ab, lower=1, overwrite_ab=1)  # what cholesky_banded calls
    if info != 0:
        raise ObservabilityError("the POS error processes are not determined (knot normal matrix singular)")
    # S = N_xx − N_xa N_aa⁻¹ N_ax, r = g_x − N_xa N_aa⁻¹ g_a (work.schur: by blocks of knot rows)
    gram, wv = work.schur.reduce(chol, nb.cross, nb.g_a)
    S = nb.N_xx - gram
    S = 0.5 * (S + S.T)
    r = nb.g_x - wv
    if prior_sigma is not None:
        wt = 1.0 / prior_sigma.reshape(-1) ** 2
        idx = np.arange(layout.i_offset, layout.n)
        S[idx, idx] += wt
        r[idx] += wt * state.pass_offsets_m.reshape(-1)
    if boresight_prior is not None:  # (mean, σ): ½ Σ ((b − mean)/σ)² joins the objective
        wt = 1.0 / boresight_prior[1] ** 2
        S[0:3, 0:3] += np.diag(wt)
        r[0:3] += wt * (state.boresight_rad - boresight_prior[0])
    return _System(S, r, chol, m, work.schur, lin, layout, obs, fr)


def _tb_solve(chol: np.ndarray, b: np.ndarray) -> np.ndarray:
    """L⁻¹ b for L in lower banded form (LAPACK dtbtrs)."""
    x, info = dtbtrs(chol, b, uplo="L")
    if info != 0:
        raise ObservabilityError("the POS error processes are not determined (singular knot factor)")
    return x


def knots_from_step(sys: _System, dx: np.ndarray) -> np.ndarray:
    """The knot values after the step dx: z = −N_aa⁻¹ (g_a + N_ax dx) = −L⁻ᵀ L⁻¹ (g_a + N_ax dx)."""
    return sys.schur.knots(sys.chol, dx)


def solve_gls(
    obs: Observations,
    state: State,
    r_nom: np.ndarray,
    options: AdjustOptions,
    model: ErrorModel,
    plane_var_m2: np.ndarray | None = None,
    fr: _Frame | None = None,
    rough_planes: np.ndarray | None = None,
    first_lin: Linearization | None = None,
) -> GlsSolution:
    """The iterated GLS solution from ``state`` (linearized at the observations each time).

    ``rough_planes``: planes whose roughness variance is re-estimated from the residuals at
    every iteration (:func:`roughness_update`) until the steps and the variances settle.
    ``first_lin``: the linearization at ``state`` and the observations, when the caller has
    made it already (the first iteration's; without latency estimated)."""
    layout = Layout(len(obs.plane_names), len(obs.pass_ids), options.estimate)
    est_latency = "latency" in layout.extras
    fr = fr if fr is not None else frame_for(obs, model, options.knots_per_tau)
    pv = np.zeros(len(obs.plane_names)) if plane_var_m2 is None else np.asarray(plane_var_m2, float).copy()
    rough = np.zeros(0, int) if rough_planes is None else np.asarray(rough_planes, int)
    prior_sigma = offset_prior_sigma(obs, options) if layout.offsets else None
    bs_prior = None if options.boresight_prior_rad is None else np.asarray(options.boresight_prior_rad, float)
    converged, it = False, 0
    v = np.zeros((len(obs), 2))  # the scanner residuals (range, scan angle)
    pos_c = None  # the POS errors' estimate, with cylinders (:func:`pos_errors`)
    work = work_for(obs, layout, fr)
    # the caller's first linearization becomes the buffers of the next ones (it is not kept)
    buffers = LinearizationBuffers(len(obs), layout.extras, layout.offsets, first_lin)
    for it in range(1, options.max_iterations + 1):
        bases = tangent_bases(state.normals)
        if it == 1 and first_lin is not None:
            lin = first_lin
        else:
            lin = linearize_adjusted(obs, state, r_nom, v, est_latency, bases, buffers, pos_c)
        sys = assemble(lin, layout, obs, fr, pv, state, prior_sigma, bs_prior, work)
        fac = _factor(sys.S, obs, layout)
        dx = fac.solve(-sys.r)
        z = knots_from_step(sys, dx)
        # the white part of each misclosure after the fit: F + A dx + J z
        e = white_misclosure(work.plan, sys.m, dx, z, out=work.e)
        state = _apply(state, dx, layout, bases)
        k = np.divide(e, sys.m, out=work.k)
        v = scanner_residuals(lin, obs, k, pv, state.cylinder_rows(obs.plane_index))
        if state.cylinders is not None:
            pos_c = pos_errors(work.knots, z)
        settled = True
        new = pv
        if rough.size and it < options.max_iterations:
            new = roughness_update(e, sys.m, pv, obs.plane_index, rough)
            settled = bool(np.all(np.abs(new - pv) <= VC_TOL * (np.maximum(new, pv) + 1e-12)))
        if step_converged(dx, layout, options, sys.S, it, fac.inverse) and settled and it > 1:
            converged = True
            break
        pv = new
    zPz = _quad_banded(fr.prior, z)
    ePe = float(np.sum(e**2 / sys.m))
    vtpv = ePe + zPz
    df = len(obs) - layout.n - rough.size
    if prior_sigma is not None:
        o = state.pass_offsets_m.reshape(-1)
        vtpv += float(np.sum(o**2 / prior_sigma.reshape(-1) ** 2))
        df += 3 * len(obs.pass_ids)
    if bs_prior is not None:
        vtpv += float(np.sum(((state.boresight_rad - bs_prior[0]) / bs_prior[1]) ** 2))
        df += 3
    log_det_naa = 2.0 * float(np.sum(np.log(sys.chol[0])))
    neg2 = vtpv + log_det_naa - fr.log_det_prior + float(np.sum(np.log(sys.m))) + fac.log_det
    return GlsSolution(
        state, sys.S, fac.inverse(), lin, sys.m, e, vtpv, df, it, converged, layout, z, fr.grid, pv, neg2, sys
    )


def _factor(S: np.ndarray, obs: Observations, layout: Layout) -> CholeskyFactor:
    """The Cholesky factor of the reduced normal matrix; a singular one is an observability
    error naming the cause (as :func:`calib.boresight.gausshelmert.solve_normal` says it)."""
    try:
        return CholeskyFactor(S)
    except np.linalg.LinAlgError:
        raise singular_error(S, obs, layout) from None


def _quad_banded(ab: np.ndarray, z: np.ndarray) -> float:
    """zᵀ P z for P in lower banded form."""
    out = float(np.sum(ab[0] * z * z))
    for d in range(1, ab.shape[0]):
        out += 2.0 * float(np.sum(ab[d, :-d] * z[d:] * z[:-d]))
    return out


#: the roughness variances have settled when none changes by more than this fraction
VC_TOL = 0.05


def roughness_update(e, m, pv, plane_index, planes) -> np.ndarray:
    """New roughness variances of ``planes`` (indices) from the white residuals ``e`` (with
    variances ``m``, which hold the current ``pv``): the mean squared residual beyond what the
    model explains without the roughness, with the plane's own three unknowns taken out of its
    degrees of freedom (a simplified Helmert variance-component estimate)."""
    out = pv.copy()
    n = np.bincount(plane_index, minlength=pv.size)
    e2 = np.bincount(plane_index, e * e, minlength=pv.size)
    base = np.bincount(plane_index, m, minlength=pv.size) - n * pv
    j = np.asarray(planes, int)
    j = j[n[j] > 3]  # every plane at once
    out[j] = np.maximum(0.0, e2[j] / (n[j] - 3) - base[j] / n[j])
    return out


def gls_information(obs: Observations, state: State, r_nom, estimate, model: ErrorModel, knots_per_tau=None):
    """The GLS normal matrix (Schur complement over the POS processes) at ``state`` without
    solving: ``(S, S⁻¹, layout)``, for predictions and the observability judgement."""
    options = AdjustOptions(estimate=tuple(estimate))
    layout = Layout(len(obs.plane_names), len(obs.pass_ids), options.estimate)
    fr = frame_for(obs, model, knots_per_tau or options.knots_per_tau)
    lin = linearize_at_state(obs, state, r_nom, layout)
    prior_sigma = offset_prior_sigma(obs, options) if layout.offsets else None
    sys = assemble(lin, layout, obs, fr, np.zeros(len(obs.plane_names)), state, prior_sigma)
    try:
        Sinv = np.linalg.inv(sys.S)
    except np.linalg.LinAlgError:
        Sinv = np.linalg.pinv(sys.S)
    return sys.S, Sinv, layout
