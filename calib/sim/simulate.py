"""The MLS simulator (the thesis's simulator, Chapter 3, generalised): a scenario and a seed in,
a calibration bundle's content and its truth out.

    scenario ──► site (a-priori mount), scene of rectangles, pass plan
             ──► vessel motion along the plan ──► true trajectory
             ──► profiles at the profiler's rates, exact ray casting with the TRUE mount
                 (against the walls' waviness and roughness where the scenario gives them)
             ──► observations: (time, range, scan angle) as the scanner reports them,
                 the observed trajectory (POS errors) with its sigmas, and the truth

The injected systematic errors are the truth of the geometry: the beam of a return leaves the
scanner along the true mount (a-priori mount with the true boresight and the lever-arm error)
at the true time, and the reported observations follow the :class:`calib.core.georef.Mount` sign
conventions, so that georeferencing them with the true mount and the true trajectory puts every
noise-free return exactly on the surface it hit (:meth:`calib.sim.scene.Scene.distance_m` = 0:
on its rectangle, or on the displaced surface of a wavy or rough one):

    ρ_reported = ρ_true − δρ,    α_beam = α_reported + δα,    pose sampled at t_reported + Δt.

The rays' origins and directions are computed by :func:`calib.core.georef.georeference` itself (at
range 0 and 1), so simulator and georeferencing share one model of the trajectory's
interpolation. Per profile batch the scene first gives the sector of scan angles each rectangle
can occupy (:meth:`calib.sim.scene.Scene.scan_sectors`); only those rays are cast exactly.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from calib.core import frames
from calib.core.errors import CalibError
from calib.core.georef import Mount, georeference
from calib.core.trajectory import Poses, Trajectory
from calib.io.bundle import ScanPoints, write_bundle
from calib.io.site import Site
from calib.sim.motion import sail
from calib.sim.scenario import ScannerModel, Scenario
from calib.sim.scenariofile import load_scenario
from calib.sim.scene import BACKGROUND_KINDS, Scene
from calib.survey.passplan import PassPlan, plan_passes

#: Ray slots (profiles × points per 360°) handled per batch.
_BATCH_SLOTS = 1 << 20
#: Reported POS sigmas are floored here (a channel without noise still gets a usable weight).
_SIGMA_FLOOR = np.array([1e-6, 1e-6, 1e-6, 1e-8, 1e-8, 1e-8])


class SimulationError(CalibError, ValueError):
    """The simulation cannot produce what was asked (the message says why)."""


@dataclass(frozen=True)
class SimResult:
    """Everything one simulation produced; ``points`` and the observed trajectory are what a
    real acquisition would give, the rest is truth."""

    scenario: Scenario
    seed: int
    site: Site  # a-priori mount, LGF reference, approximate target centres
    scene: Scene  # the true surfaces in the LGF (rectangles = mean planes, and their shapes)
    plan: PassPlan
    mount_true: Mount
    trajectory_true: Trajectory
    trajectory_observed: Trajectory  # with POS errors and sigmas
    points: ScanPoints
    surface_index: np.ndarray  # (n,) index into scene.rectangles of the surface each return hit
    target_index: np.ndarray  # (n,) index into site.targets; −1 for any other surface
    p_true_lgf_m: np.ndarray  # (n, 3) the true hit points
    pose_errors: np.ndarray | None  # (n, 6) per-point POS errors (``per_point`` model only)
    truth: dict  # JSON-ready, as written to truth.json

    def observed_poses(self) -> Poses:
        """The POS observation of every point as the calibration sees it: the observed
        trajectory at the point's reported time, plus the per-point errors of the
        ``per_point`` model (with the sigmas the trajectory reports)."""
        poses = self.trajectory_observed.interpolate(self.points.t_gps_s)
        e = self.pose_errors
        if e is None:
            return poses
        rpy = poses.rpy_rad + e[:, 3:]
        rpy[:, 2] = frames.wrap_2pi(rpy[:, 2])
        return Poses(
            poses.p_lgf_m + e[:, :3],
            rpy,
            frames.attitude_matrix(*rpy.T),
            poses.sigma_p_m,
            poses.sigma_rpy_rad,
        )

    def point_counts(self) -> dict[int, dict[str, int]]:
        """Returns per pass and per named surface (targets, validation planes); every other
        surface is counted as ``background``."""
        names = [
            "background" if k in BACKGROUND_KINDS else r.name
            for r, k in zip(self.scene.rectangles, self.scene.kinds)
        ]
        keys = list(dict.fromkeys(names + ["background"]))
        out = {}
        for p in self.plan.passes:
            sel = self.surface_index[self.points.pass_id == p.id]
            counts = np.bincount(sel, minlength=len(names))
            row = dict.fromkeys(keys, 0)
            for name, c in zip(names, counts):
                row[name] += int(c)
            out[p.id] = row
        return out

    def write(self, path: str | Path, compress_points: bool = False) -> Path:
        """Write the calibration bundle (docs/architecture.md §4) with ``truth.json``."""
        if self.pose_errors is not None:
            raise SimulationError(
                "POS noise model 'per_point' gives every point its own pose error, which a "
                "trajectory file cannot carry; it exists only in memory "
                "(SimResult.observed_poses()). Use 'white' or 'gauss_markov' for a bundle."
            )
        return write_bundle(
            path,
            self.site,
            self.trajectory_observed,
            self.points,
            self.truth,
            compress_points=compress_points,
        )


# -- the scanner ----------------------------------------------------------------------------


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


def _covering(traj: Trajectory, t0: float, t1: float) -> Trajectory:
    """The part of ``traj`` whose intervals cover [t0, t1]."""
    tt = traj.t_gps_s
    i0 = max(int(np.searchsorted(tt, t0, "right")) - 1, 0)
    i1 = min(int(np.searchsorted(tt, t1, "left")) + 1, tt.size)
    return traj.select(slice(i0, max(i1, i0 + 2)))


def _motion_bounds(traj: Trajectory) -> tuple[float, float]:
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
    parts = list(_scan_batches(scanner, scene, traj, mount, t_start_s, t_end_s))
    if not parts:
        e = np.empty(0)
        return ScanReturns(e, e, e, np.empty(0, np.int64), e, np.empty((0, 3)))
    return ScanReturns.concatenate(parts)


def _scan_batches(scanner, scene, traj, mount, t_start_s, t_end_s):
    """:func:`scan`, one batch of profiles at a time."""
    rate = scanner.effective_profile_rate_hz
    K = scanner.effective_points_per_360
    d_alpha = 2.0 * np.pi / K
    dt = 1.0 / (rate * K)
    window = scanner.window_mask()
    n_prof = int(np.floor((t_end_s - t_start_s) * rate))
    geom = replace(mount, range_offset_m=0.0)
    v_max, w_max = _motion_bounds(traj)
    half = 0.5 / rate  # half a profile's duration
    reach = min(scanner.max_range_m, 200.0) + float(np.linalg.norm(mount.lever_arm_m))
    grow_m = 0.02 + 2.0 * half * (v_max + w_max * reach)
    pad_rad = 2.0 * w_max * half + 2.0 * d_alpha
    batch = max(1, _BATCH_SLOTS // K)
    for p0 in range(0, n_prof, batch):
        prof = np.arange(p0, min(p0 + batch, n_prof))
        B = prof.size
        # sectors from the pose at each profile's middle
        poses = traj.interpolate(t_start_s + (prof * K + K / 2) * dt + mount.time_offset_s)
        M = poses.r_b_n @ mount.r_s_b
        origin = poses.p_lgf_m + poses.r_b_n @ mount.lever_arm_m
        sec = scene.scan_sectors(origin, M[:, :, 0], M[:, :, 1], M[:, :, 2], grow_m)
        b_idx, r_idx = np.nonzero(sec.hit)
        if b_idx.size == 0:
            continue
        # each sector as measured-angle index ranges [lo, end) of its profile's row; a range
        # that passes K wraps to [0, end − K)
        start = sec.start_rad[b_idx, r_idx] - mount.scan_angle_offset_rad - pad_rad
        lo = np.mod(np.floor(start / d_alpha).astype(np.int64), K)
        end = lo + np.minimum(
            np.ceil((sec.width_rad[b_idx, r_idx] + 2 * pad_rad) / d_alpha).astype(np.int64) + 2, K
        )
        wrap = end > K
        row = b_idx * K
        keys_lo = np.concatenate([row + lo, row[wrap]])
        keys_hi = np.concatenate([row + np.minimum(end, K), row[wrap] + end[wrap] - K])
        owner = np.concatenate([r_idx, r_idx[wrap]])
        diff = np.zeros(B * K + 1, np.int16)
        np.add.at(diff, keys_lo, 1)
        np.add.at(diff, keys_hi, -1)
        cover = np.cumsum(diff[:-1], dtype=np.int16).reshape(B, K) > 0
        cand = np.flatnonzero(cover & window)
        if cand.size == 0:
            continue
        t_rep = t_start_s + (p0 * K + cand) * dt
        alpha = (cand % K) * d_alpha
        sub = _covering(traj, t_rep[0] + mount.time_offset_s, t_rep[-1] + mount.time_offset_s)
        o = georeference(t_rep, np.zeros(cand.size), alpha, sub, geom)
        d = georeference(t_rep, np.ones(cand.size), alpha, sub, geom) - o
        comps = (o[:, 0], o[:, 1], o[:, 2], d[:, 0], d[:, 1], d[:, 2])
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
        keep = np.flatnonzero(surf >= 0)
        if keep.size == 0:
            continue
        rho, s = best[keep], surf[keep]
        dk = d[keep]
        x = o[keep] + rho[:, None] * dk
        yield ScanReturns(
            t_rep[keep], alpha[keep], rho, s, np.abs(np.einsum("ij,ij->i", dk, scene.normals(s, x))), x
        )


# -- orchestration --------------------------------------------------------------------------


def _deg3(v_rad) -> dict:
    r, p, y = (float(x) for x in np.degrees(v_rad))
    return {"roll": r, "pitch": p, "yaw": y}


def _plane(rect, kind: str, shape) -> dict:
    out = {
        "name": rect.name,
        "kind": kind,
        "normal": [float(x) for x in rect.normal],
        "d": rect.d,
        "center_lgf_m": [float(x) for x in rect.center_m],
        "width_m": rect.width_m,
        "height_m": rect.height_m,
        "inclination_deg": float(np.degrees(rect.inclination_rad)),
        "reflectivity": rect.reflectivity,
    }
    if shape is not None and not shape.flat:  # the plane is the surface's least-squares plane
        out["shape"] = shape.to_dict()
    return out


def _truth(
    sc: Scenario,
    seed: int,
    overrides: list[str],
    scene: Scene,
    plan: PassPlan,
    mount: Mount,
    run,
    counts: dict[int, dict[str, int]],
) -> dict:
    t = sc.truth

    def planes(*kinds: str) -> list[dict]:
        return [
            _plane(r, k, sh) for r, k, sh in zip(scene.rectangles, scene.kinds, scene.shapes) if k in kinds
        ]

    return {
        "format": "marine-mls simulation truth v1",
        "scenario": sc.name,
        "seed": int(seed),
        "overrides": list(overrides),
        "convention": "canonical (docs/architecture.md §3): R_bs = Rz(yaw)·Ry(pitch)·Rx(roll) about the body "
        "FRD axes; thesis pitch = −canonical pitch",
        "boresight_deg": _deg3(mount.boresight_rad),
        "boresight_thesis_deg": _deg3(frames.boresight_to_thesis(*mount.boresight_rad)),
        "boresight_apriori_deg": _deg3(sc.mount.boresight_rad),
        "boresight_error_deg": _deg3(mount.boresight_rad - sc.mount.boresight_rad),
        "lever_arm_m": [float(x) for x in mount.lever_arm_m],
        "lever_arm_apriori_m": [float(x) for x in sc.mount.lever_arm_m],
        "lever_arm_error_m": [float(x) for x in t.lever_arm_error_m],
        "nominal_deg": [float(x) for x in np.degrees(mount.nominal_rad)],
        "range_offset_m": float(t.range_offset_m),
        "scan_angle_offset_deg": float(np.degrees(t.scan_angle_offset_rad)),
        "time_offset_s": float(t.time_offset_s),
        "reference": sc.reference.as_dict(),
        "targets": planes("target"),
        "validation_planes": planes("validation"),
        "background": planes(*BACKGROUND_KINDS),
        "passes": [
            {
                "id": p.id,
                "order": p.order,
                "relative_heading_deg": float(np.degrees(p.relative_heading_rad)),
                "heading_deg": float(np.degrees(p.heading_rad)),
                "start_lgf_m": [float(x) for x in p.start_lgf_m],
                "end_lgf_m": [float(x) for x in p.end_lgf_m],
                "line_gps_s": [float(x) for x in run.line_times[p.id]],
                "capture_gps_s": [float(x) for x in run.capture_times[p.id]],
                "points": counts[p.id],
            }
            for p in plan.passes
        ],
        "wave_phases_deg": {k: float(np.degrees(v)) for k, v in run.phases_rad.items()},
        "settings": sc.to_dict(),
    }


def simulate(
    scenario: Scenario | str | Path,
    seed: int = 0,
    *,
    overrides: Sequence[str] | Mapping[str, Any] = (),
    progress: Callable[[int, int], None] | None = None,
) -> SimResult:
    """Simulate a scenario (a :class:`Scenario`, or a shipped name / YAML path loaded with
    ``overrides``). ``progress(done, total)`` is called after each pass."""
    if not isinstance(scenario, Scenario):
        scenario = load_scenario(scenario, overrides)
    elif overrides:
        raise SimulationError("overrides apply when the scenario is loaded by name or path")
    applied = (
        [f"{k}={v!r}" for k, v in overrides.items()]
        if isinstance(overrides, Mapping)
        else [str(o) for o in overrides]
    )
    sc = scenario
    rng_motion, rng_pos, rng_scan, rng_point = (
        np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(4)
    )
    site = sc.site()
    scene = sc.scene()
    rects = lambda kind: [scene.rectangles[i] for i in scene.indices(kind)]  # noqa: E731
    plan = plan_passes(
        rects("target"),
        sc.wall_azimuth_rad,
        sc.standoff_m,
        sc.passes,
        track_down_m=-float(sc.mount.lever_arm_m[2]),  # the scanner at up = 0 on a level vessel
        safe_wall_distance_m=sc.safe_wall_distance_m,
        capture_margin_m=sc.capture_margin_m,
        also_capture=rects("validation") if sc.capture_validation_planes else (),
    )
    run = sail(plan, sc.motion, sc.start_gps_s, sc.reference, rng_motion)
    traj = run.trajectory
    mount = sc.truth.true_mount(sc.mount)

    parts, pass_ids = [], []
    guard = abs(mount.time_offset_s) + 1e-3
    for i, p in enumerate(plan.passes):
        t0, t1 = run.capture_times[p.id]
        l0, l1 = run.line_times[p.id]
        for part in _scan_batches(sc.scanner, scene, traj, mount, max(t0, l0 + guard), min(t1, l1 - guard)):
            parts.append(part)
            pass_ids.append(np.full(part.t_gps_s.size, p.id, np.int64))
        if progress is not None:
            progress(i + 1, len(plan.passes))
    if not parts:
        raise SimulationError(
            f"scenario {sc.name!r}: no return in any pass (check the scene, "
            f"the angular windows and the range limits)"
        )
    ret = ScanReturns.concatenate(parts)
    n = ret.t_gps_s.size

    d_range, d_angle = sc.scanner_noise.draw(ret.range_true_m, ret.cos_incidence, rng_scan)
    measured_m = ret.range_true_m - mount.range_offset_m + d_range
    # the scanner records what it *measures* inside its window: a return that noise or a range
    # offset puts beyond the window's edge is not recorded (the bundle reader refuses such ranges)
    rec = np.flatnonzero((measured_m >= sc.scanner.min_range_m) & (measured_m <= sc.scanner.max_range_m))
    points = ScanPoints(
        pass_id=np.concatenate(pass_ids)[rec],
        t_gps_s=ret.t_gps_s[rec],
        range_m=measured_m[rec],
        scan_angle_rad=frames.wrap_2pi(ret.alpha_rad + d_angle)[rec],
        intensity=(scene.reflectivity[ret.surface] * ret.cos_incidence)[rec],
    )

    pos = sc.pos_noise
    e = pos.epoch_errors(traj.t_gps_s, rng_pos)
    rpy = traj.rpy_rad + e[:, 3:]
    rpy[:, 2] = frames.wrap_2pi(rpy[:, 2])
    sig = None if pos.model == "none" else np.maximum(pos.sigma, _SIGMA_FLOOR)
    m = traj.t_gps_s.size
    observed = Trajectory(
        traj.t_gps_s,
        traj.p_lgf_m + e[:, :3],
        rpy,
        traj.frame,
        sigma_p_m=None if sig is None else np.tile(sig[:3], (m, 1)),
        sigma_rpy_rad=None if sig is None else np.tile(sig[3:], (m, 1)),
        max_gap_s=traj.max_gap_s,
        name="observed trajectory",
    )

    point_errors = pos.point_errors(n, rng_point)  # drawn for every return: same seed, same draws
    target_of_surface = np.full(len(scene), -1, np.int64)
    target_of_surface[scene.indices("target")] = np.arange(len(scene.indices("target")))
    result = SimResult(
        scenario=sc,
        seed=int(seed),
        site=site,
        scene=scene,
        plan=plan,
        mount_true=mount,
        trajectory_true=traj,
        trajectory_observed=observed,
        points=points,
        surface_index=ret.surface[rec],
        target_index=target_of_surface[ret.surface[rec]],
        p_true_lgf_m=ret.p_lgf_m[rec],
        pose_errors=None if point_errors is None else point_errors[rec],
        truth={},
    )
    truth = _truth(sc, seed, applied, scene, plan, mount, run, result.point_counts())
    return replace(result, truth=truth)
