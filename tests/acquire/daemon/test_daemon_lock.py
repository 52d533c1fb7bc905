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
        for _ in range(200):
            if sup.state == "running":
                break
            await asyncio.sleep(0.05)
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
