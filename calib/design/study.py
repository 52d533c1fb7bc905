"""Site design study (docs/architecture.md §7 "Design study"; thesis Chapters 3–4 as a tool): which targets,
inclinations, sizes and passes observe the boresight best, before anything is installed — the
study run from its specification to its rows and recommendation.

Two instruments, both driven by the simulator (:func:`calib.sim.simulate.simulate`):

* **Visibility criteria** (thesis §3.4.4, Appendix C; :mod:`calib.design.criteria`): one target per
  inclination, one systematic error injected at the thesis's magnitude, a level vessel and no
  noise; each pass's copy of the target, georeferenced with the error-free mount, is scored
  with Type I and Type II against the true plane.
* **Predicted σ of the boresight** (thesis §4.4.1.2, Fig. 4.12; :mod:`calib.design.prediction`)
  of every configuration of the sweeps (:mod:`calib.design.layouts`), in design scenes
  (:mod:`calib.design.scenes`).

One simulation serves every pass subset of a configuration; configurations run in parallel
processes (``jobs``), each with the same seed, so results do not depend on the number of
processes. The tables, figures and summary are :mod:`calib.design.summary`.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np

from calib.design.criteria import criteria_rows, injected, summarize
from calib.design.layouts import Constraint, Layout, StudySpec, default_spec, layouts
from calib.design.prediction import (
    ANGLES,
    DEFAULT_ESTIMATOR,
    ESTIMATOR_MODEL,
    MODELS,
    REALISTIC,
    DesignError,
    Prediction,
    Sigmas,
    predict,
    prepare,
    scan_angle_roll_correlation,
    select_passes,
)
from calib.design.scenes import design_scenario, scenario_targets, square_target, surface_inclination_deg
from calib.design.yawlines import yaw_lines_or_why
from calib.sim.scenario import Scenario
from calib.sim.scenariofile import load_scenario
from calib.sim.simulate import SimulationError, simulate
from calib.survey.passplan import PassPlanError

# ---------------------------------------------------------------------------------------------
# Tasks (run in worker processes)
# ---------------------------------------------------------------------------------------------

SIGMA_COLUMNS = (
    [
        "scenario",
        "group",
        "label",
        "n_targets",
        "inclinations_deg",
        "sizes_m",
        "standoff_m",
        "height_m",
        "spread_m",
        "stagger_m",
        "setback_m",
        "passes",
        "headings_deg",
        "n_points",
        "observable",
        "correlation_time_s",
    ]
    + [f"sigma_{m}_{a}_deg" for m in MODELS for a in ANGLES + ("total",)]
    + ["realistic_total_deg", "estimator"]
    + [
        f"corr_{m}_{a}_{b}"
        for m in ("white", "realistic")
        for a, b in (("roll", "pitch"), ("roll", "yaw"), ("pitch", "yaw"))
    ]
    + ["note"]
)


def sigma_row(
    scenario: str,
    layout: Layout,
    pred: Prediction | None,
    subset: Sequence[int],
    headings: dict,
    correlation_time_s: float | Sequence[float],
    note: str = "",
) -> dict:
    """One line of ``sigma.csv``."""
    tg = layout.targets
    row = {
        "scenario": scenario,
        "group": layout.group,
        "label": layout.label,
        "n_targets": len(tg),
        "inclinations_deg": tuple(round(surface_inclination_deg(s), 6) for s in tg),
        "sizes_m": tuple((s.width_m, s.height_m) for s in tg),
        "standoff_m": layout.standoff_m,
        "height_m": layout.params.get("height_m", float(np.mean([s.up_m for s in tg]))),
        "spread_m": layout.params.get("spread_m", float(np.ptp([s.along_m for s in tg]))),
        "stagger_m": layout.params.get("stagger_m", float(np.ptp([s.up_m for s in tg]))),
        "setback_m": layout.params.get("setback_m", 0.0),
        "passes": tuple(int(p) for p in subset),
        "headings_deg": tuple(round(headings.get(p, float("nan")), 3) for p in subset),
        "n_points": 0 if pred is None else pred.n_points,
        "observable": bool(pred is not None and pred.observable),
        "correlation_time_s": tuple(float(x) for x in np.atleast_1d(correlation_time_s)),
        "note": note,
    }
    for m in MODELS:
        s = np.full(3, np.inf) if pred is None or not pred.observable else pred.sigma_deg(m)
        for a, v in zip(ANGLES, s, strict=False):
            row[f"sigma_{m}_{a}_deg"] = float(v)
        row[f"sigma_{m}_total_deg"] = float(np.sqrt(np.sum(s**2)))
    usable = pred if pred is not None and pred.observable else None  # a prediction with σ
    real = usable.realistic_model if usable is not None else ESTIMATOR_MODEL[DEFAULT_ESTIMATOR]
    row["realistic_total_deg"] = row[f"sigma_{real}_total_deg"]
    # the calibration's --estimator the realistic σ is for (gls, thesis or pass_offsets)
    row["estimator"] = usable.estimator if usable is not None else ""
    for name, m in (("white", "white"), ("realistic", real)):
        c = usable.correlation(m) if usable is not None else np.full((3, 3), np.nan)
        for (a, b), v in zip(
            (("roll", "pitch"), ("roll", "yaw"), ("pitch", "yaw")), (c[0, 1], c[0, 2], c[1, 2]), strict=False
        ):
            row[f"corr_{name}_{a}_{b}"] = float(v)
    return row


def headings_deg(base: Scenario) -> dict:
    """Relative heading of each pass of ``base`` in degrees, [0°, 360°)."""
    return {p.id: float(np.degrees(p.relative_heading_rad)) % 360.0 for p in base.passes}


#: The recommendation's search predicts only these: white, GLS (the realistic σ it minimizes)
#: and the thesis adjustments for comparison (the winner gets every model).
_SEARCH_MODELS = ("white",) + REALISTIC


def _sigma_task(
    base: Scenario, layout: Layout, sigmas: Sigmas, seed: int, models: Sequence[str] = MODELS
) -> list[dict]:
    sc = design_scenario(base, layout.targets, standoff_m=layout.standoff_m)
    headings, tau = headings_deg(base), sigmas.correlation_time_s
    try:
        sim, obs, planes = prepare(sc, sigmas, seed)
    except (PassPlanError, SimulationError, DesignError) as e:
        return [sigma_row(base.name, layout, None, s, headings, tau, str(e)) for s in layout.pass_subsets]
    rows = []
    for subset in layout.pass_subsets:
        o, p = select_passes(obs, planes, subset)
        rows.append(
            sigma_row(base.name, layout, predict(o, sim.mount_true, p, tau, models), subset, headings, tau)
        )
    return rows


def _criteria_task(
    base: Scenario, error: str, magnitude: float, inclination_deg: float, size_m: float, seed: int
) -> list[dict]:
    """One target at one inclination, one error injected, a level vessel, no noise."""
    tg = square_target(base, "P", inclination_deg, size_m)
    sc = design_scenario(base, [tg], level=True, truth=injected(error, magnitude, base.mount.boresight_rad))
    return criteria_rows(simulate(sc, seed), error, magnitude, inclination_deg)


def run_tasks(
    tasks: list[tuple[Callable, tuple]], jobs: int, progress: Callable[[int, int], None] | None
) -> list:
    """Run ``func(*args)`` for every task, in ``jobs`` processes; results in task order."""
    n = len(tasks)
    out: list = [None] * n
    if jobs <= 1 or n <= 1:
        for i, (f, args) in enumerate(tasks):
            out[i] = f(*args)
            if progress is not None:
                progress(i + 1, n)
        return out
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor, as_completed

    # fork: workers inherit the imported modules and need no ``__main__`` guard in the caller
    methods = multiprocessing.get_all_start_methods()
    ctx = multiprocessing.get_context("fork" if "fork" in methods else None)
    with ProcessPoolExecutor(max_workers=jobs, mp_context=ctx) as ex:
        futures = {ex.submit(f, *args): i for i, (f, args) in enumerate(tasks)}
        for done, fut in enumerate(as_completed(futures), start=1):
            out[futures[fut]] = fut.result()
            if progress is not None:
                progress(done, n)
    return out


# ---------------------------------------------------------------------------------------------
# The study
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Recommendation:
    """The best layout under the constraint, and the scenario's own site beside it."""

    constraint: Constraint
    layout: Layout
    row: dict  # its line of sigma.csv
    baseline_row: dict | None  # the scenario's own targets on the same passes

    @property
    def estimator_name(self) -> str:
        """The calibration's estimator to use (``mls calib run --estimator``): ``gls`` unless the
        prediction was made without it."""
        return self.row["estimator"]

    @property
    def estimator(self) -> tuple[str, ...]:
        """The adjustment's extra unknowns to use (``AdjustOptions.estimate``): per-pass offsets
        with the ``pass_offsets`` estimator, none otherwise (GLS estimates the POS errors
        itself)."""
        return ("pass_offsets",) if self.row["estimator"] == "pass_offsets" else ()


def recommend(
    rows: Sequence[dict],
    layouts_: Sequence[Layout],
    constraint: Constraint,
    baseline_rows: Sequence[dict] = (),
) -> Recommendation:
    """The ``layout`` row with the smallest realistic σ (the GLS estimator's; ties: the smaller
    white σ)."""
    cands = [
        (r, lay) for r, lay in zip(rows, layouts_, strict=False) if r["group"] == "layout" and r["observable"]
    ]
    if not cands:
        raise DesignError(
            "no observable layout satisfies the constraint "
            f"({constraint.n_targets} targets ≤ {constraint.max_size_m:g} m, passes "
            f"{', '.join(map(str, constraint.passes))})"
        )
    row, lay = min(cands, key=lambda c: (c[0]["realistic_total_deg"], c[0]["sigma_white_total_deg"]))
    base = [r for r in baseline_rows if tuple(sorted(r["passes"])) == tuple(sorted(constraint.passes))]
    return Recommendation(constraint, lay, row, base[0] if base else None)


@dataclass
class StudyResult:
    scenario: Scenario
    spec: StudySpec
    sigmas: Sigmas
    criteria: list[dict]  # per error × inclination × pass
    visibility: list[dict]  # per error × inclination
    sigma: list[dict]  # per configuration × pass subset
    layouts: list[Layout]  # sigma[i] belongs to layouts[layout_of_row[i]]
    layout_of_row: list[int]
    roll_scan_correlation: float  # |ρ| at the scenario's own site
    recommendation: Recommendation | None
    runtime_s: float
    yaw_lines: list[dict]  # per line set × feature set (calib.design.yawlines)
    yaw_lines_note: str = ""  # why there are none

    def rows(self, group: str) -> list[dict]:
        return [r for r in self.sigma if r["group"] == group]


def run_study(
    scenario: Scenario | str,
    spec: StudySpec | None = None,
    *,
    jobs: int = 1,
    progress: Callable[[int, int], None] | None = None,
) -> StudyResult:
    """The whole study of a scenario (a :class:`Scenario` or a shipped name / YAML path)."""
    t0 = time.perf_counter()
    base = scenario if isinstance(scenario, Scenario) else load_scenario(scenario)
    spec = spec or default_spec(base)
    sigmas = Sigmas.of_scenario(base)
    lays = layouts(base, spec)
    tasks: list[tuple[Callable, tuple]] = [
        (_criteria_task, (base, e, spec.magnitudes[e], inc, spec.criteria_size_m, spec.seed))
        for e in spec.errors
        for inc in spec.criteria_inclinations_deg
    ]
    n_crit = len(tasks)
    tasks += [
        (_sigma_task, (base, lay, sigmas, spec.seed, _SEARCH_MODELS if lay.group == "layout" else MODELS))
        for lay in lays
    ]
    results = run_tasks(tasks, jobs, progress)
    criteria = [r for part in results[:n_crit] for r in part]
    visibility = summarize(criteria)
    sigma, owner = [], []
    for k, part in enumerate(results[n_crit:]):
        sigma += part
        owner += [k] * len(part)
    # |ρ(roll, scan-angle offset)| on the scenario's own targets
    sim, obs, planes = prepare(design_scenario(base, scenario_targets(base)), sigmas, spec.seed)
    rho = scan_angle_roll_correlation(obs, sim.mount_true, planes)
    rec = None
    if "layout" in spec.groups:
        rec = recommend(
            sigma,
            [lays[k] for k in owner],
            spec.constraint,
            [r for r in sigma if r["group"] == "site_passes"],
        )
        # the winner with every model
        full = _sigma_task(base, rec.layout, sigmas, spec.seed)[0]
        sigma[next(i for i, r in enumerate(sigma) if r is rec.row)] = full
        rec = replace(rec, row=full)
    yaw, yaw_note = (
        yaw_lines_or_why(base, sigmas, spec.yaw_line_offsets_m, spec.seed)
        if "yaw_lines" in spec.groups
        else ([], "")
    )
    return StudyResult(
        scenario=base,
        spec=spec,
        sigmas=sigmas,
        criteria=criteria,
        visibility=visibility,
        sigma=sigma,
        layouts=lays,
        layout_of_row=owner,
        roll_scan_correlation=rho,
        recommendation=rec,
        runtime_s=time.perf_counter() - t0,
        yaw_lines=yaw,
        yaw_lines_note=yaw_note,
    )
