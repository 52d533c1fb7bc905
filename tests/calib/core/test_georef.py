"""calib.core.georef: direct georeferencing, its inverse, and the fast kernel against the plain one."""

from __future__ import annotations

import numpy as np
import pytest

from calib.core import frames, georef
from calib.core.georef import Mount, georeference, georeference_poses, inverse_georeference
from calib.core.trajectory import Trajectory, TrajectoryError

D = np.radians
FULL_MOUNT = Mount(
    lever_arm_m=[0.42, -0.31, -1.85],
    nominal_rad=D([1.5, -20.0, 178.0]),
    boresight_rad=D([0.208, 1.245, 0.149]),
    range_offset_m=0.004,
    scan_angle_offset_rad=D(0.003),
    time_offset_s=0.0007,
)


def scan(traj: Trajectory, n: int, rng, sort=True):
    """n returns spread over the trajectory (kept inside it despite the time offset)."""
    t = rng.uniform(traj.t_gps_s[0] + 0.01, traj.t_gps_s[-1] - 0.01, n)
    if sort:
        t.sort()
    return t, rng.uniform(0.5, 120.0, n), rng.uniform(-np.pi, 3 * np.pi, n)


def round_trip_error(t, rho, alpha, traj, mount):
    x = georeference(t, rho, alpha, traj, mount)
    obs = inverse_georeference(x, t, traj, mount)
    x2 = georeference(t, obs.range_m, obs.scan_angle_rad, traj, mount)
    return (
        np.abs(x2 - x).max(),
        np.abs(obs.range_m - rho).max(),
        np.abs(frames.wrap_pi(obs.scan_angle_rad - alpha)).max(),
        np.abs(obs.out_of_plane_m).max(),
    )


def test_round_trip_dense_path(wave_trajectory):
    # 40 000 sorted points over 400 intervals: ~100 per interval, the per-interval (dense) path
    traj = wave_trajectory(duration_s=2.0, rate_hz=200.0)
    t, rho, alpha = scan(traj, 40_000, np.random.default_rng(1))
    dx, drho, dalpha, oop = round_trip_error(t, rho, alpha, traj, FULL_MOUNT)
    assert dx < 1e-9 and drho < 1e-9 and dalpha < 1e-12 and oop < 1e-9


def test_round_trip_sparse_path(wave_trajectory):
    # unsorted points (and few per interval): the per-point gather path
    traj = wave_trajectory(duration_s=2.0, rate_hz=200.0)
    t, rho, alpha = scan(traj, 3_000, np.random.default_rng(2), sort=False)
    dx, drho, dalpha, oop = round_trip_error(t, rho, alpha, traj, FULL_MOUNT)
    assert dx < 1e-9 and drho < 1e-9 and dalpha < 1e-12 and oop < 1e-9
    # sorted but sparse (5 points over 400 intervals): also the gather path
    dx, *_ = round_trip_error(*(a[:5] for a in scan(traj, 5, np.random.default_rng(3))), traj, FULL_MOUNT)
    assert dx < 1e-9


@pytest.mark.parametrize("sort", [True, False])
def test_fast_kernel_matches_the_plain_reference(wave_trajectory, sort):
    traj = wave_trajectory(duration_s=3.0, rate_hz=200.0, heading_deg=359.8)  # heading wraps
    t, rho, alpha = scan(traj, 50_000, np.random.default_rng(4), sort=sort)
    x = georeference(t, rho, alpha, traj, FULL_MOUNT)
    poses = traj.interpolate(t + FULL_MOUNT.time_offset_s)
    assert np.abs(x - georeference_poses(poses, rho, alpha, FULL_MOUNT)).max() < 1e-9
    out = np.empty((t.size, 3))  # a row-major output array given by the caller
    assert georeference(t, rho, alpha, traj, FULL_MOUNT, out=out) is out
    assert np.abs(out - x).max() < 1e-12


def test_large_interval_rotations_use_exact_trigonometry():
    # 1 Hz epochs, 30° of yaw per second: above the series' range, exact sin/cos are used
    t = np.arange(0.0, 6.0)
    rpy = np.stack([np.zeros(6), np.zeros(6), D(30.0) * t], axis=1)
    traj = Trajectory(t, np.zeros((6, 3)), rpy, frames.LocalFrame(0.0, 0.0, 0.0))
    rng = np.random.default_rng(5)
    tp, rho, alpha = (
        np.sort(rng.uniform(0, 5, 2000)),
        rng.uniform(1, 50, 2000),
        rng.uniform(0, 2 * np.pi, 2000),
    )
    x = georeference(tp, rho, alpha, traj, FULL_MOUNT)
    poses = traj.interpolate(tp + FULL_MOUNT.time_offset_s)
    assert np.abs(x - georeference_poses(poses, rho, alpha, FULL_MOUNT)).max() < 1e-9


def test_conventions_by_hand():
    # level vessel heading north at the origin, scanner 1 m forward, 2 m starboard, 3 m below
    traj = Trajectory([0.0, 1.0], [[10.0, 20.0, 0.0]] * 2, np.zeros((2, 3)), frames.LocalFrame(0.0, 0.0, 0.0))
    mount = Mount(lever_arm_m=[1.0, 2.0, 3.0])
    x = georeference(
        np.array([0.5, 0.5, 0.5]), np.array([10.0, 10.0, 10.0]), D([0.0, 90.0, 270.0]), traj, mount
    )
    # α = 0° starboard horizontal, 90° down, 270° up
    np.testing.assert_allclose(x, [[11, 32, 3], [11, 22, 13], [11, 22, -7]], atol=1e-12)
    # heading 90° (east): starboard points south
    traj = Trajectory([0.0, 1.0], np.zeros((2, 3)), [[0, 0, D(90.0)]] * 2, traj.frame)
    x = georeference(np.array([0.5]), np.array([10.0]), np.array([0.0]), traj, Mount())
    np.testing.assert_allclose(x, [[-10.0, 0.0, 0.0]], atol=1e-12)


def test_offsets_follow_their_definitions(wave_trajectory):
    traj = wave_trajectory(duration_s=1.0)
    t, rho, alpha = scan(traj, 500, np.random.default_rng(6))
    base = Mount(lever_arm_m=[0.4, 0.1, -1.0], boresight_rad=D([0.2, 1.2, 0.1]))
    # ρ_true = ρ + δρ, α_true = α + δα, sampled at t + Δt
    shifted = Mount(base.lever_arm_m, base.nominal_rad, base.boresight_rad, 0.01, 0.002, 0.003)
    np.testing.assert_allclose(
        georeference(t, rho, alpha, traj, shifted),
        georeference(t + 0.003, rho + 0.01, alpha + 0.002, traj, base),
        atol=1e-9,
    )


def test_inverse_reports_out_of_plane_distance(wave_trajectory):
    traj = wave_trajectory(duration_s=1.0)
    t = np.array([traj.t_gps_s[0] + 0.5])
    x = georeference(t, np.array([20.0]), np.array([0.3]), traj, FULL_MOUNT)
    poses = traj.interpolate(t + FULL_MOUNT.time_offset_s)
    scanner_x_lgf = poses.r_b_n[0] @ FULL_MOUNT.r_s_b[:, 0]
    obs = inverse_georeference(x + 0.25 * scanner_x_lgf, t, traj, FULL_MOUNT)
    assert obs.out_of_plane_m[0] == pytest.approx(0.25, abs=1e-9)
    assert obs.range_m[0] == pytest.approx(20.0, abs=1e-9)


def test_cos_sin_table_is_exact_to_float_precision():
    a = np.concatenate([np.linspace(0.0, 2 * np.pi, 200_001), [np.pi / 2, np.pi, -1e-300]])
    c, s = georef._cos_sin(a)
    assert np.abs(c - np.cos(a)).max() < 2.5e-16 and np.abs(s - np.sin(a)).max() < 2.5e-16
    a = np.linspace(-20.0, 20.0, 200_001)  # beyond one turn: within one ulp of the angle
    c, s = georef._cos_sin(a)
    ulp = np.spacing(np.abs(a)) + 1e-15
    assert np.all(np.abs(c - np.cos(a)) <= ulp) and np.all(np.abs(s - np.sin(a)) <= ulp)


@pytest.mark.parametrize("theta_max", [0.0, 1e-6, 3e-4, 0.01, 0.2])
def test_slerp_series_match_sin_and_versin(theta_max):
    x = np.linspace(-theta_max, theta_max, 10_001)
    s, c = np.empty_like(x), np.empty_like(x)
    georef._sin_versin(x, georef._series_length(theta_max), s, c)
    assert np.abs(s - np.sin(x)).max() <= 1e-16
    # 1 − cos x from np.cos loses digits for small x; compare with 2·sin²(x/2)
    assert np.abs(c - 2 * np.sin(x / 2) ** 2).max() <= 1e-17
    assert georef._series_length(0.3) is None  # beyond the series: exact sin/cos


def test_bad_input(wave_trajectory):
    traj = wave_trajectory(duration_s=1.0)
    t0 = traj.t_gps_s[0]
    assert georeference(np.empty(0), np.empty(0), np.empty(0), traj, Mount()).shape == (0, 3)
    with pytest.raises(ValueError, match="equal length"):
        georeference(np.array([t0]), np.array([1.0, 2.0]), np.array([0.0]), traj, Mount())
    with pytest.raises(TrajectoryError, match="1 of 2 times fall outside"):
        georeference(np.array([t0, t0 - 5.0]), np.ones(2), np.zeros(2), traj, Mount())
    x = georeference(
        np.array([t0 + 0.1, t0 + 0.2]), np.array([np.nan, 5.0]), np.array([0.0, 0.1]), traj, Mount()
    )
    assert np.isnan(x[0]).all() and np.isfinite(x[1]).all()
    with pytest.raises(ValueError, match="lever_arm_m must be 3 finite numbers"):
        Mount(lever_arm_m=[0.0, 1.0])
