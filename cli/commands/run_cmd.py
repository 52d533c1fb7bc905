"""``mls calib run``: boresight calibration of a bundle. Added to the ``mls calib``
group of :mod:`cli.commands.calib_cmd`; the work is :func:`calib.boresight.pipeline.run_bundle`."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated, NoReturn

import typer

from cli.commands.calib_cmd import app, parse_triple_deg
from cli.options import HistoryDb, bundle_argument, force_option, out_option, skip_uncovered_option

if TYPE_CHECKING:
    from rich.console import Console
    from rich.progress import ProgressColumn

    from calib.boresight.pipeline import CalibrationOptions, CalibrationRun
    from calib.watch.targetless import TargetlessRun

RUN_HELP = (
    "Calibrate the boresight from a calibration bundle (or a recorded session).\n\n"
    "Georeferences every pass with the a-priori mount, extracts each target (seeded by its "
    "centre in site.yaml, RANSAC plane, its own rectangle by size and reflectivity), runs the "
    "plane-based adjustment (GLS over Gauss–Markov POS errors, with tie patches of the scene, "
    "unless --estimator / --tie-patches say otherwise) and writes result.json, report.md and PNG plots into "
    "--out (default BUNDLE/calib/). Prints the estimates with their formal and realistic σ "
    "(use the realistic one: POS errors are correlated in time) and records the result in "
    "the calibration history. A session directory is first exported to OUT/bundle as 'mls "
    "export SESSION --bundle OUT/bundle' would (OUT defaults to SESSION/calib/). An OUT that "
    "already holds files is refused unless --force. Warnings (a pass planned in site.yaml "
    "without points, points of an unplanned pass, points dropped by --skip-uncovered, …) go "
    "to stderr and into report.md.\n\n"
    "Every result carries a verdict (result.json 'verdict' and its reasons): trusted; questionable "
    "(a check failed: a target group removed as a gross error, a target lost in two passes, targets "
    "and scene disagreeing, τ-sensitivity, jackknife, a poorly observed angle); refused (no "
    "convergence, σ̂0² > 2, a gross error that could not be removed). A refused result exits with "
    "status 4 and is not recorded in the history unless --accept-refused.\n\n"
    "Without targets (site.yaml lists none, or --targetless) the boresight comes from the scene "
    "alone: tie patches and piles seen from lines of different headings and offsets, the mount "
    "watch's estimator over the whole survey from the a-priori mount, repeated until it settles; "
    "the report compares it with the last calibration with targets in the history. A session is "
    "then not exported whole: its lines (the marked passes, else the straight runs of the heading, "
    "as mls watch cuts them) are read chunk by chunk and thinned at random (seeded) to the returns "
    "the calibration uses (1 M), written to OUT/bundle.\n\n"
    "Example: mls sim dataset --scenario montreal --out sim-mtl && mls calib run sim-mtl "
    "--mount lidar-2024"
)


def _fail(message: str, code: int = 1) -> NoReturn:
    """One line ``error: <message>`` on stderr and exit status ``code``."""
    from rich.console import Console
    from rich.markup import escape

    # emoji=False: "points.csv:100:3" stays itself (rich would turn ":100:" into an emoji)
    Console(stderr=True, emoji=False).print(
        f"[red]error:[/red] {escape(message)}", highlight=False, soft_wrap=True
    )
    raise typer.Exit(code)


def _is_session(path: Path) -> bool:
    """An acquisition session directory (MCAP segments; the daemon also keeps a copy of the
    site file there) rather than a bundle (points.csv)."""
    return (
        path.is_dir()
        and any(path.glob("*.mcap"))
        and not any((path / n).exists() for n in ("points.csv", "points.csv.gz"))
    )


def _progress_callback(progress):
    tasks: dict[str, int] = {}

    def update(stage: str, done: float, total: float | None) -> None:
        if stage not in tasks:
            for t in tasks.values():  # the previous stage is over
                task = progress.tasks[t]
                progress.update(t, completed=task.total if task.total else 1, total=task.total or 1)
            tasks[stage] = progress.add_task(stage, total=total)
        progress.update(tasks[stage], completed=done, total=total)

    return update


def _table(run, out_dir: Path):
    import numpy as np
    from rich.table import Table

    res = run.result
    chi2 = res.chi2_test()
    table = Table(
        title=f"boresight → {out_dir / 'result.json'}",
        caption=(
            f"σ̂0² {res.sigma0_squared:.3f} (χ² test "
            f"{'passed' if chi2['passed'] else 'FAILED'}) · {res.iterations} iterations · {res.n_points:,} points, "
            f"{res.outlier_point_ids.size} outliers · {run.timings_s['total_s']:.1f} s"
        ),
    )
    table.add_column("angle")
    for col in ("estimate °", "σ formal °", "σ realistic °"):
        table.add_column(col, justify="right")
    for name, b, sf, sr in zip(
        ("roll", "pitch", "yaw"),
        np.degrees(res.boresight_rad),
        np.degrees(res.sigma_formal_rad),
        np.degrees(res.sigma_realistic_rad),
        strict=True,
    ):
        table.add_row(name, f"{b:.4f}", f"{sf:.4f}", f"{sr:.4f}")
    return table


def _say_verdict(console, verdict) -> None:
    """The verdict, and each reason on its own line."""
    from rich.markup import escape

    colour = {"trusted": "green", "questionable": "yellow", "refused": "red"}[verdict.status]
    console.print(f"verdict: [bold {colour}]{verdict.status}[/]", highlight=False)
    for r in verdict.reasons:
        console.print(f"  · {escape(r)}", highlight=False, soft_wrap=True)


def _export(session: Path, bundle_dir: Path, console, columns) -> Path:
    """Export a recorded session to a bundle (what ``mls export`` does); returns the bundle."""
    from rich.progress import Progress

    from calib.core.errors import MlsError
    from office.jobs.export import export_session

    try:
        with Progress(*columns, console=console, transient=True) as progress:
            res = export_session(session, bundle_dir, progress=_progress_callback(progress))
    except (MlsError, OSError) as e:
        _fail(
            f"{session} is a recorded session and could not be exported to a bundle: {e} "
            f"(run 'mls export {session} --bundle DIR' with its options, then 'mls calib run "
            f"DIR')"
        )
    console.print(
        f"exported the session to {res.bundle} ({res.points:,} points, "
        f"{len(res.passes)} passes from {res.pass_source})",
        highlight=False,
    )
    _warn(res.warnings)
    return Path(res.bundle)


def _export_thinned(session: Path, bundle_dir: Path, console, columns) -> Path:
    """A targetless calibration's bundle of a recorded session: its lines (marked passes, else
    the straight runs of the heading) thinned at random to the returns the calibration uses."""
    from rich.progress import Progress

    from calib.core.errors import MlsError
    from calib.watch.targetless import TARGETLESS_OPTIONS
    from office.deliver.surveylines import thinned_bundle

    try:
        with Progress(*columns, console=console, transient=True) as progress:
            res = thinned_bundle(
                session, bundle_dir, TARGETLESS_OPTIONS.max_points, progress=_progress_callback(progress)
            )
    except (MlsError, OSError) as e:
        _fail(f"{session}: its lines could not be read for a targetless calibration: {e}")
    console.print(
        f"read {res.n_lines} lines ({res.line_seconds / 60:.1f} min) of the session: {res.n_points:,} returns "
        f"drawn at random over the lines, in {res.bundle}",
        highlight=False,
    )
    _warn(res.warnings)
    return res.bundle


def _warn(warnings) -> None:
    """Each warning on one line of stderr."""
    from rich.console import Console
    from rich.markup import escape

    err = Console(stderr=True, emoji=False)
    for w in warnings:
        err.print(f"[yellow]warning:[/yellow] {escape(w)}", highlight=False, soft_wrap=True)


@app.command("run", help=RUN_HELP)
def run(
    bundle: Annotated[
        Path,
        bundle_argument(
            "Calibration bundle "
            "directory (site.yaml, trajectory.csv or .sbet, "
            "points.csv[.gz]), or a recorded session directory.",
            metavar="BUNDLE|SESSION",
        ),
    ],
    out: Annotated[Path | None, out_option("Output directory (created); default BUNDLE/calib/.")] = None,
    force: Annotated[
        bool,
        force_option(
            "Write into an output directory that already holds files (a previous run's: same names replaced)."
        ),
    ] = False,
    skip_uncovered: Annotated[
        bool,
        skip_uncovered_option(
            "Drop the points outside the trajectory or in its gaps (counted per pass in the "
            "warnings and the report) instead of stopping with an error."
        ),
    ] = False,
    subsample: Annotated[
        float | None,
        typer.Option(
            "--subsample",
            metavar="M",
            help="Voxel subsampling of each target per pass (m), "
            "e.g. 0.05: one point per voxel, the nearest its centre (thesis §4.4.4). Default: "
            "every extracted point.",
        ),
    ] = None,
    estimate: Annotated[
        str,
        typer.Option(
            "--estimate",
            metavar="LIST",
            help="Extra unknowns, comma-separated: range_offset, "
            "lever_arm_x, lever_arm_y, latency, pass_offsets (each reported with its correlation "
            "to the boresight; refused with an explanation when not observable).",
        ),
    ] = "",
    estimator: Annotated[
        str,
        typer.Option(
            "--estimator",
            metavar="NAME",
            help="gls (default): the POS errors as Gauss–Markov processes estimated with the "
            "boresight (its σ is realistic); thesis: white weights as in the thesis, realistic σ by "
            "propagation; pass_offsets: thesis weights plus a translation per pass. The report shows "
            "the default beside the thesis estimator.",
        ),
    ] = "gls",
    tie_patches: Annotated[
        str,
        typer.Option(
            "--tie-patches",
            metavar="MODE",
            help="auto (default, with gls): add planar patches of the wall and other surfaces seen "
            "from two or more headings, each with its own plane and roughness; off: targets only.",
        ),
    ] = "auto",
    apriori_deg: Annotated[
        str | None,
        typer.Option(
            "--apriori-deg",
            metavar="R,P,Y",
            help="A-priori boresight roll,pitch,yaw in "
            "degrees (canonical convention); default site.yaml's mount.boresight_apriori_deg.",
        ),
    ] = None,
    correlation_time_s: Annotated[
        float | None,
        typer.Option(
            "--correlation-time-s",
            metavar="S",
            help="Correlation time of the POS errors "
            "(first-order Gauss–Markov); default site.yaml's pos_sigmas.correlation_time_s, else "
            "estimated from the data with gls (the report shows τ/3, τ, 3τ) or 60 s with thesis.",
        ),
    ] = None,
    error_model: Annotated[
        str,
        typer.Option(
            "--error-model",
            metavar="MODEL",
            help="POS error model of the "
            "realistic σ: gauss_markov (correlated in time), pass_bias (constant within each "
            "pass) or white (independent: realistic = formal).",
        ),
    ] = "gauss_markov",
    extraction: Annotated[
        str,
        typer.Option(
            "--extraction",
            metavar="MODE",
            help="seeded: search around each target's "
            "centre in site.yaml; auto: find bright planar rectangles of the configured sizes.",
        ),
    ] = "seeded",
    search_radius_m: Annotated[
        float,
        typer.Option(
            "--search-radius-m",
            help="Seeded search radius beyond each target's half-diagonal "
            "(m): covers a wrong a-priori boresight and approximate centres.",
        ),
    ] = 2.0,
    mount: Annotated[
        str,
        typer.Option(
            "--mount",
            metavar="ID",
            help="Mount id the result "
            "is recorded under in the history (a new id after every "
            "re-installation of the scanner).",
        ),
    ] = "default",
    vessel: Annotated[
        str | None, typer.Option("--vessel", help="Vessel name for the history; default site.yaml's vessel.")
    ] = None,
    db: HistoryDb = None,
    no_history: Annotated[
        bool, typer.Option("--no-history", help="Do not record the result in the calibration history.")
    ] = False,
    no_plots: Annotated[
        bool, typer.Option("--no-plots", help="Write result.json and report.md only (faster).")
    ] = False,
    targetless: Annotated[
        bool,
        typer.Option(
            "--targetless",
            help="Calibrate from the scene alone (tie patches and piles seen from lines of different "
            "headings and offsets), not from targets; what happens when site.yaml lists no targets. "
            "Compared in the report with the last calibration with targets in the history.",
        ),
    ] = False,
    accept_refused: Annotated[
        bool,
        typer.Option(
            "--accept-refused",
            help="Exit 0 and record the result in the history even when its verdict is 'refused' (it stays "
            "marked refused in result.json, the report and the history).",
        ),
    ] = False,
) -> None:
    """``mls calib run`` (its help text is :data:`RUN_HELP`)."""
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, TextColumn, TimeElapsedColumn

    from calib.core.errors import MlsError
    from calib.io.outputs import hold_output_dir

    if not bundle.is_dir():
        _fail(
            f"{bundle}: not a directory (a calibration bundle is a directory with site.yaml, "
            f"trajectory.csv and points.csv)"
        )
    options = _calibration_options(
        apriori_deg,
        subsample,
        correlation_time_s,
        estimate,
        estimator,
        tie_patches,
        error_model,
        extraction,
        search_radius_m,
    )
    out_dir = out if out is not None else bundle / "calib"
    try:  # before anything is computed or exported; held until the command ends
        hold_output_dir(out_dir, "--out" if out is not None else "the output directory (--out)", force)
    except MlsError as e:
        _fail(str(e), 2)

    console = Console()
    columns = (TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn())
    targetless = targetless or not _site_targets(bundle)  # a session keeps a copy of its site file
    if _is_session(bundle):
        export = _export_thinned if targetless else _export
        bundle = export(bundle, out_dir / "bundle", console, columns)
    cal: CalibrationRun | TargetlessRun
    if targetless:
        history = None if no_history else (vessel, mount, db)
        cal = _calibrate_targetless(bundle, out_dir, options, console, columns, skip_uncovered, history)
    else:
        cal = _calibrate(
            bundle, out_dir, options, console, columns, plots=not no_plots, skip_uncovered=skip_uncovered
        )
    _judge(cal, out_dir, console, accept_refused)
    if not no_history:
        _record(cal, bundle, out_dir, console, vessel, mount, db)


def _calibration_options(
    apriori_deg: str | None,
    subsample: float | None,
    correlation_time_s: float | None,
    estimate: str,
    estimator: str,
    tie_patches: str,
    error_model: str,
    extraction: str,
    search_radius_m: float,
) -> CalibrationOptions:
    """The pipeline's options from the command's; exit status 2 for a value it refuses."""
    import math

    import numpy as np

    from calib.boresight.pipeline import CalibrationOptions
    from calib.core.errors import MlsError
    from calib.extraction.extract import ExtractOptions

    try:
        apriori = parse_triple_deg(apriori_deg, "--apriori-deg") if apriori_deg else None
    except typer.BadParameter as e:
        _fail(f"--apriori-deg: {e.message}", 2)
    if subsample is not None and not (math.isfinite(subsample) and subsample > 0):
        _fail(f"--subsample {subsample!r}: expected a positive voxel size in metres, e.g. 0.05", 2)
    if correlation_time_s is not None and not (math.isfinite(correlation_time_s) and correlation_time_s > 0):
        _fail(f"--correlation-time-s {correlation_time_s!r}: expected a positive number of seconds", 2)
    extras = tuple(e.strip() for e in estimate.split(",") if e.strip())
    try:
        return CalibrationOptions(
            subsample_m=subsample,
            estimate=extras,
            estimator=estimator,
            tie_patches=tie_patches,
            apriori_rad=None if apriori is None else tuple(np.radians(apriori)),
            error_model=error_model,
            correlation_time_s=correlation_time_s,
            extraction=ExtractOptions(mode=extraction, search_radius_m=search_radius_m),
        )
    except MlsError as e:  # an option the pipeline refuses
        _fail(str(e), 2)


def _calibrate(
    bundle: Path,
    out_dir: Path,
    options: CalibrationOptions,
    console: Console,
    columns: tuple[ProgressColumn, ...],
    *,
    plots: bool,
    skip_uncovered: bool,
) -> CalibrationRun:
    """Calibrate the bundle into ``out_dir`` (a progress bar per stage); print the result table,
    its warnings and what was written."""
    from rich.progress import Progress

    from calib.boresight.pipeline import run_bundle
    from calib.core.errors import MlsError

    try:
        with Progress(*columns, console=console, transient=True) as progress:
            cal, paths = run_bundle(
                bundle,
                out_dir,
                options,
                _progress_callback(progress),
                plots=plots,
                skip_uncovered=skip_uncovered,
            )
    except (MlsError, OSError) as e:  # OSError: reading the bundle or writing into out_dir
        _fail(str(e))
    console.print(_table(cal, out_dir))
    _warn(cal.warnings)
    pngs = sum(p.suffix == ".png" for p in paths)
    console.print(
        f"wrote result.json, report.md{f' and {pngs} plots' if pngs else ''} to {out_dir}", highlight=False
    )
    return cal


def _site_targets(bundle: Path) -> bool:
    """Whether the bundle's site.yaml lists targets (an unreadable one: the calibration says why)."""
    from calib.core.errors import MlsError
    from calib.io.site import load_site

    try:
        return bool(load_site(bundle / "site.yaml").targets)
    except (MlsError, OSError):
        return True


def _calibrate_targetless(
    bundle: Path,
    out_dir: Path,
    options: CalibrationOptions,
    console: Console,
    columns: tuple[ProgressColumn, ...],
    skip_uncovered: bool,
    history: tuple | None,
) -> TargetlessRun:
    """The targetless calibration of the bundle into ``out_dir``, compared with the last
    calibration with targets of ``history`` (vessel, mount, db; None: not looked up)."""
    from rich.markup import escape
    from rich.progress import Progress

    from calib.core.errors import MlsError
    from calib.watch.targetless import last_target_calibration, targetless_bundle
    from calib.watch.targetlessreport import compare_with, sigma_text, write_targetless

    console.print("targetless: no target used, the boresight from the scene's tie patches and piles")
    try:
        with Progress(*columns, console=console, transient=True) as progress:
            run = targetless_bundle(
                bundle,
                apriori_rad=options.apriori_rad,
                progress=_progress_callback(progress),
                skip_uncovered=skip_uncovered,
            )
        previous = None
        if history is not None:
            vessel, mount, db = history
            previous = last_target_calibration(vessel or run.site.vessel, mount, db)
        comparison = compare_with(run, previous)
        write_targetless(run, out_dir, comparison)
    except (MlsError, OSError) as e:
        _fail(str(e))
    console.print(escape(sigma_text(run)), highlight=False)
    if comparison is not None:
        console.print(f"against {comparison['with']}: {escape(comparison['message'])}", highlight=False)
    _warn(run.warnings)
    console.print(f"wrote result.json and report.md to {out_dir}", highlight=False)
    return run


def _judge(
    cal: CalibrationRun | TargetlessRun, out_dir: Path, console: Console, accept_refused: bool
) -> None:
    """Say the verdict; a refused result ends the command (its own exit status) unless
    ``--accept-refused``."""
    from calib.boresight.checks.verdict import REFUSED_EXIT_STATUS

    verdict = cal.verdict
    _say_verdict(console, verdict)
    if verdict.status == "refused" and not accept_refused:
        _fail(
            f"verdict refused: the result in {out_dir} must not be used (see report.md); it was not recorded "
            f"in the history. --accept-refused records it anyway, marked",
            REFUSED_EXIT_STATUS,
        )


def _record(
    cal: CalibrationRun | TargetlessRun,
    bundle: Path,
    out_dir: Path,
    console: Console,
    vessel: str | None,
    mount: str,
    db: Path | None,
) -> None:
    """Record the result in the calibration history; exit status 1 when it cannot be."""
    import sqlite3

    from calib.assess.history import record_result
    from calib.core.errors import MlsError

    try:
        row = record_result(cal.doc, bundle, vessel or cal.site.vessel, mount, db=db)
    except (MlsError, OSError, sqlite3.Error) as e:
        _fail(f"the result is in {out_dir} but was not recorded in the history: {e}")
    console.print(f"recorded in the calibration history as #{row} (mount {mount})", highlight=False)
