"""``mls sim devices`` and ``mls sim replay``: the simulated devices (``sim_devices``), loaded
lazily inside the commands (``acquire`` never imports ``sim_devices`` at module level).

``devices`` turns a scenario into the byte streams of the INS (pty), the profiler and the PPS
(UDP) and the CAN event markers, in real time, with scripted faults; ``replay`` re-emits a
recorded session's raw channels with their original timing. Both print where each device is,
can write a vessel config for ``mls acquire``, and stop cleanly on Ctrl-C / SIGTERM.
"""

from __future__ import annotations

import signal
import threading
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from cli.commands.sim_cmd import app, simulation_bar
from cli.options import (
    CanChannel,
    InsProtocol,
    InsRate,
    PointRateScale,
    PpsPort,
    ProfilerPort,
    can_port_option,
    profiler_host_option,
    realtime_option,
    run_dir_option,
    scenario_option,
    seed_option,
    session_argument,
    set_option,
    speed_option,
    write_config_option,
)

if TYPE_CHECKING:
    from rich.console import Console

    from sim_devices.faults import FaultPlan
    from sim_devices.feed import ScenarioFeed


def _parse_devices(text: str) -> tuple[str, ...]:
    from sim_devices.runner import DEVICES

    names = tuple(n.strip() for n in text.split(",") if n.strip())
    bad = [n for n in names if n not in DEVICES]
    if bad or not names:
        raise typer.BadParameter(f"{text!r}: expected a comma-separated subset of {','.join(DEVICES)}")
    return names


def _locations_table(locations: dict, run_dir: Path, title: str):
    from rich import box
    from rich.table import Table

    t = Table(title=title, title_justify="left", box=box.SIMPLE_HEAD, pad_edge=False)
    for col in ("device", "where", "what"):
        t.add_column(col, no_wrap=col != "what")
    for name, loc in locations.items():
        if name == "ins":
            where = f"{loc['link']} → {loc['pty']}"
            what = f"{loc.get('protocol') or 'raw'}" + (
                f" {loc['rate_hz']:g} Hz" if loc.get("rate_hz") else ""
            )
        elif name == "can":
            where = f"{loc['interface']} {loc['channel']}" + (f" port {loc['port']}" if "port" in loc else "")
            what = f"event markers ({loc['markers']})" if "markers" in loc else "recorded CAN frames"
        else:
            host, port = loc["address"]
            where = f"udp {host}:{port}"
            what = loc.get("protocol") or loc.get("format", "")
            if "profile_rate_hz" in loc:
                what += (
                    f" {loc['profile_rate_hz']:.1f} profiles/s × {loc['points_per_profile']} pts "
                    f"({loc['packets_per_profile']} packets)"
                )
            if "jitter_s" in loc:
                what += f" pulses, stamp jitter σ {loc['jitter_s'] * 1e6:g} µs"
        t.add_row(name, where, what)
    t.caption = f"run directory {run_dir}: truth_clock.json, faults.json, devices.json, stats/"
    t.caption_justify = "left"
    return t


def _stats_table(stats: dict, title: str):
    from rich import box
    from rich.table import Table

    t = Table(title=title, title_justify="left", box=box.SIMPLE_HEAD, pad_edge=False)
    for col in ("device", "status", "sent", "faults applied", "timing error median / p99", "CPU"):
        t.add_column(col, justify="left" if col in ("device", "status", "faults applied") else "right")
    for name, st in stats.items():
        s, tm = st.get("stats", {}), st.get("timing", {})
        sent = {
            "ins": f"{s.get('epochs', s.get('messages', 0))} epochs",
            "profiler": f"{s.get('packets', s.get('messages', 0))} datagrams",
            "pps": f"{s.get('pulses', s.get('messages', 0))} pulses",
            "can": f"{s.get('markers', s.get('messages', 0))} frames",
        }[name]
        faults = ", ".join(
            f"{k} {s[k]}"
            for k in (
                "lost",
                "reordered",
                "duplicated",
                "corrupted",
                "garbage_bytes",
                "unplugs",
                "suppressed",
            )
            if s.get(k)
        )
        timing = (
            f"{tm['error_median_us'] / 1e3:.2f} / {tm['error_p99_us'] / 1e3:.2f} ms"
            if "error_median_us" in tm
            else "–"
        )
        cpu = f"{100 * tm['cpu_fraction']:.0f} %" if tm.get("wall_s", 0) > 0.5 else "–"
        t.add_row(name, st.get("status", "?"), sent, faults or "–", timing, cpu)
    return t


def _run_until_done(run, console, total_s: float, label: str, stop: threading.Event) -> bool:
    """Progress bar until every emulator ends; True if ``stop`` was set (Ctrl-C / SIGTERM)."""
    from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

    with Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        TextColumn("{task.completed:.1f}/{task.total:.1f} s"),
        TimeRemainingColumn(),
        console=console,
        transient=True,
    ) as bar:
        task = bar.add_task(label, total=total_s)
        while not stop.is_set() and not run.wait(0.2):
            bar.update(task, completed=run.elapsed_s())
    if stop.is_set():
        console.print("stopping the emulators …", highlight=False)
        return True
    return False


class _SigtermAsInterrupt:
    """SIGTERM raises KeyboardInterrupt (the Ctrl-C path: stop the emulators, clean up)."""

    def __enter__(self):
        self.previous = signal.signal(signal.SIGTERM, signal.default_int_handler)
        return self

    def __exit__(self, *exc) -> None:
        signal.signal(signal.SIGTERM, self.previous)


class _StopOnSignal:
    """While the emulators run, Ctrl-C and SIGTERM only set an event that the waiting loop
    polls: an exception raised at whatever line the signal lands on (inside a lock, a join, a
    terminal write) could leave the stop half done."""

    def __init__(self) -> None:
        self.event = threading.Event()

    def __enter__(self) -> threading.Event:
        handler = lambda *_: self.event.set()  # noqa: E731
        self.previous = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
        return self.event

    def __exit__(self, *exc) -> None:
        for s, h in self.previous.items():
            signal.signal(s, h)


def _check_config(path: Path, console) -> None:
    from acquire.daemon.config import VesselConfigError, load_vessel_config

    try:
        load_vessel_config(path)
    except VesselConfigError as e:
        console.print(f"[red]the written vessel config does not validate[/red] (a bug): {e}", highlight=False)
        raise typer.Exit(1) from None
    console.print(f"vessel config for `mls acquire --config`: {path.resolve()}", highlight=False)


@app.command("devices")
def devices(
    scenario: Annotated[
        str,
        scenario_option(
            "A shipped scenario (montreal, montreal_piles, harbour_cal, terrestrial, tower) or a scenario YAML file."
        ),
    ],
    seed: Annotated[int, seed_option("Random seed of the simulation, the jitters and the faults.")] = 0,
    speed: Annotated[
        float,
        speed_option(
            "Scenario seconds per real second (2 = twice as fast; the GPS clock then "
            "runs 2× the host's, and above 2 the PPS comes faster than gpsd's rules "
            "accept, so a daemon's clock model will not lock)."
        ),
    ] = 1.0,
    faults: Annotated[
        Path | None,
        typer.Option(
            "--faults",
            metavar="FILE",
            help="Fault timeline (YAML): unplug, garbage, bad checksums, UDP "
            "loss/reorder/duplication, PPS loss, profiler clock offset/drift, "
            "INS latency jump, GNSS outage, late ZDA, INS leap second, host clock step "
            "(for a daemon started with mls acquire --sim-host-clock RUN_DIR/host_clock).",
        ),
    ] = None,
    write_config: Annotated[
        Path | None, write_config_option("Write a vessel config for `mls acquire` that uses these devices.")
    ] = None,
    run_dir: Annotated[
        Path, run_dir_option("Run directory: the INS link 'ins', truth_clock.json, faults.json, stats/.")
    ] = Path("mls-sim"),
    start: Annotated[
        str | None,
        typer.Option(
            "--start",
            metavar="SECONDS|pass:N",
            help="Start the run this many scenario seconds after the scenario's start, "
            "or at the line start of pass N (default: the beginning).",
        ),
    ] = None,
    duration: Annotated[
        float | None,
        typer.Option(
            "--duration", min=0.001, help="Scenario seconds to run (default: to the scenario's end)."
        ),
    ] = None,
    point_rate_scale: PointRateScale = None,
    set_: Annotated[
        list[str] | None, set_option("Override a scenario value by dotted key (repeatable; values are YAML).")
    ] = None,
    only: Annotated[
        str,
        typer.Option(
            "--devices",
            metavar="LIST",
            help="The emulators to run (comma-separated subset of ins,profiler,pps,can).",
        ),
    ] = "ins,profiler,pps,can",
    ins_protocol: InsProtocol = "nmea",
    ins_rate: InsRate = 100.0,
    ins_latency_ms: Annotated[
        float, typer.Option("--ins-latency-ms", min=0.0, help="INS output latency (ms).")
    ] = 3.0,
    ins_jitter_ms: Annotated[
        float, typer.Option("--ins-jitter-ms", min=0.0, help="INS output jitter, uniform (ms).")
    ] = 0.5,
    ins_alignment_s: Annotated[
        float,
        typer.Option(
            "--ins-alignment-s", min=0.0, help="Seconds of INS alignment at the start (status: aligning)."
        ),
    ] = 0.0,
    stdbin_version: Annotated[
        int, typer.Option("--stdbin-version", min=2, max=5, help="STDBIN protocol version.")
    ] = 3,
    profiler_host: Annotated[
        str, profiler_host_option("Where the profiler sends its datagrams.")
    ] = "127.0.0.1",
    profiler_port: ProfilerPort = 0,
    pps_port: PpsPort = 0,
    pps_jitter_us: Annotated[
        float, typer.Option("--pps-jitter-us", min=0.0, help="PPS stamp jitter σ (µs).")
    ] = 20.0,
    can_channel: CanChannel = "239.74.163.2",
    can_port: Annotated[
        int, can_port_option("CAN udp_multicast port (a vessel config can only use 43113).")
    ] = 43113,
    clock_drift_ppm: Annotated[
        float,
        typer.Option(
            "--clock-drift-ppm", help="Truth clock: GPS time runs this much faster than the host clock."
        ),
    ] = 0.0,
    realtime: Annotated[
        bool,
        realtime_option(
            "Run the emulators SCHED_FIFO where permitted (root or RLIMIT_RTPRIO): "
            "sub-millisecond timing on a busy machine."
        ),
    ] = False,
    lead_s: Annotated[
        float,
        typer.Option(
            "--lead-s",
            min=0.05,
            max=60.0,
            help="Seconds between the emulators being ready (and the vessel config written) "
            "and the first byte of the run: time for a daemon to start.",
        ),
    ] = 0.25,
    time_base: Annotated[
        str,
        typer.Option(
            "--time",
            metavar="now|scenario",
            help="Devices send today's date and time (now: the scenario moved by whole "
            "seconds, recorded in truth_clock.json) or the scenario's own.",
        ),
    ] = "now",
) -> None:
    """Run the simulated INS, profiler, PPS and CAN devices in real time.

    The scenario is simulated, then each device runs in its own process: the INS writes NMEA or
    STDBIN to a pty behind the stable link RUN_DIR/ins, the profiler sends ZFP1 packets and the
    PPS its pulses over UDP, the CAN emulator sends pass start/end markers. All share one truth
    clock (RUN_DIR/truth_clock.json). Ctrl-C stops them cleanly."""
    from rich.console import Console

    from calib.core.errors import MlsError
    from sim_devices.canbus import CanSettings
    from sim_devices.faults import FaultPlan, load_faults
    from sim_devices.ins import InsSettings
    from sim_devices.pps import PpsSettings
    from sim_devices.profiler import ProfilerSettings
    from sim_devices.runner import DeviceRun, DevicesSpec

    console = Console(emoji=False)  # ":100:" of file:line:column is no emoji
    _check_paths(console, run_dir, write_config)
    names = _parse_devices(only)
    if time_base not in ("now", "scenario"):
        raise typer.BadParameter(f"{time_base!r}: expected now or scenario", param_hint="--time")
    overrides = _overrides(set_, point_rate_scale)
    with _SigtermAsInterrupt():
        try:
            spec = DevicesSpec(
                run_dir=run_dir,
                devices=names,
                speed=speed,
                drift_ppm=clock_drift_ppm,
                seed=seed,
                ins=InsSettings(
                    protocol=ins_protocol,
                    rate_hz=ins_rate,
                    stdbin_version=stdbin_version,
                    latency_s=ins_latency_ms / 1e3,
                    jitter_s=ins_jitter_ms / 1e3,
                    alignment_s=ins_alignment_s,
                ),
                profiler=ProfilerSettings(host=profiler_host, port=profiler_port),
                pps=PpsSettings(port=pps_port, jitter_s=pps_jitter_us / 1e6),
                can=CanSettings(channel=can_channel, port=can_port),
                realtime=realtime,
                lead_s=lead_s,
            )
            plan = load_faults(faults) if faults is not None else FaultPlan()
            feed = _simulate_feed(console, scenario, seed, overrides, start, duration, ins_rate, time_base)
            run = DeviceRun(feed, spec, plan)
        except (MlsError, ValueError, OSError) as e:  # ValueError: the emulators' settings
            console.print(f"[red]error:[/red] {e}", highlight=False)
            raise typer.Exit(2) from None
        except KeyboardInterrupt:
            raise typer.Exit(130) from None
        title = f"{feed.name} (seed {seed}): {feed.duration_s:g} scenario s at ×{speed:g}"
        _serve(
            run,
            console,
            lambda loc: _locations_table(loc, run.run_dir, title),
            _fault_notes(plan),
            write_config,
            feed.duration_s,
            f"{feed.name} scenario time",
            "emulators",
        )


def _overrides(set_: list[str] | None, point_rate_scale: float | None) -> list[str]:
    """The scenario overrides: those of ``--set``, then ``--point-rate-scale``."""
    overrides = list(set_ or ())
    if point_rate_scale is not None:
        overrides.append(f"scanner.point_rate_scale={point_rate_scale!r}")
    return overrides


def _simulate_feed(
    console: Console,
    scenario: str,
    seed: int,
    overrides: list[str],
    start: str | None,
    duration: float | None,
    ins_rate: float,
    time_base: str,
) -> ScenarioFeed:
    """Simulate the scenario (a progress bar) and cut the devices' feed from it."""
    from calib.sim.simulate import simulate
    from sim_devices.feed import make_feed

    with simulation_bar(console, f"simulating {scenario}") as (bar, task, progress):
        sim = simulate(scenario, seed, overrides=overrides, progress=progress)
        return make_feed(sim, start, duration, ins_rate, "now" if time_base == "now" else 0)


def _fault_notes(plan: FaultPlan) -> list[str]:
    """The faults scheduled, in one note (none without faults)."""
    if not plan.faults:
        return []
    return [
        f"{len(plan.faults)} faults scheduled (faults.json): "
        + ", ".join(f"{f.kind} at {f.at_s:g} s" for f in plan.faults)
    ]


def _check_paths(console, run_dir: Path, write_config: Path | None) -> None:
    """A file where the run directory goes, or a directory where the vessel config goes: one
    line and exit status 2, before anything starts."""
    problem = None
    if run_dir.exists() and not run_dir.is_dir():
        problem = f"{run_dir}: --run-dir names a directory, but this is a file"
    elif write_config is not None and write_config.is_dir():
        problem = f"{write_config}: --write-config names a file, but this is a directory"
    if problem is not None:
        console.print(f"[red]error:[/red] {problem}", highlight=False)
        raise typer.Exit(2)


def _serve(
    run,
    console,
    locations_table,
    notes: list[str],
    write_config: Path | None,
    total_s: float,
    label: str,
    title: str,
) -> None:
    """Start the run, say where the devices are, wait for its end or Ctrl-C / SIGTERM
    (:class:`_StopOnSignal`), stop it, and print what each emulator did (exit 1 if one crashed)."""
    from calib.core.errors import MlsError

    with run, _StopOnSignal() as stop:
        try:
            locations = run.start()
            console.print(locations_table(locations))
            for note in notes:
                console.print(note, highlight=False)
            if write_config is not None:
                _check_config(run.write_vessel_config(write_config), console)
            console.file.flush()
            interrupted = _run_until_done(run, console, total_s, label, stop)
        except (MlsError, ValueError) as e:
            console.print(f"[red]error:[/red] {e}", highlight=False)
            raise typer.Exit(1) from None
        stats = run.stop()
    console.print(_stats_table(stats, title + (" (stopped)" if interrupted else "")))
    crashed = [s for s in stats.values() if s.get("status") in ("crashed", "failed to start")]
    for s in crashed:
        console.print(f"[red]{s['device']}:[/red] {s.get('error', s['status'])}", highlight=False)
    if crashed:
        raise typer.Exit(1)


# -- replay -------------------------------------------------------------------------------------


def read_session(session_dir: Path):
    """A recorded session (MCAP segments) as a :class:`sim_devices.replay.RecordedSession`."""
    from acquire.log.read import iter_messages, raw_channels
    from sim_devices.replay import RecordedMessage, RecordedSession

    raw = raw_channels(session_dir)

    def messages(topics):
        for env in iter_messages(raw.path, topics):
            yield RecordedMessage(env.topic, env.host_ns, env.payload)

    return RecordedSession(
        raw.name, raw.channels, raw.counts, raw.first_host_ns, raw.last_host_ns, messages, raw.gps_fit
    )


@app.command("replay")
def replay(
    session: Annotated[
        Path, session_argument("A session directory (YYYYmmddTHHMMSSZ_<vessel>/ with seg-*.mcap).")
    ],
    speed: Annotated[float, speed_option("Replay speed (2 = twice as fast).")] = 1.0,
    run_dir: Annotated[Path, run_dir_option("Run directory: the INS link 'ins', devices.json.")] = Path(
        "mls-replay"
    ),
    write_config: Annotated[
        Path | None, write_config_option("Write a vessel config for `mls acquire` that uses the replay.")
    ] = None,
    profiler_host: Annotated[str, profiler_host_option("Where the profiler datagrams go.")] = "127.0.0.1",
    profiler_port: ProfilerPort = 0,
    pps_port: PpsPort = 0,
    can_channel: CanChannel = "239.74.163.2",
    can_port: Annotated[int, can_port_option("CAN udp_multicast port.")] = 43113,
    realtime: Annotated[bool, realtime_option("Run the replay SCHED_FIFO where permitted.")] = False,
) -> None:
    """Re-emit a recorded session's raw channels with their original timing.

    /ins/raw goes to a pty behind RUN_DIR/ins, /lidar/raw to the profiler UDP port, /pps as PPS
    datagrams, /can/<name> on the CAN bus — the same transports the emulators use. Ctrl-C stops."""
    from rich.console import Console

    from calib.core.errors import MlsError
    from sim_devices.canbus import CanSettings
    from sim_devices.replay import ReplayRun, ReplaySpec

    console = Console(emoji=False)  # ":100:" of file:line:column is no emoji
    _check_paths(console, run_dir, write_config)
    with _SigtermAsInterrupt():
        try:
            with console.status(f"reading {session}"):
                rec = read_session(session)
            spec = ReplaySpec(
                run_dir=run_dir,
                speed=speed,
                profiler=(profiler_host, profiler_port),
                pps=("127.0.0.1", pps_port),
                can=CanSettings(channel=can_channel, port=can_port),
                realtime=realtime,
            )
            run = ReplayRun(rec, spec)
        except (MlsError, ValueError, OSError) as e:
            console.print(f"[red]error:[/red] {e}", highlight=False)
            raise typer.Exit(2) from None
        except KeyboardInterrupt:
            raise typer.Exit(130) from None
        counts = ", ".join(f"{t} {rec.counts[t]}" for t in sorted(rec.channels))
        title = f"replay of {rec.name}: {rec.duration_s:.1f} s at ×{speed:g} ({counts})"
        _serve(
            run,
            console,
            lambda loc: _locations_table(loc, run.run_dir, title),
            [],
            write_config,
            rec.duration_s / speed,
            "replay",
            "replay",
        )
