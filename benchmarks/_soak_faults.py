"""The faults of ``benchmarks/soak.py``: the seeded plan, the disk ballast, the MQTT side
(broker restarts, command floods, retained commands, the ``cmd/result`` replies).

Faults on the host's side (:func:`host_plan`) happen at host seconds after the daemon is up;
the devices' faults (:func:`segment_faults`) go into the fault timeline of each run of the
emulators (``mls sim devices --faults``): an INS unplug (``serial_unplug``) and a pause of the
profiler's UDP sender (``udp_loss`` with probability 1).
"""

from __future__ import annotations

import json
import os
import random
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import paho.mqtt.client as paho

GIB = 2**30
MIB = 2**20
#: the disk is never filled below this much free space
DISK_FLOOR_BYTES = 5 * GIB
HOST_KINDS = ("broker_restart", "command_flood", "disk_pressure")
FLOOD_MARKS, FLOOD_ROTATES, FLOOD_INVALID = 140, 50, 10


@dataclass
class Fault:
    """One fault as done: its kind, what it was, host monotonic ns of its start and end."""

    kind: str
    detail: str
    start_ns: int
    end_ns: int
    alarms: list[dict] = field(default_factory=list)


def host_plan(rng: random.Random, run_s: float) -> list[tuple[float, str, dict]]:
    """(host seconds after the start, kind, parameters) of the host faults: the kinds in a
    shuffled cycle, one every 20–60 s (fewer in a short run), from 20 s on, none in the last 15 s."""
    gap = min(max(run_s / 40, 20.0), 60.0)
    plan, t, cycle = [], 20.0 + rng.uniform(0, 5), []
    while t < run_s - 15.0:
        if not cycle:
            cycle = rng.sample(HOST_KINDS, len(HOST_KINDS))
        kind = cycle.pop()
        plan.append((round(t, 2), kind, _host_params(rng, kind)))
        t += gap * rng.uniform(0.8, 1.2)
    return plan


def _host_params(rng: random.Random, kind: str) -> dict:
    if kind == "broker_restart":
        return {"down_s": round(rng.uniform(1.0, 6.0), 2), "crash": rng.random() < 0.5}
    if kind == "command_flood":
        return {"seconds": round(rng.uniform(1.0, 4.0), 2)}
    return {"hold_s": round(rng.uniform(3.0, 8.0), 2)}


def segment_faults(rng: random.Random, scenario_s: float, speed: float) -> list[dict]:
    """The devices' faults of one run of the emulators (scenario seconds): maybe an INS unplug
    in its first half, maybe a pause of the profiler in its second half, 1–5 host seconds each."""
    out = []
    half = scenario_s / 2
    if half > 30 * speed and rng.random() < 0.6:
        at = rng.uniform(10 * speed, half - 10 * speed)
        out.append({"at_s": round(at, 2), "kind": "serial_unplug", "duration_s": _fault_s(rng, speed)})
    if half > 30 * speed and rng.random() < 0.6:
        at = rng.uniform(half, scenario_s - 15 * speed)
        out.append(
            {
                "at_s": round(at, 2),
                "kind": "udp_loss",
                "device": "profiler",
                "duration_s": _fault_s(rng, speed),
                "probability": 1.0,
            }
        )
    return out


def _fault_s(rng: random.Random, speed: float) -> float:
    return round(rng.uniform(1.0, 5.0) * speed, 2)


def faults_yaml(seed: int, faults: list[dict]) -> str:
    lines = [f"seed: {seed}", "faults:"]
    lines += ["  - " + json.dumps(f) for f in faults]  # JSON flow mappings are YAML
    return "\n".join(lines) + "\n"


# -- the disk -----------------------------------------------------------------------------------


def free_bytes(path: Path) -> int:
    st = os.statvfs(path)
    return st.f_bavail * st.f_frsize


@dataclass(frozen=True)
class DiskLimits:
    """The daemon's ``disk_warning_mb`` chosen from the free space at the start: the run's own
    writing (``expected_bytes``, × 1.5) never brings the free space within 25 % of it, and the
    ballast that takes the free space to 90 % of it leaves at least :data:`DISK_FLOOR_BYTES`."""

    warning_mb: int
    usable: bool
    why: str = ""

    @classmethod
    def choose(cls, path: Path, expected_bytes: float) -> DiskLimits:
        lowest = free_bytes(path) - 1.5 * expected_bytes
        warning = lowest / 1.25
        if 0.9 * warning < DISK_FLOOR_BYTES:
            why = (
                f"{free_bytes(path) / GIB:.1f} GiB free, the run writes ~{expected_bytes / GIB:.1f} GiB: "
                f"no room for a ballast above {DISK_FLOOR_BYTES / GIB:.0f} GiB free"
            )
            return cls(10240, False, why)
        return cls(int(warning / MIB), True)


class Ballast:
    """A file in the session directory's file system, allocated (``posix_fallocate``: ext4 and
    xfs reserve the blocks without writing them) so that the free space drops to 90 % of the
    daemon's warning threshold, never below :data:`DISK_FLOOR_BYTES`; removed by :meth:`empty`."""

    def __init__(self, directory: Path, warning_mb: int):
        self.path = directory / "soak-ballast"
        self.target = max(int(0.9 * warning_mb * MIB), DISK_FLOOR_BYTES)

    def fill(self) -> int:
        """Allocate the ballast; returns its size in bytes (0 when the disk is already low)."""
        size = free_bytes(self.path.parent) - self.target
        if size <= 0:
            return 0
        fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        try:
            os.posix_fallocate(fd, 0, size)
        finally:
            os.close(fd)
        return size

    def empty(self) -> None:
        self.path.unlink(missing_ok=True)


# -- MQTT ---------------------------------------------------------------------------------------


def _client(name: str) -> paho.Client:
    c = paho.Client(paho.CallbackAPIVersion.VERSION2, client_id=f"mls-soak-{name}-{os.getpid()}")
    c.reconnect_delay_set(0.2, 2)
    return c


class ResultCounter:
    """Subscribed to ``<base>/cmd/result`` (reconnecting across broker restarts): counts the
    replies, accepted (``ok``) or refused, and refusals by reason."""

    def __init__(self, host: str, port: int, base: str):
        self.topic = f"{base}/cmd/result"
        self.ok = self.refused = 0
        self.reasons: dict[str, int] = {}
        self._lock = threading.Lock()
        self.client = _client("results")
        self.client.on_connect = lambda c, *_: c.subscribe(self.topic, qos=1)
        self.client.on_message = self._on_message
        self.client.connect_async(host, port, keepalive=5)
        self.client.loop_start()

    def _on_message(self, _c, _u, msg) -> None:
        try:
            reply = json.loads(msg.payload)
        except ValueError:
            return
        with self._lock:
            if reply.get("ok"):
                self.ok += 1
            else:
                self.refused += 1
                reason = _reason(str(reply.get("message", "")))
                self.reasons[reason] = self.reasons.get(reason, 0) + 1

    def stop(self) -> None:
        self.client.loop_stop()
        self.client.disconnect()


def _reason(message: str) -> str:
    """A refusal's kind: rate limited or invalid."""
    return "rate limited" if "rate limited" in message else "invalid"


def _publish_all(host: str, port: int, messages: list[tuple[str, bytes, bool]], seconds: float) -> int:
    """Publish (topic, payload, retain) at QoS 1 spread over ``seconds``; returns how many the
    broker acknowledged."""
    c = _client("cmd")
    c.connect(host, port, keepalive=10)
    c.loop_start()
    try:
        infos = []
        for topic, payload, retain in messages:
            infos.append(c.publish(topic, payload, qos=1, retain=retain))
            time.sleep(seconds / len(messages))
        for info in infos:
            info.wait_for_publish(10)
        return sum(info.is_published() for info in infos)
    finally:
        c.loop_stop()
        c.disconnect()


def flood(host: str, port: int, base: str, rng: random.Random, seconds: float, n0: int) -> dict:
    """:data:`FLOOD_MARKS` ``cmd/mark``, :data:`FLOOD_ROTATES` ``cmd/rotate`` and
    :data:`FLOOD_INVALID` malformed marks, shuffled, within ``seconds``; ids from ``n0``."""
    msgs = [(f"{base}/cmd/mark", {"text": f"soak mark {n0 + i}", "id": n0 + i}) for i in range(FLOOD_MARKS)]
    msgs += [(f"{base}/cmd/rotate", {"id": n0 + FLOOD_MARKS + i}) for i in range(FLOOD_ROTATES)]
    bad = [{"text": "x" * 300}, {"text": "a\x07b"}, {"text": "ok", "extra": 1}, {"pass_id": 1}]
    msgs += [(f"{base}/cmd/mark", bad[i % len(bad)]) for i in range(FLOOD_INVALID)]
    rng.shuffle(msgs)
    payloads = [(t, json.dumps(p).encode(), False) for t, p in msgs]
    acked = _publish_all(host, port, payloads, seconds)
    return {"sent": len(payloads), "acked": acked, "marks": FLOOD_MARKS, "rotates": FLOOD_ROTATES}


def retained(host: str, port: int, base: str, n0: int) -> int:
    """Retained ``cmd/mark`` and ``cmd/rotate`` (published while the daemon is not yet back on
    the restarted broker, so that its subscription receives them as retained: to be ignored);
    the broker keeps them, one a topic, until its next restart (no persistence)."""
    msgs = [
        (f"{base}/cmd/mark", json.dumps({"text": f"retained {n0}", "id": n0}).encode(), True),
        (f"{base}/cmd/rotate", json.dumps({"id": n0 + 1}).encode(), True),
    ]
    return _publish_all(host, port, msgs, 0.0)
