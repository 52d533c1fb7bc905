"""``mls status``: one-shot status of the running daemon, read from its local status socket."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import typer

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
    socket: Path = typer.Option(
        None,
        "--socket",
        help=f"Status socket of the daemon [default: the config's status.socket, else {DEFAULT_SOCKET}].",
    ),
    config: Path = typer.Option(None, "--config", "-c", help="Vessel config: take the socket path from it."),
    as_json: bool = typer.Option(False, "--json", help="Print the raw snapshot as JSON."),
    timeout_s: float = typer.Option(3.0, "--timeout", help="Seconds to wait for the daemon."),
) -> None:
    """Show the running daemon's status once: state, clock, devices, log, active alarms.

    Exit status: 0 ok, 1 daemon unreachable, 2 critical alarms active or daemon state lost.
    """
    import json

    from rich.console import Console
    from rich.table import Table

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
            cols = list(dict.fromkeys(c for v in sensors.values() for c in v))
            dt = Table(title="devices")
            dt.add_column("device", style="bold")
            for c in cols:
                dt.add_column(c)
            for name, v in sorted(sensors.items()):
                dt.add_row(name, *(_fmt(v.get(c)) for c in cols))
            con.print(dt)
        if snap.get("checklist"):
            ct = Table(title="checklist", show_header=False)
            for k, v in snap["checklist"].items():
                ct.add_row(k, _fmt(v))
            con.print(ct)
        at = Table(title=f"active alarms: {len(alarms)}")
        for c in ("severity", "name", "device", "message"):
            at.add_column(c)
        for a in alarms:
            at.add_row(*(_fmt(a.get(c)) for c in ("severity", "name", "device", "message")))
        con.print(at)
    state = snap.get("status", {}).get("state")
    alarms = snap.get("status", {}).get("alarms") or []
    if state == "lost" or any(a.get("severity") == "critical" for a in alarms):
        raise typer.Exit(EXIT_CRITICAL)
