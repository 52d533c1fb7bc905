"""install/install.py staging the whole tree with ``--root`` from a small wheelhouse made here
(a fake marine-mls whose ``mls`` prints its version, pip's own wheel): the tree, its modes and the
owners it records; a second run changes nothing (every path, mode, owner, hash and file time);
an existing config is kept; an upgrade keeps config and sessions; ``--uninstall`` leaves the
data; ``systemd-analyze verify`` passes on the installed unit; ``mls doctor``'s unit check agrees
with what it installed. The run is the surveyor's: the script under this Python, a subprocess."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import pytest

from acquire.doctor.result import Status
from acquire.doctor.unit import unit_check
from tests.install.helpers import fake_wheelhouse, pip_wheel, run_installer, tree

pytestmark = pytest.mark.integration

PREFIX = "opt/marine-mls"
EXPECTED = {  # path → (mode, owner, group) as recorded
    "/etc/mls": ("0755", "root", "root"),
    "/var/lib/mls": ("0750", "mls", "mls"),
    "/var/lib/mls/sessions": ("0750", "mls", "mls"),
    "/etc/systemd/system/mls-acquire.service": ("0644", "root", "root"),
    "/etc/systemd/system/mls-pps-ldattach@.service": ("0644", "root", "root"),
    "/etc/sysctl.d/90-mls-net.conf": ("0644", "root", "root"),
    "/etc/udev/rules.d/99-mls-pps.rules": ("0644", "root", "root"),
    "/etc/mls/vessel.example.yaml": ("0644", "root", "root"),
    "/etc/mls/vessel.yaml": ("0640", "root", "mls"),
    "/usr/local/bin/mls": ("0777", "root", "root"),
}


@pytest.fixture(scope="module")
def wheelhouses(tmp_path_factory):
    d = tmp_path_factory.mktemp("wheelhouses")
    pip = pip_wheel(d)
    return {
        "0.1.0": fake_wheelhouse(d / "wh-0.1.0", "0.1.0", pip, extra_dep=True),
        "0.2.0": fake_wheelhouse(d / "wh-0.2.0", "0.2.0", pip),
    }


def install(wheelhouse: Path, root: Path, *args: str) -> str:
    r = run_installer("--wheelhouse", wheelhouse, "--root", root, *args)
    assert r.returncode == 0, r.stdout + r.stderr
    return r.stdout


def record(root: Path) -> dict:
    return json.loads((root / PREFIX / "install-record.json").read_text())


def run_mls(root: Path, *args: str) -> str:
    venv = root / PREFIX
    r = subprocess.run(
        [str(venv / "bin/python"), "-I", str(venv / "bin/mls"), *args],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 0, r.stderr
    return r.stdout.strip()


def test_the_staged_tree_its_modes_and_owners_then_a_second_run_changes_nothing(tmp_path, wheelhouses):
    root = tmp_path / "root"
    out = install(wheelhouses["0.1.0"], root)
    assert "created   /etc/mls/vessel.yaml" in out and "staged under" in out
    listing = tree(root)
    for path, (mode, _, _) in EXPECTED.items():
        kind, got_mode, *_ = listing[path.lstrip("/")]
        assert kind == "link" or f"{got_mode:04o}" == mode, path
    rec = record(root)
    got = {e["path"]: (e["mode"], e["owner"], e["group"]) for e in rec["entries"]}
    assert got == EXPECTED
    assert (
        rec["version"] == "0.1.0"
        and rec["wheels"]["marine-mls"] == "0.1.0"
        and rec["prefix"] == "/opt/marine-mls"
    )
    assert rec["venv"] == {"path": "/opt/marine-mls", "mode": "0755", "owner": "root", "group": "root"}
    assert os.readlink(root / "usr/local/bin/mls") == "/opt/marine-mls/bin/mls"
    # the staged venv names its final place, and runs
    assert (root / PREFIX / "bin/mls").read_text().startswith("#!/opt/marine-mls/bin/python\n")
    assert str(root) not in (root / PREFIX / "pyvenv.cfg").read_text()
    assert run_mls(root) == "0.1.0"
    unit = (root / "etc/systemd/system/mls-acquire.service").read_text()
    assert "ExecStart=/opt/marine-mls/bin/mls acquire --config /etc/mls/vessel.yaml" in unit

    again = install(wheelhouses["0.1.0"], root)
    assert tree(root) == listing
    assert again.splitlines()[:-1] == ["kept      /etc/mls/vessel.yaml"]  # then the closing line


def test_an_existing_config_is_kept(tmp_path, wheelhouses):
    root = tmp_path / "root"
    cfg = root / "etc/mls/vessel.yaml"
    cfg.parent.mkdir(parents=True)
    cfg.write_text("vessel: my-boat\n")
    os.chmod(cfg, 0o600)
    out = install(wheelhouses["0.1.0"], root)
    assert "kept      /etc/mls/vessel.yaml" in out
    assert cfg.read_text() == "vessel: my-boat\n" and (cfg.stat().st_mode & 0o777) == 0o600
    example = (root / "etc/mls/vessel.example.yaml").read_text()
    assert example == (Path(wheelhouses["0.1.0"]) / "systemd/vessel.example.yaml").read_text()


def test_an_upgrade_keeps_config_and_sessions(tmp_path, wheelhouses):
    root = tmp_path / "root"
    install(wheelhouses["0.1.0"], root)
    cfg = root / "etc/mls/vessel.yaml"
    cfg.write_text(cfg.read_text() + "# edited on board\n")
    session = root / "var/lib/mls/sessions/20261204T000000Z_survey-1/seg-000001.mcap"
    session.parent.mkdir()
    session.write_bytes(b"data")
    out = install(wheelhouses["0.2.0"], root)
    assert "marine-mls==0.2.0" in out and "removed   mls-extra-dep" in out
    assert cfg.read_text().endswith("# edited on board\n") and session.read_bytes() == b"data"
    assert record(root)["version"] == "0.2.0" and run_mls(root) == "0.2.0"
    assert unit_check(root, "0.2.0", "/opt/marine-mls").status == Status.OK


def test_uninstall_leaves_config_sessions_and_user(tmp_path, wheelhouses):
    root = tmp_path / "root"
    install(wheelhouses["0.1.0"], root)
    session = root / "var/lib/mls/sessions/s1"
    session.mkdir()
    out = install(wheelhouses["0.1.0"], root, "--uninstall")
    assert "kept: /etc/mls/vessel.yaml, /var/lib/mls/sessions, /var/lib/mls, /etc/mls and the user mls" in out
    assert session.is_dir() and (root / "etc/mls/vessel.yaml").is_file()
    for gone in (
        PREFIX,
        "usr/local/bin/mls",
        "etc/systemd/system/mls-acquire.service",
        "etc/sysctl.d/90-mls-net.conf",
        "etc/udev/rules.d/99-mls-pps.rules",
        "etc/mls/vessel.example.yaml",
    ):
        assert not os.path.lexists(root / gone), gone
    assert "nothing" not in install(wheelhouses["0.1.0"], root)  # installs again over the kept data


def test_another_prefix_is_the_units_execstart(tmp_path, wheelhouses):
    root = tmp_path / "root"
    install(wheelhouses["0.1.0"], root, "--prefix", "/opt/mls-2")
    unit = (root / "etc/systemd/system/mls-acquire.service").read_text()
    assert (
        "ExecStart=/opt/mls-2/bin/mls acquire" in unit
        and os.readlink(root / "usr/local/bin/mls") == "/opt/mls-2/bin/mls"
    )
    assert unit_check(root, "0.1.0", "/opt/mls-2").status == Status.OK


def test_a_damaged_wheelhouse_or_another_python_is_refused(tmp_path, wheelhouses):
    wh = tmp_path / "wh"
    shutil.copytree(wheelhouses["0.1.0"], wh)
    wheel = next((wh / "wheels").glob("marine_mls-*.whl"))
    wheel.write_bytes(wheel.read_bytes() + b"x")
    r = run_installer("--wheelhouse", wh, "--root", tmp_path / "root")
    assert r.returncode == 1 and "damaged wheelhouse" in r.stderr and wheel.name in r.stderr
    assert not (tmp_path / "root").exists()
    manifest = json.loads((wheelhouses["0.1.0"] / "manifest.json").read_text())
    shutil.rmtree(wh)
    shutil.copytree(wheelhouses["0.1.0"], wh)
    (wh / "manifest.json").write_text(json.dumps({**manifest, "python": "3.99"}))
    r = run_installer("--wheelhouse", wh, "--root", tmp_path / "root")
    assert r.returncode == 1 and "built for 3.99" in r.stderr


def verify_unit(root: Path) -> subprocess.CompletedProcess:
    """``systemd-analyze verify --root`` on the unit as installed (its ExecStart looked up in the
    staged tree), beside a copy of this machine's systemd units (sysinit.target, ...)."""
    exe = shutil.which("systemd-analyze")
    assert exe, "systemd-analyze not found: install systemd (apt-get install systemd)"
    units = root / "usr/lib/systemd/system"
    if not units.exists():
        shutil.copytree("/usr/lib/systemd/system", units, symlinks=False, ignore_dangling_symlinks=True)
    return subprocess.run(
        [exe, "verify", f"--root={root}", "/etc/systemd/system/mls-acquire.service"],
        capture_output=True,
        text=True,
        timeout=60,
    )


def test_systemd_analyze_verifies_the_installed_unit(tmp_path, wheelhouses):
    root = tmp_path / "root"
    install(wheelhouses["0.1.0"], root)
    r = verify_unit(root)
    assert r.returncode == 0 and r.stderr == "", r.stderr
    (root / PREFIX / "bin/mls").unlink()  # the unit's program gone: verify says so
    r = verify_unit(root)
    assert r.returncode != 0 and "/opt/marine-mls/bin/mls" in r.stderr
