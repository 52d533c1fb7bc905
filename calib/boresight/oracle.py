"""The dense GLS oracle: the best linear estimate and the Cramér–Rao bound of a small problem.

For tests and benchmarks only (n ≤ :data:`MAX_POINTS`): the misclosures' full covariance

    C = Σ_c diag(B_c σ_c) · R_c · diag(B_c σ_c) + diag(B_range² σ_range² + B_scan² σ_scan²),
    R_c[i, j] = exp(−|t_i − t_j| / τ_c)

is formed as an n × n matrix from the exponential correlation of each POS channel — at the
trajectory's epochs, linearly interpolated to the points as the poses are (the simulator's
truth), or at the point times when there is no trajectory — and the plane conditions are solved
by iterated GLS, linearized at the adjusted scanner observations like :mod:`calib.boresight.gls`. ``(Aᵀ C⁻¹ A)⁻¹`` at the solution is the
Cramér–Rao bound of the unknowns for that model: the σ no unbiased estimator can beat.
``σ_range,i`` includes the beam footprint at the point's incidence when the observations carry
a beam divergence (:func:`calib.boresight.gls.range_sigma_m`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import cho_factor, cho_solve

from calib.boresight.errormodel import ErrorModel
from calib.boresight.gausshelmert import (
    Layout,
    _apply,
    initial_state,
    plane_centers,
    step_converged,
)
from calib.boresight.ghmodel import tangent_bases
from calib.boresight.gls import (
    channel_taus,
    design_matrix,
    linearize_adjusted,
    range_sigma_m,
    scanner_residuals,
)
from calib.boresight.observations import AdjustmentError, AdjustOptions, Observations
from calib.core import frames

MAX_POINTS = 6000


@dataclass
class OracleResult:
    boresight_rad: np.ndarray
    cov: np.ndarray  # (p, p) Cramér–Rao bound of all unknowns at the solution
    names: list[str]
    iterations: int

    @property
    def crlb_sigma_rad(self) -> np.ndarray:
        return np.sqrt(np.diag(self.cov[0:3, 0:3]))


def _knot_interpolation(obs: Observations) -> tuple[np.ndarray, np.ndarray]:
    """``W`` (n, K): the points' interpolation weights of the POS errors at K knots (the
    trajectory's epochs, or the points themselves without one), and the knots' |Δt| (K, K)."""
    t = obs.t_gps_s
    if obs.trajectory is None:
        W, tk = np.eye(t.size), t
    else:
        ep = obs.trajectory.t_gps_s
        k = np.clip(np.searchsorted(ep, t, side="right") - 1, 0, ep.size - 2)
        used, inv = np.unique(np.concatenate([k, k + 1]), return_inverse=True)
        w = (t - ep[k]) / (ep[k + 1] - ep[k])
        W = np.zeros((t.size, used.size))
        W[np.arange(t.size), inv[: t.size]] = 1.0 - w
        W[np.arange(t.size), inv[t.size :]] += w
        tk = ep[used]
    return W, np.abs(tk[:, None] - tk[None, :])


def misclosure_covariance(lin, obs: Observations, model: ErrorModel) -> np.ndarray:
    g = lin.B * obs.sigma_l
    C = np.diag((lin.B[:, 6] * range_sigma_m(lin, obs)) ** 2 + g[:, 7] ** 2)
    W, dt = _knot_interpolation(obs)
    for c, tau in enumerate(channel_taus(model)):
        R = W @ np.exp(-dt / tau) @ W.T
        C += np.outer(g[:, c], g[:, c]) * R
    return C


def pos_errors(lin, obs: Observations, model: ErrorModel, k: np.ndarray) -> np.ndarray:
    """(n, 6): the POS corrections' conditional mean given the correlates ``k = C⁻¹ e``:
    ``c_c = −σ_c ∘ R_c (B_c σ_c ∘ k)`` (the dense form of :func:`calib.boresight.gls.pos_errors`)."""
    g = lin.B * obs.sigma_l
    W, dt = _knot_interpolation(obs)
    out = np.empty((len(obs), 6))
    for c, tau in enumerate(channel_taus(model)):
        out[:, c] = -obs.sigma_l[:, c] * (W @ (np.exp(-dt / tau) @ (W.T @ (g[:, c] * k))))
    return out


def dense_gls(
    obs: Observations,
    mount,
    planes_init,
    model: ErrorModel,
    estimate: tuple[str, ...] = (),
    max_iterations: int = 20,
) -> OracleResult:
    """Iterated GLS with the dense covariance (see the module docstring)."""
    if len(obs) > MAX_POINTS:
        raise AdjustmentError(f"the dense oracle takes at most {MAX_POINTS} points, got {len(obs)}")
    if "pass_offsets" in estimate:
        raise AdjustmentError(
            "the dense oracle has no pass-offset prior; estimate the boresight, planes and extras"
        )
    options = AdjustOptions(estimate=estimate, max_iterations=max_iterations)
    r_nom = frames.rotation_zyx(*mount.nominal_rad)
    state = initial_state(mount, planes_init, len(obs.pass_ids), plane_centers(obs, mount, r_nom))
    layout = Layout(len(obs.plane_names), len(obs.pass_ids), estimate)
    est_latency = "latency" in layout.extras
    it = 0
    v = np.zeros((len(obs), 2))
    pos_c = None  # with cylinders, the POS errors' estimate (as the GLS does)
    for it in range(1, max_iterations + 1):
        bases = tangent_bases(state.normals)
        lin = linearize_adjusted(obs, state, r_nom, v, est_latency, bases, pos_correction=pos_c)
        A = design_matrix(lin, layout, obs).toarray()
        cf = cho_factor(misclosure_covariance(lin, obs, model))
        CiA = cho_solve(cf, A)
        N = A.T @ CiA
        dx = -np.linalg.solve(N, CiA.T @ lin.F)
        k = cho_solve(cf, lin.F + A @ dx)
        if state.cylinders is not None:
            pos_c = pos_errors(lin, obs, model, k)
        state = _apply(state, dx, layout, bases)
        v = scanner_residuals(
            lin, obs, k, np.zeros(len(obs.plane_names)), state.cylinder_rows(obs.plane_index)
        )
        if step_converged(dx, layout, options, N, it) and it > 1:
            break
    return OracleResult(
        state.boresight_rad.copy(), np.linalg.inv(N), layout.names(obs.plane_names, obs.pass_ids), it
    )
