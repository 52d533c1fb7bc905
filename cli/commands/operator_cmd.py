"""The operator's views of the running daemon: ``mls status`` (its status once, read from the local
status socket) and ``mls checklist`` (the Textual screen for the calibration survey)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

from cli.options import json_option, socket_option, vessel_config_option

if TYPE_CHECKING:
    from rich.table import Table

DEFAULT_SOCKET = Path("/run/mls/status.sock")

EXIT_OK, EXIT_UNREACHABLE, EXIT_CRITICAL = 0, 1, 2


def _fmt(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.6g}"
    if isinstance(value, dict):
        return ", ".join(f"{k}={_fmt(v)}" for k, v in value.items()) or "-"
    if isinstance(value, list):
        return ", ".join(_fmt(v) for v in value) or "-"
    return "-" if value is None else str(value)


def status(
    socket: Annotated[
        Path | None,
        socket_option(
            f"Status socket of the daemon [default: the config's status.socket, else {DEFAULT_SOCKET}]."
        ),
    ] = None,
    config: Annotated[
        Path | None, vessel_config_option("Vessel config: take the socket path from it.")
    ] = None,
    as_json: Annotated[bool, json_option("Print the raw snapshot as JSON.")] = False,
    timeout_s: Annotated[float, typer.Option("--timeout", help="Seconds to wait for the daemon.")] = 3.0,
) -> None:
    """Show the running daemon's status once: state, clock, devices, log, active alarms (and the
    mount watch's verdict when it runs).

    Exit status: 0 ok, 1 daemon unreachable, 2 critical alarms active or daemon state lost.
    """
    import json

    from acquire.status.bus import read_snapshot

    if socket is None and config is not None:
        from acquire.daemon.config import load_vessel_config

        socket = load_vessel_config(config).status.socket
    path = socket or DEFAULT_SOCKET
    try:
        snap = read_snapshot(path, timeout_s)
    except (OSError, ValueError) as e:
        typer.echo(f"mls status: no daemon status at {path}: {e} (is mls-acquire running?)", err=True)
        raise typer.Exit(EXIT_UNREACHABLE) from None
    if as_json:
        typer.echo(json.dumps(snap, indent=2, sort_keys=True))
    else:
        _print_status(snap, path)
    state = snap.get("status", {}).get("state")
    alarms = snap.get("status", {}).get("alarms") or []
    if state == "lost" or any(a.get("severity") == "critical" for a in alarms):
        raise typer.Exit(EXIT_CRITICAL)


def _print_status(snap: dict[str, Any], path: Path) -> None:
    """The snapshot as tables: status and clock, devices, checklist, mount watch, alarms."""
    from rich.console import Console
    from rich.table import Table

    con = Console()
    st = dict(snap.get("status", {}))
    alarms = st.pop("alarms", []) or []
    t = Table(title=f"mls status — {path}", show_header=False)
    t.add_column("item", style="bold")
    t.add_column("value")
    for k, v in st.items():
        t.add_row(k, _fmt(v))
    for k, v in snap.get("clock", {}).items():
        t.add_row(f"clock.{k}", _fmt(v))
    con.print(t)
    sensors = {k.split("/", 1)[1]: v for k, v in snap.items() if k.startswith("sensors/")}
    if sensors:
        con.print(_devices_table(sensors))
    if snap.get("checklist"):
        ct = Table(title="checklist", show_header=False)
        for k, v in snap["checklist"].items():
            ct.add_row(k, _fmt(v))
        con.print(ct)
    if mount := snap.get("mount"):  # the mount watch's verdict, on a line of its own
        con.print(f"mount watch: {mount.get('verdict', '?')}", highlight=False)
    at = Table(title=f"active alarms: {len(alarms)}")
    for c in ("severity", "name", "device", "message"):
        at.add_column(c)
    for a in alarms:
        at.add_row(*(_fmt(a.get(c)) for c in ("severity", "name", "device", "message")))
    con.print(at)


def _devices_table(sensors: dict[str, dict[str, Any]]) -> Table:
    """One row per device, one column per field any device reports."""
    from rich.table import Table

    cols = list(dict.fromkeys(c for v in sensors.values() for c in v))
    dt = Table(title="devices")
    dt.add_column("device", style="bold")
    for c in cols:
        dt.add_column(c)
    for name, v in sorted(sensors.items()):
        dt.add_row(name, *(_fmt(v.get(c)) for c in cols))
    return dt


CHECKLIST_HELP = (
    "The operator's checklist for the calibration survey (keyboard-driven, fits 80×24, works "
    "over SSH).\n\n"
    "Connects to the running daemon (its local status socket by default, or MQTT) and shows the "
    "pre-survey checks with the reason of each failure, the passes (accepted / rejected with "
    "reasons), a plan view of the active line with the vessel and the targets, live cross-track "
    "error, heading error, speed and target hits, the predicted boresight σ and the most "
    "helpful next pass. Keys: c calibrate now (mls calib run on the session), ↑/↓ and Enter "
    "pass details, d the checks in full, q quit.\n\n"
    "Example: mls checklist --socket /run/mls/status.sock"
)


def checklist(
    socket: Annotated[
        Path | None,
        socket_option(
            "Status socket of the daemon (default: the config's status.socket, else /run/mls/status.sock)."
        ),
    ] = None,
    mqtt: Annotated[
        str | None,
        typer.Option(
            "--mqtt", metavar="HOST:PORT", help="Read the status from an MQTT broker instead of the socket."
        ),
    ] = None,
    vessel: Annotated[
        str, typer.Option("--vessel", help="Vessel name in the MQTT topics (<prefix>/<vessel>/…); + for any.")
    ] = "+",
    prefix: Annotated[str, typer.Option("--prefix", help="MQTT topic prefix.")] = "mls",
    config: Annotated[
        Path | None,
        vessel_config_option(
            "Vessel config: the socket path, the MQTT credentials, prefix and vessel, the session directory."
        ),
    ] = None,
    session: Annotated[
        Path | None,
        typer.Option(
            "--session",
            help='Session directory that "calibrate '
            'now" runs on (default: the one the daemon reports, under '
            "the config's session directory).",
        ),
    ] = None,
) -> None:
    """``mls checklist`` (its help text is :data:`HELP`)."""
    from acquire.status.feed import MqttFeed, SocketFeed, parse_host_port
    from acquire.ui.checklist_app import ChecklistApp

    username = password = None
    session_root = None
    if config is not None:
        from acquire.daemon.config import VesselConfigError, load_vessel_config

        try:
            cfg = load_vessel_config(config)
        except VesselConfigError as e:
            typer.echo(f"mls checklist: {e}", err=True)
            raise typer.Exit(1) from None
        if socket is None and mqtt is None:
            socket = cfg.status.socket
        if cfg.mqtt is not None:
            username, password = cfg.mqtt.username, cfg.mqtt.password
            prefix = cfg.mqtt.topic_prefix if prefix == "mls" else prefix
        vessel = cfg.vessel if vessel == "+" else vessel
        session_root = str(cfg.session_dir)
    if mqtt is not None:
        try:
            host, port = parse_host_port(mqtt)
        except ValueError as e:
            raise typer.BadParameter(str(e), param_hint="--mqtt") from None
        feed: MqttFeed | SocketFeed = MqttFeed(host, port, prefix, vessel, username, password)
    else:
        feed = SocketFeed(socket or Path("/run/mls/status.sock"))
    ChecklistApp(feed, session=str(session) if session else None, session_root=session_root).run()
