"""``mls export SESSION --bundle DIR``: a recorded session → a calibration bundle (docs/architecture.md §4);
``--foxglove OUT.mcap``: → a file Foxglove opens as it is (docs/architecture.md §8.4)."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from cli.options import SessionDir, force_option

if TYPE_CHECKING:
    from rich.console import Console

    from office.jobs.export import ExportOptions, ExportResult
    from office.jobs.foxglove import FoxgloveResult

HELP = (
    "Export a recorded session as a calibration bundle for `mls calib run` (--bundle), and/or as one "
    "MCAP file for Foxglove (--foxglove).\n\n"
    "Writes BUNDLE/trajectory.csv (the INS epochs of /ins/nav at their GPS time, canonical "
    "attitude, per-epoch sigmas), BUNDLE/points.csv (the profiler packets of /lidar/raw "
    "decoded again: per point GPS time, range, scan angle, intensity; no-returns dropped; "
    "only the points inside a pass) and BUNDLE/site.yaml (the site file with the mount of the "
    "session's vessel config). Passes come from the pass_start/pass_end marks in /events (CAN "
    "event markers, MQTT commands), or, when there are none, from the site's pass plan (where "
    "the trajectory runs along a planned line). Optionally one LAZ per pass (--laz) and the "
    "trajectory as an SBET (--sbet). A --bundle or --laz directory that already holds files, "
    "or an existing --sbet file, is refused unless --force. Warnings (a pass planned in the "
    "site without points, points of an unplanned pass, …) go to stderr and are counted in the "
    "summary.\n\n"
    "A segment that did not end normally (a torn tail after a crash or power cut, unfinished or "
    "salvaged by `mls logs recover`) is exported with a warning naming the segment and the time "
    "span lost; --require-complete refuses such a session (exit status 1).\n\n"
    "--foxglove OUT.mcap writes the session for Foxglove (open the file there, nothing to "
    "configure): the vessel's track (/vessel/fix, foxglove.LocationFix), its pose (/tf, "
    "foxglove.FrameTransform, world frame lgf_enu = east, north, up), the georeferenced profiles "
    "as point clouds (/lidar/points, foxglove.PointCloud, one per 1/--cloud-rate-hz s, at most "
    "--max-cloud-points points each, evenly decimated), alarms and events (/log, foxglove.Log) "
    "and the clock and latency numbers to plot (/clock, /latency); times are UTC. With "
    "--foxglove alone only the MCAP file is written; with --bundle as well, both. An existing "
    "OUT.mcap is refused unless --force.\n\n"
    "Example: mls export /var/lib/mls/sessions/20240709T140000Z_survey-1 --bundle calib-0709 "
    "--laz calib-0709/laz\n\n"
    "Example: mls export /var/lib/mls/sessions/20240709T140000Z_survey-1 --foxglove 0709.mcap"
)


def export(
    session: SessionDir,
    bundle: Annotated[
        Path | None, typer.Option("--bundle", "-o", help="Bundle directory to write (created).")
    ] = None,
    foxglove: Annotated[
        Path | None,
        typer.Option(
            "--foxglove", help="Write the session for Foxglove as this MCAP file (alone: only this file)."
        ),
    ] = None,
    cloud_rate_hz: Annotated[
        float,
        typer.Option("--cloud-rate-hz", min=0.01, max=1000.0, help="--foxglove: point clouds per second."),
    ] = 2.0,
    max_cloud_points: Annotated[
        int,
        typer.Option(
            "--max-cloud-points", min=1, help="--foxglove: most points in one cloud (evenly decimated)."
        ),
    ] = 50_000,
    force: Annotated[
        bool,
        force_option(
            "Write into output directories (or over an --sbet or --foxglove file) that already hold data."
        ),
    ] = False,
    laz: Annotated[
        Path | None, typer.Option("--laz", help="Also write one LAZ per pass here (UTM, a-priori mount).")
    ] = None,
    sbet: Annotated[
        Path | None,
        typer.Option(
            "--sbet", help="Also write the trajectory as an Applanix SBET (and .smrmsg with the sigmas)."
        ),
    ] = None,
    site: Annotated[
        Path | None,
        typer.Option(
            "--site", help="Site file (targets, pass plan) instead of the one stored in the session."
        ),
    ] = None,
    passes: Annotated[
        str,
        typer.Option(
            "--passes", help="Where the passes come from: auto (event marks, else the plan), events, plan."
        ),
    ] = "auto",
    cross_track_m: Annotated[
        float,
        typer.Option(
            "--max-cross-track", min=0.1, help="Plan passes: largest distance from the planned line (m)."
        ),
    ] = 5.0,
    heading_deg: Annotated[
        float,
        typer.Option(
            "--max-heading-error", min=0.1, max=90.0, help="Plan passes: largest heading error (deg)."
        ),
    ] = 20.0,
    require_complete: Annotated[
        bool,
        typer.Option(
            "--require-complete",
            help="Refuse a session with a segment that did not end normally (torn tail) instead of warning.",
        ),
    ] = False,
) -> None:
    """``mls export`` (its help text is :data:`HELP`)."""
    import time

    from rich.console import Console
    from rich.markup import escape

    from calib.core.errors import MlsError
    from office.jobs.export import ExportOptions

    console = Console()
    err = Console(stderr=True, emoji=False)  # ":100:" of file:line:column is no emoji
    t0 = time.perf_counter()
    try:
        _check_outputs(session, bundle, foxglove, laz, sbet, force)
        opts = ExportOptions(
            passes=passes,
            site_file=site,
            max_cross_track_m=cross_track_m,
            max_heading_error_deg=heading_deg,
            laz_dir=laz,
            sbet_path=sbet,
            require_complete=require_complete,
        )
        with _progress_bar(console) as progress:
            res = _export_bundle(session, bundle, opts, progress)
            fox = _export_foxglove(
                session, foxglove, cloud_rate_hz, max_cloud_points, force, require_complete, progress
            )
    except (MlsError, OSError) as e:
        err.print(f"[red]error:[/red] {escape(str(e))}", highlight=False, soft_wrap=True)
        raise typer.Exit(1) from None
    if res is not None:
        _bundle_summary(console, err, session, res, laz, time.perf_counter() - t0)
    if fox is not None:
        _foxglove_summary(console, err, session, fox, time.perf_counter() - t0)


def _check_outputs(
    session: Path,
    bundle: Path | None,
    foxglove: Path | None,
    laz: Path | None,
    sbet: Path | None,
    force: bool,
) -> None:
    """The session is a directory, something is to be written, and every output may be
    written (held or checked before the session is read)."""
    from calib.io.outputs import check_output_file, hold_output_dir
    from office.jobs.export import ExportError

    if not session.is_dir():
        raise ExportError(f"{session}: not a directory (a session is the directory the daemon recorded)")
    if bundle is None and foxglove is None:
        raise ExportError(
            "nothing to write: give --bundle DIR (calibration bundle) and/or --foxglove OUT.mcap"
        )
    if bundle is None and (laz is not None or sbet is not None):
        raise ExportError("--laz and --sbet come with --bundle DIR (they are written from the bundle)")
    if bundle is not None:  # every output, before reading the session
        hold_output_dir(bundle, "--bundle", force)
    if laz is not None:
        hold_output_dir(laz, "--laz", force)
    if sbet is not None:
        check_output_file(sbet, "--sbet", force)
    if foxglove is not None:
        check_output_file(foxglove, "--foxglove", force)


@contextmanager
def _progress_bar(console: Console) -> Iterator[Callable[[str, float, float | None], None]]:
    """One progress bar that each stage of the exports takes over; the block gets its callback."""
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    with Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        TimeElapsedColumn(),
        console=console,
        transient=True,
    ) as bar:
        task = bar.add_task("reading the session", total=None)

        def progress(stage: str, done: float, total: float | None) -> None:
            bar.update(task, description=stage, completed=done, total=total)

        yield progress


def _export_bundle(
    session: Path,
    bundle: Path | None,
    opts: ExportOptions,
    progress: Callable[[str, float, float | None], None],
) -> ExportResult | None:
    """The calibration bundle of ``--bundle`` (None when not asked for)."""
    from office.jobs.export import export_session

    if bundle is None:
        return None
    return export_session(session, bundle, opts, progress)


def _export_foxglove(
    session: Path,
    foxglove: Path | None,
    cloud_rate_hz: float,
    max_cloud_points: int,
    force: bool,
    require_complete: bool,
    progress: Callable[[str, float, float | None], None],
) -> FoxgloveResult | None:
    """The Foxglove MCAP file of ``--foxglove`` (None when not asked for)."""
    if foxglove is None:
        return None
    from office.jobs.foxglove import export_foxglove

    return export_foxglove(
        session,
        foxglove,
        cloud_rate_hz=cloud_rate_hz,
        max_points_per_cloud=max_cloud_points,
        force=force,
        require_complete=require_complete,
        progress=progress,
    )


def _bundle_summary(
    console: Console, err: Console, session: Path, res: ExportResult, laz: Path | None, elapsed_s: float
) -> None:
    """The passes table, the warnings (stderr) and the closing line of a bundle export."""
    from rich.markup import escape
    from rich.table import Table

    from calib.core import frames

    t = Table(title=f"{session.name} → {res.bundle} ({res.pass_source} passes)", title_justify="left")
    for col in ("pass", "source", "start UTC", "span s", "points"):
        t.add_column(col, justify="right" if col in ("pass", "span s", "points") else "left")
    for pw in res.passes:
        start = frames.gps_ns_to_utc(pw.start_gps_ns).strftime("%H:%M:%S.%f")[:-3]
        t.add_row(
            str(pw.pass_id),
            pw.source,
            start,
            f"{(pw.end_gps_ns - pw.start_gps_ns) / 1e9:.1f}",
            f"{res.points_per_pass.get(pw.pass_id, 0):,}",
        )
    console.print(t)
    for w in res.warnings:
        err.print(f"[yellow]warning:[/yellow] {escape(w)}", highlight=False, soft_wrap=True)
    extra = ""
    if res.laz:
        extra += f"; {len(res.laz)} LAZ files in {laz}"
    if res.sbet is not None:
        extra += f"; SBET {res.sbet}"
    console.print(
        f"{res.epochs:,} INS epochs, {res.points:,} points from {res.packets:,} packets "
        f"({res.returns_outside_passes:,} returns outside the passes){extra} in "
        f"{elapsed_s:.1f} s"
        + (
            f"; {len(res.warnings)} warning{'s' if len(res.warnings) > 1 else ''} (stderr)"
            if res.warnings
            else ""
        ),
        highlight=False,
    )


def _foxglove_summary(
    console: Console, err: Console, session: Path, fox: FoxgloveResult, elapsed_s: float
) -> None:
    """The channels table, the warnings (stderr) and the closing line of a Foxglove export."""
    from rich.markup import escape
    from rich.table import Table

    from acquire.foxglove.channels import SCHEMAS
    from calib.core import frames

    t = Table(title=f"{session.name} → {fox.path} (Foxglove)", title_justify="left")
    for col in ("channel", "schema", "messages"):
        t.add_column(col, justify="right" if col == "messages" else "left")
    for topic, n in fox.messages.items():
        t.add_row(topic, SCHEMAS[topic], f"{n:,}")
    console.print(t)
    for w in fox.warnings:
        err.print(f"[yellow]warning:[/yellow] {escape(w)}", highlight=False, soft_wrap=True)
    span = ""
    if fox.end_gps_ns > fox.start_gps_ns:
        start = frames.gps_ns_to_utc(fox.start_gps_ns).strftime("%Y-%m-%d %H:%M:%S")
        span = f", {fox.span_s:.1f} s from {start} UTC"
    console.print(
        f"{sum(fox.messages.values()):,} messages on {len(fox.messages)} channels{span}; "
        f"{fox.points:,} of {fox.returns:,} returns in {fox.messages['/lidar/points']:,} clouds "
        f"({fox.cloud_rate_hz:g} Hz) in {elapsed_s:.1f} s"
        + (
            f"; {len(fox.warnings)} warning{'s' if len(fox.warnings) > 1 else ''} (stderr)"
            if fox.warnings
            else ""
        ),
        highlight=False,
    )
