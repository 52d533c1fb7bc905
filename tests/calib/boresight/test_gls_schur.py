"""The knots' Schur complement by blocks (:class:`calib.boresight.work.schur.KnotSchur`) equals
the dense ``[N_ax | g_a]ᵀ N_aa⁻¹ [N_ax | g_a]``: for blocks that end past the last row, a single
block, and repeated reductions in the same buffers; ``g_a + N_ax dx``, the knots after a step
``−N_aa⁻¹ (g_a + N_ax dx)`` and ``L⁻¹ N_ax`` as well; so does the dense :class:`DenseSchur`,
which :func:`knot_schur` takes when every block would touch most of the unknowns."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg.lapack import dpbtrf

from calib.boresight.work.schur import DenseSchur, KnotSchur, knot_schur

BW = 11


def _problem(size: int, p: int, seed: int):
    """A banded SPD N_aa (lower form), its factor, and an N_ax whose rows each touch the first
    three columns and a few of the others, as the points of one plane at a time do."""
    rng = np.random.default_rng(seed)
    ab = np.zeros((BW + 1, size))
    ab[0] = rng.uniform(20.0, 30.0, size)
    ab[1:] = rng.normal(0, 1.0, (BW, size))
    chol, info = dpbtrf(ab.copy(), lower=1)
    assert info == 0
    dense = np.zeros((size, size))
    for d in range(BW + 1):
        i = np.arange(size - d)
        dense[i + d, i] = dense[i, i + d] = ab[d, : size - d]
    N_ax = np.zeros((size, p))
    N_ax[:, :3] = rng.normal(size=(size, 3))
    group = (np.arange(size) * 7 // size * 3) % (p - 3)  # a plane of three columns per stretch
    for k in range(3):
        N_ax[np.arange(size), 3 + (group + k) % (p - 3)] = rng.normal(size=size)
    return chol, dense, N_ax, rng.normal(size=size)


@pytest.mark.parametrize(("size", "block"), [(30, 64), (97, 16), (200, 32), (257, 64), (200, None)])
def test_the_blocked_schur_complement_equals_the_dense_one(size, block):
    """(``block`` None: :class:`DenseSchur`, the same through the dense ``L⁻¹ N_ax``.)"""
    p = 15
    chol, N_aa, N_ax, g_a = _problem(size, p, size)
    cross_at = np.flatnonzero(N_ax.reshape(-1))
    ks = KnotSchur(cross_at, size, p, BW, block) if block else DenseSchur(cross_at, size, p, BW)
    for seed in (size, size + 1):  # a second problem of the same pattern in the same buffers
        chol, N_aa, N_ax, g_a = _problem(size, p, seed)
        gram, wv = ks.reduce(chol, N_ax.reshape(-1)[cross_at], g_a)
        ref = N_ax.T @ np.linalg.solve(N_aa, np.column_stack([N_ax, g_a]))
        scale = np.max(np.abs(ref))
        np.testing.assert_allclose(gram, ref[:, :p], rtol=0, atol=1e-12 * scale)
        np.testing.assert_allclose(wv, ref[:, p], rtol=0, atol=1e-12 * scale)
        dx = np.random.default_rng(seed).normal(size=p)
        z = -np.linalg.solve(N_aa, g_a + N_ax @ dx)
        np.testing.assert_allclose(ks.knots(chol, dx), z, rtol=0, atol=1e-12 * np.max(np.abs(z)))
        if block:
            np.testing.assert_allclose(ks.cross_times(dx), g_a + N_ax @ dx, rtol=1e-14, atol=1e-14)
            np.testing.assert_array_equal(ks.dense_cross(), N_ax)
        L = np.linalg.cholesky(N_aa)
        np.testing.assert_allclose(ks.W(chol), np.linalg.solve(L, N_ax), rtol=1e-10, atol=1e-12)


def test_the_blocks_are_taken_where_they_touch_few_of_the_unknowns():
    size, p = 3972, 99
    chol, N_aa, N_ax, g_a = _problem(size, p, 1)  # three planes a stretch of the survey
    assert isinstance(knot_schur(np.flatnonzero(N_ax.reshape(-1)), size, p, BW), KnotSchur)
    everywhere = np.arange(size * p)  # every plane seen in every block of knots
    assert isinstance(knot_schur(everywhere, size, p, BW), DenseSchur)
