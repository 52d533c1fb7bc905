"""The GLS prediction (the calibration's default estimator) in the design and the survey
guidance: :func:`calib.boresight.covariance.predict_covariance` with ``estimator="gls"`` against
the dense GLS oracle, against the thesis's adjustments, the design's realistic model, and the
pass-by-pass prediction of :mod:`calib.design.passpredict` (thinning, knots, monotonicity)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from calib.boresight.covariance import information, predict_covariance
from calib.boresight.errormodel import ErrorModel
from calib.boresight.gausshelmert import initial_state, plane_centers
from calib.boresight.gls import frame_for
from calib.boresight.observations import AdjustmentError
from calib.boresight.oracle import dense_gls
from calib.core import frames
from calib.core.trajectory import Trajectory
from calib.design.layouts import Layout
from calib.design.passpredict import (
    ObservationModel,
    PassGeometry,
    build_pass_observations,
    joint_trajectory,
    predict_sigma,
)
from calib.design.prediction import (
    ANGLES,
    MODELS,
    Sigmas,
    predict,
    prepare,
    select_passes,
)
from calib.design.scenes import design_scenario, scenario_targets
from calib.design.study import sigma_row
from calib.sim.scenariofile import load_scenario
from calib.sim.simulate import simulate


@pytest.fixture(scope="module")
def montreal():
    """Noise-free observations of montreal's own targets (the thesis's site), the true mount
    and planes, and the scenario's Gauss–Markov model."""
    base = load_scenario("montreal")
    sigmas = Sigmas.of_scenario(base)
    sim, obs, planes = prepare(design_scenario(base, scenario_targets(base)), sigmas, 0)
    return obs, sim.mount_true, planes, ErrorModel("gauss_markov", sigmas.correlation_time_s)


def test_the_gls_prediction_is_the_dense_oracles_cramer_rao_bound(montreal):
    """On a small geometry (every third point, then passes 1, 3, 4, 6: ≤ 2000 points) the
    banded GLS information at the truth gives the covariance of the dense GLS oracle (the full
    n × n misclosure covariance at the trajectory's epochs, iterated to its own solution —
    the truth, the observations being noise-free)."""
    obs, mount, planes, gm = montreal
    keep = np.zeros(len(obs), bool)
    keep[::3] = True
    small = obs.select(keep)
    sub, sub_planes = select_passes(obs.select(keep), planes, (1, 3, 4, 6))
    for o, p in ((small, planes), (sub, sub_planes)):
        assert 500 < len(o) <= 2000 and o.trajectory is not None
        pred = predict_covariance(o, mount, p, model=gm, estimator="gls")
        oracle = dense_gls(o, mount, p, gm)
        np.testing.assert_allclose(oracle.boresight_rad, mount.boresight_rad, atol=1e-10)
        ref = oracle.cov[0:3, 0:3]
        np.testing.assert_allclose(pred["realistic"], ref, rtol=1e-6, atol=1e-9 * np.abs(ref).max())
        assert pred["formal"] is pred["realistic"] and pred["estimator"] == "gls"


def test_the_default_estimator_is_gls_for_gauss_markov_errors_only(montreal):
    obs, mount, planes, gm = montreal
    default = predict_covariance(obs, mount, planes, model=gm)
    gls = predict_covariance(obs, mount, planes, model=gm, estimator="gls")
    assert default["estimator"] == "gls"
    np.testing.assert_array_equal(default["realistic"], gls["realistic"])
    # white (the default model) and per-pass biases: the thesis's estimator, as before
    white = predict_covariance(obs, mount, planes)
    assert white["estimator"] == "thesis"
    r_nom = frames.rotation_zyx(*mount.nominal_rad)
    state = initial_state(mount, planes, len(obs.pass_ids), plane_centers(obs, mount, r_nom))
    np.testing.assert_allclose(white["formal"], information(obs, state, r_nom, ()).Ninv[0:3, 0:3], rtol=1e-12)
    assert predict_covariance(obs, mount, planes, model=ErrorModel("pass_bias"))["estimator"] == "thesis"
    with pytest.raises(AdjustmentError, match="Gauss–Markov"):
        predict_covariance(obs, mount, planes, model=ErrorModel("pass_bias"), estimator="gls")
    with pytest.raises(AdjustmentError, match="estimator 'dense'"):
        predict_covariance(obs, mount, planes, model=gm, estimator="dense")


def test_gls_is_never_worse_than_the_thesis_adjustments_on_montreal(montreal):
    """GLS is the best linear unbiased estimator under the Gauss–Markov model: its covariance
    lies below the thesis adjustment's realistic one (white weights, the same errors
    propagated), with or without per-pass offsets — per angle and as matrices."""
    obs, mount, planes, gm = montreal
    gls = predict_covariance(obs, mount, planes, model=gm, estimator="gls")["realistic"]
    sg = np.sqrt(np.diag(gls))
    for est in ((), ("pass_offsets",)):
        thesis = predict_covariance(obs, mount, planes, est, gm, estimator="thesis")["realistic"]
        assert np.all(sg <= np.sqrt(np.diag(thesis))), est
        assert np.linalg.eigvalsh(thesis - gls).min() >= -1e-9 * np.abs(gls).max(), est
    # and far below it where the thesis adjustment suffers most (its pitch)
    thesis = predict_covariance(obs, mount, planes, (), gm, estimator="thesis")["realistic"]
    assert sg[1] < 0.5 * np.sqrt(thesis[1, 1])


def test_the_designs_realistic_sigma_is_the_gls_estimators(montreal):
    obs, mount, planes, gm = montreal
    tau = gm.correlation_time_s
    pred = predict(obs, mount, planes, tau)
    assert set(pred.covariances) == set(MODELS)
    assert pred.realistic_model == "gls" and pred.estimator == "gls"
    ref = predict_covariance(obs, mount, planes, model=gm, estimator="gls")["realistic"]
    np.testing.assert_allclose(pred.covariances["gls"], ref, rtol=1e-12)
    # without a GLS prediction: the better thesis adjustment, as before
    old = predict(obs, mount, planes, tau, ("white", "gauss_markov", "gauss_markov_offsets"))
    assert old.realistic_model == min(("gauss_markov", "gauss_markov_offsets"), key=old.total_deg)
    assert (
        old.estimator
        == {"gauss_markov": "thesis", "gauss_markov_offsets": "pass_offsets"}[old.realistic_model]
    )
    base = load_scenario("montreal")
    layout = Layout("site", "montreal", scenario_targets(base), base.standoff_m, ())
    row = sigma_row("montreal", layout, pred, (1, 2, 3, 4, 5, 6), {}, tau)
    assert row["estimator"] == "gls"
    assert row["realistic_total_deg"] == row["sigma_gls_total_deg"]
    assert row["realistic_total_deg"] == pytest.approx(float(np.degrees(np.sqrt(np.trace(ref)))), rel=1e-12)


# -- the pass-by-pass prediction --------------------------------------------------------------


@pytest.fixture(scope="module")
def passes():
    """montreal's six passes as the survey guidance sees them: each pass's returns on the
    targets with the true trajectory around them (noise-free), and the site."""
    sim = simulate("montreal", 3)
    pts, tr = sim.points, sim.trajectory_true
    out = []
    for p in sorted(sim.plan.passes, key=lambda q: q.order):
        m = (sim.target_index >= 0) & (pts.pass_id == p.id)
        t = pts.t_gps_s[m]
        k = (tr.t_gps_s >= t[0] - 1.0) & (tr.t_gps_s <= t[-1] + 1.0)
        window = Trajectory(tr.t_gps_s[k], tr.p_lgf_m[k], tr.rpy_rad[k], tr.frame)
        out.append(
            PassGeometry(
                p.id,
                p.relative_heading_rad,
                window,
                t,
                pts.range_m[m],
                pts.scan_angle_rad[m],
                sim.target_index[m],
            )
        )
    return out, sim.site


def test_the_passes_trajectories_give_the_gls_knots(passes):
    geoms, site = passes
    names = [t.name for t in site.targets]
    obs, _ = build_pass_observations(geoms, names, ObservationModel.from_site(site))
    tr = obs.trajectory
    assert tr is not None
    # the site's beam divergence: the GLS adds the footprint at each point's incidence
    assert obs.beam_half_divergence_rad == 0.5 * site.beam_divergence_rad > 0
    np.testing.assert_array_equal(tr.t_gps_s, np.concatenate([g.trajectory.t_gps_s for g in geoms]))
    fr = frame_for(obs, ErrorModel("gauss_markov", tuple(site.pos_correlation_time_s)), 100.0)
    assert fr.grid.exact and np.all(np.isin(fr.grid.t_s, tr.t_gps_s))
    # passes that overlap in time have no common trajectory (the GLS then uses a uniform grid)
    late = geoms[1].shifted(float(geoms[0].trajectory.t_gps_s[-1] - geoms[1].trajectory.t_gps_s[0]))
    assert joint_trajectory([geoms[0].trajectory, late.trajectory]) is None
    assert joint_trajectory([geoms[2].trajectory]) is geoms[2].trajectory


def test_the_thinned_gls_prediction_follows_the_full_density(passes):
    """Every k-th point with ``thin_step=k`` against all the points: within a few per cent
    (the k points a kept one stands for share its POS errors)."""
    geoms, site = passes
    rects = site.target_rectangles(site.frame())
    model = ObservationModel.from_site(site)
    full = predict_sigma(geoms, rects, site.mount, model)
    for k in (2, 4):
        thin = predict_sigma([g.thinned(k) for g in geoms], rects, site.mount, model, thin_step=k)
        np.testing.assert_allclose(thin.realistic_rad, full.realistic_rad, rtol=0.05)
        np.testing.assert_allclose(thin.formal_rad, full.formal_rad, rtol=0.05)


def test_the_gls_sigma_never_rises_when_a_pass_is_added(passes):
    """The GLS covariance is the inverse of an information matrix each pass adds to: per angle,
    the σ of the first k passes never exceeds that of the first k − 1 — and it lies below the
    thesis estimator's realistic σ of the same passes."""
    geoms, site = passes
    rects = site.target_rectangles(site.frame())
    gls, thesis = ObservationModel.from_site(site), ObservationModel.from_site(site, "thesis")
    prev = None
    for k in range(1, len(geoms) + 1):
        now = predict_sigma(geoms[:k], rects, site.mount, gls)
        th = predict_sigma(geoms[:k], rects, site.mount, thesis)
        np.testing.assert_array_equal(now.formal_rad, th.formal_rad)  # the same geometry gate
        ok = now.observable
        assert np.all(now.realistic_rad[ok] <= th.realistic_rad[ok])
        if prev is not None:
            for i, a in enumerate(ANGLES):
                if np.isfinite(prev[i]):
                    assert now.realistic_rad[i] <= prev[i] * (1 + 1e-12), (k, a)
        prev = now.realistic_rad
    assert now.observable.all()


def test_an_observation_model_refuses_gls_without_gauss_markov_errors(passes):
    _, site = passes
    m = ObservationModel.from_site(site)
    with pytest.raises(AdjustmentError, match="Gauss–Markov"):
        replace(m, error_model=ErrorModel("pass_bias"))
    with pytest.raises(AdjustmentError, match="estimator"):
        replace(m, estimator="oracle")
