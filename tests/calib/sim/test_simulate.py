"""The MLS simulator: exact returns, the thesis's signature of every injected error,
the observed trajectory and its noise, vessel motion, and reproducible bundles written by
``mls sim dataset``."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
from typer.testing import CliRunner

from calib.core import frames
from calib.core.geometry import fit_plane
from calib.core.georef import Mount, georeference
from calib.io.bundle import read_bundle, read_truth
from calib.sim.motion import dubins_path, sample_path
from calib.sim.scenariofile import load_scenario, parse_scenario
from calib.sim.simulate import SimulationError, scan, simulate

NOISE_FREE = {
    "noise.pos.model": "none",
    "noise.scanner.sigma_range_m": 0.0,
    "noise.scanner.beam_divergence_mrad": 0.0,
    "noise.scanner.sigma_scan_angle_deg": 0.0,
}
ALL_ERRORS = {
    "truth.lever_arm_error_m": [0.05, -0.03, 0.10],
    "truth.range_offset_m": 0.02,
    "truth.scan_angle_offset_deg": 0.1,
    "truth.time_offset_s": 0.003,
}


@pytest.fixture(scope="module")
def exact():
    """Montreal, no noise, every systematic error injected, the profiler mounted tilted."""
    return simulate(
        "montreal", seed=4, overrides={**NOISE_FREE, **ALL_ERRORS, "mount.nominal_deg": [1.0, -4.0, 3.0]}
    )


def test_noise_free_returns_lie_exactly_on_their_surfaces(exact):
    """On their rectangles: the targets' planes, the wavy quay wall's displaced surface."""
    r = exact
    x = georeference(
        r.points.t_gps_s, r.points.range_m, r.points.scan_angle_rad, r.trajectory_true, r.mount_true
    )
    assert len(r.points) > 20000
    for j, rect in enumerate(r.scene.rectangles):
        s = r.surface_index == j
        assert s.sum() > 500, rect.name
        assert np.abs(r.scene.distance_m(j, x[s])).max() < 1e-9
        assert rect.contains(x[s], margin_m=1e-9).all()
        if r.scene.kinds[j] == "target":
            assert np.abs(rect.signed_distance(x[s])).max() < 1e-9
        else:  # the quay wall is wavy: off its mean plane by centimetres
            assert 0.005 < np.abs(rect.signed_distance(x[s])).max() < 0.05
    np.testing.assert_allclose(x, r.p_true_lgf_m, rtol=0, atol=1e-9)
    # the same observations georeferenced with the a-priori mount miss the planes
    x0 = georeference(
        r.points.t_gps_s, r.points.range_m, r.points.scan_angle_rad, r.trajectory_true, r.site.mount
    )
    t1 = r.scene.rectangles[0]
    assert np.abs(t1.signed_distance(x0[r.surface_index == 0])).mean() > 0.01
    # the true mount is the a-priori mount with the injected errors
    m = r.mount_true
    np.testing.assert_allclose(m.boresight_rad, np.radians([0.208, 1.245, 0.149]))
    np.testing.assert_allclose(m.lever_arm_m - r.site.mount.lever_arm_m, [0.05, -0.03, 0.10])
    assert (m.range_offset_m, m.time_offset_s) == (0.02, 0.003)
    assert m.scan_angle_offset_rad == pytest.approx(np.radians(0.1))
    np.testing.assert_array_equal(r.site.mount.boresight_rad, 0.0)
    # every pass sees every target; target_index names them
    for p in r.plan.passes:
        in_pass = r.points.pass_id == p.id
        assert np.all(np.bincount(r.target_index[in_pass & (r.target_index >= 0)]) > 50)
    assert set(np.unique(r.target_index)) == {-1, 0, 1}


def test_ray_culling_loses_no_return_and_the_nearest_hit_wins(exact):
    """Every ray slot of a stretch of each pass, cast against the whole scene, gives exactly
    the simulator's returns (sectors only prune rays that hit nothing)."""
    r = exact
    sc = r.scenario
    m = sc.scanner
    rate, K = m.effective_profile_rate_hz, m.effective_points_per_360
    geom = replace(r.mount_true, range_offset_m=0.0)
    for p in r.truth["passes"]:
        c0, c1 = p["capture_gps_s"]
        t0 = 0.5 * (c0 + c1) - 0.3
        ret = scan(m, r.scene, r.trajectory_true, r.mount_true, t0, t0 + 0.6)
        n = np.arange(int(np.floor(0.6 * rate)) * K)
        t = t0 + n / (rate * K)
        a = (n % K) * (2 * np.pi / K)
        o = georeference(t, np.zeros(n.size), a, r.trajectory_true, geom)
        d = georeference(t, np.ones(n.size), a, r.trajectory_true, geom) - o
        hits = r.scene.intersect(o, d, m.min_range_m, m.max_range_m)
        keep = hits.hit & m.window_mask()[n % K]
        assert keep.sum() > 300
        np.testing.assert_array_equal(t[keep], ret.t_gps_s)
        np.testing.assert_array_equal(hits.surface[keep], ret.surface)
        np.testing.assert_allclose(hits.range_m[keep], ret.range_true_m, rtol=0, atol=1e-9)


# -- the thesis's signatures (§4.4.1.1): one 1 m × 1 m vertical target, 5 m above, 15 m away,
#    2° errors, georeferenced with the a-priori mount --------------------------------------

THESIS_SITE = """
reference: {lat_deg: 45.5, lon_deg: -73.55, height_m: 0.0}
site: {wall_azimuth_deg: 30.0, standoff_m: 15.0, pass_length_m: 60.0, speed_mps: 2.0,
       capture_margin_m: 1.0}
scene:
  targets: [{name: T, up_m: 5.0, size_m: [1.0, 1.0], inclination_deg: 90.0}]
mount: {lever_arm_m: [0.0, 0.0, 0.0]}
scanner: {angular_windows_deg: [[300, 360], [180, 240]], point_rate_scale: 0.25}
motion: {rate_hz: 20}
"""


def _offsets(overrides: dict) -> dict[int, tuple[float, float]]:
    """Per relative heading: signed orthogonal distance (m) of the pass's target cloud centroid
    from the true plane, and the angular deviation (°) of its fitted plane."""
    r = simulate(parse_scenario(THESIS_SITE, overrides=overrides), seed=0)
    x = georeference(
        r.points.t_gps_s, r.points.range_m, r.points.scan_angle_rad, r.trajectory_observed, r.site.mount
    )
    rect = r.scene.rectangles[0]
    out = {}
    for p in r.plan.passes:
        s = (r.points.pass_id == p.id) & (r.target_index == 0)
        assert s.sum() > 500
        f = fit_plane(x[s], orient_like=rect.normal)
        # thesis Algorithm 3: atan(‖n × n_ref‖ / n·n_ref)
        dev = np.degrees(np.arctan2(np.linalg.norm(np.cross(f.normal, rect.normal)), f.normal @ rect.normal))
        out[round(np.degrees(p.relative_heading_rad))] = (
            float(rect.signed_distance(f.centroid_m[None])[0]),
            float(dev),
        )
    return out


def test_roll_boresight_separates_the_reciprocal_parallel_passes():
    o = _offsets({"truth.boresight_deg": [2.0, 0.0, 0.0]})
    assert o[0][0] > 0.1 and o[180][0] < -0.1  # opposite signs, 15 cm and more
    assert o[0][1] == pytest.approx(2.0, abs=0.01) and o[180][1] == pytest.approx(2.0, abs=0.01)


def test_pitch_and_yaw_leave_the_parallel_passes_superimposed():
    pitch = _offsets({"truth.boresight_deg": [0.0, 2.0, 0.0]})
    yaw = _offsets({"truth.boresight_deg": [0.0, 0.0, 2.0]})
    assert abs(pitch[0][0]) < 1e-9 and abs(pitch[180][0]) < 1e-9
    assert pitch[0][1] < 1e-6 and pitch[180][1] < 1e-6
    # yaw: both passes on one plane, moved only by the second-order 15 m·(1/cos 2° − 1)
    assert yaw[0][0] == pytest.approx(yaw[180][0], abs=1e-6)
    assert yaw[0][0] == pytest.approx(-15.0 * (1 / np.cos(np.radians(2.0)) - 1), rel=0.02)
    assert yaw[0][1] < 1e-6 and yaw[180][1] < 1e-6


def test_pitch_shows_on_the_side_looking_pair_and_yaw_on_the_crossing_pair():
    pitch = _offsets({"truth.boresight_deg": [0.0, 2.0, 0.0]})
    yaw = _offsets({"truth.boresight_deg": [0.0, 0.0, 2.0]})
    assert pitch[45][0] * pitch[225][0] < 0 and abs(pitch[45][0] - pitch[225][0]) > 0.2
    assert pitch[45][1] > 1.0 and pitch[225][1] > 1.0
    assert yaw[45][0] * yaw[135][0] < 0 and abs(yaw[45][0] - yaw[135][0]) > 0.5
    # and each stays blind on the other pair (thesis Figs 4.8 and 4.11)
    assert pitch[45][0] == pytest.approx(pitch[135][0], abs=1e-3)
    assert yaw[45][0] == pytest.approx(yaw[225][0], abs=2e-3)


def test_z_lever_arm_error_is_invisible_on_all_six_passes():
    o = _offsets({"truth.lever_arm_error_m": [0.0, 0.0, 0.1]})
    assert len(o) == 6
    for dist, dev in o.values():
        assert abs(dist) < 1e-9 and dev < 1e-6
    # whereas the Y lever arm error moves the parallel passes by its full 10 cm
    y = _offsets({"truth.lever_arm_error_m": [0.0, 0.1, 0.0]})
    assert y[0][0] == pytest.approx(0.1, abs=1e-9) and y[180][0] == pytest.approx(-0.1, abs=1e-9)


def test_scan_angle_offset_has_the_roll_signature():
    """Thesis §3.5.2: the scan-angle offset and the roll boresight rotate the same way."""
    roll = _offsets({"truth.boresight_deg": [2.0, 0.0, 0.0]})
    scan_off = _offsets({"truth.scan_angle_offset_deg": 2.0})
    for k in roll:
        assert scan_off[k][0] == pytest.approx(roll[k][0], abs=1e-6)


# -- observations and noise ------------------------------------------------------------------


def test_observed_trajectory_carries_pos_errors_and_their_sigmas():
    r = simulate("montreal", seed=2, overrides={"noise.pos.model": "white"})
    e = r.trajectory_observed.p_lgf_m - r.trajectory_true.p_lgf_m
    np.testing.assert_allclose(e.std(axis=0), 0.02, rtol=0.05)
    ea = frames.wrap_pi(r.trajectory_observed.rpy_rad - r.trajectory_true.rpy_rad)
    np.testing.assert_allclose(np.degrees(ea.std(axis=0)), 0.012, rtol=0.05)
    np.testing.assert_allclose(r.trajectory_observed.sigma_p_m, 0.02)
    np.testing.assert_allclose(np.degrees(r.trajectory_observed.sigma_rpy_rad), 0.012)
    assert r.pose_errors is None
    gm = simulate("montreal", seed=2)  # the scenario's Gauss–Markov errors: slowly varying
    eg = gm.trajectory_observed.p_lgf_m - gm.trajectory_true.p_lgf_m
    lag1 = [np.corrcoef(x[:-1, 0], x[1:, 0])[0, 1] for x in (e, eg)]
    assert abs(lag1[0]) < 0.05 and lag1[1] > 0.99  # exp(−0.02 s / 20 s) = 0.999


def test_per_point_pos_errors_exist_in_memory_only(tmp_path):
    r = simulate("montreal", seed=3, overrides={"noise.pos.model": "per_point"})
    np.testing.assert_array_equal(r.trajectory_observed.p_lgf_m, r.trajectory_true.p_lgf_m)
    poses = r.observed_poses()
    truth = r.trajectory_true.interpolate(r.points.t_gps_s)
    e = np.column_stack([poses.p_lgf_m - truth.p_lgf_m, frames.wrap_pi(poses.rpy_rad - truth.rpy_rad)])
    np.testing.assert_allclose(e, r.pose_errors, atol=1e-9)
    np.testing.assert_allclose(e.std(axis=0), r.scenario.pos_noise.sigma, rtol=0.05)
    np.testing.assert_allclose(poses.r_b_n, frames.attitude_matrix(*poses.rpy_rad.T))
    with pytest.raises(SimulationError, match="per_point.*only in memory"):
        r.write(tmp_path / "b")


def test_scanner_noise_and_recorded_window():
    r = simulate(
        "montreal", seed=5, overrides={"noise.pos.model": "none", "noise.scanner.beam_divergence_mrad": 0.0}
    )
    dr = r.points.range_m - _true_ranges(r)
    assert dr.std() == pytest.approx(0.002, rel=0.05) and abs(dr.mean()) < 1e-4
    a = np.degrees(r.points.scan_angle_rad)
    assert np.all(((a >= 320 - 0.1) & (a <= 358 + 0.1)) | ((a >= 182 - 0.1) & (a <= 220 + 0.1)))
    assert np.all((r.points.intensity > 0) & (r.points.intensity <= 0.9))
    near = simulate("montreal", seed=5, overrides={**NOISE_FREE, "scanner.max_range_m": 15.5})
    assert near.points.range_m.max() <= 15.5 and len(near.points) < len(r.points)


def _true_ranges(r) -> np.ndarray:
    """Distances from the true scanner origin of each return to its true hit point."""
    geom = replace(r.mount_true, range_offset_m=0.0)
    o = georeference(
        r.points.t_gps_s, np.zeros(len(r.points)), r.points.scan_angle_rad, r.trajectory_true, geom
    )
    return np.linalg.norm(r.p_true_lgf_m - o, axis=1) - r.mount_true.range_offset_m


# -- vessel motion ------------------------------------------------------------------------


def test_vessel_sails_the_plan_with_waves():
    r = simulate("montreal", seed=6, overrides=NOISE_FREE)
    traj = r.trajectory_true
    for p in r.truth["passes"]:
        t0, t1 = p["line_gps_s"]
        s = (traj.t_gps_s >= t0) & (traj.t_gps_s <= t1)
        xy = traj.p_lgf_m[s, :2]
        speed = np.linalg.norm(xy[-1] - xy[0]) / (traj.t_gps_s[s][-1] - traj.t_gps_s[s][0])
        assert speed == pytest.approx(2.0, rel=1e-9)
        np.testing.assert_allclose(xy[0], p["start_lgf_m"][:2], atol=1e-9)
        hd = frames.wrap_pi(traj.rpy_rad[s, 2] - np.radians(p["heading_deg"]))
        assert np.degrees(np.abs(hd).max()) == pytest.approx(0.3, abs=0.02)  # yaw wave
    assert np.degrees(np.abs(traj.rpy_rad[:, 0]).max()) == pytest.approx(1.5, abs=0.01)
    assert np.degrees(np.abs(traj.rpy_rad[:, 1]).max()) == pytest.approx(0.5, abs=0.01)
    heave = traj.p_lgf_m[:, 2] - r.plan.passes[0].start_lgf_m[2]
    assert np.abs(heave).max() == pytest.approx(0.05, abs=1e-3)
    # without turns the passes are separate stretches of the trajectory
    assert np.diff(traj.t_gps_s).max() == pytest.approx(30.0, abs=0.05)


def test_turns_make_one_continuous_trajectory():
    r = simulate("montreal", seed=6, overrides={**NOISE_FREE, "motion.turns": True})
    traj = r.trajectory_true
    dt = np.diff(traj.t_gps_s)
    assert dt.max() == pytest.approx(0.02, abs=1e-6)  # one grid, GPS-time float resolution
    step = np.linalg.norm(np.diff(traj.p_lgf_m[:, :2], axis=0), axis=1)
    assert step.max() <= 2.0 * 0.02 * (1 + 1e-6)
    turn_rate = np.abs(frames.wrap_pi(np.diff(traj.rpy_rad[:, 2]))) / dt
    # within a turn the heading changes at v/R (plus the yaw wave's rate)
    assert turn_rate.max() < 2.0 / 15.0 + np.radians(0.3) * 2 * np.pi / 15.0 + 1e-6


def test_dubins_turns_reach_their_end_state():
    rng = np.random.default_rng(0)
    for _ in range(50):
        p0, p1 = rng.uniform(-50, 50, 2), rng.uniform(-50, 50, 2)
        th0, th1 = rng.uniform(0, 2 * np.pi, 2)
        segs = dubins_path(p0, th0, p1, th1, 10.0)
        length = sum(s[1] for s in segs)
        pos, th = sample_path(p0, th0, segs, 10.0, np.linspace(0, length, 2001))
        np.testing.assert_allclose(pos[-1], p1, atol=1e-9)
        assert frames.wrap_pi(th[-1] - th1) == pytest.approx(0.0, abs=1e-9)
        step = np.linalg.norm(np.diff(pos, axis=0), axis=1)
        assert step.max() <= length / 2000 * (1 + 1e-9)  # continuous, unit speed
    # a reversal onto the same line is a loop of at least a half circle
    segs = dubins_path(np.zeros(2), np.pi / 2, np.zeros(2), -np.pi / 2, 15.0)
    assert sum(s[1] for s in segs) >= np.pi * 15.0


# -- the bundle -----------------------------------------------------------------------------


def _run_cli(args: list[str]):
    from cli.app import app

    result = CliRunner().invoke(app, ["sim", "dataset", *args])
    return result


def test_cli_writes_a_reproducible_bundle(tmp_path):
    a, b, c = tmp_path / "a", tmp_path / "b", tmp_path / "c"
    ra = _run_cli(["--scenario", "montreal", "--seed", "7", "--out", str(a)])
    assert ra.exit_code == 0, ra.output
    assert "T1" in ra.output and "T2" in ra.output and "other" in ra.output
    assert "wrote" in ra.output
    assert _run_cli(["--scenario", "montreal", "--seed", "7", "--out", str(b)]).exit_code == 0
    assert _run_cli(["--scenario", "montreal", "--seed", "8", "--out", str(c)]).exit_code == 0
    names = sorted(f.name for f in a.iterdir())
    assert names == ["points.csv", "site.yaml", "trajectory.csv", "truth.json"]
    for n in names:
        assert (a / n).read_bytes() == (b / n).read_bytes(), n
    assert (a / "points.csv").read_bytes() != (c / "points.csv").read_bytes()
    size = sum((a / n).stat().st_size for n in names)
    assert size < 5e6  # a few MB

    bundle = read_bundle(a)
    truth = read_truth(a)
    assert truth["scenario"] == "montreal" and truth["seed"] == 7
    assert truth["boresight_deg"] == pytest.approx({"roll": 0.208, "pitch": 1.245, "yaw": 0.149})
    assert truth["settings"]["noise"]["pos"]["model"] == "gauss_markov"
    # the site carries the a-priori mount and the LGF reference of the simulation
    assert bundle.site.reference == load_scenario("montreal").reference
    np.testing.assert_array_equal(bundle.site.mount.boresight_rad, 0.0)
    np.testing.assert_allclose(bundle.site.mount.lever_arm_m, [0.35, 0.85, -1.65])
    assert [t.name for t in bundle.site.targets] == ["T1", "T2"]
    assert bundle.trajectory.has_sigmas
    # the truth's planes are in the bundle's LGF: the site's approximate centres lie on them
    for t, plane in zip(bundle.site.target_rectangles(bundle.frame), truth["targets"]):
        assert abs(np.dot(plane["normal"], t.center_m) + plane["d"]) < 1e-6


def test_noise_free_bundle_round_trip_keeps_the_points_on_the_planes(tmp_path):
    res = _run_cli(
        [
            "--scenario",
            "montreal",
            "--seed",
            "1",
            "--out",
            str(tmp_path / "nf"),
            "--point-rate-scale",
            "0.05",
            *(f"--set={k}={v}" for k, v in {**NOISE_FREE, **ALL_ERRORS}.items()),
        ]
    )
    assert res.exit_code == 0, res.output
    b = read_bundle(tmp_path / "nf")
    truth = json.loads((tmp_path / "nf" / "truth.json").read_text())
    assert truth["settings"]["scanner"]["point_rate_scale"] == 0.05
    mount = Mount(
        lever_arm_m=truth["lever_arm_m"],
        nominal_rad=np.radians(truth["nominal_deg"]),
        boresight_rad=np.radians([truth["boresight_deg"][k] for k in ("roll", "pitch", "yaw")]),
        range_offset_m=truth["range_offset_m"],
        scan_angle_offset_rad=np.radians(truth["scan_angle_offset_deg"]),
        time_offset_s=truth["time_offset_s"],
    )
    x = georeference(b.points.t_gps_s, b.points.range_m, b.points.scan_angle_rad, b.trajectory, mount)
    planes = truth["targets"] + truth["background"]
    dist = np.min(
        np.abs(x @ np.array([p["normal"] for p in planes]).T + np.array([p["d"] for p in planes])), axis=1
    )
    # the targets are on their planes, the wavy quay wall on its surface (truth gives its shape)
    assert [p["name"] for p in planes if "shape" in p] == ["quay_wall"]
    scene = load_scenario("montreal").scene()
    on_surface = np.min(np.abs([scene.distance_m(j, x) for j in range(len(scene))]), axis=0)
    assert dist.max() > 0.005
    assert on_surface.max() < 2e-5  # the CSV's precision (heights to the µm, angles to 1e-12°)


def test_cli_reports_bad_input_clearly(tmp_path):
    res = _run_cli(
        ["--scenario", "montreal", "--out", str(tmp_path / "x"), "--set", "truth.boresight_deg=[1,2]"]
    )
    assert res.exit_code == 2
    assert "truth.boresight_deg: got [1, 2], expected a list of 3 numbers" in res.output
    res = _run_cli(["--scenario", "nowhere", "--out", str(tmp_path / "x")])
    assert res.exit_code == 2 and "neither a shipped scenario" in res.output
    assert not (tmp_path / "x").exists()


def test_the_scanner_records_only_ranges_measured_inside_its_window():
    """A return that a range offset (and noise) puts beyond the window's edge is not recorded,
    as on the real scanner (the bundle reader refuses ranges outside the physical window); a
    scenario window beyond the Z+F 9012's physical one is refused."""
    from calib.io.configfile import ConfigError

    r = simulate("montreal", seed=5, overrides={"scanner.max_range_m": 15.5, "truth.range_offset_m": -0.05})
    assert 0.3 <= r.points.range_m.min() and r.points.range_m.max() <= 15.5
    assert len(r.points) == len(r.surface_index) == len(r.p_true_lgf_m)
    for key, value in (("max_range_m", 150), ("min_range_m", 0.1)):
        with pytest.raises(
            ConfigError,
            match=rf"scanner\.{key}: got {value}, expected a range within the scanner's physical window 0\.3…119 m",
        ):
            load_scenario("montreal", [f"scanner.{key}={value}"])
