"""``mls calib``: the calibration command group and ``mls calib georef`` (other modules add
their commands to :data:`app`)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from calib.io.georef_bundle import DEFAULT_CHUNK_POINTS, PassOutput
from cli.options import Force, Las, bundle_argument, crs_option, out_option, skip_uncovered_option

app = typer.Typer(
    help="Calibration: georeferencing, boresight adjustment and assessment of bundles/results.",
    no_args_is_help=True,
)


def parse_triple_deg(text: str, option: str) -> tuple[float, float, float]:
    """``"r,p,y"`` → three finite floats, or a usage error naming the option."""
    import math

    parts = [p.strip() for p in text.split(",")]
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        values = ()
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise typer.BadParameter(
            f"got {text!r}, expected three numbers 'roll,pitch,yaw' in degrees, e.g. 0.208,1.245,0.149",
            param_hint=option,
        )
    roll, pitch, yaw = values
    return roll, pitch, yaw


def summary_table(outputs: list[PassOutput], facts: dict, out_dir: Path):
    """The terse result table of ``mls calib georef``."""
    from rich.table import Table

    from calib.core import frames

    b = facts["boresight_deg"]
    wide = facts.get("source_id_zero") or []
    table = Table(
        title=f"georeferenced passes → {out_dir}",
        caption=(
            f"CRS {facts['crs']} · boresight roll {b[0]:.4f}°, pitch {b[1]:.4f}°, "
            f"yaw {b[2]:.4f}° (canonical, from {facts['boresight_source']}) · "
            f"intensity {facts['intensity']} · the pass id is in each point's extra-bytes pass_id"
            + (
                f"; pass{'es' if len(wide) > 1 else ''} {', '.join(map(str, wide))} exceed LAS's "
                f"16-bit point_source_id: 0 there"
                if wide
                else " and point_source_id"
            )
        ),
    )
    dropped = any(o.n_dropped for o in outputs)
    table.add_column("pass", justify="right")
    table.add_column("points", justify="right")
    if dropped:
        table.add_column("dropped", justify="right", no_wrap=True)
    table.add_column("start UTC", no_wrap=True)
    table.add_column("span s", justify="right", no_wrap=True)
    table.add_column("file", no_wrap=True)
    table.add_column("size", justify="right", no_wrap=True)
    for o in outputs:
        if o.n_points:
            start = frames.gps_ns_to_utc(frames.seconds_to_gps_ns(o.t_first_gps_s))
            start_s = start.strftime("%Y-%m-%d %H:%M:%S")
            span = f"{o.t_last_gps_s - o.t_first_gps_s:.2f}"
        else:
            start_s, span = "—", "—"
        size = o.path.stat().st_size
        size_s = f"{size / 1e6:.1f} MB" if size >= 1e6 else f"{size / 1e3:.0f} kB"
        row = [str(o.pass_id), f"{o.n_points:,}"] + ([f"{o.n_dropped:,}"] if dropped else [])
        table.add_row(*row, start_s, span, o.path.name, size_s)
    return table


def run_georef(bundle: Path, out: Path, force: bool = False, **kwargs) -> list[PassOutput]:
    """Georeference with a progress bar and print the summary table; an MlsError (an --out that
    is a file or holds files without ``force``, a bad bundle, CRS, uncovered points) ends the
    command in :mod:`cli.app`: one line, exit status 1."""
    from rich.console import Console
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    from calib.io.georef_bundle import georeference_bundle
    from calib.io.outputs import hold_output_dir

    hold_output_dir(out, "--out", force)  # before reading anything; held to the end
    console = Console()
    columns = (
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("points"),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
    )
    with Progress(*columns, console=console) as progress:
        outputs, facts = georeference_bundle(bundle, out, progress=progress, **kwargs)
    console.print(summary_table(outputs, facts, out))
    return outputs


GEOREF_HELP = (
    "Georeference a calibration bundle: one LAZ per pass (LAS 1.4, point format 6).\n\n"
    "Each point gets its coordinates from the trajectory and the mount in site.yaml (lever arm, "
    "nominal rotation, boresight), adjusted standard GPS time (GPS s − 1e9), intensity scaled to "
    "16 bits (reflectances 0…1 ×65535, counts as they are: one scale per file), the pass id in "
    "the extra-bytes dimension pass_id (int64) and in point_source_id when it fits 16 bits (else "
    "0); each file carries the CRS as OGC WKT. A summary table ends the run. An --out directory "
    "that already holds files is refused unless --force.\n\n"
    "Example: mls calib georef examples/montreal-mini --out out/laz "
    "--boresight-deg 0.208,1.245,0.149"
)


@app.command("georef", help=GEOREF_HELP)
def georef(
    bundle: Annotated[
        Path,
        bundle_argument(
            "Calibration bundle directory: site.yaml, trajectory.csv (or trajectory.sbet "
            "[+ trajectory.smrmsg]) and points.csv[.gz]."
        ),
    ],
    out: Annotated[Path, out_option("Output directory (created); one file pass-<id>.laz per pass.")],
    force: Force = False,
    crs: Annotated[
        str,
        crs_option(
            "Output CRS: 'utm' (the UTM zone of the reference point, WGS84 "
            "ellipsoidal heights), 'lgf' (the local frame as x east, y north, z up), or any "
            "pyproj CRS such as EPSG:2950 (a 2D CRS keeps ellipsoidal heights)."
        ),
    ] = "utm",
    boresight_deg: Annotated[
        str | None,
        typer.Option(
            "--boresight-deg",
            metavar="R,P,Y",
            help="Boresight roll,pitch,yaw in degrees, "
            "canonical convention (docs/architecture.md §3; thesis pitch is negated); default: site.yaml's "
            "mount.boresight_apriori_deg.",
        ),
    ] = None,
    las: Las = False,
    max_gap_s: Annotated[
        float, typer.Option("--max-gap-s", min=0.0, help="Longest trajectory gap to interpolate across (s).")
    ] = 1.0,
    skip_uncovered: Annotated[
        bool,
        skip_uncovered_option(
            "Drop points outside the trajectory or in its gaps "
            "(counted in the table) instead of stopping with an error."
        ),
    ] = False,
    chunk_points: Annotated[
        int,
        typer.Option(
            "--chunk-points",
            min=1,
            help="Points georeferenced and written per step; bounds the memory one pass needs.",
        ),
    ] = DEFAULT_CHUNK_POINTS,
) -> None:
    """``mls calib georef`` (its help text is :data:`GEOREF_HELP`)."""
    bs = parse_triple_deg(boresight_deg, "--boresight-deg") if boresight_deg else None
    run_georef(
        bundle,
        out,
        crs=crs,
        boresight_deg=bs,
        compress=not las,
        max_gap_s=max_gap_s,
        skip_uncovered=skip_uncovered,
        chunk_points=chunk_points,
        force=force,
    )
