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
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from calib.core import frames
from calib.core.geometry import Rectangle
from calib.core.georef import Mount
from calib.io.bundle import SCANNER_RANGE_M
from calib.io.site import PassSpec, Site, Target
from calib.sim.motion import MotionModel
from calib.sim.noise import PosNoise, ScannerNoise
from calib.sim.scene import Scene
from calib.sim.surfaceshape import SurfaceShape

# -- the scenario ---------------------------------------------------------------------------


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

    def scene(self) -> Scene:
        return Scene(
            tuple(self.rectangle(s) for s in self.surfaces),
            tuple(s.kind for s in self.surfaces),
            tuple(s.shape for s in self.surfaces),
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
        if pn.model == "gauss_markov":
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
            **kw,
        )

    def to_dict(self) -> dict:
        """The resolved settings (for truth.json)."""
        m = self.mount
        return {
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


def with_flat_surfaces(scenario: Scenario) -> Scenario:
    """``scenario`` with every surface exactly planar (no waviness, no roughness): what the
    scenario key ``scene.flat_surfaces: true`` gives."""
    return replace(scenario, surfaces=tuple(replace(s, shape=None) for s in scenario.surfaces))
