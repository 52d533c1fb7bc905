"""A minimal, independent generator of plane observations for adjustment tests.

It does not ray-cast (the product's simulator does): it samples points uniformly on each
rectangle and finds, by bisection, the time at which the true scan plane sweeps through each
point; range and scan angle then come from the inverse georeferencing with the true mount.
Independent of :mod:`calib.sim.simulate`, so the adjustment is checked against a second route.
"""

from __future__ import annotations

import numpy as np

from calib.boresight.observations import Observations
from calib.boresight.scene_ties import facing_cylinder
from calib.core import frames
from calib.core.geometry import Rectangle, VerticalCylinder  # noqa: F401  (re-exported for tests)
from calib.core.georef import Mount, inverse_georeference
from calib.core.trajectory import Trajectory

FRAME = frames.LocalFrame(45.5, -73.55, 0.0)
SIX_FOLD_DEG = (0.0, 180.0, 45.0, 225.0, 315.0, 135.0)


def montreal_planes(spread_m: float = 3.0) -> list[Rectangle]:
    """Vertical 1.23 × 1.22 m and 45° 1.23 × 0.76 m targets on a wall facing west (x = 15 m
    east of the pass lines' closest approach), 5 m above the scanner (D = −5)."""
    az = np.radians(270.0)
    return [
        Rectangle.from_orientation("T1", [-spread_m / 2, 15.0, -5.0], 1.23, 1.22, np.radians(90.0), az),
        Rectangle.from_orientation("T2", [spread_m / 2, 15.0, -5.0], 1.23, 0.76, np.radians(45.0), az),
    ]


def pass_trajectory(
    heading_deg: float,
    t0: float,
    standoff_m: float = 15.0,
    length_m: float = 60.0,
    speed_mps: float = 2.0,
    rate_hz: float = 50.0,
    roll_amp_deg: float = 2.0,
    pitch_amp_deg: float = 1.0,
) -> Trajectory:
    """A straight pass whose closest approach to (0, 15, ·) is the standoff (wall along north at
    east = 15 m); waves in roll and pitch."""
    h = np.radians(heading_deg)
    d = np.array([np.cos(h), np.sin(h), 0.0])
    # closest approach point: the target group centre moved toward the water (west)
    centre = np.array([0.0, 15.0 - standoff_m, 0.0])
    duration = length_m / speed_mps
    t = t0 + np.arange(0.0, duration + 1e-9, 1.0 / rate_hz)
    s = (t - t0 - duration / 2) * speed_mps
    p = centre + s[:, None] * d
    tau = t - t0
    rpy = np.stack(
        [
            np.radians(roll_amp_deg) * np.sin(2 * np.pi * tau / 6.0),
            np.radians(pitch_amp_deg) * np.sin(2 * np.pi * tau / 8.0 + 1.0),
            np.full_like(tau, h % (2 * np.pi)),
        ],
        axis=1,
    )
    return Trajectory(t, p, rpy, FRAME, max_gap_s=1.0)


def _sweep_time(traj: Trajectory, mount: Mount, p: np.ndarray, iterations: int = 60):
    """Times at which the scan plane passes through each point (NaN where it never does)."""
    lo = np.full(p.shape[0], traj.t_gps_s[0] + 1e-6)
    hi = np.full(p.shape[0], traj.t_gps_s[-1] - 1e-6 - abs(mount.time_offset_s))
    f_lo = inverse_georeference(p, lo, traj, mount).out_of_plane_m
    f_hi = inverse_georeference(p, hi, traj, mount).out_of_plane_m
    ok = np.sign(f_lo) != np.sign(f_hi)
    for _ in range(iterations):
        mid = 0.5 * (lo + hi)
        f = inverse_georeference(p, mid, traj, mount).out_of_plane_m
        left = np.sign(f) == np.sign(f_lo)
        lo = np.where(left, mid, lo)
        f_lo = np.where(left, f, f_lo)
        hi = np.where(left, hi, mid)
    return np.where(ok, 0.5 * (lo + hi), np.nan)


def observations(
    mount_true: Mount,
    planes: list[Rectangle],
    headings_deg=SIX_FOLD_DEG,
    points_per_plane_per_pass: int = 100,
    sigmas=(
        0.02,
        0.02,
        0.03,
        np.radians(0.012),
        np.radians(0.012),
        np.radians(0.012),
        0.003,
        np.radians(0.005),
    ),
    noise: bool = True,
    seed: int = 0,
    max_range_m: float = 119.0,
    t_base_s: float = 1000.0,
) -> tuple[Observations, list[tuple[np.ndarray, float]], list[Trajectory]]:
    """Observations with independent per-point noise (the adjustment's own stochastic model),
    the true planes as (normal, d), and the pass trajectories."""
    rng = np.random.default_rng(seed)
    sig = np.asarray(sigmas, float)
    chunks = []
    trajs = []
    for k, hdg in enumerate(headings_deg):
        traj = pass_trajectory(hdg, t0=t_base_s + 200.0 * k)
        trajs.append(traj)
        for j, feature in enumerate(planes):
            p = _surface_samples(feature, points_per_plane_per_pass, rng)
            t = _sweep_time(traj, mount_true, p)
            keep = np.isfinite(t)
            p, t = p[keep], t[keep]
            poses = traj.interpolate(t + mount_true.time_offset_s)
            if isinstance(feature, VerticalCylinder):  # the side facing the scanner
                seen = _facing(feature, p, poses.p_lgf_m)
                p, t, poses = p[seen], t[seen], traj.interpolate(t[seen] + mount_true.time_offset_s)
            obs = inverse_georeference(p, t, traj, mount_true)
            keep = obs.range_m < max_range_m
            l = np.column_stack([poses.p_lgf_m, poses.rpy_rad, obs.range_m, obs.scan_angle_rad])
            chunks.append((t[keep], l[keep], np.full(keep.sum(), j), np.full(keep.sum(), k)))
    t = np.concatenate([c[0] for c in chunks])
    l = np.concatenate([c[1] for c in chunks])
    plane_index = np.concatenate([c[2] for c in chunks]).astype(int)
    pass_index = np.concatenate([c[3] for c in chunks]).astype(int)
    order = np.lexsort((t, pass_index))
    t, l, plane_index, pass_index = t[order], l[order], plane_index[order], pass_index[order]
    if noise:
        l = l + rng.standard_normal(l.shape) * sig
    n = t.size
    obs = Observations(
        t_gps_s=t,
        l=l,
        sigma_l=np.broadcast_to(sig, (n, 8)).copy(),
        plane_index=plane_index,
        pass_index=pass_index,
        plane_names=[r.name for r in planes],
        pass_ids=list(range(1, len(headings_deg) + 1)),
        point_ids=np.arange(n),
        pass_headings_rad={k + 1: np.radians(h) for k, h in enumerate(headings_deg)},
    )
    truth_planes = [f if isinstance(f, VerticalCylinder) else (f.normal.copy(), f.d) for f in planes]
    return obs, truth_planes, trajs


def _surface_samples(feature, n: int, rng) -> np.ndarray:
    """(n, 3) points uniform over a rectangle or a vertical cylinder's mantle."""
    if isinstance(feature, VerticalCylinder):
        phi = rng.uniform(0.0, 2.0 * np.pi, n)
        dz = rng.uniform(-0.5, 0.5, n) * feature.height_m
        ring = feature.radius_m * np.column_stack([np.cos(phi), np.sin(phi), np.zeros(n)])
        return feature.center_m + ring + dz[:, None] * np.array([0.0, 0.0, 1.0])
    uv = rng.uniform(-0.5, 0.5, (n, 2)) * [feature.width_m, feature.height_m]
    return feature.center_m + uv[:, :1] * feature.u_axis + uv[:, 1:] * feature.v_axis


def _facing(cylinder: VerticalCylinder, p: np.ndarray, vessel_m: np.ndarray) -> np.ndarray:
    """Whether each point of the cylinder faces the vessel (the beam reaches it from outside)
    within the incidence the calibration uses (:func:`calib.boresight.scene_ties.facing_cylinder`)."""
    outward = cylinder.outward_normals(p)
    front = np.einsum("ij,ij->i", outward[:, :2], (vessel_m - p)[:, :2]) > 0.0
    axis = np.broadcast_to(cylinder.center_m, p.shape)
    return front & facing_cylinder(p, vessel_m, axis)


def pile_row(n_piles: int = 4, first_along_m: float = 6.0, spacing_m: float = 5.0) -> list[VerticalCylinder]:
    """Piles of 0.3–1.2 m diameter 1.5 m in front of :func:`montreal_planes`'s wall (east = 13.5 m),
    from the water to the wall's top (D from −1 to −8), along north from ``first_along_m``."""
    diameters = (0.3, 0.6, 0.9, 1.2)
    return [
        VerticalCylinder(
            name=f"pile_{k}",
            center_m=np.array([first_along_m + k * spacing_m, 13.5, -4.5]),
            radius_m=0.5 * diameters[k % len(diameters)],
            height_m=7.0,
        )
        for k in range(n_piles)
    ]
