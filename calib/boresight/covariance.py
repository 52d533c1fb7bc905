"""The covariance of the boresight beyond one solution: realistic σ, and σ predicted without adjusting.

- formal: ``Q_xx = N⁻¹`` (σ0 = 1), from the normal matrix of a solution;
- realistic: POS errors are correlated in time, so within a pass they act nearly as biases.
  :func:`propagated_covariance` propagates the observation errors through the estimator with a
  first-order Gauss–Markov correlation of the POS channels (σ from the trajectory, correlation
  time from the site or the caller), ``Cov = N⁻¹ (Σ_ij g_i g_jᵀ ρ(t_i − t_j)) N⁻¹`` — evaluated
  in O(n) with decayed cumulative sums (:mod:`calib.boresight.errormodel`);
- :func:`predict_covariance`: the covariance an estimator would give for a geometry (e.g.
  hypothetical passes and targets) from one linearization at the truth, for the site design and
  the operator guidance: the GLS estimator's (:mod:`calib.boresight.gls`, the calibration's
  default; its covariance is its realistic one and the Cramér–Rao bound of the Gauss–Markov
  model) or the thesis estimator's (white weights; realistic σ by propagation).
"""

from __future__ import annotations

import numpy as np

from calib.boresight.errormodel import ErrorModel, correlated_sum
from calib.boresight.gausshelmert import (
    Layout,
    Solution,
    initial_state,
    linearize_at_state,
    normal_equations,
    offset_prior_sigma,
    plane_centers,
)
from calib.boresight.ghmodel import State
from calib.boresight.gls import gls_information
from calib.boresight.observations import AdjustmentError, AdjustOptions, Observations
from calib.core import frames


def _rows_of_inverse(lin, layout, obs, Ninv_rows, M) -> np.ndarray:
    """(n, r) = (Ninv_rows · A_iᵀ) / M_i for every point, without forming A."""
    r = Ninv_rows.shape[0]
    out = lin.A_boresight @ Ninv_rows[:, 0:3].T
    for i, name in enumerate(layout.extras):
        out += lin.A_extra[name][:, None] * Ninv_rows[:, layout.i_extra + i][None, :]
    P = Ninv_rows[:, layout.i_plane : layout.i_offset].T.reshape(-1, 3, r)  # (planes, 3, r)
    out += np.einsum("ic,icr->ir", lin.A_plane, P[obs.plane_index])
    if layout.offsets:
        O = Ninv_rows[:, layout.i_offset :].T.reshape(-1, 3, r)
        out += np.einsum("ic,icr->ir", lin.A_offset, O[obs.pass_index])
    return out / M[:, None]


# ---------------------------------------------------------------------------------------------
# Realistic covariance: propagation of time-correlated POS errors
# ---------------------------------------------------------------------------------------------


def reported_rows(layout: Layout) -> np.ndarray:
    """Indices of the boresight, the extras and the pass offsets (the unknowns reported with a
    realistic σ; the planes are not): just the boresight when nothing extra is estimated."""
    idx = np.arange(layout.i_plane)
    if layout.offsets:
        idx = np.concatenate([idx, np.arange(layout.i_offset, layout.n)])
    return idx


def propagated_covariance(
    sol: Solution, obs: Observations, model: ErrorModel, rows: slice | np.ndarray = slice(0, 3)
) -> np.ndarray:
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
# Prediction
# ---------------------------------------------------------------------------------------------


def information(obs: Observations, state: State, r_nom, estimate) -> Solution:
    """One linearization at ``state`` and the normal matrix (with the offset prior), wrapped as
    a solution so that the covariance machinery applies to it."""
    layout = Layout(len(obs.plane_names), len(obs.pass_ids), estimate)
    lin = linearize_at_state(obs, state, r_nom, layout)
    M = np.einsum("ij,ij->i", lin.B**2, obs.sigma_l**2)
    N, _ = normal_equations(lin, layout, obs, np.zeros(len(obs)), M)
    if layout.offsets:
        prior = offset_prior_sigma(obs, AdjustOptions(estimate=tuple(estimate)))
        idx = np.arange(layout.i_offset, layout.n)
        N[idx, idx] += 1.0 / prior.reshape(-1) ** 2
    try:
        Ninv = np.linalg.inv(N)
    except np.linalg.LinAlgError:
        Ninv = np.linalg.pinv(N)
    return Solution(state, N, Ninv, lin, M, np.zeros(len(obs)), 0.0, len(obs) - layout.n, 0, True, layout)


#: the estimators a prediction can stand for (``pass_offsets`` is ``"thesis"`` with
#: ``estimate=("pass_offsets",)``)
PREDICTION_ESTIMATORS = ("gls", "thesis")


def default_estimator(model: ErrorModel) -> str:
    """The estimator :func:`predict_covariance` assumes when none is given: GLS for Gauss–Markov
    POS errors (the calibration's default), the thesis estimator for the other models."""
    return "gls" if model.kind == "gauss_markov" else "thesis"


#: independent POS errors, the default of the predicted covariance
_WHITE = ErrorModel("white")


def predict_covariance(
    obs: Observations,
    mount,
    planes,
    estimate: tuple[str, ...] = (),
    model: ErrorModel = _WHITE,
    estimator: str | None = None,
) -> dict:
    """Boresight covariance the geometry in ``obs`` would give, without adjusting.

    ``obs`` holds noise-free observations (e.g. simulated for hypothetical passes and targets)
    with the sigmas to assume, and its trajectory where there is one (the GLS knots are then its
    epochs, as in the calibration); ``planes`` the true (normal, d) per plane. The normal
    matrix is formed once, linearized at the truth (the mount's boresight, the true planes).

    ``estimator``:

    - ``"gls"``: the GLS estimator (:func:`calib.boresight.gls.gls_information`), with the POS
      errors as Gauss–Markov processes of ``model`` (which must be ``gauss_markov``). Its
      covariance ``S⁻¹`` is both its formal and its realistic covariance, and the Cramér–Rao
      bound of the model: ``formal`` = ``realistic``.
    - ``"thesis"``: white weights (the thesis's adjustment): ``formal`` = ``N⁻¹``, ``realistic``
      = the errors of ``model`` propagated through it (= ``formal`` for a white model).
    - ``None`` (default): ``"gls"`` when ``model`` is Gauss–Markov, else ``"thesis"``
      (:func:`default_estimator`). Callers that pass only a white or pass-bias model get what
      they always got; a Gauss–Markov model now means the calibration's default estimator.

    ``estimate`` adds unknowns as in :class:`~calib.boresight.observations.AdjustOptions`
    (``pass_offsets`` with the thesis estimator is the ``pass_offsets`` adjustment). Returns
    ``{"formal": 3×3, "realistic": 3×3, "correlation": 3×3 (of formal), "estimator": name}``,
    radians².
    """
    est = default_estimator(model) if estimator is None else estimator
    if est not in PREDICTION_ESTIMATORS:
        raise AdjustmentError(f"estimator {est!r}: expected one of {', '.join(PREDICTION_ESTIMATORS)}")
    if est == "gls" and model.kind != "gauss_markov":
        raise AdjustmentError(
            f"the GLS estimator models the POS errors as Gauss–Markov processes; error model "
            f"{model.kind!r} goes with the thesis estimator"
        )
    r_nom = frames.rotation_zyx(*mount.nominal_rad)
    state = initial_state(mount, planes, len(obs.pass_ids), plane_centers(obs, mount, r_nom))
    if est == "gls":
        _, S_inv, _ = gls_information(obs, state, r_nom, estimate, model)
        formal = realistic = 0.5 * (S_inv[0:3, 0:3] + S_inv[0:3, 0:3].T)
    else:
        sol = information(obs, state, r_nom, estimate)
        formal = sol.Ninv[0:3, 0:3]
        realistic = formal if model.kind == "white" else propagated_covariance(sol, obs, model)
    s = np.sqrt(np.diag(formal))
    return {
        "formal": formal,
        "realistic": realistic,
        "correlation": formal / np.outer(s, s),
        "estimator": est,
    }
