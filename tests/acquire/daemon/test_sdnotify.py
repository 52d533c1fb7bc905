"""sd_notify against a real AF_UNIX datagram socket (path and abstract), and the health watchdog."""

from __future__ import annotations

import os
import socket

import pytest

from acquire.daemon import sdnotify
from acquire.daemon.sdnotify import HealthWatchdog, notify, watchdog_period_s

pytestmark = pytest.mark.integration  # real Unix sockets


@pytest.fixture(params=["path", "abstract"])
def notify_socket(request, tmp_path, monkeypatch):
    s = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    if request.param == "path":
        name = str(tmp_path / "notify.sock")
        s.bind(name)
    else:
        abstract = f"mls-test-{os.getpid()}-{id(s)}"
        s.bind(b"\0" + abstract.encode())
        name = "@" + abstract
    s.settimeout(2.0)
    monkeypatch.setenv("NOTIFY_SOCKET", name)
    yield s
    s.close()


def test_ready_status_stopping_reach_the_socket(notify_socket):
    assert sdnotify.ready("serving 4 devices")
    assert notify_socket.recv(4096) == b"READY=1\nSTATUS=serving 4 devices"
    assert sdnotify.status("degraded: PPS lost")
    assert notify_socket.recv(4096) == b"STATUS=degraded: PPS lost"
    assert sdnotify.stopping()
    assert notify_socket.recv(4096) == b"STOPPING=1"


def test_watchdog_pings_only_while_every_check_passes(notify_socket):
    health = {"writer": (True, "ok")}
    wd = HealthWatchdog({"drivers": lambda: (True, "4/4 alive"), "writer": lambda: health["writer"]})
    assert wd.beat()
    assert notify_socket.recv(4096) == b"STATUS=running"  # first beat: state change
    assert notify_socket.recv(4096) == b"WATCHDOG=1"
    assert wd.beat() and notify_socket.recv(4096) == b"WATCHDOG=1"
    health["writer"] = (False, "log writer stalled for 12.0 s")
    assert not wd.beat()
    assert notify_socket.recv(4096) == b"STATUS=unhealthy: writer: log writer stalled for 12.0 s"
    assert not wd.beat()  # no ping, no repeated status
    notify_socket.settimeout(0.2)
    with pytest.raises(socket.timeout):
        notify_socket.recv(4096)
    wd.add_check("broken", lambda: 1 / 0)
    health["writer"] = (True, "ok")
    assert wd.evaluate() == ["broken: check raised ZeroDivisionError: division by zero"]
    assert wd.pings == 2


def test_an_advisory_is_named_in_status_but_never_withholds_the_ping(notify_socket):
    """A device that is not connected: systemd shows it (STATUS=), the watchdog keeps pinging
    (a restart would not bring the device back)."""
    down = {"ins": "[Errno 2] could not open port /dev/ttyUSB9: [Errno 2] No such file or directory"}

    def devices():
        return (not down, "; ".join(f"{n} not connected: {e}" for n, e in down.items()))

    health = {"log": (True, "ok")}
    wd = HealthWatchdog({"log": lambda: health["log"]}, advisories={"devices": devices})
    assert wd.beat()
    assert notify_socket.recv(4096) == (
        b"STATUS=running, degraded: devices: ins not connected: [Errno 2] could not open port "
        b"/dev/ttyUSB9: [Errno 2] No such file or directory"
    )
    assert notify_socket.recv(4096) == b"WATCHDOG=1"
    assert wd.beat() and notify_socket.recv(4096) == b"WATCHDOG=1"  # no repeated status
    health["log"] = (False, "log writer stalled")
    assert not wd.beat()
    assert notify_socket.recv(4096) == (
        b"STATUS=unhealthy: log: log writer stalled; devices: ins not connected: [Errno 2] could not "
        b"open port /dev/ttyUSB9: [Errno 2] No such file or directory"
    )
    health["log"] = (True, "ok")
    down.clear()
    assert wd.beat()
    assert notify_socket.recv(4096) == b"STATUS=running"
    assert notify_socket.recv(4096) == b"WATCHDOG=1"
    assert wd.pings == 3


def test_outside_systemd_nothing_is_sent(monkeypatch):
    monkeypatch.delenv("NOTIFY_SOCKET", raising=False)
    assert notify("READY=1") is False
    assert HealthWatchdog({"ok": lambda: (True, "")}).beat() is True


def test_watchdog_period_from_the_environment():
    assert watchdog_period_s({"WATCHDOG_USEC": "30000000"}) == 30.0
    assert watchdog_period_s({"WATCHDOG_USEC": "30000000", "WATCHDOG_PID": str(os.getpid())}) == 30.0
    assert watchdog_period_s({"WATCHDOG_USEC": "30000000", "WATCHDOG_PID": "1"}) is None
    assert watchdog_period_s({}) is None
