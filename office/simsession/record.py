"""``mls sim session``: a recorded session written offline, faster than real time, in the format
the daemon writes (docs/architecture.md §4.5), from a simulator scenario.

The survey (:func:`survey_scenario`): lines back and forth along the quay (the scenario's first
line's length and speed, relative headings 0° and 180° at its standoff, its gap or turns between
lines) until the session's length, the profiler recording its full circle at ``rate_scale`` of
the full Z+F point rate (the simulator's rule: profile rate and points per 360° each × √F), and,
unless left out, the quay's surroundings (:func:`quay_surroundings`) so that the scanner sees
more than the calibration targets. :func:`calib.sim.simulate.simulate` sails it (true and
observed trajectories, truth); the returns are cast chunk by chunk (:mod:`office.simsession.lidar`).

What goes into the session, on the truth clock (:class:`sim_devices.clock.TruthClock`: host
``CLOCK_MONOTONIC`` an hour after boot at the first line's start; every record's ``log_time`` is
the GPS time of its host stamp, clock LOCKED):

- ``/ins/raw``: the INS emulator's own writes (:class:`sim_devices.ins.InsEmulator`: NMEA or
  STDBIN, its latency and jitter), decoded by the daemon's own device
  (:class:`acquire.daemon.devices.InsDevice`) into its ``/ins/nav`` records — its decoder dates
  time-of-day tags from the simulated host's UTC, not this machine's;
- ``/lidar/raw``: the profiler emulator's datagrams, device time = the packet's ``t0``;
- ``/pps``: the PPS emulator's pulses labelled by the daemon's :class:`~acquire.timing.timekeeper.
  TimeKeeper` with the INS's time messages (its clock model primed with 8 pulses before the
  session); ``/clock`` and ``/latency`` every ``status.period_s`` from that clock model and the
  daemon's :class:`~acquire.timing.latency.LatencyMonitor` (``/status`` is not written: it
  describes the daemon process);
- ``/can/marks`` and ``/events``: the CAN emulator's pass marks of every line wholly inside the
  session, as the daemon's CAN device logs them; ``session_start``, ``simulated_session`` (what
  was simulated), alarms, ``session_end``.

The records go through the daemon's :class:`~acquire.log.sessionlog.SessionWriter` whose writer
loop (:meth:`SessionWriter._run`'s body: ``_write_all`` and ``_maintain`` of
:class:`acquire.log.segments.SegmentLog`) runs on the caller's thread, on the simulated host
clock (:class:`OfflineSessionWriter`): chunk flushes, fsyncs, disk checks and segment rotation by
size or by ``rotate_s`` of session time are the daemon's own. The directory also gets
``vessel.yaml`` (the vessel config of these devices), ``site.yaml`` (the survey's lines),
``session.json`` (with a ``simulation`` section) and ``truth.json`` (the simulation's truth).
"""

from __future__ import annotations

import json
import math
import os
import re
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

from acquire.errors import AcquireError
from office.simsession.lidar import LidarStream
from office.simsession.recorder import Recorder

if TYPE_CHECKING:
    from calib.io.site import Site
    from calib.sim.result import SimResult
    from calib.sim.scenario import Scenario
    from sim_devices.clock import TruthClock
    from sim_devices.feed import PassMark

NS_PER_S = 1_000_000_000
HOST_ANCHOR_NS = 3600 * NS_PER_S  # the vessel PC's CLOCK_MONOTONIC at the first line's start
SIM_POINT_RATE_SCALE = 1e-4  # simulate() only sails the survey: its own scan is kept tiny
SCANNER_ABOVE_WATER_M = 2.5
WAREHOUSE_SETBACK_M = 25.0
WAREHOUSE_HEIGHT_M = 12.0
SURROUNDINGS_REACH_M = 125.0  # beyond the lines' ends (the scanner reaches 119 m)
PROFILER_PORT, PPS_PORT = 55010, 55011  # in vessel.yaml only: nothing listens offline
SESSION_FILE_RE = re.compile(
    r"^(seg-\d{6}\.mcap(\.torn)?|session\.json(\.tmp)?|vessel\.yaml|site\.yaml|truth\.json"
    r"|session\.lock|\.reserve)$"
)


class SimSessionError(AcquireError, ValueError):
    """The session cannot be written as asked (the message says why)."""


@dataclass(frozen=True)
class SessionSpec:
    scenario: str = "montreal"
    out: Path = Path("sessions")
    minutes: float = 1.0
    rate_scale: float = 1.0
    seed: int = 0
    force: bool = False
    overrides: tuple[str, ...] = ()
    ins_protocol: str = "nmea"
    ins_rate_hz: float = 100.0
    surroundings: bool = True
    rotate_s: float | None = None  # segment rotation (vessel config session.rotate_s; None: the daemon's)


@dataclass(frozen=True)
class SessionResult:
    path: Path
    duration_s: float
    passes: dict[int, tuple[int, int]]  # pass id → (start, end) GPS ns of its marks
    returns_per_pass: dict[int, int]  # returns whose wire time lies in the pass (ends included)
    profiles: int
    packets: int
    points: int  # slots sent, returns and no-returns
    returns: int
    epochs: int  # INS epochs written to /ins/nav
    segments: int
    bytes_written: int
    wall_s: float
    profile_rate_hz: float
    points_per_360: int
    truth: dict = field(repr=False, default_factory=dict)


# -- the survey ---------------------------------------------------------------------------------


def quay_surroundings(sc, line_length_m: float) -> tuple:
    """A quay for the survey to see beyond the calibration scene (site frame, flat): its wall face
    5 cm behind the scene's wall plane from the water (``SCANNER_ABOVE_WATER_M`` below the
    scanner) to the deck (the top of the scenario's highest surface or pile), a warehouse facade set
    back on the deck, and the water surface from the wall to three standoffs out (a stand-in for
    what a survey sees below the horizon near the vessel; a NIR scanner gets few returns from open
    water), all running ``SURROUNDINGS_REACH_M`` beyond the lines' ends."""
    from calib.sim.scenario import Surface

    water_up = -SCANNER_ABOVE_WATER_M
    deck_up = max(
        [s.up_m + 0.5 * s.height_m * math.sin(s.inclination_rad) for s in sc.surfaces]
        + [p.top_up_m for p in sc.piles]
    )
    width = line_length_m + 2 * SURROUNDINGS_REACH_M
    far_out = 3.0 * sc.standoff_m
    return (
        Surface(
            "survey_quay_wall", "wall", 0.0, -0.05, 0.5 * (deck_up + water_up), width, deck_up - water_up,
            reflectivity=0.25,
        ),
        Surface(
            "survey_warehouse", "wall", 0.0, -WAREHOUSE_SETBACK_M, deck_up + 0.5 * WAREHOUSE_HEIGHT_M,
            width, WAREHOUSE_HEIGHT_M, reflectivity=0.35,
        ),
        Surface(
            "survey_water", "other", 0.0, 0.5 * far_out, water_up, width, far_out, inclination_rad=0.0,
            reflectivity=0.05,
        ),
    )  # fmt: skip


def survey_scenario(sc, duration_s: float, rate_scale: float, surroundings: bool = True):
    """The scenario ``sc`` as a survey of at least ``duration_s`` (module docstring)."""
    from calib.io.site import PassSpec

    first = sc.passes[0]
    line_s = first.length_m / first.speed_mps
    cycle_s = line_s + (0.0 if sc.motion.turns else sc.motion.pass_gap_s)  # a lower bound with turns
    n = math.ceil(duration_s / cycle_s) + 1
    passes = tuple(
        PassSpec(i + 1, 0.0 if i % 2 == 0 else math.pi, first.length_m, first.speed_mps) for i in range(n)
    )
    scanner = replace(sc.scanner, angular_windows_rad=(), point_rate_scale=float(rate_scale))
    extra = quay_surroundings(sc, first.length_m) if surroundings else ()
    return replace(sc, passes=passes, scanner=scanner, surfaces=sc.surfaces + extra)


# -- the output directory -----------------------------------------------------------------------


def _clear_session(path: Path) -> None:
    """Remove an earlier session at ``path`` (``--force``): only a session directory holding
    nothing but a session's files, and that no writer holds."""
    import fcntl

    from acquire.log.session import LOCK_NAME, SESSION_RE

    if not path.is_dir() or not SESSION_RE.match(path.name):
        raise SimSessionError(f"{path}: exists and is not a session directory; not replaced")
    entries = list(path.iterdir())
    other = [e.name for e in entries if not (e.is_file() and SESSION_FILE_RE.match(e.name))]
    if other:
        raise SimSessionError(
            f"{path}: holds files a session does not ({', '.join(sorted(other)[:5])}); not replaced"
        )
    lock = path / LOCK_NAME
    if lock.exists():
        fd = os.open(lock, os.O_RDWR | os.O_CLOEXEC)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise SimSessionError(f"{path}: a writer holds the session ({lock}); not replaced") from None
        finally:
            os.close(fd)
    for e in entries:
        e.unlink()
    path.rmdir()


def _check_out(out: Path, name: str, force: bool) -> None:
    if out.exists() and not out.is_dir():
        raise SimSessionError(
            f"{out}: --out names a directory (sessions are created inside), but this is a file"
        )
    target = out / name
    if target.exists() or target.is_symlink():
        if not force:
            raise SimSessionError(f"{target}: the session exists; add --force to replace it")
        _clear_session(target)


# -- the session --------------------------------------------------------------------------------


def _vessel_config(tmp: Path, out: Path, sim, site, spec: SessionSpec, lidar: LidarStream):
    """The vessel config of these devices (as ``mls sim devices --write-config`` writes it, the
    session directory being ``out``), written with its site file as ``tmp/vessel.yaml`` and
    ``tmp/site.yaml`` and loaded."""
    import yaml

    from acquire.daemon.config import load_vessel_config
    from sim_devices.canbus import DEFAULT_GROUP
    from sim_devices.ins import InsSettings
    from sim_devices.vesselconfig import vessel_config

    locations: dict[str, dict] = {
        "ins": {"link": str(out / "ins"), "protocol": spec.ins_protocol},
        "profiler": {"address": ["127.0.0.1", PROFILER_PORT]},
        "pps": {"address": ["127.0.0.1", PPS_PORT]},
        "can": {"interface": "udp_multicast", "channel": DEFAULT_GROUP},
    }
    cfg = vessel_config(
        vessel=sim.scenario.vessel,
        run_dir=out,
        locations=locations,
        ins=InsSettings(protocol=spec.ins_protocol, rate_hz=spec.ins_rate_hz),
        profiler_rate_hz=lidar.rate_hz,
        profiler_latency_s=lidar.latency_ns / NS_PER_S,
        profiler_points_per_360=lidar.K,
        site=site,
        site_file="site.yaml",
    )
    cfg["session"] = {"directory": str(out)}
    if spec.rotate_s is not None:
        cfg["session"]["rotate_s"] = float(spec.rotate_s)
    site.dump(tmp / "site.yaml")
    head = (
        f"# marine-mls vessel config of a session written offline by `mls sim session` (scenario "
        f"{sim.scenario.name}, seed {spec.seed}):\n# its devices are the emulators'; nothing was opened.\n"
    )
    path = tmp / "vessel.yaml"
    path.write_text(head + yaml.safe_dump(cfg, sort_keys=False, default_flow_style=None), encoding="utf-8")
    return load_vessel_config(path)


@dataclass
class SessionPlan:
    """A survey sailed, ready to be recorded (:func:`plan_session`)."""

    spec: SessionSpec
    survey: Scenario
    sim: SimResult  # (its own scan tiny: the stream casts the returns)
    t0_ns: int
    t_end_ns: int
    windows: dict[int, tuple[int, int]]  # pass id → GPS ns of its marks
    marks: tuple[PassMark, ...]  # of those passes
    site: Site  # of those passes
    clock: TruthClock
    lidar: LidarStream
    t_wall: float = field(default_factory=time.perf_counter)

    @property
    def duration_s(self) -> float:
        return (self.t_end_ns - self.t0_ns) / NS_PER_S


def write_session(
    spec: SessionSpec,
    sim_progress: Callable[[int, int], None] | None = None,
    progress: Callable[[float, float, int], None] | None = None,
) -> SessionResult:
    """Simulate the survey and write its session under ``spec.out`` (module docstring).
    ``sim_progress(done, total)``: passes sailed; ``progress(done_s, total_s, returns)``: after
    each chunk written."""
    return record_session(plan_session(spec, sim_progress), progress)


def plan_session(spec: SessionSpec, sim_progress: Callable[[int, int], None] | None = None) -> SessionPlan:
    """Check the output, sail the survey, cut the session window (the lines wholly inside it
    are its passes) and set up the profiler stream."""
    from acquire.log.session import session_name
    from calib.core.frames import gps_ns_to_utc
    from calib.sim.simulate import simulate
    from sim_devices.clock import TruthClock
    from sim_devices.feed import seconds_to_ns

    t_wall = time.perf_counter()
    base = _calibration_scenario(spec)
    duration_ns = round(spec.minutes * 60 * NS_PER_S)
    t0 = int(seconds_to_ns(base.start_gps_s))  # the first line starts at the scenario's start
    _check_out(Path(spec.out), session_name(base.vessel, gps_ns_to_utc(t0)), spec.force)
    survey = survey_scenario(base, duration_ns / NS_PER_S, spec.rate_scale, spec.surroundings)
    tiny = replace(survey, scanner=replace(survey.scanner, point_rate_scale=SIM_POINT_RATE_SCALE))
    sim = simulate(tiny, spec.seed, progress=sim_progress)
    t_end = t0 + duration_ns
    if int(seconds_to_ns(sim.trajectory_true.t_gps_s[-1])) < t_end:
        raise SimSessionError(f"the survey's trajectory ends before {spec.minutes:g} min (a bug)")
    marks, windows = _session_passes(spec, survey, sim, t0, t_end)
    clock = TruthClock(HOST_ANCHOR_NS, t0)
    lidar = LidarStream(
        survey,
        sim.scene,
        replace(sim.trajectory_true, max_gap_s=math.inf),
        sim.mount_true,
        t0,
        t_end,
        clock,
        spec.seed,
        [(pid, a, b) for pid, (a, b) in windows.items()],
    )
    return SessionPlan(
        spec,
        survey,
        sim,
        t0,
        t_end,
        dict(sorted(windows.items())),
        tuple(m for m in marks if m.pass_id in windows),
        replace(sim.site, passes=tuple(p for p in sim.site.passes if p.id in windows)),
        clock,
        lidar,
        t_wall,
    )


def _calibration_scenario(spec: SessionSpec) -> Scenario:
    """The spec's scenario with its overrides, the spec's numbers checked: a calibration scene
    (a production survey is refused)."""
    from calib.sim.scenariofile import load_scenario

    if not spec.minutes > 0 or not 0 < spec.rate_scale <= 1:
        raise SimSessionError(
            f"--minutes {spec.minutes:g}, --rate-scale {spec.rate_scale:g}: expected minutes > 0 "
            f"and 0 < scale ≤ 1"
        )
    if spec.ins_protocol not in ("nmea", "stdbin"):
        raise SimSessionError(f"INS protocol {spec.ins_protocol!r}: expected nmea or stdbin")
    base = load_scenario(spec.scenario, list(spec.overrides))
    if base.production is not None:
        raise SimSessionError(
            f"scenario {base.name!r} is a production survey (its 'production' section): mls sim session "
            f"sails the calibration scene's lines; play a production survey with mls sim devices and the "
            f"daemon, or write it as a bundle with mls sim dataset"
        )
    return base


def _session_passes(
    spec: SessionSpec, survey: Scenario, sim: SimResult, t0: int, t_end: int
) -> tuple[tuple[PassMark, ...], dict[int, tuple[int, int]]]:
    """The pass marks of the session window, and the passes wholly inside it (pass id → GPS ns
    of its start and end marks); a window without one is refused."""
    from sim_devices.feed import pass_marks

    marks = pass_marks(sim, t0, t_end)
    starts = {m.pass_id: m.gps_ns for m in marks if m.kind == "pass_start"}
    windows = {
        m.pass_id: (starts[m.pass_id], m.gps_ns)
        for m in marks
        if m.kind == "pass_end" and m.pass_id in starts
    }
    if not windows:
        first = survey.passes[0]
        raise SimSessionError(
            f"a session of {spec.minutes:g} min holds no complete line (lines of "
            f"{first.length_m / first.speed_mps:g} s from its start): make it longer or the lines "
            f"shorter (--set site.pass_length_m=...)"
        )
    return marks, windows


def record_session(
    plan: SessionPlan, progress: Callable[[float, float, int], None] | None = None
) -> SessionResult:
    """Write the planned session (the vessel config, the daemon's pieces, every record, the
    truth); on an exception (Ctrl-C) the session is closed with what it holds so far."""
    spec, sim, lidar = plan.spec, plan.sim, plan.lidar
    out = Path(spec.out)
    out.mkdir(parents=True, exist_ok=True)
    run = None
    try:
        with tempfile.TemporaryDirectory(prefix="mls-sim-session-") as tmp:
            cfg = _vessel_config(Path(tmp), out.resolve(), sim, plan.site, spec, lidar)
            run = Recorder(cfg, plan.clock, spec, sim, lidar, plan.marks, plan.t0_ns, plan.t_end_ns)
            session_dir = run.open(_simulation(plan))
        run.record(progress)
    finally:
        if run is not None:  # the daemon's shutdown, also after an error or Ctrl-C
            run.close("end of simulation" if run.done else "interrupted")
    truth = _truth(plan)
    (session_dir / "truth.json").write_text(json.dumps(truth, indent=1) + "\n", encoding="utf-8")
    assert run is not None  # the recorder ran (or the exception went on)
    assert run.writer is not None  # its session was opened
    st = run.writer.stats()
    c = lidar.counts
    result = SessionResult(
        session_dir,
        plan.duration_s,
        plan.windows,
        dict(sorted(c.per_pass.items())),
        c.profiles,
        c.packets,
        c.points,
        c.returns,
        run.ins.records,
        st.segments,
        st.bytes_written,
        time.perf_counter() - plan.t_wall,
        lidar.rate_hz,
        lidar.K,
        truth,
    )
    written = {
        k: getattr(result, k)
        for k in ("profiles", "packets", "points", "returns", "epochs", "segments", "bytes_written")
    }
    written["returns_per_pass"] = {str(k): v for k, v in result.returns_per_pass.items()}
    run.update_summary({"written": {**written, "wall_s": round(result.wall_s, 3)}})
    return result


def _simulation(plan: SessionPlan) -> dict:
    """What was simulated (``session.json``'s ``simulation`` and the ``simulated_session`` event)."""
    from sim_devices.vesselconfig import FULL_RATE_PTS_S

    spec, lidar = plan.spec, plan.lidar

    point_rate = lidar.rate_hz * lidar.K
    return {
        "tool": "mls sim session (written offline, faster than real time)",
        "scenario": spec.scenario,
        "seed": spec.seed,
        "overrides": list(spec.overrides),
        "minutes": spec.minutes,
        "window_gps_ns": [plan.t0_ns, plan.t_end_ns],
        "rate_scale": spec.rate_scale,
        "profiler": {
            "scaling": "profile rate and points per 360° each × √rate_scale "
            "(the simulator's scanner.point_rate_scale)",
            "profile_rate_hz": lidar.rate_hz,
            "points_per_360": lidar.K,
            "points_per_profile": lidar.points_per_profile,
            "point_rate_hz": point_rate,
            "full_rate_fraction": point_rate / FULL_RATE_PTS_S,
        },
        "ins": {"protocol": spec.ins_protocol, "rate_hz": spec.ins_rate_hz},
        "lines": f"{len(plan.survey.passes)} planned back and forth along the quay; "
        "passes: those wholly inside the session",
        "surroundings": spec.surroundings,
        "truth_clock": plan.clock.to_dict(),
        "truth_file": "truth.json",
    }


def _truth(plan: SessionPlan) -> dict:
    """The simulation's truth for the lines in the session, with the returns counted per pass
    and surface (targets and validation planes by name, the rest as ``background``)."""
    from calib.sim.scene import BACKGROUND_KINDS

    sim, survey, spec, lidar, windows = plan.sim, plan.survey, plan.spec, plan.lidar, plan.windows
    truth = dict(sim.truth)
    names = [
        "background" if k in BACKGROUND_KINDS else name
        for name, k in zip(sim.scene.names, sim.scene.kinds, strict=True)
    ]
    keys = list(dict.fromkeys(names + ["background"]))
    passes = []
    for p in truth["passes"]:
        if p["id"] not in windows:
            continue
        row = dict.fromkeys(keys, 0)
        for name, n in zip(names, lidar.counts.per_pass_surface[p["id"]].tolist(), strict=True):
            row[name] += int(n)
        passes.append({**p, "points": row})
    truth["passes"] = passes
    truth["overrides"] = list(spec.overrides)
    truth["settings"] = {**truth["settings"], "scanner": survey.scanner.to_dict()}
    truth["survey"] = {
        "tool": "mls sim session",
        "lines": "back and forth along the quay (relative headings 0° and 180°)",
        "surroundings": [s.name for s in survey.surfaces if s.name.startswith("survey_")],
        "returns_by_surface": {  # rectangles, then cylinders (their geometry: truth["cylinders"])
            name: int(n) for name, n in zip(sim.scene.names, lidar.counts.per_surface.tolist(), strict=True)
        },
    }
    return truth
