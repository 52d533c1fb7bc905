"""Raw scanner points georeferenced pass by pass (with the trajectory, or per-point poses)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from calib.core.georef import Mount, georeference, georeference_poses
from calib.core.trajectory import Poses, Trajectory
from calib.io.bundle import ScanPoints


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
