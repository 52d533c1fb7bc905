"""The GLS iteration's reused buffers give the numbers of the straightforward computation: the
linearization into buffers (only the estimated columns, the poses' cos and sin kept) equals
:func:`calib.boresight.ghmodel.linearize` bit for bit, the georeferencing without Jacobians
equals its F and points, the cross product with an axis equals the general one, the repeated
banded solve equals LAPACK's, the normal equations written into the solve's buffer equal the
fresh ones, and the Cholesky factor's step, inverse and log-determinant equal numpy's."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg.lapack import dtbtrs

from calib.boresight import gls
from calib.boresight.errormodel import ErrorModel
from calib.boresight.gausshelmert import Layout, linearize_at_state, pose_rates, step_converged
from calib.boresight.ghmodel import EXTRA_NAMES, _cross_axis, georeferenced, linearize, tangent_bases
from calib.boresight.observations import AdjustOptions
from calib.boresight.work.banded import BlockSolver, block_layout
from calib.boresight.work.dense import CholeskyFactor
from calib.boresight.work.linearization import LinearizationBuffers
from tests.calib.boresight.test_gls_work import TAUS, _start, random_problem


def _moved(state, seed: int):
    """``state`` with every unknown moved a little (pass offsets and extras included)."""
    rng = np.random.default_rng(seed)
    s = state.copy()
    s.boresight_rad = s.boresight_rad + rng.normal(0, 1e-3, 3)
    s.pass_offsets_m = rng.normal(0, 0.02, s.pass_offsets_m.shape)
    s.lever_arm_m = s.lever_arm_m + rng.normal(0, 0.01, 3)
    s.range_offset_m, s.scan_angle_offset_rad, s.latency_s = 0.004, 1e-4, 0.002
    return s


def _assert_same_columns(lin, ref, extras, offsets: bool):
    for name in ("F", "A_boresight", "A_plane", "B"):
        np.testing.assert_array_equal(getattr(lin, name), getattr(ref, name))
    assert sorted(lin.A_extra) == sorted(extras)
    for name in extras:
        np.testing.assert_array_equal(lin.A_extra[name], ref.A_extra[name])
    if offsets:
        np.testing.assert_array_equal(lin.A_offset, ref.A_offset)
    else:
        assert lin.A_offset.shape[0] == 0
    assert lin.x_lgf_m.shape[0] == 0  # the iterations do not georeference


@pytest.mark.parametrize(
    ("extras", "offsets", "zero_offsets"),
    [
        pytest.param((), False, True, id="boresight"),
        pytest.param(("lever_arm_x", "range_offset"), True, False, id="extras-offsets"),
        pytest.param(tuple(EXTRA_NAMES), True, False, id="all-extras-latency"),
    ],
)
def test_the_buffered_linearization_equals_linearize(extras, offsets, zero_offsets):
    obs, planes = random_problem(11, exact=True)
    state, r_nom = _start(obs, planes)
    v = np.random.default_rng(3).normal(0, 1e-3, (len(obs), 2))
    latency = "latency" in extras
    buffers = LinearizationBuffers(len(obs), extras, offsets)
    for seed in (1, 2):  # the second time with the poses' cos and sin kept from the first
        s = _moved(state, seed)
        if zero_offsets:
            s.pass_offsets_m[:] = 0.0
        l_obs = obs.l.copy()
        l_obs[:, 6:8] += v
        rates = pose_rates(obs.latency_trajectory(), obs.t_gps_s + s.latency_s) if latency else None
        bases = tangent_bases(s.normals)
        ref = linearize(s, r_nom, obs.plane_index, obs.pass_index, l_obs, rates, bases)
        buffers.observations(obs.l, v)
        lin = buffers.linearize(s, r_nom, obs.plane_index, obs.pass_index, rates, bases)
        _assert_same_columns(lin, ref, extras, offsets)


def test_an_adopted_linearization_keeps_only_the_estimated_columns():
    obs, planes = random_problem(12)
    state, r_nom = _start(obs, planes)
    layout = Layout(len(obs.plane_names), len(obs.pass_ids), ("lever_arm_y",))
    lin0 = linearize_at_state(obs, state, r_nom, layout)
    buffers = LinearizationBuffers(len(obs), layout.extras, layout.offsets, lin0)
    assert buffers.lin.F is lin0.F
    assert sorted(buffers.lin.A_extra) == ["lever_arm_y"]
    assert sorted(lin0.A_extra) == sorted(EXTRA_NAMES[:4])  # the caller's own is left whole


@pytest.mark.parametrize("zero_offsets", [True, False])
def test_georeferenced_equals_the_linearizations_f_and_points(zero_offsets):
    obs, planes = random_problem(13)
    state, r_nom = _start(obs, planes)
    s = _moved(state, 4)
    if zero_offsets:
        s.pass_offsets_m[:] = 0.0
    ref = linearize(s, r_nom, obs.plane_index, obs.pass_index, obs.l)
    F, x = georeferenced(s, r_nom, obs.plane_index, obs.pass_index, obs.l)
    np.testing.assert_array_equal(F, ref.F)
    np.testing.assert_array_equal(x, ref.x_lgf_m)


def _banded_factor(size: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    ab = np.zeros((gls.BANDWIDTH + 1, size))
    ab[0] = rng.uniform(1.0, 2.0, size)
    ab[1:] = rng.normal(0, 0.05, (gls.BANDWIDTH, size))
    return np.asfortranarray(ab)


@pytest.mark.parametrize("size", [5, 40, 97, 200])
def test_the_block_solver_equals_lapack_solve_after_solve(size):
    solver = BlockSolver(block_layout(size, gls.BANDWIDTH), 7)
    for seed in (size, size + 1):  # a second factor and right-hand side in the same buffers
        ab = _banded_factor(size, seed)
        rhs = np.random.default_rng(seed).normal(size=(size, 7))
        ref, info = dtbtrs(ab, rhs, uplo="L")
        assert info == 0
        np.testing.assert_allclose(solver.solve(ab, rhs), ref, rtol=1e-12, atol=1e-12)
    solver.W[...] = rhs  # the right-hand side already in the solver's buffer
    assert solver.solve(ab, solver.W) is solver.W
    np.testing.assert_allclose(solver.W, ref, rtol=1e-12, atol=1e-12)


def test_the_normal_equations_into_the_solvers_buffer_equal_the_fresh_ones():
    obs, planes = random_problem(14, exact=True)
    state, r_nom = _start(obs, planes)
    layout = Layout(len(obs.plane_names), len(obs.pass_ids), ("pass_offsets",))
    fr = gls.frame_for(obs, ErrorModel("gauss_markov", TAUS), AdjustOptions().knots_per_tau)
    lin = linearize_at_state(obs, state, r_nom, layout)
    work = gls.work_for(obs, layout, fr)
    gls.assemble(lin, layout, obs, fr, np.zeros(len(obs.plane_names)), state, None, work=work)
    fresh = work.plan.normals()
    out = np.full_like(fresh.N_ax, np.nan)
    into = work.plan.normals(N_ax_out=out)
    assert into.N_ax is out
    np.testing.assert_array_equal(out, fresh.N_ax)
    np.testing.assert_array_equal(into.ab, fresh.ab)


def test_the_cholesky_factor_gives_numpys_step_inverse_and_log_det():
    rng = np.random.default_rng(5)
    X = rng.normal(size=(40, 12))
    S = X.T @ X + np.eye(12)
    rhs = rng.normal(size=12)
    fac = CholeskyFactor(S)
    np.testing.assert_allclose(fac.solve(rhs), np.linalg.solve(S, rhs), rtol=1e-12)
    np.testing.assert_allclose(fac.inverse(), np.linalg.inv(S), rtol=1e-12, atol=1e-14)
    np.testing.assert_array_equal(fac.inverse(), fac.inverse().T)
    assert fac.log_det == pytest.approx(np.linalg.slogdet(S)[1], rel=1e-13)
    with pytest.raises(np.linalg.LinAlgError):
        CholeskyFactor(S - 100.0 * np.eye(12))


def test_the_convergence_test_with_a_given_inverse_is_the_same():
    layout = Layout(2, 3, ())
    rng = np.random.default_rng(6)
    X = rng.normal(size=(50, layout.n))
    N = 1e-6 * X.T @ X  # σ of order 100: the steps below are far above the absolute tolerances
    sd = np.sqrt(np.diag(np.linalg.inv(N)))
    options = AdjustOptions()
    for scale, converged in ((0.5, True), (2.0, False)):
        dx = scale * options.rel_tol * sd * rng.choice([-1.0, 1.0], layout.n)
        assert step_converged(dx, layout, options, N, 2) == converged
        assert step_converged(dx, layout, options, N, 2, CholeskyFactor(N).inverse) == converged


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_the_cross_product_with_an_axis_is_the_general_ones(axis):
    v = np.random.default_rng(axis).normal(size=(3, 50))
    expect = np.cross(np.eye(3)[axis], v.T).T
    got = np.array([np.broadcast_to(c, (50,)) for c in _cross_axis(axis, tuple(v))])
    np.testing.assert_array_equal(got, expect)
