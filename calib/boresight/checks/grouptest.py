"""Gross errors found per group, not per point (docs/architecture.md §7.4a).

A target seen in one pass is one group of points that can be wrong together: the wall beside a
target taken for it, a ledge, a neighbour's panel. Its points then sit on a plane offset or
tilted from the target's adjusted plane, and the point-wise data snooping of
:func:`calib.boresight.adjust.adjust` cannot see it (each point alone fits within a few σ once
the boresight, the planes and the POS processes have absorbed part of the error, and the plane's
roughness component the rest).

The test: the group gets a plane of its own, three extra unknowns ``h`` (an offset along the
normal and two tilts: the plane's own design columns restricted to the group's rows, ``C``).
With everything else re-estimated (the boresight, the planes, the extras and the POS error
processes), the decrease of the GLS objective is the score test

    T = rᵀ Q⁺ r,   r = Cᵀ W e,   Q = Cᵀ W C − Cᵀ W [A J] N⁻¹ [A J]ᵀ W C,

``W`` the white weights, ``e`` the white residuals, ``N`` the full normal matrix (the POS knots
eliminated through the banded factor that the solution already holds). Under the model ``T`` is
χ² with as many degrees of freedom as ``Q`` has directions the rest of the model does not
absorb (a group that alone defines its plane carries none and is not testable). ``T`` is divided
by the variance factor when that exceeds 1, and by the groups' common inflation (the median over
the groups of ``T``/median(χ²), at least 1): a misfit that every group shares is not one group's
fault. (On the project's simulated bundles the raw ``T`` averages ≈ 1.4 × its degrees of
freedom — the score equals the exact likelihood ratio of giving the group its own plane, checked
against a re-solve, so the excess is what the model leaves out.) A group is a gross error when its p-value is below the family-wise
``alpha`` shared over the tested groups (Šidák). The worst one goes, the adjustment is solved
again, until none is left.

Only the targets' groups are tested: a tie patch of a real wall is not a plane over 1.5 m, and
its passes disagree by the waviness they sample, which the patches' own agreement check
(:func:`calib.boresight.scene_ties.patches_agree`) judges as a whole.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

from calib.boresight.gls import GlsSolution, _tb_solve
from calib.boresight.observations import Observations

#: family-wise false-rejection rate of the group tests (over the groups tested in one round)
GROUP_ALPHA = 0.001
#: a direction of Q holding less than this fraction of the group's own information is absorbed
ABSORBED = 1e-10


@dataclass(frozen=True)
class GroupTest:
    """One group's test."""

    plane: str
    pass_id: int
    n_points: int
    statistic: float  # T / max(1, σ̂0²)
    df: int
    p_value: float
    offset_m: float  # the group's own offset from the adjusted plane (h[0])

    def as_dict(self) -> dict:
        return {
            "plane": self.plane,
            "pass_id": int(self.pass_id),
            "n_points": int(self.n_points),
            "statistic": float(self.statistic),
            "df": int(self.df),
            "p_value": float(self.p_value),
            "offset_m": float(self.offset_m),
        }


def target_groups(obs: Observations) -> list[tuple[int, int, np.ndarray]]:
    """(plane index, pass index, rows) of every target seen in a pass."""
    patch = set(obs.patch_planes)
    out = []
    for j in range(len(obs.plane_names)):
        if j in patch:
            continue
        for k in range(len(obs.pass_ids)):
            rows = np.flatnonzero((obs.plane_index == j) & (obs.pass_index == k))
            if rows.size:
                out.append((j, k, rows))
    return out


def _score(sol: GlsSolution, rows: np.ndarray) -> tuple[float, int, float]:
    """(T, degrees of freedom, offset) of one group, T not yet scaled by the variance factor."""
    sys = sol.system
    w = 1.0 / sys.m[rows]
    C = sol.lin.A_plane[rows]
    Cw = C * w[:, None]
    n_cc = C.T @ Cw
    n_cx = (sys.A[rows].T @ Cw).T  # (3, p)
    n_ca = (sys.J[rows].T @ Cw).T  # (3, 6K)
    u = _tb_solve(sys.chol, np.ascontiguousarray(np.asarray(n_ca).T))
    R = n_cx.T - sys.W.T @ u  # (p, 3)
    Q = n_cc - u.T @ u - R.T @ sol.Ninv @ R
    r = Cw.T @ sol.e[rows]
    scale = 1.0 / np.sqrt(np.maximum(np.diag(n_cc), 1e-300))
    lam, vec = np.linalg.eigh(0.5 * (Q + Q.T) * np.outer(scale, scale))
    keep = lam > ABSORBED
    if not keep.any():
        return 0.0, 0, float("nan")
    proj = vec[:, keep].T @ (r * scale)
    h = -(scale[:, None] * vec[:, keep]) @ (proj / lam[keep])
    return float(np.sum(proj**2 / lam[keep])), int(keep.sum()), float(h[-1])


#: the groups' common inflation is estimated from at least this many testable groups
MIN_GROUPS_FOR_FACTOR = 4


def group_factor(raw: list[tuple[float, int]]) -> float:
    """The inflation every group shares: the median of T/median(χ²_df) over the testable
    groups, at least 1. On simulated data under the model it is ≈ 1.3 (what the model leaves
    out that every group sees alike: the scanner's noise is not exactly white, the POS error
    not exactly first-order Gauss–Markov between epochs); one bad group barely moves a median."""
    ratios = [t / stats.chi2.median(df) for t, df in raw if df > 0]
    if len(ratios) < MIN_GROUPS_FOR_FACTOR:
        return 1.0
    return max(1.0, float(np.median(ratios)))


def group_tests(sol: GlsSolution, obs: Observations) -> list[GroupTest]:
    """Every target group's test at the solution ``sol`` of ``obs``: T divided by the variance
    factor (when > 1) and by the groups' common inflation (:func:`group_factor`)."""
    variance_factor = max(1.0, sol.vtpv / max(sol.df, 1))
    groups = target_groups(obs)
    raw = [_score(sol, rows) for _, _, rows in groups]
    factor = variance_factor * group_factor([(t / variance_factor, df) for t, df, _ in raw])
    out = []
    for (j, k, rows), (t, df, offset) in zip(groups, raw, strict=False):
        stat = t / factor
        p = float(stats.chi2.sf(stat, df)) if df else 1.0
        out.append(GroupTest(obs.plane_names[j], obs.pass_ids[k], rows.size, stat, df, p, offset))
    return out


def worst_gross_error(tests: list[GroupTest], alpha: float = GROUP_ALPHA) -> GroupTest | None:
    """The group with the smallest p-value when it is below the Šidák level for ``alpha``
    over the testable groups, else None."""
    testable = [t for t in tests if t.df > 0]
    if not testable:
        return None
    per_test = 1.0 - (1.0 - alpha) ** (1.0 / len(testable))
    worst = min(testable, key=lambda t: t.p_value)
    return worst if worst.p_value < per_test else None
