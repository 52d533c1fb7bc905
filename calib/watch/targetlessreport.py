"""The outputs of a targetless calibration (:mod:`calib.watch.targetless`): result.json and a
report.md that says it had no target, how the rounds went, which features carried it, and how it
compares with the last calibration with targets in the history."""

from __future__ import annotations

from pathlib import Path

from calib.boresight.report_gls import crlb_lines
from calib.boresight.result import write_result
from calib.watch.targetless import TargetlessRun

ANGLES = ("roll", "pitch", "yaw")


def compare_with(run: TargetlessRun, previous) -> dict | None:
    """The comparison with ``previous`` (a history record or None), as result.json carries it."""
    if previous is None:
        return None
    from calib.assess.history import compare

    c = compare(previous, run.doc, a_label=previous.label, b_label="this targetless run")
    return {
        "with": previous.label,
        "changed": c.changed,
        "message": c.message,
        "difference_deg": {a.angle: a.difference_deg for a in c.angles},
        "n_sigma": {a.angle: a.n_sigma for a in c.angles},
    }


def write_targetless(run: TargetlessRun, out_dir, comparison: dict | None = None) -> list[Path]:
    """result.json (with ``comparison`` when given) and report.md into ``out_dir`` (created)."""
    from calib.io.outputs import make_output_dir

    out = make_output_dir(out_dir)
    doc = {**run.doc, "comparison_with_targets": comparison, "warnings": list(run.warnings)}
    report = out / "report.md"
    report.write_text("\n".join(report_lines(run, comparison)) + "\n", encoding="utf-8")
    return [write_result(out / "result.json", doc), report]


def report_lines(run: TargetlessRun, comparison: dict | None) -> list[str]:
    d = run.doc
    L = [
        "# Targetless boresight calibration",
        "",
        f"Source: `{run.source}`. **No target**: the boresight comes from the scene's tie patches and "
        "piles seen from lines of different headings and offsets (docs/architecture.md §7.9).",
        "",
        f"Verdict: **{d['verdict']}**" + ("" if not d["verdict_reasons"] else ":"),
        *[f"- {r}" for r in d["verdict_reasons"]],
        "",
        "| angle | estimate | σ realistic | a priori | held at a priori |",
        "|---|---|---|---|---|",
    ]
    for a in ANGLES:
        L.append(
            f"| {a} | {d['boresight_deg'][a]:.4f}° | {d['sigma_realistic_deg'][a]:.4f}° "
            f"| {d['apriori_deg'][a]:.4f}° | {'yes' if d['held_deg'][a] else 'no'} |"
        )
    L += _rounds(d["rounds"]) + _features(d) + crlb_lines(d) + _comparison(comparison)
    if run.warnings:
        L += ["", "## Warnings", "", *[f"- {w}" for w in run.warnings]]
    return L


def _rounds(rounds: list[dict]) -> list[str]:
    L = [
        "",
        "## Rounds",
        "",
        "Each round georeferences with the previous boresight, cuts the features again and solves.",
        "",
        "| round | step roll, pitch, yaw (mdeg) | largest step / σ | features | time |",
        "|---|---|---|---|---|",
    ]
    for r in rounds:
        step = ", ".join(f"{1000 * x:+.1f}" for x in r["step_deg"])
        L.append(
            f"| {r['round']} | {step} | {r['largest_step_sigma']:.2f} | {r['n_features']} | {r['runtime_s']:.0f} s |"
        )
    failed = [r for r in rounds if r.get("group_failed")]
    if failed:
        L += [""] + [
            f"Round {r['round']} failed its group test ({r['group_failed']}): its features were cut at a "
            "mount still far off, so its estimate only started the next round."
            for r in failed
        ]
    return L


def _features(d: dict) -> list[str]:
    feats = d["tie_features"]
    n_cyl = sum(f["name"].startswith("cyl_") for f in feats)
    lines = sorted({p for f in feats for p in f["pass_ids"]})
    L = [
        "",
        "## Features",
        "",
        f"{len(feats)} features ({len(feats) - n_cyl} planar patches, {n_cyl} piles) from lines "
        f"{', '.join(map(str, lines))}; {len(d['moved_features'])} dropped as moving between lines, "
        f"{len(d['undetermined_features'])} as not determined by their own points. "
        f"Group test χ² {d['group_test']['chi2']:.1f} on {d['group_test']['df']} degrees of freedom.",
    ]
    return L


def _comparison(c: dict | None) -> list[str]:
    if c is None:
        return ["", "## Against the last calibration with targets", "", "None in the history."]
    rows = [f"| {a} | {1000 * c['difference_deg'][a]:+.1f} mdeg | {c['n_sigma'][a]:.1f} σ |" for a in ANGLES]
    return [
        "",
        f"## Against the last calibration with targets ({c['with']})",
        "",
        "| angle | this − that | |",
        "|---|---|---|",
        *rows,
        "",
        c["message"],
    ]


def sigma_text(run: TargetlessRun) -> str:
    """One line for the terminal: each angle's estimate and σ, held angles marked."""
    d = run.doc
    return (
        ", ".join(
            f"{a} {d['boresight_deg'][a]:.4f}° ± {d['sigma_realistic_deg'][a]:.4f}°"
            + (" (a priori: not determined)" if d["held_deg"][a] else "")
            for a in ANGLES
        )
        + f" · {len(run.rounds)} rounds, {run.runtime_s:.0f} s"
    )
