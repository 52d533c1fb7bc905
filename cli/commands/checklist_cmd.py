"""``mls checklist``: the operator's Textual screen for the calibration survey."""

from __future__ import annotations

from pathlib import Path

import typer

HELP = (
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
    socket: Path = typer.Option(
        None,
        "--socket",
        help="Status socket of the daemon (default: the config's status.socket, else /run/mls/status.sock).",
    ),
    mqtt: str = typer.Option(
        None, "--mqtt", metavar="HOST:PORT", help="Read the status from an MQTT broker instead of the socket."
    ),
    vessel: str = typer.Option(
        "+", "--vessel", help="Vessel name in the MQTT topics (<prefix>/<vessel>/…); + for any."
    ),
    prefix: str = typer.Option("mls", "--prefix", help="MQTT topic prefix."),
    config: Path = typer.Option(
        None,
        "--config",
        "-c",
        help="Vessel config: the socket path, "
        "the MQTT credentials, prefix and vessel, the session directory.",
    ),
    session: Path = typer.Option(
        None,
        "--session",
        help='Session directory that "calibrate '
        'now" runs on (default: the one the daemon reports, under '
        "the config's session directory).",
    ),
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
        feed = MqttFeed(host, port, prefix, vessel, username, password)
    else:
        feed = SocketFeed(socket or Path("/run/mls/status.sock"))
    ChecklistApp(feed, session=str(session) if session else None, session_root=session_root).run()
