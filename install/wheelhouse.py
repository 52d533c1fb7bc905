"""Build the offline wheelhouse of marine-mls: ``make wheelhouse`` (``.venv/bin/python install/wheelhouse.py``).

The vessel PC usually has no internet and the package is published nowhere, so everything the
installer needs travels in one directory (and the same as a ``.tar.gz``)::

    dist/marine-mls-<version>-wheelhouse/
        install.py          the installer (install/install.py), run with the system python3
        manifest.json       project, version, Python and platform, every wheel: name, version, sha256
        SHA256SUMS          every file, for ``sha256sum -c SHA256SUMS``
        systemd/            the unit files, sysctl, udev rule and vessel.example.yaml
        wheels/             the project's wheel, every runtime dependency's, and pip's

The dependencies are those of ``pyproject.toml`` (``[project] dependencies``, no extras), at the
versions installed in the venv that runs this script: ``pip freeze`` of that venv is handed to
``pip wheel`` as constraints, so pip resolves the same tree the tests ran against and fails if
it cannot (a pin that does not fit pyproject). ``pip wheel`` downloads a published wheel where
there is one and builds the others; pip's cache makes a second build quick. pip's own wheel
(the version of this venv's pip) is added so that the installer needs neither ``ensurepip`` nor
the ``python3-venv`` package on the vessel: it makes the venv ``--without-pip`` and runs pip
from its wheel.

The project's wheel is built from a copy of the source tree (``pyproject.toml``, ``README.md``
and the packages ``[tool.setuptools.packages.find]`` names), so the build leaves no ``build/``
in the working tree. The wheels target the interpreter that builds them (``manifest.json``
``python``, ``platform``): build with the Python of the vessel PC (Debian 12: 3.11,
``make wheelhouse PYTHON=python3.11`` for a new ``.venv``).

Usage: ``python install/wheelhouse.py [--out dist] [--no-archive]``; it prints the directory and
the archive it wrote. Exit status 0, or 1 with one line naming what failed.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import sysconfig
import tarfile
import tempfile
import tomllib
from dataclasses import dataclass
from pathlib import Path


def _installer():
    """The installer beside this file (stdlib only, copied into the wheelhouse): one name
    normalization and one checksum for the wheelhouse and for the install that reads it."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("mls_installer", Path(__file__).with_name("install.py"))
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclasses look the module up
    spec.loader.exec_module(module)
    return module


_INSTALLER = _installer()
normalize, sha256_of = _INSTALLER.normalize, _INSTALLER.sha256_of

REPO = Path(__file__).resolve().parents[1]
#: what the installer needs beside the wheels (from systemd/)
SYSTEMD_FILES = (
    "mls-acquire.service",
    "mls-pps-ldattach@.service",
    "90-mls-net.conf",
    "99-mls-pps.rules",
    "vessel.example.yaml",
)
MANIFEST_FORMAT = 1
_WHEEL_NAME = re.compile(r"^(?P<name>[^-]+)-(?P<version>[^-]+)(-\d[^-]*)?-[^-]+-[^-]+-[^-]+\.whl$")


class BuildError(RuntimeError):
    """A step of the build failed (the message says which and why)."""


@dataclass(frozen=True, kw_only=True)
class Wheel:
    file: str
    name: str  # normalized (PEP 503): lower case, runs of -_. as one -
    version: str
    sha256: str
    size_bytes: int


def wheel_of(path: Path) -> Wheel:
    m = _WHEEL_NAME.match(path.name)
    if m is None:
        raise BuildError(f"{path.name}: not a wheel file name")
    return Wheel(
        file=path.name,
        name=normalize(m["name"]),
        version=m["version"],
        sha256=sha256_of(path),
        size_bytes=path.stat().st_size,
    )


def project_meta(repo: Path = REPO) -> tuple[str, str, list[str]]:
    """(name, version, packages to include) from ``pyproject.toml``."""
    data = tomllib.loads((repo / "pyproject.toml").read_text())
    find = data.get("tool", {}).get("setuptools", {}).get("packages", {}).get("find", {})
    packages = sorted({p.rstrip("*") for p in find.get("include", [])})
    return data["project"]["name"], data["project"]["version"], packages


def _run(cmd: list[str], what: str) -> str:
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode != 0:
        tail = "\n".join((r.stderr or r.stdout).strip().splitlines()[-15:])
        raise BuildError(f"{what} failed (exit {r.returncode}): {' '.join(cmd)}\n{tail}")
    return r.stdout


def pins(python: str) -> dict[str, str]:
    """``name → version`` of every distribution installed in ``python``'s environment (the
    editable project left out)."""
    out = _run([python, "-m", "pip", "freeze", "--exclude-editable", "--all"], "pip freeze")
    found = {}
    for line in out.splitlines():
        name, sep, version = line.strip().partition("==")
        if sep and " " not in name:
            found[normalize(name)] = version
    return found


def copy_source(repo: Path, dest: Path, packages: list[str]) -> Path:
    """The files the project's wheel is built from, copied to ``dest``."""
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc", "*.egg-info")
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(repo / name, dest / name)
    for pkg in packages:
        shutil.copytree(repo / pkg, dest / pkg, ignore=ignore)
    return dest


def build_wheels(python: str, source: Path, wheels: Path, pinned: dict[str, str], work: Path) -> None:
    """``pip wheel`` of the project with its runtime dependencies at the pinned versions, then
    pip's own wheel."""
    constraints = work / "constraints.txt"
    constraints.write_text("".join(f"{n}=={v}\n" for n, v in sorted(pinned.items())))
    _run(
        [
            python,
            "-m",
            "pip",
            "wheel",
            "--quiet",
            "--wheel-dir",
            str(wheels),
            "--constraint",
            str(constraints),
        ]
        + [str(source)],
        "pip wheel (the project and its dependencies)",
    )
    pip_pin = f"pip=={pinned['pip']}" if "pip" in pinned else "pip"
    _run(
        [python, "-m", "pip", "download", "--quiet", "--no-deps", "--only-binary=:all:", "-d", str(wheels)]
        + [pip_pin],
        "pip download (pip's own wheel)",
    )


def check_pins(found: list[Wheel], pinned: dict[str, str], project: str, version: str) -> None:
    """Every wheel at the version installed in the venv, the project's at pyproject's."""
    bad = [
        f"{w.name} {w.version} (the venv has {pinned[w.name]})"
        for w in found
        if w.name in pinned and pinned[w.name] != w.version
    ]
    own = [w for w in found if w.name == normalize(project)]
    if len(own) != 1 or own[0].version != version:
        bad.append(f"{project}: wheels {[w.file for w in own]}, expected version {version}")
    if bad:
        raise BuildError("wheels at other versions than the venv's: " + "; ".join(bad))


def write_manifest(out: Path, project: str, version: str, wheels: list[Wheel]) -> dict:
    """``manifest.json`` and ``SHA256SUMS`` of the assembled directory ``out``."""
    files = sorted(str(p.relative_to(out)) for p in out.rglob("*") if p.is_file() and p.name != "SHA256SUMS")
    manifest = {
        "format": MANIFEST_FORMAT,
        "project": normalize(project),
        "version": version,
        "python": f"{sys.version_info.major}.{sys.version_info.minor}",
        "platform": sysconfig.get_platform(),
        "wheels": [w.__dict__ for w in sorted(wheels, key=lambda w: w.name)],
        "files": {f: sha256_of(out / f) for f in files if not f.startswith("wheels/")},
    }
    (out / "manifest.json").write_text(json.dumps(manifest, indent=2) + "\n")
    files = sorted({*files, "manifest.json"})
    (out / "SHA256SUMS").write_text("".join(f"{sha256_of(out / f)}  {f}\n" for f in files))
    return manifest


def assemble(out: Path, wheels_dir: Path, repo: Path, project: str, version: str) -> dict:
    """Lay out ``out`` (replaced when it exists) from built wheels and the repository's
    installer and systemd files; returns the manifest."""
    tmp = out.with_name(out.name + ".partial")
    shutil.rmtree(tmp, ignore_errors=True)
    (tmp / "systemd").mkdir(parents=True)
    shutil.copytree(wheels_dir, tmp / "wheels")
    shutil.copy2(repo / "install" / "install.py", tmp / "install.py")
    os.chmod(tmp / "install.py", 0o755)
    for name in SYSTEMD_FILES:
        shutil.copy2(repo / "systemd" / name, tmp / "systemd" / name)
    wheels = [wheel_of(p) for p in sorted((tmp / "wheels").glob("*.whl"))]
    manifest = write_manifest(tmp, project, version, wheels)
    shutil.rmtree(out, ignore_errors=True)
    tmp.rename(out)
    return manifest


def archive(out: Path) -> Path:
    """``<out>.tar.gz`` holding ``out`` under its own name (files sorted, owners root)."""
    path = out.with_name(out.name + ".tar.gz")

    def reset(info: tarfile.TarInfo) -> tarfile.TarInfo:
        info.uid = info.gid = 0
        info.uname = info.gname = "root"
        return info

    with tarfile.open(path, "w:gz") as tar:
        tar.add(out, arcname=out.name, filter=reset, recursive=False)
        for p in sorted(out.rglob("*")):
            tar.add(p, arcname=f"{out.name}/{p.relative_to(out)}", filter=reset, recursive=False)
    return path


def build(out_root: Path, repo: Path = REPO, python: str = sys.executable, make_archive: bool = True):
    """Build ``<out_root>/<project>-<version>-wheelhouse`` (and its archive); returns
    ``(directory, archive or None, manifest)``."""
    project, version, packages = project_meta(repo)
    out = out_root / f"{normalize(project)}-{version}-wheelhouse"
    out_root.mkdir(parents=True, exist_ok=True)
    pinned = pins(python)
    with tempfile.TemporaryDirectory(prefix="mls-wheelhouse-") as tmp:
        work = Path(tmp)
        for d in ("src", "wheels"):
            (work / d).mkdir()
        source = copy_source(repo, work / "src", packages)
        build_wheels(python, source, work / "wheels", pinned, work)
        check_pins([wheel_of(p) for p in (work / "wheels").glob("*.whl")], pinned, project, version)
        manifest = assemble(out, work / "wheels", repo, project, version)
    return out, archive(out) if make_archive else None, manifest


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=REPO / "dist", help="directory to write into [dist]")
    ap.add_argument("--no-archive", action="store_true", help="the directory only, no .tar.gz")
    args = ap.parse_args(argv)
    try:
        out, tar, manifest = build(args.out.resolve(), make_archive=not args.no_archive)
    except (BuildError, OSError) as e:
        print(f"wheelhouse: {e}", file=sys.stderr)
        return 1
    print(f"wheelhouse: {out} ({len(manifest['wheels'])} wheels, Python {manifest['python']})")
    if tar is not None:
        print(f"archive: {tar} ({tar.stat().st_size / 2**20:.0f} MiB)")
    print(
        f"install on the vessel PC: tar xzf {tar.name if tar else out.name} && sudo python3 {out.name}/install.py"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
