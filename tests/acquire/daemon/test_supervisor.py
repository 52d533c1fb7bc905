"""The supervisor in-process with small fake devices on a real pty, real UDP sockets and a
python-can virtual bus: what reaches the session, the status socket, sd_notify and the consumer
taps, and an orderly stop that leaves no task behind."""

from __future__ import annotations

import asyncio
import json
import socket
import subprocess
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from acquire.daemon.config import load_vessel_config
from acquire.daemon.supervisor import Supervisor
from acquire.log.read import iter_messages
from acquire.log.recover import session_info
from acquire.status.bus import read_snapshot
from drivers.can import parse_can_frame
from tests.acquire.daemon_util import MLS, ROOT, NotifyCollector, free_port
from tests.acquire.fakedevices import FakeDevices, devices_yaml
from tests.waiting import wait_until_async

pytestmark = [pytest.mark.realtime, pytest.mark.integration, pytest.mark.xdist_group("daemon-fake")]
NS = 1_000_000_000


def _gps_now_ns() -> int:
    """Now in GPS time, 0.3 s past a whole second (NMEA TIME__ before the first ZDA is dated
    from the host's clock, as the INS would be on the vessel)."""
    from acquire.timing.timekeeper import coarse_gps_offset_ns

    return (time.monotonic_ns() + coarse_gps_offset_ns()) // NS * NS + 300_000_000


def _config(tmp: Path, prof: int, pps: int, extra: str = "") -> Path:
    cfg = tmp / "vessel.yaml"
    cfg.write_text(
        "vessel: fake-1\ndevices:\n"
        + devices_yaml(tmp, prof, pps)
        + textwrap.dedent(f"""\
          - name: marks
            kind: can
            transport: {{type: can, interface: virtual, channel: mls-test-{prof}}}
        session: {{directory: sessions, flush_s: 0.2}}
        status: {{socket: status.sock, period_s: 0.5}}
        mount: {{lever_arm_m: [0.1, 0.2, -1.0], nominal_deg: [0, 0, 90], boresight_apriori_deg: [0, 0, 0]}}
        """)
        + extra
    )
    return cfg


class Recorder:
    """A consumer that keeps what its tap delivers and publishes a checklist section."""

    name = "recorder"

    def __init__(self):
        self.items: list[tuple[str, object, int]] = []

    async def run(self, tap, checklist):
        async for kind, rec, gps_ns in tap:
            self.items.append((kind, rec, gps_ns))
            navs = sum(1 for k, _, _ in self.items if k == "nav")
            if navs % 10 == 1:
                checklist.publish("guidance", {"navs_seen": navs})


class Crasher:
    name = "crasher"
    kinds = ("event",)

    def __init__(self):
        self.runs = 0

    async def run(self, tap, checklist):
        self.runs += 1
        await tap.get()
        raise RuntimeError("guidance bug")


@pytest.fixture(scope="session")  # runs once per worker, whatever the test order
def fake_run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("fakerun")
    prof, pps = free_port(), free_port()
    cfg = load_vessel_config(_config(tmp, prof, pps))
    notify = NotifyCollector(tmp / "notify.sock")
    notify.start()
    rec, crash = Recorder(), Crasher()
    fake = FakeDevices(tmp / "ins", prof, pps, seconds=6.0, gps0_ns=_gps_now_ns())

    def marker(kind, pass_id, seq):
        def send():
            import can

            from drivers.can import event_marker_message

            with can.Bus(interface="virtual", channel=f"mls-test-{prof}") as bus:
                bus.send(event_marker_message(kind, pass_id, seq))

        return send

    fake.hooks += [(1.0, marker("pass_start", 3, 1)), (5.0, marker("pass_end", 3, 2))]
    out = {}

    async def scenario():
        sup = Supervisor(
            cfg,
            consumers=[rec, crash],
            env={"NOTIFY_SOCKET": str(tmp / "notify.sock"), "WATCHDOG_USEC": "1000000"},
        )
        task = asyncio.create_task(sup.run())
        await wait_until_async(lambda: notify.with_line("READY=1") or task.done(), 30, "READY=1")
        assert not task.done(), task
        fake.start()
        await asyncio.to_thread(fake.join, 30)

        async def everything_handled():
            """A status snapshot published after the daemon handled all the fakes sent: every
            profile and INS epoch, the CAN markers through the taps."""
            kinds = [k for k, _, _ in rec.items]
            if kinds.count("nav") < len(fake.epochs) or kinds.count("profile") < len(fake.datagrams) // 3:
                return None
            if sum(k == "event" and r["event"] == "pass_end" for k, r, _ in rec.items) < 1:
                return None
            snap = await asyncio.to_thread(read_snapshot, cfg.status.socket)
            return snap if snap["sensors/profiler"]["records"] == len(fake.datagrams) // 3 else None

        out["snapshot"] = await wait_until_async(
            everything_handled, 30, "the daemon to handle what the fake devices sent", interval_s=0.05
        )
        out["health"] = sup.drivers_health()
        sup.request_stop("test")
        out["rc"] = await task
        out["left"] = [t for t in asyncio.all_tasks() if t is not asyncio.current_task()]
        out["sup"] = sup

    try:
        asyncio.run(scenario())
    finally:
        fake.close()
        notify.stop()
    session = out["sup"].writer.session_dir
    return {
        **out,
        "tmp": tmp,
        "cfg": cfg,
        "fake": fake,
        "notify": notify,
        "recorder": rec,
        "crasher": crash,
        "session": session,
    }


def test_raw_channels_keep_the_exact_bytes_and_the_session_closes_complete(fake_run):
    s, fake = fake_run["session"], fake_run["fake"]
    ins = b"".join(m.payload for m in iter_messages(s, {"/ins/raw"}))
    assert ins == bytes(fake.ins_bytes)
    lidar = [m.payload for m in iter_messages(s, {"/lidar/raw"})]
    assert lidar == fake.datagrams
    info = session_info(s)
    assert [seg.state for seg in info.segments] == ["complete"]
    assert all(c.missing == c.duplicates == 0 for c in info.channels.values())
    assert (s / "vessel.yaml").read_bytes() == Path(fake_run["cfg"].source).read_bytes()
    assert fake_run["rc"] == 0 and fake_run["left"] == []
    assert not fake_run["cfg"].status.socket.exists()


def test_nav_records_take_the_ins_time_tag_and_the_clock_locks_on_labelled_pulses(fake_run):
    s, fake = fake_run["session"], fake_run["fake"]
    nav = [m for m in iter_messages(s, {"/ins/nav"})]
    assert [m.payload["time_gps_ns"] for m in nav] == fake.epochs
    assert {m.payload["time_source"] for m in nav} == {"device"}
    assert all(m.publish_time_ns == m.payload["time_gps_ns"] for m in nav)
    assert abs(nav[0].payload["roll_deg"] - np.degrees(0.01)) < 1e-3  # canonical, degrees at the edge
    pps = [m.payload for m in iter_messages(s, {"/pps"})]
    labelled = [p for p in pps if p["gps_s"] is not None]
    assert [p["gps_s"] for p in labelled] == [g for g, _ in fake.pulses][-len(labelled) :]
    assert len(labelled) >= len(fake.pulses) - 1 and all(p["accepted"] for p in labelled)
    clock = fake_run["snapshot"]["clock"]
    assert clock["edges_accepted"] == len(labelled)
    # the fake devices share the truth clock GPS = gps0 + host − start: the model finds it
    locked = [m for m in iter_messages(s, {"/lidar/raw"}) if m.clock == "LOCKED"]
    err = np.array([m.log_time_ns - fake.gps(m.host_ns) for m in locked])
    assert len(locked) > 50 and np.abs(err).max() < 200_000  # < 0.2 ms: the host's own jitter


def test_can_markers_become_pass_events_and_raw_frames(fake_run):
    s = fake_run["session"]
    frames = [parse_can_frame(m.payload) for m in iter_messages(s, {"/can/marks"})]
    assert [(i, len(d)) for i, d, _ in frames] == [(0x6E0, 8), (0x6E0, 8)]
    ev = [
        m.payload for m in iter_messages(s, {"/events"}) if m.payload["event"] in ("pass_start", "pass_end")
    ]
    assert [(e["event"], e["pass_id"], e["source"]) for e in ev] == [
        ("pass_start", 3, "can:marks"),
        ("pass_end", 3, "can:marks"),
    ]


def test_status_socket_notify_and_checklist(fake_run):
    snap = fake_run["snapshot"]
    st = snap["status"]
    assert st["state"] == "running" and st["vessel"] == "fake-1" and st["clock"] == "LOCKED"
    assert st["devices"] == {
        "ins": "connected",
        "profiler": "connected",
        "pps": "connected",
        "marks": "connected",
    }
    assert snap["sensors/profiler"]["records"] == len(fake_run["fake"].datagrams) // 3
    ins = snap["sensors/ins"]
    assert ins["pps_flag"] is True
    # in sync; or, after a change of latency level (a loaded machine's late sender at the end of
    # the run), waiting for three samples at the new level — with the change alarmed, not silent
    relevel = {a["name"] for a in st["alarms"] if a["device"] == "ins"} & {"latency_jump", "time_step"}
    assert ins["sync"] == "ok" or (ins["sync"] == "waiting" and relevel), (ins, st["alarms"])
    check = snap["checklist"]
    assert check["presurvey"]["clock_locked"]["ok"] and check["presurvey"]["ins_navigating"]["ok"]
    assert check["presurvey"]["mount_configured"]["ok"]
    assert check["guidance"]["navs_seen"] >= 250
    assert fake_run["health"] == (True, "4/4 device tasks alive")
    n = fake_run["notify"]
    ready, stopping = n.with_line("READY=1"), n.with_line("STOPPING=1")
    pings = n.with_line("WATCHDOG=1")
    assert len(ready) == 1 and len(stopping) == 1
    assert len([t for t in pings if ready[0] < t < stopping[0]]) >= 6  # every 0.5 s


def test_consumers_get_the_records_and_a_failing_one_is_restarted_with_an_alarm(fake_run):
    items = fake_run["recorder"].items
    navs = [r for k, r, _ in items if k == "nav"]
    profiles = [(r, g) for k, r, g in items if k == "profile"]
    assert len(navs) == len(fake_run["fake"].epochs)
    assert len(profiles) == len(fake_run["fake"].datagrams) // 3
    assert all(g == int(p.gps_ns[0]) for p, g in profiles)
    assert any(k == "event" and r["event"] == "pass_start" for k, r, _ in items)
    assert fake_run["crasher"].runs >= 2
    ev = [m.payload for m in iter_messages(fake_run["session"], {"/events"})]
    failed = [e for e in ev if e["event"] == "consumer_failed"]
    assert failed and "guidance bug" in failed[0]["error"]
    assert any(e["event"] == "alarm" and e["name"] == "consumer_failed" for e in ev)


def _mls(*args, cwd=None) -> subprocess.CompletedProcess:
    return subprocess.run([*MLS, *args], capture_output=True, text=True, cwd=cwd or ROOT, timeout=60)


def test_invalid_config_prints_one_error_per_line_and_exits_2(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text(
        textwrap.dedent("""\
        vessel: "bad name"
        devices:
          - {name: ins, kind: ins, protocol: nmea, transport: {type: serial, port: dev/ttyS0, baud: 11520}}
          - {name: p, kind: pps, source: {type: udp, host: 127.0.0.1, port: 70000}, time_device: gnss}
        session: {directory: /tmp/x, flush_s: 2}
        colour: blue
        """)
    )
    r = _mls("acquire", "--config", str(bad))
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    errors = [ln for ln in lines if ln.startswith(f"{bad}:")]
    assert len(errors) == 7, lines
    for what in ("vessel", "port", "baud", "70000", "time_device", "flush_s", "colour"):
        assert sum(what in e for e in errors) >= 1, (what, errors)
    assert lines[-1] == f"mls acquire: {bad}: 7 errors in the vessel config"


def test_check_mode_and_a_second_ins_is_refused(tmp_path):
    cfg = _config(tmp_path, 45001, 45002)
    r = _mls("acquire", "--config", str(cfg), "--check")
    assert r.returncode == 0, r.stderr
    assert "profiler" in r.stdout and "udp 127.0.0.1:45001" in r.stdout
    two = cfg.read_text().replace(
        "devices:\n",
        "devices:\n  - {name: ins2, kind: ins, protocol: nmea, "
        "transport: {type: udp, host: 127.0.0.1, port: 45003}}\n",
    )
    cfg.write_text(two)
    r = _mls("acquire", "--config", str(cfg))
    # refused when the config is read, at the second one's line, naming the first's
    assert (
        r.returncode == 2 and "devices[1]: a second ins device ('ins'; the first, 'ins2', at " in r.stderr
    ), r.stderr


def test_a_status_socket_in_use_is_a_start_failure_that_leaves_it_and_no_session(tmp_path):
    cfg = _config(tmp_path, free_port(), free_port())
    busy = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    busy.bind(str(tmp_path / "status.sock"))
    busy.listen(1)
    try:
        r = _mls("acquire", "--config", str(cfg), cwd=tmp_path)
        assert (tmp_path / "status.sock").is_socket()  # another's socket: not unlinked
    finally:
        busy.close()
    assert r.returncode == 1
    assert "cannot start: status socket" in r.stderr and "another daemon" in r.stderr
    assert not (tmp_path / "sessions").exists() or not any((tmp_path / "sessions").iterdir())


def test_an_absent_device_alarms_and_a_driver_bug_withholds_the_watchdog(tmp_path):
    cfg = tmp_path / "vessel.yaml"
    cfg.write_text(
        textwrap.dedent(f"""\
        vessel: wd
        devices:
          - {{name: ins, kind: ins, protocol: nmea, transport: {{type: udp, host: 127.0.0.1, port: {free_port()}}}}}
          - {{name: pps, kind: pps, source: {{type: kernel, device: {tmp_path}/pps9}}, time_device: ins}}
        session: {{directory: sessions}}
        status: {{socket: status.sock}}
        """)
    )
    notify = NotifyCollector(tmp_path / "notify.sock")
    notify.start()
    out = {}

    async def scenario():
        sup = Supervisor(
            load_vessel_config(cfg),
            env={"NOTIFY_SOCKET": str(tmp_path / "notify.sock"), "WATCHDOG_USEC": "400000"},
        )
        ins = sup.devices["ins"]
        bug = asyncio.Event()

        async def buggy_run():
            await bug.wait()
            raise ZeroDivisionError("division by zero in a driver")

        ins.run = buggy_run
        task = asyncio.create_task(sup.run())
        await wait_until_async(  # a few watchdog rounds (every 0.2 s) with the devices up
            lambda: len(notify.with_line("WATCHDOG=1")) >= 3 or task.done(), 30, "3 watchdog pings"
        )
        assert not task.done(), task
        rounds: list[bool] = []  # the watchdog's rounds from here on: healthy (pinged) or not
        beat = sup.watchdog.beat
        sup.watchdog.beat = lambda: rounds.append(beat()) or rounds[-1]
        out["before"] = (
            sup.drivers_health(),
            sup.status_doc()["devices"],
            len(notify.with_line("WATCHDOG=1")),
        )
        bug.set()
        await wait_until_async(lambda: not sup.drivers_health()[0], 10, "the driver failure")
        out["during"] = (sup.drivers_health(), sup.status_doc()["devices"]["ins"])
        n, k = len(notify.with_line("WATCHDOG=1")), len(rounds)
        # two watchdog rounds while it stays failed (re-opened after 0.5 s, it fails again
        # at once: the driver is never healthy in between): no ping in them
        await wait_until_async(lambda: len(rounds) >= k + 2, 10, "two watchdog rounds")
        out["rounds_while_failed"] = rounds[k:]
        out["pings_while_failed"] = len(notify.with_line("WATCHDOG=1")) - n
        out["alarms"] = {(a.name, a.device) for a in sup.alarms.active()}
        sup.request_stop("test")
        out["rc"] = await task

    try:
        asyncio.run(scenario())
    finally:
        notify.stop()
    (ok, why), devices, pings = out["before"]
    assert ok and devices == {"ins": "connected", "pps": "unavailable"} and pings >= 3
    (ok, why), state = out["during"]
    assert not ok and "ZeroDivisionError: division by zero in a driver" in why and state == "failed"
    assert out["pings_while_failed"] == 0 and out["rounds_while_failed"] == [False] * len(
        out["rounds_while_failed"]
    )
    assert any("unhealthy: drivers: ins: ZeroDivisionError" in m for _, m in notify.messages)
    assert {("driver_failed", "ins"), ("device_unavailable", "pps")} <= out["alarms"]
    assert out["rc"] == 0


def test_mqtt_commands_mark_passes_in_events_and_rotate_the_segment(tmp_path, mosquitto):
    import aiomqtt

    cfg = tmp_path / "vessel.yaml"
    cfg.write_text(
        textwrap.dedent(f"""\
        vessel: cmd-1
        devices:
          - {{name: ins, kind: ins, protocol: nmea, transport: {{type: udp, host: 127.0.0.1, port: {free_port()}}}}}
        session: {{directory: sessions}}
        status: {{socket: status.sock}}
        mqtt: {{host: 127.0.0.1, port: {mosquitto.port}, topic_prefix: cmdtest, commands_enabled: true}}
        """)
    )
    results = []

    async def scenario():
        sup = Supervisor(load_vessel_config(cfg))
        task = asyncio.create_task(sup.run())
        async with aiomqtt.Client(mosquitto.host, mosquitto.port) as c:
            await c.subscribe("cmdtest/cmd-1/#", qos=1)
            await wait_until_async(
                lambda: sup.mqtt and sup.mqtt.connected and sup.mqtt.subscribed,
                20,
                "the daemon's MQTT commands",
            )
            for name, args in (
                ("pass_start", {"pass_id": 2, "id": 7}),
                ("mark", {"text": "buoy 4"}),
                ("rotate", {}),
                ("pass_end", {"pass_id": "2"}),
            ):
                await c.publish(f"cmdtest/cmd-1/cmd/{name}", json.dumps(args), qos=1)
            async for m in c.messages:
                if str(m.topic).endswith("cmd/result"):
                    results.append(json.loads(m.payload))
                    if len(results) == 4:
                        break
        sup.request_stop("test")
        await task
        return sup.writer.session_dir

    session = asyncio.run(asyncio.wait_for(scenario(), 30))
    assert [r["ok"] for r in results] == [True, True, True, False]
    assert results[0]["id"] == 7 and "pass 2 logged at GPS" in results[0]["message"]
    assert "argument 'pass_id' must be int" in results[3]["message"]
    ev = [m.payload for m in iter_messages(session, {"/events"})]
    marks = [
        (e["event"], e.get("pass_id"), e.get("text"), e["source"])
        for e in ev
        if e["event"] in ("pass_start", "mark", "rotate", "pass_end")
    ]
    assert marks == [
        ("pass_start", 2, None, "mqtt"),
        ("mark", None, "buoy 4", "mqtt"),
        ("rotate", None, None, "mqtt"),
    ]
    assert len(session_info(session).segments) == 2  # the rotate command opened a new segment
