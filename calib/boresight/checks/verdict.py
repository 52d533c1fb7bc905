"""The calibration's verdict (docs/architecture.md §7.7a): can the number be used?

A confident wrong boresight is the worst thing a calibration can give: every later survey
inherits it, and nothing downstream can see it. So every result carries one of

- ``trusted``: every check below passed; the realistic σ is what the data support;
- ``questionable``: the number is probably usable but a check failed (the reasons say which);
  compare it with a previous calibration or sail more passes before relying on it;
- ``refused``: the data contradict the model (the adjustment did not converge, the misfit is
  far beyond the error model, a gross error could not be removed) or do not determine an angle
  (realistic σ > 0.5°): ``mls calib run`` exits non-zero and the history marks the entry.

The checks, each with its threshold named below: the χ² test of the variance factor; target
groups removed by the group test (:mod:`calib.boresight.checks.grouptest`) or kept because nothing
could replace them; a target lost (missing or rejected by the extraction) in two passes or
more; the targets and the scene's tie patches disagreeing; the boresight moving by more than
1.5 σ when the POS correlation time is taken 3× shorter or longer (only when τ was estimated);
the delete-one-pass jackknife scattering more than three times the realistic σ; an angle observed
worse than :data:`MAX_SIGMA_RAD`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from calib.boresight.observability import ANGLE_NAMES

VERDICTS = ("trusted", "questionable", "refused")
#: ``mls calib run``'s exit status for a refused result (without --accept-refused)
REFUSED_EXIT_STATUS = 4
#: a variance factor beyond this is a model that does not fit the data: refused
REFUSE_SIGMA0_SQUARED = 2.0
#: up to this the realistic σ is scaled by σ̂0 and the result stays trusted (a scanner σ a
#: little optimistic is common); beyond it the misfit is a reason
QUESTION_SIGMA0_SQUARED = 1.5
#: an angle known worse than this (realistic σ) is poorly calibrated: questionable
MAX_SIGMA_RAD = float(np.radians(0.1))
#: an angle known worse than this is not calibrated at all (an a-priori mount drawing is as good)
REFUSE_SIGMA_RAD = float(np.radians(0.5))
#: the jackknife may scatter up to this multiple of the realistic σ
MAX_JACKKNIFE_RATIO = 3.0
#: a target lost in this many passes or more weakens the geometry the pattern was chosen for
MAX_LOST_PASSES = 2
#: the boresight may move by this many σ between τ/3 and 3τ
MAX_TAU_SHIFT_SIGMA = 1.5


@dataclass(frozen=True)
class Evidence:
    """What the verdict is judged on (built by the pipeline from the run)."""

    converged: bool
    sigma0_squared: float
    chi2_lower: float
    sigma_realistic_rad: np.ndarray  # (3,) already scaled by σ̂0 when σ̂0² > 1
    sigma_jackknife_rad: np.ndarray | None = None
    removed_groups: list[dict] = field(default_factory=list)
    lost_passes: dict[str, list[int]] = field(default_factory=dict)  # target -> pass ids
    patch_check: dict | None = None  # calib.boresight.scene_ties.patches_agree, when run
    tau_rows: list[dict] | None = None  # calib.boresight.tau.tau_sensitivity, when τ was estimated


@dataclass(frozen=True)
class Verdict:
    status: str  # of VERDICTS
    reasons: list[str]  # why not trusted (empty when trusted)
    notes: list[str]  # checks passed with a remark


def judge(ev: Evidence) -> Verdict:
    """The verdict of a calibration from its evidence (module docstring)."""
    refuse: list[str] = []
    question: list[str] = []
    notes: list[str] = []
    if not ev.converged:
        refuse.append("the adjustment did not converge")
    _variance_factor(ev, refuse, question, notes)
    for g in ev.removed_groups:
        (question if g.get("removed") else refuse).append(
            f"gross error {'removed' if g.get('removed') else 'found but kept'}: {g['reason']}"
        )
    for name, passes in sorted(ev.lost_passes.items()):
        if len(passes) >= MAX_LOST_PASSES:
            question.append(
                f"target {name} lost in {len(passes)} passes ({', '.join(map(str, passes))}): the pattern's "
                f"geometry is weaker than planned"
            )
    if ev.patch_check is not None and not ev.patch_check.get("agree", True):
        question.append(
            f"the targets and the scene's tie patches disagree (χ² = {ev.patch_check['chi2']:.1f} on "
            f"{ev.patch_check['dof']} degrees of freedom, p = {ev.patch_check['p_value']:.2g}); σ widened to "
            f"cover both"
        )
    refuse += [
        f"{name} is not calibrated: known to ±{np.degrees(s):.2f}° only (> {np.degrees(REFUSE_SIGMA_RAD):g}°)"
        for name, s in zip(ANGLE_NAMES, ev.sigma_realistic_rad, strict=False)
        if s > REFUSE_SIGMA_RAD
    ]
    question += _tau_reasons(ev.tau_rows)
    question += _spread_reasons(ev)
    status = "refused" if refuse else ("questionable" if question else "trusted")
    return Verdict(status, refuse + question, notes)


def _variance_factor(ev: Evidence, refuse: list[str], question: list[str], notes: list[str]) -> None:
    s2 = ev.sigma0_squared
    if s2 > REFUSE_SIGMA0_SQUARED:
        refuse.append(
            f"σ̂0² = {s2:.2f} > {REFUSE_SIGMA0_SQUARED:g}: the data do not fit the error model (wrong "
            f"scanner or POS σ, a target that is not what site.yaml says, something moving)"
        )
    elif s2 > QUESTION_SIGMA0_SQUARED:
        question.append(f"σ̂0² = {s2:.2f} > {QUESTION_SIGMA0_SQUARED:g}: the data fit the error model poorly")
    elif s2 > 1.0:
        notes.append(f"σ̂0² = {s2:.2f}: the realistic σ is scaled by σ̂0 = {np.sqrt(s2):.2f}")
    elif s2 < ev.chi2_lower:
        notes.append(f"σ̂0² = {s2:.2f}: the error model is pessimistic (σ may be larger than needed)")


def _tau_reasons(rows: list[dict] | None) -> list[str]:
    if not rows or len(rows) != 3:
        return []
    mid = np.asarray(rows[1]["boresight_deg"])
    sig = np.asarray(rows[1]["sigma_deg"])
    out = []
    for row in (rows[0], rows[2]):
        shift = np.abs(np.asarray(row["boresight_deg"]) - mid) / np.maximum(sig, 1e-12)
        if shift.max() > MAX_TAU_SHIFT_SIGMA:
            a = int(np.argmax(shift))
            out.append(
                f"the {ANGLE_NAMES[a]} moves by {shift[a]:.1f} σ with the POS correlation time taken "
                f"{row['tau_s']:.1f} s instead of {rows[1]['tau_s']:.1f} s (estimated, not configured: set "
                f"site.yaml pos_sigmas.correlation_time_s)"
            )
    return out


def _spread_reasons(ev: Evidence) -> list[str]:
    out = []
    sig = ev.sigma_realistic_rad
    for a, name in enumerate(ANGLE_NAMES):
        if MAX_SIGMA_RAD < sig[a] <= REFUSE_SIGMA_RAD:
            out.append(
                f"{name} is determined to ±{np.degrees(sig[a]):.3f}° only (> {np.degrees(MAX_SIGMA_RAD):g}°): "
                f"the passes do not observe it well"
            )
    if ev.sigma_jackknife_rad is not None:
        ratio = ev.sigma_jackknife_rad / np.maximum(sig, 1e-15)
        if ratio.max() > MAX_JACKKNIFE_RATIO:
            a = int(np.argmax(ratio))
            out.append(
                f"leaving out one pass at a time scatters the {ANGLE_NAMES[a]} {ratio[a]:.1f}× its realistic σ: "
                f"one pass disagrees with the others"
            )
    return out


def as_doc(v: Verdict) -> dict:
    """The result.json keys of a verdict."""
    return {"verdict": v.status, "verdict_reasons": list(v.reasons), "verdict_notes": list(v.notes)}


def untrusted_warning(result: dict, label: str) -> str | None:
    """The warning a user of a calibration result (georef, the mount watch) gets when its
    verdict is not trusted; None when it is."""
    status = result.get("verdict")
    if status == "trusted":
        return None
    if status is None:
        return f"calibration {label} has no verdict (an older result): its reliability was not checked"
    reasons = "; ".join(result.get("verdict_reasons") or []) or "no reason recorded"
    return f"calibration {label} is {status.upper()}: {reasons}"


def evidence(
    res, lost_passes: dict[str, list[int]], patch_check: dict | None, tau_rows: list[dict] | None
) -> Evidence:
    """The evidence of an adjustment result (:class:`calib.boresight.adjust.AdjustmentResult`)
    with what the pipeline adds: the targets lost per pass, the patches' check, the τ rows."""
    return Evidence(
        converged=res.converged,
        sigma0_squared=float(res.sigma0_squared),
        chi2_lower=res.chi2_test()["lower"],
        sigma_realistic_rad=res.sigma_realistic_rad,
        sigma_jackknife_rad=None if res.cov_jackknife is None else np.sqrt(np.diag(res.cov_jackknife)),
        removed_groups=list(res.removed_groups),
        lost_passes=lost_passes,
        patch_check=patch_check,
        tau_rows=tau_rows,
    )
