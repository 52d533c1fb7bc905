"""``mls design``: the site design study (docs/architecture.md §7 "Design study", :mod:`calib.design.study`)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from cli.options import Force, out_option, scenario_option, seed_option, set_option

HELP = (
    "Site design study: which targets, inclinations, sizes and passes observe the boresight "
    "best, before anything is installed on the quay.\n\n"
    "--scenario NAME runs the whole study of a simulation scenario (montreal, terrestrial or a "
    "scenario YAML): the thesis's visibility criteria (Type I and II) of the eight systematic "
    "errors over plane inclinations and passes, and the predicted boresight σ over pass subsets, "
    "inclination, size, 2- and 3-plane combinations, standoff and target height, under white "
    "noise and under time-correlated POS errors; then it recommends the best layout under a "
    "constraint (--targets, --max-size, --passes) and writes CSV tables, PNG figures and "
    "summary.md to --out. Its yaw_lines group predicts, for a scene with piles, how much lines "
    "parallel to the wall farther out (--yaw-line-offsets) sharpen the boresight yaw.\n\n"
    "--site site.yaml predicts σ for a planned site and its pass pattern: after each pass in "
    "the sailing order, and which pass would help most next; with piles in the site config "
    "(piles: name, center, diameter_m, bottom_height_m, top_height_m) also the lines for yaw."
)


def _number_list(text: str | None, kind, ok, expected: str, hint: str) -> tuple | None:
    """A comma-separated list of ``kind`` values, each ``ok``; else a refusal naming ``hint``
    and what was ``expected``."""
    if text is None:
        return None
    try:
        values = tuple(kind(x) for x in text.replace(" ", "").split(",") if x)
    except ValueError:
        values = ()
    if not values or not all(ok(v) for v in values):
        raise typer.BadParameter(f"{text!r}: expected {expected}", param_hint=hint)
    return values


def _passes(text: str | None) -> tuple[int, ...] | None:
    return _number_list(text, int, lambda _: True, "pass ids separated by commas, e.g. 1,2,3,4", "--passes")


def _offsets(text: str | None) -> tuple[float, ...] | None:
    return _number_list(
        text,
        float,
        lambda x: 0 < x < 120,
        "metres beyond the standoff, each in (0, 120), separated by commas, e.g. 20,40,60",
        "--yaw-line-offsets",
    )


def design(
    scenario: Annotated[
        str | None,
        scenario_option(
            "Study a shipped scenario (montreal, montreal_piles, harbour_cal, terrestrial, tower) or a scenario YAML file."
        ),
    ] = None,
    site: Annotated[
        Path | None,
        typer.Option(
            "--site",
            metavar="SITE.YAML",
            help="Predict σ for the planned site and pattern of a site config (what-if).",
        ),
    ] = None,
    out: Annotated[
        Path | None,
        out_option(
            "Output directory (created): CSV tables, PNG figures, summary.md. Required with "
            "--scenario; with --site it receives whatif.csv. One that holds files is refused unless --force."
        ),
    ] = None,
    force: Force = False,
    jobs: Annotated[
        int, typer.Option("--jobs", "-j", min=1, help="Worker processes (results do not depend on it).")
    ] = 1,
    targets: Annotated[
        int | None,
        typer.Option(
            "--targets",
            min=1,
            help="Constraint of the recommendation: number of targets (default: the scenario's).",
        ),
    ] = None,
    max_size: Annotated[
        float | None,
        typer.Option(
            "--max-size",
            min=0.05,
            help="Constraint: largest target dimension in metres (default: the scenario's largest).",
        ),
    ] = None,
    passes: Annotated[
        str | None,
        typer.Option(
            "--passes",
            metavar="IDS",
            help="Constraint: pass ids the survey may sail, e.g. 1,2,3,4 (default: all).",
        ),
    ] = None,
    group: Annotated[
        list[str] | None,
        typer.Option(
            "--group",
            metavar="GROUP",
            help="Only these σ sweeps (repeatable): passes, site_passes, inclination, size, planes, "
            "standoff, height, layout (the recommendation's search), yaw_lines (lines for yaw).",
        ),
    ] = None,
    error: Annotated[
        list[str] | None,
        typer.Option(
            "--error",
            metavar="ERROR",
            help="Only these systematic errors in the visibility criteria (repeatable): "
            "boresight_roll, boresight_pitch, boresight_yaw, lever_arm_x, lever_arm_y, "
            "lever_arm_z, range_offset, scan_angle_offset; 'none' skips the criteria.",
        ),
    ] = None,
    yaw_line_offsets: Annotated[
        str | None,
        typer.Option(
            "--yaw-line-offsets",
            metavar="METRES",
            help="yaw_lines: pairs of lines parallel to the wall this far beyond the standoff, "
            "comma-separated (default 20,40,60).",
        ),
    ] = None,
    seeds: Annotated[
        int,
        typer.Option(
            "--seeds",
            min=0,
            help="Monte Carlo check: simulate the recommended site and the scenario's own site with "
            "the scenario's noise this many times, adjust, and report the errors side by side.",
        ),
    ] = 0,
    template: Annotated[
        str,
        typer.Option(
            "--template",
            metavar="NAME|PATH",
            help="With --site: the scenario that supplies the profiler, its rates and the vessel motion.",
        ),
    ] = "montreal",
    scanner_height_m: Annotated[
        float | None,
        typer.Option(
            "--scanner-height-m",
            help="With --site: ellipsoidal height of the scanner on the water (default: the site's "
            "reference height).",
        ),
    ] = None,
    seed: Annotated[int, seed_option("Simulation seed (vessel motion phases).")] = 0,
    set_: Annotated[
        list[str] | None,
        set_option("Override a scenario value by dotted key, as for mls sim dataset (repeatable)."),
    ] = None,
    figures: Annotated[bool, typer.Option("--figures/--no-figures", help="Write the PNG figures.")] = True,
) -> None:
    """``mls design`` (its help text is :data:`HELP`)."""
    from rich.console import Console
    from rich.markup import escape

    from calib.core.errors import MlsError

    console = Console(emoji=False)  # ":100:" of file:line:column is no emoji
    if (scenario is None) == (site is None):
        console.print("[red]error:[/red] give exactly one of --scenario and --site")
        raise typer.Exit(2)
    if scenario is not None and out is None:
        console.print("[red]error:[/red] --scenario needs --out DIR for the tables and figures")
        raise typer.Exit(2)
    try:
        if site is not None:
            _what_if(console, site, out, force, template, scanner_height_m, seed)
        else:
            _study(
                console,
                scenario,
                out,
                force,
                jobs,
                targets,
                max_size,
                _passes(passes),
                _offsets(yaw_line_offsets),
                group or [],
                error or [],
                seeds,
                seed,
                set_ or [],
                figures,
            )
    except (MlsError, OSError) as e:
        console.print(f"[red]error:[/red] {escape(str(e))}", highlight=False, soft_wrap=True)
        raise typer.Exit(2) from None


def _progress(console):
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    return Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        console=console,
        transient=True,
    )


def _study(
    console,
    scenario,
    out,
    force,
    jobs,
    targets,
    max_size,
    passes,
    yaw_offsets_m,
    group,
    error,
    seeds,
    seed,
    overrides,
    figures,
) -> None:
    from calib.design.layouts import default_spec
    from calib.design.sitecheck import compare_sites
    from calib.design.study import run_study
    from calib.design.summary import write_study
    from calib.io.outputs import hold_output_dir
    from calib.sim.scenariofile import load_scenario

    base = load_scenario(scenario, list(overrides))
    changes: dict = {"seed": seed, "n_targets": targets, "max_size_m": max_size, "passes": passes}
    if group:
        changes["groups"] = tuple(group)
    if yaw_offsets_m is not None:
        changes["yaw_line_offsets_m"] = yaw_offsets_m
    if error:
        changes["errors"] = () if list(error) == ["none"] else tuple(error)
    spec = default_spec(base, **changes)
    hold_output_dir(out, "--out", force)  # the options are valid: before the study; held to the end
    with _progress(console) as bar:
        task = bar.add_task(f"design study of {base.name}", total=None)
        result = run_study(
            base, spec, jobs=jobs, progress=lambda d, n: bar.update(task, completed=d, total=n)
        )
        empirical = None
        rec = result.recommendation
        if seeds and rec is not None:
            bar.update(task, description=f"Monte Carlo, {seeds} seeds", completed=0, total=None)
            empirical = compare_sites(
                base, rec, seeds, jobs, lambda d, n: bar.update(task, completed=d, total=n)
            )
        bar.update(task, description="writing tables and figures", completed=0, total=None)
        files = write_study(result, out, empirical, figures=figures, jobs=jobs)
    _study_table(console, result, empirical)
    _yaw_table(console, result)
    console.print(
        f"wrote {len(files)} files to {out} in {result.runtime_s:.1f} s of study "
        f"(summary: {Path(out) / 'summary.md'})",
        highlight=False,
    )


def _study_table(console, result, empirical) -> None:
    from rich import box
    from rich.table import Table

    from calib.design.prediction import ESTIMATOR_MODEL
    from calib.design.scenes import surface_inclination_deg

    rec = result.recommendation
    t = Table(
        title=f"{result.scenario.name}: predicted boresight σ (°)",
        title_justify="left",
        box=box.SIMPLE_HEAD,
        pad_edge=False,
    )
    for col in ("site", "model", "roll", "pitch", "yaw", "total"):
        t.add_column(col, justify="left" if col in ("site", "model") else "right", no_wrap=True)
    if rec is not None:
        real = ESTIMATOR_MODEL.get(rec.estimator_name or "gls", "gls")
        for name, row in (("recommended", rec.row), ("scenario's", rec.baseline_row)):
            if row is None:
                continue
            for m, label in (("white", "white"), (real, f"realistic ({rec.estimator_name or 'gls'})")):
                t.add_row(
                    name,
                    label,
                    *(f"{row[f'sigma_{m}_{a}_deg']:.4f}" for a in ("roll", "pitch", "yaw", "total")),
                )
        console.print(t)
        console.print(
            "recommended: "
            + ", ".join(
                f"{s.name} {surface_inclination_deg(s):g}° {s.width_m:g}×{s.height_m:g} m at along {s.along_m + 0.0:+.2f} m, "
                f"up {s.up_m:.2f} m, out {s.out_m + 0.0:+.2f} m"
                for s in rec.layout.targets
            )
            + f" — adjust with --estimator {rec.estimator_name or 'gls'}",
            highlight=False,
        )
    from calib.design.summary import findings

    for f in findings(result):
        console.print(
            f"  {'[green]yes[/green]' if f['holds'] else '[yellow]no[/yellow]'}  {f['name']}: {f['ours']}",
            highlight=False,
        )
    if empirical:
        for name, r in empirical["rms_deg"].items():
            console.print(
                f"  Monte Carlo ({empirical['seeds']} seeds) {name}: RMS roll "
                f"{r[0]:.4f}°, pitch {r[1]:.4f}°, yaw {r[2]:.4f}°",
                highlight=False,
            )


def _yaw_table(console, result) -> None:
    from rich import box
    from rich.table import Table

    from calib.design.yawlines import best_for_yaw

    if not result.yaw_lines:
        if result.yaw_lines_note:
            console.print(f"lines for yaw: not predicted ({result.yaw_lines_note})", highlight=False)
        return
    t = Table(title="lines for yaw: GLS σ (mdeg)", title_justify="left", box=box.SIMPLE_HEAD, pad_edge=False)
    for col in ("lines", "features", "roll", "pitch", "yaw"):
        t.add_column(col, justify="left" if col in ("lines", "features") else "right", no_wrap=True)
    for r in result.yaw_lines:
        t.add_row(
            r["lines"],
            r["features"],
            *(f"{1000 * r[f'sigma_{a}_deg']:.1f}" for a in ("roll", "pitch", "yaw")),
        )
    console.print(t)
    best = best_for_yaw(result.yaw_lines)
    console.print(
        f"for yaw: sail {best['lines']} with the {best['features']} (σ yaw {1000 * best['sigma_yaw_deg']:.1f} mdeg)",
        highlight=False,
    )


def _what_if(console, site_path, out, force, template, scanner_height_m, seed) -> None:
    from rich import box
    from rich.table import Table

    from calib.design.prediction import ESTIMATOR_MODEL
    from calib.design.whatif import what_if, write_what_if
    from calib.io.outputs import hold_output_dir
    from calib.io.site import load_site

    site = load_site(site_path)
    if out is not None:
        hold_output_dir(out, "--out", force)  # before the prediction; held to the end
    with _progress(console) as bar:
        bar.add_task(f"predicting σ for {site_path}", total=None)
        w = what_if(site, template, scanner_height_m, seed)
    t = Table(
        title=f"{site_path}: predicted boresight σ (°) after each pass",
        title_justify="left",
        box=box.SIMPLE_HEAD,
        pad_edge=False,
    )
    for col in (
        "passes",
        "points",
        "white roll",
        "pitch",
        "yaw",
        "realistic roll",
        "pitch",
        "yaw",
        "adjust",
        "next best",
    ):
        t.add_column(col, justify="right", no_wrap=True)
    for r in w.rows:
        real = ESTIMATOR_MODEL.get(r["estimator"] or "gls", "gls")
        cells = [f"{r[f'sigma_{m}_{a}_deg']:.4f}" for m in ("white", real) for a in ("roll", "pitch", "yaw")]
        t.add_row(
            ",".join(map(str, r["passes"])),
            str(r["n_points"]),
            *cells,
            r["estimator"] or "—",
            str(r["next_best_pass"] or "—"),
        )
    console.print(t)
    console.print(
        f"|ρ(roll, scan-angle offset)| = {w.roll_scan_correlation:.4f}: the boresight "
        f"absorbs a scan-angle offset",
        highlight=False,
    )
    _yaw_table(console, w)
    if out is not None:
        files = write_what_if(w, out)
        console.print(f"wrote {', '.join(str(f) for f in files)}", highlight=False)
