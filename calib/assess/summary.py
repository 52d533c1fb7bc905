"""The report of a relative accuracy assessment: distances as a surveyor reads them, the verdict
of each surface, the summary in words, the histograms and height figures, ``assessment.md`` and
``assessment.json``.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from calib.assess.c2c import DistanceStats
from calib.assess.results import ANGLES, STATES, Assessment, Comparison


def fmt_length(x_m: float | None) -> str:
    """A distance as a surveyor reads it: 1.38 m, 48 mm, 3.2 mm, 0.41 mm."""
    if x_m is None or not math.isfinite(x_m):
        return "—"
    a = abs(x_m)
    if a >= 1.0:
        return f"{x_m:.2f} m"
    if a >= 0.01:
        return f"{x_m * 1e3:.0f} mm"
    if a >= 0.001:
        return f"{x_m * 1e3:.1f} mm"
    return f"{x_m * 1e3:.2f} mm"


def fmt_ratio(r: float) -> str:
    if not math.isfinite(r):
        return "∞"
    return f"{r:.0f}×" if r >= 10 else f"{r:.1f}×"


def verdict(c: Comparison) -> str:
    """One phrase on the distance after the calibration (surface comparisons)."""
    after = c.after.median_m
    if after > c.before.median_m:
        return "WORSE than before: check the result and the site's mount"
    if c.expected_upper_m is None or c.expected_upper_calibration_m is None:  # set together
        return ""
    if after <= c.expected_upper_m:
        return (
            f"at the noise level of the scanner and the POS (expected "
            f"{fmt_length(c.expected_median_m)}, 95 % bound {fmt_length(c.expected_upper_m)})"
        )
    if after <= c.expected_upper_calibration_m:
        return (
            f"above the sensors' noise level ({fmt_length(c.expected_upper_m)}) but within "
            f"what the calibration's own σ allows ({fmt_length(c.expected_upper_calibration_m)})"
        )
    return (
        f"larger than the sensors' noise ({fmt_length(c.expected_upper_m)}) and the "
        f"calibration's σ ({fmt_length(c.expected_upper_calibration_m)}) explain"
    )


def _pair_label(a: Assessment, pair) -> str:
    h = a.headings_deg
    return f"{pair[0]} ({h[pair[0]]:.0f}°) ↔ {pair[1]} ({h[pair[1]]:.0f}°)"


def plot_histograms(a: Assessment, out_dir: Path) -> list[Path]:
    """Overlaid histograms of the C2C before and after, one PNG per surface and pair
    (log-spaced bins: before and after differ by orders of magnitude)."""
    from matplotlib.figure import Figure

    paths = []
    for c in a.comparisons:
        d0, d1 = c.d_before_m * 1e3, c.d_after_m * 1e3
        pos = np.concatenate([d0[d0 > 0], d1[d1 > 0]])
        if pos.size == 0:
            continue
        lo = max(float(np.percentile(pos, 0.5)), 1e-3)
        hi = max(float(pos.max()), lo * 10)
        bins = np.geomspace(lo, hi, 60)
        fig = Figure(figsize=(7.5, 4.2))
        ax = fig.subplots()
        where = "whole overlap" if c.source == "overlap" else f"{c.name} ({c.height_m:.0f} m)"
        for d, label, color in (
            (d0, "before (a-priori mount)", "tab:blue"),
            (d1, "after (estimated mount)", "tab:brown"),
        ):
            med = float(np.median(d))
            ax.hist(
                np.clip(d, lo, hi),
                bins=bins,  # type: ignore[arg-type]  # matplotlib's stubs refuse the array hist takes
                histtype="stepfilled",
                alpha=0.45,
                color=color,
                label=f"{label}: median {fmt_length(med / 1e3)}",
            )
            ax.axvline(med, color=color, lw=1.5, ls="--")
        if c.expected_median_m:
            ax.axvline(
                c.expected_median_m * 1e3,
                color="k",
                lw=1.0,
                ls=":",
                label=f"expected (scanner + POS): {fmt_length(c.expected_median_m)}",
            )
        ax.set_xscale("log")
        ax.set_xlabel(f"cloud-to-cloud distance (mm, local LS plane, k = {a.options.k})")
        ax.set_ylabel("returns")
        ax.set_title(f"{where} — passes {_pair_label(a, c.pair)}")
        ax.legend(fontsize=8)
        fig.subplots_adjust(left=0.09, right=0.98, bottom=0.12, top=0.92)
        p = Path(out_dir) / f"hist_{c.pair[0]}-{c.pair[1]}_{c.name}.png"
        fig.savefig(p, dpi=110)
        paths.append(p)
    return paths


def plot_heights(a: Assessment, out_dir: Path, max_points: int = 20000) -> list[Path]:
    """Distance against the height above the water, before and after, with the binned medians
    and the fitted line; one PNG per pair."""
    from matplotlib.figure import Figure

    rng = np.random.default_rng(0)
    paths = []
    for pair in a.pairs:
        planes = a.planes(pair)
        if not planes:
            continue
        h = np.concatenate([c.heights_m for c in planes])
        fig = Figure(figsize=(9.0, 5.0))
        axes = fig.subplots(1, 2, sharey=True)
        sub = rng.choice(h.size, min(h.size, max_points), replace=False)
        for ax, state, color in zip(axes, STATES, ("tab:blue", "tab:brown"), strict=False):
            d = np.concatenate([getattr(c, f"d_{state}_m") for c in planes]) * 1e3
            fit = a.height_fit(pair, state)
            ax.scatter(d[sub], h[sub], s=2, alpha=0.25, color=color, lw=0)
            ax.plot(
                fit.bin_medians_m * 1e3,
                fit.bin_heights_m,
                "o-",
                color="k",
                ms=3,
                lw=1,
                label="median per 2 m of height",
            )
            hh = np.linspace(*fit.height_span_m, 20)
            ax.plot(
                (fit.intercept_m + fit.slope_m_per_m * hh) * 1e3,
                hh,
                "--",
                color="tab:red",
                label=f"fit: {fit.slope_m_per_m * 1e3:.1f} mm per m of height",
            )
            ax.set_xlabel(f"C2C distance {state} (mm)")
            ax.set_title(f"{state} the calibration")
            ax.set_xlim(left=0)
            ax.legend(fontsize=8, loc="lower right")
        axes[0].set_ylabel("height above the water (m)")
        fig.suptitle(f"Distance against height — passes {_pair_label(a, pair)}")
        fig.subplots_adjust(left=0.07, right=0.98, bottom=0.1, top=0.87, wspace=0.06)
        p = Path(out_dir) / f"height_{pair[0]}-{pair[1]}.png"
        fig.savefig(p, dpi=110)
        paths.append(p)
    return paths


def summary_lines(a: Assessment) -> list[str]:
    """The improvement in words, one sentence per line."""
    lines = []
    for pair in a.pairs:
        label = _pair_label(a, pair)
        planes = sorted(a.planes(pair), key=lambda c: -c.height_m)
        for c in planes:
            lines.append(
                f"Passes {label}: median C2C on {c.name} ({c.height_m:.0f} m) went from "
                f"{fmt_length(c.before.median_m)} to {fmt_length(c.after.median_m)} "
                f"({fmt_ratio(c.improvement)} smaller); {verdict(c)}."
            )
        for c in a.comparisons:
            if c.source == "overlap" and c.pair == pair:
                lines.append(
                    f"Passes {label}, whole overlap ({c.after.count:,} returns): median "
                    f"from {fmt_length(c.before.median_m)} to "
                    f"{fmt_length(c.after.median_m)}."
                )
        try:
            b, f = a.height_fit(pair, "before"), a.height_fit(pair, "after")
        except KeyError:
            continue
        if b.height_span_m[1] - b.height_span_m[0] >= 5.0:
            grow = "grew" if b.slope_m_per_m > 0 else "changed"
            lines.append(
                f"Passes {label}: before the calibration the distances {grow} by "
                f"{b.slope_m_per_m * 1e3:.1f} mm per metre of height ({b.height_span_m[0]:.0f}–"
                f"{b.height_span_m[1]:.0f} m), after by {f.slope_m_per_m * 1e3:.1f} mm per metre"
                + (
                    "; a boresight error moves reciprocal passes apart in proportion to the range, "
                    "so this growth is its signature."
                    if b.slope_m_per_m > 2e-3
                    else "."
                )
            )
            if abs(f.slope_m_per_m) > max(2e-3, 0.2 * abs(b.slope_m_per_m)):
                lines.append(
                    f"Passes {label}: the distances after still change with height: a "
                    f"boresight error remains."
                )
    if a.truth_boresight_deg is not None:
        err = {k: a.boresight_after_deg[k] - a.truth_boresight_deg[k] for k in ANGLES}
        lines.append(
            "Simulated bundle: the estimate differs from the true boresight by "
            + ", ".join(f"{k} {err[k]:+.4f}°" for k in ANGLES)
            + "."
        )
    return lines


def _stats_cells(s: DistanceStats) -> list[str]:
    return [fmt_length(s.mean_m), fmt_length(s.median_m), fmt_length(s.rms_m), fmt_length(s.p95_m)]


def _intro(a: Assessment) -> list[str]:
    """The title, the boresight before and after, and the method."""
    b0, b1 = a.boresight_before_deg, a.boresight_after_deg
    return [
        f"# Relative accuracy assessment — {a.bundle_path.name}",
        "",
        f"Boresight before (site.yaml a priori): roll {b0['roll']:.4f}°, pitch {b0['pitch']:.4f}°, "
        f"yaw {b0['yaw']:.4f}°; after (calibration result): roll {b1['roll']:.4f}°, pitch "
        f"{b1['pitch']:.4f}°, yaw {b1['yaw']:.4f}° (canonical convention).",
        "",
        f"Method: the same returns of two passes are georeferenced with each mount and compared "
        f"with cloud-to-cloud distances to local least-squares planes (k = {a.options.k}; "
        f"CloudCompare's C2C `-MODEL LS KNN {a.options.k}`), the first pass of a pair against "
        f"the second. Surfaces: "
        + (
            "the site's validation planes"
            if a.plane_source == "site"
            else "planar patches found automatically in both passes (the site lists no "
            "validation planes, or --auto-planes)"
        )
        + f", and the whole overlap of the passes. Heights are above the water line "
        f"(the scanner's mean height + {a.options.scanner_height_m:g} m).",
        "",
    ]


#: the columns of a pair's table (a "true mount median" column follows on a simulated bundle)
_PAIR_COLUMNS = (
    "surface",
    "height",
    "returns",
    "before mean",
    "before median",
    "before RMS",
    "before p95",
    "after mean",
    "after median",
    "after RMS",
    "after p95",
    "×",
    "expected",
    "floor",
    "calib. σ",
)


def _pair_table(rows) -> list[str]:
    """A pair's comparisons, one row per surface (the highest first, the whole overlap last)."""
    head = list(_PAIR_COLUMNS)
    truth_col = any(c.true_mount is not None for c in rows)
    if truth_col:
        head.append("true mount median")
    out = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for c in sorted(rows, key=lambda c: (c.source == "overlap", -c.height_m)):
        cells = [
            c.name if c.source != "overlap" else "whole overlap",
            f"{c.height_m:.1f} m",
            f"{c.after.count:,}",
            *_stats_cells(c.before),
            *_stats_cells(c.after),
            fmt_ratio(c.improvement),
            fmt_length(c.expected_median_m),
            fmt_length(c.floor_median_m),
            fmt_length(c.boresight_offset_sigma_m),
        ]
        if truth_col:
            cells.append(fmt_length(c.true_mount.median_m if c.true_mount else None))
        out.append("| " + " | ".join(cells) + " |")
    out.append("")
    return out


def _truth_table(rows) -> list[str]:
    """A pair's surfaces against the true planes (a simulated bundle; none without)."""
    truth_rows = [(c, c.truth) for c in rows if c.truth]
    if not truth_rows:
        return []
    out = [
        "Against the true planes (simulated bundle): signed distance of each pass's "
        "returns, mean ± standard deviation.",
        "",
        "| surface | true plane | pass | before | after | true mount |",
        "|---|---|---|---|---|---|",
    ]
    for c, truth in sorted(truth_rows, key=lambda ct: -ct[0].height_m):
        for pid in c.pair:
            cells = [
                f"{fmt_length(truth[s][pid].mean_m)} ± {fmt_length(truth[s][pid].std_m)}"
                if s in truth
                else "—"
                for s in ("before", "after", "true")
            ]
            out.append(f"| {c.name} | {c.truth_plane} | {pid} | " + " | ".join(cells) + " |")
    out.append("")
    return out


def assessment_markdown(a: Assessment, figures: Sequence[Path] = ()) -> str:
    """``assessment.md``: the summary in words, the tables and the figures."""
    out = _intro(a) + ["## Summary", ""]
    out += [f"- {line}" for line in summary_lines(a)]
    out += [
        "",
        "*Expected*: the median C2C the scanner sigmas and the POS sigmas of site.yaml "
        "give for these very returns and C2C's local planes (POS errors as one offset per "
        "pass); *floor*: the median once the two patches' planes coincide (their own scatter "
        "kept); *calib. σ*: the σ of the relative offset the result's own boresight σ "
        "allows.",
        "",
    ]
    for pair in a.pairs:
        rows = [c for c in a.comparisons if c.pair == pair]
        if rows:
            out += [f"## Passes {_pair_label(a, pair)}", ""]
            out += _pair_table(rows) + _truth_table(rows)
    if a.notes:
        out += ["## Notes", ""] + [f"- {n}" for n in a.notes] + [""]
    if figures:
        out += ["## Figures", ""] + [f"![{p.stem}]({p.name})" for p in figures] + [""]
    return "\n".join(out)


def write_assessment(a: Assessment, out_dir) -> dict[str, list[Path]]:
    """Write ``assessment.md``, ``assessment.json`` and the PNG figures into ``out_dir``."""
    from calib.io.outputs import make_output_dir

    d = make_output_dir(out_dir)
    figures = plot_heights(a, d) + plot_histograms(a, d)
    md = d / "assessment.md"
    md.write_text(assessment_markdown(a, figures), encoding="utf-8")
    js = d / "assessment.json"
    js.write_text(json.dumps(a.to_dict(), indent=2) + "\n", encoding="utf-8")
    return {"markdown": [md], "json": [js], "figures": figures}
