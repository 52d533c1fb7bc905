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
   per finished pass (:func:`progress_line`, :func:`pass_events`).
3. When every pass is accepted, or the scenario has ended, the daemon is stopped (SIGTERM: the
   session is closed cleanly), then the devices.
4. ``export`` — ``mls export SESSION --bundle OUT/bundle``;
5. ``calibration`` — ``mls calib run OUT/bundle --out OUT/calib --no-history``;
6. the comparison of the recovered boresight with the truth the devices were fed
   (``OUT/run/scenario_truth.json``): :func:`comparison_rows` and :func:`comparison_table`.

No process outlives the demo: on success, on an error (:class:`DemoError` names the step and
its log) and on Ctrl-C / SIGTERM (:class:`Interrupted`) every child still running gets SIGTERM
(SIGKILL after a grace period) sent to its whole process group; a child is also asked by the
kernel to stop (SIGTERM, ``PR_SET_PDEATHSIG``) should the demo itself be killed.
"""

from __future__ import annotations

import ctypes
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from acquire.status.bus import StatusListener

NS_PER_S = 1_000_000_000
MARKER = ".mls-demo"  # in OUT: the directory is a demo's, its contents may be removed
#: What a demo writes in OUT (``laz`` was the output of the earlier ``mls demo``).
DEMO_ENTRIES = frozenset({MARKER, "run", "bundle", "calib", "logs", "vessel.yaml", "vessel.site.yaml", "laz"})
SIX_FOLD_DEG = (0.0, 180.0, 45.0, 225.0, 315.0, 135.0)
ANGLES = ("roll", "pitch", "yaw")
MLS = (sys.executable, "-m", "cli.app")


class DemoError(RuntimeError):
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
# Child processes
# =============================================================================================


def _child_setup(parent_pid: int) -> Callable[[], None]:
    """In the child before exec: be stopped (SIGTERM) when the demo dies (Linux's
    ``PR_SET_PDEATHSIG``; nothing is imported or allocated after the fork)."""
    try:
        prctl = ctypes.CDLL(None, use_errno=True).prctl
    except (OSError, AttributeError):
        prctl = None
    sigterm = int(signal.SIGTERM)

    def setup() -> None:
        if prctl is not None:
            prctl(1, sigterm)  # PR_SET_PDEATHSIG
        if os.getppid() != parent_pid:  # the demo died before the prctl
            os.kill(os.getpid(), sigterm)

    return setup


class Child:
    """A child process in its own process group (``setpgid``), output to ``log``; the group is
    what gets signalled."""

    def __init__(self, step: str, args: list[str], log: Path):
        self.step, self.args, self.log = step, args, log
        log.parent.mkdir(parents=True, exist_ok=True)
        with open(log, "wb") as f:
            f.write(("$ " + " ".join(args) + "\n").encode())
            f.flush()
            self.p = subprocess.Popen(
                args,
                stdin=subprocess.DEVNULL,
                stdout=f,
                stderr=subprocess.STDOUT,
                process_group=0,
                preexec_fn=_child_setup(os.getpid()),
            )

    def poll(self) -> int | None:
        return self.p.poll()

    def send(self, sig: int) -> None:
        try:
            os.killpg(self.p.pid, sig)
        except (ProcessLookupError, PermissionError):
            pass

    def group_left(self) -> list[int]:
        """Processes still in the child's group (in the demo's session: not a stranger that
        reused the number)."""
        sid, out = os.getsid(0), []
        for d in Path("/proc").iterdir():
            if d.name.isdigit():
                try:
                    stat = (d / "stat").read_text()
                except OSError:
                    continue
                f = stat[stat.rfind(")") + 2 :].split()  # state ppid pgrp session ...
                if f[0] != "Z" and int(f[2]) == self.p.pid and int(f[3]) == sid:
                    out.append(int(d.name))
        return out

    def stop(self, sig: int = signal.SIGTERM, grace_s: float = 10.0) -> int | None:
        """Signal the group and wait; SIGKILL the group after ``grace_s``. Returns the exit
        code of the child itself (None if it had to be killed)."""
        if self.p.poll() is None:
            self.send(sig)
            try:
                return self.p.wait(grace_s)
            except subprocess.TimeoutExpired:
                pass
        code = self.p.poll()
        if code is None or self.group_left():  # the child, or what is left of its group
            self.send(signal.SIGKILL)
        if code is None:
            try:
                self.p.wait(5.0)
            except subprocess.TimeoutExpired:
                pass
        return code

    def wait(self, timeout_s: float, interrupted: Callable[[], None]) -> int:
        deadline = time.monotonic() + timeout_s
        while True:
            interrupted()
            code = self.p.poll()
            if code is not None:
                return code
            if time.monotonic() > deadline:
                raise DemoError(self.step, f"no result after {timeout_s:g} s", self.log)
            time.sleep(0.1)

    def tail(self, n: int = 4) -> str:
        try:
            lines = [ln.strip() for ln in self.log.read_text(errors="replace").splitlines()]
        except OSError:
            return ""
        return " / ".join([ln for ln in lines if ln][-n:])


# =============================================================================================
# What is printed while the survey runs (pure)
# =============================================================================================


def _sigma_text(g: dict) -> str:
    """The predicted realistic σ of the accepted passes (n/o: not observable yet)."""
    cur = ((g.get("sigma") or {}).get("current")) or {}
    r = cur.get("realistic_deg") or {}
    if not cur.get("passes"):
        return "σ —"
    return "σ " + " ".join(f"{a} " + ("n/o" if r.get(a) is None else f"{r[a]:.3f}°") for a in ANGLES)


def progress_line(g: dict, clock_state: str | None, elapsed_s: float) -> str:
    """One line of at most ~80 characters: the elapsed time, the active pass and its state,
    XTE, accepted passes, predicted σ (realistic, roll pitch yaw, n/o: not observable yet) and
    the clock when it is not LOCKED."""
    passes = g.get("passes") or []
    a = g.get("active") or {}
    parts = [f"{int(elapsed_s) // 60:02d}:{int(elapsed_s) % 60:02d}"]
    if not g:
        parts.append("waiting for the guidance")
    else:
        if a:
            state = str(a.get("state", "approach"))
            if state == "capture" and "along_m" in a:
                c0, c1 = a.get("capture_m", (0.0, 0.0))
                state += f" {max(a['along_m'] - c0, 0.0):.0f}/{c1 - c0:.0f} m"
            parts.append(f"pass {a.get('pass_id')} {state}")
            if "xte_m" in a:
                parts.append(f"· XTE {a['xte_m']:+.2f} m")
        else:
            parts.append("all passes sailed" if passes else "no plan")
        parts.append(f"· {g.get('accepted', 0)}/{len(passes)} accepted")
        cur = ((g.get("sigma") or {}).get("current")) or {}
        r = cur.get("realistic_deg") or {}
        if cur.get("passes"):
            parts.append("· σ° " + " ".join("n/o" if r.get(x) is None else f"{r[x]:.3f}" for x in ANGLES))
    if clock_state != "LOCKED":
        parts.append(f"· clock {clock_state or '—'}")
    return " ".join(parts)


def pass_events(before: dict, after: dict) -> list[str]:
    """A line for every pass that got a new verdict between two guidance messages."""
    old = {p["id"]: p.get("attempts", 0) for p in (before.get("passes") or [])}
    out = []
    for p in after.get("passes") or []:
        if p.get("attempts", 0) <= old.get(p["id"], 0) or p.get("status") not in ("accepted", "rejected"):
            continue
        hits = ", ".join(f"{k} {v}" for k, v in (p.get("hits") or {}).items())
        st = p.get("stats") or {}
        if p["status"] == "accepted":
            line = (
                f"✔ pass {p['id']} ({p['relative_heading_deg']:.0f}°) accepted: hits {hits}; "
                f"max XTE {st.get('max_xte_m', math.nan):.2f} m"
            )
        else:
            line = f"✘ pass {p['id']} ({p['relative_heading_deg']:.0f}°) rejected: " + "; ".join(
                p.get("reasons") or []
            )
        out.append(line)
    return out


def _sigma_passes(g: dict) -> list:
    return list(((g.get("sigma") or {}).get("current") or {}).get("passes") or [])


def sigma_events(before: dict, after: dict) -> list[str]:
    """A line when the guidance has predicted the σ of a new set of accepted passes."""
    passes = _sigma_passes(after)
    if not passes or passes == _sigma_passes(before):
        return []
    line = f"  predicted {_sigma_text(after)} with passes {', '.join(str(p) for p in passes)}"
    rose = (after.get("sigma") or {}).get("current", {}).get("rose") or []
    if rose:  # see acquire.guidance.state.sigma_rises
        line += f" ({', '.join(rose)} σ rose: the pass's POS bias outweighs its geometry)"
    return [line]


def sigma_covers_accepted(g: dict) -> bool:
    """Whether the σ prediction includes every accepted pass."""
    accepted = sorted(p["id"] for p in g.get("passes") or [] if p.get("status") == "accepted")
    return sorted(_sigma_passes(g)) == accepted


# =============================================================================================
# The comparison (pure)
# =============================================================================================


@dataclass(frozen=True)
class AngleComparison:
    angle: str
    convention: str  # "canonical" | "thesis"
    truth_deg: float
    recovered_deg: float
    sigma_formal_deg: float
    sigma_realistic_deg: float

    @property
    def error_deg(self) -> float:
        return self.recovered_deg - self.truth_deg

    @property
    def error_sigmas(self) -> float:
        """The error in units of the realistic σ."""
        return self.error_deg / self.sigma_realistic_deg if self.sigma_realistic_deg > 0 else math.inf


def comparison_rows(result: dict, truth: dict) -> list[AngleComparison]:
    """Recovered (``result.json``) against the truth (``scenario_truth.json``), canonical and
    in the thesis convention (roll, −pitch, yaw; docs/architecture.md §3)."""
    b, sf, sr = result["boresight_deg"], result["sigma_deg"], result["sigma_realistic_deg"]
    t = truth["boresight_deg"]
    rows = [
        AngleComparison(a, "canonical", float(t[a]), float(b[a]), float(sf[a]), float(sr[a])) for a in ANGLES
    ]
    sign = {"roll": 1.0, "pitch": -1.0, "yaw": 1.0}
    rows += [
        AngleComparison(
            r.angle,
            "thesis",
            sign[r.angle] * r.truth_deg,
            sign[r.angle] * r.recovered_deg,
            r.sigma_formal_deg,
            r.sigma_realistic_deg,
        )
        for r in rows
    ]
    return rows


def comparison_table(rows: list[AngleComparison]):
    from rich import box
    from rich.table import Table

    t = Table(
        title="boresight: recovered vs truth (degrees)",
        box=box.SIMPLE_HEAD,
        title_justify="left",
        pad_edge=False,
        show_edge=False,
    )
    for col in ("", "truth", "recovered", "error", "σ formal", "σ realistic", "error/σ"):
        t.add_column(col, justify="right" if col else "left", no_wrap=True)
    for i, r in enumerate(rows):
        if i and r.convention != rows[i - 1].convention:
            t.add_section()
        name = r.angle if r.convention == "canonical" else f"thesis {r.angle}"
        bad = abs(r.error_sigmas) > 3
        t.add_row(
            name,
            f"{r.truth_deg:+.4f}",
            f"{r.recovered_deg:+.4f}",
            f"{r.error_deg:+.4f}",
            f"{r.sigma_formal_deg:.4f}",
            f"{r.sigma_realistic_deg:.4f}",
            f"[{'bold red' if bad else 'green'}]{r.error_sigmas:+.2f}[/]",
        )
    t.caption = (
        "canonical: docs/architecture.md §3 (R_bs = Rz(yaw)·Ry(pitch)·Rx(roll), pitch + bow up); thesis: "
        "the iXblue/NWU convention of Shahraji 2022 (pitch negated); error/σ in realistic σ"
    )
    t.caption_justify = "left"
    return t


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
    file, or nothing but what a demo writes); a directory holding anything else is refused."""
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


def run_demo(settings: DemoSettings, console, interrupted: Callable[[], None] = lambda: None) -> DemoResult:
    """Run the demo (module docstring). ``interrupted()`` raises :class:`Interrupted` when the
    user asked to stop; every child is stopped when this returns or raises."""
    t_start = time.monotonic()
    out = settings.out
    prepare_out(out)
    out = out.resolve()
    logs, run_dir = out / "logs", out / "run"
    config = out / "vessel.yaml"
    children: list[Child] = []
    watcher: StatusListener | None = None
    say = lambda text: console.print(text, highlight=False)  # noqa: E731
    try:
        # 1. the simulated devices (they write the vessel config once they run)
        say(
            f"[bold]mls demo[/bold]: the {settings.scenario} scenario on simulated devices, "
            f"acquired, exported and calibrated in {out}"
        )
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
        children.append(devices)
        deadline = time.monotonic() + settings.start_timeout_s
        _wait_for_config(config, devices, deadline, interrupted)
        window = json.loads((run_dir / "truth_clock.json").read_text())["window"]
        say(
            f"devices: INS on {run_dir / 'ins'}, profiler and PPS over UDP; "
            f"{window['duration_s']:.0f} s of survey in real time (log {devices.log})"
        )
        # 2. the daemon
        daemon = Child(
            "acquisition daemon (mls acquire)",
            [*MLS, "acquire", "--config", str(config)],
            logs / "acquire.log",
        )
        children.append(daemon)
        from acquire.daemon.config import load_vessel_config

        cfg = load_vessel_config(config)
        watcher = StatusListener(cfg.status.socket)
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
        say(
            f"daemon: acquiring into {cfg.session_dir}, status on {cfg.status.socket} "
            f"(log {daemon.log}); watch it with: mls checklist --socket {cfg.status.socket}"
        )
        g = _follow(devices, daemon, watcher, console, window["duration_s"] + 60.0, t_start, interrupted)
        # 3. stop the daemon (orderly: the session is closed), then the devices
        session_name = (watcher.latest("status") or {}).get("session")
        code = daemon.stop(signal.SIGTERM, 30.0)
        if code != 0:
            raise DemoError(
                daemon.step, f"did not stop cleanly (exit code {code}): {daemon.tail()}", daemon.log
            )
        devices.stop(signal.SIGTERM, 10.0)
        watcher.stop()
        watcher = None
        session = cfg.session_dir / session_name if session_name else None
        if session is None or not session.is_dir():
            found = sorted(p for p in cfg.session_dir.iterdir() if p.is_dir())
            if len(found) != 1:
                raise DemoError(
                    "finding the session", f"{len(found)} sessions in {cfg.session_dir}", daemon.log
                )
            session = found[0]
        n_passes = len(g.get("passes") or [])
        accepted = int(g.get("accepted", 0))
        say(f"session {session} closed: {accepted}/{n_passes} passes accepted by the guidance")
        # 4. export, 5. calibration
        bundle, calib = out / "bundle", out / "calib"
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
            [*MLS, "calib", "run", str(bundle), "--out", str(calib), "--no-history"],
            logs / "calib.log",
            settings.step_timeout_s,
            interrupted,
            say,
        )
        try:
            result = json.loads((calib / "result.json").read_text())
            truth = json.loads((run_dir / "scenario_truth.json").read_text())
            rows = comparison_rows(result, truth)
        except (OSError, ValueError, KeyError, TypeError) as e:
            raise DemoError("reading the results", f"{type(e).__name__}: {e}", logs / "calib.log") from None
        return DemoResult(
            out, session, bundle, calib, result, truth, rows, accepted, n_passes, sorted(calib.glob("*.png"))
        )
    finally:
        if watcher is not None:
            watcher.stop()
        for c in reversed(children):  # the daemon before the devices
            c.stop(signal.SIGTERM, 10.0)


def _step(
    children: list[Child], step: str, args: list[str], log: Path, timeout_s: float, interrupted, say
) -> None:
    say(f"{step.split(' (')[0]}: mls {' '.join(args[len(MLS) :])}")
    c = Child(step, args, log)
    children.append(c)
    code = c.wait(timeout_s, interrupted)
    if code != 0:
        raise DemoError(step, f"exit code {code}: {c.tail()}", log)


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
            clock = (watcher.latest("clock") or {}).get("state")
            if live is not None:
                line = Text(
                    progress_line(last, clock, time.monotonic() - t_start), no_wrap=True, overflow="ellipsis"
                )
                live.update(line, refresh=True)
            passes = last.get("passes") or []
            if passes and all(p.get("status") == "accepted" for p in passes):
                done_at = done_at or time.monotonic()
                if sigma_covers_accepted(last) or time.monotonic() - done_at > 15.0:
                    return last  # with the σ prediction of all the passes
            code = daemon.poll()
            if code is not None:
                raise DemoError(
                    daemon.step, f"ended during the survey (exit code {code}): {daemon.tail()}", daemon.log
                )
            code = devices.poll()
            if code is not None and ended_at is None:
                if code != 0:
                    raise DemoError(
                        devices.step, f"ended with exit code {code}: {devices.tail()}", devices.log
                    )
                ended_at = time.monotonic()  # the scenario is over: the last verdict follows
            if ended_at is not None and time.monotonic() - ended_at > 3.0:
                return last
            if time.monotonic() > deadline:
                raise DemoError(daemon.step, f"the survey did not end within {timeout_s:.0f} s", daemon.log)
            time.sleep(0.25)
    finally:
        if live is not None:
            live.stop()
