"""Monte Carlo check of a prediction: a scenario simulated with its noise and adjusted, seed by
seed, beside the covariance predicted from its noise-free twin.

The adjustments are the calibration's estimators (``mls calib run --estimator``): ``gls`` (the
default: the POS errors as Gauss–Markov processes with the scenario's correlation times),
``thesis`` (white weights) and ``pass_offsets`` (white weights and per-pass trajectory offsets).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from calib.boresight.adjust import adjust
from calib.boresight.errormodel import ErrorModel
from calib.boresight.observations import AdjustOptions
from calib.design.prediction import (
    ESTIMATOR_MODEL,
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


def adjust_options(estimator: str, sigmas: Sigmas) -> AdjustOptions:
    """The adjustment of ``estimator`` (of :data:`calib.design.prediction.ESTIMATOR_MODEL`)
    with the Gauss–Markov correlation times of ``sigmas``, no outlier search, no jackknife, and
    the design's observability limit."""
    if estimator not in ESTIMATOR_MODEL:
        raise DesignError(f"unknown estimator {estimator!r}; expected one of {', '.join(ESTIMATOR_MODEL)}")
    return AdjustOptions(
        estimate=("pass_offsets",) if estimator == "pass_offsets" else (),
        estimator="gls" if estimator == "gls" else "thesis",
        error_model=ErrorModel("gauss_markov", tuple(sigmas.correlation_time_s)),
        outliers="none",
        jackknife=False,
        max_sigma_rad=UNOBSERVABLE_RAD,
    )


def _mc_task(scenario: Scenario, seed: int, estimators: tuple[str, ...]) -> np.ndarray:
    sim = simulate(scenario, seed)
    sigmas = Sigmas.of_scenario(scenario)
    obs = observations(sim, sigmas, noisy=True)
    out = []
    for est in estimators:
        res = adjust(obs, sim.site.mount, target_planes(sim), adjust_options(est, sigmas))
        out.append(res.boresight_rad - sim.mount_true.boresight_rad)
    return np.array(out)


def empirical_errors(
    scenario: Scenario,
    seeds: Sequence[int],
    estimators: Sequence[str] = ("gls",),
    jobs: int = 1,
    progress=None,
) -> dict[str, np.ndarray]:
    """Boresight errors (estimate − truth, rad; (len(seeds), 3) per estimator) of the scenario
    simulated with its noise, one simulation per seed adjusted with each of ``estimators``
    (``gls``, ``thesis``, ``pass_offsets``: :func:`adjust_options`)."""
    est = tuple(estimators)
    for e in est:
        adjust_options(e, Sigmas.of_scenario(scenario))  # an unknown name: before simulating
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
