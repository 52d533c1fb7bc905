"""The systemd unit passes `systemd-analyze verify` with no output; its hardening keeps serial.

`verify` checks that ExecStart's binary exists. The shipped unit points at the install path
(/opt/marine-mls/bin/mls), so the test verifies a copy in which only that path is replaced by
this venv's `mls` entry point: every other line is verified exactly as shipped.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.integration

SYSTEMD = Path(__file__).resolve().parents[3] / "systemd"
UNIT = SYSTEMD / "mls-acquire.service"
LDATTACH = SYSTEMD / "mls-pps-ldattach@.service"
SHIPPED_EXEC = "/opt/marine-mls/bin/mls"


def _analyze() -> str:
    exe = shutil.which("systemd-analyze")
    if exe is None:
        raise AssertionError("systemd-analyze not found: install systemd (apt-get install systemd)")
    return exe


def _lines(path: Path) -> list[tuple[str, str]]:
    out = []
    for line in path.read_text().splitlines():
        if line and not line.startswith(("#", "[")) and "=" in line:
            key, _, value = line.partition("=")
            out.append((key.strip(), value.strip()))
    return out


def _local_copy(tmp_path: Path) -> Path:
    mls = Path(sys.executable).parent / "mls"
    assert mls.exists(), f"{mls} missing: install the project (pip install -e .)"
    text = UNIT.read_text()
    assert text.count(f"ExecStart={SHIPPED_EXEC} ") == 1
    local = tmp_path / UNIT.name
    local.write_text(text.replace(f"ExecStart={SHIPPED_EXEC} ", f"ExecStart={mls} "))
    diff = [(a, b) for a, b in zip(text.splitlines(), local.read_text().splitlines()) if a != b]
    assert len(diff) == 1 and diff[0][0].startswith("ExecStart=")
    return local


def test_unit_verifies_without_any_warning(tmp_path):
    r = subprocess.run(
        [_analyze(), "verify", str(_local_copy(tmp_path))], capture_output=True, text=True, timeout=60
    )
    assert r.returncode == 0 and r.stderr == "", r.stderr


def test_ldattach_template_instance_verifies(tmp_path):
    instance = tmp_path / "mls-pps-ldattach@ttyS0.service"
    instance.write_text(LDATTACH.read_text())
    r = subprocess.run([_analyze(), "verify", str(instance)], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and r.stderr == "", r.stderr


def test_unit_settings_that_the_daemon_relies_on():
    settings = _lines(UNIT)
    get = {k: v for k, v in settings}
    assert get["Type"] == "notify" and get["NotifyAccess"] == "main"
    assert int(get["WatchdogSec"]) > 0 and get["Restart"] == "on-failure"
    assert get["User"] == "mls" and get["SupplementaryGroups"] == "dialout"
    assert get["DevicePolicy"] == "closed"
    allowed = sorted(v for k, v in settings if k == "DeviceAllow")
    assert allowed == ["char-pps r", "char-ttyACM rw", "char-ttyS rw", "char-ttyUSB rw"]
    # options that would take the serial ports or the dialout group away are absent
    assert "PrivateDevices" not in get and "PrivateUsers" not in get
    assert "AF_CAN" in get["RestrictAddressFamilies"]  # python-can's socketcan


def test_security_exposure_is_low(tmp_path):
    r = subprocess.run(
        [_analyze(), "security", "--offline=true", str(_local_copy(tmp_path))],
        capture_output=True,
        text=True,
        timeout=60,
    )
    m = re.search(r"Overall exposure level for \S+: (\d+\.\d+)", r.stdout)
    assert m, r.stdout[-500:] + r.stderr
    exposure = float(m.group(1))
    print(f"\nsystemd-analyze security --offline=true: exposure {exposure}")
    assert exposure <= 2.0, r.stdout


def test_udev_rule_asks_for_the_ldattach_unit_and_opens_pps_to_dialout():
    rules = [
        ln
        for ln in (SYSTEMD / "99-mls-pps.rules").read_text().splitlines()
        if ln.strip() and not ln.startswith("#")
    ]
    assert len(rules) == 2
    assert 'ENV{SYSTEMD_WANTS}+="mls-pps-ldattach@%k.service"' in rules[0]
    assert 'SUBSYSTEM=="tty"' in rules[0] and 'TAG+="systemd"' in rules[0]
    assert rules[1] == 'SUBSYSTEM=="pps", GROUP="dialout", MODE="0640"'
    for rule in rules:  # every clause is KEY op "value"
        for clause in rule.split(", "):
            assert re.fullmatch(r'[A-Z_]+(\{[A-Z_]+\})?(==|!=|\+=|=)"[^"]*"', clause), clause
