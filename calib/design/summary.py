"""Outputs of the design study: ``sigma.csv`` and the other tables, the σ figures, the thesis's
findings checked on the study, ``recommendation.json`` and ``summary.md``.
"""

from __future__ import annotations

import csv
import json
import math
from collections.abc import Callable, Sequence
from dataclasses import asdict
from pathlib import Path

import numpy as np

from calib.design.criteria import (
    CRITERIA_COLUMNS,
    VISIBILITY_COLUMNS,
    plot_criteria,
)
from calib.design.narrative import (  # findings: what `mls design` checks, from here
    ESTIMATOR_NAMES,
    findings,  # noqa: F401
    summary_markdown,
    tau_text,
)
from calib.design.prediction import ANGLES, ESTIMATOR_MODEL
from calib.design.scenes import surface_inclination_deg
from calib.design.study import SIGMA_COLUMNS, StudyResult, run_tasks
from calib.design.yawlines import YAW_LINE_COLUMNS, plot_yaw_lines

#: Colours of the six passes in the thesis's order (0°, 180°, 45°, 225°, 315°, 135°).
_MAX_LAYOUT_BARS = 25


def _fmt(v) -> str:
    if isinstance(v, tuple):  # a list; a list of pairs (sizes) as 1.23x0.76;…
        return ";".join("x".join(_fmt(y) for y in x) if isinstance(x, tuple) else _fmt(x) for x in v)
    if isinstance(v, float):
        return f"{v:.6g}"
    return str(v)


def write_csv(path: Path, rows: Sequence[dict], columns: Sequence[str]) -> Path:
    with open(path, "w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(columns)
        for r in rows:
            w.writerow([_fmt(r.get(c, "")) for c in columns])
    return path


def plot_sigma_group(rows: Sequence[dict], group: str, path: Path, title: str = "") -> Path:
    """Thesis Fig. 4.12 style: σ of roll, pitch, yaw per configuration of one group's rows of
    ``sigma.csv``, white noise (top) and realistic (bottom: Gauss–Markov POS errors, the
    calibration's estimator — GLS, its σ the Cramér–Rao bound)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [r for r in rows if r["group"] == group and r["observable"]]
    if group == "layout":  # the search: its best candidates only
        rows = sorted(rows, key=lambda r: r["realistic_total_deg"])[:_MAX_LAYOUT_BARS]
    if group in ("passes", "site_passes"):
        labels = ["/".join(f"{h:g}" for h in r["headings_deg"]) for r in rows]
    else:
        labels = [r["label"] for r in rows]
    x = np.arange(len(rows))
    width = 0.27
    label_in = 0.3 + 0.065 * max((len(t) for t in labels), default=1)  # rotated tick labels
    fig_w, fig_h = max(7.0, 0.22 * len(rows) + 3), 6.5 + label_in
    fig, axes = plt.subplots(2, 1, figsize=(fig_w, fig_h), sharex=True)

    def realistic(r, a):
        return r[f"sigma_{ESTIMATOR_MODEL[r['estimator']]}_{a}_deg"]

    tau = tau_text(rows[0]) if rows else "?"
    est = ", ".join(dict.fromkeys(ESTIMATOR_NAMES[r["estimator"]] for r in rows)) or "?"
    for ax, what, key in (
        (axes[0], "white noise (formal)", lambda r, a: r[f"sigma_white_{a}_deg"]),
        (axes[1], f"realistic (Gauss–Markov POS errors, τ = {tau} s, {est})", realistic),
    ):
        for k, (a, colour) in enumerate(zip(ANGLES, ("tab:blue", "tab:orange", "tab:green"), strict=False)):
            ax.bar(x + (k - 1) * width, [key(r, a) for r in rows], width, label=a, color=colour)
        ax.set_ylabel("σ (°)")
        ax.set_title(f"{title}{group}: {what}", fontsize=10)
        ax.grid(axis="y", alpha=0.3)
        ax.legend(fontsize=8)
    axes[1].set_xticks(x)
    axes[1].set_xticklabels(labels, rotation=90, fontsize=7)
    fig.subplots_adjust(
        left=0.8 / fig_w, right=1 - 0.15 / fig_w, top=1 - 0.35 / fig_h, hspace=0.2, bottom=label_in / fig_h
    )
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def recommendation_json(result: StudyResult) -> dict:
    rec = result.recommendation
    if rec is None:
        return {}

    def value(v):  # JSON has no tuple, inf or NaN
        if isinstance(v, tuple):
            return [value(x) for x in v]
        return None if isinstance(v, float) and not math.isfinite(v) else v

    def clean(r):
        return {k: value(v) for k, v in r.items()}

    return {
        "scenario": result.scenario.name,
        "constraint": asdict(rec.constraint),
        "estimator": rec.estimator_name,  # mls calib run --estimator
        "estimate": list(rec.estimator),
        "targets": [
            {
                "name": s.name,
                "inclination_deg": surface_inclination_deg(s),
                "size_m": [s.width_m, s.height_m],
                "along_m": round(s.along_m, 6) + 0.0,
                "out_m": round(s.out_m, 6) + 0.0,
                "up_m": round(s.up_m, 6),
            }
            for s in rec.layout.targets
        ],
        "predicted": clean(rec.row),
        "scenario_site": clean(rec.baseline_row) if rec.baseline_row else None,
        "roll_scan_angle_correlation": result.roll_scan_correlation,
    }


def write_study(
    result: StudyResult,
    out_dir: str | Path,
    empirical: dict | None = None,
    figures: bool = True,
    jobs: int = 1,
) -> list[Path]:
    """CSV tables, PNG figures (drawn in ``jobs`` processes) and ``summary.md`` into
    ``out_dir`` (created)."""
    from calib.io.outputs import make_output_dir

    out = make_output_dir(out_dir)
    files = [
        write_csv(out / "criteria.csv", result.criteria, CRITERIA_COLUMNS),
        write_csv(out / "visibility.csv", result.visibility, VISIBILITY_COLUMNS),
        write_csv(out / "sigma.csv", result.sigma, SIGMA_COLUMNS),
    ]
    if result.yaw_lines:
        files.append(write_csv(out / "yaw_lines.csv", result.yaw_lines, YAW_LINE_COLUMNS))
    if result.recommendation is not None:
        p = out / "recommendation.json"
        p.write_text(json.dumps(recommendation_json(result), indent=2, default=float) + "\n")
        files.append(p)
    if figures:
        title = f"{result.scenario.name}: "
        tasks: list[tuple[Callable, tuple]] = [
            (
                plot_criteria,
                ([r for r in result.criteria if r["error"] == e], e, out / f"criteria_{e}.png", title),
            )
            for e in dict.fromkeys(r["error"] for r in result.criteria)
        ]
        tasks += [
            (plot_sigma_group, (result.rows(g), g, out / f"sigma_{g}.png", title))
            for g in result.spec.groups
            if any(r["observable"] for r in result.rows(g))
        ]
        if result.yaw_lines:
            tasks.append((plot_yaw_lines, (result.yaw_lines, out / "sigma_yaw_lines.png", title)))
        files += run_tasks(tasks, jobs, None)
    p = out / "summary.md"
    p.write_text(summary_markdown(result, empirical), encoding="utf-8")
    files.append(p)
    return files
