"""The installer's test kit (not a module of tests): the two scripts of install/ loaded as they
run (plain files, not project packages), a small fake wheelhouse made offline, the installer run
as the surveyor runs it, and a listing of a tree (modes, owners, hashes) to compare runs."""

from __future__ import annotations

import base64
import hashlib
import importlib.util
import os
import subprocess
import sys
import zipfile
from pathlib import Path

from tests.conftest import PROJECT_ROOT

INSTALL_PY = PROJECT_ROOT / "install" / "install.py"


def load(name: str):
    """``install/<name>.py`` as a module."""
    spec = importlib.util.spec_from_file_location(
        f"mls_install_{name}", PROJECT_ROOT / "install" / f"{name}.py"
    )
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look the module up
    spec.loader.exec_module(module)
    return module


def _record_line(name: str, data: bytes) -> str:
    digest = base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b"=").decode()
    return f"{name},sha256={digest},{len(data)}\n"


def write_wheel(
    directory: Path, name: str, version: str, files: dict[str, bytes], entry_points: str = ""
) -> Path:
    """A pure-Python wheel ``name-version-py3-none-any.whl`` holding ``files``."""
    dist = f"{name.replace('-', '_')}-{version}"
    info = f"{dist}.dist-info"
    files = dict(files)
    files[f"{info}/METADATA"] = f"Metadata-Version: 2.1\nName: {name}\nVersion: {version}\n".encode()
    files[f"{info}/WHEEL"] = (
        b"Wheel-Version: 1.0\nGenerator: mls-tests\nRoot-Is-Purelib: true\nTag: py3-none-any\n"
    )
    if entry_points:
        files[f"{info}/entry_points.txt"] = entry_points.encode()
    record = "".join(_record_line(n, d) for n, d in sorted(files.items())) + f"{info}/RECORD,,\n"
    path = directory / f"{dist}-py3-none-any.whl"
    with zipfile.ZipFile(path, "w") as z:
        for n, d in sorted(files.items()):
            z.writestr(n, d)
        z.writestr(f"{info}/RECORD", record)
    return path


def pip_wheel(directory: Path) -> Path:
    """The wheel of the pip this interpreter has installed (offline: its files zipped again)."""
    import pip

    site = Path(pip.__file__).parent.parent
    info = next(site.glob(f"pip-{pip.__version__}.dist-info"))
    files = {}
    for base in (site / "pip", info):
        for p in sorted(base.rglob("*")):
            if (
                p.is_file()
                and "__pycache__" not in p.parts
                and p.name not in ("RECORD", "INSTALLER", "REQUESTED", "direct_url.json")
            ):
                files[str(p.relative_to(site))] = p.read_bytes()
    dist = f"pip-{pip.__version__}"
    record = "".join(_record_line(n, d) for n, d in sorted(files.items())) + f"{dist}.dist-info/RECORD,,\n"
    path = directory / f"{dist}-py3-none-any.whl"
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as z:
        for n, d in files.items():
            z.writestr(n, d)
        z.writestr(f"{dist}.dist-info/RECORD", record)
    return path


def fake_wheelhouse(out: Path, version: str, pip_whl: Path, extra_dep: bool = False) -> Path:
    """A wheelhouse laid out by install/wheelhouse.py around a fake marine-mls ``version`` (its
    ``mls`` prints the version) and pip's wheel; ``extra_dep`` adds a second distribution."""
    wheelhouse = load("wheelhouse")
    wheels = out.with_name(out.name + "-wheels")
    wheels.mkdir(parents=True)
    code = f'VERSION = "{version}"\n\n\ndef main():\n    print(VERSION)\n'.encode()
    write_wheel(
        wheels,
        "marine-mls",
        version,
        {"mls_fake/__init__.py": code},
        "[console_scripts]\nmls = mls_fake:main\n",
    )
    if extra_dep:
        write_wheel(wheels, "mls-extra-dep", "1.0", {"mls_extra_dep.py": b"X = 1\n"})
    (wheels / pip_whl.name).write_bytes(pip_whl.read_bytes())
    wheelhouse.assemble(out, wheels, PROJECT_ROOT, "marine-mls", version)
    return out


def run_installer(
    *args: str | Path, script: Path = INSTALL_PY, env: dict | None = None
) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, str(script), *map(str, args)], capture_output=True, text=True, timeout=300, env=env
    )


def tree(root: Path) -> dict[str, tuple]:
    """path → (kind, mode, uid, gid, sha256 or link target, mtime_ns of a file)."""
    out = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for name in [*dirnames, *filenames]:
            p = Path(dirpath) / name
            st = os.lstat(p)
            rel = str(p.relative_to(root))
            if p.is_symlink():
                out[rel] = ("link", 0, st.st_uid, st.st_gid, os.readlink(p), 0)
            elif p.is_dir():
                out[rel] = ("dir", st.st_mode & 0o7777, st.st_uid, st.st_gid, "", 0)
            else:
                digest = hashlib.sha256(p.read_bytes()).hexdigest()
                out[rel] = ("file", st.st_mode & 0o7777, st.st_uid, st.st_gid, digest, st.st_mtime_ns)
    return out
