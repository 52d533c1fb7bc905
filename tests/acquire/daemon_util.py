"""Helpers of the daemon integration tests (not a test module): processes in their own process
groups (killed as groups at the end, never left behind), and background collectors of what the
daemon publishes — status-socket lines, MQTT messages, sd_notify datagrams — each stamped with
the host monotonic time it arrived."""

from __future__ import annotations

import asyncio
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from acquire.status.bus import StatusListener
from tests import waiting

MLS = [sys.executable, "-m", "cli.app"]
ROOT = Path(__file__).resolve().parents[2]


def sim_devices_cmd(
    run: Path, duration_s: float, faults: Path, prof: int, pps: int, *extra: str
) -> list[str]:
    """``mls sim devices`` as the live daemon tests run it: montreal from pass 1, the INS on a pty,
    profiler and PPS over UDP to the given ports, the fault timeline ``faults``; ``extra`` adds
    options (clock drift, jitter, speed)."""
    return [
        *MLS,
        *("sim", "devices", "--scenario", "montreal", "--start", "pass:1"),
        *("--duration", str(duration_s), "--faults", str(faults), *extra),
        *("--devices", "ins,profiler,pps", "--profiler-port", str(prof), "--pps-port", str(pps)),
        *("--run-dir", str(run)),
    ]


def start_emulators(
    run: Path, duration_s: float, faults: Path, prof: int, pps: int, log: Path, procs: list
) -> tuple[Proc, TruthClock]:
    """The emulators as the live fault tests run them (real time, the host clock 35 ppm off, PPS
    jitter 20 µs), added to ``procs``; returns them and their truth clock once it is written."""
    sim = Proc(
        sim_devices_cmd(
            run,
            duration_s,
            faults,
            prof,
            pps,
            "--speed",
            "1",
            "--clock-drift-ppm",
            "35",
            "--pps-jitter-us",
            "20",
        ),
        log,
    )
    procs.append(sim)
    wait_until(lambda: (run / "truth_clock.json").exists(), 120, "the emulators to start", sim)
    return sim, TruthClock.read(run / "truth_clock.json")


def free_port(kind=socket.SOCK_DGRAM) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Proc:
    """A child process in its own session (process group); ``kill()`` ends the whole group."""

    def __init__(self, args: list[str], log: Path, env: dict | None = None, cwd: Path | None = None):
        self.log = log
        self.args = args
        with open(log, "ab") as f:
            self.p = subprocess.Popen(
                args,
                stdout=f,
                stderr=subprocess.STDOUT,
                cwd=cwd or ROOT,
                env={**os.environ, **(env or {})},
                start_new_session=True,
            )

    @property
    def pid(self) -> int:
        return self.p.pid

    def alive(self) -> bool:
        return self.p.poll() is None

    def signal(self, sig: int) -> None:
        if self.alive():
            os.killpg(self.p.pid, sig)

    def wait(self, timeout_s: float) -> int:
        return self.p.wait(timeout_s)

    def kill(self) -> None:
        try:
            os.killpg(self.p.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        try:
            self.p.wait(10)
        except subprocess.TimeoutExpired:
            pass

    def output(self) -> str:
        return self.log.read_text(errors="replace")


def wait_until(cond, timeout_s: float, what: str, proc: Proc | None = None, poll_s: float = 0.05):
    """:func:`tests.waiting.wait_until`, giving up at once when ``proc`` ends (its output in the
    message)."""

    def still_running() -> None:
        if proc is not None and not proc.alive():
            raise AssertionError(f"{what}: the process ended ({proc.p.returncode}):\n{proc.output()[-3000:]}")

    return waiting.wait_until(
        cond,
        timeout_s,
        what,
        interval_s=poll_s,
        between=still_running,
        detail=None if proc is None else (lambda: proc.output()[-3000:]),
    )


def sleep_until_host_ns(t_ns: int) -> None:
    """Until host time ``t_ns``: a step of a fault timeline that runs in real time beside the
    emulators (the broker killed at scenario second 20), not a wait for an outcome."""
    time.sleep(max(t_ns - time.monotonic_ns(), 0) / 1e9)


def wait_handled(sock: SocketCollector, after_ns: int, timeout_s: float = 30.0, **minimum: dict) -> bool:
    """Wait until the daemon has handled everything its devices sent before ``after_ns`` (the
    emulators had ended by then): two successive ``metrics`` documents on the status socket, both
    published after ``after_ns``, with the same device counters (nothing was left to handle in
    between) and each device's counters at least ``minimum`` (``profiler={"chunks": n}``).
    Returns False at the timeout: the caller goes on, and its checks say what is missing."""

    def counters(doc: dict) -> dict:
        return {n: (d.get("chunks"), d.get("records")) for n, d in doc["devices"].items()}

    def handled() -> bool:
        docs = [r.data for r in sock.topic("metrics") if r.host_ns > after_ns]
        if len(docs) < 2 or counters(docs[-2]) != counters(docs[-1]):
            return False
        last = docs[-1]["devices"]
        return all(last[dev].get(k, 0) >= v for dev, at_least in minimum.items() for k, v in at_least.items())

    return waiting.wait_until(
        handled, timeout_s, "the daemon to handle what was sent", interval_s=0.05, fail=False
    )


def logged_counts(sessions: Path, topics: set[str]) -> dict[str, int]:
    """Messages per topic in the complete chunks of every segment of the sessions under
    ``sessions`` (a live segment too: its torn tail, being written, is not counted)."""
    from acquire.log.recover import scan_segment, segment_paths

    counts = dict.fromkeys(topics, 0)
    for session in sorted(p for p in sessions.iterdir() if p.is_dir()):
        for path in segment_paths(session):
            channels: dict[int, str] = {}
            for rec in scan_segment(path):
                kind = type(rec).__name__
                if kind == "Channel":
                    channels[rec.id] = rec.topic
                elif kind == "Message" and channels.get(rec.channel_id) in counts:
                    counts[channels[rec.channel_id]] += 1
    return counts


def wait_logged(sessions: Path, minimum: dict[str, int], timeout_s: float = 30.0) -> bool:
    """Wait until the session files hold at least ``minimum`` messages per topic in complete
    chunks (what a ``kill -9`` keeps). False at the timeout, as :func:`wait_handled`."""
    return waiting.wait_until(
        lambda: all(n >= minimum[t] for t, n in logged_counts(sessions, set(minimum)).items()),
        timeout_s,
        f"{minimum} in the session files",
        interval_s=0.5,
        fail=False,
    )


@dataclass
class Received:
    host_ns: int  # when the test process received it (CLOCK_MONOTONIC)
    topic: str
    data: object


class SocketCollector(StatusListener):
    """Every JSON line of the daemon's status socket (reconnecting when the daemon restarts)."""

    def __init__(self, path: Path):
        super().__init__(path, retry_s=0.05)
        self.lines: list[Received] = []

    def handle(self, received_ns: int, topic: str, data) -> None:
        self.lines.append(Received(received_ns, topic, data))

    def topic(self, name: str) -> list[Received]:
        return [r for r in list(self.lines) if r.topic == name]


class MqttCollector(threading.Thread):
    """Every MQTT message under ``topic`` (a filter), reconnecting when the broker restarts."""

    def __init__(self, host: str, port: int, topic: str):
        super().__init__(daemon=True)
        self.host, self.port, self.filter = host, port, topic
        self.messages: list[Received] = []
        self.connects = 0
        self._loop: asyncio.AbstractEventLoop | None = None
        self._task: asyncio.Task | None = None
        self._ready = threading.Event()

    def run(self) -> None:
        asyncio.run(self._main())

    async def _main(self) -> None:
        import aiomqtt

        self._loop = asyncio.get_running_loop()
        self._task = asyncio.current_task()
        try:
            while True:
                try:
                    async with aiomqtt.Client(self.host, self.port, keepalive=5) as c:
                        await c.subscribe(self.filter, qos=1)
                        self.connects += 1
                        self._ready.set()
                        async for m in c.messages:
                            try:
                                data = json.loads(m.payload)
                            except ValueError:
                                data = bytes(m.payload)
                            self.messages.append(Received(time.monotonic_ns(), str(m.topic), data))
                except aiomqtt.MqttError:
                    await asyncio.sleep(0.2)
        except asyncio.CancelledError:
            pass

    def start(self) -> MqttCollector:
        super().start()
        if not self._ready.wait(10):
            raise AssertionError(f"MQTT collector could not subscribe on {self.host}:{self.port}")
        return self

    def stop(self) -> None:
        if self._loop is not None and self._task is not None:
            self._loop.call_soon_threadsafe(self._task.cancel)
        if self.is_alive():
            self.join(5)

    def topic(self, suffix: str) -> list[Received]:
        return [r for r in list(self.messages) if r.topic.endswith("/" + suffix)]


class NotifyCollector(threading.Thread):
    """A ``NOTIFY_SOCKET`` (AF_UNIX datagrams) that records every sd_notify message."""

    def __init__(self, path: Path):
        super().__init__(daemon=True)
        self.path = path
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(str(path))
        self.sock.settimeout(0.2)
        self.messages: list[tuple[int, str]] = []
        self._halt = threading.Event()

    def run(self) -> None:
        while not self._halt.is_set():
            try:
                data = self.sock.recv(4096)
            except TimeoutError:
                continue
            except OSError:
                return
            self.messages.append((time.monotonic_ns(), data.decode()))

    def stop(self) -> None:
        self._halt.set()
        if self.is_alive():
            self.join(5)
        self.sock.close()

    def with_line(self, line: str) -> list[int]:
        return [t for t, m in list(self.messages) if line in m.split("\n")]


@dataclass
class TruthClock:
    """The emulators' ``truth_clock.json`` (host monotonic → GPS ns)."""

    host_anchor_ns: int
    gps_anchor_ns: int
    rate: float
    window: dict = field(default_factory=dict)

    @classmethod
    def read(cls, path: Path) -> TruthClock:
        d = json.loads(path.read_text())
        return cls(int(d["host_anchor_ns"]), int(d["gps_anchor_ns"]), float(d["rate"]), d.get("window", {}))

    def gps_ns(self, host_ns):
        import numpy as np

        h = np.asarray(host_ns, dtype=np.int64)
        return self.gps_anchor_ns + np.rint((h - self.host_anchor_ns).astype(np.float64) * self.rate).astype(
            np.int64
        )

    def host_ns(self, gps_ns: int) -> int:
        """The host monotonic ns of a GPS instant (the inverse of :meth:`gps_ns`)."""
        return self.host_anchor_ns + round((int(gps_ns) - self.gps_anchor_ns) / self.rate)


class Recording:
    """What a collector received, as plain data (shareable between test workers as JSON)."""

    def __init__(self, items: list[Received]):
        self.items = items

    @classmethod
    def of(cls, collector) -> Recording:
        items = collector.lines if hasattr(collector, "lines") else collector.messages
        return cls(
            [
                Received(r.host_ns, r.topic, r.data if not isinstance(r.data, bytes) else r.data.hex())
                for r in list(items)
            ]
        )

    def to_json(self) -> list:
        return [[r.host_ns, r.topic, r.data] for r in self.items]

    @classmethod
    def from_json(cls, rows: list) -> Recording:
        return cls([Received(h, t, d) for h, t, d in rows])

    def topic(self, name: str) -> list[Received]:
        """Messages on ``name`` (a status topic, or the last part of an MQTT topic)."""
        return [r for r in self.items if r.topic == name or r.topic.endswith("/" + name)]

    def with_line(self, line: str) -> list[int]:
        """sd_notify recordings (topic "notify"): the times of messages holding ``line``."""
        return [r.host_ns for r in self.items if line in str(r.data).split("\n")]


def run_once(tmp_path_factory, key: str, produce) -> dict:
    """``produce(directory) -> dict`` once per test session, even when pytest-xdist spreads the
    tests that need it over several workers (they share the session's base temp directory): the
    first worker runs it under a file lock and leaves the JSON result (or its failure) for the
    others."""
    import fcntl
    import traceback

    base = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        base = base.parent
    out = base / f"{key}.json"
    with open(base / f"{key}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not out.exists():
            d = base / key
            d.mkdir(exist_ok=True)
            try:
                result = {"ok": produce(d)}
            except BaseException:
                result = {"error": traceback.format_exc()}
            out.write_text(json.dumps(result))
        result = json.loads(out.read_text())
    if "error" in result:
        raise AssertionError(f"the shared run {key!r} failed:\n{result['error']}")
    return result["ok"]
