"""Live target hits (docs/architecture.md §8), pure and vectorized over points: which returns of a batch
of profiles lie on the targets (:func:`target_hits`: gate returns by range and scan angle around
each target first, then georeference only those)."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from acquire.guidance.lines import GuidanceSettings
from calib.core.georef import Mount, georeference
from calib.core.trajectory import Trajectory
from calib.sim.scene import Scene

_DEFAULT_SETTINGS = GuidanceSettings()  # (immutable: one instance shared by the calls)


@dataclass(frozen=True)
class TargetHits:
    """Returns found on the targets, and how many points the gate let through."""

    t_gps_s: np.ndarray
    range_m: np.ndarray
    scan_angle_rad: np.ndarray
    target_index: np.ndarray  # into the scene's rectangles
    n_points: int  # returns looked at
    n_gated: int  # returns georeferenced (inside some target's range/angle gate)
    n_uncovered: int = 0  # gated returns the trajectory could not place

    def counts(self, n_targets: int) -> np.ndarray:
        return np.bincount(self.target_index, minlength=n_targets)

    @staticmethod
    def empty(n_points: int = 0) -> TargetHits:
        e = np.empty(0)
        return TargetHits(e, e, e, np.empty(0, np.int64), n_points, 0)


def target_hits(
    t_gps_s,
    range_m,
    scan_angle_rad,
    profile_of_point,
    t_profile_gps_s,
    traj: Trajectory,
    mount: Mount,
    scene: Scene,
    *,
    settings: GuidanceSettings = _DEFAULT_SETTINGS,
    intensity=None,
) -> TargetHits:
    """Which returns of a batch of profiles lie on the targets (the scene's rectangles).

    ``profile_of_point`` (n,) indexes ``t_profile_gps_s`` (P,), each profile's mid time. Per
    profile the scan plane is placed with the pose at that time, and each target gives a
    sector of beam angles (:meth:`calib.sim.scene.Scene.scan_sectors`, the target grown by
    ``gate_grow_m``, widened by ``gate_pad_rad``) and a range band (distance to its centre ±
    half its diagonal ± the growth). Only the returns inside some gate are georeferenced (with
    their own time's pose); a hit lies within ``hit_plane_tolerance_m`` of the target's plane
    and inside the rectangle grown by ``hit_edge_margin_m``. NaN ranges (no return) never pass.
    """
    s = settings
    t = np.asarray(t_gps_s, float)
    rho = np.asarray(range_m, float)
    alpha = np.asarray(scan_angle_rad, float)
    pi = np.asarray(profile_of_point, np.int64)
    n = t.size
    if n == 0 or len(scene) == 0:
        return TargetHits.empty(n)
    tp = np.asarray(t_profile_gps_s, float)
    poses = traj.interpolate(tp + mount.time_offset_s)
    M = poses.r_b_n @ mount.r_s_b
    origin = poses.p_lgf_m + poses.r_b_n @ mount.lever_arm_m
    sec = scene.scan_sectors(origin, M[:, :, 0], M[:, :, 1], M[:, :, 2], s.gate_grow_m)
    centers = np.array([r.center_m for r in scene.rectangles])
    half_diag = np.array([0.5 * math.hypot(r.width_m, r.height_m) for r in scene.rectangles])
    dist = np.linalg.norm(centers[None, :, :] - origin[:, None, :], axis=2)  # (P, R)
    # returns only (most of a profile over water has none), then the gates on those
    ret = np.flatnonzero(~np.isnan(rho))
    rho_r = rho[ret] + mount.range_offset_m
    keep = rho_r > 0
    if s.min_intensity is not None and intensity is not None:
        keep &= np.asarray(intensity)[ret] >= s.min_intensity
    if not keep.all():
        ret, rho_r = ret[keep], rho_r[keep]
    beam = alpha[ret] + (mount.scan_angle_offset_rad + s.gate_pad_rad)
    pr = pi[ret]
    two_pi = 2.0 * math.pi
    gated = np.zeros(ret.size, bool)
    for r in range(len(scene)):
        if not sec.hit[:, r].any():
            continue
        ok = sec.hit[:, r].take(pr)
        ok &= np.mod(beam - sec.start_rad[:, r].take(pr), two_pi) <= (
            sec.width_rad[:, r] + 2 * s.gate_pad_rad
        ).take(pr)
        ok &= np.abs(rho_r - dist[:, r].take(pr)) <= half_diag[r] + s.gate_grow_m
        gated |= ok
    idx = ret[gated]
    if idx.size == 0:
        return TargetHits.empty(n)
    uncovered = traj.uncovered(t[idx] + mount.time_offset_s)
    n_uncovered = int(uncovered.sum())
    idx = idx[~uncovered]
    if idx.size == 0:
        return replace(TargetHits.empty(n), n_gated=int(gated.sum()), n_uncovered=n_uncovered)
    p = georeference(t[idx], rho[idx], alpha[idx], traj, mount)
    best = np.full(idx.size, np.inf)
    which = np.full(idx.size, -1, np.int64)
    for r, rect in enumerate(scene.rectangles):
        dd = np.abs(rect.signed_distance(p))
        ok = (dd <= s.hit_plane_tolerance_m) & rect.contains(p, s.hit_edge_margin_m) & (dd < best)
        best[ok] = dd[ok]
        which[ok] = r
    on = which >= 0
    k = idx[on]
    return TargetHits(t[k], rho[k], alpha[k], which[on], n, int(gated.sum()), n_uncovered)
