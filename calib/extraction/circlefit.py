"""Circle fits of tie-cylinder candidates (:mod:`calib.extraction.cylinders`), all candidates at
once by ``bincount``: the algebraic (Kåsa) fit, Gauss–Newton steps of the geometric fit with a
centre per pass and one radius, and the lean of each candidate's axis the residuals show."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

GAUSS_NEWTON_STEPS = 10  # from the algebraic fit: converged to far below the noise
_TINY_M = 1e-12


@dataclass(frozen=True, kw_only=True)
class Circles:
    """One circle per candidate: a centre per (candidate, pass) group, one radius."""

    group: np.ndarray  # (k,) each member's group
    group_cand: np.ndarray  # (G,)
    center_m: np.ndarray  # (G, 2) north, east
    radius_m: np.ndarray  # (m,)
    residual_m: np.ndarray  # (k,) horizontal distance to its pass's axis − the radius


def sums(group: np.ndarray, n: int, *weights: np.ndarray) -> list[np.ndarray]:
    return [np.bincount(group, w, minlength=n) for w in weights]


def _kasa(xy: np.ndarray, cand: np.ndarray, m: int) -> tuple[np.ndarray, np.ndarray]:
    """The algebraic circle fit of each candidate: centres (m, 2) and radii (m,); x² + y² =
    2a·x + 2b·y + c solved in least squares about the candidate's centroid."""
    n = np.maximum(np.bincount(cand, minlength=m), 1)
    mean = np.column_stack(sums(cand, m, xy[:, 0], xy[:, 1])) / n[:, None]
    q = xy - mean[cand]
    w = (2.0 * q[:, 0], 2.0 * q[:, 1], np.ones(q.shape[0]))
    t = q[:, 0] ** 2 + q[:, 1] ** 2
    normal = np.empty((m, 3, 3))
    for a in range(3):
        for b in range(a, 3):
            normal[:, a, b] = normal[:, b, a] = np.bincount(cand, w[a] * w[b], minlength=m)
    rhs = np.column_stack(sums(cand, m, w[0] * t, w[1] * t, t))
    ridge = 1e-12 * np.trace(normal, axis1=1, axis2=2)  # collinear points: a huge circle, not an error
    sol = np.linalg.solve(normal + ridge[:, None, None] * np.eye(3), rhs[:, :, None])[:, :, 0]
    r2 = sol[:, 2] + sol[:, 0] ** 2 + sol[:, 1] ** 2
    return mean + sol[:, :2], np.sqrt(np.maximum(r2, 0.0))


def _gauss_newton(xy, group, group_cand, center_g, radius, steps: int):
    """Gauss–Newton steps of the geometric fit: a centre per group, one radius per candidate
    (the radius eliminated first: each group's 2 × 2 block solved in closed form)."""
    n_g, m = center_g.shape[0], radius.size
    cand = group_cand[group]
    n_pts = np.bincount(cand, minlength=m).astype(float)
    damp = 1e-9 * np.bincount(group, minlength=n_g) + _TINY_M  # a point-like arc: no division by 0
    center_g, radius = center_g.copy(), radius.copy()
    for _ in range(steps):
        d = xy - center_g[group]
        rho = np.hypot(d[:, 0], d[:, 1])
        u0, u1 = (d / np.maximum(rho, _TINY_M)[:, None]).T
        e = rho - radius[cand]
        a11, a12, a22, b1, b2, f1, f2 = sums(group, n_g, u0 * u0, u0 * u1, u1 * u1, u0, u1, u0 * e, u1 * e)
        a11, a22 = a11 + damp, a22 + damp
        det = a11 * a22 - a12 * a12
        ab1, ab2 = (a22 * b1 - a12 * b2) / det, (a11 * b2 - a12 * b1) / det  # A⁻¹ b
        af1, af2 = (a22 * f1 - a12 * f2) / det, (a11 * f2 - a12 * f1) / det  # A⁻¹ f
        q = np.bincount(group_cand, b1 * ab1 + b2 * ab2, minlength=m)
        g = np.bincount(group_cand, b1 * af1 + b2 * af2, minlength=m)
        dr = (np.bincount(cand, e, minlength=m) - g) / np.maximum(n_pts - q, 1e-9 * n_pts + _TINY_M)
        center_g[:, 0] += af1 - ab1 * dr[group_cand]
        center_g[:, 1] += af2 - ab2 * dr[group_cand]
        radius += dr
    return center_g, radius


def fit_circles(xy: np.ndarray, cand: np.ndarray, pass_index: np.ndarray, m: int, n_pass: int) -> Circles:
    """Kåsa, then GAUSS_NEWTON_STEPS of the geometric fit with a centre per pass."""
    uniq, group = np.unique(cand * n_pass + pass_index, return_inverse=True)
    group_cand = uniq // n_pass
    center, radius = _kasa(xy, cand, m)
    with np.errstate(all="ignore"):  # a degenerate candidate ends non-finite: rejected by its radius
        center_g, radius = _gauss_newton(
            xy, group, group_cand, center[group_cand], radius, GAUSS_NEWTON_STEPS
        )
        d = xy - center_g[group]
        residual = np.hypot(d[:, 0], d[:, 1]) - radius[cand]
    return Circles(
        group=group, group_cand=group_cand, center_m=center_g, radius_m=radius, residual_m=residual
    )


def lean(d: np.ndarray, z: np.ndarray, circles: Circles, m: int) -> tuple[np.ndarray, np.ndarray]:
    """(m,) each candidate's lean (deg) and how clearly its points show it, each (m,): the slope
    s (2,) of its axis with height that best explains the circle residuals, linearized about the
    upright fit (a residual ``|d| − r`` ≈ ``u·s (up − mean up of its pass)``, ``u`` the point's
    radial unit vector), as an angle; and ``√(sᵀ N s) / σ``, N the normal matrix of s and σ the
    residuals' RMS about it (a χ with 2 degrees of freedom for an upright pile: a lean across
    a narrow arc's line of sight moves its points along the surface and shows as nothing)."""
    g = circles.group
    n_g = np.maximum(np.bincount(g, minlength=len(circles.group_cand)), 1)
    up = -(z - np.bincount(g, z, minlength=n_g.size)[g] / n_g[g])
    u = d / np.maximum(np.hypot(d[:, 0], d[:, 1]), _TINY_M)[:, None]
    a = u * up[:, None]  # (n, 2) the residual's derivative by s
    e = circles.residual_m
    cand = circles.group_cand[g]
    n11, n12, n22, b1, b2, ee = sums(
        cand,
        m,
        a[:, 0] ** 2,
        a[:, 0] * a[:, 1],
        a[:, 1] ** 2,
        a[:, 0] * e,
        a[:, 1] * e,
        e * e,
    )
    n = np.bincount(cand, minlength=m)
    det = n11 * n22 - n12**2
    with np.errstate(divide="ignore", invalid="ignore"):
        s1 = np.where(det > 0, (n22 * b1 - n12 * b2) / det, np.nan)
        s2 = np.where(det > 0, (n11 * b2 - n12 * b1) / det, np.nan)
        explained = s1 * b1 + s2 * b2  # sᵀ N s (= sᵀ b at the solution)
        sigma2 = np.maximum(ee - explained, 0.0) / np.maximum(n - 2.0, 1.0)
        z_lean = np.sqrt(np.maximum(explained, 0.0) / np.maximum(sigma2, _TINY_M**2))
    return np.degrees(np.arctan(np.hypot(s1, s2))), z_lean
