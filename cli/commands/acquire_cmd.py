"""``mls acquire --config vessel.yaml``: the acquisition daemon (what systemd runs)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from cli.options import vessel_config_option

if TYPE_CHECKING:
    from acquire.daemon.config import VesselConfig
    from acquire.daemon.supervisor import Supervisor
    from acquire.guidance.daemon import GuidanceConsumer
    from acquire.watch.daemon import MountWatchConsumer

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
    config: Annotated[Path, vessel_config_option("Vessel config (YAML), see systemd/vessel.example.yaml.")],
    check: Annotated[
        bool,
        typer.Option(
            "--check",
            help="Validate the config, print a summary of the devices, test-bind every UDP port the "
            "daemon listens on (exit 1 when one is taken) and exit.",
        ),
    ] = False,
    log_level: Annotated[
        str, typer.Option("--log-level", help="Log level on stderr: debug, info, warning, error.")
    ] = "info",
    sim_host_clock: Annotated[
        Path | None,
        typer.Option(
            "--sim-host-clock",
            hidden=True,
            help="Tests only: read the host clock through the simulated devices' fake (their "
            "run directory's host_clock file, with the host_clock_step faults). Never on a vessel.",
        ),
    ] = None,
) -> None:
    """``mls acquire`` (its help text is :data:`HELP`)."""
    _one_blas_thread()
    cfg = _load_config(config)
    daemon = _build_daemon(cfg, sim_host_clock)
    if check:
        raise typer.Exit(_check(config, cfg, daemon))
    raise typer.Exit(_run(daemon.supervisor, log_level))


def _one_blas_thread() -> None:
    """BLAS on one thread (before numpy loads; the environment's own setting wins): the daemon's
    numeric work — the guidance's σ prediction, the mount watch's block solves — runs in worker
    threads beside the acquisition, and a BLAS spinning on every core starves the event loop
    (and solves no faster on a 2-core vessel PC)."""
    import os

    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")


def _load_config(config: Path) -> VesselConfig:
    """The vessel config; every error printed (one per line) and exit status 2 when invalid."""
    import sys

    from acquire.daemon.config import VesselConfigError, load_vessel_config
    from calib.core.errors import MlsError

    try:
        return load_vessel_config(config)
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


@dataclass(frozen=True)
class _Daemon:
    """The supervisor with its optional consumers (already added to it)."""

    supervisor: Supervisor
    guidance: GuidanceConsumer | None
    watch: MountWatchConsumer | None


def _build_daemon(cfg: VesselConfig, sim_host_clock: Path | None = None) -> _Daemon:
    """The supervisor of the config with the line guidance and the mount watch it asks for;
    exit status 2 when the config asks for what cannot be done (StartupError, *SetupError).
    ``sim_host_clock``: the simulated devices' fake host clock's file (tests only)."""
    import sys

    from acquire.console.daemon import console_consumer
    from acquire.daemon.supervisor import Supervisor
    from acquire.foxglove.daemon import foxglove_consumer
    from acquire.guidance.daemon import guidance_consumer
    from acquire.watch.daemon import mount_watch_consumer
    from calib.core.errors import MlsError
    from drivers.timing import FakeHostClock

    try:
        host_clock = None if sim_host_clock is None else FakeHostClock(str(sim_host_clock))
        sup = Supervisor(cfg, host_clock=host_clock)
        guidance = guidance_consumer(cfg, sup)
        watch = mount_watch_consumer(cfg, sup)
        console = console_consumer(cfg, sup)
        foxglove = foxglove_consumer(cfg, sup)
    except MlsError as e:
        print(f"mls acquire: {e}", file=sys.stderr)
        raise typer.Exit(EXIT_CONFIG) from None
    if guidance is not None:
        sup.consumers.append(guidance)
    if watch is not None:
        sup.consumers.append(watch)
    sup.consumers.extend(c for c in (console, foxglove) if c is not None)
    return _Daemon(supervisor=sup, guidance=guidance, watch=watch)


def _check(config: Path, cfg: VesselConfig, daemon: _Daemon) -> int:
    """``--check``: the devices table, the ports that cannot be bound, a session root the daemon
    would refuse, what the guidance and the mount watch will do; the exit status (1 when a port is
    taken or the session root is unsafe)."""
    import sys

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
    root = _session_root_problem(cfg)
    if root is not None:
        print(f"mls acquire: {config}: {root}", file=sys.stderr)
    for line in busy:
        print(line, file=sys.stderr)
    if daemon.guidance is not None:
        print(_guidance_line(cfg, daemon.guidance))
    if daemon.watch is not None:
        print(_watch_line(cfg, daemon.watch))
    if busy:
        print(f"mls acquire: {config}: {len(busy)} port(s) cannot be bound", file=sys.stderr)
    return EXIT_FAILED if busy or root is not None else EXIT_OK


def _session_root_problem(cfg: VesselConfig) -> str | None:
    """Why the daemon would refuse ``session.directory`` at start (another user's, writable by
    others), or None; a missing root is fine (the daemon makes it), and nothing is made here."""
    from acquire.status.runfiles import UnsafeRunFile, check_private_dir

    if not Path(cfg.session_dir).exists():
        return None
    try:
        check_private_dir(
            cfg.session_dir, "session root", "choose another session.directory", sticky_ok=False
        )
    except UnsafeRunFile as e:
        return str(e)
    return None


def _guidance_line(cfg: VesselConfig, guidance: GuidanceConsumer) -> str:
    """What the line guidance accepts, in one line."""
    g, tol = guidance.guidance, cfg.guidance
    return (
        f"guidance: {len(g.plan.passes)} passes around {len(g.target_names)} targets "
        f"({', '.join(g.target_names)}) of {cfg.site_file}; accepted within "
        f"{tol.max_xte_m:g} m XTE, {tol.max_heading_error_deg:g}° heading, "
        f"±{tol.max_speed_error_mps:g} m/s, ≥ {tol.min_points_per_target} points per "
        f"target, gaps ≤ {tol.max_gap_s:g} s"
    )


def _watch_line(cfg: VesselConfig, watch: MountWatchConsumer) -> str:
    """What the mount watch watches for, in one line."""
    w, b = cfg.watch, watch.info["boresight_deg"]
    return (
        f"mount watch: calibrated boresight roll {b[0]:+.4f}°, pitch {b[1]:+.4f}°, yaw "
        f"{b[2]:+.4f}° of {w.calibration}; tuned to {w.shift_deg:g}°, "
        f"{w.false_alarms_per_hour:g} false alarms per hour; {w.max_points_per_s} returns/s "
        f"kept; lines of {w.min_line_s:g}–{w.max_line_s:g} s"
    )


def _run(sup: Supervisor, log_level: str) -> int:
    """Run the daemon until it stops; its exit status (1 when it cannot start)."""
    import asyncio
    import logging
    import sys

    from acquire.daemon.supervisor import StartupError

    logging.basicConfig(
        level=getattr(logging, log_level.upper(), logging.INFO),
        stream=sys.stderr,
        format="%(asctime)s %(name)s %(levelname)s: %(message)s",
    )
    try:
        return asyncio.run(sup.run())
    except StartupError as e:
        print(f"mls acquire: cannot start: {e}", file=sys.stderr)
        raise typer.Exit(EXIT_FAILED) from None


def _listen_endpoints(cfg: VesselConfig) -> list[tuple[str, str, str, int]]:
    """(what, protocol, host, port) of every port the daemon will listen on: the devices', the
    console's and the live Foxglove server's."""
    from acquire.daemon.configdevices import listen_endpoints

    out = [
        (f"device {d.name!r}", proto, host, port) for d, proto, host, port in listen_endpoints(cfg.devices)
    ]
    web = cfg.web
    if web is not None:
        out.append(("web.port (the console)", "tcp", web.host, web.port))
        if web.foxglove_port is not None:
            out.append(("web.foxglove_port (Foxglove live)", "tcp", web.host, web.foxglove_port))
    return out


def _bind_failures(cfg: VesselConfig) -> list[str]:
    """Test-bind every port the daemon will listen on (then release it): one line per port
    another process holds (or the address is not this host's), naming its owner."""
    import socket

    out = []
    for what, proto, host, port in _listen_endpoints(cfg):
        kind = socket.SOCK_DGRAM if proto == "udp" else socket.SOCK_STREAM
        try:
            with socket.socket(socket.AF_INET, kind) as sock:
                sock.bind((host, port))
        except OSError as e:
            out.append(
                f"{cfg.source}: {what}: cannot bind {proto} {host}:{port} "
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
