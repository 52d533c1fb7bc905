"""A calibration on the simulator's montreal site with piles before the wall (scenario
``montreal_piles``): the piles are found, chosen as tie cylinders and fitted where the simulator
put them; the report states what each kind of feature adds against the Cramér–Rao bound."""

from __future__ import annotations

import numpy as np
import pytest

from calib.boresight.pipeline import CalibrationOptions, calibrate
from calib.boresight.report import report_markdown
from calib.sim.simulate import simulate


@pytest.fixture(scope="module")
def piles():
    sim = simulate("montreal_piles", 1)
    run = calibrate(sim.site, sim.trajectory_observed, sim.points, CalibrationOptions(jackknife=False))
    return sim, run


def test_the_piles_are_chosen_as_tie_cylinders_where_they_stand(piles):
    """Every chosen cylinder is one of the simulator's piles: its axis within 2 cm and its
    radius within 1 cm of the truth (a centre per pass: the POS errors do not bend them)."""
    sim, run = piles
    doc = run.doc
    assert run.result.converged and run.result.iterations <= 10
    cyls = doc["tie_cylinders"]
    assert len(cyls) >= 3, doc.get("tie_cylinder_candidates")
    truth = sim.scene.cylinders
    for c in cyls:
        d = [np.hypot(*(np.array(c["axis_center_lgf_m"][:2]) - t.center_m[:2])) for t in truth]
        j = int(np.argmin(d))
        assert d[j] < 0.02 and abs(c["radius_m"] - truth[j].radius_m) < 0.01, (c, truth[j])
    shapes = {p["name"]: p["shape"] for p in doc["planes"]}
    assert {c["name"] for c in cyls} == {n for n, s in shapes.items() if s == "cylinder"}


def test_the_cylinders_shrink_the_bound_and_the_estimate_covers_the_truth(piles):
    """The Cramér–Rao σ of yaw falls as the patches and then the cylinders are added, and the
    estimate is within 3σ of the truth on every angle."""
    sim, run = piles
    crlb = run.doc["crlb_by_features_deg"]
    assert list(crlb) == ["targets", "+ planar patches", "+ cylinders"]
    yaw = [crlb[k][2] for k in crlb]
    assert yaw[2] < yaw[1] <= yaw[0], crlb
    assert yaw[2] <= 0.8 * yaw[0], crlb
    err = np.abs(run.result.boresight_rad - sim.mount_true.boresight_rad)
    assert np.all(err <= 3 * run.result.sigma_realistic_rad), (err, run.result.sigma_realistic_rad)


def test_the_report_tables_the_cylinders_and_the_bounds(piles):
    _, run = piles
    md = report_markdown(run)
    assert "Tie cylinders:" in md and "| cylinder | points |" in md
    for name in (c["name"] for c in run.doc["tie_cylinders"]):
        assert f"| {name} |" in md
    assert "| features | roll (mdeg) | pitch (mdeg) | yaw (mdeg) |" in md
    assert "| + cylinders |" in md


def test_a_harbour_site_keeps_its_piles_beside_a_hundred_wall_patches():
    """harbour_cal: a long wall with fenders and a wing wall gives over a hundred patch
    candidates, which under white weights look as if they fixed yaw; the piles keep a budget of
    their own and take the yaw bound well below the patches' (the GLS with the POS errors'
    correlation), and the estimate covers the truth."""
    sim = simulate("harbour_cal", 2)
    run = calibrate(sim.site, sim.trajectory_observed, sim.points, CalibrationOptions(jackknife=False))
    doc = run.doc
    assert doc["tie_patch_candidates"]["found"] > 100 and len(doc["tie_patches"]) == 30
    assert len(doc["tie_cylinders"]) >= 3, doc.get("tie_cylinder_candidates")
    crlb = doc["crlb_by_features_deg"]
    assert crlb["+ cylinders"][2] < 0.75 * crlb["+ planar patches"][2], crlb
    err = np.abs(run.result.boresight_rad - sim.mount_true.boresight_rad)
    assert np.all(err <= 3 * run.result.sigma_realistic_rad), (err, run.result.sigma_realistic_rad)


def test_the_cylinders_have_a_budget_of_their_own_and_no_least_gain():
    from calib.boresight.scene_ties import MIN_GAIN, choose

    rng = np.random.default_rng(3)
    eye = np.eye(3)
    patches = [np.diag(rng.uniform(1.0, 10.0, 3)) for _ in range(8)]  # each fixes every angle a bit
    piles = [1e-3 * eye, 2e-3 * eye, 5e-4 * eye]  # small gains: below MIN_GAIN
    info = np.stack(patches + piles)
    is_cyl = np.arange(len(info)) >= len(patches)
    chosen, gains = choose(info, eye, max_patches=4, is_cylinder=is_cyl, max_cylinders=2)
    assert sum(not is_cyl[j] for j in chosen) == 4  # the patches' budget
    assert sorted(j for j in chosen if is_cyl[j]) == [8, 9]  # the two best piles, below MIN_GAIN
    assert all(g < MIN_GAIN for j, g in zip(chosen, gains, strict=True) if is_cyl[j])
    # without kinds: one budget, the least gain for all (the piles are not worth their planes)
    plain, _ = choose(info, eye, max_patches=20)
    assert len(plain) == 8 and not any(is_cyl[j] for j in plain)
    # a pile with fewer points than the adjustment takes is never chosen, however few compete
    counts = np.array([50] * 8 + [9, 40, 0])
    few, _ = choose(info, eye, max_patches=4, is_cylinder=is_cyl, max_cylinders=3, n_points=counts)
    assert sorted(j for j in few if is_cyl[j]) == [9]


def test_piles_leaning_like_driven_piles_are_left_out_not_fitted_upright():
    """montreal_piles with its piles leaning 0.7–1.0° (the simulator leans them; the adjustment
    models upright cylinders): every pile is rejected as leaning, no patch is cut on one, and
    the estimate covers the truth (kept upright, they biased roll by 1σ on average)."""
    leans = {
        "P1": "[0.8, -0.4]",
        "P2": "[-0.5, 0.9]",
        "P3": "[0.3, 0.6]",
        "P4": "[-1.0, -0.2]",
        "P5": "[0.6, -0.7]",
    }
    sim = simulate("montreal_piles", 3, overrides=[f"scene.piles.{k}.lean_deg={v}" for k, v in leans.items()])
    run = calibrate(sim.site, sim.trajectory_observed, sim.points, CalibrationOptions(jackknife=False))
    doc = run.doc
    assert not doc.get("tie_cylinders") and doc["tie_cylinder_candidates"]["rejected"]["leaning"] >= 4
    assert "rejected as leaning: the adjustment models upright piles" in report_markdown(run)
    err = np.abs(run.result.boresight_rad - sim.mount_true.boresight_rad)
    assert np.all(err <= 3 * run.result.sigma_realistic_rad), (err, run.result.sigma_realistic_rad)
