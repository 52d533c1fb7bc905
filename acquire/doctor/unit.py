"""The installed systemd unit matches the installed software: the unit's ``ExecStart`` names an
``mls`` that exists, the venv it lives in holds the version ``install.py`` installed (its install
record, ``<prefix>/install-record.json``, docs/doctor.md), the unit is the one the installer
wrote (sha256), systemd has loaded it (no pending daemon-reload), and the ``mls`` running this
check is that software. Paths are read under ``root`` (a tree staged with ``install.py --root``)."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

from acquire.doctor.clock import Runner
from acquire.doctor.result import CheckResult, fail, ok, warn

UNIT = "/etc/systemd/system/mls-acquire.service"
RECORD = "install-record.json"
INSTALL = "run the wheelhouse's install.py (README, 'On the vessel PC')"


def _under(root: Path, path: str | Path) -> Path:
    return root / str(path).lstrip("/")


def exec_start(unit_text: str) -> Path | None:
    for line in unit_text.splitlines():
        if line.startswith("ExecStart="):
            return Path(line.partition("=")[2].split()[0].lstrip("-@+!:"))
    return None


def venv_version(venv: Path) -> str | None:
    """The marine-mls version installed in the venv (its dist-info), None when none is."""
    found = sorted(venv.glob("lib/python3*/site-packages/marine_mls-*.dist-info"))
    return found[-1].name.removesuffix(".dist-info").split("-", 1)[1] if found else None


def unit_check(
    root: Path, running_version: str, running_prefix: str, run: Runner | None = None
) -> CheckResult:
    """``run`` (systemd's view, when it runs here) asks ``systemctl show`` about the unit."""
    unit = _under(root, UNIT)
    if not unit.is_file():
        return warn("unit", f"{UNIT} not installed", f"to run the daemon as a service: {INSTALL}")
    text = unit.read_text()
    exe = exec_start(text)
    prefix = None if exe is None else exe.parent.parent
    data: dict[str, str | None] = {
        "unit": UNIT,
        "exec_start": str(exe),
        "prefix": str(prefix),
        "running_version": running_version,
    }
    if exe is None or prefix is None or not _under(root, exe).exists():
        return fail("unit", f"{UNIT}: ExecStart={exe} does not exist", INSTALL, data=data)
    data["installed_version"] = installed = venv_version(_under(root, prefix))
    try:
        record = json.loads(_under(root, prefix / RECORD).read_text())
    except (OSError, ValueError):
        return warn(
            "unit",
            f"{UNIT} runs {exe} (marine-mls {installed}), not installed by install.py "
            "(no install record): cannot tell whether they fit",
            INSTALL,
            data=data,
        )
    data["recorded_version"] = record.get("version")
    if record.get("version") != installed:
        return fail(
            "unit",
            f"{UNIT} was installed with marine-mls {record.get('version')}, {prefix} holds {installed}",
            f"{INSTALL} of {installed}",
            data=data,
        )
    if hashlib.sha256(unit.read_bytes()).hexdigest() != (record.get("unit") or {}).get("sha256"):
        return warn(
            "unit",
            f"{UNIT} differs from the one install.py {installed} wrote (edited?)",
            "put local changes in a drop-in (systemctl edit mls-acquire) and " + INSTALL,
            data=data,
        )
    if run is not None and (
        got := run(["systemctl", "show", "--property=NeedDaemonReload", "mls-acquire.service"])
    ):
        if got[0] == 0 and "NeedDaemonReload=yes" in got[1]:
            return warn(
                "unit",
                f"{UNIT} changed on disk since systemd loaded it",
                "systemctl daemon-reload",
                data=data,
            )
    if running_version != installed or Path(running_prefix) != prefix:
        return warn(
            "unit",
            f"the service runs marine-mls {installed} from {prefix}; this mls is {running_version} "
            f"from {running_prefix}",
            f"run {prefix}/bin/mls doctor to check the service's own software",
            data=data,
        )
    return ok("unit", f"{UNIT} runs {exe}, marine-mls {installed} as installed", data=data)
