"""Checks of the input before anything is computed (docs/architecture.md §7.1): points that
cannot be georeferenced, a trajectory that does not cover them or never comes near a target,
a site without targets. Each refusal says what to do."""

from __future__ import annotations

import numpy as np

from calib.core.errors import CalibError
from calib.core.trajectory import Poses, Trajectory
from calib.io.bundle import SCANNER_RANGE_M, ScanPoints
from calib.io.site import Site


class CalibrationError(CalibError, ValueError):
    """The input cannot be calibrated as given (the message says why and what to do)."""


# -- checks ---------------------------------------------------------------------------------


def check_points(points: ScanPoints, trajectory: Trajectory, time_offset_s: float = 0.0) -> None:
    """Refuse what cannot be georeferenced: non-finite times or observations, times going
    backwards within a pass, and points the trajectory does not cover (named by pass)."""
    t, pid = points.t_gps_s, points.pass_id
    bad = ~np.isfinite(t)
    if bad.any():
        i = int(np.argmax(bad))
        raise CalibrationError(
            f"{int(bad.sum())} point time(s) are NaN or infinite (first: "
            f"point {i}, pass {int(pid[i])}); fix or drop them"
        )
    for name, arr in (("range", points.range_m), ("scan angle", points.scan_angle_rad)):
        bad = ~np.isfinite(arr)
        if bad.any():
            i = int(np.argmax(bad))
            raise CalibrationError(
                f"{name} is NaN or infinite for {int(bad.sum())} point(s) "
                f"(first: point {i}, pass {int(pid[i])})"
            )
    back = (pid[1:] == pid[:-1]) & (np.diff(t) < 0)
    if back.any():
        i = int(np.argmax(back)) + 1
        raise CalibrationError(
            f"point times go backwards within pass {int(pid[i])} at point {i} "
            f"({t[i]:.6f} s after {t[i - 1]:.6f} s): the points of a pass "
            f"must be in time order"
        )
    uncovered = trajectory.uncovered(t + time_offset_s)
    if uncovered.any():
        parts = []
        for p in np.unique(pid[uncovered]):
            m = uncovered & (pid == p)
            parts.append(
                f"pass {int(p)}: {int(m.sum())} of {int(np.sum(pid == p))} points, "
                f"{t[m].min():.3f}…{t[m].max():.3f} s ({trajectory.where_uncovered(t[m] + time_offset_s)})"
            )
        raise CalibrationError(
            f"the trajectory does not cover the points: {trajectory.name} spans "
            f"{trajectory.t_gps_s[0]:.3f}…{trajectory.t_gps_s[-1]:.3f} s (gaps > "
            f"{trajectory.max_gap_s:g} s refused); {'; '.join(parts)}. Export the trajectory over "
            f"every pass, or drop these points with --skip-uncovered (mls calib run)."
        )


def check_within_reach(trajectory: Trajectory, rects) -> None:
    """Refuse a trajectory that never comes within the scanner's range of any target (a wrong
    reference point in site.yaml, another datum, another site's file), naming the distance."""
    p = trajectory.p_lgf_m[:: max(1, len(trajectory.p_lgf_m) // 20000)]
    nearest = {r.name: float(np.min(np.linalg.norm(p - r.center_m, axis=1))) for r in rects}
    reach_m = SCANNER_RANGE_M[1]
    if min(nearest.values()) <= reach_m:
        return
    near = ", ".join(f"{name} {d / 1000:,.1f} km" for name, d in nearest.items())
    raise CalibrationError(
        f"the trajectory never comes within the scanner's range ({reach_m:g} m) of a target: its "
        f"closest approach is {near}; check site.yaml's reference point and the targets' centres against "
        f"the trajectory's datum (the same survey, the same coordinates?)"
    )


def drop_uncovered(
    points: ScanPoints, trajectory: Trajectory, time_offset_s: float = 0.0
) -> tuple[ScanPoints, np.ndarray, list[str]]:
    """The points the trajectory covers, their indices in ``points`` and one warning per pass
    that lost points (``--skip-uncovered``)."""
    bad = trajectory.uncovered(points.t_gps_s + time_offset_s)
    keep = np.flatnonzero(~bad)
    warnings = []
    for p in np.unique(points.pass_id[bad]):
        m = points.pass_id == p
        n, total = int(np.sum(bad & m)), int(np.sum(m))
        warnings.append(
            f"pass {int(p)}: dropped {n:,} of {total:,} points outside the trajectory's coverage "
            f"({trajectory.t_gps_s[0]:.3f}…{trajectory.t_gps_s[-1]:.3f} s, gaps > "
            f"{trajectory.max_gap_s:g} s) (--skip-uncovered)"
        )
    return points.select(keep), keep, warnings


def check_input(site: Site, points: ScanPoints, poses: Poses | None) -> None:
    if not site.targets:
        raise CalibrationError(
            "site.yaml configures no targets: list the planar targets "
            "(name, centre, size, inclination, facing) under 'targets'"
        )
    if len(points) == 0:
        raise CalibrationError("the bundle holds no points")
    if poses is not None and poses.p_lgf_m.shape != (len(points), 3):
        raise CalibrationError(f"per-point poses for {poses.p_lgf_m.shape[0]} points, expected {len(points)}")
