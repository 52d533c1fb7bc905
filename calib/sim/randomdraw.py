"""The randomized calibration scenario (``mls sim dataset --scenario random --seed N``): one seed
draws one geometry over the ranges an independent simulator showed the calibration must survive
(tests/data/foreign/geometry.md): a tilted mount, any wall azimuth, short to long standoffs,
two or three targets flush with the wall or proud of it, with or without reflectivity contrast,
a wavy wall, lever arm, boresight, POS noise, and the six-fold pass headings each a little off.

:func:`draw_geometry` draws (SI units, radians); :func:`scenario_document` turns the draw into a
scenario document with the keys of ``scenarios/montreal.yaml``, which
:func:`calib.sim.scenariofile.parse_scenario` reads like any scenario file (``--set`` overrides
on top); :func:`fit_passes` places the passes from the standoff and the mount's tilt so that the
scanner sweeps the targets. truth.json's ``settings.random_draw`` holds the draw, the placement
and the document (saved as YAML, it reruns the draw as a scenario file).

The draw has a random stream of its own (the seed with :data:`DRAW_STREAM_KEY`), apart from the
simulation's noise, which the same seed drives.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import yaml

from calib.io.site import SIX_FOLD_RELATIVE_HEADINGS_DEG
from calib.sim.scenario import Scenario
from calib.sim.scenariofile import parse_scenario
from calib.sim.surfaceshape import SurfaceShape
from calib.survey.passplan import PassPlanError

RANDOM_SCENARIO = "random"
#: Appended to the seed for the draw's stream (the simulation spawns its own from the bare seed).
DRAW_STREAM_KEY = 0x4D4C5352

# -- the ranges ------------------------------------------------------------------------------

MAX_NOMINAL_TILT_RAD = float(np.radians(30.0))  # nominal mount roll and pitch (yaw 0)
STANDOFF_RANGE_M = (5.0, 40.0)
PROUD_RANGE_M = (0.0, 0.6)  # from the wall's bulges to the target plate's nearest edge
FLUSH_PROBABILITY = 0.2  # a target resting on the wall (proud 0)
INCLINED_RANGE_RAD = (float(np.radians(30.0)), float(np.radians(60.0)))
THIRD_TARGET_PROBABILITY = 0.5
TARGET_HEIGHT_RANGE_M = (0.5, 6.0)  # the group's centre above the scanner
TARGET_HEIGHT_SPREAD_M = 0.3  # each target's own height about the group's
TARGET_GAP_RANGE_M = (2.0, 4.0)  # between neighbouring target centres along the wall
VERTICAL_SIZE_M = (1.23, 1.22)  # montreal's plates (width, height along the slope)
INCLINED_SIZE_M = (1.23, 0.76)
WALL_REFLECTIVITY_RANGE = (0.15, 0.35)
CONTRAST_RANGE = (1.0, 4.0)  # target reflectivity / wall reflectivity
NO_CONTRAST_PROBABILITY = 0.2
MAX_TARGET_REFLECTIVITY = 0.95
WALL_WAVINESS_RANGE_M = (0.0, 0.012)  # RMS
FLAT_WALL_PROBABILITY = 0.15
WALL_WAVELENGTH_M = (3.0, 8.0)
WALL_ROUGHNESS_M = 0.001
WALL_BEYOND_ALONG_RANGE_M = (2.0, 25.0)  # the wall beyond the outer targets' edges, each side
WALL_BEYOND_UP_RANGE_M = (0.6, 4.0)  # the wall below and above the targets' edges
LEVER_ARM_LIMIT_M = (1.0, 1.0, 2.0)  # |x|, |y|, |z| (body FRD)
MAX_BORESIGHT_RAD = float(np.radians(2.0))
SIGMA_POSITION_RANGE_M = (0.005, 0.03)
SIGMA_ATTITUDE_RANGE_RAD = (float(np.radians(0.002)), float(np.radians(0.01)))
TAU_RANGE_S = (5.0, 60.0)
HEADING_JITTER_RAD = float(np.radians(5.0))
#: a scanner that normalizes its intensity (no cos-incidence fall-off), as an independent simulator's
FLAT_INTENSITY_PROBABILITY = 0.5
#: site.yaml silent on the POS correlation time (the calibration estimates it)
TAU_UNSTATED_PROBABILITY = 0.5
#: piles before the wall beside the targets (tie cylinders), drawn from a stream of their own so
#: that a seed's other values are what they were before piles were drawn
PILES_PROBABILITY = 0.5
PILE_STREAM_KEY = 0x50494C45
PILE_COUNT_RANGE = (1, 4)
PILE_DIAMETER_RANGE_M = (0.3, 1.2)
PILE_OUT_RANGE_M = (1.0, 4.0)  # the axis from the wall's face
PILE_BEYOND_RANGE_M = (0.5, 4.0)  # along, the pile's edge beyond the outer targets' edges

# -- pass placement ---------------------------------------------------------------------------

PASS_LENGTH_M = 60.0
SPEED_MPS = 2.0
MAX_SAFE_WALL_DISTANCE_M = 5.0
MIN_SAFE_WALL_DISTANCE_M = 1.0
BASE_CAPTURE_MARGIN_M = 2.0  # montreal's: the vessel's roll, pitch and yaw
MIN_CAPTURE_MARGIN_M = 0.5

#: What the draw does not vary (montreal's site, scanner, motion and scanner noise).
FIXED_DOCUMENT: dict[str, Any] = {
    "reference": {"lat_deg": 45.5065, "lon_deg": -73.5518, "height_m": -24.5},
    "start_utc": "2019-07-09T14:00:00Z",
    "vessel": "sim-random",
    "scanner": {"profile_rate_hz": 200.0, "points_per_360": 5080, "point_rate_scale": 0.1},
    "motion": {
        "rate_hz": 50.0,
        "roll": {"amplitude_deg": 1.5, "period_s": 4.0},
        "pitch": {"amplitude_deg": 0.5, "period_s": 5.5},
        "heave": {"amplitude_m": 0.05, "period_s": 6.0},
        "yaw": {"amplitude_deg": 0.3, "period_s": 15.0},
        "turns": False,
        "pass_gap_s": 30.0,
    },
    "scanner_noise": {
        "sigma_range_m": 0.002,
        "sigma_range_per_m": 0.0,
        "beam_divergence_mrad": 0.5,
        "sigma_scan_angle_deg": 0.005,
    },
}


@dataclass(frozen=True)
class TargetDraw:
    """One target in the site frame (``along_m``, ``up_m``: its centre; ``proud_m``: from the
    wall's bulges to the plate's nearest edge, 0 = resting on the wall)."""

    name: str
    inclination_rad: float
    proud_m: float
    along_m: float
    up_m: float
    width_m: float
    height_m: float

    def to_dict(self) -> dict:
        return {
            "name": self.name,
            "inclination_deg": float(np.degrees(self.inclination_rad)),
            "proud_m": self.proud_m,
            "along_m": self.along_m,
            "up_m": self.up_m,
            "size_m": [self.width_m, self.height_m],
        }


@dataclass(frozen=True)
class PileDraw:
    """One pile in the site frame: its axis ``along_m`` along the wall and ``out_m`` from it."""

    name: str
    along_m: float
    out_m: float
    diameter_m: float

    def to_dict(self) -> dict:
        return {
            "name": self.name,
            "along_m": self.along_m,
            "out_m": self.out_m,
            "diameter_m": self.diameter_m,
        }


@dataclass(frozen=True)
class GeometryDraw:
    """One draw of the randomized scenario (SI units, radians)."""

    seed: int
    nominal_rad: np.ndarray  # (3,) roll, pitch, yaw (0) of the nominal mount
    wall_azimuth_rad: float
    standoff_m: float
    targets: tuple[TargetDraw, ...]
    wall_reflectivity: float
    target_reflectivity: float
    wall_waviness_m: float  # RMS
    wall_beyond_m: np.ndarray  # (4,) the wall beyond the targets: left, right, below, above
    lever_arm_m: np.ndarray  # (3,) body FRD
    boresight_rad: np.ndarray  # (3,) the true boresight, canonical
    sigma_position_m: float
    sigma_attitude_rad: float
    tau_position_s: float
    tau_attitude_s: float
    relative_headings_rad: tuple[float, ...]  # the six passes', relative to the wall
    intensity_follows_incidence: bool = True
    tau_in_site: bool = True
    piles: tuple[PileDraw, ...] = ()

    @property
    def contrast(self) -> float:
        """Target reflectivity over the wall's (1: no contrast)."""
        return self.target_reflectivity / self.wall_reflectivity

    def to_dict(self) -> dict:
        """For truth.json (degrees at the edge)."""
        return {
            "seed": self.seed,
            "nominal_deg": [float(x) for x in np.degrees(self.nominal_rad)],
            "wall_azimuth_deg": float(np.degrees(self.wall_azimuth_rad)),
            "standoff_m": self.standoff_m,
            "targets": [t.to_dict() for t in self.targets],
            "wall_reflectivity": self.wall_reflectivity,
            "target_reflectivity": self.target_reflectivity,
            "contrast": self.contrast,
            "wall_waviness_m": self.wall_waviness_m,
            "wall_beyond_m": [float(x) for x in self.wall_beyond_m],
            "lever_arm_m": [float(x) for x in self.lever_arm_m],
            "boresight_deg": [float(x) for x in np.degrees(self.boresight_rad)],
            "sigma_position_m": self.sigma_position_m,
            "sigma_attitude_deg": float(np.degrees(self.sigma_attitude_rad)),
            "tau_position_s": self.tau_position_s,
            "tau_attitude_s": self.tau_attitude_s,
            "relative_headings_deg": [float(np.degrees(h)) for h in self.relative_headings_rad],
            "intensity_follows_incidence": self.intensity_follows_incidence,
            "tau_in_site": self.tau_in_site,
            "piles": [p.to_dict() for p in self.piles],
        }


# -- the draw ---------------------------------------------------------------------------------


def draw_rng(seed: int) -> np.random.Generator:
    return np.random.default_rng([int(seed), DRAW_STREAM_KEY])


def _uniform(rng: np.random.Generator, bounds: tuple[float, float]) -> float:
    return float(rng.uniform(*bounds))


def _log_uniform(rng: np.random.Generator, bounds: tuple[float, float]) -> float:
    """Uniform in log (a scale: as likely 1 cm as 2 cm, 10 s as 20 s), clipped against rounding."""
    lo, hi = bounds
    return float(np.clip(np.exp(rng.uniform(np.log(lo), np.log(hi))), lo, hi))


def _symmetric(rng: np.random.Generator, limit, n: int | None = None):
    return rng.uniform(-1.0, 1.0, n) * np.asarray(limit, float)


def draw_targets(rng: np.random.Generator) -> tuple[TargetDraw, ...]:
    """Two targets (one vertical, one inclined) or three (the third either), in a random order
    along the wall, neighbours 2–4 m apart, the group centred on along 0."""
    inclinations = [float(np.pi / 2), _uniform(rng, INCLINED_RANGE_RAD)]
    if rng.uniform() < THIRD_TARGET_PROBABILITY:
        inclinations.append(float(np.pi / 2) if rng.uniform() < 0.5 else _uniform(rng, INCLINED_RANGE_RAD))
    order = rng.permutation(len(inclinations))
    gaps = rng.uniform(*TARGET_GAP_RANGE_M, len(inclinations) - 1)
    along = np.concatenate([[0.0], np.cumsum(gaps)])
    along -= along.mean()
    height_m = _uniform(rng, TARGET_HEIGHT_RANGE_M)
    out = []
    for k, i in enumerate(order):
        proud = 0.0 if rng.uniform() < FLUSH_PROBABILITY else _uniform(rng, PROUD_RANGE_M)
        vertical = inclinations[i] == np.pi / 2
        width, height = VERTICAL_SIZE_M if vertical else INCLINED_SIZE_M
        out.append(
            TargetDraw(
                name=f"T{i + 1}",
                inclination_rad=inclinations[i],
                proud_m=proud,
                along_m=float(along[k]),
                up_m=height_m + float(_symmetric(rng, TARGET_HEIGHT_SPREAD_M)),
                width_m=width,
                height_m=height,
            )
        )
    return tuple(sorted(out, key=lambda t: t.name))


def _reflectivities(rng: np.random.Generator) -> tuple[float, float]:
    """(wall, target): no contrast at times, else a target up to 4× brighter than the wall."""
    wall = _uniform(rng, WALL_REFLECTIVITY_RANGE)
    contrast = 1.0 if rng.uniform() < NO_CONTRAST_PROBABILITY else _uniform(rng, CONTRAST_RANGE)
    return wall, min(MAX_TARGET_REFLECTIVITY, wall * contrast)


def draw_geometry(seed: int) -> GeometryDraw:
    """The geometry of seed ``seed`` (the same seed, the same draw)."""
    rng = draw_rng(seed)
    roll, pitch = _symmetric(rng, MAX_NOMINAL_TILT_RAD, 2)
    wall_azimuth = float(rng.uniform(0.0, 2.0 * np.pi))
    standoff = _uniform(rng, STANDOFF_RANGE_M)
    targets = draw_targets(rng)
    wall_refl, target_refl = _reflectivities(rng)
    waviness = 0.0 if rng.uniform() < FLAT_WALL_PROBABILITY else _uniform(rng, WALL_WAVINESS_RANGE_M)
    lever_arm = _symmetric(rng, LEVER_ARM_LIMIT_M, 3)
    boresight = _symmetric(rng, MAX_BORESIGHT_RAD, 3)
    sigma_p = _log_uniform(rng, SIGMA_POSITION_RANGE_M)
    sigma_a = _log_uniform(rng, SIGMA_ATTITUDE_RANGE_RAD)
    tau_p, tau_a = _log_uniform(rng, TAU_RANGE_S), _log_uniform(rng, TAU_RANGE_S)
    jitter = _symmetric(rng, HEADING_JITTER_RAD, len(SIX_FOLD_RELATIVE_HEADINGS_DEG))
    headings = np.radians(SIX_FOLD_RELATIVE_HEADINGS_DEG) + jitter
    # drawn last: a seed's other values do not depend on how the wall's size is drawn
    beyond = np.concatenate(
        [rng.uniform(*WALL_BEYOND_ALONG_RANGE_M, 2), rng.uniform(*WALL_BEYOND_UP_RANGE_M, 2)]
    )
    flat_intensity, tau_unstated = rng.uniform(size=2) < (
        FLAT_INTENSITY_PROBABILITY,
        TAU_UNSTATED_PROBABILITY,
    )
    return GeometryDraw(
        seed=int(seed),
        nominal_rad=np.array([roll, pitch, 0.0]),
        wall_azimuth_rad=wall_azimuth,
        standoff_m=standoff,
        targets=targets,
        wall_reflectivity=wall_refl,
        target_reflectivity=target_refl,
        wall_waviness_m=waviness,
        wall_beyond_m=beyond,
        lever_arm_m=lever_arm,
        boresight_rad=boresight,
        sigma_position_m=sigma_p,
        sigma_attitude_rad=sigma_a,
        tau_position_s=tau_p,
        tau_attitude_s=tau_a,
        relative_headings_rad=tuple(float(h) for h in headings),
        intensity_follows_incidence=not bool(flat_intensity),
        tau_in_site=not bool(tau_unstated),
        piles=draw_piles(seed, targets),
    )


def draw_piles(seed: int, targets: tuple[TargetDraw, ...]) -> tuple[PileDraw, ...]:
    """None, or one to four piles of 0.3–1.2 m 1–4 m before the wall, each beside the target
    group (beyond its outer edges, either side: they do not hide the targets from a
    perpendicular pass) and :data:`PILE_CLEARANCE_M` clear of the others."""
    rng = np.random.default_rng([int(seed), DRAW_STREAM_KEY, PILE_STREAM_KEY])
    if rng.uniform() >= PILES_PROBABILITY:
        return ()
    lo, hi = targets_along_m(targets)
    piles: list[PileDraw] = []
    for _ in range(int(rng.integers(PILE_COUNT_RANGE[0], PILE_COUNT_RANGE[1] + 1))):
        diameter = _uniform(rng, PILE_DIAMETER_RANGE_M)
        beyond = _uniform(rng, PILE_BEYOND_RANGE_M) + diameter / 2
        along = hi + beyond if rng.uniform() < 0.5 else lo - beyond
        pile = PileDraw(f"P{len(piles) + 1}", float(along), _uniform(rng, PILE_OUT_RANGE_M), diameter)
        if all(_clear(pile, other) for other in piles):
            piles.append(pile)
    return tuple(piles)


def targets_along_m(targets: tuple[TargetDraw, ...]) -> tuple[float, float]:
    """The target group's extent along the wall: its outer edges."""
    return min(t.along_m - t.width_m / 2 for t in targets), max(t.along_m + t.width_m / 2 for t in targets)


#: the least gap between two piles' surfaces (a drawn pile closer to an earlier one is dropped)
PILE_CLEARANCE_M = 0.5


def _clear(a: PileDraw, b: PileDraw) -> bool:
    gap = float(np.hypot(a.along_m - b.along_m, a.out_m - b.out_m)) - (a.diameter_m + b.diameter_m) / 2
    return gap >= PILE_CLEARANCE_M


# -- the scenario document --------------------------------------------------------------------


def wall_extent_m(g: GeometryDraw) -> tuple[float, float, float, float]:
    """(along, up, width, height) of the wall: the targets' extent and the drawn wall beyond."""
    along = np.array([[t.along_m - t.width_m / 2, t.along_m + t.width_m / 2] for t in g.targets])
    up = np.array([[t.up_m - t.height_m / 2, t.up_m + t.height_m / 2] for t in g.targets])
    left, right, below, above = (float(x) for x in g.wall_beyond_m)
    a0, a1 = along.min() - left, along.max() + right
    u0, u1 = up.min() - below, up.max() + above
    return float((a0 + a1) / 2), float((u0 + u1) / 2), float(a1 - a0), float(u1 - u0)


def wall_shape(g: GeometryDraw) -> SurfaceShape:
    return SurfaceShape(g.wall_waviness_m, WALL_WAVELENGTH_M, WALL_ROUGHNESS_M)


def wall_clearance_m(g: GeometryDraw) -> float:
    """How far the wall's bulges reach out of its mean plane (a target plate rests on them)."""
    _, _, width, height = wall_extent_m(g)
    field = wall_shape(g).field("quay_wall", width, height)
    return 0.0 if field is None else float(field.bound_m)


def target_out_m(t: TargetDraw, clearance_m: float) -> float:
    """The centre's distance out from the wall's mean plane: the plate's top edge (nearest the
    wall, as montreal's T2 leans) ``proud_m`` beyond the wall's bulges."""
    return clearance_m + t.proud_m + t.height_m * float(np.cos(t.inclination_rad)) / 2


def wanted_capture_margin_m(g: GeometryDraw) -> float:
    """Montreal's margin, plus how far a scan plane tilted by the mount's pitch meets the
    targets ahead of or behind the scanner: the height above it times tan |pitch|; with piles,
    at least what reaches the farthest one's far side."""
    reach_up = max(abs(t.up_m) + t.height_m / 2 for t in g.targets)
    margin = BASE_CAPTURE_MARGIN_M + reach_up * float(np.tan(abs(g.nominal_rad[1])))
    if not g.piles:
        return margin
    lo, hi = targets_along_m(g.targets)
    beyond = max(max(p.along_m - hi, lo - p.along_m) + p.diameter_m / 2 for p in g.piles)
    return max(margin, beyond + 1.0)


def safe_wall_distance_m(standoff_m: float) -> float:
    """Half the standoff, at most 5 m: a short standoff still has room for the oblique passes."""
    return min(MAX_SAFE_WALL_DISTANCE_M, standoff_m / 2)


def _target_entry(t: TargetDraw, clearance_m: float, reflectivity: float) -> dict:
    return {
        "name": t.name,
        "along_m": t.along_m,
        "out_m": target_out_m(t, clearance_m),
        "up_m": t.up_m,
        "size_m": [t.width_m, t.height_m],
        "inclination_deg": float(np.degrees(t.inclination_rad)),
        "reflectivity": reflectivity,
    }


def _wall_entry(g: GeometryDraw) -> dict:
    along, up, width, height = wall_extent_m(g)
    return {
        "name": "quay_wall",
        "kind": "wall",
        "along_m": along,
        "out_m": 0.0,
        "up_m": up,
        "size_m": [width, height],
        "inclination_deg": 90.0,
        "reflectivity": g.wall_reflectivity,
        "waviness": {"amplitude_m": g.wall_waviness_m, "wavelength_m": list(WALL_WAVELENGTH_M)},
        "roughness_m": WALL_ROUGHNESS_M,
    }


def _pile_entries(g: GeometryDraw) -> list[dict]:
    """The piles, from the wall's foot to its top."""
    _, up, _, height = wall_extent_m(g)
    return [
        {
            **p.to_dict(),
            "bottom_up_m": up - height / 2,
            "top_up_m": up + height / 2,
            "reflectivity": g.wall_reflectivity,
        }
        for p in g.piles
    ]


def _noise_entry(g: GeometryDraw) -> dict:
    sigma_a_deg = float(np.degrees(g.sigma_attitude_rad))
    return {
        "scanner": {
            **FIXED_DOCUMENT["scanner_noise"],
            "intensity_follows_incidence": g.intensity_follows_incidence,
        },
        "pos": {
            "model": "gauss_markov",
            "tau_in_site": g.tau_in_site,
            "sigma_position_m": [g.sigma_position_m] * 3,
            "sigma_attitude_deg": [sigma_a_deg] * 3,
            "tau_position_s": [g.tau_position_s] * 3,
            "tau_attitude_s": [g.tau_attitude_s] * 3,
        },
    }


def scenario_document(g: GeometryDraw) -> dict:
    """The draw as a scenario document (the keys of ``scenarios/montreal.yaml``)."""
    clearance = wall_clearance_m(g)
    fixed = FIXED_DOCUMENT
    return {
        "name": RANDOM_SCENARIO,
        "description": f"randomized calibration geometry, seed {g.seed} (calib.sim.randomdraw)",
        "reference": dict(fixed["reference"]),
        "start_utc": fixed["start_utc"],
        "vessel": fixed["vessel"],
        "site": {
            "wall_azimuth_deg": float(np.degrees(g.wall_azimuth_rad)),
            "standoff_m": g.standoff_m,
            "passes": [
                {"id": i + 1, "relative_heading_deg": float(np.degrees(h))}
                for i, h in enumerate(g.relative_headings_rad)
            ],
            "pass_length_m": PASS_LENGTH_M,
            "speed_mps": SPEED_MPS,
            "safe_wall_distance_m": safe_wall_distance_m(g.standoff_m),
            "capture_margin_m": wanted_capture_margin_m(g),
        },
        "scene": {
            "targets": [_target_entry(t, clearance, g.target_reflectivity) for t in g.targets],
            "surfaces": [_wall_entry(g)],
            **({"piles": _pile_entries(g)} if g.piles else {}),
        },
        "mount": {
            "lever_arm_m": [float(x) for x in g.lever_arm_m],
            "nominal_deg": [float(x) for x in np.degrees(g.nominal_rad)],
            "boresight_apriori_deg": [0.0, 0.0, 0.0],
        },
        "truth": {"boresight_deg": [float(x) for x in np.degrees(g.boresight_rad)]},
        "scanner": dict(fixed["scanner"]),
        "motion": {k: v if not isinstance(v, dict) else dict(v) for k, v in fixed["motion"].items()},
        "noise": _noise_entry(g),
    }


# -- the scenario ----------------------------------------------------------------------------


def _plans(sc: Scenario) -> bool:
    try:
        sc.pass_plan()
    except PassPlanError:
        return False
    return True


def fit_passes(sc: Scenario) -> Scenario:
    """``sc`` with passes that can be sailed: where an oblique pass toward the wall must turn
    away before the end of its capture window, the margin shrinks (down to 0.5 m: the targets
    are then only partly swept in that pass), then the safe wall distance (down to 1 m). As
    given when nothing plans (simulating then says why)."""
    for safe in dict.fromkeys(
        [sc.safe_wall_distance_m, min(sc.safe_wall_distance_m, MIN_SAFE_WALL_DISTANCE_M)]
    ):
        margin = sc.capture_margin_m
        while True:
            candidate = replace(sc, safe_wall_distance_m=safe, capture_margin_m=margin)
            if _plans(candidate):
                return candidate
            if margin <= MIN_CAPTURE_MARGIN_M:
                break
            margin = max(MIN_CAPTURE_MARGIN_M, 0.75 * margin)
    return sc


def random_scenario(seed: int, overrides: Sequence[str] | Mapping[str, Any] = ()) -> Scenario:
    """The randomized scenario of ``seed``, ``overrides`` (dotted ``key=value``, as for a
    scenario file) applied to its document, its passes fitted; ``draw`` records the draw."""
    g = draw_geometry(seed)
    doc = scenario_document(g)
    sc = parse_scenario(yaml.safe_dump(doc, sort_keys=False), f"random-seed-{seed}.yaml", overrides)
    fitted = fit_passes(sc)
    record = {
        **g.to_dict(),
        "placement": {
            "pass_length_m": PASS_LENGTH_M,
            "wanted_capture_margin_m": sc.capture_margin_m,
            "capture_margin_m": fitted.capture_margin_m,
            "safe_wall_distance_m": fitted.safe_wall_distance_m,
            "wall_clearance_m": wall_clearance_m(g),
        },
        "scenario_document": doc,
    }
    return replace(fitted, draw=record)
