"""The session root (``session.directory``) is checked at start-up: another user's directory or
one every user may write (sticky bit or not: the daemon salvages every session it finds there)
is refused with one line naming the path, the owner and mode found and the fix, before a
session is made; a missing root is made, this user's and not writable by others."""

from __future__ import annotations

import os
import stat
import subprocess
import textwrap
from pathlib import Path

import pytest

from acquire.status.runfiles import UnsafeRunFile, check_session_root
from tests.acquire.daemon_util import MLS, ROOT, free_port

pytestmark = pytest.mark.integration
as_root = pytest.mark.skipif(os.geteuid() != 0, reason="giving a directory to another user takes root")


def _config(tmp: Path, root: Path) -> Path:
    cfg = tmp / "vessel.yaml"
    cfg.write_text(
        textwrap.dedent(f"""\
        vessel: root-1
        devices:
          - {{name: ins, kind: ins, protocol: nmea, transport: {{type: udp, host: 127.0.0.1, port: {free_port()}}}}}
        session: {{directory: {root}}}
        status: {{socket: {tmp}/status.sock}}
        """)
    )
    return cfg


def _acquire(cfg: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [*MLS, "acquire", "--config", str(cfg)], capture_output=True, text=True, cwd=ROOT, timeout=60
    )


@pytest.mark.parametrize("mode", [0o777, 0o1777])
def test_a_session_root_every_user_can_write_is_refused_in_one_line(tmp_path, mode):
    root = tmp_path / "sessions"
    root.mkdir()
    os.chmod(root, mode)
    r = _acquire(_config(tmp_path, root))
    assert r.returncode == 1, r.stderr
    (line,) = r.stderr.strip().splitlines()
    assert line.startswith(f"mls acquire: cannot start: session directory: {root}: the session root")
    assert f"(owner uid {os.geteuid()}) is writable by every user (mode {mode:o}" in line
    assert f"chmod o-w {root}" in line and "choose another session.directory" in line
    assert list(root.iterdir()) == []  # no session made, nothing salvaged
    assert not (tmp_path / "status.sock").exists()


@as_root
def test_a_session_root_of_another_user_is_refused_in_one_line(tmp_path):
    root = tmp_path / "sessions"
    root.mkdir()
    os.chown(root, 65534, 65534)
    r = _acquire(_config(tmp_path, root))
    assert r.returncode == 1, r.stderr
    (line,) = r.stderr.strip().splitlines()
    assert f"{root}: the session root belongs to uid 65534 (mode 755)" in line
    assert f"not to this user (uid 0) or root: refused; give it to this user (chown 0 {root})" in line
    assert list(root.iterdir()) == []


def test_a_missing_session_root_is_made_private_and_accepted(tmp_path):
    root = tmp_path / "data" / "sessions"
    old = os.umask(0)  # even with no umask, the root is not made writable by others
    try:
        check_session_root(root)
    finally:
        os.umask(old)
    st = os.stat(root)
    assert st.st_uid == os.geteuid() and stat.S_IMODE(st.st_mode) == 0o755
    check_session_root(root)  # as found the next time


def test_the_session_roots_a_daemon_may_use(tmp_path):
    for mode in (0o700, 0o755, 0o775):  # group-writable: the operators' group, as before
        root = tmp_path / f"ok-{mode:o}"
        root.mkdir()
        os.chmod(root, mode)
        check_session_root(root)
    os.chmod(root, 0o1777)
    with pytest.raises(UnsafeRunFile, match="sticky bit, not enough here"):
        check_session_root(root)


@as_root
def test_a_root_owned_session_root_is_accepted_as_the_run_directory_is(tmp_path):
    root = tmp_path / "by-root"
    root.mkdir()
    os.chown(root, 0, 0)
    check_session_root(root)
