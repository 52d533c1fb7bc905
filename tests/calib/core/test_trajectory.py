"""calib.core.trajectory: interpolation (linear positions, slerp attitude, linear sigmas), coverage."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from calib.core import frames
from calib.core.trajectory import Trajectory, TrajectoryError

D = np.radians
FRAME = frames.LocalFrame(45.5, -73.55, 0.0)


def two_epochs(rpy0_deg, rpy1_deg, **kw) -> Trajectory:
    return Trajectory(
        [100.0, 101.0], [[0.0, 0.0, 0.0], [2.0, -4.0, 1.0]], D([rpy0_deg, rpy1_deg]), FRAME, **kw
    )


def angle_between(Ra, Rb) -> np.ndarray:
    """Rotation angle of Raᵀ·Rb (vectorized)."""
    tr = np.einsum("...ji,...ji->...", Ra, Rb)
    return np.arccos(np.clip((tr - 1.0) / 2.0, -1.0, 1.0))


def test_heading_across_north_stays_between_the_two_samples():
    traj = two_epochs([0, 0, 359.9], [0, 0, 0.1])
    w = np.linspace(0.0, 1.0, 101)
    heading_deg = np.degrees(traj.interpolate(100.0 + w).rpy_rad[:, 2])
    assert np.all((heading_deg >= 359.9 - 1e-9) | (heading_deg <= 0.1 + 1e-9))
    # it moves 0.2° through north, linearly in w (a pure yaw: slerp is linear in the angle)
    np.testing.assert_allclose(frames.wrap_pi(D(heading_deg - 359.9)), D(0.2 * w), atol=1e-12)
    assert heading_deg[50] == pytest.approx(0.0, abs=1e-9) or heading_deg[50] == pytest.approx(
        360.0, abs=1e-9
    )


def test_interpolation_is_linear_in_position_and_sigma_and_exact_at_epochs():
    traj = two_epochs(
        [1, 2, 3],
        [2, 1, 5],
        sigma_p_m=[[0.01, 0.02, 0.03], [0.03, 0.02, 0.01]],
        sigma_rpy_rad=D([[0.01, 0.01, 0.02], [0.02, 0.01, 0.01]]),
    )
    poses = traj.interpolate(np.array([100.0, 100.25, 101.0]))
    np.testing.assert_allclose(poses.p_lgf_m, [[0, 0, 0], [0.5, -1.0, 0.25], [2, -4, 1]], atol=1e-15)
    np.testing.assert_allclose(poses.sigma_p_m[1], [0.015, 0.02, 0.025], atol=1e-15)
    np.testing.assert_allclose(poses.sigma_rpy_rad[1], D([0.0125, 0.01, 0.0175]), atol=1e-15)
    np.testing.assert_allclose(np.degrees(poses.rpy_rad[[0, 2]]), [[1, 2, 3], [2, 1, 5]], atol=1e-12)
    np.testing.assert_allclose(poses.r_b_n, frames.attitude_matrix(*poses.rpy_rad.T), atol=1e-15)


def test_no_sigmas_gives_none():
    poses = two_epochs([0, 0, 0], [0, 0, 1]).interpolate(np.array([100.5]))
    assert poses.sigma_p_m is None and poses.sigma_rpy_rad is None


rotvec = st.lists(st.floats(-1.8, 1.8), min_size=3, max_size=3)


@settings(max_examples=100, deadline=None)
@given(rotvec, rotvec, st.floats(0.0, 1.0))
def test_slerp_of_random_rotations_stays_on_the_geodesic(v0, v1, w):
    R0 = frames.rotation_from_vector(np.array(v0))
    R1 = frames.rotation_from_vector(np.array(v1))
    theta = float(angle_between(R0, R1))
    assume(theta < np.pi - 1e-3)  # the geodesic is not unique at 180°
    r0, p0, y0 = frames.euler_zyx_from_matrix(R0)
    r1, p1, y1 = frames.euler_zyx_from_matrix(R1)
    assume(max(abs(p0), abs(p1)) < D(85.0))  # Euler angles degenerate near ±90° pitch
    traj = Trajectory([0.0, 1.0], np.zeros((2, 3)), [[r0, p0, y0], [r1, p1, y1]], FRAME)
    R = traj.interpolate(np.array([w])).r_b_n[0]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    # on the geodesic: the angles from either end add up to the whole, in proportion w
    assert float(angle_between(R0, R)) == pytest.approx(w * theta, abs=1e-7)
    assert float(angle_between(R, R1)) == pytest.approx((1 - w) * theta, abs=1e-7)


def test_refuses_to_extrapolate_and_names_the_times():
    traj = two_epochs([0, 0, 0], [0, 0, 1])
    with pytest.raises(
        TrajectoryError,
        match=r"covers t = 100\.000 … 101\.000 s .* 2 of 3 times "
        r"fall outside: first 99\.500 s, last 101\.250 s",
    ):
        traj.interpolate(np.array([99.5, 100.5, 101.25]))
    with pytest.raises(TrajectoryError, match="1 times are NaN"):
        traj.interpolate(np.array([100.5, np.nan]))


def test_gaps_longer_than_max_gap_are_refused_but_their_end_samples_are_not():
    t = np.array([0.0, 0.5, 1.0, 5.0, 5.5])
    traj = Trajectory(t, np.zeros((5, 3)), np.zeros((5, 3)), FRAME, max_gap_s=1.0)
    bad = traj.uncovered(np.array([0.25, 1.0, 3.0, 5.0, 5.5, 6.0]))
    assert bad.tolist() == [False, False, True, False, False, True]
    # a gap as the last interval: its last sample is still a sample
    traj = Trajectory([0.0, 1.0, 10.0], np.zeros((3, 3)), np.zeros((3, 3)), FRAME)
    assert traj.uncovered(np.array([10.0, 9.0])).tolist() == [False, True]
    with pytest.raises(TrajectoryError, match=r"gaps > 1 s refused\); 1 of 1 times fall outside"):
        traj.check_coverage(np.array([5.0]))


@pytest.mark.parametrize(
    ("t", "p", "rpy", "match"),
    [
        ([0.0], [[0, 0, 0]], [[0, 0, 0]], "needs at least 2 epochs"),
        ([0.0, 0.0], [[0, 0, 0]] * 2, [[0, 0, 0]] * 2, r"increase strictly; epoch 1 \(t=0\.000000\)"),
        ([0.0, np.nan], [[0, 0, 0]] * 2, [[0, 0, 0]] * 2, "non-finite time at epoch 1"),
        ([0.0, 1.0], [[0, 0, 0]], [[0, 0, 0]] * 2, r"p_lgf_m has shape \(1, 3\), expected \(2, 3\)"),
        ([0.0, 1.0], [[0, 0, 0]] * 2, [[0, 0, 0], [0, np.inf, 0]], "non-finite rpy_rad at epoch 1"),
    ],
)
def test_malformed_trajectories_are_refused(t, p, rpy, match):
    with pytest.raises(TrajectoryError, match=match):
        Trajectory(t, p, rpy, FRAME)


def test_from_geodetic_with_frame_and_select(wave_trajectory):
    traj = wave_trajectory(duration_s=2.0, rate_hz=50.0, sigmas=True)
    lat, lon, h = traj.geodetic()
    again = Trajectory.from_geodetic(traj.t_gps_s, lat, lon, h, traj.rpy_rad, traj.frame)
    np.testing.assert_allclose(again.p_lgf_m, traj.p_lgf_m, atol=1e-8)
    mean = Trajectory.from_geodetic(traj.t_gps_s, lat, lon, h, traj.rpy_rad)
    assert mean.frame.lat_deg == pytest.approx(float(np.mean(lat)), abs=1e-12)
    other = traj.with_frame(frames.LocalFrame(45.5001, -73.5501, -29.0))
    lat2, lon2, h2 = other.geodetic()
    np.testing.assert_allclose([lat2, lon2], [lat, lon], atol=1e-12)
    np.testing.assert_allclose(h2, h, atol=1e-6)
    assert traj.with_frame(traj.frame) is traj
    part = traj.select(slice(10, 20))
    assert part.t_gps_s.size == 10 and part.has_sigmas
    np.testing.assert_array_equal(part.sigma_p_m, traj.sigma_p_m[10:20])
