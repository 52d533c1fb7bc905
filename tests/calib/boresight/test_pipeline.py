"""The calibration pipeline (calib.boresight.pipeline) on the simulator's Montreal site, in memory:
the estimator's statistics where its model holds, convergence from a 2° misalignment, the
labels and extraction routes, extra unknowns, and the clear errors."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from calib.boresight.observability import ObservabilityError
from calib.boresight.observations import AdjustmentError
from calib.boresight.pipeline import CalibrationError, CalibrationOptions, calibrate
from calib.boresight.report import report_markdown
from calib.io.bundle import ScanPoints
from calib.sim.simulate import simulate

#: The estimator's own stochastic model: independent POS errors for every point, and range
#: noise without the beam-divergence term the site's σ_range does not describe.
PER_POINT = {"noise.pos.model": "per_point", "noise.scanner.beam_divergence_mrad": 0.0}
FAST = CalibrationOptions(estimator="thesis", jackknife=False, error_model="white")
T1_ONLY = [
    {
        "name": "T1",
        "along_m": -1.75,
        "out_m": 0.03,
        "up_m": 5.0,
        "size_m": [1.23, 1.22],
        "inclination_deg": 90.0,
        "reflectivity": 0.9,
    }
]


def _run(r, options=FAST, **kw):
    return calibrate(r.site, r.trajectory_observed, r.points, options, **kw)


@pytest.mark.slow
def test_per_point_monte_carlo_through_the_extraction():
    """20 seeds of Montreal with per-point POS errors, targets extracted from the
    simulated returns: |estimate − truth| ≤ 3 σ_formal for ≥ 97 % of the 60 angles and the
    mean σ̂0² within [0.9, 1.1]."""
    z, s02 = [], []
    for seed in range(20):
        r = simulate("montreal", seed, overrides=PER_POINT)
        res = _run(r, poses=r.observed_poses()).result
        z.append((res.boresight_rad - r.mount_true.boresight_rad) / res.sigma_formal_rad)
        s02.append(res.sigma0_squared)
    z = np.array(z)
    assert np.mean(np.abs(z) <= 3.0) >= 0.97, z
    assert 0.9 <= np.mean(s02) <= 1.1, s02
    assert 0.7 < np.sqrt(np.mean(z**2)) < 1.4  # σ_formal is neither optimistic nor inflated


def test_labels_and_extraction_give_the_same_boresight():
    """The simulator's own labels and the extraction select nearly the same points (the
    extraction trims the targets' rims): the estimates agree within a formal σ."""
    r = simulate("montreal", 7, overrides=PER_POINT)
    poses = r.observed_poses()
    by_extraction = _run(r, poses=poses)
    by_labels = _run(r, poses=poses, labels=r.target_index)
    a, b = by_extraction.result, by_labels.result
    assert by_labels.doc["extraction"]["mode"] == "labels"
    totals = by_labels.extraction.totals()
    assert totals == {name: int(np.sum(r.target_index == j)) for j, name in enumerate(("T1", "T2"))}
    assert 0.85 * sum(totals.values()) < a.n_points < sum(totals.values())
    assert np.all(np.abs(a.boresight_rad - b.boresight_rad) < b.sigma_formal_rad)
    for res in (a, b):
        assert np.all(np.abs(res.boresight_rad - r.mount_true.boresight_rad) <= 3 * res.sigma_formal_rad)


@pytest.mark.parametrize("truth_deg", [(2.0, -2.0, 2.0), (-2.0, 2.0, -2.0), (2.0, 2.0, -1.0)])
def test_converges_from_a_two_degree_misalignment_within_six_iterations(truth_deg):
    """A priori 0, truth up to 2° in every angle, the scenario's Gauss–Markov POS errors: the
    extraction copes with targets displaced by ~0.6 m and the adjustment converges in ≤ 6
    iterations, to the same boresight as with strict absolute tolerances alone."""
    r = simulate("montreal", 2, overrides={"truth.boresight_deg": list(truth_deg)})
    options = CalibrationOptions(jackknife=False)
    run = _run(r, options)
    res = run.result
    assert run.warnings == []
    assert res.converged and res.iterations <= 6
    assert np.all(np.abs(res.boresight_rad - np.radians(truth_deg)) <= 3 * res.sigma_realistic_rad)
    strict = _run(r, replace(options, tol_angle_rad=1e-12, tol_m=1e-10, rel_tol=0.0)).result
    assert strict.converged and strict.iterations > res.iterations
    assert np.all(np.abs(res.boresight_rad - strict.boresight_rad) < 1e-3 * res.sigma_formal_rad)


def test_subsampling_and_an_extra_unknown():
    """--subsample 0.1 keeps one point per 10 cm voxel of each target and pass (the thesis's
    Table 4.3 density); a 3 cm range offset is estimated with its correlations to the
    boresight."""
    r = simulate("montreal", 3, overrides={**PER_POINT, "truth.range_offset_m": 0.03})
    full = _run(r, poses=r.observed_poses())
    thin = _run(r, replace(FAST, subsample_m=0.1, estimate=("range_offset",)), poses=r.observed_poses())
    assert thin.doc["extraction"]["subsample_m"] == 0.1
    assert 0.2 * full.result.n_points < thin.result.n_points < 0.6 * full.result.n_points
    e = thin.result.extras["range_offset"]
    assert abs(e["value"] - 0.03) <= 3 * e["sigma"] and e["sigma"] < 0.005
    assert set(thin.doc["extras"]["range_offset_m"]["correlation_with_boresight"]) == {"roll", "pitch", "yaw"}
    # the white error model: the realistic σ is the formal one
    assert thin.doc["extras"]["range_offset_m"]["sigma_realistic"] == e["sigma"]
    res = thin.result
    err = np.abs(res.boresight_rad - r.mount_true.boresight_rad)
    assert np.all(err <= 3 * res.sigma_formal_rad)


def test_an_extra_under_gauss_markov_pos_errors_is_judged_by_its_realistic_sigma():
    """No range offset injected, the scenario's Gauss–Markov POS errors: the estimated range
    offset is many formal σ from 0 (which would call it significant) but within its realistic
    σ, which result.json and the report state beside the formal one."""
    r = simulate("montreal", 3)
    assert r.mount_true.range_offset_m == 0.0
    run = _run(r, CalibrationOptions(estimator="thesis", jackknife=False, estimate=("range_offset",)))
    e = run.doc["extras"]["range_offset_m"]
    assert set(e) == {"value", "sigma", "sigma_realistic", "correlation_with_boresight"}
    assert abs(e["value"]) > 10 * e["sigma"]
    assert abs(e["value"]) <= 2 * e["sigma_realistic"]
    assert e["sigma_realistic"] > 10 * e["sigma"]
    row = next(x for x in report_markdown(run).splitlines() if x.startswith("| range_offset_m |"))
    cells = [c.strip().strip("*") for c in row.strip("|").split("|")]
    assert float(cells[2]) == pytest.approx(e["sigma"], rel=5e-3)
    assert float(cells[3]) == pytest.approx(e["sigma_realistic"], rel=5e-3)


def test_hitting_the_iteration_cap_is_a_warning_and_not_converged():
    """A 2° misalignment and an iteration cap of 1: the result says converged = False and the
    run warns not to use it (in result.json and in the report)."""
    r = simulate("montreal", 2, overrides={"truth.boresight_deg": [2.0, -2.0, 2.0]})
    run = _run(r, replace(FAST, max_iterations=1, outliers="none"), labels=r.target_index)
    assert run.result.converged is False and run.result.iterations == 1
    assert run.doc["converged"] is False and run.doc["iterations"] == 1
    warning = (
        "the adjustment did not converge in 1 iterations: do not use the result; check "
        "the a-priori boresight and the extraction"
    )
    assert run.warnings == [warning] and run.doc["warnings"] == [warning]
    md = report_markdown(run)
    assert "The adjustment **did not converge** in 1 iterations" in md
    assert f"- ⚠ {warning}" in md
    ok = _run(r, replace(FAST, max_iterations=6), labels=r.target_index)
    assert ok.result.converged and ok.warnings == []


def test_correlation_time_comes_from_the_site_else_the_default_is_stated():
    r = simulate("montreal", 4)
    run = _run(r, CalibrationOptions(estimator="thesis", jackknife=False))
    assert run.doc["realistic_error_model"] == {
        "kind": "gauss_markov",
        "correlation_time_s": [20.0, 20.0, 20.0, 10.0, 10.0, 10.0],
    }
    assert run.doc["realistic_correlation_time_source"].startswith("site.yaml")
    bare = replace(r.site, pos_correlation_time_s=None)
    run = calibrate(
        bare, r.trajectory_observed, r.points, CalibrationOptions(estimator="thesis", jackknife=False)
    )
    assert run.doc["realistic_error_model"]["correlation_time_s"] == 60.0
    assert any("assumes 60 s" in n for n in run.notes)
    res = run.result
    assert np.all(res.sigma_realistic_rad > 5 * res.sigma_formal_rad)
    forced = _run(r, CalibrationOptions(estimator="thesis", jackknife=False, correlation_time_s=5.0))
    assert forced.doc["realistic_error_model"]["correlation_time_s"] == 5.0
    assert forced.doc["realistic_correlation_time_source"] == "command line"


# -- clear, specific errors ---------------------------------------------------------------------


def test_only_reciprocal_parallel_passes_names_pitch_yaw_and_the_passes_to_sail():
    r = simulate(
        "montreal",
        0,
        overrides={
            "site.passes": [{"id": 1, "relative_heading_deg": 0}, {"id": 2, "relative_heading_deg": 180}]
        },
    )
    with pytest.raises(ObservabilityError) as e:
        _run(r)
    msg = str(e.value)
    assert "pitch and yaw are not observable with passes 1 (0°), 2 (180°)" in msg
    assert "45°/225° or 315°/135°" in msg and "45°/135° or 315°/225°" in msg


def test_a_single_target_is_refused():
    r = simulate("montreal", 0, overrides={"scene.targets": T1_ONLY})
    with pytest.raises(AdjustmentError, match=r"only one target \(T1\)"):
        _run(r)


def test_a_target_with_fewer_than_ten_points_is_named():
    r = simulate("montreal", 0)
    labels = r.target_index.copy()
    t2 = np.flatnonzero(labels == 1)
    labels[t2[7:]] = -1  # 7 points of T2 left
    with pytest.raises(AdjustmentError, match=r"fewer than 10 points: T2 \(7 points\)"):
        _run(r, labels=labels)
    # an 8 cm target is too small to be extracted in any pass: warned per pass, then refused
    tiny = simulate("montreal", 0, overrides={"scene.targets.1.size_m": [0.08, 0.08]})
    with pytest.raises(AdjustmentError, match=r"fewer than 10 points: T2 \(0 points\)"):
        _run(tiny)


def test_a_target_without_three_points_in_any_pass_is_named():
    """Enough points over all passes but fewer than 3 in each: no pass gives it an a-priori
    plane, and the error names it (it was a TypeError in the adjustment)."""
    r = simulate("montreal", 0)
    labels = r.target_index.copy()
    t2 = np.flatnonzero(labels == 1)
    for pid in np.unique(r.points.pass_id[t2]):
        labels[t2[r.points.pass_id[t2] == pid][2:]] = -1  # 2 points of T2 per pass
    assert np.count_nonzero(labels == 1) >= 10
    with pytest.raises(CalibrationError, match=r"target\(s\) T2: no pass holds 3 of its points"):
        _run(r, labels=labels)


def _points_with(r, **arrays) -> ScanPoints:
    p = r.points
    fields = {
        f: getattr(p, f).copy() for f in ("pass_id", "t_gps_s", "range_m", "scan_angle_rad", "intensity")
    }
    for name, (index, value) in arrays.items():
        fields[name][index] = value
    return ScanPoints(**fields)


def test_nan_and_out_of_order_times_are_refused():
    r = simulate("montreal", 0)
    pts = _points_with(r, t_gps_s=(100, np.nan))
    with pytest.raises(
        CalibrationError,
        match=r"1 point time\(s\) are NaN or infinite "
        r"\(first: point 100, pass 1\)",
    ):
        calibrate(r.site, r.trajectory_observed, pts, FAST)
    t = r.points.t_gps_s
    pts = _points_with(r, t_gps_s=(200, t[198]))
    with pytest.raises(CalibrationError, match="point times go backwards within pass 1 at point 200"):
        calibrate(r.site, r.trajectory_observed, pts, FAST)


def test_a_trajectory_that_does_not_cover_the_points_is_refused():
    r = simulate("montreal", 0)
    traj = r.trajectory_observed
    cut = traj.select(traj.t_gps_s < r.points.t_gps_s[r.points.pass_id == 4].min())
    with pytest.raises(CalibrationError) as e:
        calibrate(r.site, cut, r.points, FAST)
    msg = str(e.value)
    assert msg.startswith("the trajectory does not cover the points")
    n4 = int(np.sum(r.points.pass_id == 4))
    assert f"pass 4: {n4} of {n4} points" in msg and "pass 6:" in msg and "pass 3:" not in msg


def test_a_target_missing_from_one_pass_is_a_warning_and_the_run_continues():
    r = simulate("montreal", 0)
    keep = ~((r.target_index == 1) & (r.points.pass_id == 3))
    run = calibrate(r.site, r.trajectory_observed, r.points.select(keep), CalibrationOptions(jackknife=False))
    assert [w for w in run.warnings if "missing" in w] == [
        "target T2 is missing from pass 3: no plane with its orientation among its points"
    ]
    assert run.doc["warnings"] == run.warnings
    assert run.doc["extraction"]["points_per_pass"]["3"]["T2"] == 0
    res = run.result
    assert res.converged
    err = np.abs(res.boresight_rad - r.mount_true.boresight_rad)
    assert np.all(err <= 3 * res.sigma_realistic_rad)


def test_a_trajectory_far_from_the_site_names_the_distance():
    """The trajectory 470 km from the targets (another datum, a wrong reference point): one
    error naming the closest approach per target, before any extraction."""
    r = simulate("montreal", 0)
    far = replace(r.trajectory_observed, p_lgf_m=r.trajectory_observed.p_lgf_m + [470e3, 0.0, 0.0])
    with pytest.raises(CalibrationError, match=r"closest approach is T1 4\d\d\.\d km, T2 4\d\d\.\d km"):
        calibrate(r.site, far, r.points, FAST)
