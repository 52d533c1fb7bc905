"""Shared helpers for the driver tests: the real captures in ``tests/data/real`` (see its README),
and the fake host clock of the simulated devices, handed to what reads the host clock."""

from __future__ import annotations

import os
import select
import socket
import struct
import time
from pathlib import Path

import pytest
from hypothesis import HealthCheck, settings

from drivers.timing import FakeHostClock
from tests.waiting import wait_until

#: real device captures shipped with the tests (licences and provenance beside them)
REAL = Path(__file__).resolve().parents[1] / "data" / "real"

#: hypothesis settings for the decoder properties (the folder must stay fast on 2 cores)
PROPERTY = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def real_file(*parts: str) -> Path:
    path = REAL.joinpath(*parts)
    if not path.is_file():
        pytest.fail(f"real capture {path} is missing: the repository ships it under tests/data/real")
    return path


def real_dir(*parts: str) -> Path:
    path = REAL.joinpath(*parts)
    if not path.is_dir():
        pytest.fail(f"real capture folder {path} is missing: the repository ships it under tests/data/real")
    return path


def fake_host_clock(path: Path, steps: list[tuple[int, int]]) -> FakeHostClock:
    """A :class:`~drivers.timing.FakeHostClock` on ``path`` with these ``(host monotonic ns,
    step ns)`` steps, its file looked at on every read, to hand to what reads the host clock
    (nothing else sees it)."""
    path.write_text("# host_monotonic_ns step_ns\n" + "".join(f"{t} {s}\n" for t, s in steps))
    return FakeHostClock(str(path), poll_ns=0)


def step_host_clock(path: Path, at_ns: int, step_ns: int) -> None:
    """Add a step of ``step_ns`` at host monotonic ``at_ns`` to the fake host clock's file
    (:func:`fake_host_clock`), as the emulators do: a step whose instant has passed when it is
    written happened then. The file's mtime is moved on by a nanosecond, so that the
    :class:`~drivers.timing.FakeHostClock` re-reads it even within the file system's timestamp
    granularity."""
    before = path.stat().st_mtime_ns
    with open(path, "a", encoding="utf-8") as f:
        f.write(f"{at_ns} {step_ns}\n")
    st = path.stat()
    os.utime(path, ns=(st.st_atime_ns, max(st.st_mtime_ns, before + 1)))


def realtime_offset_bounds_ns(tries: int = 5) -> tuple[int, int]:
    """``CLOCK_REALTIME − CLOCK_MONOTONIC`` as bounds ``(lo, hi)``: from the narrowest of
    ``tries`` monotonic–realtime–monotonic brackets, so that a preemption between the reads (a
    loaded machine) widens the bounds instead of shifting a single estimate."""
    best = None
    for _ in range(tries):
        a = time.monotonic_ns()
        r = time.clock_gettime_ns(time.CLOCK_REALTIME)
        b = time.monotonic_ns()
        if best is None or b - a < best[1] - best[0]:
            best = (r - b, r - a)
    assert best is not None
    return best


_SO_TIMESTAMPNS = 35  # Linux (Python lacks the names)
_SO_MEMINFO = 55


def wait_for_kernel_rx_stamps(timeout_s: float = 10.0) -> None:
    """Wait until the kernel stamps datagrams as they arrive. The first socket that asks for
    ``SO_TIMESTAMPNS`` turns stamping on a moment later (a deferred work item); until then a
    datagram is stamped when it is read. Call it while the socket under test is open (it keeps
    stamping on): a probe datagram, once readable, must carry a stamp older than the read."""
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        rx.setsockopt(socket.SOL_SOCKET, _SO_TIMESTAMPNS, 1)
        rx.bind(("127.0.0.1", 0))

        def stamped_on_arrival() -> bool:
            tx.sendto(b"probe", rx.getsockname())
            if not select.select([rx], [], [], 5.0)[0]:
                return False
            read_ns = time.time_ns()  # after the datagram was there: a stamp of the read is later
            _, anc, _, _ = rx.recvmsg(16, socket.CMSG_SPACE(16))
            stamps = [struct.unpack_from("@qq", v) for lvl, kind, v in anc if kind == _SO_TIMESTAMPNS]
            return bool(stamps) and stamps[0][0] * 1_000_000_000 + stamps[0][1] < read_ns

        wait_until(stamped_on_arrival, timeout_s, "the kernel's receive stamps", interval_s=0.001)
    finally:
        rx.close()
        tx.close()


def queued_bytes(sock: socket.socket) -> int:
    """Memory of the datagrams waiting in ``sock``'s receive queue (``SO_MEMINFO``): it grows
    when a datagram has arrived, before anything reads it."""
    return struct.unpack("9I", sock.getsockopt(socket.SOL_SOCKET, _SO_MEMINFO, 36))[0]


def send_each_arrived(tx: socket.socket, rx: socket.socket, payloads, to=None) -> list[tuple[int, int]]:
    """Send each payload from ``tx`` to ``rx`` and wait until it is in ``rx``'s receive queue (a
    loopback datagram may be delivered by the kernel's softirq thread after ``sendto`` returns);
    nothing may read ``rx`` meanwhile. Returns (monotonic ns before the send, after the arrival
    was seen) of each: bounds of its arrival."""
    out = []
    for p in payloads:
        queued = queued_bytes(rx)
        t0 = time.monotonic_ns()
        tx.sendto(p, to or rx.getsockname())
        wait_until(lambda q=queued: queued_bytes(rx) > q, 10, "the datagram to arrive", interval_s=0.0005)
        out.append((t0, time.monotonic_ns()))
    return out
