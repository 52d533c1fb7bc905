"""A simulation scenario: the site's surfaces, the injected (true) errors, the scanner, and the
motion and noise models, with what follows from them (the scene, the site config of the
simulated bundle, the resolved settings of truth.json). :mod:`calib.sim.scenariofile` reads one
from YAML.

Scene coordinates are given in the *site frame*: ``along_m`` along the wall direction
(``site.wall_azimuth_deg``), ``out_m`` from the wall face toward the water (the water lies to
the left of the wall direction, so pass 0° sees the wall to starboard) and ``up_m`` above the
scanner's mean height. The site frame's origin is the scenario's ``reference`` point, which is
also the origin of the LGF (NED) the simulation and the bundle use. A surface faces the water
unless ``facing_deg`` turns it (clockwise seen from above). A surface may have a shape
(waviness and roughness, :mod:`calib.sim.surfaceshape`); its rectangle is then its mean plane.
A :class:`Pile` (a pile, a post, a dolphin's pile) is a vertical cylinder standing on the
site-frame point (``along_m``, ``out_m``) from ``bottom_up_m`` to ``top_up_m``; the scene holds
it as a :class:`~calib.core.geometry.VerticalCylinder` after the rectangles.

A scenario with a :class:`ProductionSpec` is a *production survey* (:mod:`calib.sim.production`):
lines along the harbour front of :mod:`calib.sim.harbour` instead of calibration passes, with an
optional :class:`MountEvent` (the boresight changing during the survey).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from calib.core import frames
from calib.core.geometry import Rectangle, VerticalCylinder
from calib.core.georef import Mount
from calib.io.bundle import SCANNER_RANGE_M
from calib.io.site import PassSpec, Site, SitePile, Target
from calib.sim.cylinders import LeaningCylinder
from calib.sim.motion import MotionModel
from calib.sim.noise import PosNoise, ScannerNoise
from calib.sim.scene import BACKGROUND_KINDS, Scene
from calib.sim.surfaceshape import SurfaceShape
from calib.survey.passplan import PassPlan, plan_passes

# -- the scenario ---------------------------------------------------------------------------

#: The largest boresight change a mount event may inject (rad): a knocked scanner, not a new mount.
MAX_MOUNT_STEP_RAD = float(np.radians(5.0))


@dataclass(frozen=True)
class Surface:
    """A rectangle in site-frame coordinates (see the module docstring)."""

    name: str
    kind: str  # "target", "validation", "wall", "ground" or "other"
    along_m: float
    out_m: float
    up_m: float
    width_m: float
    height_m: float
    inclination_rad: float = float(np.pi / 2)
    facing_rad: float = 0.0  # relative to the water-facing direction
    reflectivity: float = 0.9
    shape: SurfaceShape | None = None  # waviness and roughness; None = flat


@dataclass(frozen=True, kw_only=True)
class Pile:
    """A vertical cylinder in site-frame coordinates (see the module docstring): its axis at
    (``along_m``, ``out_m``), from ``bottom_up_m`` to ``top_up_m``; always background."""

    name: str
    kind: str = "other"  # "wall", "ground" or "other"
    along_m: float
    out_m: float
    bottom_up_m: float
    top_up_m: float
    diameter_m: float
    reflectivity: float = 0.3
    #: the axis's lean from vertical toward along and toward out (deg): its top displaced by
    #: height × tan; the calibration models vertical cylinders (a misspecification to test)
    lean_deg: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self):
        if self.kind not in BACKGROUND_KINDS:
            raise ValueError(
                f"Pile {self.name!r}: kind {self.kind!r}, expected one of {', '.join(BACKGROUND_KINDS)}"
            )
        if not (np.isfinite(self.diameter_m) and self.diameter_m > 0):
            raise ValueError(f"Pile {self.name!r}: diameter_m must be > 0, got {self.diameter_m!r}")
        if not self.top_up_m > self.bottom_up_m:
            raise ValueError(
                f"Pile {self.name!r}: top_up_m ({self.top_up_m!r}) must lie above "
                f"bottom_up_m ({self.bottom_up_m!r})"
            )

    def to_dict(self) -> dict:
        return {
            "name": self.name,
            "kind": self.kind,
            "along_m": float(self.along_m),
            "out_m": float(self.out_m),
            "bottom_up_m": float(self.bottom_up_m),
            "top_up_m": float(self.top_up_m),
            "diameter_m": float(self.diameter_m),
            "reflectivity": float(self.reflectivity),
            **({"lean_deg": [float(x) for x in self.lean_deg]} if any(self.lean_deg) else {}),
        }


@dataclass(frozen=True)
class InjectedErrors:
    """The systematic errors of the simulated system (the truth the calibration must find)."""

    boresight_rad: np.ndarray = field(default_factory=lambda: np.zeros(3))  # true, canonical
    lever_arm_error_m: np.ndarray = field(default_factory=lambda: np.zeros(3))
    range_offset_m: float = 0.0
    scan_angle_offset_rad: float = 0.0
    time_offset_s: float = 0.0  # LiDAR–POS latency, Mount.time_offset_s

    def true_mount(self, apriori: Mount) -> Mount:
        return Mount(
            lever_arm_m=apriori.lever_arm_m + np.asarray(self.lever_arm_error_m, float),
            nominal_rad=apriori.nominal_rad,
            boresight_rad=np.asarray(self.boresight_rad, float),
            range_offset_m=float(self.range_offset_m),
            scan_angle_offset_rad=float(self.scan_angle_offset_rad),
            time_offset_s=float(self.time_offset_s),
        )


@dataclass(frozen=True)
class ScannerModel:
    """The profiler (Z+F Profiler 9012 defaults).

    ``point_rate_scale`` F scales the point rate; the profile rate and the points per 360° are
    each scaled by √F so that the point spacing stays as square as the real one.
    ``angular_windows_rad``: (start, end) pairs of measured scan angles that are recorded (an
    end below its start wraps through 0); empty = the full circle. ``min_range_m`` …
    ``max_range_m``: the measured ranges recorded, inside the physical window
    :data:`calib.io.bundle.SCANNER_RANGE_M` (0.3 … 119 m) that the bundle reader enforces.
    """

    profile_rate_hz: float = 200.0
    points_per_360: int = 5080
    max_range_m: float = SCANNER_RANGE_M[1]  # the recording window lies inside the physical one
    min_range_m: float = SCANNER_RANGE_M[0]
    angular_windows_rad: tuple[tuple[float, float], ...] = ()
    point_rate_scale: float = 1.0

    @property
    def effective_profile_rate_hz(self) -> float:
        return self.profile_rate_hz * np.sqrt(self.point_rate_scale)

    @property
    def effective_points_per_360(self) -> int:
        return max(int(round(self.points_per_360 * np.sqrt(self.point_rate_scale))), 4)

    def window_mask(self) -> np.ndarray:
        """(K,) whether each of the K measured angles of a profile is recorded."""
        K = self.effective_points_per_360
        if not self.angular_windows_rad:
            return np.ones(K, bool)
        a = np.arange(K) * (2.0 * np.pi / K)
        mask = np.zeros(K, bool)
        for lo, hi in self.angular_windows_rad:
            lo, hi = frames.wrap_2pi(lo), frames.wrap_2pi(hi)
            if hi == lo:  # a full turn
                mask[:] = True
            elif lo < hi:
                mask |= (a >= lo) & (a <= hi)
            else:
                mask |= (a >= lo) | (a <= hi)
        return mask

    def to_dict(self) -> dict:
        return {
            "profile_rate_hz": self.profile_rate_hz,
            "points_per_360": self.points_per_360,
            "max_range_m": self.max_range_m,
            "min_range_m": self.min_range_m,
            "angular_windows_deg": [
                [float(np.degrees(a)), float(np.degrees(b))] for a, b in self.angular_windows_rad
            ],
            "point_rate_scale": self.point_rate_scale,
            "effective_profile_rate_hz": float(self.effective_profile_rate_hz),
            "effective_points_per_360": self.effective_points_per_360,
        }


@dataclass(frozen=True)
class MountEvent:
    """A change of the scanner's boresight during a production survey (what the mount watch must
    detect): ``step_rad`` (canonical roll, pitch, yaw, added to the true boresight) at ``t_s``
    seconds after the survey's start, at once (``creep_s`` 0) or as a linear ramp over
    ``creep_s`` seconds (a mount slowly giving way)."""

    t_s: float
    step_rad: np.ndarray
    creep_s: float = 0.0

    def __post_init__(self):
        step = np.asarray(self.step_rad, float).reshape(-1)
        object.__setattr__(self, "step_rad", step)
        object.__setattr__(self, "t_s", float(self.t_s))
        object.__setattr__(self, "creep_s", float(self.creep_s))
        if step.shape != (3,) or not np.all(np.isfinite(step)):
            raise ValueError(f"MountEvent.step_rad must be 3 finite angles, got {self.step_rad!r}")
        if np.any(np.abs(step) > MAX_MOUNT_STEP_RAD):
            raise ValueError(f"MountEvent.step_rad must stay within ±5°, got {np.degrees(step)!r}°")
        if not (np.isfinite(self.t_s) and self.t_s >= 0):
            raise ValueError(f"MountEvent.t_s must be ≥ 0, got {self.t_s!r}")
        if not (np.isfinite(self.creep_s) and self.creep_s >= 0):
            raise ValueError(f"MountEvent.creep_s must be ≥ 0, got {self.creep_s!r}")

    def delta_rad(self, t_rel_s) -> np.ndarray:
        """(n, 3) boresight change at ``t_rel_s`` seconds after the survey's start: 0 before
        ``t_s``, the whole step from ``t_s + creep_s`` on, linear in between."""
        t = np.atleast_1d(np.asarray(t_rel_s, float))
        if self.creep_s > 0:
            f = np.clip((t - self.t_s) / self.creep_s, 0.0, 1.0)
        else:
            f = (t >= self.t_s).astype(float)
        return f[:, None] * self.step_rad

    def to_dict(self) -> dict:
        return {
            "t_s": self.t_s,
            "step_deg": [float(x) for x in np.degrees(self.step_rad)],
            "creep_s": self.creep_s,
        }


@dataclass(frozen=True)
class ProductionSpec:
    """A production survey of the harbour front (:mod:`calib.sim.production`): lines parallel to
    the quay wall at ``offsets_m`` from its face, each pair of lines there and back at one offset
    (consecutive lines always on opposite headings), ``line_length_m`` long, each at its own
    speed drawn uniformly in ``speeds_mps`` (min, max), joined by Dubins turns, until
    ``duration_s`` (the line under way is finished) or for ``n_lines`` lines when given. The
    profiler records its full circle at ``rate_scale`` of the full Z+F point rate. Harbour
    options: ``wavy_wall`` (the quay wall 4.5 cm RMS wavy over 1.5–6 m instead of 1 cm over
    3–8 m), ``moving_hulls`` (the moored hulls heave, sway and roll in the swell and drift
    between lines), ``water`` (the water surface, which returns every downward ray: about
    doubles the returns)."""

    duration_s: float = 3600.0
    offsets_m: tuple[float, ...] = (12.0, 20.0, 30.0)
    line_length_m: float = 350.0
    speeds_mps: tuple[float, float] = (1.5, 3.5)
    mount_event: MountEvent | None = None
    wavy_wall: bool = False
    moving_hulls: bool = False
    water: bool = False
    rate_scale: float = 0.02
    n_lines: int | None = None

    #: Lines keep this far from the wall face (the moored hull and the jetty reach 6.5 m) and
    #: no farther than the hull moored across the basin (66 m) minus a margin.
    MIN_OFFSET_M = 10.0
    MAX_OFFSET_M = 55.0

    def __post_init__(self):
        offsets = tuple(float(x) for x in np.atleast_1d(self.offsets_m))
        speeds = tuple(float(x) for x in np.atleast_1d(self.speeds_mps))
        object.__setattr__(self, "offsets_m", offsets)
        object.__setattr__(self, "speeds_mps", speeds)
        if not offsets or not all(self.MIN_OFFSET_M <= o <= self.MAX_OFFSET_M for o in offsets):
            raise ValueError(
                f"ProductionSpec.offsets_m must be one or more distances in "
                f"{self.MIN_OFFSET_M:g}…{self.MAX_OFFSET_M:g} m, got {self.offsets_m!r}"
            )
        if len(speeds) != 2 or not 0 < speeds[0] <= speeds[1] <= 10.0:
            raise ValueError(f"ProductionSpec.speeds_mps must be (min, max) in 0…10 m/s, got {speeds!r}")
        if not (np.isfinite(self.duration_s) and self.duration_s > 0):
            raise ValueError(f"ProductionSpec.duration_s must be > 0, got {self.duration_s!r}")
        if not 10.0 <= self.line_length_m <= 5000.0:
            raise ValueError(f"ProductionSpec.line_length_m must be 10…5000 m, got {self.line_length_m!r}")
        if not 0 < self.rate_scale <= 1.0:
            raise ValueError(f"ProductionSpec.rate_scale must be in (0, 1], got {self.rate_scale!r}")
        if self.n_lines is not None and self.n_lines < 1:
            raise ValueError(f"ProductionSpec.n_lines must be ≥ 1, got {self.n_lines!r}")

    def to_dict(self) -> dict:
        """For truth.json (degrees at the edge)."""
        return {
            "duration_s": float(self.duration_s),
            "offsets_m": list(self.offsets_m),
            "line_length_m": float(self.line_length_m),
            "speeds_mps": list(self.speeds_mps),
            "mount_event": None if self.mount_event is None else self.mount_event.to_dict(),
            "wavy_wall": bool(self.wavy_wall),
            "moving_hulls": bool(self.moving_hulls),
            "water": bool(self.water),
            "rate_scale": float(self.rate_scale),
            "n_lines": self.n_lines,
        }


@dataclass(frozen=True)
class Scenario:
    name: str
    description: str
    reference: frames.LocalFrame
    start_gps_s: float
    vessel: str
    wall_azimuth_rad: float
    standoff_m: float
    passes: tuple[PassSpec, ...]
    safe_wall_distance_m: float
    capture_margin_m: float
    capture_validation_planes: bool
    surfaces: tuple[Surface, ...]
    mount: Mount  # a priori (what the site config says)
    truth: InjectedErrors
    scanner: ScannerModel
    motion: MotionModel
    scanner_noise: ScannerNoise
    pos_noise: PosNoise
    production: ProductionSpec | None = None  # a production survey instead of the passes
    #: what a randomized scenario drew (:mod:`calib.sim.randomdraw`, JSON-ready, degrees at the
    #: edge), written to truth.json's ``settings.random_draw``; None for a scenario file
    draw: dict | None = None
    piles: tuple[Pile, ...] = ()  # vertical cylinders, after the surfaces in the scene

    # -- geometry ---------------------------------------------------------------------------

    @property
    def water_azimuth_rad(self) -> float:
        return float(frames.wrap_2pi(self.wall_azimuth_rad - np.pi / 2))

    def site_to_lgf(self, along_m, out_m, up_m) -> np.ndarray:
        """Site-frame coordinates → (n, 3) LGF (NED) metres."""
        a, w = self.wall_azimuth_rad, self.water_azimuth_rad
        along, out, up = (np.atleast_1d(np.asarray(x, float)) for x in (along_m, out_m, up_m))
        return np.column_stack(
            [along * np.cos(a) + out * np.cos(w), along * np.sin(a) + out * np.sin(w), -up]
        )

    def lgf_to_site(self, p_lgf) -> tuple[float, float, float]:
        """One LGF (NED) point → site frame (along the wall, out toward the water, up), metres:
        the inverse of :meth:`site_to_lgf`."""
        a, w = self.wall_azimuth_rad, self.water_azimuth_rad
        n, e, d = (float(x) for x in p_lgf)
        return n * np.cos(a) + e * np.sin(a), n * np.cos(w) + e * np.sin(w), -d

    def rectangle(self, s: Surface) -> Rectangle:
        c = self.site_to_lgf(s.along_m, s.out_m, s.up_m)[0]
        return Rectangle.from_orientation(
            s.name,
            c,
            s.width_m,
            s.height_m,
            s.inclination_rad,
            self.water_azimuth_rad + s.facing_rad,
            s.reflectivity,
        )

    def cylinder(self, p: Pile) -> VerticalCylinder:
        shape = dict(
            name=p.name,
            center_m=self.site_to_lgf(p.along_m, p.out_m, 0.5 * (p.bottom_up_m + p.top_up_m))[0],
            radius_m=0.5 * float(p.diameter_m),
            height_m=float(p.top_up_m - p.bottom_up_m),
            reflectivity=float(p.reflectivity),
        )
        if not any(p.lean_deg):
            return VerticalCylinder(**shape)
        along, out = np.tan(np.radians(p.lean_deg))
        slope_ne = (self.site_to_lgf(along, out, 0.0)[0, :2]).tolist()
        return LeaningCylinder(**shape, slope_ne=(slope_ne[0], slope_ne[1]))

    def scene(self) -> Scene:
        """The surfaces (rectangles) and then the piles (cylinders) in the LGF."""
        return Scene(
            tuple(self.rectangle(s) for s in self.surfaces),
            tuple(s.kind for s in self.surfaces) + tuple(p.kind for p in self.piles),
            tuple(s.shape for s in self.surfaces),
            tuple(self.cylinder(p) for p in self.piles),
        )

    def pass_plan(self) -> PassPlan:
        """The calibration passes around the targets (the scanner at up = 0 on a level
        vessel); :class:`~calib.survey.passplan.PassPlanError` when they cannot be sailed."""
        scene = self.scene()
        rects = lambda kind: [scene.rectangles[i] for i in scene.indices(kind)]  # noqa: E731
        return plan_passes(
            rects("target"),
            self.wall_azimuth_rad,
            self.standoff_m,
            self.passes,
            track_down_m=-float(self.mount.lever_arm_m[2]),
            safe_wall_distance_m=self.safe_wall_distance_m,
            capture_margin_m=self.capture_margin_m,
            also_capture=rects("validation") if self.capture_validation_planes else (),
        )

    def _targets(self, kind: str) -> tuple[Target, ...]:
        out = []
        for s in self.surfaces:
            if s.kind != kind:
                continue
            r = self.rectangle(s)
            lat, lon, h = self.reference.to_geodetic(r.center_m[None])
            out.append(
                Target(
                    s.name,
                    float(lat[0]),
                    float(lon[0]),
                    float(h[0]),
                    s.width_m,
                    s.height_m,
                    s.inclination_rad,
                    float(frames.wrap_2pi(self.water_azimuth_rad + s.facing_rad)),
                    s.reflectivity,
                )
            )
        return tuple(out)

    def site(self) -> Site:
        """The site config of the simulated bundle: the a-priori mount, the LGF reference, the
        targets' approximate centres, and the observation sigmas the noise models use."""
        kw: dict = {}
        sn, pn = self.scanner_noise, self.pos_noise
        if sn.sigma_range_m > 0:
            kw["sigma_range_m"] = sn.sigma_range_m
        kw["sigma_range_per_m"] = sn.sigma_range_per_m
        kw["beam_divergence_rad"] = sn.beam_divergence_rad
        if sn.sigma_scan_angle_rad > 0:
            kw["sigma_scan_angle_rad"] = sn.sigma_scan_angle_rad
        if pn.model != "none" and np.all(pn.sigma_position_m > 0):
            kw["sigma_position_m"] = pn.sigma_position_m
        if pn.model != "none" and np.all(pn.sigma_attitude_rad > 0):
            kw["sigma_attitude_rad"] = pn.sigma_attitude_rad
        if pn.model == "gauss_markov" and pn.tau_in_site:
            kw["pos_correlation_time_s"] = np.concatenate(
                [np.broadcast_to(pn.tau_position_s, 3), np.broadcast_to(pn.tau_attitude_s, 3)]
            )
        return Site(
            mount=self.mount,
            targets=self._targets("target"),
            reference=self.reference,
            vessel=self.vessel,
            wall_azimuth_rad=self.wall_azimuth_rad,
            standoff_m=self.standoff_m,
            passes=self.passes,
            validation_planes=self._targets("validation"),
            piles=self._site_piles(),
            **kw,
        )

    def _site_piles(self) -> tuple[SitePile, ...]:
        out = []
        for p in self.piles:
            c = self.cylinder(p)
            lat, lon, h = self.reference.to_geodetic(c.center_m[None])
            half = 0.5 * c.height_m
            out.append(
                SitePile(
                    p.name, float(lat[0]), float(lon[0]), float(h[0]) - half, float(h[0]) + half, p.diameter_m
                )
            )
        return tuple(out)

    def to_dict(self) -> dict:
        """The resolved settings (for truth.json)."""
        m = self.mount
        out = {
            "name": self.name,
            "description": self.description,
            "reference": self.reference.as_dict(),
            "start_gps_s": self.start_gps_s,
            "wall_azimuth_deg": float(np.degrees(self.wall_azimuth_rad)),
            "standoff_m": self.standoff_m,
            "safe_wall_distance_m": self.safe_wall_distance_m,
            "capture_margin_m": self.capture_margin_m,
            "mount_apriori": {
                "lever_arm_m": [float(x) for x in m.lever_arm_m],
                "nominal_deg": [float(x) for x in np.degrees(m.nominal_rad)],
                "boresight_apriori_deg": [float(x) for x in np.degrees(m.boresight_rad)],
            },
            "scanner": self.scanner.to_dict(),
            "motion": self.motion.to_dict(),
            "noise": {"scanner": self.scanner_noise.to_dict(), "pos": self.pos_noise.to_dict()},
        }
        if self.draw is not None:
            out["random_draw"] = self.draw
        return out


def with_flat_surfaces(scenario: Scenario) -> Scenario:
    """``scenario`` with every surface exactly planar (no waviness, no roughness): what the
    scenario key ``scene.flat_surfaces: true`` gives."""
    return replace(scenario, surfaces=tuple(replace(s, shape=None) for s in scenario.surfaces))
