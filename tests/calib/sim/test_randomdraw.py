"""The randomized calibration scenario (``--scenario random --seed N``): reproducible from its
seed, within the stated ranges, sailed so that the targets are seen, written as a bundle that
reads back, with the draw in truth.json."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from calib.io.bundle import read_bundle, read_truth
from calib.sim.randomdraw import (
    draw_geometry,
    random_scenario,
    scenario_document,
    targets_along_m,
    wall_clearance_m,
    wall_shape,
)
from calib.sim.simulate import simulate
from cli.app import app

SEEDS = st.integers(min_value=0, max_value=2**32 - 1)
SIX_FOLD_DEG = np.array([0.0, 180.0, 45.0, 225.0, 315.0, 135.0])


def test_the_same_seed_draws_the_same_geometry():
    assert draw_geometry(7).to_dict() == draw_geometry(7).to_dict()
    assert draw_geometry(7).to_dict() != draw_geometry(8).to_dict()
    assert random_scenario(7).to_dict() == random_scenario(7).to_dict()


@settings(max_examples=300, deadline=None)
@given(SEEDS)
def test_the_draw_stays_within_the_stated_ranges(seed):
    g = draw_geometry(seed)
    roll_deg, pitch_deg, yaw_deg = np.degrees(g.nominal_rad)
    assert abs(roll_deg) <= 30 and abs(pitch_deg) <= 30 and yaw_deg == 0
    assert 0 <= g.wall_azimuth_rad < 2 * np.pi
    assert 5 <= g.standoff_m <= 40
    incl_deg = sorted(np.degrees(t.inclination_rad) for t in g.targets)
    assert len(g.targets) in (2, 3) and incl_deg[-1] == 90 and 30 <= incl_deg[0] <= 60
    assert all(0 <= t.proud_m <= 0.6 for t in g.targets)
    along = sorted(t.along_m for t in g.targets)
    assert np.all(np.diff(along) >= 2.0) and abs(np.mean(along)) < 1e-9
    assert 1 - 1e-12 <= g.contrast <= 4 + 1e-12 and g.target_reflectivity <= 0.95
    assert 0 <= g.wall_waviness_m <= 0.012
    assert np.all((g.wall_beyond_m[:2] >= 2) & (g.wall_beyond_m[:2] <= 25))
    assert np.all((g.wall_beyond_m[2:] >= 0.6) & (g.wall_beyond_m[2:] <= 4))
    assert np.all(np.abs(g.lever_arm_m) <= [1, 1, 2])
    assert np.all(np.abs(np.degrees(g.boresight_rad)) <= 2)
    assert 0.005 <= g.sigma_position_m <= 0.03
    assert 0.002 <= np.degrees(g.sigma_attitude_rad) <= 0.01
    assert 5 <= g.tau_position_s <= 60 and 5 <= g.tau_attitude_s <= 60
    assert np.all(np.abs(np.degrees(g.relative_headings_rad) - SIX_FOLD_DEG) <= 5)


@settings(max_examples=40, deadline=None)
@given(SEEDS)
def test_the_scenario_is_the_draw_and_its_passes_can_be_sailed(seed):
    g = draw_geometry(seed)
    sc = random_scenario(seed)
    assert sc.standoff_m == g.standoff_m and sc.wall_azimuth_rad == pytest.approx(g.wall_azimuth_rad)
    np.testing.assert_allclose(sc.mount.nominal_rad, g.nominal_rad, atol=1e-12)
    np.testing.assert_allclose(sc.mount.lever_arm_m, g.lever_arm_m)
    np.testing.assert_allclose(sc.truth.boresight_rad, g.boresight_rad, atol=1e-12)
    np.testing.assert_allclose(sc.pos_noise.tau, [g.tau_position_s] * 3 + [g.tau_attitude_s] * 3)
    assert 0.5 <= sc.capture_margin_m and 1.0 <= sc.safe_wall_distance_m <= min(5.0, g.standoff_m / 2)
    assert len(sc.pass_plan().passes) == 6  # placed from the standoff: every pass plans
    # a plate resting on the wall (proud 0) clears the wall's bulges: nothing behind the wall
    targets = [s for s in sc.surfaces if s.kind == "target"]
    assert len(targets) == len(g.targets)
    for s, t in zip(sorted(targets, key=lambda s: s.name), g.targets, strict=True):
        back_out_m = s.out_m - s.height_m * np.cos(s.inclination_rad) / 2
        assert back_out_m == pytest.approx(wall_clearance_m(g) + t.proud_m)


def test_a_flush_target_sits_on_the_walls_bulges():
    g = draw_geometry(3)
    wall = next(s for s in scenario_document(g)["scene"]["surfaces"] if s["kind"] == "wall")
    field = wall_shape(g).field("quay_wall", *wall["size_m"])
    a, b = np.meshgrid(*(np.linspace(-x / 2, x / 2, 200) for x in wall["size_m"]))
    assert 0 < np.abs(field.height_m(a.ravel(), b.ravel())).max() <= wall_clearance_m(g)


@pytest.mark.parametrize("seed", [0, 1, 2, 3, 4, 5])
def test_targets_are_seen_in_most_passes(seed):
    res = simulate("random", seed)
    counts = res.point_counts()
    for t in res.site.targets:
        seen = [pid for pid, c in counts.items() if c[t.name] >= 30]
        assert len(seen) >= 4, (seed, t.name, {pid: c[t.name] for pid, c in counts.items()})


def test_set_overrides_apply_on_top_of_the_draw():
    sc = random_scenario(4, ["site.standoff_m=12.0", "noise.pos.model=white"])
    assert sc.standoff_m == 12.0 and sc.pos_noise.model == "white"
    assert sc.draw is not None and sc.draw["standoff_m"] == draw_geometry(4).standoff_m


def test_mls_sim_dataset_writes_a_bundle_that_reads_back_with_the_draw(tmp_path):
    out = tmp_path / "bundle"
    args = ["sim", "dataset", "--scenario", "random", "--seed", "11", "--out", str(out)]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    assert {p.name for p in out.iterdir()} >= {"site.yaml", "trajectory.csv", "points.csv", "truth.json"}
    bundle = read_bundle(out)
    g = draw_geometry(11)
    np.testing.assert_allclose(bundle.site.mount.nominal_rad, g.nominal_rad, atol=1e-9)
    np.testing.assert_allclose(bundle.site.mount.lever_arm_m, g.lever_arm_m, atol=1e-9)
    assert [t.name for t in bundle.site.targets] == [t.name for t in g.targets]
    assert sorted(np.unique(bundle.points.pass_id).tolist()) == [1, 2, 3, 4, 5, 6]
    truth = read_truth(out)
    assert truth["scenario"] == "random" and truth["seed"] == 11
    drawn = truth["settings"]["random_draw"]
    assert drawn["seed"] == 11
    for key in ("wall_azimuth_deg", "standoff_m", "contrast", "wall_waviness_m", "tau_position_s"):
        assert drawn[key] == pytest.approx(g.to_dict()[key])
    np.testing.assert_allclose(drawn["nominal_deg"], np.degrees(g.nominal_rad))
    np.testing.assert_allclose(
        [truth["boresight_deg"][a] for a in ("roll", "pitch", "yaw")], np.degrees(g.boresight_rad)
    )
    assert drawn["scenario_document"] == scenario_document(g)
    assert drawn["placement"]["capture_margin_m"] == pytest.approx(truth["settings"]["capture_margin_m"])


def test_about_half_of_the_draws_have_piles_beside_the_targets_and_clear_of_each_other():
    """Over 400 seeds: piles in 40–60 % of the draws, each 0.3–1.2 m across, 1–4 m before the
    wall, beyond the targets' outer edges by 0.5–4 m, 0.5 m clear of the others; the scenario
    casts them as cylinders and the capture margin it asks for reaches the farthest."""
    with_piles = 0
    for seed in range(400):
        g = draw_geometry(seed)
        if not g.piles:
            continue
        with_piles += 1
        lo, hi = targets_along_m(g.targets)
        for k, p in enumerate(g.piles):
            assert 0.3 <= p.diameter_m <= 1.2 and 1.0 <= p.out_m <= 4.0
            edge = max(p.along_m - p.diameter_m / 2 - hi, lo - p.along_m - p.diameter_m / 2)
            assert 0.5 - 1e-9 <= edge <= 4.0 + 1e-9, (seed, p)
            for q in g.piles[:k]:
                gap = np.hypot(p.along_m - q.along_m, p.out_m - q.out_m) - (p.diameter_m + q.diameter_m) / 2
                assert gap >= 0.5, (seed, p, q)
        if seed < 40:
            sc = random_scenario(seed)
            assert [c.name for c in sc.scene().cylinders] == [p.name for p in g.piles]
            reach = max(max(p.along_m - hi, lo - p.along_m) + p.diameter_m / 2 for p in g.piles)
            assert (
                scenario_document(g)["site"]["capture_margin_m"] >= reach
            )  # as wanted (fitting may shrink it)
    assert 0.4 <= with_piles / 400 <= 0.6, with_piles
