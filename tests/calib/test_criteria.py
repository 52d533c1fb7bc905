"""Visibility criteria (issue 9; thesis §3.4.4, Appendix C): Type I and Type II on known point
sets, and the thesis's findings on simulated targets — a Z lever-arm error is invisible in
every configuration, a scan-angle offset acts exactly like a roll boresight."""

from __future__ import annotations

import numpy as np
import pytest

from calib.criteria import (MIN_CRITERIA_POINTS, SYSTEMATIC_ERRORS, THESIS_MAGNITUDES,
                            CriteriaError, injected, is_angular, normalized, pass_spread,
                            plane_criteria, thesis_tilt_deg, type1)  # fmt: skip
from calib.design import (Sigmas, default_spec, design_scenario, observations, run_study,
                          scan_angle_roll_correlation, target_planes)  # fmt: skip
from calib.geometry import Rectangle
from calib.scenario import load_scenario
from calib.simulate import simulate

RECT = Rectangle.from_orientation("T", [10.0, -4.0, -5.0], 1.0, 1.0, np.radians(70.0),
                                  np.radians(125.0))  # fmt: skip


def _grid(rect: Rectangle, n: int = 21) -> np.ndarray:
    u, v = np.meshgrid(np.linspace(-0.5, 0.5, n), np.linspace(-0.5, 0.5, n))
    return rect.center_m + u.reshape(-1, 1) * rect.u_axis + v.reshape(-1, 1) * rect.v_axis


def _rot(axis, angle):
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def test_type2_of_a_rotated_and_shifted_copy_is_its_angle_and_offset():
    p = _grid(RECT)
    c = plane_criteria(p, RECT)
    assert (c.n_points, c.angular_deviation_rad) == (441, pytest.approx(0.0, abs=1e-12))
    assert c.signed_distance_m == pytest.approx(0.0, abs=1e-12)
    assert c.planarity == pytest.approx(1.0, abs=1e-9)  # a square: λ1 = λ2, λ3 = 0
    assert c.centroidal_distance_m == pytest.approx(0.0, abs=1e-12)
    # tilt the copy by 1.5° about its width axis and push it 4 cm along the normal
    q = (p - RECT.center_m) @ _rot(RECT.u_axis, np.radians(1.5)).T + RECT.center_m
    q = q + 0.04 * RECT.normal + 0.3 * RECT.u_axis  # and slide it 30 cm within the plane
    c = plane_criteria(q, RECT)
    assert np.degrees(c.angular_deviation_rad) == pytest.approx(1.5, abs=1e-9)
    assert c.signed_distance_m == pytest.approx(0.04, abs=1e-12)
    assert c.centroidal_distance_m == pytest.approx(np.hypot(0.04, 0.3), abs=1e-12)
    assert c.normal @ RECT.normal > 0  # oriented like the true plane
    # a single scan line is collinear: planarity 0; fewer than 3 points: missing
    line = RECT.center_m + np.linspace(-0.5, 0.5, 30)[:, None] * RECT.u_axis
    assert plane_criteria(line, RECT).planarity == pytest.approx(0.0, abs=1e-9)
    assert plane_criteria(line[:2], RECT).n_points == 0
    assert np.isnan(plane_criteria(line[:2], RECT).signed_distance_m)


def test_type1_normalizes_the_centroidal_distance_over_the_configurations():
    np.testing.assert_allclose(normalized([2.0, 4.0, 3.0, np.nan]), [0.0, 1.0, 0.5, np.nan])
    np.testing.assert_array_equal(normalized([3.0, 3.0]), [0.0, 0.0])
    # thesis Algorithm 2: planarity · (1 − z); the farthest copy scores 0, a missing pass 0
    np.testing.assert_allclose(type1([0.9, 0.8, 1.0, np.nan], [0.1, 0.5, 0.3, np.nan]),
                               [0.9, 0.0, 0.5, 0.0])  # fmt: skip


def test_pass_spread_is_the_largest_normal_angle_and_distance_range():
    n = [[1, 0, 0], _rot([0, 0, 1], np.radians(2.0)) @ [1, 0, 0],
         _rot([0, 1, 0], np.radians(-1.0)) @ [1, 0, 0], [np.nan] * 3]
    ang, dist = pass_spread(n, [0.01, -0.02, 0.005, 9.0])
    # between the +2° (about z) and the −1° (about y) normals: arccos(cos2°·cos1°)
    assert np.degrees(ang) == pytest.approx(np.degrees(np.arccos(np.cos(np.radians(2)) *
                                                                 np.cos(np.radians(1)))), abs=1e-9)
    assert dist == pytest.approx(0.03)
    assert pass_spread([[1, 0, 0]], [0.3]) == (0.0, 0.0)


def test_injected_errors_follow_the_thesis_magnitudes():
    assert set(THESIS_MAGNITUDES) == set(SYSTEMATIC_ERRORS) and len(SYSTEMATIC_ERRORS) == 8
    assert np.degrees(THESIS_MAGNITUDES["boresight_pitch"]) == pytest.approx(2.0)
    assert np.degrees(THESIS_MAGNITUDES["scan_angle_offset"]) == pytest.approx(1.0)
    assert THESIS_MAGNITUDES["lever_arm_z"] == THESIS_MAGNITUDES["range_offset"] == 0.10
    t = injected("boresight_yaw", 0.03, apriori_boresight_rad=[0.001, 0.002, 0.003])
    np.testing.assert_allclose(t.boresight_rad, [0.001, 0.002, 0.033])
    np.testing.assert_array_equal(injected("lever_arm_y", 0.1).lever_arm_error_m, [0, 0.1, 0])
    assert injected("range_offset", 0.1).range_offset_m == 0.1
    assert injected("scan_angle_offset", 0.02).scan_angle_offset_rad == 0.02
    assert is_angular("scan_angle_offset") and not is_angular("range_offset")
    # the thesis's Chapter 3 angle (0° vertical) beside ours (90° vertical, < 0 tilted back):
    # its inclined terrestrial target "−50°" is ours 40°, its weak "60°" (Fig. 3.9b) ours −30°
    assert [thesis_tilt_deg(i) for i in (90, 40, 0, -30, -90)] == [0, -50, -90, 60, 0]
    with pytest.raises(CriteriaError, match="unknown systematic error 'latency'"):
        injected("latency", 0.1)


@pytest.fixture(scope="module")
def terrestrial():
    """The thesis's Chapter 3 sweep (19 inclinations, six passes) for four errors."""
    base = load_scenario("terrestrial")
    spec = default_spec(base, groups=(), errors=("boresight_roll", "lever_arm_y", "lever_arm_z",
                                                 "scan_angle_offset"),  # fmt: skip
                        magnitudes={**THESIS_MAGNITUDES, "scan_angle_offset": np.radians(2.0)})
    return run_study(base, spec)


def test_a_z_lever_arm_error_is_invisible_in_every_configuration(terrestrial):
    """Thesis C.2.5: with the vessel level, a Z lever-arm error moves every point of every pass
    by the same vertical vector; the plane's own offset absorbs it. All 19 inclinations (the
    thesis's −90…90° sweep) × six passes; any pass subset shows no more than all six."""
    vis = [v for v in terrestrial.visibility if v["error"] == "lever_arm_z"]
    assert [v["inclination_deg"] for v in vis] == list(range(-90, 91, 10))
    # every inclination compares at least four passes (a plane seen edge-on by the others)
    assert all(len(v["passes_used"]) >= 4 for v in vis)
    assert sum(len(v["passes_used"]) for v in vis) >= 19 * 6 - 4
    assert max(v["distance_spread_m"] for v in vis) < 1e-9
    assert max(v["angle_spread_deg"] for v in vis) < 1e-9
    assert not any(v["visible"] for v in vis)
    # …whereas the criterion does see a 10 cm lever-arm error across the track: passes 0°/180°
    # on a vertical target move it by ±10 cm
    y = {v["inclination_deg"]: v for v in terrestrial.visibility if v["error"] == "lever_arm_y"}
    assert y[90]["distance_spread_m"] == pytest.approx(0.20, abs=1e-6)
    assert all(v["visible"] for i, v in y.items() if i != 0)  # a horizontal plane: no
    # the Z error does shift a non-vertical plane — but every pass alike
    rows = [r for r in terrestrial.criteria if r["error"] == "lever_arm_z" and r["inclination_deg"] == 0]
    np.testing.assert_allclose([r["signed_distance_m"] for r in rows], 0.10, atol=1e-9)


def test_a_scan_angle_offset_is_a_roll_boresight(terrestrial):
    """Thesis §3.5.2 finds the two correlated; for a profiler they are the same rotation
    (about the scanner's x axis): at equal magnitude every pass's copy is identical."""
    roll = [r for r in terrestrial.criteria if r["error"] == "boresight_roll"]
    scan = [r for r in terrestrial.criteria if r["error"] == "scan_angle_offset"]
    assert len(roll) == len(scan) == 19 * 6
    for a, b in zip(roll, scan):
        assert (a["inclination_deg"], a["pass_id"], a["n_points"]) == \
               (b["inclination_deg"], b["pass_id"], b["n_points"])
        if a["n_points"] >= MIN_CRITERIA_POINTS:
            assert a["signed_distance_m"] == pytest.approx(b["signed_distance_m"], abs=1e-9)
            assert a["angular_deviation_deg"] == pytest.approx(b["angular_deviation_deg"], abs=1e-7)
    # and the study reports |ρ| = 1 through the linearization
    assert terrestrial.roll_scan_correlation > 0.999999


def test_roll_and_scan_angle_offset_are_correlated_for_any_nominal_mount():
    """Through the adjustment's linearization (roll and the scan-angle offset estimated together
    with pitch, yaw and the planes), on the montreal site, with a tilted nominal mount too."""
    base = load_scenario("montreal")
    sig = Sigmas.of_scenario(base)
    for nominal in ([0.0, 0.0, 0.0], [1.0, -4.0, 3.0]):
        sc = load_scenario("montreal", {"mount.nominal_deg": nominal})
        sim = simulate(design_scenario(sc, [s for s in sc.surfaces if s.kind == "target"]), 0)
        rho = scan_angle_roll_correlation(observations(sim, sig, noisy=False), sim.mount_true,
                                          target_planes(sim))  # fmt: skip
        assert rho > 0.9999, nominal
