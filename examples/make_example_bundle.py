"""Make ``examples/montreal-mini``: a small, deterministic calibration bundle (≤ 1 MB).

A vessel sails two 24 m passes (heading 0° and 180°) past a quay at 15 m standoff, with a swell
(roll, pitch, yaw, heave), while a 2D profiler scans across the track. The scene is the quay face
(30 × 5 m) and two targets standing on the quay 5 m above the scanner, as in the Port of
Montreal campaign of the thesis: T1 vertical 1.23 × 1.22 m, T2 inclined 45°, 1.23 × 0.76 m.

Points are not simulated (the simulator, ``calib.sim.simulate``, comes later); they are placed on the
rectangles where the scan plane cuts them (every 8th profile of 200/s, a fixed step along each
rectangle), and ``calib.core.georef.inverse_georeference`` turns them into the range and scan angle
the scanner would report. There is no noise, so georeferencing with the true boresight (in
``truth.json``; canonical roll 0.208°, pitch 1.245°, yaw 0.149°) puts every point on its
rectangle; ``site.yaml`` carries a zero a-priori boresight, as before a calibration.

    .venv/bin/python examples/make_example_bundle.py [OUT_DIR]   (default examples/montreal-mini)
"""

from __future__ import annotations

import datetime
import sys
from pathlib import Path

import numpy as np

from calib.core import frames
from calib.core.geometry import Rectangle
from calib.core.georef import Mount, inverse_georeference
from calib.core.trajectory import Trajectory
from calib.io.bundle import ScanPoints, write_bundle
from calib.io.site import PassSpec, Site, Target

REFERENCE = frames.LocalFrame(45.5, -73.55, -30.0)  # LGF origin (ellipsoidal height)
T_START_GPS_S = frames.gps_ns_to_seconds(
    frames.utc_to_gps_ns(datetime.datetime(2021, 8, 17, 14, tzinfo=datetime.UTC))
)
TRAJECTORY_RATE_HZ = 50.0
PROFILE_RATE_HZ = 25.0  # every 8th profile of the Z+F's 200 per second
ROTATION_PERIOD_S = 1.0 / 200.0
SPEED_MPS = 2.0
PASS_LENGTH_M = 24.0
TURN_S = 40.0  # time between the passes (no trajectory: a gap)
STANDOFF_M = 15.0
LEVER_ARM_M = [0.42, -0.31, -1.85]
TRUE_BORESIGHT_DEG = (0.208, 1.245, 0.149)  # canonical (thesis: 0.208, −1.245, 0.149)

#: name, centre (north, east, down) in the LGF, width, height, inclination°, facing°,
#: reflectivity, sampling step along the height (m)
SCENE = [
    ("T1", (-3.0, STANDOFF_M + 0.5, -7.0), 1.23, 1.22, 90.0, 270.0, 0.9, 0.02),
    ("T2", (3.0, STANDOFF_M + 0.5, -7.0), 1.23, 0.76, 45.0, 270.0, 0.9, 0.02),
    ("quay-face", (0.0, STANDOFF_M, -2.0), 30.0, 5.0, 90.0, 270.0, 0.35, 0.25),
]


def trajectory() -> Trajectory:
    """Two straight passes along the quay with a swell; 1 s run-in and run-out each."""
    parts, t_pass = [], T_START_GPS_S
    duration = PASS_LENGTH_M / SPEED_MPS + 2.0
    for heading_deg in (0.0, 180.0):
        t = t_pass + np.arange(0.0, duration + 1e-9, 1.0 / TRAJECTORY_RATE_HZ)
        s = t - T_START_GPS_S
        along = -0.5 * PASS_LENGTH_M - SPEED_MPS + SPEED_MPS * (t - t_pass)
        north = along if heading_deg == 0.0 else -along
        p = np.stack([north, 0.05 * np.sin(0.3 * s), 0.15 * np.sin(2 * np.pi * s / 5.5)], axis=1)
        rpy = np.stack(
            [
                np.radians(2.5) * np.sin(2 * np.pi * s / 6.0),
                np.radians(0.8) * np.sin(2 * np.pi * s / 4.5 + 0.7),
                frames.wrap_2pi(np.radians(heading_deg + 0.4 * np.sin(2 * np.pi * s / 9.0))),
            ],
            axis=1,
        )  # pass 1's heading swings across 360°/0°
        parts.append((t, p, rpy))
        t_pass = t[-1] + TURN_S
    t, p, rpy = (np.concatenate(x) for x in zip(*parts))
    n = t.size
    sig_p = np.tile([0.02, 0.02, 0.03], (n, 1))
    sig_a = np.radians(np.tile([0.008, 0.008, 0.02], (n, 1)))
    return Trajectory(t, p, rpy, REFERENCE, sig_p, sig_a, max_gap_s=1.0, name="montreal-mini")


def _cut(rect: Rectangle, v, t, traj: Trajectory, mount: Mount):
    """The points of ``rect`` at heights ``v`` (along its v axis) that lie in the scan plane at
    times ``t``: (u, points, scanner origins). Solves n·(c + u·U + v·V − o) = 0 for u, which is
    well conditioned here because the width axis U runs along the track."""
    poses = traj.interpolate(t)
    origin = poses.p_lgf_m + poses.r_b_n @ mount.lever_arm_m
    normal = poses.r_b_n @ mount.r_s_b[:, 0]  # the scanner's x axis: normal of the scan plane
    q = rect.center_m + v[:, None] * rect.v_axis - origin
    u = -np.einsum("ij,ij->i", normal, q) / (normal @ rect.u_axis)
    return u, origin + q + u[:, None] * rect.u_axis, origin


def scan_rectangle(rect: Rectangle, step_m: float, t_profiles, traj: Trajectory, mount: Mount):
    """Where each profile's scan plane cuts ``rect`` (every ``step_m`` along its height), each
    point at the time the rotating beam passes it: (times, LGF points, point → scanner)."""
    v = np.arange(-0.5 * rect.height_m, 0.5 * rect.height_m + 1e-9, step_m)
    t = np.repeat(t_profiles, v.size)
    v = np.tile(v, t_profiles.size)
    t_beam = t
    for _ in range(3):  # the beam's time depends on its angle: a short fixed-point iteration
        _, p, _ = _cut(rect, v, t_beam, traj, mount)
        alpha = inverse_georeference(p, t_beam, traj, mount).scan_angle_rad
        t_beam = t + alpha / (2 * np.pi) * ROTATION_PERIOD_S
    u, p, origin = _cut(rect, v, t_beam, traj, mount)
    keep = (np.abs(u) <= 0.5 * rect.width_m) & ((origin - p) @ rect.normal > 0)
    return t_beam[keep], p[keep], (origin - p)[keep]


def main(out_dir: Path) -> None:
    traj = trajectory()
    true_mount = Mount(lever_arm_m=LEVER_ARM_M, boresight_rad=np.radians(TRUE_BORESIGHT_DEG))
    scene = []  # (Target, sampling step)
    for name, c, w, h, incl, facing, refl, step in SCENE:
        lat, lon, hgt = (float(x[0]) for x in REFERENCE.to_geodetic(np.array([c])))
        target = Target(name, lat, lon, hgt, w, h, float(np.radians(incl)), float(np.radians(facing)), refl)
        scene.append((target, step))
    site = Site(
        mount=Mount(lever_arm_m=LEVER_ARM_M),  # a-priori boresight 0: before calibration
        targets=tuple(t for t, _ in scene if t.name.startswith("T")),
        reference=REFERENCE,
        vessel="montreal-mini",
        standoff_m=STANDOFF_M,
        passes=(
            PassSpec(1, 0.0, PASS_LENGTH_M, SPEED_MPS),
            PassSpec(2, float(np.pi), PASS_LENGTH_M, SPEED_MPS),
        ),
        validation_planes=tuple(t for t, _ in scene if not t.name.startswith("T")),
    )

    gap = int(np.flatnonzero(np.diff(traj.t_gps_s) > traj.max_gap_s)[0])
    pass_spans = [(traj.t_gps_s[0], traj.t_gps_s[gap]), (traj.t_gps_s[gap + 1], traj.t_gps_s[-1])]
    parts = []
    for pass_id, (t0, t1) in enumerate(pass_spans, start=1):
        t_profiles = np.arange(t0 + 1.0, t1 - 1.0, 1.0 / PROFILE_RATE_HZ)
        for target, step in scene:
            rect = target.rectangle(REFERENCE)
            t, p, to_scanner = scan_rectangle(rect, step, t_profiles, traj, true_mount)
            obs = inverse_georeference(p, t, traj, true_mount)
            assert np.abs(obs.out_of_plane_m).max() < 1e-9, "points must lie in the scan plane"
            incidence = np.abs(to_scanner @ rect.normal) / np.linalg.norm(to_scanner, axis=1)
            intensity = np.round(rect.reflectivity * incidence, 3)
            parts.append(ScanPoints(np.full(t.size, pass_id), t, obs.range_m, obs.scan_angle_rad, intensity))
    points = ScanPoints.concatenate(parts)
    points = points.select(np.lexsort((points.t_gps_s, points.pass_id)))
    truth = {
        "generator": "examples/make_example_bundle.py (exact points, no noise)",
        "convention": "canonical (docs/architecture.md §3)",
        "boresight_deg": dict(zip(("roll", "pitch", "yaw"), TRUE_BORESIGHT_DEG)),
        "lever_arm_m": LEVER_ARM_M,
        "range_offset_m": 0.0,
        "scan_angle_offset_deg": 0.0,
        "time_offset_s": 0.0,
    }
    write_bundle(out_dir, site, traj, points, truth=truth, compress_points=True)
    size = sum(f.stat().st_size for f in out_dir.iterdir())
    print(
        f"{out_dir}: {len(points)} points in {len(pass_spans)} passes, "
        f"{traj.t_gps_s.size} trajectory epochs, {size / 1e3:.0f} kB"
    )


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).parent / "montreal-mini")
