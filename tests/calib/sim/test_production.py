"""The production survey (issue 19, "mount watch"): lines along the harbour front on opposite
headings at their offsets, a mount event that moves the returns off their surfaces from its time
on (a step at once, a creep linearly), hulls that move between lines while the wall stays put,
reproducible results, the scenario file, a bundle that reads back and a feed the devices play."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from calib.core.errors import ConfigError
from calib.core.georef import georeference
from calib.io.bundle import read_bundle, read_truth
from calib.sim.production import MountEvent, ProductionSpec, simulate_production
from calib.sim.scenariofile import load_scenario
from calib.sim.simulate import simulate

NOISE_FREE = {
    "noise.pos.model": "none",
    "noise.scanner.sigma_range_m": 0.0,
    "noise.scanner.beam_divergence_mrad": 0.0,
    "noise.scanner.sigma_scan_angle_deg": 0.0,
}
STEP_DEG = np.array([0.1, 0.0, 0.0])


def small(**kw) -> ProductionSpec:
    """Short lines at a low point rate: a few seconds of simulation."""
    base = {"n_lines": 2, "line_length_m": 80.0, "offsets_m": (12.0, 20.0), "rate_scale": 0.01}
    return ProductionSpec(**{**base, **kw})


def site_coordinates(sc, p_lgf_m) -> tuple[np.ndarray, np.ndarray]:
    """(along, out) of LGF points in the site frame."""
    a, w = sc.wall_azimuth_rad, sc.water_azimuth_rad
    p = np.asarray(p_lgf_m)
    return p[:, 0] * np.cos(a) + p[:, 1] * np.sin(a), p[:, 0] * np.cos(w) + p[:, 1] * np.sin(w)


def distances(r, mount) -> np.ndarray:
    """Each return georeferenced with ``mount`` on the true trajectory: its distance from the
    (shaped) surface it hit."""
    x = georeference(r.points.t_gps_s, r.points.range_m, r.points.scan_angle_rad, r.trajectory_true, mount)
    return r.scene.distance_m(r.surface_index, x)


def stepped(mount, delta_rad):
    return replace(mount, boresight_rad=mount.boresight_rad + delta_rad)


@pytest.fixture(scope="module")
def harbour():
    return load_scenario("harbour", NOISE_FREE)


@pytest.fixture(scope="module")
def step_run(harbour):
    """A 0.1° roll step in the middle of the second line (speed fixed: 80 m at 2 m/s)."""
    spec = small(speeds_mps=(2.0, 2.0))
    t_mid_2 = None
    r0 = simulate_production(harbour, replace(spec, rate_scale=1e-4), seed=1)  # the same lines, cheaply
    line2 = r0.truth["lines"][1]
    t_mid_2 = 0.5 * (line2["t_start_gps_s"] + line2["t_end_gps_s"]) - harbour.start_gps_s
    ev = MountEvent(t_mid_2 + 0.0123, np.radians(STEP_DEG))
    return simulate_production(harbour, replace(spec, mount_event=ev), seed=1)


# -- the lines ----------------------------------------------------------------------------------


def test_lines_alternate_headings_at_their_offsets_and_turns_keep_off_the_wall(harbour):
    spec = ProductionSpec(
        n_lines=6, line_length_m=80.0, offsets_m=(12.0, 20.0, 30.0), rate_scale=1e-4, speeds_mps=(1.5, 3.5)
    )
    r = simulate_production(harbour, spec, seed=3)
    lines = r.truth["lines"]
    assert [ln["id"] for ln in lines] == [1, 2, 3, 4, 5, 6] == [p.id for p in r.plan.passes]
    traj = r.trajectory_true
    along, out = site_coordinates(r.scenario, traj.p_lgf_m)
    headings, speeds = [], []
    for ln, nominal in zip(lines, (12.0, 12.0, 20.0, 20.0, 30.0, 30.0)):
        on = (traj.t_gps_s >= ln["t_start_gps_s"]) & (traj.t_gps_s <= ln["t_end_gps_s"])
        # there and back at one offset: the line back lies 0.1 m off (one way round the U-turn)
        assert abs(ln["offset_m"] - nominal) <= 0.1 + 1e-9
        np.testing.assert_allclose(out[on], ln["offset_m"], atol=1e-6)
        yaw = traj.rpy_rad[on, 2]
        headings.append(np.degrees(np.angle(np.mean(np.exp(1j * yaw)))) % 360.0)
        assert headings[-1] == pytest.approx(ln["heading_deg"], abs=0.5)
        v = np.diff(along[on]) / np.diff(traj.t_gps_s[on])
        assert np.abs(v).mean() == pytest.approx(ln["speed_mps"], rel=1e-3)
        speeds.append(ln["speed_mps"])
    for h0, h1 in zip(headings[:-1], headings[1:]):  # every consecutive pair: opposite headings
        assert abs((h1 - h0) % 360.0 - 180.0) < 2.0
    assert all(1.5 <= v <= 3.5 for v in speeds) and len(set(speeds)) == 6
    # the turns (30 → 12 m included) swing out, never toward the wall
    assert out.min() > 11.8
    # the line times are the pass marks' times
    for p in r.truth["passes"]:
        ln = lines[p["id"] - 1]
        assert p["line_gps_s"] == [ln["t_start_gps_s"], ln["t_end_gps_s"]]


def test_duration_sets_the_number_of_lines(harbour):
    spec = ProductionSpec(duration_s=400.0, line_length_m=100.0, speeds_mps=(2.0, 2.0), rate_scale=1e-4)
    r = simulate_production(harbour, spec, seed=0)
    t_s = [
        (ln["t_start_gps_s"] - harbour.start_gps_s, ln["t_end_gps_s"] - harbour.start_gps_s)
        for ln in r.truth["lines"]
    ]
    # the line under way at 400 s is finished, and no line starts after
    assert t_s[-1][0] < 400.0 <= t_s[-1][1] and t_s[-2][1] < 400.0
    assert len(t_s) == 5 and all(b - a == pytest.approx(50.0, abs=0.02) for a, b in t_s)


# -- the mount event ----------------------------------------------------------------------------


def test_a_step_moves_the_returns_off_their_surfaces_from_its_time_on(step_run):
    r = step_run
    ev = r.truth["mount_event"]
    t_eff = ev["effective_t_gps_s"]
    period_s = 1.0 / r.scenario.scanner.effective_profile_rate_hz
    assert 0.0 <= t_eff - ev["t_gps_s"] <= period_s and ev["step_deg"] == pytest.approx(list(STEP_DEG))
    assert r.truth["mount_calibrated"] == pytest.approx([0.208, 1.245, 0.149])
    np.testing.assert_allclose(np.degrees(r.mount_true.boresight_rad), [0.208, 1.245, 0.149])
    before = r.points.t_gps_s < t_eff
    assert 5000 < before.sum() < len(r.points) - 5000
    calibrated = distances(r, r.mount_true)
    after_step = distances(r, stepped(r.mount_true, np.radians(STEP_DEG)))
    # before the step: on their surfaces with the calibrated mount (flat and shaped alike)
    assert np.abs(calibrated[before]).max() < 1e-3
    # from it on: off them by centimetres with the calibrated mount, on them with the stepped one
    assert np.percentile(np.abs(calibrated[~before]), 90) > 0.01
    assert np.abs(after_step[~before]).max() < 1e-3
    assert np.percentile(np.abs(after_step[before]), 90) > 0.01


def _roll_estimate(r, sel) -> float:
    """The boresight roll change (rad) that puts the selected returns back on their surfaces
    (Gauss–Newton)."""
    eps, roll = 1e-6, 0.0
    sub = replace(r, points=r.points.select(sel), surface_index=r.surface_index[sel])
    for _ in range(3):
        d0 = distances(sub, stepped(r.mount_true, [roll, 0.0, 0.0]))
        jac = (distances(sub, stepped(r.mount_true, [roll + eps, 0.0, 0.0])) - d0) / eps
        roll -= float((jac @ d0) / (jac @ jac))
    return roll


def test_a_creep_changes_the_mount_linearly(harbour):
    creep_s = 40.0
    ev = MountEvent(10.0, np.radians(STEP_DEG), creep_s)
    r = simulate_production(
        harbour, small(n_lines=1, line_length_m=100.0, speeds_mps=(1.5, 1.5), mount_event=ev), 2
    )
    np.testing.assert_allclose(ev.delta_rad([0.0, 10.0, 20.0, 50.0, 99.0]), np.radians([[0, 0, 0], [0, 0, 0], [0.025, 0, 0], [0.1, 0, 0], [0.1, 0, 0]]), atol=1e-15)  # fmt: skip
    t_rel = r.points.t_gps_s - harbour.start_gps_s
    assert r.truth["mount_event"]["creep_s"] == creep_s
    t_win = np.arange(11.0, 49.0, 2.0)
    est = np.array([_roll_estimate(r, np.abs(t_rel - t) < 0.5) for t in t_win])
    slope, intercept = np.polyfit(t_win, np.degrees(est), 1)
    assert slope == pytest.approx(0.1 / creep_s, rel=0.1)  # °/s
    assert intercept + slope * 10.0 == pytest.approx(0.0, abs=0.005)
    # piecewise constant in pieces of ≤ 5 s: never more than half a piece's change from the ramp
    ramp = np.degrees(ev.delta_rad(t_win)[:, 0])
    assert np.abs(np.degrees(est) - ramp).max() <= 0.1 * 2.5 / creep_s + 1e-4
    assert abs(np.degrees(_roll_estimate(r, t_rel < 9.5))) < 1e-5
    assert np.degrees(_roll_estimate(r, t_rel > 50.5)) == pytest.approx(0.1, abs=1e-5)


# -- the harbour --------------------------------------------------------------------------------


def test_the_harbour_shows_faces_turned_toward_the_track(step_run):
    r = step_run
    along_axis = r.scenario.site_to_lgf(1.0, 0.0, 0.0)[0]
    normals = np.array([rect.normal for rect in r.scene.rectangles])
    # turned fenders and bollards, wing walls, hulls, fenders' sides; the piles (cylinders) face every way
    turned = np.concatenate([np.abs(normals @ along_axis) > 0.3, np.ones(len(r.scene.cylinders), bool)])
    assert len(r.scene) <= 150 and turned.sum() >= 20
    for line in (1, 2):
        hits = r.surface_index[r.points.pass_id == line]
        assert turned[hits].mean() > 0.01
        assert len(np.unique(hits[turned[hits]])) >= 5
    names = set(r.scene.names)
    for part in ("quay_wall_a", "revetment", "wing_wall_a", "pile_0", "fender_0", "bollard_0_a",
                 "jetty_head", "deck_a", "warehouse_1", "hull_workboat_s21", "hull_barge_s21"):  # fmt: skip
        assert part in names


def test_moving_hulls_move_between_lines_and_the_wall_does_not(harbour):
    r = simulate_production(harbour, small(moving_hulls=True, offsets_m=(12.0,)), seed=4)
    names = np.array(r.scene.names)
    hull = np.char.startswith(names, "hull_workboat_")[r.surface_index]
    wall = np.isin(names, ["quay_wall_a", "quay_wall_b"])[r.surface_index]
    # the true hits measured against the scene at rest
    d = r.scene.distance_m(r.surface_index, r.p_true_lgf_m)
    mean_offset = []
    for line in (1, 2):
        on = r.points.pass_id == line
        assert (on & hull).sum() > 500 and (on & wall).sum() > 500
        assert np.abs(d[on & wall]).max() < 1e-9
        assert np.sqrt(np.mean(d[on & hull] ** 2)) > 0.02  # off the hull at rest
        mean_offset.append(np.mean(d[on & hull]))
    assert abs(mean_offset[0] - mean_offset[1]) > 0.02  # seen in different places
    assert set(r.truth["hulls"]["surfaces"]) == {"workboat", "barge"}
    assert len(r.truth["hulls"]["drift"]) == 2
    # without the swell the hulls lie where the scene has them
    still = simulate_production(harbour, small(offsets_m=(12.0,)), seed=4)
    assert np.abs(still.scene.distance_m(still.surface_index, still.p_true_lgf_m)).max() < 1e-9


def test_the_same_seed_gives_the_same_survey(harbour):
    spec = small(
        moving_hulls=True, rate_scale=0.002, mount_event=MountEvent(30.0, np.radians([0.0, 0.1, 0.0]), 20.0)
    )
    noisy = load_scenario("harbour")
    a, b = (simulate_production(noisy, spec, seed=7) for _ in range(2))
    c = simulate_production(noisy, spec, seed=8)
    for f in ("pass_id", "t_gps_s", "range_m", "scan_angle_rad", "intensity"):
        assert np.array_equal(getattr(a.points, f), getattr(b.points, f))
    assert np.array_equal(a.trajectory_observed.rpy_rad, b.trajectory_observed.rpy_rad)
    assert json.dumps(a.truth, sort_keys=True) == json.dumps(b.truth, sort_keys=True)
    assert len(a.points) != len(c.points) or not np.array_equal(a.points.range_m, c.points.range_m)


# -- the scenario file, the bundle, the feed ------------------------------------------------------


def test_the_harbour_scenario_file_and_its_overrides():
    sc = load_scenario("harbour")
    p = sc.production
    assert p is not None and p.mount_event is None and (p.wavy_wall, p.moving_hulls, p.water) == (False,) * 3
    assert (p.duration_s, p.offsets_m, p.line_length_m, p.speeds_mps, p.rate_scale) == (
        3600.0, (12.0, 20.0, 30.0), 350.0, (1.5, 3.5), 0.02,
    )  # fmt: skip
    assert sc.scanner.angular_windows_rad == () and sc.scanner.max_range_m == 119.0
    assert sc.scanner.point_rate_scale == 0.02 and sc.motion.turns
    assert 80 <= len(sc.surfaces) <= 150 and sc.scene()  # the harbour, at rest
    ev = load_scenario(
        "harbour",
        ["production.mount_event.step_deg=[0.1,0,0]", "production.mount_event.creep_s=120"],
    ).production.mount_event
    assert ev.t_s == 1800.0 and ev.creep_s == 120.0  # t_s: half the survey by default
    np.testing.assert_allclose(ev.step_rad, np.radians([0.1, 0.0, 0.0]))
    sc = load_scenario(
        "harbour",
        {"production.mount_event": {"t_s": 600, "step_deg": [0, 0, -0.2]}, "production.wavy_wall": True},
    )
    assert sc.production.mount_event.t_s == 600.0 and sc.production.wavy_wall
    wall = next(s for s in sc.surfaces if s.name == "quay_wall_a")
    assert wall.shape.waviness_amplitude_m == 0.045
    # --point-rate-scale (an override of scanner.point_rate_scale) wins over production.rate_scale
    assert load_scenario("harbour", ["scanner.point_rate_scale=0.005"]).production.rate_scale == 0.005
    # any scenario becomes a production survey of the harbour with its own mount and noise
    sc = load_scenario("montreal", ["production.duration_s=600"])
    assert sc.production.duration_s == 600.0 and "quay_wall_b" in [s.name for s in sc.surfaces]


@pytest.mark.parametrize(
    ("override", "where"),
    [
        ("production.mount_event.creep_s=-1", r"--set:1:\d+: production\.mount_event\.creep_s: got -1, expected a number ≥ 0"),
        ("production.mount_event.step_deg=[9,0,0]", r"production\.mount_event\.step_deg: got \[9, 0, 0\], expected 3 angles within ±5°"),
        ("production.offsets_m=[12,5]", r"production\.offsets_m\[1\]: got 5, expected a number ≥ 10"),
        ("production.speeds_mps=[3,2]", r"production\.speeds_mps: got \[3, 2\], expected \[min, max\]"),
        ("production.n_lines=0", r"production\.n_lines: got 0, expected an integer ≥ 1"),
        ("production.mount_event.when=3", r"production\.mount_event\.when: unknown key"),
    ],
)  # fmt: skip
def test_bad_production_values_name_the_key(override, where):
    with pytest.raises(ConfigError, match=where):
        load_scenario("harbour", ["production.mount_event.step_deg=[0.1,0,0]", override])


def test_simulate_plays_it_and_the_bundle_reads_back(tmp_path):
    overrides = {
        **NOISE_FREE,
        "noise.pos.model": "gauss_markov",
        "production.n_lines": 2,
        "production.line_length_m": 60.0,
        "production.rate_scale": 0.005,
        "production.mount_event": {"t_s": 10.0, "step_deg": [0.0, 0.0, 0.1]},
    }
    r = simulate("harbour", 5, overrides=overrides)
    assert r.scenario.production is not None and r.site.targets == ()
    assert sorted(set(r.points.pass_id.tolist())) == [1, 2] and len(r.points) > 2000
    b = read_bundle(r.write(tmp_path / "bundle"))
    assert b.pass_warnings() == [] and [p.id for p in b.site.passes] == [1, 2]
    assert np.array_equal(b.points.pass_id, r.points.pass_id)
    np.testing.assert_allclose(b.points.range_m, r.points.range_m, atol=1e-4)
    truth = read_truth(tmp_path / "bundle")
    assert truth["mount_event"]["step_deg"] == [0.0, 0.0, 0.1] and truth["mount_event"]["creep_s"] == 0.0
    assert truth["mount_event"]["t_gps_s"] == r.scenario.start_gps_s + 10.0
    assert {"production", "mount_calibrated", "lines"} <= set(truth)
    assert set(truth["lines"][0]) == {
        "id",
        "t_start_gps_s",
        "t_end_gps_s",
        "heading_deg",
        "offset_m",
        "speed_mps",
    }
    assert truth["overrides"] and truth["production"]["line_length_m"] == 60.0


def test_the_devices_feed_plays_every_return(harbour):
    from sim_devices.feed import make_feed

    ev = MountEvent(20.0, np.radians(STEP_DEG), 15.0)  # pieces of ≤ 5 s and ≤ 1 s: one grid per line
    r = simulate_production(harbour, small(moving_hulls=True, rate_scale=0.004, mount_event=ev), seed=6)
    feed = make_feed(r)
    assert feed.grid.ret_point.size == len(r.points) and feed.grid.returns_outside == 0
    assert [(m.kind, m.pass_id) for m in feed.marks] == [
        ("pass_start", 1), ("pass_end", 1), ("pass_start", 2), ("pass_end", 2),
    ]  # fmt: skip
