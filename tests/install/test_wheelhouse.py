"""``make wheelhouse`` for real: the wheels pin what .venv runs (and nothing is missing), the
manifest and SHA256SUMS hold, the archive holds the directory; the installer puts it into a fresh
venv with the network off (no index, proxies to a closed port), and that venv simulates a
calibration bundle and calibrates it end to end; systemd-analyze verifies the unit it installed,
and ``mls doctor``'s unit check agrees. Slow: it builds and installs every wheel."""

from __future__ import annotations

import json
import os
import subprocess
import tarfile
from importlib.metadata import distribution, version
from pathlib import Path

import pytest

from acquire.doctor.result import Status
from acquire.doctor.unit import unit_check
from tests.install.helpers import run_installer
from tests.install.test_installer import PREFIX, verify_unit

pytestmark = [pytest.mark.slow, pytest.mark.integration, pytest.mark.xdist_group("wheelhouse")]

NETWORK_OFF = {
    **{k: v for k, v in os.environ.items() if not k.startswith("PIP_")},
    **{k: "http://127.0.0.1:9" for k in ("http_proxy", "https_proxy", "HTTP_PROXY", "HTTPS_PROXY")},
    "PIP_INDEX_URL": "http://127.0.0.1:9/simple",
    "no_proxy": "",
}


def normalize(name: str) -> str:
    return name.replace("_", "-").replace(".", "-").lower()


def test_the_wheelhouse_pins_what_the_venv_runs(real_wheelhouse):
    out, tar, manifest = real_wheelhouse
    wheels = {w["name"]: w["version"] for w in manifest["wheels"]}
    assert wheels.pop("marine-mls") == manifest["version"] == version("marine-mls")
    assert "pip" in wheels
    assert {n: v for n, v in wheels.items()} == {n: version(n) for n in wheels}
    for req in distribution("marine-mls").requires or []:
        if "extra ==" not in req:  # runtime dependencies, not the test/dev/bench extras
            name = normalize(
                req.split(";")[0].split("[")[0].split("=")[0].split("<")[0].split(">")[0].strip()
            )
            assert name in wheels, req
    r = subprocess.run(
        ["sha256sum", "--check", "--quiet", "SHA256SUMS"], cwd=out, capture_output=True, text=True
    )
    assert r.returncode == 0, r.stdout + r.stderr
    assert json.loads((out / "manifest.json").read_text())["files"].keys() >= {
        "install.py",
        "systemd/mls-acquire.service",
    }
    with tarfile.open(tar) as t:
        names = t.getnames()
    assert f"{out.name}/manifest.json" in names and f"{out.name}/install.py" in names
    assert sum(n.endswith(".whl") for n in names) == len(manifest["wheels"])


def test_installed_offline_it_calibrates_end_to_end(real_wheelhouse, tmp_path):
    out, _, manifest = real_wheelhouse
    root = tmp_path / "root"
    r = run_installer("--root", root, script=out / "install.py", env=NETWORK_OFF)
    assert r.returncode == 0, r.stdout + r.stderr
    python, mls = root / PREFIX / "bin/python", root / PREFIX / "bin/mls"

    def run(*args: str) -> str:
        p = subprocess.run(
            [str(python), "-I", str(mls), *args], capture_output=True, text=True, cwd=tmp_path, timeout=600
        )
        assert p.returncode == 0, p.stdout + p.stderr
        return p.stdout

    where = subprocess.run(
        [str(python), "-I", "-c", "import cli; print(cli.__file__)"], capture_output=True, text=True
    )
    assert where.stdout.startswith(str(root / PREFIX)), where  # the wheel's code, not this tree's
    assert run("version").strip() == manifest["version"]
    run("sim", "dataset", "--scenario", "montreal", "--point-rate-scale", "0.05", "--out", "bundle")
    run("calib", "run", "bundle", "--no-history", "--no-plots")
    result = json.loads((tmp_path / "bundle/calib/result.json").read_text())
    assert result["verdict"] in ("trusted", "questionable") and result["converged"]
    assert set(result["boresight_deg"]) == {"roll", "pitch", "yaw"}
    assert unit_check(root, manifest["version"], "/opt/marine-mls").status == Status.OK
    v = verify_unit(root)
    assert v.returncode == 0 and v.stderr == "", v.stderr
    assert Path(root / "etc/mls/vessel.yaml").read_text() == (out / "systemd/vessel.example.yaml").read_text()
