"""How POS errors are correlated in time, and the O(n) double sums that propagate them.

Used by :mod:`calib.boresight.covariance` for ``sigma_realistic`` and by predictions of the site design and
the operator guidance. Σ_i Σ_j q_i q_jᵀ ρ(t_i − t_j) with ρ = exp(−|Δt|/τ) is evaluated with
decayed cumulative sums (forward and backward), never with an n × n matrix.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Default correlation time of the POS errors for ``sigma_realistic`` when none is configured.
DEFAULT_POS_CORRELATION_S = 60.0


@dataclass(frozen=True)
class ErrorModel:
    """How POS errors are correlated, for ``sigma_realistic`` and predictions.

    ``kind``: ``"white"`` (independent per point: the formal model), ``"gauss_markov"``
    (exponential correlation across all points, passes included, with ``correlation_time_s``:
    one value, or six for north, east, down, roll, pitch, heading) or ``"pass_bias"`` (constant
    within a pass, independent between passes).
    """

    kind: str = "gauss_markov"
    correlation_time_s: float | tuple[float, ...] = DEFAULT_POS_CORRELATION_S

    def __post_init__(self):
        if self.kind not in ("white", "gauss_markov", "pass_bias"):
            raise ValueError(f"ErrorModel.kind {self.kind!r}: expected white, gauss_markov or pass_bias")
        tau = np.atleast_1d(np.asarray(self.correlation_time_s, float))
        if tau.size not in (1, 6) or not np.all(tau > 0):
            raise ValueError("ErrorModel.correlation_time_s: one or six positive values (s)")
        object.__setattr__(
            self, "correlation_time_s", float(tau[0]) if tau.size == 1 else tuple(float(x) for x in tau)
        )

    def tau_s(self, channel: int) -> float:
        """Correlation time of POS channel 0–5 (N, E, D, roll, pitch, heading)."""
        tau = self.correlation_time_s
        return tau if isinstance(tau, float) else tau[channel]


def decayed_cumsum(t: np.ndarray, h: np.ndarray, tau: float) -> np.ndarray:
    """F_i = Σ_{j ≤ i} h_j · exp(−(t_i − t_j)/τ) for sorted t, in O(n), overflow-safe."""
    n = t.shape[0]
    out = np.empty_like(h)
    carry = np.zeros(h.shape[1:])
    t_prev = t[0]
    start = 0
    while start < n:
        t0 = t[start]
        end = max(int(np.searchsorted(t, t0 + 600.0 * tau, side="right")), start + 1)
        e = np.exp((t[start:end] - t0) / tau)
        cs = np.cumsum(h[start:end] * e[:, None], axis=0) / e[:, None]
        out[start:end] = cs + carry * np.exp(-(t[start:end] - t_prev) / tau)[:, None]
        carry = out[end - 1]
        t_prev = t[end - 1]
        start = end
    return out


def correlated_sum(t, q, model: ErrorModel, pass_index, tau_s: float) -> np.ndarray:
    """Σ_i Σ_j q_i q_jᵀ ρ(i, j) for one error channel with correlation time ``tau_s``."""
    if model.kind == "white":
        return q.T @ q
    if model.kind == "pass_bias":
        out = np.zeros((q.shape[1], q.shape[1]))
        for k in np.unique(pass_index):
            s = q[pass_index == k].sum(axis=0)
            out += np.outer(s, s)
        return out
    order = np.argsort(t, kind="stable")
    ts, qs = t[order], q[order]
    fwd = decayed_cumsum(ts, qs, tau_s)
    bwd = decayed_cumsum(-ts[::-1], qs[::-1], tau_s)[::-1]
    s = qs.T @ (fwd + bwd - qs)
    return 0.5 * (s + s.T)
