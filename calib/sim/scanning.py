"""The profiler's exact returns: profiles fired at the scanner's rates from a vessel on a
trajectory, each ray cast exactly against the scene with the TRUE mount.

The rays' origins and directions are computed by :func:`calib.core.georef.georeference` itself (at
range 0 and 1), so simulator and georeferencing share one model of the trajectory's
interpolation. Per profile batch the scene first gives the sector of scan angles each surface
(rectangle or cylinder) can occupy (:meth:`calib.sim.scene.Scene.scan_sectors`); only those rays
are cast exactly. The reported observations follow the :class:`calib.core.georef.Mount` sign
conventions (see :mod:`calib.sim.simulate`).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, replace

import numpy as np

from calib.core.georef import Mount, georeference
from calib.core.trajectory import Trajectory
from calib.sim.scenario import ScannerModel
from calib.sim.scene import Scene

#: Ray slots (profiles × points per 360°) handled per batch.
_BATCH_SLOTS = 1 << 20


@dataclass(frozen=True)
class ScanReturns:
    """Noise-free returns of the profiler (what :func:`scan` gives)."""

    t_gps_s: np.ndarray  # reported time
    alpha_rad: np.ndarray  # encoder angle (reported, before noise)
    range_true_m: np.ndarray  # distance travelled by the beam
    surface: np.ndarray
    cos_incidence: np.ndarray
    p_lgf_m: np.ndarray  # (n, 3)

    @staticmethod
    def concatenate(parts: list[ScanReturns]) -> ScanReturns:
        return ScanReturns(
            *(
                np.concatenate([getattr(p, f) for p in parts])
                for f in ("t_gps_s", "alpha_rad", "range_true_m", "surface", "cos_incidence", "p_lgf_m")
            )
        )


def _expand_ranges(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Concatenation of ``arange(lo[i], hi[i])`` for all i."""
    n = np.maximum(hi - lo, 0)
    total = int(n.sum())
    if total == 0:
        return np.empty(0, np.int64)
    starts = np.cumsum(n) - n
    return np.arange(total) + np.repeat(lo - starts, n)


def covering(traj: Trajectory, t0: float, t1: float) -> Trajectory:
    """The part of ``traj`` whose intervals cover [t0, t1]."""
    tt = traj.t_gps_s
    i0 = max(int(np.searchsorted(tt, t0, "right")) - 1, 0)
    i1 = min(int(np.searchsorted(tt, t1, "left")) + 1, tt.size)
    return traj.select(slice(i0, max(i1, i0 + 2)))


def motion_bounds(traj: Trajectory) -> tuple[float, float]:
    """Largest speed (m/s) and rotation rate (rad/s) between epochs."""
    dt = np.diff(traj.t_gps_s)
    v = np.linalg.norm(np.diff(traj.p_lgf_m, axis=0), axis=1) / dt
    w = np.linalg.norm(traj.interval_rotvec, axis=1) / dt
    return float(v.max()), float(w.max())


def scan(
    scanner: ScannerModel, scene: Scene, traj: Trajectory, mount: Mount, t_start_s: float, t_end_s: float
) -> ScanReturns:
    """Exact returns of the profiles fired in [t_start_s, t_end_s) (reported time) from the
    vessel on ``traj`` with the scanner mounted as ``mount`` (the truth)."""
    parts = list(scan_batches(scanner, scene, traj, mount, t_start_s, t_end_s))
    if not parts:
        e = np.empty(0)
        return ScanReturns(e, e, e, np.empty(0, np.int64), e, np.empty((0, 3)))
    return ScanReturns.concatenate(parts)


@dataclass(frozen=True, kw_only=True)
class _ProfileGrid:
    """The profiler's firing grid and how much a scene sector is widened for the motion within
    a profile."""

    rate_hz: float  # profiles per second
    K: int  # points per 360°
    d_alpha_rad: float  # between two points of a profile
    dt_s: float  # between two points
    window: np.ndarray  # (K,) the angles the profiler measures
    grow_m: float  # sectors grown by this (the motion within half a profile)
    pad_rad: float  # … and widened by this
    batch: int  # profiles per batch


def _profile_grid(scanner: ScannerModel, traj: Trajectory, mount: Mount) -> _ProfileGrid:
    rate = scanner.effective_profile_rate_hz
    K = scanner.effective_points_per_360
    d_alpha = 2.0 * np.pi / K
    v_max, w_max = motion_bounds(traj)
    half = 0.5 / rate  # half a profile's duration
    reach = min(scanner.max_range_m, 200.0) + float(np.linalg.norm(mount.lever_arm_m))
    return _ProfileGrid(
        rate_hz=rate,
        K=K,
        d_alpha_rad=d_alpha,
        dt_s=1.0 / (rate * K),
        window=scanner.window_mask(),
        grow_m=0.02 + 2.0 * half * (v_max + w_max * reach),
        pad_rad=2.0 * w_max * half + 2.0 * d_alpha,
        batch=max(1, _BATCH_SLOTS // K),
    )


def _sector_slots(sec, b_idx, r_idx, n_profiles: int, g: _ProfileGrid, mount: Mount):
    """Each hit sector as measured-angle slot ranges [lo, end) of its profile's row (a range
    that passes K wraps to [0, end − K)): the ranges' ends and owners (surfaces), and the
    slots some sector covers within the window."""
    K = g.K
    start = sec.start_rad[b_idx, r_idx] - mount.scan_angle_offset_rad - g.pad_rad
    lo = np.mod(np.floor(start / g.d_alpha_rad).astype(np.int64), K)
    end = lo + np.minimum(
        np.ceil((sec.width_rad[b_idx, r_idx] + 2 * g.pad_rad) / g.d_alpha_rad).astype(np.int64) + 2, K
    )
    wrap = end > K
    row = b_idx * K
    keys_lo = np.concatenate([row + lo, row[wrap]])
    keys_hi = np.concatenate([row + np.minimum(end, K), row[wrap] + end[wrap] - K])
    owner = np.concatenate([r_idx, r_idx[wrap]])
    diff = np.zeros(n_profiles * K + 1, np.int16)
    np.add.at(diff, keys_lo, 1)
    np.add.at(diff, keys_hi, -1)
    cover = np.cumsum(diff[:-1], dtype=np.int16).reshape(n_profiles, K) > 0
    return keys_lo, keys_hi, owner, np.flatnonzero(cover & g.window)


def _nearest_hits(scanner: ScannerModel, scene: Scene, cand, keys_lo, keys_hi, owner, comps):
    """For each candidate slot the nearest surface hit within the range limits among the
    sectors covering it: range (inf) and surface (−1: none)."""
    best = np.full(cand.size, np.inf)
    surf = np.full(cand.size, -1, np.int64)
    pos_lo, pos_hi = np.searchsorted(cand, keys_lo), np.searchsorted(cand, keys_hi)
    for j in np.unique(owner):
        sel = owner == j
        idx = _expand_ranges(pos_lo[sel], pos_hi[sel])
        if idx.size == 0:
            continue
        rho, inside = scene.hit_range(j, *(c[idx] for c in comps))
        ok = inside & (rho > scanner.min_range_m) & (rho <= scanner.max_range_m) & (rho < best[idx])
        best[idx[ok]] = rho[ok]
        surf[idx[ok]] = j
    return best, surf


def scan_batches(
    scanner: ScannerModel, scene: Scene, traj: Trajectory, mount: Mount, t_start_s: float, t_end_s: float
) -> Iterator[ScanReturns]:
    """:func:`scan`, one batch of profiles at a time (memory bounded by the batch). Profile ``k``
    fires at ``t_start_s + k / effective_profile_rate_hz``, ``k < floor((t_end_s − t_start_s) ·
    rate)``: scanning [t0, t1) and then [t1, t2) with t1 − t0 a whole number of profile periods
    continues one profile grid."""
    g = _profile_grid(scanner, traj, mount)
    K, dt = g.K, g.dt_s
    n_prof = int(np.floor((t_end_s - t_start_s) * g.rate_hz))
    geom = replace(mount, range_offset_m=0.0)
    for p0 in range(0, n_prof, g.batch):
        prof = np.arange(p0, min(p0 + g.batch, n_prof))
        # sectors from the pose at each profile's middle
        poses = traj.interpolate(t_start_s + (prof * K + K / 2) * dt + mount.time_offset_s)
        M = poses.r_b_n @ mount.r_s_b
        origin = poses.p_lgf_m + poses.r_b_n @ mount.lever_arm_m
        sec = scene.scan_sectors(origin, M[:, :, 0], M[:, :, 1], M[:, :, 2], g.grow_m)
        b_idx, r_idx = np.nonzero(sec.hit)
        if b_idx.size == 0:
            continue
        keys_lo, keys_hi, owner, cand = _sector_slots(sec, b_idx, r_idx, prof.size, g, mount)
        if cand.size == 0:
            continue
        t_rep = t_start_s + (p0 * K + cand) * dt
        alpha = (cand % K) * g.d_alpha_rad
        sub = covering(traj, t_rep[0] + mount.time_offset_s, t_rep[-1] + mount.time_offset_s)
        o = georeference(t_rep, np.zeros(cand.size), alpha, sub, geom)
        d = georeference(t_rep, np.ones(cand.size), alpha, sub, geom) - o
        comps = (o[:, 0], o[:, 1], o[:, 2], d[:, 0], d[:, 1], d[:, 2])
        best, surf = _nearest_hits(scanner, scene, cand, keys_lo, keys_hi, owner, comps)
        keep = np.flatnonzero(surf >= 0)
        if keep.size == 0:
            continue
        rho, s = best[keep], surf[keep]
        dk = d[keep]
        x = o[keep] + rho[:, None] * dk
        yield ScanReturns(
            t_rep[keep], alpha[keep], rho, s, np.abs(np.einsum("ij,ij->i", dk, scene.normals(s, x))), x
        )
