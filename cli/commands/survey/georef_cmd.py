"""``mls georef SESSION|BUNDLE --out DIR``: a whole survey → LAZ tiles with per-point σ
(:mod:`office.deliver`, docs/architecture.md §8)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from cli.options import Calibration, Las, SurveySource, crs_option, force_option, out_option

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
    source: SurveySource = ...,
    out: Annotated[Path, out_option("Directory of the tiles (created).")] = ...,
    calibration: Calibration = None,
    history: Path | None = typer.Option(None, "--history", help="Calibration history database (for #ID)."),
    sbet: Path | None = typer.Option(None, "--sbet", help="Post-processed trajectory (Applanix SBET)."),
    smrmsg: Path | None = typer.Option(None, "--smrmsg", help="The SBET's sigmas (SMRMSG)."),
    crs: Annotated[str, crs_option("Output CRS: utm (the zone of the site), lgf, or EPSG:…")] = "utm",
    tile_m: float | None = typer.Option(
        None, "--tile-m", min=1.0, help="Square tiles of this size (CRS units) instead of one per line."
    ),
    keep_transits: bool = typer.Option(
        False, "--keep-transits", help="Line tiles: put the returns outside every line into tile 'transit'."
    ),
    max_tile_points: int = typer.Option(
        20_000_000,
        "--max-tile-points",
        min=1000,
        help="Split a larger tile into files -p01, -p02… (time order).",
    ),
    chunk_s: float = typer.Option(2.0, "--chunk-s", min=0.5, max=600.0, help="Seconds of survey per task."),
    range_m: tuple[float, float] = typer.Option((1.0, 119.0), "--range-m", help="Range window MIN MAX (m)."),
    scan_angle_deg: tuple[float, float] | None = typer.Option(
        None, "--scan-angle-deg", help="Window of the scanner's own angle MIN MAX (deg, 0…360)."
    ),
    intensity_min: int = typer.Option(
        0, "--intensity-min", min=0, max=65535, help="Intensity floor (count)."
    ),
    time_gps_s: tuple[float, float] | None = typer.Option(
        None, "--time-gps-s", help="GPS-time window START END (s since the GPS epoch)."
    ),
    vessel_box_m: tuple[float, float, float, float, float, float] | None = typer.Option(
        None,
        "--vessel-box-m",
        help="The vessel in the body frame (x fwd, y stbd, z down; m): X0 X1 Y0 Y1 Z0 Z1; its returns are left out.",
    ),
    las: Las = False,
    workers: int | None = typer.Option(
        None, "--workers", min=1, help="Run on a local Dask cluster of this many worker processes."
    ),
    scheduler: str | None = typer.Option(
        None, "--scheduler", help="Run on a Dask cluster: 'local' (all cores) or tcp://HOST:8786."
    ),
    resume: bool = typer.Option(False, "--resume", help="Continue a job that stopped (same inputs)."),
    force: Annotated[bool, force_option("Start over in a non-empty OUT (files replaced).")] = False,
) -> None:
    """``mls georef`` (its help text is :data:`HELP`)."""
    from rich.console import Console
    from rich.markup import escape
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    from office.deliver.engine import run_georef
    from office.deliver.executors import DaskExecutor, InProcess
    from office.deliver.options import Filters, GeorefError, GeorefOptions

    def window(w):  # typer gives (None, None) for an unset tuple option
        return None if w is None or w[0] is None else w

    console, err = Console(), Console(stderr=True, emoji=False)
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
            scan_angle_deg=window(scan_angle_deg),
            intensity_min=intensity_min,
            time_gps_s=window(time_gps_s),
            vessel_box_m=window(vessel_box_m),
        ),
    )
    executor = DaskExecutor(scheduler, workers) if (workers or scheduler) else InProcess()
    columns = (
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("{task.fields[points]:>13,} points  {task.fields[rate]:>9,.0f} points/s"),
        TimeRemainingColumn(),
    )
    try:
        with Progress(*columns, console=console, transient=True) as bar:
            tasks: dict[str, tuple] = {}

            def progress(stage: str, done: int, total: int, points: int) -> None:
                import time

                if stage not in tasks:
                    tasks[stage] = (bar.add_task(stage, total=total, points=0, rate=0.0), time.monotonic())
                task, t0 = tasks[stage]
                dt = time.monotonic() - t0
                bar.update(
                    task, completed=done, total=total, points=points, rate=points / dt if dt > 0 else 0.0
                )

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
    for w in res.warnings:
        err.print(f"[yellow]warning:[/yellow] {escape(w)}", highlight=False, soft_wrap=True)
    skipped = f"; resumed: {res.chunks - res.chunks_run} chunks already done" if resume else ""
    console.print(
        f"{res.n_points:,} points in {len(res.files)} files in {out} ({res.executor}, "
        f"{res.wall_s:.1f} s, {res.n_points / max(res.wall_s, 1e-9):,.0f} points/s){skipped}; "
        f"see {out / 'summary.md'}",
        highlight=False,
    )
