"""One daemon per config (acquire/daemon/pidlock.py): a second ``mls acquire`` on the same config
is refused with the holder's PID before it touches the session directory or the status socket,
the first stays reachable; a stale lock left by a dead daemon is taken over with a warning."""

from __future__ import annotations

import asyncio
import json
import logging
import os
import signal
import socket
import subprocess
import textwrap
from pathlib import Path

import pytest

from acquire.daemon.config import load_vessel_config
from acquire.daemon.pidlock import LockHeld, PidLock, lock_path_for, read_holder
from acquire.daemon.supervisor import Supervisor
from acquire.log.read import iter_messages
from acquire.log.recover import session_dirs
from acquire.status.bus import read_snapshot
from tests.acquire.daemon_util import MLS, ROOT, Proc, free_port, wait_until
from tests.waiting import wait_until_async

pytestmark = [pytest.mark.integration]


def _config(tmp: Path) -> Path:
    cfg = tmp / "vessel.yaml"
    cfg.write_text(
        textwrap.dedent(f"""\
        vessel: lock-1
        devices:
          - {{name: ins, kind: ins, protocol: nmea, transport: {{type: udp, host: 127.0.0.1, port: {free_port()}}}}}
          - {{name: pps, kind: pps, source: {{type: udp, host: 127.0.0.1, port: {free_port()}}}, time_device: ins}}
        session: {{directory: sessions}}
        status: {{socket: run/status.sock, period_s: 0.5}}
        """)
    )
    return cfg


def _mls(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([*MLS, *args], capture_output=True, text=True, cwd=ROOT, timeout=60)


def _running(sock: Path) -> bool:
    try:
        return read_snapshot(sock, 1.0).get("status", {}).get("state") == "running"
    except (OSError, ValueError):
        return False


def _dead_pid() -> int:
    p = subprocess.Popen(["true"])
    p.wait()
    return p.pid


def test_a_second_daemon_on_the_same_config_is_refused_and_the_first_stays_reachable(tmp_path):
    cfg = _config(tmp_path)
    sock, lock = tmp_path / "run" / "status.sock", tmp_path / "run" / "status.sock.lock"
    first = Proc([*MLS, "acquire", "--config", str(cfg)], tmp_path / "first.log")
    try:
        wait_until(lambda: _running(sock), 60, "the first daemon running", first)
        sessions = session_dirs(tmp_path / "sessions")
        assert len(sessions) == 1
        holder = read_holder(lock)
        assert holder.pid == first.pid and holder.host == socket.gethostname() and holder.started_utc

        second = _mls("acquire", "--config", str(cfg))
        assert second.returncode == 1, second.stderr
        assert "mls acquire: cannot start: daemon lock:" in second.stderr
        assert f"pid {first.pid}" in second.stderr and str(lock) in second.stderr
        assert session_dirs(tmp_path / "sessions") == sessions  # no junk session
        assert sorted(p.name for p in (tmp_path / "sessions").iterdir()) == [sessions[0].name]
        assert sock.is_socket() and first.alive()
        st = _mls("status", "--config", str(cfg), "--json")
        assert st.returncode in (0, 2), st.stderr  # reachable (2: a critical alarm is active)
        status = json.loads(st.stdout)["status"]
        assert status["state"] == "running" and status["pid"] == first.pid
        assert read_holder(lock).pid == first.pid

        first.signal(signal.SIGTERM)
        assert first.wait(30) == 0, first.output()[-3000:]
    finally:
        first.kill()
    assert not sock.exists()
    assert lock.exists() and lock.read_text() == ""  # released: no stale holder for the next start
    assert "took over" not in first.output()


def test_a_stale_lock_of_a_dead_daemon_is_taken_over_with_a_warning(tmp_path, caplog):
    cfg = load_vessel_config(_config(tmp_path))
    lock = lock_path_for(cfg.status.socket)
    lock.parent.mkdir(parents=True)
    dead = _dead_pid()
    stale = {"pid": dead, "host": socket.gethostname(), "started_utc": "2025-01-01T00:00:00+00:00"}
    lock.write_text(json.dumps(stale) + "\n")
    out = {}

    async def scenario():
        sup = Supervisor(cfg)
        task = asyncio.create_task(sup.run())
        await wait_until_async(lambda: sup.state == "running" or task.done(), 10, "the daemon to run")
        out["holder"] = read_holder(lock)
        out["stale"] = sup.stale_lock
        out["session"] = sup.writer.session_dir
        sup.request_stop("test")
        out["rc"] = await task

    with caplog.at_level(logging.WARNING, logger="mls.acquire"):
        asyncio.run(scenario())
    assert out["rc"] == 0
    assert out["holder"].pid == os.getpid()
    assert out["stale"]["pid"] == dead and out["stale"]["path"] == str(lock)
    warnings = [r.getMessage() for r in caplog.records if "took over the stale lock" in r.getMessage()]
    assert len(warnings) == 1 and f"pid {dead}" in warnings[0] and "is no longer running" in warnings[0]
    (start,) = [
        m.payload
        for m in iter_messages(out["session"], topics=["/events"])
        if m.payload["event"] == "session_start"
    ]
    assert start["stale_lock"]["pid"] == dead
    assert lock.read_text() == ""


def test_the_lock_names_its_holder_and_an_orderly_release_empties_it(tmp_path):
    path = tmp_path / "status.sock.lock"
    a = PidLock(path, "vessel.yaml")
    assert a.acquire() is None
    with pytest.raises(LockHeld) as e:
        PidLock(path).acquire()  # a second open file description: refused like another process
    assert f"pid {os.getpid()}" in str(e.value) and str(path) in str(e.value)
    assert "config vessel.yaml" in str(e.value)
    a.release()
    assert path.read_text() == ""
    b = PidLock(path)
    assert b.acquire() is None  # empty: nothing stale to report
    b.release()


# -- the files a root daemon opens: never through a symlink, never another user's -------------------


def test_a_symlink_at_the_lock_path_is_refused_and_its_target_left_whole(tmp_path):
    from acquire.status.runfiles import UnsafeRunFile

    target = tmp_path / "precious"
    target.write_text("do not truncate me\n")
    run = tmp_path / "run"
    run.mkdir()
    lock = run / "status.sock.lock"
    lock.symlink_to(target)
    with pytest.raises(UnsafeRunFile, match="symbolic link: refused") as e:
        PidLock(lock).acquire()
    assert isinstance(e.value, OSError) and "\n" not in str(e.value)  # the supervisor's StartupError
    assert target.read_text() == "do not truncate me\n" and lock.is_symlink()


def test_a_hard_link_or_another_users_lock_file_is_refused(tmp_path):
    from acquire.status.runfiles import UnsafeRunFile

    target = tmp_path / "precious"
    target.write_text("keep\n")
    lock = tmp_path / "run" / "status.sock.lock"
    lock.parent.mkdir()
    os.link(target, lock)
    with pytest.raises(UnsafeRunFile, match="2 hard links"):
        PidLock(lock).acquire()
    assert target.read_text() == "keep\n"
    if os.geteuid() == 0:  # root can give the file away: another user's lock file
        lock.unlink()
        lock.write_text("")
        os.chown(lock, 65534, 65534)
        with pytest.raises(UnsafeRunFile, match="belongs to uid 65534"):
            PidLock(lock).acquire()


def test_a_run_directory_others_can_write_is_refused_unless_sticky(tmp_path):
    from acquire.status.runfiles import UnsafeRunFile

    run = tmp_path / "run"
    run.mkdir()
    os.chmod(run, 0o777)
    with pytest.raises(UnsafeRunFile, match=r"writable by every user \(mode 777, no sticky bit\).*chmod o-w"):
        PidLock(run / "status.sock.lock").acquire()
    assert not (run / "status.sock.lock").exists()
    with pytest.raises(UnsafeRunFile, match="writable by every user"):
        asyncio.run(_serve_once(run / "status.sock"))
    os.chmod(run, 0o1777)  # as /tmp: others cannot replace this user's files
    lock = PidLock(run / "status.sock.lock")
    lock.acquire()
    lock.release()


async def _serve_once(path: Path) -> None:
    from acquire.status.bus import StatusServer

    async with StatusServer(path):
        pass


def test_the_status_socket_path_must_be_a_socket_of_this_user(tmp_path):
    from acquire.status.runfiles import UnsafeRunFile

    target = tmp_path / "precious"
    target.write_text("keep\n")
    sock = tmp_path / "run" / "status.sock"
    sock.parent.mkdir()
    sock.symlink_to(target)
    with pytest.raises(UnsafeRunFile, match="symbolic link"):
        asyncio.run(_serve_once(sock))
    assert sock.is_symlink() and target.read_text() == "keep\n"
    os.chmod(target, 0o600)
    sock.unlink()
    sock.mkdir()
    with pytest.raises(UnsafeRunFile, match="not a socket: refused \\(not removed\\)"):
        asyncio.run(_serve_once(sock))
    assert sock.is_dir() and oct(target.stat().st_mode & 0o777) == "0o600"
    sock.rmdir()
    asyncio.run(_serve_once(sock))  # a stale socket or none: served, then removed
    assert not sock.exists()


def test_mls_acquire_refuses_a_symlinked_lock_in_one_line(tmp_path):
    cfg = _config(tmp_path)
    target = tmp_path / "precious"
    target.write_text("keep\n")
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "status.sock.lock").symlink_to(target)
    r = _mls("acquire", "--config", str(cfg))
    assert r.returncode == 1, r.stderr
    assert "mls acquire: cannot start: daemon lock:" in r.stderr and "symbolic link" in r.stderr
    assert "Traceback" not in r.stderr and target.read_text() == "keep\n"
    assert not (tmp_path / "sessions").exists() or not any((tmp_path / "sessions").iterdir())
