"""``mls plan``: the calibration lines of a site as GeoJSON, and NMEA XTE/APB for an autopilot."""

from __future__ import annotations

import re
from pathlib import Path

import typer

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
        raise typer.BadParameter(f"got {text!r}, expected LAT,LON in degrees, e.g. "
                                 f"45.5065,-73.5518", param_hint="--position") from None  # fmt: skip
    if not (-90 <= lat <= 90 and -180 <= lon <= 360):
        raise typer.BadParameter(f"{text!r}: latitude or longitude out of range",
                                 param_hint="--position")  # fmt: skip
    return lat, lon


class _Output:
    """Where the sentences go: stdout, a file/serial device, or UDP."""

    def __init__(self, dest: str):
        import socket
        import sys

        self.sock = self.fh = None
        self._own = dest != "-"
        if dest == "-":
            self.fh = sys.stdout.buffer
        elif dest.startswith("udp://"):
            from acquire.status.feed import parse_host_port

            try:
                self.addr = parse_host_port(dest[len("udp://"):], default_port=10110)
            except ValueError as e:
                raise typer.BadParameter(str(e), param_hint="--nmea-out") from None
            self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        else:
            self.fh = open(dest, "ab", buffering=0)  # noqa: SIM115 (closed in close())

    def write(self, data: bytes) -> None:
        if self.sock is not None:
            self.sock.sendto(data, self.addr)
        else:
            self.fh.write(data)
            self.fh.flush()

    def close(self) -> None:
        if self.sock is not None:
            self.sock.close()
        elif self.fh is not None and self._own:
            self.fh.close()


async def _follow(socket_path: Path, plan, frame, active: int | None, out: _Output, talker: str,
                  lookahead_m: float) -> None:  # fmt: skip
    import numpy as np

    from acquire.guidance.autopilot import autopilot_sentences
    from acquire.status.feed import LINK, SocketFeed, guidance_of

    async for topic, data in SocketFeed(socket_path):
        if topic == LINK:
            typer.echo(f"mls plan: {'connected to' if data['up'] else 'waiting for'} "
                       f"{data['detail']}", err=True)  # fmt: skip
            continue
        if topic != "checklist":
            continue
        g = guidance_of(data)
        vessel = g.get("vessel") or {}
        pid = active or (g.get("active") or {}).get("pass_id")
        if pid is None or "lat_deg" not in vessel:
            continue
        p = frame.to_lgf([vessel["lat_deg"]], [vessel["lon_deg"]], [frame.height_m])[0]
        line = plan.by_id(int(pid))
        p[2] = line.start_lgf_m[2]
        for s in autopilot_sentences(np.asarray(p), line, talker=talker, lookahead_m=lookahead_m):
            out.write(s)


def plan(
    site_file: Path = typer.Argument(..., metavar="SITE", help="Site config (site.yaml) with "
                                     "reference, targets, wall azimuth, standoff and passes."),
    out: Path = typer.Option(None, "--out", "-o", help="GeoJSON file to write (the lines, "
                             "capture windows and targets)."),  # fmt: skip
    capture_margin_m: float = typer.Option(3.0, "--capture-margin-m", min=0.0, help="Along-track "
                                           "margin of the capture window around the targets."),
    safe_wall_distance_m: float = typer.Option(5.0, "--safe-wall-distance-m", min=0.0,
                                               help="Closest a line may come to the wall."),
    nmea: bool = typer.Option(False, "--nmea", help="Emit NMEA $--XTE and $--APB for the "
                              "active line (with --position or --follow)."),  # fmt: skip
    active_pass: int = typer.Option(None, "--active-pass", "-p", help="Pass id the autopilot "
                                    "follows (default: the daemon's active pass with --follow, "
                                    "else the first pass)."),  # fmt: skip
    position: str = typer.Option(None, "--position", metavar="LAT,LON", help="Vessel position "
                                 "(degrees) for a one-shot XTE/APB."),  # fmt: skip
    follow: bool = typer.Option(False, "--follow", help="Follow the vessel from the daemon's "
                                "status socket and emit at every update until Ctrl-C."),
    socket: Path = typer.Option(Path("/run/mls/status.sock"), "--socket",
                                help="Status socket of the daemon (with --follow)."),
    nmea_out: str = typer.Option("-", "--nmea-out", help="Where the sentences go: - (stdout), "
                                 "a file or serial device path, or udp://HOST:PORT."),
    talker: str = typer.Option("GP", "--talker", help="NMEA talker id of the sentences."),
    lookahead_m: float = typer.Option(20.0, "--lookahead-m", min=1.0, help="Look-ahead distance "
                                      "of the heading-to-steer law."),  # fmt: skip
) -> None:
    """``mls plan`` (its help text is :data:`HELP`)."""
    import json

    import numpy as np
    from rich.console import Console
    from rich.markup import escape
    from rich.table import Table

    from calib.io.configfile import ConfigError
    from calib.survey.passplan import PassPlanError, plan_site
    from calib.survey.planexport import plan_geojson
    from calib.io.site import load_site

    err = Console(stderr=True)
    if not re.fullmatch(r"[A-Z]{2}", talker):
        raise typer.BadParameter(f"got {talker!r}, expected two capital letters such as GP, "
                                 f"II or IN", param_hint="--talker")  # fmt: skip
    if nmea and not (position or follow):
        raise typer.BadParameter("--nmea needs --position LAT,LON (once) or --follow (live)",
                                 param_hint="--nmea")  # fmt: skip
    if (position or follow) and not nmea:
        raise typer.BadParameter("--position and --follow go with --nmea", param_hint="--nmea")
    try:
        site = load_site(site_file)
        frame = site.frame()
        pp = plan_site(site, capture_margin_m=capture_margin_m,
                       safe_wall_distance_m=safe_wall_distance_m)  # fmt: skip
        if active_pass is not None:
            pp.by_id(active_pass)
    except (ConfigError, PassPlanError, KeyError, OSError) as e:
        msg = e.args[0] if isinstance(e, KeyError) else str(e)
        if isinstance(e, ConfigError) and "reference" in msg:
            msg += " (mls plan needs the site's reference point to place the lines)"
        err.print(f"[red]error:[/red] {escape(msg)}", highlight=False, soft_wrap=True)
        raise typer.Exit(1) from None

    if out is not None:
        doc = plan_geojson(pp, frame, site.targets, name=f"{site.vessel} calibration lines")
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(doc, indent=1) + "\n", encoding="utf-8")

    if nmea:
        from acquire.guidance.autopilot import autopilot_sentences

        lat_lon = _latlon(position) if position else None
        dest = _Output(nmea_out)
        try:
            if lat_lon:
                lat, lon = lat_lon
                line = pp.by_id(active_pass if active_pass is not None else pp.passes[0].id)
                p = frame.to_lgf([lat], [lon], [frame.height_m])[0]
                p[2] = line.start_lgf_m[2]
                for s in autopilot_sentences(np.asarray(p), line, talker=talker,
                                             lookahead_m=lookahead_m):  # fmt: skip
                    dest.write(s)
            else:
                import asyncio

                try:
                    asyncio.run(_follow(socket, pp, frame, active_pass, dest, talker,
                                        lookahead_m))  # fmt: skip
                except KeyboardInterrupt:
                    pass
        finally:
            dest.close()
        if out is None:
            return

    from rich import box

    table = Table(title=f"calibration lines of {site_file}" + (f" → {out}" if out else ""),
                  caption="hdg: true heading; rel: to the wall; window: the capture window "
                  "from the line's start; side: where the targets are", box=box.SIMPLE_HEAD)
    for col in ("pass", "#", "hdg", "rel", "len m", "m/s", "window m", "window s", "side"):
        table.add_column(col, justify="left" if col == "side" else "right", no_wrap=True)
    for p in pp.passes:
        cw = p.capture_window_s
        table.add_row(str(p.id), str(p.order), f"{np.degrees(p.heading_rad):.1f}°",
                      f"{np.degrees(p.relative_heading_rad):.0f}°", f"{p.length_m:.1f}",
                      f"{p.speed_mps:g}", f"{p.capture_start_m:.1f}–{p.capture_end_m:.1f}",
                      f"{cw[0]:.1f}–{cw[1]:.1f}", p.targets_side)  # fmt: skip
    Console().print(table)
