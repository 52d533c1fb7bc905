#!/usr/bin/env python3
"""Install marine-mls on the vessel PC from its offline wheelhouse: run once, as root.

    tar xzf marine-mls-<version>-wheelhouse.tar.gz
    sudo python3 marine-mls-<version>-wheelhouse/install.py        # install or upgrade
    sudo python3 marine-mls-<version>-wheelhouse/install.py --uninstall
    python3 install.py --root /tmp/stage                           # stage the tree (packaging, tests)

It needs the system ``python3`` (the one the wheels were built for, ``manifest.json`` ``python``)
and nothing from the network: the standard library only, ``python3 -m venv --without-pip`` and
pip run from the wheelhouse's own pip wheel (no ``ensurepip``, no ``python3-venv`` package).

What it puts where (``--prefix`` [``/opt/marine-mls``]; every path under ``--root`` [``/``]):

- the venv ``<prefix>`` with every wheel of the manifest at its version (each wheel's sha256
  checked first), pip's excepted (it installs them; the daemon needs no pip), and nothing else;
  ``/usr/local/bin/mls`` → ``<prefix>/bin/mls``;
- the system user and group ``mls`` (``useradd --system``; home ``/var/lib/mls``, no shell);
- ``/etc/systemd/system/mls-acquire.service`` (``ExecStart`` on ``<prefix>/bin/mls``) and
  ``mls-pps-ldattach@.service``, ``/etc/sysctl.d/90-mls-net.conf`` (32 MiB UDP receive buffer),
  ``/etc/udev/rules.d/99-mls-pps.rules``;
- ``/etc/mls/vessel.yaml`` from the example **only when there is none** (an existing config is
  never touched), and the example itself as ``/etc/mls/vessel.example.yaml`` (to compare after an
  upgrade); ``/var/lib/mls/sessions`` for the session logs;
- ``<prefix>/install-record.json``: the version, every entry above with its mode, owner, group
  and sha256, the wheels installed and the unit's sha256 (``mls doctor`` compares the unit and
  the software with it).

Then, when systemd runs: ``systemctl daemon-reload`` (units changed), ``sysctl -p`` on the new
sysctl file, ``udevadm control --reload`` (rule changed). The service is neither enabled nor
restarted: edit the config, run ``mls doctor``, then ``systemctl enable --now mls-acquire``.

Idempotent: a file is written only when its content differs, a mode or owner set only when it
differs, pip runs only when a wheel's version is not the one installed; a second run changes
nothing. An upgrade (a newer wheelhouse) replaces the software, units and example and keeps the
config and the sessions. ``--uninstall`` stops and disables the service and removes the software,
units, sysctl and udev files; it keeps ``/etc/mls`` (the config), ``/var/lib/mls`` (the sessions)
and the ``mls`` user.

``--root DIR`` stages the whole tree into DIR for packaging: no user is created and nothing is
reloaded; owners are set only when running as root and the user exists, and are recorded in
the install record in any case. The venv's scripts name ``<prefix>``, not DIR, so the tree works
once copied to ``/``.

Exit status: 0 done, 1 failed (one line naming what and what to do).
"""

from __future__ import annotations

import argparse
import grp
import hashlib
import json
import os
import pwd
import shutil
import subprocess
import sys
from dataclasses import asdict, dataclass
from pathlib import Path

DEFAULT_PREFIX = "/opt/marine-mls"
USER = GROUP = "mls"
HOME = "/var/lib/mls"
RECORD = "install-record.json"
RECORD_FORMAT = 1
UNIT = "/etc/systemd/system/mls-acquire.service"
SHIPPED_EXEC = "/opt/marine-mls/bin/mls"


class InstallError(RuntimeError):
    """The installation cannot go on (the message says why and what to do)."""


@dataclass(frozen=True, kw_only=True)
class Entry:
    """One thing the installer puts on the target (paths without ``--root``)."""

    path: str
    kind: str  # dir | file | config (written only when absent) | symlink
    mode: int
    owner: str = "root"
    group: str = "root"
    source: str | None = None  # file, config: the wheelhouse file
    target: str | None = None  # symlink
    keep: bool = False  # left in place by --uninstall


def shipped(path: str) -> Entry:
    """A file of the wheelhouse's ``systemd/`` installed as ``path`` (0644, root's)."""
    return Entry(path=path, kind="file", mode=0o644, source=f"systemd/{Path(path).name}")


def entries(prefix: str) -> list[Entry]:
    """Everything outside the venv, in creation order (directories before their files)."""
    example = "systemd/vessel.example.yaml"
    return [
        Entry(path="/etc/mls", kind="dir", mode=0o755, keep=True),
        Entry(path=HOME, kind="dir", mode=0o750, owner=USER, group=GROUP, keep=True),
        Entry(path=f"{HOME}/sessions", kind="dir", mode=0o750, owner=USER, group=GROUP, keep=True),
        shipped(UNIT),
        shipped("/etc/systemd/system/mls-pps-ldattach@.service"),
        shipped("/etc/sysctl.d/90-mls-net.conf"),
        shipped("/etc/udev/rules.d/99-mls-pps.rules"),
        shipped("/etc/mls/vessel.example.yaml"),
        Entry(path="/etc/mls/vessel.yaml", kind="config", mode=0o640, group=GROUP, source=example, keep=True),
        Entry(path="/usr/local/bin/mls", kind="symlink", mode=0o777, target=f"{prefix}/bin/mls"),
    ]


def sha256_bytes(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def sha256_of(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def normalize(name: str) -> str:
    out = "".join(c if c.isalnum() else "-" for c in name.lower())
    while "--" in out:
        out = out.replace("--", "-")
    return out


# -- the wheelhouse ------------------------------------------------------------------------------


def load_manifest(wheelhouse: Path) -> dict:
    path = wheelhouse / "manifest.json"
    try:
        manifest = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise InstallError(
            f"{path}: cannot read the wheelhouse manifest ({e}); build it with `make wheelhouse` "
            f"and pass its directory with --wheelhouse"
        ) from None
    if manifest.get("format") != 1 or not manifest.get("wheels"):
        raise InstallError(f"{path}: not a marine-mls wheelhouse manifest (format 1 with wheels)")
    return manifest


def verify_wheelhouse(wheelhouse: Path, manifest: dict) -> None:
    """Every wheel and file of the manifest is there with its sha256."""
    expected = {f"wheels/{w['file']}": w["sha256"] for w in manifest["wheels"]}
    expected.update(manifest.get("files", {}))
    bad = []
    for rel, digest in sorted(expected.items()):
        p = wheelhouse / rel
        if not p.is_file():
            bad.append(f"{rel} missing")
        elif sha256_of(p) != digest:
            bad.append(f"{rel} sha256 differs from the manifest")
    if bad:
        raise InstallError(f"{wheelhouse}: damaged wheelhouse: {'; '.join(bad)}; copy it again")


def python_version(python: str) -> str:
    r = subprocess.run(
        [python, "-c", "import sys; print('%d.%d' % sys.version_info[:2])"], capture_output=True, text=True
    )
    if r.returncode != 0:
        raise InstallError(f"{python}: cannot run it ({r.stderr.strip()}); pass --python")
    return r.stdout.strip()


# -- files, directories, owners ------------------------------------------------------------------


@dataclass(kw_only=True)
class Target:
    """Where the tree goes (``root``), and whether owners can be set."""

    root: Path
    prefix: str
    staged: bool  # --root other than /: no users, no reloads
    log: list[str]

    def at(self, path: str) -> Path:
        return self.root / path.lstrip("/")

    def ids(self, owner: str, group: str) -> tuple[int, int] | None:
        """uid, gid to chown to; None when not root or the user/group does not exist here."""
        if os.geteuid() != 0:
            return None
        try:
            return pwd.getpwnam(owner).pw_uid, grp.getgrnam(group).gr_gid
        except KeyError:
            return None

    def note(self, what: str, path: str) -> None:
        self.log.append(f"{what:9} {path}")


def set_meta(t: Target, p: Path, e: Entry) -> bool:
    """Mode and owner of ``p`` as ``e`` says; True when anything changed."""
    st = os.lstat(p)
    changed = False
    if (st.st_mode & 0o7777) != e.mode:
        os.chmod(p, e.mode)
        changed = True
    ids = t.ids(e.owner, e.group)
    if ids is not None and (st.st_uid, st.st_gid) != ids:
        os.chown(p, *ids)
        changed = True
    return changed


def make_parents(p: Path) -> None:
    """Missing parent directories, mode 0755 whatever the umask."""
    missing = []
    for parent in p.parents:
        if parent.exists():
            break
        missing.append(parent)
    for d in reversed(missing):
        d.mkdir()
        os.chmod(d, 0o755)


def put_dir(t: Target, e: Entry) -> bool:
    """The directory with its mode and owner (an existing one's content untouched)."""
    p = t.at(e.path)
    if p.is_dir():
        if set_meta(t, p, e):
            t.note("mode", e.path)
            return True
        return False
    make_parents(p)
    p.mkdir()
    set_meta(t, p, e)
    t.note("created", e.path)
    return True


def put_file(t: Target, e: Entry, data: bytes) -> bool:
    """Write ``data`` (atomically) unless the file holds it already; a config is never replaced.
    True when the content changed."""
    p = t.at(e.path)
    if p.exists() or p.is_symlink():
        if e.kind == "config":
            t.note("kept", e.path)
            return False
        if p.is_file() and not p.is_symlink() and sha256_of(p) == sha256_bytes(data):
            if set_meta(t, p, e):
                t.note("mode", e.path)
            return False
    make_parents(p)
    tmp = p.with_name(f".{p.name}.mls-install")
    tmp.write_bytes(data)
    set_meta(t, tmp, e)
    existed = p.exists()
    os.replace(tmp, p)
    t.note("updated" if existed else "created", e.path)
    return True


def put_symlink(t: Target, e: Entry) -> bool:
    p = t.at(e.path)
    assert e.target is not None
    if p.is_symlink() and os.readlink(p) == e.target:
        return False
    if p.exists() and not p.is_symlink():
        raise InstallError(f"{p} exists and is not a symbolic link: move it away, then run again")
    make_parents(p)
    if p.is_symlink():
        p.unlink()
    os.symlink(e.target, p)
    t.note("linked", f"{e.path} -> {e.target}")
    return True


def content(e: Entry, wheelhouse: Path, prefix: str) -> bytes:
    """The bytes of a file entry: the unit's ExecStart on ``prefix``."""
    assert e.source is not None
    data = (wheelhouse / e.source).read_bytes()
    if e.path == UNIT and prefix != DEFAULT_PREFIX:
        data = data.replace(f"ExecStart={SHIPPED_EXEC} ".encode(), f"ExecStart={prefix}/bin/mls ".encode())
    return data


# -- the venv --------------------------------------------------------------------------------------


def ensure_venv(t: Target, python: str, version: str) -> Path:
    """The venv at the prefix, made ``--without-pip`` when missing (or of another Python)."""
    venv = t.at(t.prefix)
    cfg = venv / "pyvenv.cfg"
    if cfg.is_file():
        line = next((ln for ln in cfg.read_text().splitlines() if ln.startswith("version")), "")
        if line.partition("=")[2].strip().startswith(version + "."):
            return venv
        if not (venv / RECORD).is_file():
            raise InstallError(f"{venv}: a venv of another Python not made by this installer: remove it")
        shutil.rmtree(venv)
    elif venv.exists() and any(venv.iterdir()):
        raise InstallError(f"{venv} exists and is not a venv: choose another --prefix or remove it")
    make_parents(venv)
    r = subprocess.run([python, "-m", "venv", "--without-pip", str(venv)], capture_output=True, text=True)
    if r.returncode != 0:
        raise InstallError(f"{python} -m venv {venv} failed: {r.stderr.strip()}")
    os.chmod(venv, 0o755)
    t.note("created", f"{t.prefix} (venv, Python {version})")
    return venv


_LIST = (
    "import importlib.metadata as m, json, sys; print(json.dumps({d.metadata['Name']: d.version "
    "for d in m.distributions(path=[p for p in sys.path if p.endswith('site-packages')])}))"
)


def installed(venv: Path) -> dict[str, str]:
    """Distribution → version in the venv (``-I -B``: no environment, no bytecode written)."""
    r = subprocess.run(
        [str(venv / "bin" / "python"), "-I", "-B", "-c", _LIST], capture_output=True, text=True
    )
    if r.returncode != 0:
        raise InstallError(f"{venv}: its python does not run: {r.stderr.strip()}")
    return {normalize(k): v for k, v in json.loads(r.stdout).items()}


def pip(venv: Path, wheelhouse: Path, manifest: dict, *args: str) -> None:
    """pip from the wheelhouse's pip wheel, isolated from any pip config, offline."""
    wheel = next((w for w in manifest["wheels"] if w["name"] == "pip"), None)
    if wheel is None:
        raise InstallError(f"{wheelhouse}: no pip wheel in the manifest: rebuild it with `make wheelhouse`")
    cmd = [str(venv / "bin" / "python"), str(wheelhouse / "wheels" / wheel["file"] / "pip"), "--isolated"]
    cmd += ["--disable-pip-version-check", "--no-input", *args]
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode != 0:
        tail = "\n".join((r.stderr or r.stdout).strip().splitlines()[-10:])
        raise InstallError(f"pip {args[0]} failed (exit {r.returncode}):\n{tail}")


def venv_wheels(manifest: dict) -> dict[str, str]:
    """What the venv holds: every wheel of the manifest but pip's (the tool that installs them,
    run from its wheel; the daemon needs no pip)."""
    return {w["name"]: w["version"] for w in manifest["wheels"] if w["name"] != "pip"}


def sync_wheels(t: Target, venv: Path, wheelhouse: Path, manifest: dict) -> bool:
    """Every wheel of :func:`venv_wheels` at its version, nothing else; True when pip ran."""
    wanted = venv_wheels(manifest)
    have = installed(venv)
    missing = sorted(f"{n}=={v}" for n, v in wanted.items() if have.get(n) != v)
    stale = sorted(n for n in have if n not in wanted)
    if missing:
        links = str(wheelhouse / "wheels")
        pip(
            venv,
            wheelhouse,
            manifest,
            "install",
            "--no-index",
            "--find-links",
            links,
            "--no-cache-dir",
            "--no-warn-script-location",
            *missing,
        )
        t.note("installed", ", ".join(missing) if len(missing) <= 3 else f"{len(missing)} wheels")
    if stale:
        pip(venv, wheelhouse, manifest, "uninstall", "--yes", *stale)
        t.note("removed", ", ".join(stale))
    return bool(missing or stale)


def relocate(t: Target, venv: Path) -> None:
    """A staged venv names ``<prefix>``, not ``<root>/<prefix>`` (scripts, activate, pyvenv.cfg)."""
    staged, final = str(venv).encode(), t.prefix.encode()
    for p in [venv / "pyvenv.cfg", *sorted((venv / "bin").iterdir())]:
        if p.is_symlink() or not p.is_file():
            continue
        data = p.read_bytes()
        if staged in data and b"\0" not in data:
            mode = p.stat().st_mode & 0o7777
            p.write_bytes(data.replace(staged, final))
            os.chmod(p, mode)


# -- the record ----------------------------------------------------------------------------------


def record_doc(t: Target, manifest: dict, done: list[Entry]) -> dict:
    def one(e: Entry) -> dict:
        d = {k: v for k, v in asdict(e).items() if k not in ("source",) and v is not None}
        d["mode"] = f"{e.mode:04o}"
        p = t.at(e.path)
        if e.kind in ("file", "config") and p.is_file():
            d["sha256"] = sha256_of(p)
        return d

    unit = t.at(UNIT)
    return {
        "format": RECORD_FORMAT,
        "project": manifest["project"],
        "version": manifest["version"],
        "prefix": t.prefix,
        "python": manifest["python"],
        "user": USER,
        "group": GROUP,
        "unit": {"path": UNIT, "sha256": sha256_of(unit) if unit.is_file() else None},
        "venv": {"path": t.prefix, "mode": "0755", "owner": "root", "group": "root"},
        "wheels": venv_wheels(manifest),
        "entries": [one(e) for e in done],
    }


def write_record(t: Target, manifest: dict, done: list[Entry]) -> None:
    data = (json.dumps(record_doc(t, manifest, done), indent=2, sort_keys=True) + "\n").encode()
    e = Entry(path=f"{t.prefix}/{RECORD}", kind="file", mode=0o644)
    put_file(t, e, data)


# -- the system: account and reloads -------------------------------------------------------------


def run_tool(t: Target, cmd: list[str]) -> None:
    """A system command; a failure is a warning (the install stands)."""
    if shutil.which(cmd[0]) is None:
        t.log.append(f"skipped   {' '.join(cmd)} ({cmd[0]} not installed)")
        return
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode == 0:
        t.note("ran", " ".join(cmd))
    else:
        t.note("warning", f"{' '.join(cmd)}: exit {r.returncode}: {r.stderr.strip()[:200]}")


def ensure_account(t: Target) -> None:
    """The system group and user ``mls`` (home /var/lib/mls, no login shell)."""
    try:
        pwd.getpwnam(USER)
        return
    except KeyError:
        pass
    cmd = ["useradd", "--system", "--home-dir", HOME, "--no-create-home", "--shell", "/usr/sbin/nologin"]
    try:
        grp.getgrnam(GROUP)
        cmd += ["--gid", GROUP]
    except KeyError:
        cmd += ["--user-group"]
    r = subprocess.run([*cmd, USER], capture_output=True, text=True)
    if r.returncode != 0:
        raise InstallError(f"useradd {USER} failed: {r.stderr.strip()}; create the user, then run again")
    t.note("created", f"user and group {USER}")


def systemd_running(t: Target) -> bool:
    return not t.staged and os.path.isdir("/run/systemd/system")


def reload_system(t: Target, changed: set[str]) -> None:
    if t.staged:
        return
    if systemd_running(t) and changed & {UNIT, "/etc/systemd/system/mls-pps-ldattach@.service"}:
        run_tool(t, ["systemctl", "daemon-reload"])
    if "/etc/sysctl.d/90-mls-net.conf" in changed:
        run_tool(t, ["sysctl", "-p", "/etc/sysctl.d/90-mls-net.conf"])
    if "/etc/udev/rules.d/99-mls-pps.rules" in changed and os.path.exists("/run/udev/control"):
        run_tool(t, ["udevadm", "control", "--reload"])


# -- install, uninstall --------------------------------------------------------------------------


def install(t: Target, wheelhouse: Path, python: str) -> None:
    manifest = load_manifest(wheelhouse)
    verify_wheelhouse(wheelhouse, manifest)
    version = python_version(python)
    if version != manifest["python"]:
        raise InstallError(
            f"{python} is Python {version}, the wheelhouse was built for {manifest['python']}: "
            f"pass --python python{manifest['python']}, or build the wheelhouse with this Python"
        )
    if not t.staged:
        ensure_account(t)
    venv = ensure_venv(t, python, version)
    if sync_wheels(t, venv, wheelhouse, manifest) and t.staged:
        relocate(t, venv)
    plan = entries(t.prefix)
    changed = set()
    for e in plan:
        if e.kind == "dir":
            done = put_dir(t, e)
        elif e.kind == "symlink":
            done = put_symlink(t, e)
        else:
            done = put_file(t, e, content(e, wheelhouse, t.prefix))
        if done:
            changed.add(e.path)
    write_record(t, manifest, plan)
    reload_system(t, changed)


def uninstall(t: Target) -> list[str]:
    """Remove what :func:`install` made but the config, the sessions and the user; returns what
    was kept."""
    if systemd_running(t) and t.at(UNIT).exists():
        run_tool(t, ["systemctl", "disable", "--now", "mls-acquire.service"])
    kept = []
    for e in reversed(entries(t.prefix)):
        p = t.at(e.path)
        if e.keep:
            if p.exists():
                kept.append(e.path)
            continue
        if e.kind == "symlink" and not (p.is_symlink() and os.readlink(p) == e.target):
            continue
        if p.is_file() or p.is_symlink():
            p.unlink()
            t.note("removed", e.path)
    venv = t.at(t.prefix)
    if (venv / "pyvenv.cfg").is_file():
        shutil.rmtree(venv)
        t.note("removed", f"{t.prefix} (venv)")
    if systemd_running(t):
        run_tool(t, ["systemctl", "daemon-reload"])
    return kept


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    here = Path(__file__).resolve().parent
    ap = argparse.ArgumentParser(description="Install marine-mls from its offline wheelhouse (run as root).")
    ap.add_argument("--wheelhouse", type=Path, default=here, help="the wheelhouse directory [this script's]")
    ap.add_argument("--prefix", default=DEFAULT_PREFIX, help=f"the venv [{DEFAULT_PREFIX}]")
    ap.add_argument("--root", type=Path, default=Path("/"), help="stage the tree under this directory [/]")
    ap.add_argument("--python", default=sys.executable, help="the Python of the venv [this one]")
    ap.add_argument(
        "--uninstall", action="store_true", help="remove the software; keep config, sessions, user"
    )
    args = ap.parse_args(argv)
    if not args.prefix.startswith("/"):
        ap.error(f"--prefix {args.prefix}: an absolute path")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    os.umask(0o022)  # the venv readable by the daemon's user whatever root's umask
    root = args.root.resolve()
    t = Target(root=root, prefix=args.prefix.rstrip("/") or "/", staged=root != Path("/"), log=[])
    if not t.staged and os.geteuid() != 0:
        print(
            "install.py: run it as root (sudo python3 install.py), or stage with --root DIR", file=sys.stderr
        )
        return 1
    kept: list[str] = []
    try:
        if args.uninstall:
            kept = uninstall(t)
        else:
            install(t, args.wheelhouse.resolve(), args.python)
    except (InstallError, OSError) as e:
        print("\n".join(t.log))
        print(f"install.py: {e}", file=sys.stderr)
        return 1
    print("\n".join(t.log) if t.log else "nothing to change: already installed as the wheelhouse says")
    where = f" (staged under {root})" if t.staged else ""
    if args.uninstall:
        print(f"uninstalled{where}; kept: {', '.join(kept) or 'nothing'} and the user {USER}")
    else:
        print(
            f"marine-mls installed in {t.prefix}{where}. Next: edit /etc/mls/vessel.yaml, run "
            "`mls doctor --config /etc/mls/vessel.yaml`, then `systemctl enable --now mls-acquire`"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
