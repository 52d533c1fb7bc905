"""``mls georef SESSION|BUNDLE --out DIR``: a whole survey → LAZ tiles with per-point σ
(:mod:`office.deliver`, docs/architecture.md §8)."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, TypeVar

import typer

from cli.options import Calibration, Las, SurveySource, crs_option, force_option, out_option

if TYPE_CHECKING:
    from office.deliver.engine import GeorefResult

#: a window option: (min, max) or a box
_WindowT = TypeVar("_WindowT", bound=tuple[float, ...])

HELP = (
    "Georeference a whole survey (a recorded session, or a calibration bundle) into LAS 1.4 "
    "point-format-6 tiles with per-point uncertainty.\n\n"
    "Every return is georeferenced with the trajectory (the session's INS, or a post-processed "
    "--sbet with its --smrmsg) and the calibrated mount (--calibration: a result.json or a "
    "calibration-history id such as #12; without it the vessel config's a-priori boresight), "
    "filtered (range and scan-angle windows, intensity floor, time window, the vessel's own "
    "returns) and written to OUT as one tile per survey line (default; returns outside the "
    "lines are left out unless --keep-transits) or as squares of --tile-m metres in the output "
    "--crs. Each point carries the extra-bytes dimensions sigma_h_m and sigma_v_m (1σ horizontal "
    "and vertical, from the trajectory's σ at that instant, the scanner's range and angle σ and "
    "the calibration's boresight and lever-arm covariance); each file carries the calibration's "
    "provenance in a VLR (mount id, result fingerprint, software version). OUT/summary.md and "
    "summary.json list the files with their σ.\n\n"
    "The survey is cut into time chunks (--chunk-s) that run in this process, or on a Dask "
    "cluster: --workers N starts a local cluster of N worker processes, --scheduler "
    "tcp://HOST:8786 uses a running one (its workers must see OUT). A killed job continues with "
    "--resume and loses no finished tile; a tile file is never half written. A non-empty OUT is "
    "refused unless --resume or --force.\n\n"
    "Example: mls georef /var/lib/mls/sessions/20240709T140000Z_survey-1 --calibration "
    "calib-0709/result.json --out deliverable-0709 --workers 2"
)


def georef(
    source: SurveySource,
    out: Annotated[Path, out_option("Directory of the tiles (created).")],
    calibration: Calibration = None,
    history: Annotated[
        Path | None, typer.Option("--history", help="Calibration history database (for #ID).")
    ] = None,
    sbet: Annotated[
        Path | None, typer.Option("--sbet", help="Post-processed trajectory (Applanix SBET).")
    ] = None,
    smrmsg: Annotated[Path | None, typer.Option("--smrmsg", help="The SBET's sigmas (SMRMSG).")] = None,
    crs: Annotated[str, crs_option("Output CRS: utm (the zone of the site), lgf, or EPSG:…")] = "utm",
    tile_m: Annotated[
        float | None,
        typer.Option(
            "--tile-m", min=1.0, help="Square tiles of this size (CRS units) instead of one per line."
        ),
    ] = None,
    keep_transits: Annotated[
        bool,
        typer.Option(
            "--keep-transits", help="Line tiles: put the returns outside every line into tile 'transit'."
        ),
    ] = False,
    max_tile_points: Annotated[
        int,
        typer.Option(
            "--max-tile-points", min=1000, help="Split a larger tile into files -p01, -p02… (time order)."
        ),
    ] = 20_000_000,
    chunk_s: Annotated[
        float, typer.Option("--chunk-s", min=0.5, max=600.0, help="Seconds of survey per task.")
    ] = 2.0,
    range_m: Annotated[tuple[float, float], typer.Option("--range-m", help="Range window MIN MAX (m).")] = (
        1.0,
        119.0,
    ),
    scan_angle_deg: Annotated[
        tuple[float, float] | None,
        typer.Option("--scan-angle-deg", help="Window of the scanner's own angle MIN MAX (deg, 0…360)."),
    ] = None,
    intensity_min: Annotated[
        int, typer.Option("--intensity-min", min=0, max=65535, help="Intensity floor (count).")
    ] = 0,
    time_gps_s: Annotated[
        tuple[float, float] | None,
        typer.Option("--time-gps-s", help="GPS-time window START END (s since the GPS epoch)."),
    ] = None,
    vessel_box_m: Annotated[
        tuple[float, float, float, float, float, float] | None,
        typer.Option(
            "--vessel-box-m",
            help="The vessel in the body frame (x fwd, y stbd, z down; m): X0 X1 Y0 Y1 Z0 Z1; its returns are left out.",
        ),
    ] = None,
    las: Las = False,
    workers: Annotated[
        int | None,
        typer.Option("--workers", min=1, help="Run on a local Dask cluster of this many worker processes."),
    ] = None,
    scheduler: Annotated[
        str | None,
        typer.Option("--scheduler", help="Run on a Dask cluster: 'local' (all cores) or tcp://HOST:8786."),
    ] = None,
    resume: Annotated[
        bool, typer.Option("--resume", help="Continue a job that stopped (same inputs).")
    ] = False,
    force: Annotated[bool, force_option("Start over in a non-empty OUT (files replaced).")] = False,
) -> None:
    """``mls georef`` (its help text is :data:`HELP`)."""
    from office.deliver.engine import run_georef
    from office.deliver.executors import DaskExecutor, InProcess
    from office.deliver.options import Filters, GeorefError, GeorefOptions

    if resume and force:
        raise GeorefError("--resume and --force: choose one (continue the job, or start over)")
    options = GeorefOptions(
        crs=crs,
        tiling="square" if tile_m else "line",
        tile_m=tile_m,
        keep_transits=keep_transits,
        chunk_s=chunk_s,
        max_tile_points=max_tile_points,
        compress=not las,
        filters=Filters(
            range_m=range_m,
            scan_angle_deg=_window(scan_angle_deg),
            intensity_min=intensity_min,
            time_gps_s=_window(time_gps_s),
            vessel_box_m=_window(vessel_box_m),
        ),
    )
    executor = DaskExecutor(scheduler, workers) if (workers or scheduler) else InProcess()
    try:
        with _progress_bar() as progress:
            res = run_georef(
                source,
                out,
                options,
                calibration,
                executor=executor,
                resume=resume,
                force=force,
                sbet=sbet,
                smrmsg=smrmsg,
                db=history,
                progress=progress,
            )
    finally:
        executor.close()
    _print_outcome(res, out, resume)


def _window(w: _WindowT | None) -> _WindowT | None:
    """A window option, None when unset (typer gives (None, None) for an unset tuple option)."""
    return None if w is None or w[0] is None else w


@contextmanager
def _progress_bar() -> Iterator[Callable[[str, int, int, int], None]]:
    """A progress bar per stage of the job on stdout, with the points done and their rate; the
    block gets the engine's progress callback ``(stage, done, total, points)``."""
    import time

    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TaskID, TextColumn, TimeRemainingColumn

    columns = (
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("{task.fields[points]:>13,} points  {task.fields[rate]:>9,.0f} points/s"),
        TimeRemainingColumn(),
    )
    with Progress(*columns, console=Console(), transient=True) as bar:
        tasks: dict[str, tuple[TaskID, float]] = {}

        def progress(stage: str, done: int, total: int, points: int) -> None:
            if stage not in tasks:
                tasks[stage] = (bar.add_task(stage, total=total, points=0, rate=0.0), time.monotonic())
            task, t0 = tasks[stage]
            dt = time.monotonic() - t0
            bar.update(task, completed=done, total=total, points=points, rate=points / dt if dt > 0 else 0.0)

        yield progress


def _print_outcome(res: GeorefResult, out: Path, resume: bool) -> None:
    """The warnings on stderr, then one line: points, files, executor, throughput."""
    from rich.console import Console
    from rich.markup import escape

    console, err = Console(), Console(stderr=True, emoji=False)
    for w in res.warnings:
        err.print(f"[yellow]warning:[/yellow] {escape(w)}", highlight=False, soft_wrap=True)
    skipped = f"; resumed: {res.chunks - res.chunks_run} chunks already done" if resume else ""
    console.print(
        f"{res.n_points:,} points in {len(res.files)} files in {out} ({res.executor}, "
        f"{res.wall_s:.1f} s, {res.n_points / max(res.wall_s, 1e-9):,.0f} points/s){skipped}; "
        f"see {out / 'summary.md'}",
        highlight=False,
    )
