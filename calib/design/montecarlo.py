"""Monte Carlo check of a prediction: a scenario simulated with its noise and adjusted, seed by
seed, beside the covariance predicted from its noise-free twin.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from calib.boresight.adjust import adjust
from calib.boresight.observations import AdjustOptions
from calib.design.prediction import (
    UNOBSERVABLE_RAD,
    DesignError,
    Sigmas,
    observations,
    predict,
    prepare,
    target_planes,
)
from calib.design.scenes import design_scenario
from calib.design.study import run_tasks
from calib.sim.scenario import Scenario
from calib.sim.simulate import simulate


def _mc_task(scenario: Scenario, seed: int, estimates: tuple[tuple[str, ...], ...]) -> np.ndarray:
    sim = simulate(scenario, seed)
    obs = observations(sim, Sigmas.of_scenario(scenario), noisy=True)
    out = []
    for est in estimates:
        res = adjust(
            obs,
            sim.site.mount,
            target_planes(sim),
            AdjustOptions(estimate=est, outliers="none", jackknife=False, max_sigma_rad=UNOBSERVABLE_RAD),
        )
        out.append(res.boresight_rad - sim.mount_true.boresight_rad)
    return np.array(out)


def empirical_errors(
    scenario: Scenario,
    seeds: Sequence[int],
    estimates: Sequence[tuple[str, ...]] = ((),),
    jobs: int = 1,
    progress=None,
) -> dict[tuple[str, ...], np.ndarray]:
    """Boresight errors (estimate − truth, rad; (len(seeds), 3) per adjustment option) of the
    scenario simulated with its noise, one simulation per seed adjusted with each of
    ``estimates`` (``AdjustOptions.estimate`` values)."""
    est = tuple(tuple(e) for e in estimates)
    res = np.array(run_tasks([(_mc_task, (scenario, int(s), est)) for s in seeds], jobs, progress))
    return {e: res[:, k] for k, e in enumerate(est)}


def predicted_covariance(scenario: Scenario, model: str, seed: int = 0) -> np.ndarray:
    """Predicted boresight covariance (rad²) of a noisy scenario under ``model`` (see
    :func:`predict`), from its noise-free twin with the same seed (same waves)."""
    sigmas = Sigmas.of_scenario(scenario)
    sim, obs, planes = prepare(design_scenario(scenario, scenario.surfaces), sigmas, seed)
    pred = predict(obs, sim.mount_true, planes, sigmas.correlation_time_s, (model,))
    if not pred.observable:
        raise DesignError(f"scenario {scenario.name!r}: the boresight is not observable")
    return pred.covariances[model]
