"""The daemon against the simulated devices, one 50-s real-time run with faults.

``mls sim devices`` (scenario montreal from pass 1, INS NMEA 100 Hz on a pty, profiler ZFP1
over UDP, PPS over UDP with 20 µs jitter, truth clock drifting 35 ppm, at ×1: the clock's
physics are real time) feeds ``mls acquire`` (its own process, started first, with a
``NOTIFY_SOCKET`` and ``WATCHDOG_USEC``) and a real mosquitto on loopback. The fault timeline,
in scenario seconds: a 20 ms INS latency jump at 10 s (5 s), a 1 s profiler clock offset at
18 s (4 s), PPS loss at 26 s (5 s), the INS pty unplugged at 39 s (2 s). The test kills the
broker at 20 s and restarts it at 24 s; after the run it kills the daemon with SIGKILL,
restarts it (which salvages the torn session) and stops it with SIGTERM. One module fixture
runs all of it — once per test session, even when pytest-xdist spreads these tests over
workers (:func:`~tests.acquire.daemon_util.run_once`) — and the tests below each check one
aspect of what it recorded.
"""

from __future__ import annotations

import contextlib
import json
import signal
import textwrap
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from acquire.log.read import iter_messages
from acquire.log.recover import session_info
from tests.acquire.daemon_util import (
    MLS,
    MqttCollector,
    NotifyCollector,
    Proc,
    Recording,
    SocketCollector,
    TruthClock,
    free_port,
    run_once,
    sleep_until_host_ns,
    start_emulators,
    wait_handled,
    wait_logged,
    wait_until,
)
from tests.mosquitto import Mosquitto

pytestmark = [pytest.mark.realtime, pytest.mark.integration, pytest.mark.xdist_group("daemon-faults")]

NS = 1_000_000_000
DURATION_S = 50.0
FAULTS = """\
faults:
  - {at_s: 10.0, kind: ins_latency_jump, latency_s: 0.02, duration_s: 5.0}
  - {at_s: 18.0, kind: profiler_clock_offset, offset_s: 1.0, duration_s: 4.0}
  - {at_s: 26.0, kind: pps_loss, duration_s: 5.0}
  - {at_s: 39.0, kind: serial_unplug, duration_s: 2.0}
"""
BROKER_KILL_S, BROKER_BACK_S = 20.0, 24.0
PREFIX = "mlstest/faults"


@dataclass
class FaultRun:
    tmp: Path
    run_dir: Path
    truth: TruthClock
    faults: list[dict]
    sim_stats: dict
    sessions: list[Path]
    sock: Recording  # status-socket lines
    mqtt: Recording  # MQTT messages
    notify: Recording  # sd_notify datagrams
    broker_killed_ns: int
    broker_back_ns: int
    kill_ns: int
    daemon1_rc: int
    daemon2_rc: int
    daemon1_log: str
    daemon2_log: str

    def fault(self, kind: str) -> dict:
        return next(f for f in self.faults if f["kind"] == kind)

    def events(self, session: Path) -> list:
        return list(iter_messages(session, {"/events"}))


def _vessel_yaml(tmp: Path, run: Path, prof: int, pps: int, broker: int) -> str:
    return textwrap.dedent(f"""\
        vessel: faults
        devices:
          - name: ins
            kind: ins
            protocol: nmea
            transport: {{type: serial, port: {run}/ins, baud: 921600}}
            latency: {{band_ms: [0.0, 30.0], jump_ms: 5.0, rate_hz: 100.0, gap_s: 0.5}}
          - name: profiler
            kind: profiler
            protocol: zfp1
            transport: {{type: udp, host: 127.0.0.1, port: {prof}}}
            latency: {{band_ms: [0.0, 34.5], jump_ms: 5.0, rate_hz: 63.2, gap_s: 0.5}}
          - name: pps
            kind: pps
            source: {{type: udp, host: 127.0.0.1, port: {pps}}}
            time_device: ins
            time_messages: [ZDA]
        session: {{directory: {tmp}/sessions, rotate_s: 20, flush_s: 0.5}}
        status: {{socket: {tmp}/status.sock}}
        mqtt: {{host: 127.0.0.1, port: {broker}, topic_prefix: mlstest, keepalive_s: 2}}
        """)


@pytest.fixture(scope="session")
def fault_run(tmp_path_factory) -> FaultRun:
    d = run_once(tmp_path_factory, "mls-fault-run", _fault_run)
    p = {k: Path(v) for k, v in d.items() if k in ("tmp", "run_dir")}
    return FaultRun(
        p["tmp"],
        p["run_dir"],
        TruthClock.read(p["run_dir"] / "truth_clock.json"),
        d["faults"],
        d["sim_stats"],
        [Path(s) for s in d["sessions"]],
        Recording.from_json(d["sock"]),
        Recording.from_json(d["mqtt"]),
        Recording.from_json(d["notify"]),
        d["broker_killed_ns"],
        d["broker_back_ns"],
        d["kill_ns"],
        d["daemon1_rc"],
        d["daemon2_rc"],
        d["daemon1_log"],
        d["daemon2_log"],
    )


def _fault_run(tmp: Path) -> dict:
    """The run itself (once per test session: :func:`run_once`); returns plain data."""
    run = tmp / "run"
    run.mkdir()
    (tmp / "faults.yaml").write_text(FAULTS)
    prof, pps = free_port(), free_port()
    broker = Mosquitto(tmp / "broker").start()
    cfg = tmp / "vessel.yaml"
    cfg.write_text(_vessel_yaml(tmp, run, prof, pps, broker.port))
    procs: list[Proc] = []
    mqtt = MqttCollector(broker.host, broker.port, f"{PREFIX}/#").start()
    notify = NotifyCollector(tmp / "notify.sock")
    notify.start()
    env = {"NOTIFY_SOCKET": str(tmp / "notify.sock"), "WATCHDOG_USEC": "2000000"}
    sock = SocketCollector(tmp / "status.sock")
    try:
        daemon = Proc([*MLS, "acquire", "--config", str(cfg)], tmp / "daemon1.log", env)
        procs.append(daemon)
        wait_until(lambda: notify.with_line("READY=1"), 30, "READY=1 from the daemon", daemon)
        sock.start()
        sim, truth = start_emulators(run, DURATION_S, tmp / "faults.yaml", prof, pps, tmp / "sim.log", procs)
        start_ns = truth.window["start_host_ns"]
        sleep_until_host_ns(start_ns + int(BROKER_KILL_S * NS))
        killed_ns = time.monotonic_ns()
        broker.kill()
        sleep_until_host_ns(start_ns + int(BROKER_BACK_S * NS))
        broker.start()
        back_ns = time.monotonic_ns()
        assert sim.wait(DURATION_S + 60) == 0, sim.output()[-3000:]
        sim_end_ns = time.monotonic_ns()
        sent = {
            n: json.loads((run / "stats" / f"{n}.json").read_text())["stats"] for n in ("profiler", "pps")
        }
        # everything received handled, and in complete chunks of the file (what the kill keeps)
        wait_handled(
            sock,
            sim_end_ns,
            profiler={"chunks": sent["profiler"]["datagrams_sent"]},
            pps={"records": len(sent["pps"]["edges"])},
        )
        wait_logged(
            tmp / "sessions",
            {"/lidar/raw": sent["profiler"]["datagrams_sent"], "/pps": len(sent["pps"]["edges"])},
        )
        assert daemon.alive(), daemon.output()[-3000:]
        kill_ns = time.monotonic_ns()
        daemon.signal(signal.SIGKILL)
        rc1 = daemon.wait(10)
        wait_until(
            lambda: any(r.data == {"state": "lost"} and r.host_ns > kill_ns for r in mqtt.topic("status")),
            15,
            "the last will",
        )
        daemon2 = Proc([*MLS, "acquire", "--config", str(cfg)], tmp / "daemon2.log", env)
        procs.append(daemon2)
        wait_until(lambda: len(notify.with_line("READY=1")) >= 2, 30, "READY=1 after the restart", daemon2)
        ready2 = notify.with_line("READY=1")[1]
        wait_until(  # the restarted daemon's status reached MQTT and the status socket's collector
            lambda: (
                any(
                    r.host_ns > ready2 and isinstance(r.data, dict) and r.data.get("state") == "running"
                    for r in mqtt.topic("status")
                )
                and any(r.host_ns > ready2 for r in sock.topic("status"))
            ),
            30,
            "the restarted daemon's status",
            daemon2,
        )
        daemon2.signal(signal.SIGTERM)
        rc2 = daemon2.wait(30)
        wait_until(
            lambda: any(
                isinstance(r.data, dict) and r.data.get("state") == "stopped" for r in mqtt.topic("status")
            ),
            10,
            "the final status on MQTT",
        )
    finally:  # every step, even when one of them fails: no process is left behind
        with contextlib.ExitStack() as cleanup:
            cleanup.callback(broker.stop)
            for stop in (notify.stop, mqtt.stop, sock.stop, *(p.kill for p in procs)):
                cleanup.callback(stop)
    stats = {n: json.loads((run / "stats" / f"{n}.json").read_text()) for n in ("profiler", "pps", "ins")}
    return {
        "tmp": str(tmp),
        "run_dir": str(run),
        "faults": json.loads((run / "faults.json").read_text())["faults"],
        "sim_stats": stats["profiler"] | {"pps": stats["pps"], "ins": stats["ins"]},
        "sessions": [str(p) for p in sorted(q for q in (tmp / "sessions").iterdir() if q.is_dir())],
        "sock": Recording.of(sock).to_json(),
        "mqtt": Recording.of(mqtt).to_json(),
        "notify": [[t, "notify", m] for t, m in notify.messages],
        "broker_killed_ns": killed_ns,
        "broker_back_ns": back_ns,
        "kill_ns": kill_ns,
        "daemon1_rc": rc1,
        "daemon2_rc": rc2,
        "daemon1_log": daemon.output(),
        "daemon2_log": daemon2.output(),
    }


def _raw_records(session: Path):
    return list(iter_messages(session, {"/ins/raw", "/lidar/raw"}))


def test_clock_model_tracks_the_truth_clock_within_50_us_rms_after_30_s(fault_run):
    s1 = fault_run.sessions[0]
    recs = [m for m in _raw_records(s1) if m.clock != "UNLOCKED"]
    assert len(recs) > 5000
    host = np.array([m.host_ns for m in recs], dtype=np.int64)
    log = np.array([m.log_time_ns for m in recs], dtype=np.int64)
    err_us = (log - fault_run.truth.gps_ns(host)) / 1e3
    first_lock = int(host.min())
    late = host >= first_lock + 30 * NS
    rms_late = float(np.sqrt(np.mean(err_us[late] ** 2)))
    rms_all = float(np.sqrt(np.mean(err_us**2)))
    print(
        f"\nclock estimate error against the truth clock: RMS {rms_all:.1f} µs over "
        f"{len(recs)} records, RMS {rms_late:.1f} µs (max {np.abs(err_us[late]).max():.1f} µs) "
        f"over the {int(late.sum())} records ≥ 30 s after the lock"
    )
    assert late.sum() > 1000
    assert rms_late <= 50.0
    # the fitted drift is the truth's 35 ppm (the clock topic, at the end of the run)
    clocks = [r.data for r in fault_run.sock.topic("clock") if r.data.get("state") == "LOCKED"]
    assert abs(clocks[-1]["drift_ppm"] - 35.0) < 2.0, clocks[-1]


def test_pps_loss_gives_holdover_with_a_growing_bound_then_locked_again(fault_run):
    f = fault_run.fault("pps_loss")
    clock = [(m.host_ns, m.payload) for m in iter_messages(fault_run.sessions[0], {"/clock"})]
    window = [(h, d) for h, d in clock if f["start_host_ns"] <= h <= f["end_host_ns"] + 2 * NS]
    hold = [(h, d["error_bound_us"]) for h, d in window if d["state"] == "HOLDOVER"]
    assert len(hold) >= 3, [d["state"] for _, d in window]
    # locked until the first missing pulse, HOLDOVER 1.5 s after it, never UNLOCKED
    assert {d["state"] for _, d in window} <= {"LOCKED", "HOLDOVER"}
    assert hold[0][0] - f["start_host_ns"] < 3 * NS
    bounds = [b for _, b in hold]
    assert bounds == sorted(bounds) and bounds[-1] > bounds[0], bounds
    # LOCKED again until the INS unplug takes the ZDA sentences (the labels) away
    unplug = fault_run.fault("serial_unplug")["start_host_ns"]
    after = [d["state"] for h, d in clock if f["end_host_ns"] + 3 * NS < h < unplug]
    assert len(after) >= 4 and set(after) == {"LOCKED"}, after
    ev = [
        (m.host_ns, m.payload)
        for m in fault_run.events(fault_run.sessions[0])
        if m.payload["event"] == "clock_state"
        and f["start_host_ns"] <= m.host_ns <= f["end_host_ns"] + 3 * NS
    ]
    assert [(d["from"], d["to"]) for _, d in ev] == [("LOCKED", "HOLDOVER"), ("HOLDOVER", "LOCKED")], ev
    live = [
        r.data["state"]
        for r in fault_run.sock.topic("clock")
        if f["start_host_ns"] <= r.host_ns <= f["end_host_ns"] + 5 * NS
    ]
    assert "HOLDOVER" in live and live[-1] == "LOCKED", live


@pytest.mark.parametrize(
    ("kind", "alarm", "device"),
    [
        ("ins_latency_jump", "latency_jump", "ins"),
        ("profiler_clock_offset", "time_step", "profiler"),
    ],
)
def test_alarm_within_2_s_on_the_socket_in_mqtt_and_in_events(fault_run, kind, alarm, device):
    f = fault_run.fault(kind)
    t0 = f["start_host_ns"]

    def first(items):
        return min(
            (
                t
                for t, d in items
                if d.get("action") == "raise"
                and d.get("name") == alarm
                and d.get("device") == device
                and t >= t0 - NS
            ),
            default=None,
        )

    on_socket = first((r.host_ns, r.data) for r in fault_run.sock.topic("alarms"))
    on_mqtt = first((r.host_ns, r.data) for r in fault_run.mqtt.topic("alarms"))
    in_events = first(
        (m.payload["first_host_ns"], m.payload)
        for m in fault_run.events(fault_run.sessions[0])
        if m.payload["event"] == "alarm"
    )
    delays = {
        k: None if v is None else (v - t0) / NS
        for k, v in (("socket", on_socket), ("mqtt", on_mqtt), ("events", in_events))
    }
    print(f"\n{alarm}/{device} after the {kind} fault: {delays}")
    assert all(d is not None and 0 <= d <= 2.0 for d in delays.values()), delays


def test_ins_unplug_and_replug_reconnects_logs_the_gap_and_the_daemon_survives(fault_run):
    f = fault_run.fault("serial_unplug")
    events = [m.payload for m in fault_run.events(fault_run.sessions[0])]
    ins = [e for e in events if e.get("device") == "ins"]
    kinds = [e["event"] for e in ins if e["event"] in ("connected", "disconnected", "data_gap")]
    # connected at start, lost at the unplug, connected again, then the gap is logged
    assert kinds[:1] == ["connected"] or kinds[0] == "disconnected"
    i = kinds.index("disconnected", 0 if kinds[0] == "disconnected" else 1)
    assert "connected" in kinds[i:] and "data_gap" in kinds[i:], kinds
    gap = next(e for e in ins if e["event"] == "data_gap" and e["gap_s"] > 1.5)
    assert 2.0 <= gap["gap_s"] <= 6.0, gap
    assert f["start_host_ns"] - NS <= gap["last_host_ns"] <= f["start_host_ns"] + NS
    # the INS is read again after the replug, to the end of the run
    nav = [m.host_ns for m in iter_messages(fault_run.sessions[0], {"/ins/nav"})]
    end = fault_run.truth.window["end_host_ns"]
    after = [h for h in nav if f["end_host_ns"] + 6 * NS < h < end]
    assert len(after) >= 0.9 * 100 * (end - f["end_host_ns"] - 6 * NS) / NS  # 100 Hz again
    assert fault_run.daemon1_rc == -signal.SIGKILL  # it ran until the test killed it


def test_broker_restart_leaves_acquisition_unaffected_and_mqtt_reconnects(fault_run):
    r = fault_run
    lidar = np.array([m.host_ns for m in iter_messages(r.sessions[0], {"/lidar/raw"})], dtype=np.int64)
    around = lidar[(lidar > r.broker_killed_ns - NS) & (lidar < r.broker_back_ns + 3 * NS)]
    assert np.diff(around).max() < 0.1 * NS  # the profiler stream never paused
    # every datagram the emulator sent was received and logged, once
    assert len(lidar) == r.sim_stats["stats"]["datagrams_sent"]
    status = [m.payload for m in iter_messages(r.sessions[0], {"/status"})]
    assert all(s["log"]["dropped"] == 0 for s in status)
    mq = [s["mqtt"] for s in status]
    assert "disconnected" in mq and mq[-1] == "connected", mq
    # after the restart the broker (no persistence) got the retained topics again
    back = [m for m in r.mqtt.items if m.host_ns > r.broker_back_ns]
    topics = {m.topic.rsplit("/", 1)[-1] for m in back}
    assert {"status", "clock", "metrics", "checklist"} <= topics, topics
    metrics = [x.data for x in r.sock.topic("metrics") if x.host_ns < r.kill_ns][-1]
    assert metrics["mqtt"]["connects"] >= 2 and metrics["mqtt"]["connected"]


def test_sigkill_sends_the_last_will_and_the_restart_salvages_every_record(fault_run):
    r = fault_run
    will = [m for m in r.mqtt.topic("status") if m.data == {"state": "lost"}]
    assert will and will[0].host_ns - r.kill_ns < 5 * NS
    s1, s2 = r.sessions
    assert sorted(p.name for p in s1.glob("*.torn")) and (s1 / "session.json").exists()
    info = session_info(s1)
    assert all(seg.state == "complete" for seg in info.segments), info.segments
    assert len(info.segments) >= 3  # rotated every 20 s; only the last one was torn
    recovered = [seg for seg in info.segments if seg.recovery]
    assert len(recovered) == 1 and recovered[0].name == info.segments[-1].name
    for ch in info.channels.values():
        assert ch.missing == ch.duplicates == ch.backwards == 0, ch
    # every PPS pulse the emulator sent is in /pps exactly once
    sent = [e["sequence"] for e in r.sim_stats["pps"]["stats"]["edges"]]
    logged = [m.payload["sequence"] for m in iter_messages(s1, {"/pps"})]
    assert sorted(logged) == sent
    start = [m.payload for m in iter_messages(s2, {"/events"}) if m.payload["event"] == "session_start"]
    assert list(start[0]["salvaged"]) == [s1.name]


def test_sigterm_stops_cleanly_with_a_final_status_and_the_watchdog_pinged(fault_run):
    r = fault_run
    assert r.daemon2_rc == 0, r.daemon2_log[-2000:]
    assert "Traceback" not in r.daemon1_log and "Traceback" not in r.daemon2_log
    info = session_info(r.sessions[1])
    assert [s.state for s in info.segments] == ["complete"] and info.segments[0].end_reason == "shutdown"
    ends = [
        m.payload for m in iter_messages(r.sessions[1], {"/events"}) if m.payload["event"] == "session_end"
    ]
    assert ends and ends[0]["reason"] == "SIGTERM"
    assert r.sock.topic("status")[-1].data["state"] == "stopped"
    mq = [m.data for m in r.mqtt.topic("status")]
    assert mq[-1]["state"] == "stopped"  # published retained before a clean disconnect: no will
    assert r.notify.with_line("STOPPING=1")
    ready = r.notify.with_line("READY=1")
    pings = r.notify.with_line("WATCHDOG=1")
    first_run = [t for t in pings if ready[0] < t < r.kill_ns]
    assert len(first_run) >= 0.8 * (r.kill_ns - ready[0]) / NS  # every second (WatchdogSec 2 s)
