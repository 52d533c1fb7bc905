"""Raw scanner points georeferenced pass by pass (with the trajectory, or per-point poses), and
the heading of each pass."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from calib.core import frames
from calib.core.georef import Mount, georeference, georeference_poses
from calib.core.sampling import random_subset
from calib.core.trajectory import Poses, Trajectory
from calib.io.bundle import ScanPoints

#: returns per line whose trajectory heading is averaged into the line's heading
HEADING_SAMPLES = 5000


def georeference_passes(
    points: ScanPoints,
    trajectory: Trajectory,
    mount: Mount,
    poses: Poses | None,
    progress: Callable[[str, float, float | None], None] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Points and beam origins (the scanner's position) in the LGF, pass by pass."""
    n = len(points)
    p, origin = np.empty((n, 3)), np.empty((n, 3))
    pass_ids = points.pass_ids()
    zero = np.zeros(n)
    for k, pid in enumerate(pass_ids):
        sel = np.flatnonzero(points.pass_id == pid)
        t, rho, alpha = points.t_gps_s[sel], points.range_m[sel], points.scan_angle_rad[sel]
        if poses is None:
            p[sel] = georeference(t, rho, alpha, trajectory, mount)
            origin[sel] = georeference(t, zero[sel], alpha, trajectory, mount)
        else:
            sub = Poses(poses.p_lgf_m[sel], poses.rpy_rad[sel], poses.r_b_n[sel])
            p[sel] = georeference_poses(sub, rho, alpha, mount)
            origin[sel] = georeference_poses(sub, zero[sel], alpha, mount)
        if progress is not None:
            progress("georeferencing passes", k + 1, len(pass_ids))
    return p, origin


def pass_headings(
    obs_heading_rad: np.ndarray, pass_id: np.ndarray, wall_azimuth_rad: float
) -> dict[int, float]:
    """Heading of each pass relative to the wall direction: the circular mean of the vessel's
    heading at the pass's points."""
    out = {}
    for p in np.unique(pass_id):
        h = obs_heading_rad[pass_id == p]
        mean = np.arctan2(np.mean(np.sin(h)), np.mean(np.cos(h)))
        out[int(p)] = float(frames.wrap_2pi(mean - wall_azimuth_rad))
    return out


def line_headings(
    points: ScanPoints, trajectory: Trajectory, wall_azimuth_rad: float, time_offset_s: float = 0.0
) -> dict[int, float]:
    """:func:`pass_headings` of each line from at most :data:`HEADING_SAMPLES` of its returns
    drawn at random (seeded): a line's heading varies slowly, and interpolating the trajectory
    at every return took a fifth of a watch block's CPU."""
    pid = points.pass_id
    pick = np.concatenate(
        [random_subset(np.flatnonzero(pid == p), HEADING_SAMPLES, seed=int(p)) for p in points.pass_ids()]
    )
    yaw = trajectory.interpolate(points.t_gps_s[pick] + time_offset_s).rpy_rad[:, 2]
    return pass_headings(yaw, pid[pick], wall_azimuth_rad)
