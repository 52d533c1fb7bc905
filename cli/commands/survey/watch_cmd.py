"""``mls watch SESSION|BUNDLE --out DIR``: the mount watch over a finished survey
(:mod:`office.deliver.watchjob`, docs/architecture.md §7.8)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated

import typer

from cli.options import Calibration, SurveySource, force_option, out_option

HELP = (
    "Watch the scanner mount over a finished survey: did the boresight move during it?\n\n"
    "The survey (a recorded session, or a calibration bundle) is read line by line — the pass "
    "marks, or in a session without marks the straight runs of the heading — and grouped into "
    "blocks of consecutive lines of opposite headings. In each block the planar pieces of the "
    "scene seen from both headings (tie patches: the quay wall, piles, fenders…) are "
    "georeferenced with the calibrated mount (--calibration: a result.json or a history id such "
    "as #12; without it the vessel config's a-priori boresight) and the boresight correction that "
    "reconciles them is estimated with the POS errors modelled (GLS), so an INS drift is not "
    "read as a mount change. A sequential test (CUSUM per angle, tuned to --shift-deg, with at "
    "most --false-alarms-per-hour) tests the corrections against the calibrated mount, as the "
    "daemon does live.\n\n"
    "OUT gets watch.md (the verdict, then block by block the correction with σ and which lines "
    "and patches carried it), watch.json and watch.png (the correction along time with ±σ, the "
    "test statistic and the alarm). Exit status 3 when the mount moved. A non-empty OUT is "
    "refused unless --force.\n\n"
    "Example: mls watch /var/lib/mls/sessions/20240709T140000Z_survey-1 --calibration "
    "calib-0709/result.json --out watch-0709"
)

#: exit status when the watch finds that the mount moved
EXIT_SHIFT = 3


def watch(
    source: SurveySource,
    out: Annotated[Path, out_option("Directory of the report (created).")],
    calibration: Calibration = None,
    shift_deg: Annotated[
        float, typer.Option("--shift-deg", min=0.001, help="The change the test is tuned to (deg).")
    ] = 0.1,
    false_alarms_per_hour: Annotated[
        float, typer.Option("--false-alarms-per-hour", min=1e-6, help="The test's false-alarm rate bound.")
    ] = 0.01,
    max_points_per_s: Annotated[
        float,
        typer.Option(
            "--max-points-per-s", min=100.0, help="Returns used per second of survey (evenly thinned)."
        ),
    ] = 20_000.0,
    min_line_s: Annotated[
        float, typer.Option("--min-line-s", min=1.0, help="Shortest line (s) without pass marks.")
    ] = 20.0,
    plot: Annotated[bool, typer.Option("--plot/--no-plot", help="Write watch.png.")] = True,
    force: Annotated[bool, force_option("Replace the report in a non-empty OUT.")] = False,
) -> None:
    """``mls watch`` (its help text is :data:`HELP`)."""
    from rich.console import Console
    from rich.markup import escape
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TaskID, TextColumn, TimeElapsedColumn

    from acquire import __version__
    from calib.watch.report import run_verdict
    from calib.watch.sequential import WatchDesign
    from office.deliver.watchjob import WatchJob, run_watch_job

    console, err = Console(), Console(stderr=True, emoji=False)
    from calib.io.outputs import hold_output_dir  # the report's writer lock, held to the end

    hold_output_dir(out, "--out", force)
    job = WatchJob(
        source,
        out,
        calibration,
        design=WatchDesign(shift_rad=math.radians(shift_deg), false_alarms_per_hour=false_alarms_per_hour),
        max_points_per_s=max_points_per_s,
        min_line_s=min_line_s,
        force=force,
        plot=plot,
    )
    columns = (TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn())
    with Progress(*columns, console=err, transient=True) as bar:
        tasks: dict[str, TaskID] = {}

        def progress(stage: str, done: int, total: int) -> None:
            if stage not in tasks:
                tasks[stage] = bar.add_task(stage, total=total)
            bar.update(tasks[stage], completed=done, total=total)

        outcome = run_watch_job(job, f"marine-mls {__version__}", progress)
    for w in outcome.warnings:
        err.print(f"[yellow]warning:[/] {escape(w)}")
    run = outcome.run
    console.print(
        f"{len(outcome.lines)} line(s), {len(run.blocks)} block(s), {outcome.n_points:,} returns used"
    )
    console.print(("[bold red]" if run.alarm else "[bold green]") + escape(run_verdict(run)))
    for p in outcome.written:
        console.print(f"  {escape(str(p))}")
    if run.alarm is not None:
        raise typer.Exit(EXIT_SHIFT)
