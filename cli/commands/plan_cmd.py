"""``mls plan``: the calibration lines of a site as GeoJSON, and NMEA XTE/APB for an autopilot."""

from __future__ import annotations

import re
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, NoReturn

import typer

from cli.options import out_option, socket_option

if TYPE_CHECKING:
    from rich.table import Table

    from calib.core.frames import LocalFrame
    from calib.io.site import Site
    from calib.survey.passplan import PassPlan

HELP = (
    "Plan the calibration lines of a site (the six-fold pattern of its pass plan) and write them "
    "as GeoJSON; optionally emit NMEA $--XTE/$--APB for an autopilot following one line.\n\n"
    "The GeoJSON holds per pass a LineString (start → end, WGS84 lon/lat + ellipsoidal height) "
    "with pass id, order, true and wall-relative heading, speed and the capture window, a second "
    "LineString over the capture window only, and a Point per target. A table of the lines ends "
    "the run.\n\n"
    "NMEA: --nmea with --position LAT,LON prints the XTE and APB sentences once for the active "
    "line (--active-pass, default the first); with --follow it reads the vessel's position from "
    "the running daemon's status socket and writes them at every update to --nmea-out (stdout, "
    "a file or serial device, or udp://HOST:PORT) until Ctrl-C. XTE direction to steer: L when "
    "the vessel is to starboard of the line.\n\n"
    "Example: mls plan site.yaml --out lines.geojson"
)


def _latlon(text: str) -> tuple[float, float]:
    try:
        lat, lon = (float(x) for x in text.split(","))
    except ValueError:
        raise typer.BadParameter(
            f"got {text!r}, expected LAT,LON in degrees, e.g. 45.5065,-73.5518", param_hint="--position"
        ) from None
    if not (-90 <= lat <= 90 and -180 <= lon <= 360):
        raise typer.BadParameter(f"{text!r}: latitude or longitude out of range", param_hint="--position")
    return lat, lon


def _say_link(data: dict) -> None:
    """The status feed's link events, on stderr (``mls plan --follow``)."""
    typer.echo(f"mls plan: {'connected to' if data['up'] else 'waiting for'} {data['detail']}", err=True)


def plan(
    site_file: Annotated[
        Path,
        typer.Argument(
            metavar="SITE",
            help="Site config (site.yaml) with reference, targets, wall azimuth, standoff and passes.",
        ),
    ],
    out: Annotated[
        Path | None, out_option("GeoJSON file to write (the lines, capture windows and targets).")
    ] = None,
    capture_margin_m: Annotated[
        float,
        typer.Option(
            "--capture-margin-m", min=0.0, help="Along-track margin of the capture window around the targets."
        ),
    ] = 3.0,
    safe_wall_distance_m: Annotated[
        float, typer.Option("--safe-wall-distance-m", min=0.0, help="Closest a line may come to the wall.")
    ] = 5.0,
    nmea: Annotated[
        bool,
        typer.Option(
            "--nmea", help="Emit NMEA $--XTE and $--APB for the active line (with --position or --follow)."
        ),
    ] = False,
    active_pass: Annotated[
        int | None,
        typer.Option(
            "--active-pass",
            "-p",
            help="Pass id the autopilot "
            "follows (default: the daemon's active pass with --follow, "
            "else the first pass).",
        ),
    ] = None,
    position: Annotated[
        str | None,
        typer.Option(
            "--position", metavar="LAT,LON", help="Vessel position (degrees) for a one-shot XTE/APB."
        ),
    ] = None,
    follow: Annotated[
        bool,
        typer.Option(
            "--follow",
            help="Follow the vessel from the daemon's status socket and emit at every update until Ctrl-C.",
        ),
    ] = False,
    socket: Annotated[Path, socket_option("Status socket of the daemon (with --follow).")] = Path(
        "/run/mls/status.sock"
    ),
    nmea_out: Annotated[
        str,
        typer.Option(
            "--nmea-out",
            help="Where the sentences go: - (stdout), a file or serial device path, or udp://HOST:PORT.",
        ),
    ] = "-",
    talker: Annotated[str, typer.Option("--talker", help="NMEA talker id of the sentences.")] = "GP",
    lookahead_m: Annotated[
        float, typer.Option("--lookahead-m", min=1.0, help="Look-ahead distance of the heading-to-steer law.")
    ] = 20.0,
) -> None:
    """``mls plan`` (its help text is :data:`HELP`)."""
    from rich.console import Console

    _check_nmea_options(talker, nmea, position, follow)
    site, frame, pp = _plan(site_file, capture_margin_m, safe_wall_distance_m, active_pass)
    if out is not None:
        _write_geojson(out, pp, frame, site)
    if nmea:
        _emit_nmea(pp, frame, nmea_out, position, active_pass, socket, talker, lookahead_m)
        if out is None:
            return
    Console().print(_lines_table(pp, site_file, out))


def _fail(message: str) -> NoReturn:
    """One line ``error: <message>`` on stderr and exit status 1."""
    from rich.console import Console
    from rich.markup import escape

    err = Console(stderr=True, emoji=False)  # ":100:" of file:line:column is no emoji
    err.print(f"[red]error:[/red] {escape(message)}", highlight=False, soft_wrap=True)
    raise typer.Exit(1)


def _check_nmea_options(talker: str, nmea: bool, position: str | None, follow: bool) -> None:
    """Usage errors: a talker id of two capitals; --nmea with one of --position and --follow."""
    if not re.fullmatch(r"[A-Z]{2}", talker):
        raise typer.BadParameter(
            f"got {talker!r}, expected two capital letters such as GP, II or IN", param_hint="--talker"
        )
    if nmea and not (position or follow):
        raise typer.BadParameter(
            "--nmea needs --position LAT,LON (once) or --follow (live)", param_hint="--nmea"
        )
    if (position or follow) and not nmea:
        raise typer.BadParameter("--position and --follow go with --nmea", param_hint="--nmea")


def _plan(
    site_file: Path, capture_margin_m: float, safe_wall_distance_m: float, active_pass: int | None
) -> tuple[Site, LocalFrame, PassPlan]:
    """The site, its LGF and the plan of its lines (the active pass checked to be one of them);
    exit status 1 when the site cannot be planned."""
    from calib.core.errors import ConfigError, MlsError
    from calib.io.site import load_site
    from calib.survey.passplan import plan_site

    try:
        site = load_site(site_file)
        frame = site.frame()
        pp = plan_site(site, capture_margin_m=capture_margin_m, safe_wall_distance_m=safe_wall_distance_m)
        if active_pass is not None:
            pp.by_id(active_pass)
    except (MlsError, KeyError, OSError) as e:
        msg = e.args[0] if isinstance(e, KeyError) else str(e)
        if isinstance(e, ConfigError) and "reference" in msg:
            msg += " (mls plan needs the site's reference point to place the lines)"
        _fail(msg)
    return site, frame, pp


def _write_geojson(out: Path, pp: PassPlan, frame: LocalFrame, site: Site) -> None:
    """The lines, capture windows and targets as GeoJSON; exit status 1 when it cannot be written."""
    from calib.survey.planexport import write_plan_geojson

    try:
        if out.is_dir():
            raise IsADirectoryError(f"{out}: --out names a file, but this is a directory")
        write_plan_geojson(out, pp, frame, site.targets, name=f"{site.vessel} calibration lines")
    except OSError as e:
        _fail(str(e))


def _emit_nmea(
    pp: PassPlan,
    frame: LocalFrame,
    nmea_out: str,
    position: str | None,
    active_pass: int | None,
    socket: Path,
    talker: str,
    lookahead_m: float,
) -> None:
    """$--XTE and $--APB to ``nmea_out``: once for ``position``, else at every update of the
    daemon's status until Ctrl-C."""
    from acquire.guidance.autopilot_out import NmeaOutput, NmeaOutputError, follow_daemon, sentences_at

    lat_lon = _latlon(position) if position else None
    try:
        dest = NmeaOutput(nmea_out)
    except NmeaOutputError as e:
        raise typer.BadParameter(str(e), param_hint="--nmea-out") from None
    try:
        if lat_lon:
            lat, lon = lat_lon
            line = pp.by_id(active_pass if active_pass is not None else pp.passes[0].id)
            for s in sentences_at(frame, line, lat, lon, talker=talker, lookahead_m=lookahead_m):
                dest.write(s)
        else:
            import asyncio

            try:
                asyncio.run(
                    follow_daemon(
                        socket, pp, frame, active_pass, dest, talker, lookahead_m, on_link=_say_link
                    )
                )
            except KeyboardInterrupt:
                pass
    finally:
        dest.close()


def _lines_table(pp: PassPlan, site_file: Path, out: Path | None) -> Table:
    """The planned lines: heading, length, speed, capture window, targets' side."""
    import numpy as np
    from rich import box
    from rich.table import Table

    table = Table(
        title=f"calibration lines of {site_file}" + (f" → {out}" if out else ""),
        caption="hdg: true heading; rel: to the wall; window: the capture window "
        "from the line's start; side: where the targets are",
        box=box.SIMPLE_HEAD,
    )
    for col in ("pass", "#", "hdg", "rel", "len m", "m/s", "window m", "window s", "side"):
        table.add_column(col, justify="left" if col == "side" else "right", no_wrap=True)
    for p in pp.passes:
        cw = p.capture_window_s
        table.add_row(
            str(p.id),
            str(p.order),
            f"{np.degrees(p.heading_rad):.1f}°",
            f"{np.degrees(p.relative_heading_rad):.0f}°",
            f"{p.length_m:.1f}",
            f"{p.speed_mps:g}",
            f"{p.capture_start_m:.1f}–{p.capture_end_m:.1f}",
            f"{cw[0]:.1f}–{cw[1]:.1f}",
            p.targets_side,
        )
    return table
