"""Boresight adjustment on synthetic plane observations (tests/calib/synth.py)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy import stats

from calib.boresight.adjust import adjust
from calib.boresight.covariance import predict_covariance
from calib.boresight.errormodel import ErrorModel
from calib.boresight.observability import ObservabilityError
from calib.boresight.observations import AdjustmentError, AdjustOptions, build_observations
from calib.boresight.report import _chi2_sentence, extras_table
from calib.boresight.result import result_to_dict
from calib.core.georef import Mount
from calib.core.trajectory import Trajectory
from tests.calib import synth

TRUTH_RAD = np.radians([0.208, 1.245, 0.149])
WHITE = ErrorModel("white")
QUICK = AdjustOptions(estimator="thesis", jackknife=False, error_model=WHITE)


@pytest.fixture(scope="module")
def clean():
    """Noise-free observations of the Montreal-like site and the true planes."""
    obs, planes, _ = synth.observations(
        Mount(boresight_rad=TRUTH_RAD), synth.montreal_planes(), points_per_plane_per_pass=60, noise=False
    )
    return obs, planes


def _with_noise(obs, seed, sigma_scale=1.0):
    rng = np.random.default_rng(seed)
    out = obs.select(np.ones(len(obs), bool))
    out.l = obs.l + rng.standard_normal(obs.l.shape) * obs.sigma_l * sigma_scale
    return out


@pytest.mark.parametrize("truth_deg", [(2.0, -2.0, 2.0), (-1.5, 2.0, -0.7), (0.2, 1.2, 0.1)])
def test_converges_from_zero_within_six_iterations(truth_deg):
    truth = np.radians(truth_deg)
    obs, planes, _ = synth.observations(
        Mount(boresight_rad=truth), synth.montreal_planes(), points_per_plane_per_pass=40, noise=False
    )
    # planes initialized as the extraction would: offset and tilted by the a-priori error
    init = [(n + np.array([0.02, -0.03, 0.01]), d + 0.1) for n, d in planes]
    res = adjust(obs, Mount(), init, QUICK)
    assert res.converged and res.iterations <= 6
    np.testing.assert_allclose(np.degrees(res.boresight_rad), truth_deg, atol=1e-9)


def test_per_point_monte_carlo_covers_truth_and_sigma0(clean):
    obs, planes = clean
    z, s02 = [], []
    for seed in range(20):
        res = adjust(_with_noise(obs, seed), Mount(), planes, QUICK)
        z.append((res.boresight_rad - TRUTH_RAD) / res.sigma_formal_rad)
        s02.append(res.sigma0_squared)
        assert res.chi2_test()["df"] == len(obs) - 3 - 3 * 2
    z = np.array(z)
    assert np.mean(np.abs(z) <= 3.0) >= 0.97
    assert 0.9 <= np.mean(s02) <= 1.1
    # not trivially wide: the normalized errors have a spread near 1
    assert 0.6 < np.sqrt(np.mean(z**2)) < 1.5


def _gauss_markov(t, sigma, tau, rng):
    order = np.argsort(t)
    ts = t[order]
    a = np.exp(-np.diff(ts) / tau)
    eps = rng.standard_normal(ts.size)
    x = np.empty(ts.size)
    x[0] = sigma * eps[0]
    b = np.sqrt(1 - a * a) * sigma
    for i in range(1, ts.size):
        x[i] = a[i - 1] * x[i - 1] + b[i - 1] * eps[i]
    out = np.empty_like(x)
    out[order] = x
    return out


@pytest.mark.slow
def test_realistic_sigma_matches_gauss_markov_spread(clean):
    """The propagated covariance predicts the spread of the estimates under time-correlated
    POS errors (position and attitude, τ = 30 s), while the formal σ is far too small."""
    obs, planes = clean
    tau = 30.0
    model = ErrorModel("gauss_markov", tau)
    errs, real, formal = [], None, None
    for seed in range(120):
        rng = np.random.default_rng(seed)
        o = obs.select(np.ones(len(obs), bool))
        l = obs.l.copy()
        for c in range(6):
            l[:, c] += _gauss_markov(obs.t_gps_s, obs.sigma_l[0, c], tau, rng)
        l[:, 6:] += rng.standard_normal((len(obs), 2)) * obs.sigma_l[:, 6:]
        o.l = l
        res = adjust(
            o,
            Mount(),
            planes,
            AdjustOptions(estimator="thesis", jackknife=False, error_model=model, outliers="none"),
        )
        errs.append(res.boresight_rad - TRUTH_RAD)
        real, formal = res.sigma_realistic_rad, res.sigma_formal_rad
    spread = np.std(errs, axis=0)
    ratio = spread / real
    assert np.all((ratio > 0.75) & (ratio < 1.33)), ratio
    assert np.all(spread / formal > 3.0)  # the formal σ would mislead
    assert np.mean(np.abs(np.array(errs)) <= 2 * real) >= 0.9


def test_outliers_are_found_and_listed(clean):
    obs, planes = clean
    o = _with_noise(obs, 5)
    bad = np.array([3, 100, 250, 400, 555])
    # gross errors that move points 25 cm off their plane (≈ 10 σ of the condition); a range
    # blunder at grazing incidence would mostly slide along the plane, invisible and harmless
    normals = np.array([n for n, _ in planes])
    o.l[bad, 0:3] += 0.25 * normals[o.plane_index[bad]]
    res = adjust(o, Mount(), planes, QUICK)
    assert set(bad) <= set(res.outlier_point_ids.tolist())
    assert res.outlier_point_ids.size <= bad.size + 3
    assert np.all(np.abs(res.boresight_rad - TRUTH_RAD) <= 4 * res.sigma_formal_rad)


def _spread_site():
    """Targets spread along the wall, in range and in height (what the design study favours)."""
    return synth.montreal_planes(spread_m=12.0) + [
        synth.Rectangle.from_orientation(
            "T3", [0.0, 25.0, -15.0], 1.2, 1.2, np.radians(60.0), np.radians(270.0)
        ),
    ]


@pytest.mark.parametrize(
    ("name", "mount_kw", "value", "spread"),
    [
        ("range_offset", {"range_offset_m": 0.04}, 0.04, False),
        ("lever_arm_y", {"lever_arm_m": [0.0, 0.05, 0.0]}, 0.05, False),
        ("lever_arm_x", {"lever_arm_m": [0.05, 0.0, 0.0]}, 0.05, True),
    ],
)
def test_extra_unknowns_recover_injected_values(name, mount_kw, value, spread):
    mount_true = Mount(boresight_rad=TRUTH_RAD, **mount_kw)
    planes_rect = _spread_site() if spread else synth.montreal_planes()
    obs, planes, _ = synth.observations(mount_true, planes_rect, points_per_plane_per_pass=60, noise=False)
    apriori = Mount(nominal_rad=mount_true.nominal_rad)
    res = adjust(
        obs,
        apriori,
        planes,
        AdjustOptions(estimator="thesis", estimate=(name,), jackknife=False, error_model=WHITE),
    )
    assert res.extras[name]["value"] == pytest.approx(value, abs=1e-9)
    np.testing.assert_allclose(res.boresight_rad, TRUTH_RAD, atol=1e-10)
    corr = res.extras[name]["correlation_with_boresight"]
    assert len(corr) == 3 and all(-1 <= c <= 1 for c in corr)


def test_scan_angle_offset_is_refused_as_part_of_the_boresight():
    """A scan-angle offset is a rotation about the scanner's x axis: for any mount the boresight
    contains it (thesis §3.5.2 finds them correlated), so asking for it is a clear error."""
    with pytest.raises(AdjustmentError, match="rotation about the scanner's own x axis"):
        AdjustOptions(estimate=("scan_angle_offset",))


def test_lever_arm_x_and_pitch_are_confused_on_a_two_target_site(clean):
    """On the thesis's site (two targets at one range) an along-track lever-arm error looks like
    a pitch boresight; the error says so instead of printing a number."""
    obs, planes = clean
    with pytest.raises(ObservabilityError, match="pitch.*lever_arm_x"):
        adjust(obs, Mount(), planes, AdjustOptions(estimate=("lever_arm_x",)))


def test_a_latency_without_the_trajectory_is_refused(clean):
    """Observations built without a trajectory cannot move the poses with Δt: a clear error
    (it was an AttributeError on None)."""
    obs, planes = clean
    assert obs.trajectory is None
    with pytest.raises(AdjustmentError, match="estimating the latency needs the trajectory"):
        adjust(obs, Mount(), planes, AdjustOptions(estimate=("latency",), jackknife=False))


def test_latency_is_estimated_from_the_trajectory():
    """With one trajectory spanning all passes, a 5 ms LiDAR–POS latency is recovered (on a
    site spread in range: at one range a time shift looks like a pitch, as lever arm x does)."""
    mount_true = Mount(boresight_rad=TRUTH_RAD, time_offset_s=0.005)
    obs, planes, trajs = synth.observations(
        mount_true, _spread_site(), points_per_plane_per_pass=60, noise=False
    )
    traj = Trajectory(
        np.concatenate([t.t_gps_s for t in trajs]),
        np.concatenate([t.p_lgf_m for t in trajs]),
        np.concatenate([t.rpy_rad for t in trajs]),
        synth.FRAME,
        max_gap_s=500.0,
    )
    sig = obs.sigma_l[0]
    ob2 = build_observations(
        traj,
        obs.t_gps_s,
        obs.l[:, 6],
        obs.l[:, 7],
        obs.plane_index,
        np.array(obs.pass_ids)[obs.pass_index],
        obs.plane_names,
        sig[6],
        sig[7],
        sig[0:3],
        sig[3:6],
        pass_headings_rad=obs.pass_headings_rad,
    )
    res = adjust(
        ob2,
        Mount(),
        planes,
        AdjustOptions(estimator="thesis", estimate=("latency",), jackknife=False, error_model=WHITE),
    )
    assert res.extras["latency"]["value"] == pytest.approx(0.005, abs=1e-7)
    np.testing.assert_allclose(res.boresight_rad, TRUTH_RAD, atol=1e-8)
    # reported with its correlations to the boresight (from the formal covariance), in the
    # adjustment's result and in result.json
    j = res.names.index("latency")
    sd = np.sqrt(np.diag(res.cov_all))
    expected = res.cov_all[j, 0:3] / (sd[j] * sd[0:3])
    e = res.extras["latency"]
    np.testing.assert_allclose(e["correlation_with_boresight"], expected, rtol=1e-12)
    assert np.all(np.abs(expected) <= 1.0) and np.max(np.abs(expected)) > 0.01
    assert e["sigma"] == pytest.approx(sd[j]) and e["sigma_realistic"] == e["sigma"]  # white
    doc = result_to_dict(res, np.zeros(3), "test")["extras"]["latency_s"]
    assert doc["correlation_with_boresight"] == dict(zip(("roll", "pitch", "yaw"), expected))
    assert doc["sigma_realistic"] == doc["sigma"]


def test_prediction_equals_the_formal_covariance_of_the_adjustment(clean):
    obs, planes = clean
    res = adjust(_with_noise(obs, 1, sigma_scale=1e-6), Mount(), planes, QUICK)
    pred = predict_covariance(obs, Mount(boresight_rad=TRUTH_RAD), planes)
    np.testing.assert_allclose(pred["formal"], res.cov_formal, rtol=1e-4)
    gm = predict_covariance(obs, Mount(boresight_rad=TRUTH_RAD), planes, model=ErrorModel("pass_bias"))
    assert np.all(np.diag(gm["realistic"]) > 10 * np.diag(pred["formal"]))


def test_pass_offsets_absorb_per_pass_translations():
    """A 5 cm translation of each pass's trajectory biases the plain estimate; estimating
    pass offsets on a site whose targets are spread in range and height removes it."""
    planes = _spread_site()
    obs, truth_planes, _ = synth.observations(
        Mount(boresight_rad=TRUTH_RAD), planes, points_per_plane_per_pass=60, noise=False
    )
    shifts = np.random.default_rng(2).normal(0.0, 0.05, (len(obs.pass_ids), 3))
    o = obs.select(np.ones(len(obs), bool))
    o.l[:, 0:3] += shifts[o.pass_index]
    plain = adjust(o, Mount(), truth_planes, QUICK)
    with_offsets = adjust(
        o,
        Mount(),
        truth_planes,
        AdjustOptions(
            estimator="thesis",
            estimate=("pass_offsets",),
            jackknife=False,
            error_model=WHITE,
            pass_offset_sigma_m=[0.1, 0.1, 0.1],
            max_sigma_rad=np.radians(1.0),
        ),
    )
    err_plain = np.abs(plain.boresight_rad - TRUTH_RAD).max()
    err_off = np.abs(with_offsets.boresight_rad - TRUTH_RAD).max()
    assert err_plain > np.radians(0.01)
    assert err_off < err_plain / 20
    # each pass offset is reported with its 3 × 3 correlation with the boresight (rows north,
    # east, down; columns roll, pitch, yaw), in the result, result.json and the report
    res = with_offsets
    sd = np.sqrt(np.diag(res.cov_all))
    doc = result_to_dict(res, np.zeros(3), "test")["extras"]
    for pid in o.pass_ids:
        e = res.extras[f"pass{pid}_offset_m"]
        rows = [res.names.index(f"pass{pid}.offset_{c}") for c in ("north", "east", "down")]
        expected = res.cov_all[np.ix_(rows, range(3))] / np.outer(sd[rows], sd[0:3])
        np.testing.assert_allclose(e["correlation_with_boresight"], expected, rtol=1e-12)
        np.testing.assert_allclose(e["sigma_realistic"], sd[rows], rtol=1e-12)  # white model
        d = doc[f"pass{pid}_offset_m"]["correlation_with_boresight"]
        assert list(d) == ["north", "east", "down"]
        assert [[d[c][a] for a in ("roll", "pitch", "yaw")] for c in d] == expected.tolist()
    # on a site spread in range and height the offsets and the angles separate: |ρ| small,
    # but not zero
    rho = np.abs([e["correlation_with_boresight"] for e in res.extras.values()])
    assert 0.01 < rho.max() < 0.5
    table = extras_table(doc)
    row = next(x for x in table if x.startswith("| pass1_offset_m down |"))
    cells = [c.strip().strip("*") for c in row.strip("|").split("|")]
    assert float(cells[1]) == pytest.approx(res.extras["pass1_offset_m"]["value"][2], abs=1e-6)
    assert [float(x) for x in cells[4:7]] == pytest.approx(
        res.extras["pass1_offset_m"]["correlation_with_boresight"][2], abs=5e-3
    )
    assert sum(x.startswith("| pass") for x in table) == 3 * len(o.pass_ids)


def test_extras_carry_a_realistic_sigma_under_gauss_markov_pos_errors(clean):
    """A range offset estimated (truth 0) under time-correlated POS errors (τ = 30 s): the
    formal σ makes most estimates look significant, its realistic σ covers the truth."""
    obs, planes = clean
    tau = 30.0
    model = ErrorModel("gauss_markov", tau)
    value, formal, real = [], [], []
    for seed in range(30):
        rng = np.random.default_rng(seed)
        o = obs.select(np.ones(len(obs), bool))
        o.l = obs.l.copy()
        for c in range(6):
            o.l[:, c] += _gauss_markov(obs.t_gps_s, obs.sigma_l[0, c], tau, rng)
        o.l[:, 6:] += rng.standard_normal((len(obs), 2)) * obs.sigma_l[:, 6:]
        res = adjust(
            o,
            Mount(),
            planes,
            AdjustOptions(
                estimator="thesis",
                estimate=("range_offset",),
                jackknife=False,
                error_model=model,
                outliers="none",
            ),
        )
        e = res.extras["range_offset"]
        value.append(e["value"])
        formal.append(e["sigma"])
        real.append(e["sigma_realistic"])
    value, formal, real = map(np.array, (value, formal, real))
    assert np.all(real > 5 * formal)
    assert np.mean(np.abs(value) > 3 * formal) >= 0.5  # the formal σ would mislead
    assert np.mean(np.abs(value) <= 2 * real) >= 0.9
    assert 0.6 < np.std(value) / np.mean(real) < 1.5  # and it is not merely wide


def test_chi2_test_bounds_are_the_two_sided_quantiles_and_the_verdict_flips(clean):
    """σ̂0² = vᵀPv / df with df·σ̂0² ~ χ²(df): accepted within [χ²_{α/2}, χ²_{1−α/2}] / df."""
    obs, planes = clean
    res = adjust(_with_noise(obs, 4), Mount(), planes, QUICK)
    for alpha in (0.05, 0.01):
        c = res.chi2_test(alpha)
        df = len(obs) - 3 - 3 * 2
        assert c["df"] == df == res.df
        assert c["lower"] == pytest.approx(stats.chi2.ppf(alpha / 2, df) / df, rel=1e-12)
        assert c["upper"] == pytest.approx(stats.chi2.ppf(1 - alpha / 2, df) / df, rel=1e-12)
        assert c["lower"] < 1.0 < c["upper"]
        for s02, passed in (
            (1.0, True),
            (c["lower"] * 1.001, True),
            (c["upper"] * 0.999, True),
            (c["lower"] * 0.999, False),
            (c["upper"] * 1.001, False),
        ):
            assert replace(res, sigma0_squared=s02).chi2_test(alpha)["passed"] is passed, s02
    # wider at α = 0.01 than at 0.05
    assert res.chi2_test(0.01)["lower"] < res.chi2_test(0.05)["lower"]
    assert result_to_dict(res, np.zeros(3), "test")["chi2_test"] == res.chi2_test()
    c = res.chi2_test()
    assert "**failed (high)**" in _chi2_sentence(replace(res, sigma0_squared=c["upper"] * 1.5))
    assert "**failed (low)**" in _chi2_sentence(replace(res, sigma0_squared=c["lower"] * 0.5))


def test_hitting_the_iteration_cap_is_not_converged():
    """From a 2° misalignment one iteration cannot converge: converged is False, with the
    iterations done; six iterations do."""
    truth = np.radians([2.0, -2.0, 2.0])
    obs, planes, _ = synth.observations(
        Mount(boresight_rad=truth), synth.montreal_planes(), points_per_plane_per_pass=40, noise=False
    )
    for cap in (1, 2):
        res = adjust(obs, Mount(), planes, replace(QUICK, outliers="none", max_iterations=cap))
        assert not res.converged and res.iterations == cap
    res = adjust(obs, Mount(), planes, replace(QUICK, max_iterations=6))
    assert res.converged and res.iterations <= 6


# -- clear, specific errors ------------------------------------------------------------------


def test_only_reciprocal_parallel_passes_names_pitch_and_yaw():
    obs, planes, _ = synth.observations(
        Mount(boresight_rad=TRUTH_RAD),
        synth.montreal_planes(),
        headings_deg=(0.0, 180.0),
        points_per_plane_per_pass=60,
    )
    with pytest.raises(ObservabilityError) as e:
        adjust(obs, Mount(), planes, QUICK)
    msg = str(e.value)
    assert "pitch" in msg and "yaw" in msg and "not observable" in msg
    assert "45°/225°" in msg and "45°/135°" in msg


def test_single_target_is_refused(clean):
    obs, planes = clean
    one = obs.select(obs.plane_index == 0)
    one.plane_names = ["T1"]
    with pytest.raises(AdjustmentError, match="only one target \\(T1\\)"):
        adjust(one, Mount(), planes[:1], QUICK)


def test_target_with_too_few_points_is_named(clean):
    obs, planes = clean
    keep = (obs.plane_index == 0) | (np.cumsum(obs.plane_index == 1) <= 7)
    with pytest.raises(AdjustmentError, match=r"fewer than 10 points: T2 \(7 points\)"):
        adjust(obs.select(keep), Mount(), planes, QUICK)


def _one_traj():
    t = np.arange(0.0, 10.0, 0.1) + 1000.0
    n = t.size
    return Trajectory(t, np.zeros((n, 3)), np.zeros((n, 3)), synth.FRAME)


def _build(t, pass_id=None, traj=None):
    n = len(t)
    return build_observations(
        traj or _one_traj(),
        np.asarray(t),
        np.full(n, 10.0),
        np.zeros(n),
        np.zeros(n, int),
        np.ones(n, int) if pass_id is None else pass_id,
        ["T1"],
        0.003,
        1e-4,
        np.full(3, 0.02),
        np.full(3, 1e-4),
    )


def test_nan_times_are_refused():
    with pytest.raises(AdjustmentError, match="1 point time\\(s\\) are NaN"):
        _build([1001.0, np.nan, 1002.0])


def test_out_of_order_times_are_refused():
    with pytest.raises(AdjustmentError, match="go backwards within pass 1 at point 2"):
        _build([1001.0, 1002.0, 1001.5])


def test_points_outside_the_trajectory_are_refused():
    with pytest.raises(AdjustmentError, match="does not cover the points.*2 of 3 times"):
        _build([1001.0, 1020.0, 1030.0])


def test_one_gls_iteration_with_roughness_stops_unconverged_instead_of_crashing():
    """The GLS with its roughness components and an iteration cap of 1 (it once raised
    UnboundLocalError there): one iteration, not converged; a cap outside 1…1000 is refused."""
    truth = np.radians([2.0, -2.0, 2.0])
    obs, planes, _ = synth.observations(
        Mount(boresight_rad=truth), synth.montreal_planes(), points_per_plane_per_pass=40, noise=True
    )
    gls = AdjustOptions(jackknife=False, outliers="none", roughness="all", max_iterations=1)
    res = adjust(obs, Mount(), planes, gls)
    assert res.iterations == 1 and not res.converged
    for cap in (0, -3, 1001, 2.5):
        with pytest.raises(AdjustmentError, match="max_iterations"):
            AdjustOptions(max_iterations=cap)
