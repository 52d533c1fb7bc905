"""A boresight from any survey, without targets (docs/architecture.md §7.9): the mount watch's
estimator (:func:`calib.watch.block.estimate_block`) over every line of a survey, from the
a-priori mount, repeated until the scene's features stop moving.

The features — planar tie patches seen from lines of different headings and vertical cylinders
(piles) — are cut from points georeferenced with a mount; with the a-priori mount a few tenths of
a degree off, each line's copy of a surface is displaced differently and the patches are cut in
the wrong places (one draw: pitch 3σ off after the first solution, within 1σ after the second).
So each round georeferences with the previous round's boresight, cuts the features again and
solves again; the run settles when no free angle moves by more than :data:`SETTLED_SIGMA` σ (at
least two rounds, at most :data:`MAX_ROUNDS`; one not settled is questionable). The last round's estimate is the result,
with the estimator's honesty rules: the GLS over Gauss–Markov POS errors, each feature's own
roughness, moving features dropped, the group test across the scene (the last round's failed
test is no result; an earlier round's carries its estimate to the next round, which cuts the
features again), the covariance scaled by the variance factor and the groups' dispersion.

An angle the scene does not determine (σ beyond :data:`~calib.boresight.checks.verdict.REFUSE_SIGMA_RAD`:
a wall seen from one offset and no pile leaves yaw free) keeps its a-priori value and its σ
there, and the verdict refuses the result as for a target calibration: the report names it.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from calib.boresight.checks.verdict import REFUSE_SIGMA_RAD, Verdict, evidence, judge
from calib.boresight.result import result_to_dict
from calib.boresight.scene_ties import crlb_by_features
from calib.core.errors import CalibError
from calib.core.georef import Mount
from calib.core.trajectory import Trajectory
from calib.core.version import software_version
from calib.io.bundle import ScanPoints
from calib.io.site import Site
from calib.watch.block import BlockEstimate, WatchOptions, estimate_block, site_error_model, site_sigmas

#: rounds of re-georeferencing and solving, at most
MAX_ROUNDS = 4
#: the run has settled when no free angle moved by more than this many σ in a round. Near the
#: answer a round changes only where the features are cut, which scatters the estimate: by
#: 0.2–0.6 σ on a production survey with ~100 features (83, 0.62, 0.19, 0.27 σ in one's rounds),
#: by 0.6–2.3 σ on a calibration site with 7–9 (montreal_piles: 127, 1.7, 2.0, 2.3 σ) — the
#: reported σ covers it there (12 seeds: every angle within 2σ); a first round tenths of a degree
#: off moves by 80–140 σ
SETTLED_SIGMA = 3.0
#: the estimator's options for a whole survey: more features than a block, a prior that only
#: keeps the system regular (5°), an angle held only when the scene cannot determine it, and the
#: returns thinned at random to 1 M a round — the σ is the POS errors' and the features' roughness,
#: not the point count's (a 15-min survey: roll σ 3.3 mdeg from 0.44 M points, 3.1 from 0.88 M),
#: and a round's CPU grows with the points (issue 27's ceiling: 5 min for a 1-h survey)
TARGETLESS_OPTIONS = WatchOptions(
    max_patches=120,
    max_cylinders=40,  # every pile of a harbour front (12 on the simulator's)
    prior_sigma_rad=float(np.radians(5.0)),
    max_sigma_rad=REFUSE_SIGMA_RAD,
    max_points=1_000_000,
)


class TargetlessError(CalibError):
    """No targetless calibration from this survey (the message says why)."""


@dataclass(frozen=True)
class TargetlessRun:
    """A targetless calibration: result.json's document, the verdict, the last round's estimate."""

    source: str
    site: Site
    doc: dict
    verdict: Verdict
    estimate: BlockEstimate
    rounds: list[dict]
    warnings: list[str] = field(default_factory=list)
    runtime_s: float = 0.0


def calibrate_targetless(
    site: Site,
    trajectory: Trajectory,
    points: ScanPoints,
    *,
    apriori_rad: np.ndarray | None = None,
    options: WatchOptions = TARGETLESS_OPTIONS,
    progress: Callable[[str, int, int | None], None] | None = None,
    source: str = "in memory",
) -> TargetlessRun:
    """The boresight of ``points`` (lines: their ``pass_id``) from the scene alone, starting at
    the site's a-priori boresight (or ``apriori_rad``). Raises :class:`TargetlessError` when a
    round finds nothing to solve on (its status says what)."""
    clock = time.perf_counter()
    apriori = site.mount if apriori_rad is None else site.mount.with_boresight(np.asarray(apriori_rad, float))
    mount, rounds, est = apriori, [], None
    for k in range(1, MAX_ROUNDS + 1):
        if progress is not None:
            progress(f"targetless round {k}", k - 1, MAX_ROUNDS)
        est = _round(site, trajectory, points, mount, _round_options(options, k), source)
        mount = mount.with_boresight(mount.boresight_rad + est.delta_rad)
        rounds.append(_round_doc(k, est, mount))
        if k > 1 and rounds[-1]["largest_step_sigma"] <= SETTLED_SIGMA:
            break
    assert est is not None
    if est.group_failed is not None:  # the last round's group test decides, as for a block
        raise TargetlessError(f"{source}: no targetless calibration: no verdict: {est.group_failed}")
    settled = rounds[-1]["largest_step_sigma"] <= SETTLED_SIGMA and len(rounds) > 1
    verdict = _verdict(est, settled, len(rounds))
    doc = _doc(est, apriori, mount, verdict, rounds, source)
    warnings = [] if settled else [f"the estimate still moved in round {len(rounds)} (see rounds)"]
    return TargetlessRun(
        source=source,
        site=site,
        doc=doc,
        verdict=verdict,
        estimate=est,
        rounds=rounds,
        warnings=warnings,
        runtime_s=time.perf_counter() - clock,
    )


def _round_options(options: WatchOptions, k: int) -> WatchOptions:
    """Round ``k``'s options. Every round is provisional: a failed group test is kept with the
    estimate, which the next round starts from — features cut at a mount a degree or more off
    disagree between groups (1.5° on every angle: χ² 505 over 15 degrees of freedom) and are cut
    again at the better mount; only the last round's test decides (:func:`calibrate_targetless`).
    The first round has no lean rule: at the a-priori mount, tenths of a degree off, every
    upright pile looks leaning by about as much (0.3–0.5° from a mount 1.2° off in pitch) and the
    rule would throw the piles out; from the second round on the mount is within a few σ and the
    rule tells a leaning pile from an upright one."""
    options = replace(options, provisional=True)
    return options if k > 1 else replace(options, max_lean_deg=90.0)


def _round(site, trajectory, points, mount: Mount, options: WatchOptions, source: str) -> BlockEstimate:
    est = estimate_block(
        points,
        trajectory,
        mount,
        site_sigmas(site),
        site_error_model(site),
        site.wall_azimuth_rad,
        options,
        keep_result=True,
    )
    if not est.ok or est.result is None or est.delta_rad is None:
        raise TargetlessError(f"{source}: no targetless calibration: {est.status}")
    return est


def _round_doc(k: int, est: BlockEstimate, mount: Mount) -> dict:
    free = ~np.asarray(est.held)
    assert est.delta_rad is not None
    steps = np.abs(est.delta_rad[free]) / est.sigma_rad[free]
    return {
        "round": k,
        "boresight_deg": [float(x) for x in np.degrees(mount.boresight_rad)],
        "step_deg": [float(x) for x in np.degrees(est.delta_rad)],
        "sigma_deg": [float(x) for x in np.degrees(est.sigma_rad)],
        "largest_step_sigma": float(steps.max()) if steps.size else 0.0,
        "n_features": len(est.patches),
        "group_failed": est.group_failed,
        "runtime_s": est.runtime_s,
    }


def _verdict(est: BlockEstimate, settled: bool, n_rounds: int) -> Verdict:
    """The calibration's verdict on the last round's solution, with its σ as reported, and what
    only a targetless run can lack."""
    assert est.result is not None and est.cov_rad2 is not None
    res = replace(est.result, cov_realistic=est.cov_rad2, removed_groups=[])
    v = judge(evidence(res, {}, None, None))
    reasons = list(v.reasons)
    names = ("roll", "pitch", "yaw")
    held = [a for a, h in zip(names, est.held, strict=True) if h]
    if held:
        reasons.append(
            f"{', '.join(held)} not determined by the scene (no target; its σ would exceed "
            f"{np.degrees(REFUSE_SIGMA_RAD):g}°): the a-priori value is kept — sail lines at other "
            f"offsets from piles or corners (mls design --site)"
        )
    status = v.status
    if not settled:
        reasons.append(f"the estimate had not settled after {n_rounds} rounds")
        status = "refused" if status == "refused" else "questionable"
    notes = [*v.notes, "targetless: the boresight from the scene's tie patches and piles, no target"]
    return Verdict(status, reasons, notes)


def _doc(est: BlockEstimate, apriori: Mount, mount: Mount, verdict: Verdict, rounds, source: str) -> dict:
    """result.json: the adjustment's fields, the boresight and σ of the last round as reported."""
    from calib.boresight.checks.verdict import as_doc

    assert est.result is not None and est.cov_rad2 is not None
    res = replace(est.result, boresight_rad=mount.boresight_rad, cov_realistic=est.cov_rad2)
    s = np.sqrt(np.diag(est.cov_rad2))
    corr = est.cov_rad2 / np.outer(s, s)
    doc = result_to_dict(res, apriori.boresight_rad, software_version())
    extra = {
        "mode": "targetless",
        "source": source,
        **as_doc(verdict),
        "correlation": [[float(x) for x in row] for row in corr],
        "held_deg": {a: bool(h) for a, h in zip(("roll", "pitch", "yaw"), est.held, strict=True)},
        "rounds": rounds,
        "tie_features": est.as_dict()["patches"],
        "moved_features": list(est.moved_patches),
        "undetermined_features": list(est.undetermined_features),
        "crlb_by_features_deg": _crlb_by_features(est, mount),
        "group_test": {"chi2": est.group_chi2, "df": est.group_df},
        "link_test": {"chi2": est.link_chi2, "df": est.link_df},
    }
    doc.update(extra)
    return doc


def _crlb_by_features(est: BlockEstimate, mount: Mount) -> dict[str, list[float]]:
    """The Cramér–Rao σ (deg) of each angle with the planar patches, then with the piles too
    (:func:`calib.boresight.scene_ties.crlb_by_features`), at the last round's solution."""
    assert est.result is not None and est.observations is not None and est.adjust_options is not None
    return crlb_by_features(est.observations, est.result.state, mount, est.adjust_options)


def targetless_bundle(
    bundle_path, *, apriori_rad=None, progress=None, skip_uncovered: bool = False, max_gap_s: float = 1.0
) -> TargetlessRun:
    """:func:`calibrate_targetless` of a bundle directory (targets in its site.yaml are not
    used); ``skip_uncovered`` drops the points outside the trajectory (a warning per line)."""
    from calib.boresight.checks.inputs import drop_uncovered
    from calib.io.bundle import read_bundle

    if progress is not None:
        progress("reading the bundle", 0, None)
    bundle = read_bundle(bundle_path, max_gap_s=max_gap_s)
    points, warnings = bundle.points, list[str]()
    if skip_uncovered:
        points, _, warnings = drop_uncovered(points, bundle.trajectory, bundle.site.mount.time_offset_s)
    run = calibrate_targetless(
        bundle.site,
        bundle.trajectory,
        points,
        apriori_rad=apriori_rad,
        progress=progress,
        source=str(bundle_path),
    )
    return replace(run, warnings=[*warnings, *run.warnings])


def last_target_calibration(vessel: str, mount_id: str, db=None):
    """The latest calibration with targets in the history of this vessel and mount that was not
    refused (a :class:`calib.assess.history.HistoryRecord`), or None."""
    from calib.assess.history import list_results

    done = [
        r
        for r in list_results(vessel, db, mount_id)
        if r.result.get("mode") != "targetless" and r.verdict != "refused"
    ]
    return done[-1] if done else None
