"""The doctor's broker check against a real mosquitto (plain and TLS, reachable, unreachable,
refused), the installed unit against the installed software (a staged tree), and the running
daemon's live view (a real status socket serving a snapshot, a lock naming a daemon)."""

from __future__ import annotations

import json
import os
import socket
import threading
from pathlib import Path

import pytest

from acquire.daemon.pidlock import lock_path_for
from acquire.doctor.broker import broker_check
from acquire.doctor.live import live_view
from acquire.doctor.result import Status
from acquire.doctor.unit import exec_start, unit_check
from acquire.status.bus import SNAPSHOT_END
from acquire.status.mqtt import MqttSettings, MqttTls
from tests.acquire.doctor.helpers import staged_install
from tests.mosquitto import Mosquitto, free_port, make_test_pki

# -- broker ----------------------------------------------------------------------------------------


def test_no_mqtt_section_is_skipped():
    assert broker_check(None).status == Status.SKIP


@pytest.mark.integration
def test_broker_reachable_and_unreachable(mosquitto):
    r = broker_check(MqttSettings(host=mosquitto.host, port=mosquitto.port))
    assert r.status == Status.OK and r.data["connect_ms"] > 0, r.message
    r = broker_check(MqttSettings(host="127.0.0.1", port=free_port()), timeout_s=2.0)
    assert r.status == Status.WARN and "unreachable" in r.message and "Connection refused" in r.message


@pytest.mark.integration
def test_broker_over_tls_verified_and_refused(tmp_path):
    pki = make_test_pki(tmp_path / "pki")
    broker = Mosquitto(tmp_path / "broker", tls=pki).start()
    try:
        good = MqttTls(ca_file=pki.ca, cert_file=pki.client_cert, key_file=pki.client_key)
        r = broker_check(MqttSettings(host="127.0.0.1", port=broker.port, tls=good))
        assert r.status == Status.OK and r.data["tls"] and "(TLS)" in r.message, r.message
        wrong_ca = MqttTls(ca_file=pki.other_ca, cert_file=pki.client_cert, key_file=pki.client_key)
        r = broker_check(MqttSettings(host="127.0.0.1", port=broker.port, tls=wrong_ca))
        assert r.status == Status.FAIL and "refused" in r.message and "CERTIFICATE" in r.message.upper(), (
            r.message
        )
    finally:
        broker.stop()


def test_tls_files_that_cannot_be_read(tmp_path):
    r = broker_check(MqttSettings(host="127.0.0.1", port=8883, tls=MqttTls(ca_file=tmp_path / "none.pem")))
    assert r.status == Status.FAIL and "TLS files" in r.message


# -- the installed unit ------------------------------------------------------------------------------


def test_the_unit_of_the_installed_software(tmp_path):
    staged_install(tmp_path)
    r = unit_check(tmp_path, "0.1.0", "/opt/marine-mls")
    assert r.status == Status.OK and r.data["installed_version"] == "0.1.0", r.message
    r = unit_check(tmp_path, "0.2.0", "/work/venv")
    assert r.status == Status.WARN and "this mls is 0.2.0" in r.message


def test_no_unit_installed(tmp_path):
    r = unit_check(tmp_path, "0.1.0", "/opt/marine-mls")
    assert r.status == Status.WARN and "not installed" in r.message and "install.py" in r.advice


def test_a_unit_whose_program_is_missing(tmp_path):
    staged_install(tmp_path)
    (tmp_path / "opt/marine-mls/bin/mls").unlink()
    r = unit_check(tmp_path, "0.1.0", "/opt/marine-mls")
    assert r.status == Status.FAIL and "does not exist" in r.message


def test_software_upgraded_without_the_installer(tmp_path):
    staged_install(tmp_path)
    site = tmp_path / "opt/marine-mls/lib/python3.11/site-packages"
    (site / "marine_mls-0.1.0.dist-info").rename(site / "marine_mls-0.2.0.dist-info")
    r = unit_check(tmp_path, "0.2.0", "/opt/marine-mls")
    assert r.status == Status.FAIL and "installed with marine-mls 0.1.0" in r.message and "0.2.0" in r.advice


def test_an_edited_unit_and_a_pending_daemon_reload(tmp_path):
    unit = staged_install(tmp_path)
    calls = []

    def run(cmd):
        calls.append(cmd)
        return 0, "NeedDaemonReload=yes\n"

    r = unit_check(tmp_path, "0.1.0", "/opt/marine-mls", run)
    assert r.status == Status.WARN and "daemon-reload" in r.advice and calls[0][0] == "systemctl"
    unit.write_text(unit.read_text() + "Nice=-5\n")
    r = unit_check(tmp_path, "0.1.0", "/opt/marine-mls")
    assert r.status == Status.WARN and "differs" in r.message and "drop-in" in r.advice


def test_a_unit_not_installed_by_the_installer(tmp_path):
    staged_install(tmp_path)
    (tmp_path / "opt/marine-mls/install-record.json").unlink()
    r = unit_check(tmp_path, "0.1.0", "/opt/marine-mls")
    assert r.status == Status.WARN and "no install record" in r.message


def test_exec_start():
    assert exec_start("[Service]\nExecStart=-/opt/x/bin/mls acquire\n") == Path("/opt/x/bin/mls")
    assert exec_start("[Service]\n") is None


# -- the running daemon's view ---------------------------------------------------------------------

SNAPSHOT = {
    "status": {
        "state": "running",
        "pid": 4242,
        "session": "20261204T223000Z_doctor-test",
        "clock": "LOCKED",
        "devices": {"ins": "connected", "profiler": "unavailable"},
        "log": {"free_mb": 120000.5},
        "mqtt": "connected",
        "alarms": [
            {"severity": "critical", "name": "device_unavailable", "device": "profiler", "message": "m"}
        ],
    },
    "clock": {"state": "LOCKED", "error_bound_us": 3.2},
    "checklist": {"presurvey": {"receive_buffer": {"ok": True, "detail": "profiler socket buffer 64.0 MiB"}}},
}


def serve_snapshot(path: Path, snapshot: dict) -> threading.Thread:
    """A status socket that gives one client the snapshot, as the daemon's does."""
    server = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    server.bind(str(path))
    server.listen(1)

    def run():
        conn, _ = server.accept()
        with conn, server:
            for topic, data in snapshot.items():
                conn.sendall(json.dumps({"topic": topic, "data": data}).encode() + b"\n")
            conn.sendall(json.dumps({"topic": SNAPSHOT_END, "data": {}}).encode() + b"\n")
            conn.recv(1)  # until the client closes

    th = threading.Thread(target=run, daemon=True)
    th.start()
    return th


def test_live_view_of_a_running_daemon(tmp_path):
    sock = tmp_path / "status.sock"
    th = serve_snapshot(sock, SNAPSHOT)
    live = live_view(sock)
    th.join(5)
    assert live["pid"] == 4242 and live["clock"] == "LOCKED" and live["log_free_mb"] == 120000.5
    assert live["devices"] == {"ins": "connected", "profiler": "unavailable"}
    assert live["alarms"][0]["name"] == "device_unavailable" and live["clock_error_bound_us"] == 3.2
    assert live["presurvey"]["receive_buffer"]["ok"] is True


def test_no_daemon_and_a_daemon_that_does_not_answer(tmp_path):
    sock = tmp_path / "status.sock"
    assert live_view(sock) is None
    lock_path_for(sock).write_text(json.dumps({"pid": os.getpid()}))
    live = live_view(sock, timeout_s=0.5)
    assert live["pid"] == os.getpid() and "does not answer" in live["error"]
    lock_path_for(sock).write_text(json.dumps({"pid": 2**22 + 12345}))  # beyond pid_max: gone
    assert live_view(sock, timeout_s=0.5) is None
