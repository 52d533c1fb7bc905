"""``mls acquire --config vessel.yaml``: the acquisition daemon (what systemd runs)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from cli.options import vessel_config_option

EXIT_OK, EXIT_FAILED, EXIT_CONFIG = 0, 1, 2

HELP = (
    "Run the acquisition daemon: read the INS, profiler, PPS and CAN devices of the vessel "
    "config, keep the PPS clock model, check latency and sync, write the crash-safe session "
    "log, publish status to the local socket and MQTT.\n\n"
    "Runs until SIGTERM or Ctrl-C, then closes the session cleanly. Under systemd "
    "(Type=notify) it reports READY once the devices are open and pings the watchdog while "
    "every driver is alive and the log writer progresses.\n\n"
    "One daemon per config: a second one on the same config exits 1 at once, naming the PID "
    "that holds the lock beside the status socket (<socket>.lock), and leaves the running "
    "daemon, its socket and the log directory as they were.\n\n"
    "Exit status: 0 after an orderly stop, 1 when it cannot start (another daemon on the "
    "config, session directory, status socket), 2 when the config is invalid (every error "
    "printed, one per line).\n\n"
    "When the config names a site_file, the daemon also runs the line guidance of the six-fold "
    "pattern (pass acceptance with the tolerances of the config's guidance section, predicted "
    "boresight σ, pre-survey checks) and publishes it on the checklist topic that mls checklist "
    "shows.\n\n"
    "When the config's watch section names the calibrated mount (watch.calibration, a "
    "calibration result.json), the daemon also watches the mount during the survey: the "
    "boresight re-estimated from each pair of opposite lines, a sequential test against the "
    "calibration, published on the mount topic and the checklist, and the critical alarm "
    "mount_shift when it moved.\n\n"
    "Example: mls acquire --config /etc/mls/vessel.yaml"
)


def acquire(
    config: Annotated[
        Path, vessel_config_option("Vessel config (YAML), see systemd/vessel.example.yaml.")
    ] = ...,
    check: bool = typer.Option(
        False,
        "--check",
        help="Validate the config, print a summary of the devices, test-bind every UDP port the "
        "daemon listens on (exit 1 when one is taken) and exit.",
    ),
    log_level: str = typer.Option(
        "info", "--log-level", help="Log level on stderr: debug, info, warning, error."
    ),
) -> None:
    """``mls acquire`` (its help text is :data:`HELP`)."""
    import os

    # BLAS on one thread (before numpy loads; the environment's own setting wins): the daemon's
    # numeric work — the guidance's σ prediction, the mount watch's block solves — runs in worker
    # threads beside the acquisition, and a BLAS spinning on every core starves the event loop
    # (and solves no faster on a 2-core vessel PC)
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")
    import asyncio
    import logging
    import sys

    from acquire.daemon.config import VesselConfigError, load_vessel_config
    from calib.core.errors import MlsError

    try:
        cfg = load_vessel_config(config)
    except VesselConfigError as e:
        for err in e.errors:
            print(err, file=sys.stderr)
        print(
            f"mls acquire: {config}: {len(e.errors)} error{'s' if len(e.errors) != 1 else ''} "
            f"in the vessel config",
            file=sys.stderr,
        )
        raise typer.Exit(EXIT_CONFIG) from None
    except (MlsError, OSError) as e:
        print(f"mls acquire: {e}", file=sys.stderr)
        raise typer.Exit(EXIT_CONFIG) from None

    from acquire.daemon.supervisor import StartupError, Supervisor
    from acquire.guidance.daemon import guidance_consumer
    from acquire.watch.daemon import mount_watch_consumer

    try:
        sup = Supervisor(cfg)
        guidance = guidance_consumer(cfg, sup)
        watch = mount_watch_consumer(cfg, sup)
    except MlsError as e:  # the config asks for what cannot be done (StartupError, *SetupError)
        print(f"mls acquire: {e}", file=sys.stderr)
        raise typer.Exit(EXIT_CONFIG) from None
    if guidance is not None:
        sup.consumers.append(guidance)
    if watch is not None:
        sup.consumers.append(watch)
    if check:
        from rich.console import Console
        from rich.table import Table

        t = Table(title=f"{config}: vessel {cfg.vessel}, sessions in {cfg.session_dir}")
        for col in ("device", "kind", "protocol", "where"):
            t.add_column(col)
        for d in cfg.devices:
            where = d.transport or d.source
            t.add_row(d.name, d.kind, d.protocol or "-", _describe(where))
        Console().print(t)
        busy = _bind_failures(cfg)
        for line in busy:
            print(line, file=sys.stderr)
        if guidance is not None:
            g, tol = guidance.guidance, cfg.guidance
            print(
                f"guidance: {len(g.plan.passes)} passes around {len(g.target_names)} targets "
                f"({', '.join(g.target_names)}) of {cfg.site_file}; accepted within "
                f"{tol.max_xte_m:g} m XTE, {tol.max_heading_error_deg:g}° heading, "
                f"±{tol.max_speed_error_mps:g} m/s, ≥ {tol.min_points_per_target} points per "
                f"target, gaps ≤ {tol.max_gap_s:g} s"
            )
        if watch is not None:
            w, b = cfg.watch, watch.info["boresight_deg"]
            print(
                f"mount watch: calibrated boresight roll {b[0]:+.4f}°, pitch {b[1]:+.4f}°, yaw "
                f"{b[2]:+.4f}° of {w.calibration}; tuned to {w.shift_deg:g}°, "
                f"{w.false_alarms_per_hour:g} false alarms per hour; {w.max_points_per_s} returns/s "
                f"kept; lines of {w.min_line_s:g}–{w.max_line_s:g} s"
            )
        if busy:
            print(f"mls acquire: {config}: {len(busy)} port(s) cannot be bound", file=sys.stderr)
            raise typer.Exit(EXIT_FAILED)
        raise typer.Exit(EXIT_OK)

    logging.basicConfig(
        level=getattr(logging, log_level.upper(), logging.INFO),
        stream=sys.stderr,
        format="%(asctime)s %(name)s %(levelname)s: %(message)s",
    )
    try:
        code = asyncio.run(sup.run())
    except StartupError as e:
        print(f"mls acquire: cannot start: {e}", file=sys.stderr)
        raise typer.Exit(EXIT_FAILED) from None
    raise typer.Exit(code)


def _bind_failures(cfg) -> list[str]:
    """Test-bind every port the daemon will listen on (then release it): one line per port
    another process holds (or the address is not this host's), naming the device."""
    import socket

    from acquire.daemon.configdevices import listen_endpoints

    out = []
    for d, proto, host, port in listen_endpoints(cfg.devices):
        kind = socket.SOCK_DGRAM if proto == "udp" else socket.SOCK_STREAM
        try:
            with socket.socket(socket.AF_INET, kind) as sock:
                sock.bind((host, port))
        except OSError as e:
            out.append(
                f"{cfg.source}: device {d.name!r}: cannot bind {proto} {host}:{port} "
                f"({e.strerror or e}): another process listens there (a daemon already running?)"
            )
    return out


def _describe(where) -> str:
    from acquire.daemon.configschema import PpsSource

    if where is None:
        return "-"
    t = getattr(where, "type", "")
    if isinstance(where, PpsSource) and t == "udp":
        return f"udp PPS {where.host}:{where.udp_port}"
    if t == "serial":
        return f"serial {where.port} {where.baud} Bd"
    if t in ("udp", "tcp"):
        return f"{t} {where.host}:{where.port}"
    if t == "can":
        return f"can {where.interface} {where.channel}"
    if t == "kernel":
        return f"kernel PPS {where.device}"
    if t == "serial-line":
        return f"serial-line PPS {where.port} ({where.line})"
    return f"udp PPS {where.host}:{where.udp_port}"
