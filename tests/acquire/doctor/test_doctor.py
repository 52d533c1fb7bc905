"""``mls doctor`` end to end: every check of a vessel config in order, with the seams where the
machine cannot play the part (the clock tools, the free space, the kernel's rmem_max file, the
date), ``mls acquire --check`` run for real, the exit status 0 / 1 / 2, the text and the JSON
report (every field of docs/doctor.md present, nothing undocumented)."""

from __future__ import annotations

import datetime as _dt
import json
import re
import socket
import threading
import time
from pathlib import Path

import pytest
from typer.testing import CliRunner

from acquire.doctor.result import EXIT_NOT_READY, EXIT_READY, EXIT_WARNINGS, Status
from acquire.doctor.run import DoctorOptions, DoctorSeams, run_doctor
from calib.core.gpstime import BUILTIN
from cli.commands.doctor_cmd import run_acquire_check
from drivers.pps import encode_pps_datagram
from tests.acquire.doctor.helpers import free_udp_port, staged_install, vessel_yaml
from tests.acquire.doctor.test_device_checks import ME
from tests.acquire.doctor.test_host_checks import TRACKING, runner
from tests.conftest import PROJECT_ROOT

DOC = PROJECT_ROOT / "docs" / "doctor.md"
CHRONY_OK = TRACKING.format(offset="0.000004000", side="fast", leap="Normal")


class PpsEmulator:
    """PPS1 datagrams on a UDP port, host stamps one second apart, until stopped."""

    def __init__(self, port: int):
        self.port, self.done = port, threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)

    def _run(self):
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            seq, t0 = 0, time.monotonic_ns()
            while not self.done.wait(0.01):
                seq += 1
                s.sendto(encode_pps_datagram(seq, t0 + seq * 1_000_000_000), ("127.0.0.1", self.port))

    def __enter__(self):
        self.thread.start()
        return self

    def __exit__(self, *exc):
        self.done.set()
        self.thread.join(5)


def ready_machine(tmp_path: Path, **changes) -> DoctorSeams:
    tmp_path.mkdir(exist_ok=True)
    rmem = tmp_path / "rmem_max"
    rmem.write_text("33554432\n")
    root = tmp_path / "root"
    staged_install(root)
    kw = dict(
        run=runner({"chronyc": (0, CHRONY_OK)}),
        rmem_max_path=rmem,
        free_bytes=lambda path: 2**40,
        user=ME,
        leap_list=tmp_path / "no-leap-list",
        root=root,
        today=lambda: BUILTIN.expires - _dt.timedelta(days=100),
        systemd=False,
    )
    kw.update(changes)
    return DoctorSeams(**kw)


def options(path: Path, **kw) -> DoctorOptions:
    return DoctorOptions(config=path, software_version="0.1.0", software_prefix="/opt/marine-mls", **kw)


@pytest.mark.integration
def test_a_ready_vessel_pc_then_one_thing_wrong(tmp_path):
    port = free_udp_port()
    path = vessel_yaml(tmp_path, pps=f"{{type: udp, host: 127.0.0.1, port: {port}}}")
    with PpsEmulator(port):
        report = run_doctor(options(path), run_acquire_check(path), ready_machine(tmp_path))
    names = [(r.name, r.status) for r in report.checks]
    assert names == [
        ("config", Status.OK),
        ("ports", Status.OK),
        ("pps", Status.OK),
        ("clock", Status.OK),
        ("udp_buffer", Status.OK),
        ("disk", Status.OK),
        ("broker", Status.SKIP),
        ("leap_table", Status.OK),
        ("unit", Status.OK),
    ], [r.message for r in report.checks]
    assert report.exit_code == EXIT_READY and report.live is None

    small = tmp_path / "rmem_small"
    small.write_text("4194304\n")
    with PpsEmulator(port):
        report = run_doctor(
            options(path), run_acquire_check(path), ready_machine(tmp_path / "w", rmem_max_path=small)
        )
    assert [r.name for r in report.checks if r.status != Status.OK] == ["udp_buffer", "broker"]
    assert report.exit_code == EXIT_WARNINGS
    seams = ready_machine(tmp_path / "f", free_bytes=lambda path: 2**30)
    report = run_doctor(options(path, pps_wait_s=0.3), run_acquire_check(path), seams)
    failed = {r.name for r in report.checks if r.status == Status.FAIL}
    assert failed == {"pps", "disk"} and report.exit_code == EXIT_NOT_READY


@pytest.mark.integration
def test_a_taken_port_and_an_invalid_config(tmp_path):
    port = free_udp_port()
    path = vessel_yaml(tmp_path, pps=f"{{type: udp, host: 127.0.0.1, port: {port}}}")
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as other:
        other.bind(("127.0.0.1", port))
        check = run_acquire_check(path)
    assert check.exit_code == 1 and any("cannot bind udp 127.0.0.1" in e for e in check.errors)
    report = run_doctor(options(path, pps_wait_s=0.3), check, ready_machine(tmp_path))
    ports = next(r for r in report.checks if r.name == "ports")
    assert ports.status == Status.FAIL and f":{port}" in ports.message

    path.write_text(path.read_text().replace("kind: profiler", "kind: scanner"))
    check = run_acquire_check(path)
    assert check.exit_code == 2
    report = run_doctor(options(path), check, ready_machine(tmp_path / "x"))
    by = {r.name: r for r in report.checks}
    assert by["config"].status == Status.FAIL and any("scanner" in e for e in by["config"].data["errors"])
    assert all(by[n].status == Status.SKIP for n in ("ports", "serial", "pps", "disk", "broker"))
    assert by["udp_buffer"].status == Status.OK and report.exit_code == EXIT_NOT_READY


def documented_fields() -> set[str]:
    """The field names docs/doctor.md's tables list (first column, in backquotes)."""
    return set(re.findall(r"^\| `([a-z_.\[\]]+)` \|", DOC.read_text(), flags=re.M))


def json_fields(doc, prefix="") -> set[str]:
    out = set()
    for k, v in doc.items():
        out.add(prefix + k)
        if isinstance(v, dict) and k in ("counts", "software"):
            out |= json_fields(v, prefix + k + ".")
        elif isinstance(v, list) and k == "checks":
            for c in v:
                out |= {f"checks[].{f}" for f in c}
    return out


@pytest.mark.integration
def test_the_command_text_json_and_exit_status(tmp_path):
    from cli.app import app

    port = free_udp_port()
    path = vessel_yaml(tmp_path, pps=f"{{type: udp, host: 127.0.0.1, port: {port}}}")
    r = CliRunner().invoke(
        app, ["doctor", "--config", str(path), "--json", "--pps-wait", "0.3", "--hours", "0.01"]
    )
    assert r.exit_code == EXIT_NOT_READY, r.output  # no PPS arrives
    doc = json.loads(r.stdout)
    assert doc["exit_code"] == EXIT_NOT_READY and doc["ready"] is False and doc["status"] == "not_ready"
    pps = next(c for c in doc["checks"] if c["name"] == "pps")
    assert pps["status"] == "fail" and pps["device"] == "pps" and pps["advice"]
    assert json_fields(doc) <= documented_fields(), json_fields(doc) - documented_fields()
    r = CliRunner().invoke(app, ["doctor", "--config", str(path), "--pps-wait", "0.3", "--hours", "0.01"])
    assert r.exit_code == EXIT_NOT_READY
    assert re.search(r"^FAIL  pps pps +udp 127\.0\.0\.1:\d+: no pulse in 0\.3 s$", r.stdout, re.M), r.stdout
    assert "→ is the GNSS receiver tracking" in r.stdout and "mls doctor: not ready" in r.stdout


def test_every_check_is_documented():
    fields = documented_fields()
    assert {"checks[].name", "checks[].status", "checks[].advice", "live.presurvey"} <= fields
    text = DOC.read_text()
    for name in (
        "config",
        "ports",
        "serial",
        "pps",
        "clock",
        "udp_buffer",
        "disk",
        "broker",
        "leap_table",
        "unit",
    ):
        assert f"`{name}`" in text, name
