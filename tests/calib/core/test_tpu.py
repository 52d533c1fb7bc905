"""calib.core.tpu: analytic Jacobians, per-point covariance and σ, and a Monte Carlo check on a
simulated survey."""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np
import pytest

from calib.core import frames
from calib.core.errors import CalibError
from calib.core.georef import Mount, georeference_poses
from calib.core.tpu import (
    SOURCES,
    MountCovariance,
    ScannerSigmas,
    TpuError,
    point_covariance,
    point_jacobian,
    point_sigmas,
)
from calib.core.trajectory import Poses, Trajectory, TrajectoryError
from tests.calib.core.test_georef import FULL_MOUNT

D = np.radians
SCANNER = ScannerSigmas(sigma_range_m=0.003, sigma_range_per_m=2e-4, sigma_angle_rad=D(0.01))


def correlated(sigma, corr) -> np.ndarray:
    s = np.asarray(sigma, float)
    return np.asarray(corr, float) * np.outer(s, s)


BORESIGHT_COV = correlated(D([0.01, 0.01, 0.03]), [[1.0, 0.3, -0.2], [0.3, 1.0, 0.5], [-0.2, 0.5, 1.0]])
LEVER_COV = correlated([0.003, 0.003, 0.005], [[1.0, 0.2, 0.0], [0.2, 1.0, -0.3], [0.0, -0.3, 1.0]])
MOUNT_COV = MountCovariance(BORESIGHT_COV, LEVER_COV)


def returns(traj: Trajectory, n: int, rng, sort=True):
    t = rng.uniform(traj.t_gps_s[0] + 0.01, traj.t_gps_s[-1] - 0.01, n)
    if sort:
        t.sort()
    return t, rng.uniform(0.5, 120.0, n), rng.uniform(-np.pi, 3 * np.pi, n)


# -- 1. Jacobians against finite differences of georeference_poses ---------------------------


def test_jacobian_matches_central_differences(wave_trajectory):
    traj = wave_trajectory(duration_s=2.0, sigmas=True)
    t, rho, alpha = returns(traj, 200, np.random.default_rng(1))
    m = FULL_MOUNT
    poses = traj.interpolate(t + m.time_offset_s)
    p0 = poses.p_lgf_m.mean(axis=0)  # differences of smaller coordinates: less rounding

    def x(d: np.ndarray) -> np.ndarray:
        rpy = poses.rpy_rad + d[3:6]
        pp = Poses(poses.p_lgf_m - p0 + d[0:3], rpy, frames.attitude_matrix(*rpy.T))
        mm = replace(m, boresight_rad=m.boresight_rad + d[8:11], lever_arm_m=m.lever_arm_m + d[11:14])
        return georeference_poses(pp, rho + d[6], alpha + d[7], mm)

    J = point_jacobian(poses, rho, alpha, m)
    assert J.shape == (200, 3, len(SOURCES))
    for j, name in enumerate(SOURCES):
        h = 1e-3 if name.endswith("_m") else 1e-5
        d = np.zeros(len(SOURCES))
        d[j] = h
        fd = (x(d) - x(-d)) / (2 * h)
        # truncation ~h²·ρ/6 (< 2e-8 m/rad at 120 m), rounding ~1e-16·100 m / h
        np.testing.assert_allclose(J[:, :, j], fd, rtol=0, atol=5e-8, err_msg=name)
    # the angle columns are large (ρ up to 120 m), so the tolerance above is a tight relative one
    assert np.abs(J[:, :, 7]).max() > 50.0


# -- 2. point_sigmas against point_covariance --------------------------------------------------


@pytest.mark.parametrize("sigmas", [True, False])
def test_sigmas_equal_covariance_diagonal_across_blocks(wave_trajectory, sigmas):
    traj = wave_trajectory(duration_s=3.0, sigmas=sigmas)
    t, rho, alpha = returns(traj, 3000, np.random.default_rng(2), sort=False)
    cov = point_covariance(t, rho, alpha, traj, FULL_MOUNT, SCANNER, MOUNT_COV)
    assert cov.shape == (3000, 3, 3)
    np.testing.assert_allclose(cov, cov.transpose(0, 2, 1), rtol=0, atol=1e-18)
    assert np.linalg.eigvalsh(cov).min() > 0
    sh, sv = point_sigmas(t, rho, alpha, traj, FULL_MOUNT, SCANNER, MOUNT_COV, block=777)
    assert sh.dtype == np.float64
    assert sh.shape == sv.shape == (3000,)
    np.testing.assert_allclose(sh, np.sqrt(cov[:, 0, 0] + cov[:, 1, 1]), rtol=1e-12)
    np.testing.assert_allclose(sv, np.sqrt(cov[:, 2, 2]), rtol=1e-12)
    sh32, sv32 = point_sigmas(
        t, rho, alpha, traj, FULL_MOUNT, SCANNER, MOUNT_COV, block=1000, dtype=np.float32
    )
    assert sh32.dtype == np.float32
    np.testing.assert_allclose(sh32, sh, rtol=1e-6)
    np.testing.assert_allclose(sv32, sv, rtol=1e-6)


def test_sigmas_into_given_arrays_are_those_of_new_arrays(wave_trajectory):
    traj = wave_trajectory(duration_s=3.0, sigmas=True)
    t, rho, alpha = returns(traj, 2000, np.random.default_rng(5))
    sh32, sv32 = point_sigmas(
        t, rho, alpha, traj, FULL_MOUNT, SCANNER, MOUNT_COV, block=300, dtype=np.float32
    )
    rec = np.zeros(2000, [("a", "<i4"), ("sigma_h_m", "<f4"), ("b", "u1"), ("sigma_v_m", "<f4")])
    got = point_sigmas(
        t,
        rho,
        alpha,
        traj,
        FULL_MOUNT,
        SCANNER,
        MOUNT_COV,
        block=300,
        out=(rec["sigma_h_m"], rec["sigma_v_m"]),
    )
    assert got[0].base is rec or got[0].base is rec.base
    assert rec["sigma_h_m"].tobytes() == sh32.tobytes()
    assert rec["sigma_v_m"].tobytes() == sv32.tobytes()
    assert not rec["a"].any()
    assert not rec["b"].any()
    with pytest.raises(TpuError, match="out must be two float arrays of 2000"):
        point_sigmas(t, rho, alpha, traj, FULL_MOUNT, SCANNER, MOUNT_COV, out=(np.zeros(2000), np.zeros(3)))


def test_trajectory_without_sigmas_contributes_nothing(wave_trajectory):
    with_s, without = wave_trajectory(sigmas=True), wave_trajectory(sigmas=False)
    t, rho, alpha = returns(with_s, 500, np.random.default_rng(3))
    zero = MountCovariance.zero()
    sh, sv = point_sigmas(t, rho, alpha, without, FULL_MOUNT, ScannerSigmas(), zero)
    assert np.all(sh == 0)
    assert np.all(sv == 0)
    sh, sv = point_sigmas(t, rho, alpha, with_s, FULL_MOUNT, ScannerSigmas(), zero)
    assert np.all(sh > 0.028)
    assert np.all(sv > 0.03)


def test_hand_computed_sigmas_on_a_level_vessel():
    """Level, heading north, identity mount, no lever arm: a return straight down (α = 90°)
    and one to starboard (α = 0°), 10 m away; each source moves them along a known axis."""
    t = 1.3e9 + np.arange(11) * 0.1
    sp, sa = np.array([0.01, 0.02, 0.03]), D([0.01, 0.02, 0.05])
    traj = Trajectory(
        t,
        np.zeros((11, 3)),
        np.zeros((11, 3)),
        frames.LocalFrame(45.0, -73.0),
        sigma_p_m=np.tile(sp, (11, 1)),
        sigma_rpy_rad=np.tile(sa, (11, 1)),
    )
    lever = np.diag([4e-4, 1e-4, 9e-4])
    mc = MountCovariance(BORESIGHT_COV, lever)
    rho = 10.0
    s_rho = SCANNER.sigma_range_m + SCANNER.sigma_range_per_m * rho  # linear, as calib.io.site
    s_a, bs = SCANNER.sigma_angle_rad, np.diag(BORESIGHT_COV)
    sh, sv = point_sigmas([t[3], t[5]], [rho, rho], D([90.0, 0.0]), traj, Mount(), SCANNER, mc)
    # down: roll, pitch, scan angle, boresight roll and pitch move it horizontally; range vertically
    h_down = sp[0] ** 2 + sp[1] ** 2 + rho**2 * (sa[0] ** 2 + sa[1] ** 2 + s_a**2 + bs[0] + bs[1]) + 5e-4
    v_down = sp[2] ** 2 + s_rho**2 + 9e-4
    # starboard: range, heading and boresight yaw horizontal; roll, scan angle, boresight roll vertical
    h_stbd = sp[0] ** 2 + sp[1] ** 2 + s_rho**2 + rho**2 * (sa[2] ** 2 + bs[2]) + 5e-4
    v_stbd = sp[2] ** 2 + rho**2 * (s_a**2 + sa[0] ** 2 + bs[0]) + 9e-4
    np.testing.assert_allclose(sh, np.sqrt([h_down, h_stbd]), rtol=1e-12)
    np.testing.assert_allclose(sv, np.sqrt([v_down, v_stbd]), rtol=1e-12)


def test_uncovered_times_are_refused(wave_trajectory):
    traj = wave_trajectory(duration_s=1.0)
    t = traj.t_gps_s[0] + np.array([0.1, 0.5, 2.0, 3.0])
    args = (t, np.full(4, 10.0), np.zeros(4), traj, Mount(), SCANNER, MOUNT_COV)
    with pytest.raises(TrajectoryError, match="2 of 4 point times"):
        point_sigmas(*args, block=2)
    with pytest.raises(TrajectoryError):
        point_covariance(*args)


# -- 3. Monte Carlo on a simulated survey ------------------------------------------------------


def _bin_table(
    pred: np.ndarray, mc: np.ndarray, n_bins: int = 5
) -> list[tuple[float, float, float, float, int]]:
    """Quantile bins of the predicted σ: (low edge, RMS predicted, RMS Monte Carlo, ratio, count)."""
    edges = np.quantile(pred, np.linspace(0.0, 1.0, n_bins + 1))
    idx = np.clip(np.searchsorted(edges, pred, side="right") - 1, 0, n_bins - 1)
    rows = []
    for b in range(n_bins):
        sel = idx == b
        p, m = np.sqrt(np.mean(pred[sel] ** 2)), np.sqrt(np.mean(mc[sel] ** 2))
        rows.append((float(edges[b]), float(p), float(m), float(m / p), int(sel.sum())))
    return rows


def test_monte_carlo_spread_matches_predicted_sigmas_per_bin():
    from calib.sim.noise import ScannerNoise
    from calib.sim.simulate import simulate

    started = time.perf_counter()
    sim = simulate("tower", seed=0)  # quay targets and a 40 m tower: ranges ~13 … 57 m
    obs = sim.trajectory_observed
    # per-epoch sigmas varying along the survey (the simulator's are constant): the position σ
    # and the attitude σ swing in opposite phase, so both matter in different places
    u = 0.5 * (1.0 + np.sin(2.0 * np.pi * (obs.t_gps_s - obs.t_gps_s[0]) / 137.0))[:, None]
    traj = replace(
        obs,
        sigma_p_m=np.array([0.005, 0.005, 0.008]) * (0.4 + 1.6 * u),
        sigma_rpy_rad=D([0.015, 0.015, 0.04]) * (0.4 + 1.6 * (1.0 - u)),
    )
    rng = np.random.default_rng(20240611)
    keep = np.sort(rng.choice(sim.points.t_gps_s.size, 20_000, replace=False))
    t = sim.points.t_gps_s[keep]
    rho, alpha = sim.points.range_m[keep], sim.points.scan_angle_rad[keep]
    mount = replace(sim.mount_true, time_offset_s=0.0004, range_offset_m=0.003)
    assert rho.min() < 15.0
    assert rho.max() > 45.0

    sigma_h, sigma_v = point_sigmas(t, rho, alpha, traj, mount, SCANNER, MOUNT_COV, block=4096)

    # K realisations of every error source, georeferenced with the reference implementation
    poses = traj.interpolate(t + mount.time_offset_s)
    x0 = georeference_poses(poses, rho, alpha, mount)
    scanner_noise = ScannerNoise(  # the simulator's scanner noise, same σ definition
        sigma_range_m=SCANNER.sigma_range_m,
        sigma_range_per_m=SCANNER.sigma_range_per_m,
        sigma_scan_angle_rad=SCANNER.sigma_angle_rad,
    )
    K, n = 200, t.size
    # the boresight and lever-arm errors are shared by all points: K draws of them have a sample
    # covariance ~10 % off, the same for every point, which no binning averages out; so their K
    # draws are moment-matched (centred and whitened: sample mean 0, sample covariance exact)
    z = rng.standard_normal((K, 6))
    z -= z.mean(axis=0)
    z = z @ np.linalg.inv(np.linalg.cholesky(np.cov(z, rowvar=False))).T
    d_bs = z[:, :3] @ np.linalg.cholesky(BORESIGHT_COV).T
    d_la = z[:, 3:] @ np.linalg.cholesky(LEVER_COV).T
    np.testing.assert_allclose(
        np.cov(np.hstack([d_bs, d_la]), rowvar=False)[:3, :3], BORESIGHT_COV, rtol=1e-9
    )
    s1, s2 = np.zeros((n, 3)), np.zeros((n, 3))
    assert poses.sigma_p_m is not None  # the trajectory carries its σ
    assert poses.sigma_rpy_rad is not None
    for k in range(K):
        # POS errors per point with the trajectory's σ at that instant (drawn here: the
        # simulator's white_noise takes one σ per channel, not one per point)
        dp = rng.standard_normal((n, 3)) * poses.sigma_p_m
        rpy = poses.rpy_rad + rng.standard_normal((n, 3)) * poses.sigma_rpy_rad
        d_rho, d_alpha = scanner_noise.draw(rho, np.ones(n), rng)
        m_k = replace(
            mount,
            boresight_rad=mount.boresight_rad + d_bs[k],
            lever_arm_m=mount.lever_arm_m + d_la[k],
        )
        x = georeference_poses(
            Poses(poses.p_lgf_m + dp, rpy, frames.attitude_matrix(*rpy.T)), rho + d_rho, alpha + d_alpha, m_k
        )
        d = x - x0
        s1 += d
        s2 += d * d
    var = (s2 - s1 * s1 / K) / (K - 1)  # per point and axis, about the realisations' mean
    mc_h, mc_v = np.sqrt(var[:, 0] + var[:, 1]), np.sqrt(var[:, 2])
    elapsed = time.perf_counter() - started

    print(f"\nMonte Carlo: {n} points, K = {K} realisations, {elapsed:.1f} s")
    for label, pred, mc in (("sigma_h_m", sigma_h, mc_h), ("sigma_v_m", sigma_v, mc_v)):
        rows = _bin_table(pred, mc)
        print(f"{label}: bin  from_m     predicted_m  monte_carlo_m  ratio   points")
        for b, (lo, p, m, r, c) in enumerate(rows):
            print(f"           {b}  {lo:.5f}  {p:.5f}      {m:.5f}        {r:.3f}   {c}")
        for lo, p, m, r, _count in rows:
            assert abs(r - 1.0) < 0.15, (label, lo, p, m)  # the requirement
            # with the shared errors moment-matched the Monte Carlo is good to ~0.5 % per bin; 3 %
            # catches a dropped pitch, roll, scan-angle or lever-arm term or an RSS range σ
            assert abs(r - 1.0) < 0.03, (label, lo, p, m)
        # the bins are meaningful: σ grows by more than half from the lowest bin to the highest
        assert rows[-1][1] > 1.5 * rows[0][1], label
        # and point by point, the sample σ of K = 200 scatters by ~5 % around the prediction
        ratio = mc / pred
        assert abs(np.median(ratio) - 1.0) < 0.02, label
        assert np.quantile(np.abs(ratio - 1.0), 0.95) < 0.15, label


# -- 4. bad input ------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"boresight_cov_rad2": np.zeros((2, 3))}, "boresight_cov_rad2"),
        ({"lever_arm_cov_m2": np.zeros(3)}, "lever_arm_cov_m2"),
        ({"boresight_cov_rad2": np.diag([1e-8, -1e-8, 1e-8])}, "boresight_cov_rad2.*positive semi-definite"),
        (
            {"lever_arm_cov_m2": [[1e-4, 2e-4, 0], [2e-4, 1e-4, 0], [0, 0, 1e-4]]},
            "lever_arm_cov_m2.*semi-definite",
        ),
        ({"lever_arm_cov_m2": [[1e-4, 1e-5, 0], [0, 1e-4, 0], [0, 0, 1e-4]]}, "lever_arm_cov_m2.*symmetric"),
        ({"boresight_cov_rad2": np.diag([1e-8, np.nan, 1e-8])}, "boresight_cov_rad2.*non-finite"),
        ({"lever_arm_cov_m2": "big"}, "lever_arm_cov_m2"),
    ],
)
def test_bad_mount_covariance_names_the_field(kwargs, field):
    args = {"boresight_cov_rad2": BORESIGHT_COV, "lever_arm_cov_m2": LEVER_COV} | kwargs
    with pytest.raises(TpuError, match=f"MountCovariance.{field}") as exc:
        MountCovariance(**args)
    assert isinstance(exc.value, CalibError)
    assert isinstance(exc.value, ValueError)


@pytest.mark.parametrize(
    ("attr", "value"), [("sigma_range_m", -0.001), ("sigma_range_per_m", np.inf), ("sigma_angle_rad", "x")]
)
def test_bad_scanner_sigmas_name_the_field(attr, value):
    with pytest.raises(TpuError, match=f"ScannerSigmas.{attr}"):
        ScannerSigmas(**{attr: value})


def test_bad_observation_shapes_name_the_array(wave_trajectory):
    traj = wave_trajectory(duration_s=1.0)
    t = traj.t_gps_s[0] + np.array([0.1, 0.2, 0.3])
    rest = (traj, Mount(), SCANNER, MOUNT_COV)
    for fn in (point_sigmas, point_covariance):
        with pytest.raises(TpuError, match="range_m has shape \\(2,\\)"):
            fn(t, np.ones(2), np.zeros(3), *rest)
        with pytest.raises(TpuError, match="scan_angle_rad has shape \\(3, 1\\)"):
            fn(t, np.ones(3), np.zeros((3, 1)), *rest)
        with pytest.raises(TpuError, match="t_gps_s has shape \\(\\)"):
            fn(t[0], np.ones(3), np.zeros(3), *rest)
        with pytest.raises(TpuError, match="mount_cov must be a MountCovariance"):
            fn(t, np.ones(3), np.zeros(3), traj, Mount(), SCANNER, BORESIGHT_COV)  # type: ignore[arg-type]  # the wrong type on purpose
    with pytest.raises(TpuError, match="block"):
        point_sigmas(t, np.ones(3), np.zeros(3), *rest, block=0)
