"""Running the emulators: one process per device, one truth clock, one run directory.

    feed = make_feed(simulate("montreal", 0), start="pass:1", duration_s=60)
    with DeviceRun(feed, DevicesSpec(run_dir=Path("mls-sim")), load_faults("faults.yaml")) as run:
        where = run.start()          # dict: device → location (pty, UDP address, CAN channel)
        run.wait()                   # until the window ends (or Ctrl-C → run.stop())

:meth:`DeviceRun.start` forks one process per device (``fork``: they inherit the precomputed
feed), waits until each has opened its transport (the pty and the ``ins`` link exist, sockets
and the CAN bus are open), then anchors the :class:`~sim_devices.clock.TruthClock` ``lead_s``
ahead and hands it to all of them, so the first emissions are on time. Each process lowers its
timer slack (and, with ``realtime``, asks for SCHED_FIFO), ignores SIGINT (the parent decides),
stops on SIGTERM or the shared stop event, and dies with its parent (``PR_SET_PDEATHSIG``); :meth:`DeviceRun.stop` sets the event, joins,
escalates to SIGTERM/SIGKILL for a process that does not end, and removes a leftover link — no
orphan process or pty survives ``mls sim devices``.

The run directory (:data:`RUN_FILES`): ``truth_clock.json`` (the truth clock and the run
window), ``faults.json`` (every fault's window in scenario seconds, GPS ns and host ns),
``devices.json`` (where each device is, the process ids), ``scenario_truth.json`` (the
simulation's truth), ``ins`` (the link to the INS pty), ``host_clock`` (the simulated steps of
the host's realtime clock, with ``host_clock_step`` faults: a daemon given it,
``mls acquire --sim-host-clock FILE``, sees them) and, when each process ends,
``stats/<device>.json`` (what it sent, the faults it applied, its timing error and CPU).
"""

from __future__ import annotations

import gc
import json
import multiprocessing as mp
import os
import signal
import socket
import time
import traceback
from dataclasses import dataclass, field, replace
from multiprocessing.process import BaseProcess
from multiprocessing.synchronize import Event as StopEvent
from pathlib import Path

from sim_devices.canbus import CanEmulator, CanSettings
from sim_devices.clock import HOST_CLOCK_FILE, NS_PER_S, TruthClock, write_host_clock_steps
from sim_devices.errors import SimDevicesError
from sim_devices.faults import HOST, FaultError, FaultPlan
from sim_devices.feed import ScenarioFeed
from sim_devices.ins import InsEmulator, InsSettings
from sim_devices.pacing import Pacer, TimingLog, tune_process
from sim_devices.pps import PpsEmulator, PpsSettings
from sim_devices.profiler import ProfilerEmulator, ProfilerSettings
from sim_devices.vesselconfig import write_vessel_config

#: one emulator process's work (what :meth:`DeviceRun.emulators` gives)
Emulator = InsEmulator | ProfilerEmulator | PpsEmulator | CanEmulator

DEVICES = ("ins", "profiler", "pps", "can")
RUN_FILES = (
    "truth_clock.json",
    "faults.json",
    "devices.json",
    "scenario_truth.json",
    "ins",
    "stats",
    HOST_CLOCK_FILE,
)


@dataclass(frozen=True)
class DevicesSpec:
    run_dir: Path
    devices: tuple[str, ...] = DEVICES
    speed: float = 1.0  # scenario seconds per host second
    drift_ppm: float = 0.0  # truth clock: GPS runs this much faster than the host clock
    seed: int = 0  # jitter and probabilistic faults
    ins: InsSettings = field(default_factory=InsSettings)
    profiler: ProfilerSettings = field(default_factory=ProfilerSettings)
    pps: PpsSettings = field(default_factory=PpsSettings)
    can: CanSettings = field(default_factory=CanSettings)
    lead_s: float = 0.25  # clock anchor after every emulator is ready
    ready_timeout_s: float = 30.0
    realtime: bool = False  # SCHED_FIFO for the emulator processes where permitted

    def __post_init__(self) -> None:
        unknown = sorted(set(self.devices) - set(DEVICES))
        if unknown or not self.devices:
            raise ValueError(
                f"devices {list(self.devices)}: expected a non-empty subset of {', '.join(DEVICES)}"
            )
        if not 0 < self.speed <= 100:
            raise ValueError(f"speed {self.speed!r}: expected 0 < speed ≤ 100")
        if "ins" in self.devices and self.ins.protocol == "nmea" and self.speed * self.ins.zda_delay_s >= 0.9:
            raise ValueError(
                f"speed {self.speed:g} with a ZDA {self.ins.zda_delay_s:g} s after each PPS edge: the "
                f"ZDA would come after the next edge (speed × delay must stay below 0.9 s)"
            )


def free_udp_port(host: str = "127.0.0.1") -> int:
    """A port nobody has bound on ``host`` right now (the receiver binds it later)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind((host, 0))
        return s.getsockname()[1]


def _write_json(path: Path, obj) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(obj, indent=2, default=str) + "\n", encoding="utf-8")
    tmp.replace(path)


def _receive_clock(conn, stopping, parent_pid: int):
    """The truth clock from the parent, or None if it cancels, dies or we are told to stop."""
    while not stopping[0] and os.getppid() == parent_pid:
        try:
            if conn.poll(0.1):
                return conn.recv()
        except (EOFError, OSError):
            return None
    return None


def _child_main(emu, conn, parent_end, stop, stats_path: Path, parent_pid: int, realtime: bool) -> None:
    """An emulator process: prepare → ready → receive the clock → run → stats."""
    parent_end.close()  # our copy of the parent's end of the pipe
    stopping = [False]
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, lambda *_: stopping.__setitem__(0, True))
    scheduling = tune_process(signal.SIGTERM, realtime)
    if os.getppid() != parent_pid:  # the parent died before we could ask to die with it
        return
    gc.freeze()
    result: dict = {"device": emu.name, "pid": os.getpid(), "status": "not started", "scheduling": scheduling}
    try:
        try:
            info = emu.prepare()
        except Exception as e:  # reported to the parent, which stops the run
            result.update(status="failed to start", error=f"{type(e).__name__}: {e}")
            conn.send(("error", f"{emu.name}: {e}"))
            return
        conn.send(("ready", info))
        clock = _receive_clock(conn, stopping, parent_pid)
        if clock is None:
            result["status"] = "cancelled"
            return
        timing = TimingLog()
        pacer = Pacer(lambda: stopping[0] or stop.is_set(), spin_ns=emu.spin_ns)
        try:
            result["status"] = "finished" if emu.run(clock, pacer, timing) else "stopped"
        except Exception:
            result.update(status="crashed", error=traceback.format_exc())
        result["timing"] = timing.summary()
    finally:
        try:
            emu.close()
        except Exception as e:
            result.setdefault("error", f"close: {e}")
        try:
            result["stats"] = emu.stats()
        except Exception as e:
            result["stats_error"] = str(e)
        _write_json(stats_path, result)
        conn.close()


class EmulatorRun:
    """Emulator processes sharing one truth clock (the machinery of :class:`DeviceRun` and
    :class:`~sim_devices.replay.ReplayRun`): subclasses give :meth:`emulators`,
    :meth:`make_clock` and :meth:`write_run_files`."""

    def __init__(
        self, run_dir: str | Path, lead_s: float = 0.25, ready_timeout_s: float = 30.0, realtime: bool = False
    ) -> None:
        self.run_dir = Path(run_dir).resolve()
        self.realtime = realtime
        self.lead_s = lead_s
        self.ready_timeout_s = ready_timeout_s
        self.clock: TruthClock | None = None
        self.locations: dict[str, dict] = {}
        self._procs: dict[str, BaseProcess] = {}
        self._stop: StopEvent | None = None
        self._stopped = False

    def emulators(self) -> list:
        raise NotImplementedError

    def make_clock(self) -> TruthClock:
        raise NotImplementedError

    def write_run_files(self) -> None:
        raise NotImplementedError

    def _clean_run_dir(self) -> None:
        self.run_dir.mkdir(parents=True, exist_ok=True)
        (self.run_dir / "stats").mkdir(exist_ok=True)
        for name in RUN_FILES:
            p = self.run_dir / name
            if name == "stats":
                for q in p.glob("*.json"):
                    q.unlink()
            elif p.is_symlink() or p.is_file():
                p.unlink()

    def _devices_json(self, **extra) -> None:
        _write_json(
            self.run_dir / "devices.json",
            {
                "run_dir": str(self.run_dir),
                "pid": os.getpid(),
                "processes": {n: p.pid for n, p in self._procs.items()},
                **extra,
                "devices": self.locations,
            },
        )

    def start(self) -> dict[str, dict]:
        """Start every emulator; returns where each device is (also in ``devices.json``)."""
        if self._procs:
            raise SimDevicesError("this run was started already")
        self._clean_run_dir()
        ctx = mp.get_context("fork")
        self._stop = ctx.Event()
        conns = {}
        for emu in self.emulators():
            parent_end, child_end = ctx.Pipe()
            proc = ctx.Process(
                target=_child_main,
                name=f"mls-sim-{emu.name}",
                daemon=True,
                args=(
                    emu,
                    child_end,
                    parent_end,
                    self._stop,
                    self.run_dir / "stats" / f"{emu.name}.json",
                    os.getpid(),
                    self.realtime,
                ),
            )
            proc.start()
            child_end.close()
            self._procs[emu.name] = proc
            conns[emu.name] = parent_end
        try:
            deadline = time.monotonic() + self.ready_timeout_s
            for name, conn in conns.items():
                if not conn.poll(max(deadline - time.monotonic(), 0.0)):
                    raise SimDevicesError(f"{name} emulator: not ready after {self.ready_timeout_s:g} s")
                try:
                    what, info = conn.recv()
                except EOFError:
                    raise SimDevicesError(
                        f"{name} emulator: the process ended while starting "
                        f"(exit code {self._procs[name].exitcode})"
                    ) from None
                if what != "ready":
                    raise SimDevicesError(f"cannot start the {info}")
                self.locations[name] = info
            self.clock = self.make_clock()
            self.write_run_files()
            for conn in conns.values():
                conn.send(self.clock)
        except BaseException:
            for conn in conns.values():
                try:
                    conn.send(None)
                except OSError:
                    pass
            self.stop()
            raise
        finally:
            for conn in conns.values():
                conn.close()
        return self.locations

    def running(self) -> list[str]:
        return [n for n, p in self._procs.items() if p.is_alive()]

    def wait(self, timeout_s: float | None = None) -> bool:
        """Wait until every emulator has ended; False on timeout."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        for p in self._procs.values():
            p.join(None if deadline is None else max(deadline - time.monotonic(), 0.0))
        return not self.running()

    def stop(self, timeout_s: float = 3.0) -> dict[str, dict]:
        """Stop every emulator (no-op for those already ended); returns their stats."""
        if not self._stopped:
            self._stopped = True
            if self._stop is not None:
                self._stop.set()
            deadline = time.monotonic() + timeout_s
            for p in self._procs.values():
                p.join(max(deadline - time.monotonic(), 0.0))
            for sig_fn in ("terminate", "kill"):
                for p in self._procs.values():
                    if p.is_alive():
                        getattr(p, sig_fn)()
                        p.join(1.0)
            link = self.run_dir / "ins"
            if link.is_symlink():
                link.unlink()
        return self.stats()

    def stats(self) -> dict[str, dict]:
        out = {}
        for name in self._procs:
            path = self.run_dir / "stats" / f"{name}.json"
            try:
                out[name] = json.loads(path.read_text(encoding="utf-8"))
            except (OSError, ValueError):
                p = self._procs[name]
                out[name] = {"device": name, "status": f"no stats (exit code {p.exitcode})"}
        return out

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.stop()


class DeviceRun(EmulatorRun):
    """The emulators of one scenario window (see the module docstring)."""

    def __init__(self, feed: ScenarioFeed, spec: DevicesSpec, faults: FaultPlan | None = None) -> None:
        super().__init__(spec.run_dir, spec.lead_s, spec.ready_timeout_s, spec.realtime)
        self.feed = feed
        self.faults = faults or FaultPlan()
        self.faults.check_window(feed.duration_s)
        for f in self.faults.faults:
            if f.device not in spec.devices and f.device != HOST:
                raise FaultError(
                    f"{f.where}: the {f.kind} fault is for the {f.device} emulator, which "
                    f"is not running (devices: {', '.join(spec.devices)})"
                )
            if f.kind == "zda_late" and spec.ins.protocol != "nmea":
                raise FaultError(f"{f.where}: zda_late needs an NMEA INS (a STDBIN INS sends no ZDA)")
        spec = replace(spec, run_dir=self.run_dir)
        if "profiler" in spec.devices and spec.profiler.port == 0:
            spec = replace(spec, profiler=replace(spec.profiler, port=free_udp_port(spec.profiler.host)))
        if "pps" in spec.devices and spec.pps.port == 0:
            spec = replace(spec, pps=replace(spec.pps, port=free_udp_port(spec.pps.host)))
        self.spec = spec

    def emulators(self) -> list:
        s, f, fp = self.spec, self.feed, self.faults
        out: list[Emulator] = []
        if "ins" in s.devices:
            out.append(
                InsEmulator(
                    f.ins,
                    s.ins,
                    fp.for_device("ins"),
                    f.start_gps_ns,
                    f.end_gps_ns,
                    self.run_dir / "ins",
                    seed=s.seed + fp.seed,
                )
            )
        if "profiler" in s.devices:
            out.append(
                ProfilerEmulator(
                    f.grid, s.profiler, fp.for_device("profiler"), f.start_gps_ns, seed=s.seed + fp.seed + 2
                )
            )
        if "pps" in s.devices:
            out.append(
                PpsEmulator(s.pps, fp.for_device("pps"), f.start_gps_ns, f.end_gps_ns, seed=s.seed + fp.seed)
            )
        if "can" in s.devices:
            out.append(CanEmulator(f.marks, s.can))
        return out

    def make_clock(self) -> TruthClock:
        return TruthClock.starting_in(
            self.lead_s, self.feed.start_gps_ns, self.spec.drift_ppm, self.spec.speed
        )

    def _truth_clock(self) -> TruthClock:
        """The truth clock, anchored by :meth:`start` before the run files are written."""
        assert self.clock is not None, "the truth clock is made when the emulators are ready"
        return self.clock

    def window(self) -> dict:
        f, c = self.feed, self._truth_clock()
        return {
            "scenario": f.name,
            "seed": int(f.sim.seed),
            "time_shift_ns": f.time_shift_ns,
            "time_shift_note": "device GPS time = scenario GPS time (scenario_truth.json) + time_shift_ns",
            "start_gps_ns": f.start_gps_ns,
            "end_gps_ns": f.end_gps_ns,
            "duration_s": f.duration_s,
            "start_host_ns": c.host_ns(f.start_gps_ns),
            "end_host_ns": c.host_ns(f.end_gps_ns),
        }

    def write_run_files(self) -> None:
        f, c, window = self.feed, self._truth_clock(), self.window()
        c.write(self.run_dir / "truth_clock.json", window=window)
        _write_json(
            self.run_dir / "faults.json",
            {
                "source": self.faults.source,
                "seed": self.faults.seed,
                "faults": self.faults.schedule(f.start_gps_ns, c),
            },
        )
        _write_json(self.run_dir / "scenario_truth.json", f.sim.truth)
        steps = [
            (c.host_ns(f_.window_ns(f.start_gps_ns)[0]), round(f_.params["step_s"] * NS_PER_S))
            for f_ in self.faults.for_device(HOST)
            if f_.kind == "host_clock_step"
        ]
        if steps:
            write_host_clock_steps(self.run_dir / HOST_CLOCK_FILE, steps)
        self._devices_json(speed=self.spec.speed, window=window)

    def write_vessel_config(self, path: str | Path) -> Path:
        """The vessel config of this run (after :meth:`start`): see :mod:`sim_devices.vesselconfig`."""
        f, s = self.feed, self.spec
        return write_vessel_config(
            path,
            what=f"the emulators of scenario {f.name} (seed {f.sim.seed})",
            vessel=f.sim.scenario.vessel,
            run_dir=self.run_dir,
            locations=self.locations,
            speed=s.speed,
            ins=s.ins,
            profiler_rate_hz=f.grid.profile_rate_hz,
            profiler_latency_s=s.profiler.latency_s,
            profiler_points_per_360=f.grid.points_per_360,
            site=f.sim.site,
        )

    def elapsed_s(self) -> float:
        """Scenario seconds since the window's start (0 before it, the duration after it)."""
        if self.clock is None:
            return 0.0
        t = (self.clock.now_gps_ns() - self.feed.start_gps_ns) / NS_PER_S
        return min(max(t, 0.0), self.feed.duration_s)
