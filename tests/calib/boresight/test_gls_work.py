"""The GLS estimator's work arrays (calib.boresight.work) give the numbers of the straightforward
computation: on small problems with random geometry (random patches, several planes, pass
offsets and extras, exact and uniform knots, channels with different τ) the segment-Gram normal
equations, the blocked banded solve, the misclosures after a step and a whole iterated solution
equal a reference built from the sparse design and knot matrices with dense algebra, to 1e-9."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg.lapack import dtbtrs

from calib.boresight import gls
from calib.boresight.errormodel import ErrorModel
from calib.boresight.gausshelmert import (
    Layout,
    _apply,
    initial_state,
    linearize_at_state,
    normal_equations,
    offset_prior_sigma,
    plane_centers,
    solve_normal,
    step_converged,
)
from calib.boresight.ghmodel import tangent_bases
from calib.boresight.observations import AdjustOptions
from calib.boresight.work.banded import block_layout, solve_lower
from calib.boresight.work.normals import normal_matrix, white_misclosure
from calib.core import frames
from calib.core.geometry import Rectangle
from calib.core.georef import Mount
from calib.core.trajectory import Trajectory
from tests.calib import synth

TRUTH = np.radians([0.208, 1.245, 0.149])
LEVER = np.array([0.35, 0.85, -1.65])
MOUNT0 = Mount(lever_arm_m=LEVER, boresight_rad=np.zeros(3))
TAUS = (20.0, 20.0, 20.0, 10.0, 10.0, 10.0)


def random_problem(seed: int, n_patches: int = 5, points: int = 12, exact: bool = False):
    """The montreal targets plus ``n_patches`` random 1 × 1 m patches on the quay wall, with
    noise; ``exact``: the passes' epochs as the trajectory (knots at the epochs)."""
    rng = np.random.default_rng(seed)
    az = np.radians(270.0)
    patches = [
        Rectangle.from_orientation(
            f"R{i}", [rng.uniform(-14, 14), 15.0, rng.uniform(-7, -3.5)], 1.0, 1.0, np.radians(90.0), az
        )
        for i in range(n_patches)
    ]
    mount = Mount(lever_arm_m=LEVER, boresight_rad=TRUTH)
    obs, planes, trajs = synth.observations(
        mount, synth.montreal_planes() + patches, points_per_plane_per_pass=points, seed=seed
    )
    if exact:
        obs.trajectory = Trajectory(
            np.concatenate([t.t_gps_s for t in trajs]),
            np.concatenate([t.p_lgf_m for t in trajs]),
            np.concatenate([t.rpy_rad for t in trajs]),
            trajs[0].frame,
            max_gap_s=1e4,
        )
    return obs, planes


def _start(obs, planes):
    r_nom = frames.rotation_zyx(*MOUNT0.nominal_rad)
    return initial_state(MOUNT0, planes, len(obs.pass_ids), plane_centers(obs, MOUNT0, r_nom)), r_nom


def reference_system(lin, layout, obs, fr, pv, state, prior_sigma):
    """The Schur complement and its right-hand side from the sparse A and J, densely."""
    m = gls.white_variance(lin, obs, fr, pv)
    A = gls.design_matrix(lin, layout, obs).toarray()
    J = gls.knot_matrix(lin, obs, fr).toarray()
    w = 1.0 / m
    size = J.shape[1]
    P = np.zeros((size, size))
    for d in range(fr.prior.shape[0]):
        idx = np.arange(size - d)
        P[idx + d, idx] = fr.prior[d, : size - d]
        P[idx, idx + d] = fr.prior[d, : size - d]
    N_aa = J.T @ (w[:, None] * J) + P
    N_ax = J.T @ (w[:, None] * A)
    Y = np.linalg.solve(N_aa, np.column_stack([N_ax, J.T @ (w * lin.F)]))
    S = A.T @ (w[:, None] * A) - N_ax.T @ Y[:, :-1]
    r = A.T @ (w * lin.F) - N_ax.T @ Y[:, -1]
    if prior_sigma is not None:
        wt = 1.0 / prior_sigma.reshape(-1) ** 2
        idx = np.arange(layout.i_offset, layout.n)
        S[idx, idx] += wt
        r[idx] += wt * state.pass_offsets_m.reshape(-1)
    return S, r, m, A, J, N_aa


CASES = [
    pytest.param(1, (), False, id="boresight-uniform-knots"),
    pytest.param(2, ("pass_offsets",), True, id="pass-offsets-exact-knots"),
    pytest.param(3, ("range_offset", "lever_arm_x"), False, id="extras-uniform-knots"),
]


@pytest.mark.parametrize(("seed", "estimate", "exact"), CASES)
def test_the_assembled_system_equals_the_dense_reference(seed, estimate, exact):
    obs, planes = random_problem(seed, exact=exact)
    state, r_nom = _start(obs, planes)
    options = AdjustOptions(estimate=estimate)
    layout = Layout(len(obs.plane_names), len(obs.pass_ids), estimate)
    fr = gls.frame_for(obs, ErrorModel("gauss_markov", TAUS), options.knots_per_tau)
    assert fr.grid.exact == exact
    pv = np.random.default_rng(seed).uniform(0, 1e-5, len(obs.plane_names))
    lin = linearize_at_state(obs, state, r_nom, layout)
    prior_sigma = offset_prior_sigma(obs, options) if layout.offsets else None
    sys = gls.assemble(lin, layout, obs, fr, pv, state, prior_sigma)
    S, r, m, A, J, N_aa = reference_system(lin, layout, obs, fr, pv, state, prior_sigma)
    scale = np.sqrt(np.outer(np.diag(S), np.diag(S)))
    assert np.max(np.abs(sys.S - S) / scale) <= 1e-9
    assert np.max(np.abs(sys.r - r) / np.sqrt(np.diag(S))) <= 1e-9 * max(1.0, np.max(np.abs(r)))
    np.testing.assert_allclose(sys.m, m, rtol=1e-12)
    # the design and knot matrices the group tests use, and the misclosures after a step
    np.testing.assert_array_equal(sys.A.toarray(), A)
    np.testing.assert_array_equal(sys.J.toarray(), J)
    rng = np.random.default_rng(seed + 10)
    dx, z = rng.normal(0, 1e-4, layout.n), rng.normal(0, 1.0, J.shape[1])
    work = gls.work_for(obs, layout, fr)
    gls.assemble(lin, layout, obs, fr, pv, state, prior_sigma, work=work)
    e = white_misclosure(work.plan, work.m, dx, z)
    np.testing.assert_allclose(e, lin.F + A @ dx + J @ z, rtol=0, atol=1e-12 * np.max(np.abs(lin.F)))
    # the knot factor's log determinant (the likelihood's) is the dense one's
    np.testing.assert_allclose(2.0 * np.sum(np.log(sys.chol[0])), np.linalg.slogdet(N_aa)[1], rtol=1e-10)


@pytest.mark.parametrize("size", [5, 40, 97, 200])
def test_the_blocked_banded_solve_equals_lapack(size):
    rng = np.random.default_rng(size)
    bw = gls.BANDWIDTH
    ab = np.zeros((bw + 1, size))
    ab[0] = rng.uniform(1.0, 2.0, size)
    ab[1:] = rng.normal(0, 0.05, (bw, size))
    rhs = rng.normal(size=(size, 7))
    ref, info = dtbtrs(ab, rhs, uplo="L")
    assert info == 0
    np.testing.assert_allclose(solve_lower(ab, rhs, block_layout(size, bw)), ref, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("estimate", [(), ("pass_offsets", "lever_arm_y")])
def test_the_white_normal_matrix_equals_the_dense_rows(estimate):
    obs, planes = random_problem(5)
    state, r_nom = _start(obs, planes)
    layout = Layout(len(obs.plane_names), len(obs.pass_ids), estimate)
    lin = linearize_at_state(obs, state, r_nom, layout)
    M = np.einsum("ij,ij->i", lin.B**2, obs.sigma_l**2)
    ref, _ = normal_equations(lin, layout, obs, np.zeros(len(obs)), M)
    np.testing.assert_allclose(
        normal_matrix(lin, layout, obs, M), ref, rtol=1e-10, atol=1e-10 * np.abs(ref).max()
    )


def reference_solve(obs, state, r_nom, model, iterations):
    """The GLS iteration (:func:`calib.boresight.gls.solve_gls`, all planes rough) written
    straightforwardly: dense normal equations, the misclosures from the dense A and J."""
    layout = Layout(len(obs.plane_names), len(obs.pass_ids), ())
    options = AdjustOptions()
    fr = gls.frame_for(obs, model, options.knots_per_tau)
    pv = np.zeros(len(obs.plane_names))
    v = np.zeros((len(obs), 2))
    for it in range(1, iterations + 1):
        bases = tangent_bases(state.normals)
        lin = gls.linearize_adjusted(obs, state, r_nom, v, False, bases)
        S, r, m, A, J, N_aa = reference_system(lin, layout, obs, fr, pv, state, None)
        dx = solve_normal(S, -r, obs, layout)
        z = -np.linalg.solve(N_aa, J.T @ (lin.F / m) + J.T @ ((A @ dx) / m))
        e = lin.F + A @ dx + J @ z
        state = _apply(state, dx, layout, bases)
        v = gls.scanner_residuals(lin, obs, e / m, pv)
        new = gls.roughness_update(e, m, pv, obs.plane_index, np.arange(len(obs.plane_names)))
        settled = bool(np.all(np.abs(new - pv) <= gls.VC_TOL * (np.maximum(new, pv) + 1e-12)))
        if step_converged(dx, layout, options, S, it) and settled and it > 1:
            break
        pv = new
    return state, np.linalg.inv(S), it


@pytest.mark.parametrize(("seed", "exact"), [(7, False), (8, True)])
def test_a_whole_solution_equals_the_straightforward_iteration(seed, exact):
    obs, planes = random_problem(seed, n_patches=6, points=10, exact=exact)
    state, r_nom = _start(obs, planes)
    model = ErrorModel("gauss_markov", TAUS)
    rough = np.arange(len(obs.plane_names))
    sol = gls.solve_gls(obs, state, r_nom, AdjustOptions(), model, rough_planes=rough)
    ref_state, ref_cov, ref_it = reference_solve(obs, state, r_nom, model, sol.iterations)
    assert sol.iterations == ref_it
    assert np.max(np.degrees(np.abs(sol.state.boresight_rad - ref_state.boresight_rad))) <= 1e-9
    np.testing.assert_allclose(sol.state.normals, ref_state.normals, rtol=0, atol=1e-9)
    np.testing.assert_allclose(sol.state.d_m, ref_state.d_m, rtol=0, atol=1e-9)
    np.testing.assert_allclose(np.sqrt(np.diag(sol.Ninv)), np.sqrt(np.diag(ref_cov)), rtol=1e-9)
