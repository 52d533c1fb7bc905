"""The doctor's device checks, each passing and failing: serial ports (real pseudo-terminals, a
missing path, a file, modes the daemon's user may not use), the PPS — kernel device played
through the driver's ioctl seam, serial line through the same seam (and on a real pty, which has
no modem lines), UDP with real datagrams — and the daemon holding them."""

from __future__ import annotations

import os
import socket
import termios
import threading
import time

import pytest

from acquire.doctor.access import daemon_user, may
from acquire.doctor.pps import pps_check
from acquire.doctor.result import Status
from acquire.doctor.serial import serial_check, serial_devices
from drivers.pps import encode_pps_datagram
from tests.acquire.doctor.helpers import NOBODY, FakePpsKernel, config, free_udp_port

ME = daemon_user("no-such-user-mls-doctor")  # the user running the tests


@pytest.fixture
def pty():
    master, slave = os.openpty()
    yield os.ttyname(slave)
    os.close(master)
    os.close(slave)


# -- serial ports -------------------------------------------------------------------------------


def test_a_pty_is_present_and_openable(pty):
    r = serial_check("ins", pty, ME, daemon_running=False)
    assert r.status == Status.OK and "openable" in r.message and r.device == "ins"
    assert r.data["mode"].startswith("c")


def test_a_missing_serial_path_fails_naming_where_to_look(tmp_path):
    r = serial_check("ins", str(tmp_path / "ttyUSB9"), ME, daemon_running=False)
    assert r.status == Status.FAIL and "No such file" in r.message and "/dev/serial/by-id" in r.advice


def test_a_plain_file_is_no_serial_port(tmp_path):
    (tmp_path / "tty").write_text("")
    r = serial_check("ins", str(tmp_path / "tty"), ME, daemon_running=False)
    assert r.status == Status.FAIL and "not a character device" in r.message


def test_a_port_the_daemons_user_may_not_open(pty):
    st = os.stat(pty)
    assert not may(st, NOBODY, 6)  # a pty: the owner's and group tty's only
    r = serial_check("ins", pty, NOBODY, daemon_running=False)
    assert r.status == Status.FAIL and "may not read and write" in r.message and "dialout" in r.advice


def test_a_port_the_running_daemon_holds_is_not_opened(pty):
    r = serial_check("ins", pty, ME, daemon_running=True)
    assert r.status == Status.OK and "running daemon" in r.message


def test_serial_devices_of_a_config(tmp_path):
    cfg = config(
        tmp_path,
        ins="{type: serial, port: /dev/ttyUSB0, baud: 115200}",
        pps="{type: serial-line, port: /dev/ttyS0, line: dcd}",
    )
    assert serial_devices(cfg) == [("ins", "/dev/ttyUSB0"), ("pps", "/dev/ttyS0")]


# -- PPS: kernel device --------------------------------------------------------------------------


def kernel_pps(tmp_path, path=None):
    dev = path or tmp_path / "pps0"
    if path is None:
        dev.write_bytes(b"")  # the fake kernel answers the ioctl; the open is real
    cfg = config(tmp_path, pps=f"{{type: kernel, device: {dev}}}")
    return cfg.device("pps")


@pytest.mark.parametrize(
    ("intervals_s", "status", "text"),
    [
        ([1.0], Status.OK, "pulsing (1.000 s apart)"),
        ([0.3], Status.WARN, "0.300 s apart"),
        ([], Status.WARN, "one pulse"),
    ],
)
def test_kernel_pps_pulses(tmp_path, intervals_s, status, text):
    fake = FakePpsKernel(intervals_s)
    r = pps_check(kernel_pps(tmp_path), ME, False, wait_s=0.5 if status != Status.OK else 5.0, ioctl=fake)
    assert r.status == status and text in r.message, r.message
    assert r.data["pulses"] == len(intervals_s) + 1


def test_kernel_pps_without_pulses_fails(tmp_path):
    fake = FakePpsKernel([])
    fake.stamps = []
    r = pps_check(kernel_pps(tmp_path), ME, False, wait_s=0.3, ioctl=fake)
    assert r.status == Status.FAIL and "no pulse in 0.3 s" in r.message and "ppstest" in r.advice


def test_kernel_pps_device_missing_or_unreadable(tmp_path):
    r = pps_check(kernel_pps(tmp_path, tmp_path / "pps7"), ME, False, wait_s=0.3)
    assert r.status == Status.FAIL and "No such file" in r.message and "99-mls-pps.rules" in r.advice
    dev = kernel_pps(tmp_path)
    os.chmod(tmp_path / "pps0", 0o600)
    r = pps_check(dev, NOBODY, False, wait_s=0.3)
    assert r.status == Status.FAIL and "may not read" in r.message and 'GROUP="dialout"' in r.advice


def test_a_file_that_is_no_pps_device_fails_on_the_real_ioctl(tmp_path):
    r = pps_check(kernel_pps(tmp_path), ME, False, wait_s=2.0)
    assert r.status == Status.FAIL and "PPS_FETCH" in r.message


# -- PPS: serial line ------------------------------------------------------------------------------


def test_serial_line_pps_on_a_pty_has_no_modem_lines(tmp_path, pty):
    dev = config(tmp_path, pps=f"{{type: serial-line, port: {pty}, line: dcd}}").device("pps")
    r = pps_check(dev, ME, False, wait_s=2.0)
    assert r.status == Status.FAIL and "not a UART" in r.message


def test_serial_line_pps_pulsing(tmp_path, pty):
    """DCD played by the driver's ioctl seam: it rises once a second, as a GNSS PPS does."""
    import struct

    start, period_s = time.monotonic(), 1.0
    state = {"edges": 0}
    quiet = threading.Event()  # never set: waiting for the next edge is the UART's blocking ioctl

    def fake_ioctl(fd, request, arg):
        if request == termios.TIOCMGET:
            return struct.pack("i", termios.TIOCM_CD if state["edges"] % 2 else 0)
        quiet.wait(
            max(0.0, start + period_s * (state["edges"] // 2 + 1) - time.monotonic())
            if state["edges"] % 2 == 0
            else 0.0
        )
        state["edges"] += 1
        return 0

    dev = config(tmp_path, pps=f"{{type: serial-line, port: {pty}, line: dcd}}").device("pps")
    r = pps_check(dev, ME, False, wait_s=5.0, ioctl=fake_ioctl)
    assert r.status == Status.OK and 0.9 <= r.data["interval_s"] <= 1.1, r.message


# -- PPS: UDP (the emulators' source) ------------------------------------------------------------


def test_udp_pps_pulsing_with_real_datagrams(tmp_path):
    port = free_udp_port()
    dev = config(tmp_path, pps=f"{{type: udp, host: 127.0.0.1, port: {port}}}").device("pps")
    done = threading.Event()

    def emulator():
        # datagrams carry their own host stamps, one GPS second apart, sent until the check ends
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            seq, t0 = 0, time.monotonic_ns()
            while not done.wait(0.01):
                seq += 1
                s.sendto(encode_pps_datagram(seq, t0 + seq * 1_000_000_000), ("127.0.0.1", port))

    th = threading.Thread(target=emulator, daemon=True)
    th.start()
    try:
        r = pps_check(dev, ME, False, wait_s=5.0)
    finally:
        done.set()
        th.join(5)
    assert r.status == Status.OK and r.data["interval_s"] == 1.0, r.message


def test_udp_pps_silent_busy_or_held_by_the_daemon(tmp_path):
    port = free_udp_port()
    dev = config(tmp_path, pps=f"{{type: udp, host: 127.0.0.1, port: {port}}}").device("pps")
    r = pps_check(dev, ME, False, wait_s=0.3)
    assert r.status == Status.FAIL and "no pulse" in r.message
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as other:
        other.bind(("127.0.0.1", port))
        r = pps_check(dev, ME, False, wait_s=0.3)
        assert r.status == Status.FAIL and "Errno 98" in r.message
        r = pps_check(dev, ME, True, wait_s=0.3)
        assert r.status == Status.OK and "running daemon" in r.message
