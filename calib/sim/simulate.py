"""The MLS simulator (the thesis's simulator, Chapter 3, generalised): a scenario and a seed in,
a calibration bundle's content and its truth out.

    scenario ──► site (a-priori mount), scene of rectangles and cylinders, pass plan
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
on its rectangle, on the displaced surface of a wavy or rough one, or on its cylinder):

    ρ_reported = ρ_true − δρ,    α_beam = α_reported + δα,    pose sampled at t_reported + Δt.

The profiles are cast by :mod:`calib.sim.scanning`, and :func:`calib.sim.result.observe` turns
the returns into observations and truth. A scenario with a ``production`` section is a
production survey instead (:func:`calib.sim.production.simulate_production`): :func:`simulate`
hands it over.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from calib.sim.motion import sail
from calib.sim.production import sail_production, scenario_of
from calib.sim.randomdraw import RANDOM_SCENARIO, random_scenario
from calib.sim.result import SimResult, SimulationError, observe
from calib.sim.scanning import ScanReturns, scan, scan_batches
from calib.sim.scenario import Scenario
from calib.sim.scenariofile import override_strings

__all__ = ["ScanReturns", "SimResult", "SimulationError", "scan", "simulate"]


def simulate(
    scenario: Scenario | str | Path,
    seed: int = 0,
    *,
    overrides: Sequence[str] | Mapping[str, Any] = (),
    progress: Callable[[int, int], None] | None = None,
) -> SimResult:
    """Simulate a scenario (a :class:`Scenario`, or a shipped name / YAML path loaded with
    ``overrides``; ``"random"``: the geometry :mod:`calib.sim.randomdraw` draws from ``seed``,
    with ``overrides`` on top). ``progress(done, total)`` is called after each pass (each line
    of a production survey)."""
    if isinstance(scenario, str) and scenario == RANDOM_SCENARIO:
        sc, applied = random_scenario(seed, overrides), override_strings(overrides)
    else:
        sc, applied = scenario_of(scenario, overrides)
    if sc.production is not None:  # a production survey of the harbour scene
        return sail_production(sc, sc.production, seed, applied, progress)
    rng_motion, rng_pos, rng_scan, rng_point = (
        np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(4)
    )
    scene = sc.scene()
    plan = sc.pass_plan()
    run = sail(plan, sc.motion, sc.start_gps_s, sc.reference, rng_motion)
    traj = run.trajectory
    mount = sc.truth.true_mount(sc.mount)

    parts, pass_ids = [], []
    guard = abs(mount.time_offset_s) + 1e-3
    for i, p in enumerate(plan.passes):
        t0, t1 = run.capture_times[p.id]
        l0, l1 = run.line_times[p.id]
        for part in scan_batches(sc.scanner, scene, traj, mount, max(t0, l0 + guard), min(t1, l1 - guard)):
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
    return observe(
        sc,
        seed,
        applied,
        scene,
        plan,
        run,
        mount,
        ret,
        np.concatenate(pass_ids),
        (rng_pos, rng_scan, rng_point),
    )
