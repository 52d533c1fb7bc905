"""``mls demo`` (what ``make demo`` runs): the whole job on simulated devices, end to end.

:func:`run_demo` works in a fresh run directory (``OUT``, emptied of a previous demo's files)
and runs each step as a child process in **its own process group**, its output in
``OUT/logs/<step>.log``:

1. ``devices`` — ``mls sim devices --scenario montreal`` in real time on the demo's line plan
   (:func:`scenario_overrides`: the montreal site, both targets and the six-fold pattern, with
   short lines, a longer first line on which the daemon's clock locks before its capture
   window, and short transits between the lines); the simulated vessel sails the plan's lines
   (the simulator's helmsman). They write the vessel config (with the site file and its
   ``guidance`` section) into ``OUT`` and send their first byte ``lead_s`` later, once the
   daemon has started. Time runs at ×1: the daemon's clock model locks only on a PPS that
   ticks once per host second, and the guidance accepts a pass only while the clock is LOCKED.
2. ``daemon`` — ``mls acquire --config OUT/vessel.yaml``: the devices, the clock model, the
   session log and the line guidance. The demo follows the guidance on the status socket and
   prints a live line (pass, state, cross-track error, accepted passes, predicted σ) and a line
   per finished pass (:mod:`office.jobs.demo_progress`).
3. When every pass is accepted, or the scenario has ended, the daemon is stopped (SIGTERM: the
   session is closed cleanly), then the devices.
4. ``export`` — ``mls export SESSION --bundle OUT/bundle``;
5. ``calibration`` — ``mls calib run OUT/bundle --out OUT/calib --no-history --accept-refused``
   (its verdict is shown beside the truth, whatever it is);
6. the comparison of the recovered boresight with the truth the devices were fed
   (``OUT/run/scenario_truth.json``): :mod:`office.jobs.demo_compare`.

No process outlives the demo: on success, on an error (:class:`DemoError` names the step and
its log) and on Ctrl-C / SIGTERM (:class:`Interrupted`) every child still running gets SIGTERM
(SIGKILL after a grace period) sent to its whole process group; a child is also asked by the
kernel to stop (SIGTERM, ``PR_SET_PDEATHSIG``) should the demo itself be killed
(:mod:`office.jobs.demo_children`).
"""

from __future__ import annotations

import json
import shutil
import signal
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from acquire.errors import AcquireError
from acquire.status.bus import StatusListener
from office.jobs.demo_children import Child
from office.jobs.demo_compare import AngleComparison, comparison_rows
from office.jobs.demo_progress import pass_events, progress_line, sigma_covers_accepted, sigma_events

NS_PER_S = 1_000_000_000
MARKER = ".mls-demo"  # in OUT: the directory is a demo's, its contents may be removed
#: What a demo writes in OUT (``laz`` was the output of the earlier ``mls demo``).
CONSOLE_PORT = 8480  # the web console's port when free (the default of the web section)
DEMO_ENTRIES = frozenset({MARKER, "run", "bundle", "calib", "logs", "vessel.yaml", "vessel.site.yaml", "laz"})
SIX_FOLD_DEG = (0.0, 180.0, 45.0, 225.0, 315.0, 135.0)
if TYPE_CHECKING:
    from acquire.daemon.config import VesselConfig

MLS = (sys.executable, "-m", "cli.app")


class DemoError(AcquireError, RuntimeError):
    """A step failed: ``step`` names it, ``log`` is where its output is."""

    def __init__(self, step: str, message: str, log: Path | None = None):
        self.step, self.message, self.log = step, message, log
        super().__init__(f"{step}: {message}" + (f" (log: {log})" if log else ""))


class Interrupted(Exception):
    """Ctrl-C, SIGTERM or SIGHUP while the demo runs (``signame`` says which)."""

    def __init__(self, signame: str):
        self.signame = signame
        super().__init__(signame)


# =============================================================================================
# Settings
# =============================================================================================


@dataclass(frozen=True)
class DemoSettings:
    out: Path = Path("demo-out")
    scenario: str = "montreal"
    seed: int = 0
    lead_s: float = 4.0  # the devices wait this long after writing the config: the daemon starts
    first_line_m: float = 44.0  # lead-in: the daemon's clock locks on this line before its window
    line_m: float = 18.0  # the other five lines (each holds its ~10 m capture window)
    pass_gap_s: float = 3.0  # transit from the end of a line to the start of the next
    vessel_speed_mps: float = 2.0
    capture_margin_m: float = 3.0  # = the planner's default, which the daemon's guidance uses
    extra_overrides: tuple[str, ...] = ()  # further scenario overrides (KEY=VALUE)
    start_timeout_s: float = 90.0  # simulation + emulators + daemon ready
    step_timeout_s: float = 600.0  # export, calibration


def scenario_overrides(s: DemoSettings) -> list[str]:
    """The demo's scenario overrides: the six-fold pattern on short lines (values are YAML)."""
    lines = ", ".join(
        f"{{id: {i + 1}, relative_heading_deg: {h:g}, length_m: {s.first_line_m if i == 0 else s.line_m:g}}}"
        for i, h in enumerate(SIX_FOLD_DEG)
    )
    return [
        f"site.passes=[{lines}]",
        f"site.speed_mps={s.vessel_speed_mps:g}",
        f"site.capture_margin_m={s.capture_margin_m:g}",
        f"motion.pass_gap_s={s.pass_gap_s:g}",
        *s.extra_overrides,
    ]


# =============================================================================================
# The run
# =============================================================================================


@dataclass
class DemoResult:
    out: Path
    session: Path
    bundle: Path
    calib: Path
    result: dict
    truth: dict
    rows: list[AngleComparison]
    accepted: int
    n_passes: int
    plots: list[Path] = field(default_factory=list)


def prepare_out(out: Path) -> None:
    """An empty demo directory: created, or emptied when a previous demo made it (its marker
    file, or nothing but what a demo writes); a directory holding anything else, or a file, is
    refused. (The one writer that removes its own output without --force: it can run twice in
    a row, and never removes what it did not make.)"""
    if out.exists() and not out.is_dir():
        raise DemoError("preparing the run directory", f"{out}: --out names a directory, but this is a file")
    out.mkdir(parents=True, exist_ok=True)
    entries = list(out.iterdir())
    foreign = sorted(p.name for p in entries if p.name not in DEMO_ENTRIES)
    if foreign and not (out / MARKER).is_file():
        raise DemoError(
            "preparing the run directory",
            f"{out.resolve()} is not a previous demo's "
            f"run directory (no {MARKER} in it, and it holds {', '.join(foreign[:3])}"
            f"{' …' if len(foreign) > 3 else ''}): choose another --out",
        )
    for p in entries:
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p)
        else:
            p.unlink()
    (out / MARKER).write_text("made by mls demo: everything here is removed by the next demo\n")


def _wait_for_config(path: Path, devices: Child, deadline: float, interrupted) -> None:
    from acquire.daemon.config import VesselConfigError, load_vessel_config
    from calib.io.configfile import ConfigError

    while True:
        interrupted()
        if path.is_file():
            try:  # complete once its last key (site_file) is there
                if load_vessel_config(path).site_file is not None:
                    return
            except (VesselConfigError, ConfigError, OSError):
                pass
        code = devices.poll()
        if code is not None:
            raise DemoError(
                devices.step,
                f"mls sim devices ended with exit code {code} before writing {path}: {devices.tail()}",
                devices.log,
            )
        if time.monotonic() > deadline:
            raise DemoError(devices.step, f"no vessel config {path} after the start timeout", devices.log)
        time.sleep(0.1)


@dataclass
class _Processes:
    """The demo's child processes (in start order) and its status listener: all stopped when
    the demo returns or raises."""

    children: list[Child] = field(default_factory=list)
    watcher: StatusListener | None = None

    def stop(self) -> None:
        if self.watcher is not None:
            self.watcher.stop()
        for c in reversed(self.children):  # the daemon before the devices
            c.stop(signal.SIGTERM, 10.0)


def run_demo(settings: DemoSettings, console, interrupted: Callable[[], None] = lambda: None) -> DemoResult:
    """Run the demo (module docstring). ``interrupted()`` raises :class:`Interrupted` when the
    user asked to stop; every child is stopped when this returns or raises."""
    t_start = time.monotonic()
    out = settings.out
    prepare_out(out)
    out = out.resolve()
    logs, run_dir = out / "logs", out / "run"
    config = out / "vessel.yaml"
    procs = _Processes()
    say = lambda text: console.print(text, highlight=False)  # noqa: E731
    try:
        # 1. the simulated devices (they write the vessel config once they run)
        say(
            f"[bold]mls demo[/bold]: the {settings.scenario} scenario on simulated devices, "
            f"acquired, exported and calibrated in {out}"
        )
        devices, deadline = _start_devices(settings, run_dir, config, logs, procs, interrupted)
        window = json.loads((run_dir / "truth_clock.json").read_text())["window"]
        say(
            f"devices: INS on {run_dir / 'ins'}, profiler and PPS over UDP; "
            f"{window['duration_s']:.0f} s of survey in real time (log {devices.log})"
        )
        # 2. the daemon
        daemon, cfg, watcher = _start_daemon(config, logs, procs, deadline, interrupted)
        say(
            f"daemon: acquiring into {cfg.session_dir}, status on {cfg.status.socket} "
            f"(log {daemon.log}); watch it with: mls checklist --socket {cfg.status.socket}"
        )
        if cfg.web is not None:
            say(f"console: http://{cfg.web.host}:{cfg.web.port}/ (the survey live in a browser)")
        g = _follow(devices, daemon, watcher, console, window["duration_s"] + 60.0, t_start, interrupted)
        # 3. stop the daemon (orderly: the session is closed), then the devices
        session = _close_session(devices, daemon, procs, cfg.session_dir)
        n_passes = len(g.get("passes") or [])
        accepted = int(g.get("accepted", 0))
        say(f"session {session} closed: {accepted}/{n_passes} passes accepted by the guidance")
        # 4. export, 5. calibration
        bundle, calib = out / "bundle", out / "calib"
        _export_and_calibrate(procs.children, session, bundle, calib, logs, settings, interrupted, say)
        result, truth, rows = _read_results(calib, run_dir, logs)
        return DemoResult(
            out, session, bundle, calib, result, truth, rows, accepted, n_passes, sorted(calib.glob("*.png"))
        )
    finally:
        procs.stop()


def _start_devices(
    settings: DemoSettings,
    run_dir: Path,
    config: Path,
    logs: Path,
    procs: _Processes,
    interrupted: Callable[[], None],
) -> tuple[Child, float]:
    """Start the simulated devices and wait for the vessel config they write; the child, and
    the deadline of the start (the daemon's too)."""
    devices = Child(
        "simulated devices (mls sim devices)",
        [
            *MLS,
            "sim",
            "devices",
            "--scenario",
            settings.scenario,
            "--seed",
            str(settings.seed),
            "--speed",
            "1",
            "--devices",
            "ins,profiler,pps",
            "--run-dir",
            str(run_dir),
            "--write-config",
            str(config),
            "--lead-s",
            f"{settings.lead_s:g}",
            *[a for o in scenario_overrides(settings) for a in ("--set", o)],
        ],
        logs / "devices.log",
    )
    procs.children.append(devices)
    deadline = time.monotonic() + settings.start_timeout_s
    _wait_for_config(config, devices, deadline, interrupted)
    return devices, deadline


def _console_port(preferred: int = CONSOLE_PORT) -> int:
    """``preferred`` when nothing listens there on loopback, else a free port."""
    import socket

    with socket.socket() as s:
        try:
            s.bind(("127.0.0.1", preferred))
        except OSError:
            s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _add_console(config: Path) -> None:
    """The web console on loopback in the devices' vessel config (docs/console.md), read-only:
    the demo has no operator token."""
    text = config.read_text()
    if "\nweb:" not in text:
        config.write_text(f"{text.rstrip()}\n\nweb:\n  host: 127.0.0.1\n  port: {_console_port()}\n")


def _start_daemon(
    config: Path, logs: Path, procs: _Processes, deadline: float, interrupted: Callable[[], None]
) -> tuple[Child, VesselConfig, StatusListener]:
    """Start the acquisition daemon on the devices' config and wait until its status says
    it runs; the child, its config and the listener of its status."""
    from acquire.daemon.config import load_vessel_config

    daemon = Child(
        "acquisition daemon (mls acquire)",
        [*MLS, "acquire", "--config", str(config)],
        logs / "acquire.log",
    )
    _add_console(config)
    procs.children.append(daemon)
    cfg = load_vessel_config(config)
    watcher = procs.watcher = StatusListener(cfg.status.socket)
    watcher.start()
    while (watcher.latest("status") or {}).get("state") != "running":
        interrupted()
        code = daemon.poll()
        if code is not None:
            raise DemoError(
                daemon.step, f"exited with code {code} while starting: {daemon.tail()}", daemon.log
            )
        if time.monotonic() > deadline:
            raise DemoError(daemon.step, "not running after the start timeout", daemon.log)
        time.sleep(0.05)
    return daemon, cfg, watcher


def _close_session(devices: Child, daemon: Child, procs: _Processes, session_dir: Path) -> Path:
    """Stop the daemon (orderly: the session is closed), then the devices and the listener;
    the session directory (the one the daemon reported, else the only one there)."""
    watcher = procs.watcher
    assert watcher is not None  # the daemon was started
    session_name = (watcher.latest("status") or {}).get("session")
    code = daemon.stop(signal.SIGTERM, 30.0)
    if code != 0:
        raise DemoError(daemon.step, f"did not stop cleanly (exit code {code}): {daemon.tail()}", daemon.log)
    devices.stop(signal.SIGTERM, 10.0)
    watcher.stop()
    procs.watcher = None
    session = session_dir / session_name if session_name else None
    if session is None or not session.is_dir():
        found = sorted(p for p in session_dir.iterdir() if p.is_dir())
        if len(found) != 1:
            raise DemoError("finding the session", f"{len(found)} sessions in {session_dir}", daemon.log)
        session = found[0]
    return session


def _export_and_calibrate(
    children: list[Child],
    session: Path,
    bundle: Path,
    calib: Path,
    logs: Path,
    settings: DemoSettings,
    interrupted: Callable[[], None],
    say: Callable[[str], None],
) -> None:
    """``mls export`` of the session into ``bundle``, then ``mls calib run`` into ``calib``."""
    _step(
        children,
        "export (mls export)",
        [*MLS, "export", str(session), "--bundle", str(bundle)],
        logs / "export.log",
        settings.step_timeout_s,
        interrupted,
        say,
    )
    _step(
        children,
        "calibration (mls calib run)",
        # --accept-refused: the demo shows every verdict, refused included, beside the truth
        [*MLS, "calib", "run", str(bundle), "--out", str(calib), "--no-history", "--accept-refused"],
        logs / "calib.log",
        settings.step_timeout_s,
        interrupted,
        say,
    )


def _read_results(calib: Path, run_dir: Path, logs: Path) -> tuple[dict, dict, list[AngleComparison]]:
    """The calibration's result, the scenario's truth, and the angles compared."""
    try:
        result = json.loads((calib / "result.json").read_text())
        truth = json.loads((run_dir / "scenario_truth.json").read_text())
        rows = comparison_rows(result, truth)
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise DemoError("reading the results", f"{type(e).__name__}: {e}", logs / "calib.log") from None
    return result, truth, rows


def _step(
    children: list[Child], step: str, args: list[str], log: Path, timeout_s: float, interrupted, say
) -> None:
    say(f"{step.split(' (')[0]}: mls {' '.join(args[len(MLS) :])}")
    c = Child(step, args, log)
    children.append(c)
    code = c.wait(timeout_s, interrupted)
    if code is None:
        raise DemoError(step, f"no result after {timeout_s:g} s", log)
    if code != 0:
        raise DemoError(step, f"exit code {code}: {c.tail()}", log)


def _check_children(devices: Child, daemon: Child, ended_at: float | None) -> float | None:
    """During the survey: the daemon must run; the devices end with the scenario (status 0).
    When the scenario ended (now or before): the monotonic time it ended, else None."""
    code = daemon.poll()
    if code is not None:
        raise DemoError(
            daemon.step, f"ended during the survey (exit code {code}): {daemon.tail()}", daemon.log
        )
    code = devices.poll()
    if code is not None and ended_at is None:
        if code != 0:
            raise DemoError(devices.step, f"ended with exit code {code}: {devices.tail()}", devices.log)
        ended_at = time.monotonic()  # the scenario is over: the last verdict follows
    return ended_at


def _follow(
    devices: Child,
    daemon: Child,
    watcher: StatusListener,
    console,
    timeout_s: float,
    t_start: float,
    interrupted,
) -> dict:
    """Follow the guidance until every pass is accepted or the scenario has ended (then wait
    for the last verdict); returns the last guidance message."""
    from rich.live import Live
    from rich.text import Text

    from acquire.status.feed import guidance_of

    deadline = time.monotonic() + timeout_s
    last: dict = {}
    ended_at = done_at = None
    live = (
        Live(Text(""), console=console, auto_refresh=False, transient=True) if console.is_terminal else None
    )
    if live is not None:
        live.start()
    try:
        while True:
            interrupted()
            g = guidance_of(watcher.latest("checklist"))
            for line in pass_events(last, g) + sigma_events(last, g):
                console.print(line, highlight=False)  # above the live line, when there is one
            last = g or last
            if live is not None:
                clock = (watcher.latest("clock") or {}).get("state")
                status = Text(
                    progress_line(last, clock, time.monotonic() - t_start), no_wrap=True, overflow="ellipsis"
                )
                live.update(status, refresh=True)
            passes = last.get("passes") or []
            if passes and all(p.get("status") == "accepted" for p in passes):
                done_at = done_at or time.monotonic()
                if sigma_covers_accepted(last) or time.monotonic() - done_at > 15.0:
                    return last  # with the σ prediction of all the passes
            ended_at = _check_children(devices, daemon, ended_at)
            if ended_at is not None and time.monotonic() - ended_at > 3.0:
                return last
            if time.monotonic() > deadline:
                raise DemoError(daemon.step, f"the survey did not end within {timeout_s:.0f} s", daemon.log)
            time.sleep(0.25)
    finally:
        if live is not None:
            live.stop()
