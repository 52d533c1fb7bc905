"""Soak: the acquisition daemon for a long run at a multiple of the profiler rate, under faults.

``mls acquire`` runs as its own process against ``mls sim devices`` (scenario montreal, the full
Z+F rate as in ``benchmarks/acquire.py``: ``--point-rate-scale 1``, the full 360°, INS 200 Hz
NMEA on a pty, PPS over UDP) at ``--speed`` times the real rate, for ``--minutes``; the
emulators are run again and again (one scenario, 330 scenario s, a run) so each restart is also
an INS unplug and a profiler pause of a few seconds. Random faults drawn from ``--seed``:

- broker restarts: a real mosquitto on a free loopback port (``tests/mosquitto.py``), stopped
  (SIGTERM) or crashed (SIGKILL) and started again on the same port 1–6 s later; just after it is
  back, a retained ``cmd/mark`` and ``cmd/rotate`` (the daemon must ignore and count them);
- command floods on MQTT (``commands_enabled: true``): 140 ``cmd/mark``, 50 ``cmd/rotate`` and
  10 malformed marks within 1–4 s (the daemon validates and rate-limits them);
- device unplugs in the emulators' fault timeline: the INS pty closed and opened again
  (``serial_unplug``), the profiler's UDP sender paused (``udp_loss``, probability 1), 1–5 s;
- disk pressure: the daemon's ``disk_warning_mb`` set from the free space at the start (the run's
  own writing never reaches it), and a ballast file (``posix_fallocate``, nothing written) in
  the session directory's file system that takes the free space below it for 3–8 s — never
  below 5 GiB free; the file is removed afterwards.

Measured, each with its goal:

- **records lost**: profiler datagrams the emulators sent minus the ``/lidar/raw`` messages the
  session log holds (the MCAP summaries of its segments), and INS epochs the daemon could read
  minus the ``/ins/nav`` messages — goal 0. The INS emulator counts what the unplugs took
  (``sim_devices.ins``): the epochs written while unplugged and those in flight at the unplug
  (written before it, still in the pty or the emulated UART's FIFO when it closed); every other
  epoch, those written after a replug included, is the daemon's to record: one the pty dropped
  because the daemon was not reading (``bytes_overrun``), or had not reopened the port yet, is
  the daemon's loss; the report lists when the pty overflowed, and whether just after a replug;
- **RSS growth** of the daemon (``/proc/PID/status`` VmRSS every 2 s) from the end of the
  warm-up (the first 5 minutes, or a third of a shorter run) to the end — goal ≤ 5 %;
- **open file descriptors** (``/proc/PID/fd``) and **threads** (``Threads``): first sample after
  the warm-up, last, max — goal stable (last ≤ first + 2); the host's load average alongside
  (other work on the machine delays the daemon: read the losses with it);
- the **alarms** raised and cleared by each fault (from the status socket's ``alarms``; an
  alarm belongs to the latest fault that began before it, up to 30 s after that fault's end,
  one about the alarm's device first: ``ins``/``profiler``/``pps``/``clock`` for the devices'
  faults, ``log`` for the disk, ``mqtt`` for the broker and the commands);
- the **commands** accepted / refused / rate-limited / retained / dropped (the daemon's metrics
  ``mqtt.commands``) and the ``cmd/result`` replies received.

A benchmark exits 0 whatever the figures. It stops the daemon (SIGTERM), the emulators and the
broker at the end and removes its temporary directory unless ``--keep`` (which keeps the
daemon's samples too, ``samples.json``).

Run: ``.venv/bin/python benchmarks/soak.py [--minutes 30] [--speed 3] [--seed 1] [--keep]``
"""

from __future__ import annotations

import argparse
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import textwrap
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from acquire.status.bus import StatusListener, read_snapshot  # noqa: E402
from benchmarks import _soak_faults as faults  # noqa: E402
from benchmarks._procs import Sampler, free_port, stop, udp_drops, wait_for  # noqa: E402
from benchmarks._soak_faults import Ballast, DiskLimits, Fault, ResultCounter  # noqa: E402
from tests.mosquitto import Mosquitto  # noqa: E402

MLS = [sys.executable, "-m", "cli.app"]
NS = 1_000_000_000
VESSEL = "soak"
BASE = f"mls/{VESSEL}"
SCENARIO_S = 329.0  # montreal is 330 scenario seconds long
SIM_START_S = 8.0  # host seconds for `mls sim devices` to be ready (simulation + --lead-s)
AFTER_FAULT_S = 30.0  # alarms this long after a fault's end are still its own
INS_RATE_HZ = 200
_DEVICES = {"ins", "profiler", "pps", "clock"}
#: the alarms' devices a fault of each kind is about (an alarm goes to such a fault first)
CONCERNS = {
    "ins_unplug": {"ins", "pps", "clock"},
    "profiler_pause": {"profiler"},
    "disk_pressure": {"log"},
    "broker_restart": {"mqtt"},
    "command_flood": {"mqtt", "log"},
    "start-up": _DEVICES,
    "emulators_restart": _DEVICES,
    "run_end": _DEVICES,
}
# bytes a host second the daemon may write at ×1 and the full rate: the datagrams and headers
# uncompressed, an upper bound (the segments' chunks are compressed: far less in fact)
LOG_BYTES_PER_S = 7.5e6


def vessel_yaml(tmp: Path, ports: dict, speed: float, warning_mb: int) -> str:
    return textwrap.dedent(f"""\
        vessel: {VESSEL}
        devices:
          - name: ins
            kind: ins
            protocol: nmea
            transport: {{type: serial, port: {tmp}/sim/ins, baud: 921600}}
            latency: {{band_ms: [0.0, 1000.0], rate_hz: {200 * speed}, gap_s: 2.0}}
          - name: profiler
            kind: profiler
            protocol: zfp1
            transport: {{type: udp, host: 127.0.0.1, port: {ports["profiler"]}}}
            latency: {{band_ms: [0.0, 1000.0], rate_hz: {200 * speed}, gap_s: 2.0}}
          - name: pps
            kind: pps
            source: {{type: udp, host: 127.0.0.1, port: {ports["pps"]}}}
            time_device: ins
            time_messages: [ZDA]
        session:
          directory: {tmp}/sessions
          queue_size: 200000
          disk_warning_mb: {warning_mb}
          disk_critical_mb: 0
        status: {{socket: {tmp}/status.sock}}
        mqtt: {{host: 127.0.0.1, port: {ports["broker"]}, commands_enabled: true, keepalive_s: 5}}
        """)


# -- watching the daemon ------------------------------------------------------------------------


class AlarmListener(StatusListener):
    """The status socket: every alarm raise/clear with its arrival time, the latest of the rest."""

    def __init__(self, path: Path):
        super().__init__(path)
        self.events: list[tuple[int, dict]] = []

    def handle(self, received_ns: int, topic: str, data) -> None:
        if topic == "alarms" and isinstance(data, dict):
            self.events.append((received_ns, data))
        super().handle(received_ns, topic, data)


# -- the emulators, run after run ---------------------------------------------------------------


@dataclass(eq=False)  # a thread must stay hashable
class Segments(threading.Thread):
    """Runs ``mls sim devices`` again and again until ``deadline_ns`` (monotonic), each run with
    its own fault timeline; keeps the emulators' stats and the faults as done."""

    tmp: Path
    ports: dict
    speed: float
    point_rate_scale: float
    rng: random.Random
    deadline_ns: int
    stats: list[dict] = field(default_factory=list)
    done: list[Fault] = field(default_factory=list)
    errors: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        threading.Thread.__init__(self, daemon=True, name="segments")
        self.halt = threading.Event()
        self.proc: subprocess.Popen | None = None

    def run(self) -> None:
        last_end_ns, what = time.monotonic_ns(), ("start-up", "no emulators yet")
        while not self.halt.is_set():
            left_s = (self.deadline_ns - time.monotonic_ns()) / NS - SIM_START_S
            if left_s < 10:
                break
            window = self.one(min(SCENARIO_S, left_s * self.speed), len(self.stats))
            if window is None:
                break
            self.done.append(Fault(*what, last_end_ns, window[0]))
            last_end_ns, what = window[1], ("emulators_restart", "INS pty and profiler away")
        self.done.append(Fault("run_end", "the emulators stopped", last_end_ns, last_end_ns))

    def one(self, scenario_s: float, n: int) -> tuple[int, int] | None:
        """One run of the emulators; returns its window (host monotonic ns), None if it failed."""
        run = self.tmp / "sim"
        (run / "truth_clock.json").unlink(missing_ok=True)
        plan = faults.segment_faults(self.rng, scenario_s, self.speed)
        ffile = self.tmp / f"faults-{n:03d}.yaml"
        ffile.write_text(faults.faults_yaml(self.rng.randrange(1 << 30), plan or [_no_fault()]))
        log = self.tmp / f"sim-{n:03d}.log"
        with open(log, "wb") as out:
            self.proc = subprocess.Popen(
                [*MLS, "sim", "devices", *self.sim_args(scenario_s, ffile, run, n)],
                cwd=self.tmp,
                stdout=out,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )
        try:
            wait_for(lambda: (run / "truth_clock.json").exists() or self.proc.poll() is not None, 120, "sim")
            if self.proc.poll() is not None:
                self.errors.append(f"run {n}: mls sim devices failed: {log.read_text()[-1500:]}")
                return None
            w = json.loads((run / "truth_clock.json").read_text())["window"]
            self.note_faults(plan, w["start_host_ns"])
            while self.proc.poll() is None and not self.halt.is_set():
                time.sleep(0.2)
        finally:
            stop(self.proc, grace_s=60)
        self.stats.append(
            {d: json.loads((run / "stats" / f"{d}.json").read_text()) for d in ("ins", "profiler")}
        )
        return w["start_host_ns"], w["end_host_ns"]

    def sim_args(self, scenario_s: float, ffile: Path, run: Path, n: int) -> list[str]:
        return [
            "--scenario", "montreal", "--point-rate-scale", f"{self.point_rate_scale:g}",
            "--set", "scanner.angular_windows_deg=[]", "--ins-rate", str(INS_RATE_HZ), "--lead-s", "2",
            "--speed", f"{self.speed:g}", "--duration", f"{scenario_s:.2f}", "--seed", str(n),
            "--faults", str(ffile), "--devices", "ins,profiler,pps", "--run-dir", str(run),
            "--profiler-port", str(self.ports["profiler"]), "--pps-port", str(self.ports["pps"]),
        ]  # fmt: skip

    def note_faults(self, plan: list[dict], start_host_ns: int) -> None:
        for f in plan:
            t0 = start_host_ns + round(f["at_s"] / self.speed * NS)
            t1 = t0 + round(f["duration_s"] / self.speed * NS)
            kind = "ins_unplug" if f["kind"] == "serial_unplug" else "profiler_pause"
            self.done.append(Fault(kind, f"{f['duration_s'] / self.speed:.1f} s", t0, t1))


def _no_fault() -> dict:
    """A fault that changes nothing (a timeline needs one): PPS duplicates for 1 ms at the start."""
    return {"at_s": 0.0, "kind": "udp_duplicate", "device": "pps", "duration_s": 0.001}


# -- the host's faults --------------------------------------------------------------------------


@dataclass
class HostFaults:
    broker: Mosquitto
    ballast: Ballast | None
    rng: random.Random
    done: list[Fault] = field(default_factory=list)
    sent: Counter = field(default_factory=Counter)

    def do(self, kind: str, params: dict) -> None:
        t0 = time.monotonic_ns()
        detail = getattr(self, kind)(**params)
        self.done.append(Fault(kind, detail, t0, time.monotonic_ns()))

    def broker_restart(self, down_s: float, crash: bool) -> str:
        self.broker.kill() if crash else self.broker.stop()
        time.sleep(down_s)
        self.broker.start()
        n = faults.retained(self.broker.host, self.broker.port, BASE, 100_000 + len(self.done) * 10)
        self.sent["retained"] += n
        return f"{'SIGKILL' if crash else 'SIGTERM'}, down {down_s:.1f} s, then {n} retained commands"

    def command_flood(self, seconds: float) -> str:
        r = faults.flood(self.broker.host, self.broker.port, BASE, self.rng, seconds, len(self.done) * 1000)
        self.sent["flood"] += r["sent"]
        self.sent["flood_marks"] += r["marks"]
        self.sent["flood_rotates"] += r["rotates"]
        return f"{r['sent']} commands in {seconds:.1f} s ({r['acked']} acknowledged by the broker)"

    def disk_pressure(self, hold_s: float) -> str:
        if self.ballast is None:
            return "skipped (no room for a ballast)"
        free0 = faults.free_bytes(self.ballast.path.parent)
        size = self.ballast.fill()
        free1 = faults.free_bytes(self.ballast.path.parent)
        time.sleep(hold_s)
        self.ballast.empty()
        return (
            f"ballast {size / faults.GIB:.1f} GiB for {hold_s:.1f} s: free "
            f"{free0 / faults.GIB:.1f} → {free1 / faults.GIB:.1f} GiB"
        )


def run_host_faults(host: HostFaults, plan: list, t0_ns: int, deadline_ns: int) -> None:
    for at_s, kind, params in plan:
        t = t0_ns + round(at_s * NS)
        time.sleep(max(t - time.monotonic_ns(), 0) / NS)
        if time.monotonic_ns() >= deadline_ns:
            return
        host.do(kind, params)
        print(
            f"  t={(host.done[-1].start_ns - t0_ns) / NS:7.1f} s  {kind}: {host.done[-1].detail}", flush=True
        )


# -- the session log ----------------------------------------------------------------------------


def segment_counts(path: Path) -> Counter:
    """Messages per topic of one MCAP segment: its summary statistics, else a scan."""
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        try:
            summary = make_reader(f).get_summary()
        except Exception:  # a segment without a usable summary: counted by a scan below
            summary = None
        if summary is not None and summary.statistics is not None:
            return Counter(
                {summary.channels[c].topic: n for c, n in summary.statistics.channel_message_counts.items()}
            )
    return scan_counts(path)


def scan_counts(path: Path) -> Counter:
    from mcap.records import Channel, Message
    from mcap.stream_reader import StreamReader

    topics, out = {}, Counter()
    with open(path, "rb") as f:
        try:
            for rec in StreamReader(f, skip_magic=False).records:
                if isinstance(rec, Channel):
                    topics[rec.id] = rec.topic
                elif isinstance(rec, Message):
                    out[topics.get(rec.channel_id, "?")] += 1
        except Exception:  # a torn tail: what was read so far
            pass
    return out


def session_counts(sessions: Path) -> tuple[Counter, int]:
    """Messages per topic over every session and segment; the number of segments."""
    total, n = Counter(), 0
    for seg in sorted(sessions.glob("*/seg-*.mcap")):
        total += segment_counts(seg)
        n += 1
    return total, n


# -- the run ------------------------------------------------------------------------------------


@dataclass
class Run:
    args: argparse.Namespace
    tmp: Path
    rng: random.Random = field(init=False)

    def __post_init__(self) -> None:
        self.rng = random.Random(self.args.seed)
        self.run_s = self.args.minutes * 60.0
        self.warmup_s = min(300.0, self.run_s / 3)
        self.ports = {"profiler": free_port(), "pps": free_port()}
        self.broker = Mosquitto(self.tmp / "broker")
        self.ports["broker"] = self.broker.port
        expected = LOG_BYTES_PER_S * self.args.speed * self.args.point_rate_scale * self.run_s
        (self.tmp / "sessions").mkdir()
        self.disk = DiskLimits.choose(self.tmp, expected)

    def start_daemon(self) -> subprocess.Popen:
        cfg = self.tmp / "vessel.yaml"
        cfg.write_text(vessel_yaml(self.tmp, self.ports, self.args.speed, self.disk.warning_mb))
        daemon = subprocess.Popen(
            [*MLS, "acquire", "--config", str(cfg), "--log-level", "warning"],
            cwd=self.tmp,
            stdout=subprocess.DEVNULL,
            stderr=open(self.tmp / "daemon.log", "wb"),  # noqa: SIM115 (the child keeps it)
            start_new_session=True,
        )
        wait_for(lambda: (self.tmp / "status.sock").exists() or daemon.poll() is not None, 60, "the daemon")
        if daemon.poll() is not None:
            raise RuntimeError(f"mls acquire failed: {(self.tmp / 'daemon.log').read_text()[-2000:]}")
        return daemon

    def execute(self) -> dict:
        self.broker.start()
        results = ResultCounter(self.broker.host, self.broker.port, BASE)
        daemon = self.start_daemon()
        sampler, listener = Sampler(daemon.pid), AlarmListener(self.tmp / "status.sock")
        t0 = time.monotonic_ns()
        deadline = t0 + round(self.run_s * NS)
        segments = Segments(
            self.tmp,
            self.ports,
            self.args.speed,
            self.args.point_rate_scale,
            random.Random(self.rng.random()),
            deadline,
        )
        ballast = Ballast(self.tmp, self.disk.warning_mb) if self.disk.usable else None
        host = HostFaults(self.broker, ballast, random.Random(self.rng.random()))
        try:
            for th in (sampler, listener, segments):
                th.start()
            run_host_faults(host, faults.host_plan(self.rng, self.run_s), t0, deadline)
            segments.join()
            running_until = time.monotonic_ns()
            snap = settle(self.tmp / "status.sock")
            drops = udp_drops(self.ports["profiler"])
        finally:
            segments.halt.set()
            if segments.proc is not None:
                stop(segments.proc, grace_s=60)
            if ballast is not None:
                ballast.empty()
            stop(daemon, grace_s=60)
            for th in (sampler, listener):
                th.halt.set() if th is sampler else th.stop()
            results.stop()
            self.broker.stop()
        counts, n_segments = session_counts(self.tmp / "sessions")
        return {
            "t0": t0,
            "running_until": running_until,
            "snap": snap,
            "kernel_drops": drops,
            "daemon_rc": daemon.returncode,
            "samples": sampler.samples,
            "alarms": listener.events,
            "segments": segments,
            "host": host,
            "results": results,
            "counts": counts,
            "log_segments": n_segments,
        }


def settle(sock: Path) -> dict:
    """The daemon's snapshot once it has read what it was sent (its profiler count still 1.5 s)."""
    snap, last, since = read_snapshot(sock), -1, time.monotonic()
    t_end = since + 30
    while time.monotonic() - since < 1.5 and time.monotonic() < t_end:
        time.sleep(0.5)
        snap = read_snapshot(sock)
        n = snap["metrics"]["devices"]["profiler"]["chunks"]
        if n != last:
            last, since = n, time.monotonic()
    return snap


# -- the report ---------------------------------------------------------------------------------


def goal(ok: bool) -> str:
    return "met" if ok else "NOT met"


def emulator_totals(stats: list[dict]) -> dict:
    """Sums over the runs of the emulators; INS epochs overrun (the pty full: the daemon did not
    read) estimated from their bytes at the runs' bytes per epoch."""
    out = Counter()
    for s in stats:
        p, i = s["profiler"]["stats"], s["ins"]["stats"]
        out["datagrams"] += p["datagrams_sent"]
        out["paused"] += p["lost"]
        out["epochs"] += i["epochs"]
        out["unplugged_epochs"] += i["epochs_unplugged"]
        out["in_flight_epochs"] += i["epochs_in_flight"]
        total = i["bytes_written"] + i["bytes_overrun"] + i["bytes_unplugged"]
        per_epoch = total / max(i["epochs"], 1)
        out["overrun_epochs"] += round(i["bytes_overrun"] / per_epoch) if per_epoch else 0
        out["overrun_bytes"] += i["bytes_overrun"]
        out["unplugs"] += i["unplugs"]
    return out


def report_losses(r: dict) -> None:
    em = emulator_totals(r["segments"].stats)
    logged = r["counts"]
    m = r["snap"]["metrics"]
    log_dropped = sum(m["log"]["dropped"].values())
    lost = em["datagrams"] - logged["/lidar/raw"]
    ins_expected = em["epochs"] - em["unplugged_epochs"] - em["in_flight_epochs"]
    ins_lost = ins_expected - logged["/ins/nav"]
    print(
        f"records lost, profiler: {lost:,} of {em['datagrams']:,} datagrams sent "
        f"({logged['/lidar/raw']:,} /lidar/raw in {r['log_segments']} log segments; the daemon "
        f"received {m['devices']['profiler']['chunks']:,}, log writer dropped {log_dropped:,}, socket "
        f"overflows {r['kernel_drops']}; {em['paused']:,} withheld by the pauses)   goal 0 ({goal(lost == 0)})"
    )
    print(
        f"records lost, INS: {ins_lost:,} of {ins_expected:,} epochs the daemon could read ({em['epochs']:,} "
        f"emitted; the {em['unplugs']} unplugs took {em['unplugged_epochs']:,} written while unplugged and "
        f"{em['in_flight_epochs']:,} in flight; {logged['/ins/nav']:,} /ins/nav logged, daemon decoded "
        f"{m['devices']['ins']['records']:,}; pty overrun {em['overrun_bytes']:,} bytes ≈ "
        f"{em['overrun_epochs']:,} epochs, the daemon's)   goal 0 ({goal(ins_lost == 0)})"
    )
    report_overruns(r)


def report_overruns(r: dict) -> None:
    """When the INS pty overflowed (the daemon not reading), and whether just after a replug."""
    done = r["segments"].done
    back = [f.end_ns for f in done if f.kind in ("ins_unplug", "emulators_restart", "start-up")]
    eps = sorted(tuple(e) for s in r["segments"].stats for e in s["ins"]["stats"].get("overruns", []))
    parts = []
    for t0, t1, n in eps[:20]:
        after = [t0 - b for b in back if 0 <= t0 - b <= 2 * NS]
        where = f", {after[0] / NS:.2f} s after the device came back" if after else ""
        parts.append(f"{(t0 - r['t0']) / NS:.1f} s ({n:,} B in {(t1 - t0) / NS:.2f} s{where})")
    print("INS pty overruns (host s after the start): " + ("; ".join(parts) or "none"))


def report_resources(r: dict, warmup_s: float) -> None:
    after = [s for s in r["samples"] if r["t0"] + warmup_s * NS <= s.t_ns <= r["running_until"]]
    if len(after) < 2:
        print("resources: too few samples after the warm-up")
        return
    first, last = after[0], after[-1]
    growth = 100 * (last.rss_kb - first.rss_kb) / first.rss_kb
    print(
        f"RSS of the daemon after the warm-up ({warmup_s / 60:g} min; samples until the emulators' end): {first.rss_kb / 1024:.1f} MiB → last "
        f"{last.rss_kb / 1024:.1f} MiB (max {max(s.rss_kb for s in after) / 1024:.1f}, at start "
        f"{r['samples'][0].rss_kb / 1024:.1f}): {growth:+.1f} %   goal ≤ 5 % ({goal(growth <= 5)})"
    )
    for what in ("fds", "threads"):
        a, b, mx = getattr(first, what), getattr(last, what), max(getattr(s, what) for s in after)
        print(
            f"{'open file descriptors' if what == 'fds' else 'threads'}: first after the warm-up {a}, "
            f"last {b}, max {mx}   goal stable ({goal(b <= a + 2)})"
        )
    loads = sorted(s.load1 for s in r["samples"])
    print(
        f"host load (1-min average, {os.cpu_count()} CPUs) during the run: median "
        f"{loads[len(loads) // 2]:.1f}, max {loads[-1]:.1f} (other work on the host delays the daemon)"
    )


def attribute_alarms(r: dict) -> tuple[list[Fault], list[dict]]:
    """Every alarm event to the latest fault begun before it (until 30 s after its end), one
    about the alarm's device (:data:`CONCERNS`) first."""
    done = sorted(r["segments"].done + r["host"].done, key=lambda f: f.start_ns)
    orphans = []
    for t, ev in r["alarms"]:
        near = [f for f in done if f.start_ns <= t <= f.end_ns + AFTER_FAULT_S * NS]
        about = [f for f in near if ev.get("device") in CONCERNS.get(f.kind, ())]
        owner = (about or near or [None])[-1]
        (owner.alarms if owner else orphans).append({**ev, "t": t})
    return done, orphans


def alarm_text(events: list[dict], action: str) -> str:
    c = Counter(f"{e['name']}/{e['device']}" for e in events if e.get("action") == action)
    return ", ".join(f"{k}×{n}" if n > 1 else k for k, n in sorted(c.items())) or "–"


def report_alarms(r: dict) -> None:
    done, orphans = attribute_alarms(r)
    print(f"faults ({len(done)}) and their alarms (host s after the start):")
    for f in done:
        print(
            f"  {(f.start_ns - r['t0']) / NS:7.1f} s  {f.kind:<18} {f.detail}\n"
            f"             raised: {alarm_text(f.alarms, 'raise')}; cleared: {alarm_text(f.alarms, 'clear')}"
        )
    print(
        f"alarms outside any fault: raised {alarm_text(orphans, 'raise')}; cleared {alarm_text(orphans, 'clear')}"
    )
    active = r["snap"].get("status", {}).get("alarms") or []
    print(
        "alarms active at the end (the emulators stopped): "
        + (", ".join(f"{a['name']}/{a['device']}" for a in active) or "none")
    )


def report_commands(r: dict) -> None:
    sent, res = r["host"].sent, r["results"]
    mqtt = r["snap"]["metrics"].get("mqtt") or {}
    c = mqtt.get("commands", {})
    print(
        f"commands sent: {sent['flood']} in floods ({sent['flood_marks']} marks, {sent['flood_rotates']} "
        f"rotates, the rest malformed), {sent['retained']} retained after broker restarts"
    )
    print(
        "daemon's mqtt.commands: "
        + ", ".join(f"{k} {v}" for k, v in c.items())
        + f"; MQTT connects {mqtt.get('connects')}, messages dropped {mqtt.get('dropped')}"
    )
    reasons = ", ".join(f"{k} {v}" for k, v in sorted(res.reasons.items()))
    print(f"cmd/result replies received: ok {res.ok}, refused {res.refused} ({reasons or '–'})")


def report(r: dict, run: Run) -> None:
    a = run.args
    print()
    print(
        f"soak: {a.minutes:g} min at ×{a.speed:g} the profiler rate (point rate scale {a.point_rate_scale:g}), "
        f"seed {a.seed}, {len(r['segments'].stats)} runs of the emulators, daemon exit status {r['daemon_rc']}"
    )
    if not run.disk.usable:
        print(f"disk pressure skipped: {run.disk.why}")
    for e in r["segments"].errors:
        print(f"emulators: {e}")
    report_losses(r)
    report_resources(r, run.warmup_s)
    report_commands(r)
    report_alarms(r)


def _interrupted(signum: int, _frame) -> None:
    raise SystemExit(128 + signum)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--minutes", type=float, default=30.0, help="length of the run")
    ap.add_argument("--speed", type=float, default=3.0, help="multiple of the devices' real rate")
    ap.add_argument("--seed", type=int, default=1, help="seed of the faults")
    ap.add_argument("--point-rate-scale", type=float, default=1.0, help="1 = the full Z+F point rate")
    ap.add_argument("--keep", action="store_true", help="keep the temporary directory")
    args = ap.parse_args()
    for sig in (signal.SIGTERM, signal.SIGINT):  # stop cleanly: daemon, emulators, broker, ballast
        signal.signal(sig, _interrupted)
    tmp = Path(tempfile.mkdtemp(prefix="mls-soak-"))
    try:
        run = Run(args, tmp)
        print(
            f"soak: {args.minutes:g} min at ×{args.speed:g}, seed {args.seed}, in {tmp}; disk_warning_mb "
            f"{run.disk.warning_mb} ({faults.free_bytes(tmp) / faults.GIB:.1f} GiB free now)",
            flush=True,
        )
        r = run.execute()
        report(r, run)
        samples = [[(x.t_ns - r["t0"]) / NS, x.rss_kb, x.fds, x.threads, x.load1] for x in r["samples"]]
        (tmp / "samples.json").write_text(json.dumps({"s, rss_kb, fds, threads, load1": samples}))
    finally:
        if args.keep:
            print(f"kept {tmp}")
        else:
            shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
