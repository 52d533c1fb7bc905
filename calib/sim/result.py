"""What a simulation produced (:class:`SimResult`) and how noise-free returns become it
(:func:`observe`): the scanner's noise and recording window, the observed trajectory with its POS
errors and sigmas, and the truth (``truth.json``). Shared by every kind of simulation (the
calibration passes of :mod:`calib.sim.simulate`, the production survey of
:mod:`calib.sim.production`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from calib.core import frames
from calib.core.errors import CalibError
from calib.core.georef import Mount
from calib.core.trajectory import Poses, Trajectory
from calib.io.bundle import ScanPoints, write_bundle
from calib.io.site import Site
from calib.sim.motion import VesselRun
from calib.sim.scanning import ScanReturns
from calib.sim.scenario import Scenario
from calib.sim.scene import BACKGROUND_KINDS, Scene
from calib.survey.passplan import PassPlan

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
    scene: Scene  # the true surfaces in the LGF (rectangles = mean planes, their shapes; cylinders)
    plan: PassPlan
    mount_true: Mount
    trajectory_true: Trajectory
    trajectory_observed: Trajectory  # with POS errors and sigmas
    points: ScanPoints
    surface_index: np.ndarray  # (n,) scene index of the surface each return hit (rectangles, cylinders)
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
            "background" if k in BACKGROUND_KINDS else name
            for name, k in zip(self.scene.names, self.scene.kinds, strict=True)
        ]
        keys = list(dict.fromkeys(names + ["background"]))
        out = {}
        for p in self.plan.passes:
            sel = self.surface_index[self.points.pass_id == p.id]
            counts = np.bincount(sel, minlength=len(names))
            row = dict.fromkeys(keys, 0)
            for name, c in zip(names, counts, strict=False):
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


# -- truth ----------------------------------------------------------------------------------


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


def _cylinder(c, kind: str) -> dict:
    """A vertical cylinder as truth.json gives it (its axis at mid-height, LGF)."""
    return {
        "name": c.name,
        "kind": kind,
        "center_lgf_m": [float(x) for x in c.center_m],
        "radius_m": float(c.radius_m),
        "diameter_m": 2.0 * float(c.radius_m),
        "height_m": float(c.height_m),
        "reflectivity": float(c.reflectivity),
    }


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
            _plane(r, k, sh)
            for r, k, sh in zip(scene.rectangles, scene.kinds, scene.shapes, strict=False)
            if k in kinds
        ]

    out = {
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
    if scene.cylinders:  # piles, posts, dolphins (vertical; always background)
        kinds = [scene.kinds[j] for j in scene.cylinder_indices]
        out["cylinders"] = [_cylinder(c, k) for c, k in zip(scene.cylinders, kinds, strict=True)]
    return out


# -- observations -----------------------------------------------------------------------------


def observe(
    sc: Scenario,
    seed: int,
    overrides: list[str],
    scene: Scene,
    plan: PassPlan,
    run: VesselRun,
    mount: Mount,
    ret: ScanReturns,
    pass_id: np.ndarray,
    rngs: tuple[np.random.Generator, np.random.Generator, np.random.Generator],
) -> SimResult:
    """The simulation's result from the noise-free returns ``ret`` (with their pass ids) of the
    vessel run ``run``: scanner noise and the recording window, the observed trajectory and the
    truth (``mount``: the true mount it reports). ``rngs``: the POS, scanner and per-point
    generators, in that order."""
    rng_pos, rng_scan, rng_point = rngs
    traj = run.trajectory
    n = ret.t_gps_s.size

    d_range, d_angle = sc.scanner_noise.draw(ret.range_true_m, ret.cos_incidence, rng_scan)
    measured_m = ret.range_true_m - mount.range_offset_m + d_range
    # the scanner records what it *measures* inside its window: a return that noise or a range
    # offset puts beyond the window's edge is not recorded (the bundle reader refuses such ranges)
    rec = np.flatnonzero((measured_m >= sc.scanner.min_range_m) & (measured_m <= sc.scanner.max_range_m))
    points = ScanPoints(
        pass_id=pass_id[rec],
        t_gps_s=ret.t_gps_s[rec],
        range_m=measured_m[rec],
        scan_angle_rad=frames.wrap_2pi(ret.alpha_rad + d_angle)[rec],
        intensity=(
            scene.reflectivity[ret.surface]
            * (ret.cos_incidence if sc.scanner_noise.intensity_follows_incidence else 1.0)
        )[rec],
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
        site=sc.site(),
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
    truth = _truth(sc, seed, overrides, scene, plan, mount, run, result.point_counts())
    return replace(result, truth=truth)
