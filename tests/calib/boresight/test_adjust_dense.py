"""The O(n) adjustment equals a dense textbook Gauss–Helmert solution.

The textbook solution here is written independently of calib.boresight.ghmodel/calib.boresight.adjust: its own
condition function, derivatives by complex-step differentiation (exact to machine precision),
B as an n × 8n matrix, Q_ll as 8n × 8n, four plane parameters (a, b, c, d) per plane with the
unit-length constraint enforced by Lagrange multipliers, iterated with the linearization at the
adjusted observations.
"""

from __future__ import annotations

import numpy as np

from calib.boresight.adjust import adjust
from calib.boresight.errormodel import ErrorModel
from calib.boresight.observations import AdjustOptions
from calib.core.georef import Mount
from tests.calib import synth


def _rx(a):
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.array([[o, z, z], [z, c, -s], [z, s, c]])


def _ry(a):
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.array([[c, z, s], [z, o, z], [-s, z, c]])


def _rz(a):
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.array([[c, -s, z], [s, c, z], [z, z, o]])


def _condition(l, x, plane_index, n_planes):
    """F_i for all points; l (n, 8), x = (3 boresight, then a, b, c, d per plane)."""
    R_bs = _rz(x[2]) @ _ry(x[1]) @ _rx(x[0])
    rho, alpha = l[:, 6], l[:, 7]
    r_s = np.stack([np.zeros_like(rho), rho * np.cos(alpha), rho * np.sin(alpha)], axis=1)
    v_b = r_s @ R_bs.T
    R = np.einsum("ij...,jk...,kl...->...il", _rz(l[:, 5]), _ry(l[:, 4]), _rx(l[:, 3]))
    pts = l[:, 0:3] + np.einsum("nij,nj->ni", R, v_b)
    P = x[3:].reshape(n_planes, 4)[plane_index]
    return np.einsum("ij,ij->i", P[:, 0:3], pts) + P[:, 3]


def textbook_adjustment(obs, planes_init, iterations=12):
    """Dense textbook Gauss–Helmert solution: (boresight, its covariance, σ̂0²)."""
    n, m = len(obs), len(obs.plane_names)
    u = 3 + 4 * m
    x = np.zeros(u)
    for j, (nrm, d) in enumerate(planes_init):
        x[3 + 4 * j : 7 + 4 * j] = [*nrm, d]
    l = obs.l
    Q = np.diag((obs.sigma_l**2).reshape(-1))  # 8n × 8n
    v = np.zeros(8 * n)
    h = 1e-30
    for _ in range(iterations):
        l0 = l + v.reshape(n, 8)
        F = _condition(l0, x, obs.plane_index, m)
        A = np.empty((n, u))
        for k in range(u):
            xc = x.astype(complex)
            xc[k] += 1j * h
            A[:, k] = _condition(l0, xc, obs.plane_index, m).imag / h
        B = np.zeros((n, 8 * n))
        for c in range(8):
            lc = l0.astype(complex)
            lc[:, c] += 1j * h
            B[np.arange(n), 8 * np.arange(n) + c] = _condition(lc, x, obs.plane_index, m).imag / h
        w = F + B @ (l.reshape(-1) - l0.reshape(-1))
        Minv = np.linalg.inv(B @ Q @ B.T)
        N = A.T @ Minv @ A
        # unit-length constraints: 2 n_jᵀ dn_j = 1 − n_jᵀ n_j (Lagrange multipliers)
        C = np.zeros((m, u))
        gc = np.zeros(m)
        for j in range(m):
            nj = x[3 + 4 * j : 6 + 4 * j]
            C[j, 3 + 4 * j : 6 + 4 * j] = 2 * nj
            gc[j] = 1.0 - nj @ nj
        K = np.block([[N, C.T], [C, np.zeros((m, m))]])
        rhs = np.concatenate([-A.T @ Minv @ w, gc])
        sol = np.linalg.solve(K, rhs)
        dx = sol[:u]
        v = -Q @ B.T @ Minv @ (A @ dx + w)
        x = x + dx
    Kinv = np.linalg.inv(K)
    vtpv = v @ np.linalg.solve(Q, v)
    df = n - (u - m)
    return x[0:3], Kinv[0:3, 0:3], vtpv / df


def test_adjustment_equals_dense_textbook_solution():
    truth = np.radians([0.208, 1.245, 0.149])
    obs, planes, _ = synth.observations(
        Mount(boresight_rad=truth), synth.montreal_planes(), points_per_plane_per_pass=22, seed=11
    )
    assert 200 <= len(obs) <= 300
    init = [(nrm + 0.01, d + 0.05) for nrm, d in planes]
    init = [(nrm / np.linalg.norm(nrm), d) for nrm, d in init]
    opts = AdjustOptions(
        estimator="thesis",
        outliers="none",
        jackknife=False,
        error_model=ErrorModel("white"),
        tol_angle_rad=1e-13,
        tol_m=1e-11,
        rel_tol=0.0,
    )
    fast = adjust(obs, Mount(), init, opts)
    x_dense, cov_dense, s02_dense = textbook_adjustment(obs, init)
    np.testing.assert_allclose(np.degrees(fast.boresight_rad), np.degrees(x_dense), rtol=0, atol=1e-9)
    np.testing.assert_allclose(fast.cov_formal, cov_dense, rtol=1e-7)
    np.testing.assert_allclose(fast.sigma0_squared, s02_dense, rtol=1e-7)
    # and it is a real estimate: near the truth, not at the a-priori zero
    assert np.all(np.abs(fast.boresight_rad - truth) < 4 * fast.sigma_formal_rad)
