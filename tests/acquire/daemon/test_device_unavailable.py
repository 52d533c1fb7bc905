"""A device that cannot be opened is an alarm, not a silence: ``mls acquire`` (its own process,
with a ``NOTIFY_SOCKET``, MQTT on a real mosquitto and the guidance of the example site) starts
with an INS serial path that does not exist and a profiler UDP port already bound by another
socket. Both are the critical alarm ``device_unavailable`` from start-up, with the OS error, on
the status socket, in ``mls status`` (exit 2), on MQTT, in the checklist's pre-checks and in
the sd_notify ``STATUS=`` line (the watchdog keeps pinging: a restart brings no device back);
``data_gap`` fires for devices that never delivered anything. Then the pty appears and the port
is freed: the same daemon, never restarted, reads both devices and the critical alarms clear.
One module fixture runs it; the tests below each check one aspect."""

from __future__ import annotations

import json
import signal
import socket
import subprocess
import textwrap
import time
from pathlib import Path

import pytest

from acquire.log.read import iter_messages
from acquire.status.bus import read_snapshot
from acquire.timing.timekeeper import coarse_gps_offset_ns
from tests.acquire.daemon_util import (
    MLS,
    ROOT,
    MqttCollector,
    NotifyCollector,
    Proc,
    free_port,
    wait_until,
)
from tests.acquire.fakedevices import FakeDevices

pytestmark = [pytest.mark.integration, pytest.mark.xdist_group("daemon-unavailable")]
NS = 1_000_000_000
PREFIX = "unavail"


def _vessel_yaml(tmp: Path, ins: Path, prof: int, broker: int, site: Path) -> str:
    return textwrap.dedent(f"""\
        vessel: unavail-1
        devices:
          - {{name: ins, kind: ins, protocol: nmea, transport: {{type: serial, port: {ins}, baud: 115200}},
             latency: {{band_ms: [0.0, 20.0], rate_hz: 50.0, gap_s: 1.0}}}}
          - {{name: profiler, kind: profiler, protocol: zfp1, transport: {{type: udp, host: 127.0.0.1, port: {prof}}},
             latency: {{band_ms: [0.0, 60.0], rate_hz: 20.0, gap_s: 1.0}}}}
        session: {{directory: {tmp}/sessions, flush_s: 0.2}}
        status: {{socket: {tmp}/status.sock, period_s: 0.25}}
        mqtt: {{host: 127.0.0.1, port: {broker}, topic_prefix: {PREFIX}}}
        mount: {{lever_arm_m: [0.42, -0.31, -1.85], nominal_deg: [0, 0, 0], boresight_apriori_deg: [0, 0, 0]}}
        site_file: {site}
        guidance: {{period_s: 0.25}}
        """)


def _mls_status(sock: Path) -> tuple[int, dict]:
    r = subprocess.run(
        [*MLS, "status", "--socket", str(sock), "--json"],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=60,
    )
    return r.returncode, json.loads(r.stdout)


def _alarms(snap: dict, name: str) -> dict[str, dict]:
    return {a["device"]: a for a in snap.get("status", {}).get("alarms", []) if a["name"] == name}


def _snapshot(sock: Path) -> dict:
    try:
        return read_snapshot(sock, 3.0)
    except (OSError, ValueError):
        return {}


@pytest.fixture(scope="module")
def run(tmp_path_factory, mosquitto, example_bundle) -> dict:
    tmp = tmp_path_factory.mktemp("unavailable")
    ins = tmp / "ins"  # no such path yet
    blocker = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)  # another process holds the port
    blocker.bind(("127.0.0.1", 0))
    prof = blocker.getsockname()[1]
    cfg = tmp / "vessel.yaml"
    cfg.write_text(_vessel_yaml(tmp, ins, prof, mosquitto.port, example_bundle / "site.yaml"))
    sock = tmp / "status.sock"
    notify = NotifyCollector(tmp / "notify.sock")
    notify.start()
    mqtt = MqttCollector(mosquitto.host, mosquitto.port, f"{PREFIX}/#").start()
    env = {"NOTIFY_SOCKET": str(tmp / "notify.sock"), "WATCHDOG_USEC": "1000000"}
    fake = None
    out: dict = {"tmp": tmp, "ins": ins, "prof": prof, "notify": notify, "mqtt": mqtt}
    daemon = Proc([*MLS, "acquire", "--config", str(cfg)], tmp / "daemon.log", env)
    try:
        wait_until(lambda: notify.with_line("READY=1"), 60, "READY=1 from the daemon", daemon)
        out["ready_ns"] = notify.with_line("READY=1")[0]
        out["first_snapshot"] = _snapshot(sock)

        def down() -> bool:
            snap = _snapshot(sock)
            guidance = snap.get("checklist", {}).get("guidance") or {}
            return (
                set(_alarms(snap, "device_unavailable")) == {"ins", "profiler"}
                and set(_alarms(snap, "data_gap")) == {"ins", "profiler"}
                and bool(guidance.get("prechecks"))
            )

        wait_until(down, 30, "device_unavailable and data_gap of both devices", daemon)
        out["down_seen_ns"] = seen = time.monotonic_ns()
        wait_until(  # a few watchdog periods while the devices are missing
            lambda: len([t for t in notify.with_line("WATCHDOG=1") if t > seen]) >= 3,
            30,
            "3 watchdog pings with both devices missing",
            daemon,
        )
        out["down_rc"], out["down"] = _mls_status(sock)
        out["down_ns"] = time.monotonic_ns()
        # the port is freed, the INS appears: the same daemon picks both up
        blocker.close()
        gps0 = (time.monotonic_ns() + coarse_gps_offset_ns()) // NS * NS + 300_000_000
        fake = FakeDevices(ins, prof, free_port(), seconds=12.0, gps0_ns=gps0)
        out["plugged_ns"] = time.monotonic_ns()
        fake.start()

        def up() -> bool:
            snap = _snapshot(sock)
            st = snap.get("status", {})
            return (
                st.get("devices") == {"ins": "connected", "profiler": "connected"}
                and not [a for a in st.get("alarms", []) if a["severity"] == "critical"]
                and snap.get("sensors/ins", {}).get("records", 0) > 0
                and snap.get("sensors/profiler", {}).get("records", 0) > 0
            )

        wait_until(up, 12, "both devices read and every alarm cleared", daemon)
        out["up_ns"] = up_ns = time.monotonic_ns()

        def recovered() -> bool:
            """The recovery told (a status on MQTT since, systemd's STATUS=running) and the data
            the checks count handled: more than 50 INS epochs and 50 profiler datagrams."""
            snap = _snapshot(sock)
            return (
                any(
                    isinstance(m.data, dict) and "alarms" in m.data and m.host_ns > up_ns
                    for m in mqtt.topic("status")
                )
                and any(t > out["plugged_ns"] and m == "STATUS=running" for t, m in notify.messages)
                and snap.get("sensors/ins", {}).get("records", 0) > 50
                and 3 * snap.get("sensors/profiler", {}).get("records", 0) > 50  # 3 datagrams a profile
            )

        wait_until(recovered, 30, "the recovery told and data flowing", daemon)
        out["up_rc"], out["up"] = _mls_status(sock)
        out["up_until_ns"] = time.monotonic_ns()
        out["alive"] = daemon.alive()
        daemon.signal(signal.SIGTERM)
        out["rc"] = daemon.wait(30)
    finally:
        blocker.close()
        daemon.kill()
        if fake is not None:
            fake.join(20)
            fake.close()
        notify.stop()
        mqtt.stop()
    out["log"] = daemon.output()
    out["sessions"] = sorted(p for p in (tmp / "sessions").iterdir() if p.is_dir())
    return out


def test_both_devices_are_critical_alarms_with_the_os_error_from_start_up(run):
    ins = run["ins"]
    first = _alarms(run["first_snapshot"], "device_unavailable")
    assert set(first) == {"ins", "profiler"}, run["first_snapshot"].get("status")
    assert all(a["first_host_ns"] <= run["ready_ns"] for a in first.values())  # before READY=1
    snap = run["down"]
    alarms = _alarms(snap, "device_unavailable")
    assert {a["severity"] for a in alarms.values()} == {"critical"}
    assert f"No such file or directory: '{ins}'" in alarms["ins"]["message"], alarms["ins"]
    assert "[Errno 98] Address already in use" in alarms["profiler"]["message"], alarms["profiler"]
    assert alarms["profiler"]["message"].startswith("profiler (profiler) not connected")
    st = snap["status"]
    assert st["state"] == "running" and st["devices"] == {"ins": "unavailable", "profiler": "unavailable"}
    assert "Address already in use" in snap["sensors/profiler"]["error"]
    assert snap["sensors/ins"]["records"] == snap["sensors/profiler"]["records"] == 0
    gaps = _alarms(snap, "data_gap")
    assert {a["severity"] for a in gaps.values()} == {"critical"}
    assert all("none since start" in a["message"] for a in gaps.values()), gaps
    assert run["down_rc"] == 2


def test_the_checklist_prechecks_name_each_device_and_its_error(run):
    ins = run["ins"]
    check = run["down"]["checklist"]
    pre = check["presurvey"]["devices_connected"]
    guided = {c["name"]: c for c in check["guidance"]["prechecks"]}["devices_connected"]
    for c in (pre, guided):
        assert c["ok"] is False
        assert f"ins: [Errno 2] could not open port {ins}" in c["detail"], c
        assert "profiler: [Errno 98] Address already in use" in c["detail"], c
    assert check["guidance"]["prechecks_ok"] is False
    up = run["up"]["checklist"]
    assert up["presurvey"]["devices_connected"] == {"ok": True, "detail": "2 devices connected"}
    guided = {c["name"]: c for c in up["guidance"]["prechecks"]}["devices_connected"]
    assert guided["ok"] is True


def test_mqtt_carries_the_raise_and_the_clear(run):
    mq = run["mqtt"]
    alarms = [m for m in mq.topic("alarms") if m.data.get("name") == "device_unavailable"]
    by = {(m.data["device"], m.data["action"]): m for m in alarms}
    assert {("ins", "raise"), ("profiler", "raise"), ("ins", "clear"), ("profiler", "clear")} <= set(by)
    assert "[Errno 98] Address already in use" in by[("profiler", "raise")].data["message"]
    for dev in ("ins", "profiler"):
        assert by[(dev, "clear")].host_ns > run["plugged_ns"]
        assert by[(dev, "clear")].data["message"] == f"{dev} connected"
    status = [m for m in mq.topic("status") if isinstance(m.data, dict) and "alarms" in m.data]
    down = [m.data for m in status if m.host_ns < run["down_ns"]]
    assert down and {a["device"] for a in down[-1]["alarms"] if a["name"] == "device_unavailable"} == {
        "ins",
        "profiler",
    }
    up = [m.data for m in status if run["up_ns"] < m.host_ns < run["up_until_ns"]]
    assert up and all(a["severity"] != "critical" for s in up for a in s["alarms"])


def test_systemd_status_names_the_devices_and_the_watchdog_keeps_pinging(run):
    n = run["notify"]
    ins = run["ins"]
    texts = [m for _, m in n.messages if m.startswith("STATUS=running, degraded: devices: ")]
    assert any(
        f"ins not connected: [Errno 2] could not open port {ins}" in t
        and "profiler not connected: [Errno 98] Address already in use" in t
        for t in texts
    ), n.messages
    ready = run["ready_ns"]
    # never withheld while the devices were missing: no round found the daemon unhealthy, and
    # the pings went on once both were known missing
    assert not [m for t, m in n.messages if ready < t < run["down_ns"] and m.startswith("STATUS=unhealthy")]
    pings_down = [t for t in n.with_line("WATCHDOG=1") if run["down_seen_ns"] < t < run["down_ns"]]
    assert len(pings_down) >= 3
    assert [t for t, m in n.messages if m == "STATUS=running" and t > run["plugged_ns"]]
    assert len(n.with_line("READY=1")) == 1  # one start: never restarted


def test_the_devices_recover_without_a_restart(run):
    assert run["alive"] and run["rc"] == 0, run["log"][-3000:]
    assert "Traceback" not in run["log"]
    snap = run["up"]
    assert run["up_rc"] == 0, snap.get("status")
    assert snap["status"]["devices"] == {"ins": "connected", "profiler": "connected"}
    assert "error" not in snap["sensors/ins"] and "error" not in snap["sensors/profiler"]
    (session,) = run["sessions"]
    ins = [m.host_ns for m in iter_messages(session, {"/ins/nav"})]
    lidar = [m.host_ns for m in iter_messages(session, {"/lidar/raw"})]
    assert len(ins) > 50 and len(lidar) > 50
    assert min(ins) > run["plugged_ns"] and min(lidar) > run["plugged_ns"]
    ev = [m.payload for m in iter_messages(session, {"/events"})]
    unavailable = [e for e in ev if e["event"] == "alarm" and e["name"] == "device_unavailable"]
    assert {(e["device"], e["action"]) for e in unavailable} == {
        ("ins", "raise"),
        ("profiler", "raise"),
        ("ins", "clear"),
        ("profiler", "clear"),
    }
