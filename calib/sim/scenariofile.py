"""Scenario files: YAML files (shipped ones by name, or any path), validated with errors that
name the file, line, key and value, with ``key=value`` overrides on dotted keys (a list item
by index or, for a list of named items, by name: ``scene.surfaces.quay_wall.roughness_m=0`` or
``scene.surfaces[quay_wall].roughness_m=0``), read into a
:class:`~calib.sim.scenario.Scenario` (whose docstring describes the site frame the scene's
coordinates are given in).

The shipped scenarios (``calib/sim/scenarios/*.yaml``) document every key; ``harbour.yaml``
the ``production`` section (a production survey of :mod:`calib.sim.harbour`'s harbour front,
with an optional mount event), ``montreal_piles.yaml`` the scene's ``piles`` (vertical
cylinders).
"""

from __future__ import annotations

import datetime as _dt
import re
from collections.abc import Mapping, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from calib.core import frames
from calib.core.georef import Mount
from calib.io.bundle import SCANNER_RANGE_M
from calib.io.configfile import ConfigError, Node, load_yaml
from calib.io.site import (
    DEFAULT_PASS_LENGTH_M,
    DEFAULT_PASS_SPEED_MPS,
    PassSpec,
    six_fold_passes,
)
from calib.sim.harbour import harbour_scenario
from calib.sim.motion import MotionModel, Wave
from calib.sim.noise import POS_NOISE_MODELS, PosNoise, ScannerNoise
from calib.sim.scenario import (
    MAX_MOUNT_STEP_RAD,
    InjectedErrors,
    MountEvent,
    Pile,
    ProductionSpec,
    ScannerModel,
    Scenario,
    Surface,
)
from calib.sim.scene import BACKGROUND_KINDS
from calib.sim.surfaceshape import SurfaceShape

SCENARIO_DIR = Path(__file__).resolve().parent / "scenarios"
#: When a scenario gives no ``start_utc``: the day of the thesis's Montreal survey.
DEFAULT_START_GPS_S = frames.gps_ns_to_seconds(
    frames.utc_to_gps_ns(_dt.datetime(2019, 7, 9, 14, tzinfo=_dt.UTC))
)


# -- finding and loading --------------------------------------------------------------------


def scenario_names() -> list[str]:
    """Names of the shipped scenarios."""
    return sorted(p.stem for p in SCENARIO_DIR.glob("*.yaml"))


def resolve_scenario(name_or_path: str | Path) -> Path:
    """A shipped scenario's file by name, else an existing YAML file path."""
    s = str(name_or_path)
    if s in scenario_names():
        return SCENARIO_DIR / f"{s}.yaml"
    p = Path(s)
    if p.is_file():
        return p
    raise ConfigError(
        f"scenario {s!r}: neither a shipped scenario ({', '.join(scenario_names())}) nor an existing file"
    )


def load_scenario(name_or_path: str | Path, overrides: Sequence[str] | Mapping[str, Any] = ()) -> Scenario:
    """Load and validate a scenario; ``overrides`` are ``"dotted.key=value"`` strings (the value
    is YAML: ``0.5``, ``[1, 2, 3]``, ``white``) or a mapping of dotted keys to values."""
    path = resolve_scenario(name_or_path)
    root = load_yaml(path)
    for key, node in _override_nodes(overrides):
        root = _set(root, key, node)
    return _scenario(root, default_name=path.stem)


def parse_scenario(
    text: str, source: str = "scenario.yaml", overrides: Sequence[str] | Mapping[str, Any] = ()
) -> Scenario:
    root = load_yaml(text, source=source)
    for key, node in _override_nodes(overrides):
        root = _set(root, key, node)
    return _scenario(root, default_name=Path(source).stem)


# -- overrides ------------------------------------------------------------------------------


def override_strings(overrides: Sequence[str] | Mapping[str, Any]) -> list[str]:
    """The overrides as truth.json lists them."""
    if isinstance(overrides, Mapping):
        return [f"{k}={v!r}" for k, v in overrides.items()]
    return [str(o) for o in overrides]


_BRACKETS = re.compile(r"\[([^\[\]]*)\]")


def _override_nodes(overrides) -> list[tuple[str, Node]]:
    items: list[tuple[str, str]] = []
    if isinstance(overrides, Mapping):
        items = [(str(k), yaml.safe_dump(v, default_flow_style=True)) for k, v in overrides.items()]
    else:
        for item in overrides:
            key, sep, text = str(item).partition("=")
            key = key.strip()
            if not sep or not key:
                raise ConfigError(
                    f"--set {item!r}: expected key=value with a dotted key, e.g. noise.pos.model=white"
                )
            items.append((key, text))
    out = []
    for key, text in items:
        key = _BRACKETS.sub(r".\1", key)  # a[b].c → a.b.c
        if any(not part for part in key.split(".")):
            raise ConfigError(f"--set {key}: empty part in the dotted key")
        out.append((key, load_yaml(text, source="--set")))
    return out


def _reroot(node: Node, path: str) -> Node:
    """A copy of ``node`` whose paths start at ``path``."""
    v = node.value
    if isinstance(v, dict):
        v = {k: _reroot(c, f"{path}.{k}" if path else k) for k, c in v.items()}
    elif isinstance(v, list):
        v = [_reroot(c, f"{path}[{i}]") for i, c in enumerate(v)]
    return Node(v, path, node.source, node.line, node.column)


def _set(node: Node, key: str, value: Node, full_key: str | None = None) -> Node:
    """``node`` with the dotted ``key`` (relative to it) replaced by ``value``; missing
    mappings on the way are created (validation then rejects keys that do not exist)."""
    full_key = full_key or key
    head, _, rest = key.partition(".")
    if isinstance(node.value, dict):
        child_path = f"{node.path}.{head}" if node.path else head
        if rest:
            child = node.value.get(head)
            if child is None or child.value is None:  # a missing or empty section
                child = Node({}, child_path, value.source, 1, 1)
            new = _set(child, rest, value, full_key)
        else:
            new = _reroot(value, child_path)
        return Node({**node.value, head: new}, node.path, node.source, node.line, node.column)
    if isinstance(node.value, list):
        names = [
            c.value["name"].value if isinstance(c.value, dict) and "name" in c.value else None
            for c in node.value
        ]
        if head.isdigit() and int(head) < len(node.value):
            i = int(head)
        elif not head.isdigit() and names.count(head) == 1:
            i = names.index(head)
        else:
            named = [str(n) for n in names if n is not None]
            raise ConfigError(
                f"--set {full_key}: {head!r} is not an index of the "
                f"{len(node.value)}-item list at {node.where()}"
                + (f" nor the name of one of its items ({', '.join(named)})" if named else "")
            )
        items = list(node.value)
        items[i] = _set(items[i], rest, value, full_key) if rest else _reroot(value, f"{node.path}[{i}]")
        return Node(items, node.path, node.source, node.line, node.column)
    raise ConfigError(
        f"--set {full_key}: {node.path!r} is a value ({node.plain()!r} at "
        f"{node.where()}), not a mapping or a list"
    )


# -- validation -----------------------------------------------------------------------------


def _opt(m: dict[str, Node], key: str, conv, default):
    return conv(m[key]) if key in m else default


def _number(minimum=None, maximum=None, exclusive=False):
    return lambda n: n.number(minimum, maximum, exclusive_minimum=exclusive)


def _positive(n: Node) -> float:
    return n.number(0.0, exclusive_minimum=True)


def _nonneg(n: Node) -> float:
    return n.number(0.0)


def _vec_deg(n: Node) -> np.ndarray:
    return np.radians(n.vector(3))


def _start_gps_s(n: Node) -> float:
    v = n.value
    if isinstance(v, str):
        try:
            v = _dt.datetime.fromisoformat(v)
        except ValueError:
            raise n.fail("an ISO 8601 UTC time such as 2019-07-09T14:00:00Z") from None
    if not isinstance(v, _dt.datetime):
        raise n.fail("an ISO 8601 UTC time such as 2019-07-09T14:00:00Z")
    if v.tzinfo is None:
        v = v.replace(tzinfo=_dt.UTC)
    return frames.gps_ns_to_seconds(frames.utc_to_gps_ns(v))


_SURFACE_KEYS = {
    "along_m", "out_m", "up_m", "size_m", "inclination_deg", "facing_deg", "reflectivity", "waviness",
    "roughness_m",
}  # fmt: skip
_PILE_KEYS = {"along_m", "out_m", "kind", "reflectivity", "lean_deg"}


def _shape(m: dict[str, Node]) -> SurfaceShape | None:
    """A surface's ``waviness: {amplitude_m, wavelength_m: [shortest, longest]}`` and
    ``roughness_m`` (both RMS, metres); None (flat) when neither is given."""
    if "waviness" not in m and "roughness_m" not in m:
        return None
    amplitude, wavelength = 0.0, SurfaceShape().waviness_wavelength_m
    if "waviness" in m:
        w = m["waviness"].mapping(required={"amplitude_m", "wavelength_m"})
        amplitude = w["amplitude_m"].number(0.0)
        node = w["wavelength_m"]
        lo, hi = node.vector(2)
        if not (lo > 0 and hi > 0):
            raise node.fail("[shortest, longest] wavelengths in metres, both > 0")
        if lo > hi:
            raise node.fail("[shortest, longest] wavelengths in metres, shortest first")
        wavelength = (float(lo), float(hi))
    return SurfaceShape(amplitude, wavelength, _opt(m, "roughness_m", _nonneg, 0.0))


def _surface(n: Node, kind: str | None, default_reflectivity: float) -> Surface:
    m = n.mapping(
        required={"name", "up_m", "size_m"}, optional=_SURFACE_KEYS | ({"kind"} if kind is None else set())
    )
    if kind is None:
        kind = m["kind"].string(BACKGROUND_KINDS) if "kind" in m else "other"
    size = m["size_m"].vector(2)
    if np.any(size <= 0):
        raise m["size_m"].fail("2 positive numbers (width, height along the slope)")
    return Surface(
        name=m["name"].string(),
        kind=kind,
        along_m=_opt(m, "along_m", Node.number, 0.0),
        out_m=_opt(m, "out_m", Node.number, 0.0),
        up_m=m["up_m"].number(),
        width_m=float(size[0]),
        height_m=float(size[1]),
        inclination_rad=float(np.radians(_opt(m, "inclination_deg", _number(-90.0, 90.0), 90.0))),
        facing_rad=float(np.radians(_opt(m, "facing_deg", _number(-360.0, 360.0), 0.0))),
        reflectivity=_opt(m, "reflectivity", _number(0.0, 1.0), default_reflectivity),
        shape=_shape(m),
    )


def _pile(n: Node) -> Pile:
    """A pile: ``{name, along_m, out_m, diameter_m, bottom_up_m, top_up_m[, kind, reflectivity,
    lean_deg]}`` (``lean_deg``: [toward along, toward out], each within ±20°)."""
    m = n.mapping(required={"name", "diameter_m", "bottom_up_m", "top_up_m"}, optional=_PILE_KEYS)
    bottom = m["bottom_up_m"].number()
    top = m["top_up_m"].number()
    if top <= bottom:
        raise m["top_up_m"].fail(f"a height above bottom_up_m ({bottom:g})")
    return Pile(
        name=m["name"].string(),
        kind=_opt(m, "kind", lambda x: x.string(BACKGROUND_KINDS), "other"),
        along_m=_opt(m, "along_m", Node.number, 0.0),
        out_m=_opt(m, "out_m", Node.number, 0.0),
        bottom_up_m=bottom,
        top_up_m=top,
        diameter_m=m["diameter_m"].number(0.0, 20.0, exclusive_minimum=True),
        reflectivity=_opt(m, "reflectivity", _number(0.0, 1.0), 0.3),
        lean_deg=_opt(m, "lean_deg", _lean_deg, (0.0, 0.0)),
    )


def _lean_deg(n: Node) -> tuple[float, float]:
    items = n.value
    if not isinstance(items, list) or len(items) != 2:
        raise n.fail("a list of 2 numbers [toward along, toward out] (deg)")
    along, out = (it.number(-20.0, 20.0) for it in items)
    return along, out


def _scene(n: Node) -> tuple[tuple[Surface, ...], tuple[Pile, ...]]:
    """The scene's surfaces (targets, validation planes, the rest) and piles."""
    m = n.mapping(required={"targets"}, optional={"validation_planes", "surfaces", "piles", "flat_surfaces"})
    out = [_surface(t, "target", 0.9) for t in m["targets"].sequence(min_len=1)]
    if "validation_planes" in m:
        out += [_surface(t, "validation", 0.6) for t in m["validation_planes"].sequence()]
    if "surfaces" in m:
        out += [_surface(t, None, 0.3) for t in m["surfaces"].sequence()]
    piles = tuple(_pile(t) for t in m["piles"].sequence()) if "piles" in m else ()
    names = [s.name for s in out] + [p.name for p in piles]
    for i, name in enumerate(names):
        if name in names[:i]:
            raise n.fail(f"unique surface names ({name!r} appears twice)")
    if _opt(m, "flat_surfaces", Node.boolean, False):  # every surface planar, whatever it says
        out = [replace(s, shape=None) for s in out]
    return tuple(out), piles


def _passes(m: dict[str, Node]) -> tuple[PassSpec, ...]:
    length = _opt(m, "pass_length_m", _positive, DEFAULT_PASS_LENGTH_M)
    speed = _opt(m, "speed_mps", _positive, DEFAULT_PASS_SPEED_MPS)
    if "passes" not in m or m["passes"].value == "six_fold":
        return six_fold_passes(length, speed)
    node = m["passes"]
    if not isinstance(node.value, list):
        raise node.fail("six_fold or a list of {id, relative_heading_deg[, length_m, speed_mps, standoff_m]}")
    out = []
    for pn in node.sequence(min_len=1):
        pm = pn.mapping(
            required={"id", "relative_heading_deg"}, optional={"length_m", "speed_mps", "standoff_m"}
        )
        out.append(
            PassSpec(
                pm["id"].integer(minimum=0),
                float(np.radians(pm["relative_heading_deg"].number(-360.0, 360.0))),
                _opt(pm, "length_m", _positive, length),
                _opt(pm, "speed_mps", _positive, speed),
                _opt(pm, "standoff_m", _positive, None),
            )
        )
    ids = [p.id for p in out]
    if len(set(ids)) != len(ids):
        raise node.fail("unique pass ids")
    return tuple(out)


def _mount(n: Node) -> Mount:
    m = n.mapping(optional={"lever_arm_m", "nominal_deg", "boresight_apriori_deg"})
    return Mount(
        lever_arm_m=_opt(m, "lever_arm_m", lambda x: x.vector(3), np.zeros(3)),
        nominal_rad=_opt(m, "nominal_deg", _vec_deg, np.zeros(3)),
        boresight_rad=_opt(m, "boresight_apriori_deg", _vec_deg, np.zeros(3)),
    )


def _truth(n: Node) -> InjectedErrors:
    m = n.mapping(
        optional={
            "boresight_deg",
            "lever_arm_error_m",
            "range_offset_m",
            "scan_angle_offset_deg",
            "time_offset_s",
        }
    )
    bs = _opt(m, "boresight_deg", _vec_deg, np.zeros(3))
    if np.any(np.abs(bs) > np.radians(20.0)):
        raise m["boresight_deg"].fail("boresight angles within ±20°")
    return InjectedErrors(
        boresight_rad=bs,
        lever_arm_error_m=_opt(m, "lever_arm_error_m", lambda x: x.vector(3), np.zeros(3)),
        range_offset_m=_opt(m, "range_offset_m", _number(-10.0, 10.0), 0.0),
        scan_angle_offset_rad=float(np.radians(_opt(m, "scan_angle_offset_deg", _number(-20.0, 20.0), 0.0))),
        time_offset_s=_opt(m, "time_offset_s", _number(-1.0, 1.0), 0.0),
    )


def _windows(n: Node) -> tuple[tuple[float, float], ...]:
    out = []
    for w in n.sequence():
        lo, hi = w.vector(2)
        if not (0.0 <= lo <= 360.0 and 0.0 <= hi <= 360.0):
            raise w.fail("[start_deg, end_deg] with both in 0…360")
        out.append((float(np.radians(lo)), float(np.radians(hi))))
    return tuple(out)


def _in_window(n: Node) -> float:
    """A range inside the Z+F 9012's physical window (what the bundle reader accepts)."""
    lo, hi = SCANNER_RANGE_M
    v = n.number()
    if not lo <= v <= hi:
        raise n.fail(f"a range within the scanner's physical window {lo:g}…{hi:g} m")
    return v


def _scanner(n: Node) -> ScannerModel:
    m = n.mapping(
        optional={
            "profile_rate_hz",
            "points_per_360",
            "max_range_m",
            "min_range_m",
            "angular_windows_deg",
            "point_rate_scale",
        }
    )
    d = ScannerModel()
    out = ScannerModel(
        profile_rate_hz=_opt(m, "profile_rate_hz", _positive, d.profile_rate_hz),
        points_per_360=_opt(m, "points_per_360", lambda x: x.integer(minimum=4), d.points_per_360),
        max_range_m=_opt(m, "max_range_m", _in_window, d.max_range_m),
        min_range_m=_opt(m, "min_range_m", _in_window, d.min_range_m),
        angular_windows_rad=_opt(m, "angular_windows_deg", _windows, ()),
        point_rate_scale=_opt(m, "point_rate_scale", _number(0.0, 1.0, exclusive=True), 1.0),
    )
    if out.min_range_m >= out.max_range_m:
        raise m["min_range_m"].fail(f"a number below max_range_m ({out.max_range_m:g})")
    return out


def _wave(n: Node, amp_key: str) -> Wave:
    m = n.mapping(required={amp_key, "period_s"})
    amp = m[amp_key].number(0.0)
    return Wave(
        float(np.radians(amp)) if amp_key.endswith("_deg") else amp,
        m["period_s"].number(0.0, exclusive_minimum=True),
    )


def _motion(n: Node) -> MotionModel:
    m = n.mapping(
        optional={"rate_hz", "roll", "pitch", "heave", "yaw", "turns", "turn_radius_m", "pass_gap_s"}
    )
    d = MotionModel()
    return MotionModel(
        rate_hz=_opt(m, "rate_hz", _number(2.0, 1000.0), d.rate_hz),
        roll=_opt(m, "roll", lambda x: _wave(x, "amplitude_deg"), d.roll),
        pitch=_opt(m, "pitch", lambda x: _wave(x, "amplitude_deg"), d.pitch),
        heave=_opt(m, "heave", lambda x: _wave(x, "amplitude_m"), d.heave),
        yaw=_opt(m, "yaw", lambda x: _wave(x, "amplitude_deg"), d.yaw),
        turns=_opt(m, "turns", Node.boolean, d.turns),
        turn_radius_m=_opt(m, "turn_radius_m", _positive, d.turn_radius_m),
        pass_gap_s=_opt(m, "pass_gap_s", _number(2.0), d.pass_gap_s),
    )


def _noise(n: Node) -> tuple[ScannerNoise, PosNoise]:
    m = n.mapping(optional={"scanner", "pos"})
    sn = ScannerNoise()
    if "scanner" in m:
        s = m["scanner"].mapping(
            optional={"sigma_range_m", "sigma_range_per_m", "beam_divergence_mrad", "sigma_scan_angle_deg"}
            | {"intensity_follows_incidence"}
        )
        sn = ScannerNoise(
            sigma_range_m=_opt(s, "sigma_range_m", _nonneg, 0.0),
            sigma_range_per_m=_opt(s, "sigma_range_per_m", _nonneg, 0.0),
            beam_divergence_rad=_opt(s, "beam_divergence_mrad", _nonneg, 0.0) * 1e-3,
            sigma_scan_angle_rad=float(np.radians(_opt(s, "sigma_scan_angle_deg", _nonneg, 0.0))),
            intensity_follows_incidence=_opt(s, "intensity_follows_incidence", Node.boolean, True),
        )
    pn = PosNoise()
    if "pos" in m:
        p = m["pos"].mapping(
            required={"model"},
            optional={
                "sigma_position_m",
                "sigma_attitude_deg",
                "tau_position_s",
                "tau_attitude_s",
                "tau_in_site",
            },
        )
        kw = {}
        for key, attr, conv in (
            ("sigma_position_m", "sigma_position_m", np.asarray),
            ("sigma_attitude_deg", "sigma_attitude_rad", np.radians),
            ("tau_position_s", "tau_position_s", np.asarray),
            ("tau_attitude_s", "tau_attitude_s", np.asarray),
        ):
            if key in p:
                kw[attr] = conv(p[key].vector(3, minimum=0.0))
        model = p["model"].string(POS_NOISE_MODELS)
        if model == "gauss_markov":
            for key in ("tau_position_s", "tau_attitude_s"):
                if key in p and np.any(p[key].vector(3) <= 0):
                    raise p[key].fail("3 correlation times > 0")
        pn = PosNoise(model=model, tau_in_site=_opt(p, "tau_in_site", Node.boolean, True), **kw)
    return sn, pn


def _mount_event(n: Node, duration_s: float) -> MountEvent | None:
    """``mount_event: null`` or ``{t_s (default: half the duration), step_deg, creep_s}``."""
    if n.value is None:
        return None
    m = n.mapping(required={"step_deg"}, optional={"t_s", "creep_s"})
    step = _vec_deg(m["step_deg"])
    if np.any(np.abs(step) > MAX_MOUNT_STEP_RAD):
        raise m["step_deg"].fail(f"3 angles within ±{np.degrees(MAX_MOUNT_STEP_RAD):g}° (roll, pitch, yaw)")
    return MountEvent(
        t_s=_opt(m, "t_s", _nonneg, 0.5 * duration_s),
        step_rad=step,
        creep_s=_opt(m, "creep_s", _nonneg, 0.0),
    )


def _production(n: Node, scanner: Node | None) -> ProductionSpec:
    """The ``production`` section (harbour.yaml documents it). ``rate_scale`` defaults to the
    scanner's ``point_rate_scale`` when the file gives one, else 0.02; an override of
    ``scanner.point_rate_scale`` (``--point-rate-scale``) wins over it."""
    m = n.mapping(
        optional={"duration_s", "n_lines", "offsets_m", "line_length_m", "speeds_mps", "wavy_wall",
                  "moving_hulls", "water", "rate_scale", "mount_event"}
    )  # fmt: skip
    d = ProductionSpec()
    duration = _opt(m, "duration_s", _positive, d.duration_s)
    offsets = d.offsets_m
    if "offsets_m" in m:
        lo, hi = ProductionSpec.MIN_OFFSET_M, ProductionSpec.MAX_OFFSET_M
        offsets = tuple(x.number(lo, hi) for x in m["offsets_m"].sequence(min_len=1))
    speeds = d.speeds_mps
    if "speeds_mps" in m:
        node = m["speeds_mps"]
        lo_v, hi_v = node.vector(2)
        if not 0 < lo_v <= hi_v <= 10.0:
            raise node.fail("[min, max] speeds in m/s with 0 < min ≤ max ≤ 10")
        speeds = (float(lo_v), float(hi_v))
    sm = scanner.value if scanner is not None and isinstance(scanner.value, dict) else {}
    prs = sm.get("point_rate_scale")
    rate = _opt(m, "rate_scale", _number(0.0, 1.0, exclusive=True), d.rate_scale)
    if prs is not None and ("rate_scale" not in m or prs.source == "--set"):
        rate = prs.number(0.0, 1.0, exclusive_minimum=True)
    n_lines = None
    if "n_lines" in m and m["n_lines"].value is not None:
        n_lines = m["n_lines"].integer(minimum=1)
    return ProductionSpec(
        duration_s=duration,
        offsets_m=offsets,
        line_length_m=_opt(m, "line_length_m", _number(10.0, 5000.0), d.line_length_m),
        speeds_mps=speeds,
        mount_event=_mount_event(m["mount_event"], duration) if "mount_event" in m else None,
        wavy_wall=_opt(m, "wavy_wall", Node.boolean, d.wavy_wall),
        moving_hulls=_opt(m, "moving_hulls", Node.boolean, d.moving_hulls),
        water=_opt(m, "water", Node.boolean, d.water),
        rate_scale=rate,
        n_lines=n_lines,
    )


_TOP_KEYS = {
    "name", "description", "reference", "start_utc", "vessel", "site", "scene", "mount", "truth", "scanner",
    "motion", "noise", "production",
}  # fmt: skip


def _scenario(root: Node, default_name: str) -> Scenario:
    """The scenario of a YAML tree; with a ``production`` section, a production survey of the
    harbour front (``scene``, when given, is checked and then replaced by the harbour's)."""
    section = root.value.get("production") if isinstance(root.value, dict) else None
    production = section is not None and section.value is not None  # production: null = none
    top = root.mapping(
        required={"reference", "site"} | (set() if production else {"scene"}), optional=_TOP_KEYS
    )
    ref = top["reference"].mapping(required={"lat_deg", "lon_deg"}, optional={"height_m"})
    reference = frames.LocalFrame(
        ref["lat_deg"].number(-90.0, 90.0),
        ref["lon_deg"].number(-180.0, 180.0),
        _opt(ref, "height_m", Node.number, 0.0),
    )
    sm = top["site"].mapping(
        optional={"wall_azimuth_deg", "standoff_m", "passes", "pass_length_m", "speed_mps",
                  "safe_wall_distance_m", "capture_margin_m", "capture_validation_planes"}
    )  # fmt: skip
    scanner_noise, pos_noise = _noise(top["noise"]) if "noise" in top else (ScannerNoise(), PosNoise())
    surfaces, piles = _scene(top["scene"]) if "scene" in top else ((), ())
    scenario = Scenario(
        name=_opt(top, "name", Node.string, default_name),
        description=_opt(top, "description", Node.string, ""),
        reference=reference,
        start_gps_s=_opt(top, "start_utc", _start_gps_s, DEFAULT_START_GPS_S),
        vessel=_opt(top, "vessel", Node.string, "sim-vessel"),
        wall_azimuth_rad=float(np.radians(_opt(sm, "wall_azimuth_deg", _number(-360.0, 360.0), 0.0))),
        standoff_m=_opt(sm, "standoff_m", _positive, 15.0),
        passes=_passes(sm),
        safe_wall_distance_m=_opt(sm, "safe_wall_distance_m", _nonneg, 5.0),
        capture_margin_m=_opt(sm, "capture_margin_m", _nonneg, 3.0),
        capture_validation_planes=_opt(sm, "capture_validation_planes", Node.boolean, False),
        surfaces=surfaces,
        mount=_opt(top, "mount", _mount, Mount()),
        truth=_opt(top, "truth", _truth, InjectedErrors()),
        scanner=_opt(top, "scanner", _scanner, ScannerModel()),
        motion=_opt(top, "motion", _motion, MotionModel()),
        scanner_noise=scanner_noise,
        pos_noise=pos_noise,
        piles=piles,
    )
    if production:
        scenario = harbour_scenario(scenario, _production(top["production"], top.get("scanner")))
    return scenario
