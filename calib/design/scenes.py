"""Design scenes: targets placed on a base scenario's site, and the base scenario with only those
targets in its scene.

Design scenes hold only the targets (no quay wall or ground: they never enter the adjustment),
record every scan angle (the operator sets the profiler's windows to include the targets) and
carry no noise (the prediction assumes the sigmas). Inclination as in docs/architecture.md §3: angle to the
horizontal, 90° vertical; a negative inclination tilts the plane the other way (the thesis's
terrestrial sweep, whose own angle is measured from the vertical:
:func:`calib.design.criteria.thesis_tilt_deg`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from calib.design.prediction import DesignError
from calib.sim.motion import Wave
from calib.sim.noise import PosNoise, ScannerNoise
from calib.sim.scenario import Scenario, Surface

_CLEARANCE_M = 0.03  # targets stand this far in front of the wall line


def internal_inclination(inclination_rad: float) -> float:
    """A negative inclination (tilted the other way) as the same plane with its normal flipped
    toward the water: π − |i|, so that the passes stay on the water side."""
    return float(inclination_rad if inclination_rad >= 0 else np.pi + inclination_rad)


def surface_inclination_deg(s: Surface) -> float:
    """A surface's inclination (docs/architecture.md §3; degrees, negative when tilted the other way)."""
    d = float(np.degrees(s.inclination_rad))
    return d - 180.0 if d > 90.0 + 1e-9 else d


def _ground_top(base: Scenario) -> float | None:
    ups = [s.up_m for s in base.surfaces if s.kind == "ground"]
    return max(ups) if ups else None


def ground_based(base: Scenario) -> bool:
    return _ground_top(base) is not None


def scenario_targets(base: Scenario) -> list[Surface]:
    """The targets of ``base``'s scene (at least one)."""
    out = [s for s in base.surfaces if s.kind == "target"]
    if not out:
        raise DesignError(f"scenario {base.name!r} has no target")
    return out


def target(
    base: Scenario,
    name: str,
    inclination_rad: float,
    width_m: float,
    height_m: float,
    along_m: float = 0.0,
    raise_m: float = 0.0,
    setback_m: float = 0.0,
) -> Surface:
    """A target for a design scene of ``base``: on a ground-based site (one with a ground
    surface) it stands on the ground, else its centre is at the mean height of ``base``'s
    targets; ``raise_m`` lifts it, ``setback_m`` moves it back from the wall line (away from
    the passes)."""
    i = internal_inclination(inclination_rad)
    ground = _ground_top(base)
    if ground is not None:
        up = ground + 0.5 * height_m * abs(np.sin(i)) + 0.05
    else:
        up = float(np.mean([s.up_m for s in scenario_targets(base)]))
    out = 0.5 * height_m * abs(np.cos(i)) + _CLEARANCE_M - setback_m
    return Surface(
        name,
        "target",
        float(along_m),
        float(out),
        float(up + raise_m),
        float(width_m),
        float(height_m),
        float(i),
        0.0,
        0.9,
    )


def square_target(base, name, incl_deg, size, along=0.0, raise_m=0.0, setback=0.0) -> Surface:
    """A square :func:`target` of side ``size``, its inclination in degrees."""
    return target(base, name, np.radians(incl_deg), size, size, along, raise_m, setback)


def design_scenario(
    base: Scenario,
    targets: Sequence[Surface],
    *,
    standoff_m: float | None = None,
    level: bool = False,
    truth=None,
) -> Scenario:
    """``base`` with only ``targets`` in the scene, no noise, every scan angle recorded;
    ``level`` stills the waves (the thesis's criteria isolate the error); ``truth`` replaces
    the injected errors."""
    motion = base.motion
    if level:
        motion = replace(motion, roll=Wave(), pitch=Wave(), heave=Wave(), yaw=Wave())
    return replace(
        base,
        surfaces=tuple(targets),
        piles=(),
        scanner_noise=ScannerNoise(),
        pos_noise=PosNoise("none"),
        motion=motion,
        scanner=replace(base.scanner, angular_windows_rad=()),
        standoff_m=base.standoff_m if standoff_m is None else float(standoff_m),
        truth=base.truth if truth is None else truth,
    )


def site_scenario(base: Scenario, targets: Sequence[Surface]) -> Scenario:
    """``base`` (its noise, motion, passes) with only ``targets`` in the scene and every scan
    angle recorded: a planned site to simulate with noise."""
    return replace(
        base, surfaces=tuple(targets), piles=(), scanner=replace(base.scanner, angular_windows_rad=())
    )
