"""The site config (``site.yaml``, docs/architecture.md §4): reference, mount, sigmas, targets, pass plan.

Readers accept exactly the documented keys; an unknown key, a missing key or a bad value is a
:class:`calib.io.configfile.ConfigError` naming the file, line, key and value. In memory everything
is SI and radians; degrees exist only in the YAML.

Beyond docs/architecture.md §4 a pass entry may carry ``length_m``, ``speed_mps`` and its own
``standoff_m`` (the pass-plan generator and ``mls plan`` use them; defaults below), ``piles``
lists vertical cylinders for the design's lines for yaw, and ``pos_sigmas`` may carry ``correlation_time_s``,
the correlation time of the POS errors that ``sigma_realistic`` assumes (first-order
Gauss–Markov; one number, ``[position, attitude]`` or six values for north, east, down, roll,
pitch, heading; when absent the calibration assumes 60 s and says so).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from calib.core import frames
from calib.core.geometry import Rectangle, VerticalCylinder
from calib.core.georef import Mount
from calib.io.configfile import ConfigError, Node, load_yaml

#: The six-fold line pattern (thesis Fig. 3.3): headings relative to the wall direction, in the
#: order they are sailed.
SIX_FOLD_RELATIVE_HEADINGS_DEG = (0.0, 180.0, 45.0, 225.0, 315.0, 135.0)
DEFAULT_PASS_LENGTH_M = 80.0
DEFAULT_PASS_SPEED_MPS = 2.0


@dataclass(frozen=True)
class Target:
    """A planar rectangle as configured (geodetic centre, degrees converted to radians)."""

    name: str
    lat_deg: float
    lon_deg: float
    height_m: float
    width_m: float
    height_along_slope_m: float
    inclination_rad: float
    facing_azimuth_rad: float
    reflectivity: float = 0.9

    def rectangle(self, frame: frames.LocalFrame) -> Rectangle:
        c = frame.to_lgf([self.lat_deg], [self.lon_deg], [self.height_m])[0]
        return Rectangle.from_orientation(
            self.name,
            c,
            self.width_m,
            self.height_along_slope_m,
            self.inclination_rad,
            self.facing_azimuth_rad,
            self.reflectivity,
        )

    def to_yaml(self) -> dict:
        return {
            "name": self.name,
            "center": {
                "lat_deg": float(self.lat_deg),
                "lon_deg": float(self.lon_deg),
                "height_m": float(self.height_m),
            },
            "size_m": [float(self.width_m), float(self.height_along_slope_m)],
            "inclination_deg": float(np.degrees(self.inclination_rad)),
            "facing_azimuth_deg": float(np.degrees(self.facing_azimuth_rad)),
            "reflectivity": float(self.reflectivity),
        }


@dataclass(frozen=True)
class SitePile:
    """A pile, post or dolphin's pile as configured: a vertical cylinder, its axis at a geodetic
    position from ``bottom_height_m`` to ``top_height_m`` (ellipsoidal). Optional in site.yaml:
    the calibration finds piles by itself; the design's what-if (``mls design --site``) needs
    them to predict what lines at several standoffs buy the boresight yaw."""

    name: str
    lat_deg: float
    lon_deg: float
    bottom_height_m: float
    top_height_m: float
    diameter_m: float

    def cylinder(self, frame: frames.LocalFrame) -> VerticalCylinder:
        mid = 0.5 * (self.bottom_height_m + self.top_height_m)
        return VerticalCylinder(
            name=self.name,
            center_m=frame.to_lgf([self.lat_deg], [self.lon_deg], [mid])[0],
            radius_m=0.5 * self.diameter_m,
            height_m=self.top_height_m - self.bottom_height_m,
        )

    def to_yaml(self) -> dict:
        return {
            "name": self.name,
            "center": {"lat_deg": float(self.lat_deg), "lon_deg": float(self.lon_deg)},
            "diameter_m": float(self.diameter_m),
            "bottom_height_m": float(self.bottom_height_m),
            "top_height_m": float(self.top_height_m),
        }


@dataclass(frozen=True)
class PassSpec:
    id: int
    relative_heading_rad: float
    length_m: float = DEFAULT_PASS_LENGTH_M
    speed_mps: float = DEFAULT_PASS_SPEED_MPS
    #: this line's closest approach to the targets; None: the site's ``standoff_m`` (lines at
    #: several offsets from the scene's features make the boresight yaw observable)
    standoff_m: float | None = None

    def to_yaml(self) -> dict:
        out = {
            "id": int(self.id),
            "relative_heading_deg": float(np.degrees(self.relative_heading_rad)),
            "length_m": float(self.length_m),
            "speed_mps": float(self.speed_mps),
        }
        if self.standoff_m is not None:
            out["standoff_m"] = float(self.standoff_m)
        return out


def six_fold_passes(
    length_m: float = DEFAULT_PASS_LENGTH_M, speed_mps: float = DEFAULT_PASS_SPEED_MPS
) -> tuple[PassSpec, ...]:
    return tuple(
        PassSpec(i + 1, float(np.radians(h)), length_m, speed_mps)
        for i, h in enumerate(SIX_FOLD_RELATIVE_HEADINGS_DEG)
    )


@dataclass(frozen=True)
class Site:
    mount: Mount
    targets: tuple[Target, ...]
    reference: frames.LocalFrame | None = None
    vessel: str = "vessel"
    sigma_range_m: float = 0.003
    #: range noise growing with range (m per m), and the beam divergence (full angle): on a
    #: surface seen at incidence θ the footprint adds ρ·(divergence/2)·tan θ to the range σ
    sigma_range_per_m: float = 0.0
    beam_divergence_rad: float = 0.0
    sigma_scan_angle_rad: float = float(np.radians(0.005))
    sigma_position_m: np.ndarray = field(default_factory=lambda: np.array([0.02, 0.02, 0.03]))
    sigma_attitude_rad: np.ndarray = field(default_factory=lambda: np.radians([0.012, 0.012, 0.012]))
    #: correlation times (s) of the POS errors (first-order Gauss–Markov) for north, east,
    #: down, roll, pitch, heading; None: not configured
    pos_correlation_time_s: np.ndarray | None = None
    wall_azimuth_rad: float = 0.0
    standoff_m: float = 15.0
    passes: tuple[PassSpec, ...] = field(default_factory=six_fold_passes)
    validation_planes: tuple[Target, ...] = ()
    piles: tuple[SitePile, ...] = ()
    #: False when site.yaml lists no passes and the default six-fold plan stands in (warnings
    #: about planned passes say so)
    passes_listed: bool = field(default=True, compare=False)

    def frame(self, fallback: frames.LocalFrame | None = None) -> frames.LocalFrame:
        """The LGF: the configured reference, else ``fallback`` (e.g. the trajectory mean)."""
        if self.reference is not None:
            return self.reference
        if fallback is None:
            raise ConfigError("site: no reference point configured and no fallback given")
        return fallback

    def target_rectangles(self, frame: frames.LocalFrame) -> list[Rectangle]:
        return [t.rectangle(frame) for t in self.targets]

    # -- YAML -------------------------------------------------------------------------------

    def to_yaml(self) -> dict:
        m = self.mount
        d: dict = {"vessel": str(self.vessel)}
        if self.reference is not None:
            d["reference"] = {k: float(v) for k, v in self.reference.as_dict().items()}
        d["mount"] = {
            "lever_arm_m": [float(x) for x in m.lever_arm_m],
            "nominal_deg": [float(x) for x in np.degrees(m.nominal_rad)],
            "boresight_apriori_deg": [float(x) for x in np.degrees(m.boresight_rad)],
        }
        d["scanner"] = {
            "sigma_range_m": float(self.sigma_range_m),
            "sigma_scan_angle_deg": float(np.degrees(self.sigma_scan_angle_rad)),
        }
        if self.sigma_range_per_m:
            d["scanner"]["sigma_range_per_m"] = float(self.sigma_range_per_m)
        if self.beam_divergence_rad:
            d["scanner"]["beam_divergence_mrad"] = float(self.beam_divergence_rad * 1e3)
        d["pos_sigmas"] = {
            "position_m": [float(x) for x in self.sigma_position_m],
            "attitude_deg": [float(x) for x in np.degrees(self.sigma_attitude_rad)],
        }
        if self.pos_correlation_time_s is not None:
            tau = [float(x) for x in self.pos_correlation_time_s]
            d["pos_sigmas"]["correlation_time_s"] = tau[0] if len(set(tau)) == 1 else tau
        d["wall_azimuth_deg"] = float(np.degrees(self.wall_azimuth_rad))
        d["standoff_m"] = float(self.standoff_m)
        d["targets"] = [t.to_yaml() for t in self.targets]
        d["passes"] = [p.to_yaml() for p in self.passes]
        d["validation_planes"] = [t.to_yaml() for t in self.validation_planes]
        if self.piles:
            d["piles"] = [p.to_yaml() for p in self.piles]
        return d

    def dump(self, path: str | Path) -> None:
        Path(path).write_text(yaml.safe_dump(self.to_yaml(), sort_keys=False), encoding="utf-8")


# -- reading --------------------------------------------------------------------------------


def _geodetic(node: Node) -> tuple[float, float, float]:
    m = node.mapping(required={"lat_deg", "lon_deg"}, optional={"height_m"})
    lat = m["lat_deg"].number(-90.0, 90.0)
    lon = m["lon_deg"].number(-180.0, 360.0)
    h = m["height_m"].number() if "height_m" in m else 0.0
    return lat, lon, h


def _correlation_times(node: Node) -> np.ndarray:
    """One number (all channels), [position, attitude] or six values (N, E, D, r, p, h)."""
    if isinstance(node.value, list):
        if len(node.value) not in (2, 6):
            raise node.fail("a positive number, [position, attitude] or 6 positive numbers")
        v = np.array([it.number(0.0, exclusive_minimum=True) for it in node.value])
        return np.repeat(v, 3) if v.size == 2 else v
    return np.full(6, node.number(0.0, exclusive_minimum=True))


def _target(node: Node) -> Target:
    m = node.mapping(
        required={"name", "center", "size_m", "inclination_deg", "facing_azimuth_deg"},
        optional={"reflectivity"},
    )
    lat, lon, h = _geodetic(m["center"])
    size = m["size_m"].vector(2)
    if np.any(size <= 0):
        raise m["size_m"].fail("2 positive numbers (width, height along the slope)")
    return Target(
        name=m["name"].string(),
        lat_deg=lat,
        lon_deg=lon,
        height_m=h,
        width_m=float(size[0]),
        height_along_slope_m=float(size[1]),
        inclination_rad=float(np.radians(m["inclination_deg"].number(-90.0, 90.0))),
        facing_azimuth_rad=float(np.radians(m["facing_azimuth_deg"].number(-360.0, 360.0))),
        reflectivity=m["reflectivity"].number(0.0, 1.0) if "reflectivity" in m else 0.9,
    )


def _targets(node: Node, what: str) -> tuple[Target, ...]:
    return _named(node, _target, what)


def _named(node: Node, read, what: str) -> tuple:
    """A sequence of entries read by ``read``, their names unique."""
    out = tuple(read(n) for n in node.sequence())
    names = [x.name for x in out]
    for i, name in enumerate(names):
        if name in names[:i]:
            raise node.value[i].fail(f"a unique {what} name ({name!r} appears twice)")
    return out


def _pile(node: Node) -> SitePile:
    m = node.mapping(required={"name", "center", "diameter_m", "bottom_height_m", "top_height_m"})
    cm = m["center"].mapping(required={"lat_deg", "lon_deg"})
    bottom = m["bottom_height_m"].number()
    return SitePile(
        name=m["name"].string(),
        lat_deg=cm["lat_deg"].number(-90.0, 90.0),
        lon_deg=cm["lon_deg"].number(-180.0, 360.0),
        bottom_height_m=bottom,
        top_height_m=m["top_height_m"].number(bottom, exclusive_minimum=True),
        diameter_m=m["diameter_m"].number(0.0, 10.0, exclusive_minimum=True),
    )


def _mount(node: Node) -> Mount:
    """site.yaml's ``mount``: lever arm, nominal mounting angles and a-priori boresight (each
    zero when absent)."""
    mm = node.mapping(optional={"lever_arm_m", "nominal_deg", "boresight_apriori_deg"})

    def vec(key, conv=float):
        return np.array([conv(x) for x in mm[key].vector(3)]) if key in mm else np.zeros(3)

    return Mount(
        lever_arm_m=vec("lever_arm_m"),
        nominal_rad=np.radians(vec("nominal_deg")),
        boresight_rad=np.radians(vec("boresight_apriori_deg")),
    )


def _scanner_sigmas(node: Node) -> dict:
    """site.yaml's ``scanner``: the Site fields it sets."""
    sm = node.mapping(
        optional={"sigma_range_m", "sigma_scan_angle_deg", "sigma_range_per_m", "beam_divergence_mrad"}
    )
    kw: dict = {}
    if "sigma_range_m" in sm:
        kw["sigma_range_m"] = sm["sigma_range_m"].number(0.0, exclusive_minimum=True)
    if "sigma_range_per_m" in sm:
        kw["sigma_range_per_m"] = sm["sigma_range_per_m"].number(0.0, 0.01)
    if "beam_divergence_mrad" in sm:
        kw["beam_divergence_rad"] = sm["beam_divergence_mrad"].number(0.0, 20.0) * 1e-3
    if "sigma_scan_angle_deg" in sm:
        kw["sigma_scan_angle_rad"] = float(
            np.radians(sm["sigma_scan_angle_deg"].number(0.0, exclusive_minimum=True))
        )
    return kw


def _pos_sigmas(node: Node) -> dict:
    """site.yaml's ``pos_sigmas``: the Site fields it sets."""
    pm = node.mapping(optional={"position_m", "attitude_deg", "correlation_time_s"})
    kw: dict = {}
    if "correlation_time_s" in pm:
        kw["pos_correlation_time_s"] = _correlation_times(pm["correlation_time_s"])
    for key, attr, conv in (
        ("position_m", "sigma_position_m", lambda v: v),
        ("attitude_deg", "sigma_attitude_rad", np.radians),
    ):
        if key in pm:
            v = pm[key].vector(3)
            if np.any(v <= 0):
                raise pm[key].fail("3 positive numbers")
            kw[attr] = conv(v)
    return kw


def _pass(node: Node) -> PassSpec:
    pm = node.mapping(
        required={"id", "relative_heading_deg"}, optional={"length_m", "speed_mps", "standoff_m"}
    )
    return PassSpec(
        id=pm["id"].integer(minimum=0, maximum=2**63 - 1),  # int64, as points.csv
        relative_heading_rad=float(np.radians(pm["relative_heading_deg"].number())),
        length_m=pm["length_m"].number(0.0, exclusive_minimum=True)
        if "length_m" in pm
        else DEFAULT_PASS_LENGTH_M,
        speed_mps=pm["speed_mps"].number(0.0, exclusive_minimum=True)
        if "speed_mps" in pm
        else DEFAULT_PASS_SPEED_MPS,
        standoff_m=pm["standoff_m"].number(0.0, exclusive_minimum=True) if "standoff_m" in pm else None,
    )


def _passes(node: Node) -> tuple[PassSpec, ...]:
    """site.yaml's ``passes`` (at least one, unique ids)."""
    passes = tuple(_pass(pn) for pn in node.sequence(min_len=1))
    ids = [p.id for p in passes]
    if len(set(ids)) != len(ids):
        raise node.fail("unique pass ids")
    return passes


def site_from_node(root: Node) -> Site:
    top = root.mapping(
        required={"mount", "targets"},
        optional={
            "vessel",
            "reference",
            "scanner",
            "pos_sigmas",
            "wall_azimuth_deg",
            "standoff_m",
            "passes",
            "validation_planes",
            "piles",
        },
    )
    mount = _mount(top["mount"])
    kw: dict = {}
    if "vessel" in top:
        kw["vessel"] = top["vessel"].string()
    if "reference" in top:
        kw["reference"] = frames.LocalFrame(*_geodetic(top["reference"]))
    if "scanner" in top:
        kw.update(_scanner_sigmas(top["scanner"]))
    if "pos_sigmas" in top:
        kw.update(_pos_sigmas(top["pos_sigmas"]))
    if "wall_azimuth_deg" in top:
        kw["wall_azimuth_rad"] = float(np.radians(top["wall_azimuth_deg"].number(-360.0, 360.0)))
    if "standoff_m" in top:
        kw["standoff_m"] = top["standoff_m"].number(0.0, exclusive_minimum=True)
    if "passes" in top and top["passes"].value is not None:
        kw["passes"] = _passes(top["passes"])
    else:
        kw["passes_listed"] = False
    if "validation_planes" in top:
        kw["validation_planes"] = _targets(top["validation_planes"], "validation plane")
    if "piles" in top:
        kw["piles"] = _named(top["piles"], _pile, "pile")
    return Site(mount=mount, targets=_targets(top["targets"], "target"), **kw)


def load_site(path: str | Path) -> Site:
    return site_from_node(load_yaml(path))


def parse_site(text: str, source: str = "site.yaml") -> Site:
    return site_from_node(load_yaml(text, source=source))
