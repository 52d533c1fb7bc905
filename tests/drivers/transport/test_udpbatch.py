"""The ``udp-batch`` transport on real sockets: every datagram in order with kernel receive
stamps, reading paused (not dropping) while the consumer lags, truncation counted."""

from __future__ import annotations

import asyncio
import socket
import time

import pytest

from drivers.transport import recvmmsg
from drivers.transport.base import Chunk
from drivers.transport.registry import create_transport
from drivers.transport.udp_batch import BatchUdpTransport
from tests.drivers.helpers import (
    fake_host_clock,
    queued_bytes,
    send_each_arrived,
    step_host_clock,
    wait_for_kernel_rx_stamps,
)
from tests.waiting import wait_until, wait_until_async

pytestmark = pytest.mark.integration


async def _send(port: int, payloads: list[bytes]) -> tuple[int, int]:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    t0 = time.monotonic_ns()
    for p in payloads:
        s.sendto(p, ("127.0.0.1", port))
    t1 = time.monotonic_ns()
    s.close()
    return t0, t1


@pytest.mark.parametrize("use_recvmmsg", [True, False], ids=["recvmmsg", "recvmsg"])
def test_bursts_arrive_complete_in_order_with_kernel_stamps_and_a_lagging_reader_pauses(use_recvmmsg):
    assert recvmmsg.available()  # Linux: the fast path is what the daemon runs

    async def run():
        t = create_transport(
            {
                "kind": "udp-batch",
                "host": "127.0.0.1",
                "port": 0,
                "max_chunks": 64,
                "coalesce_s": 0.005,
                "use_recvmmsg": use_recvmmsg,
            }
        )
        assert isinstance(t, BatchUdpTransport)
        await t.open()
        assert (t._mmsg is not None) == use_recvmmsg
        assert t.kernel_stamps
        assert "kernel receive stamps" in t.describe()
        wait_for_kernel_rx_stamps()  # the kernel turns receive stamping on asynchronously
        payloads = [i.to_bytes(4, "little") * 300 for i in range(3000)]  # 1.2 kB each
        t0, t1 = await _send(t.port, payloads)
        await wait_until_async(lambda: t._paused, 10, "the reader to pause")
        assert len(t._chunks) == 64  # paused at 64 waiting datagrams
        got: list[Chunk] = []
        while len(got) < len(payloads):
            got.append(await asyncio.wait_for(t.read(), 5))
        t2 = time.monotonic_ns()
        assert [d for d, _ in got] == payloads
        stamps = [h for _, h in got]
        assert stamps == sorted(stamps)
        # at arrival, not at read
        assert t0 - 1_000_000 <= stamps[0]
        assert stamps[-1] <= t1 + 1_000_000 < t2
        assert t.stats.events.get("dropped_datagrams", 0) == 0
        assert t.stats.records == 3000
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.sendto(b"x" * 65000, ("127.0.0.1", t.port))
        s.sendto(b"after", ("127.0.0.1", t.port))
        s.close()
        data, _ = await asyncio.wait_for(t.read(), 5)
        await t.close()
        return data, t.stats.rejected

    data, rejected = asyncio.run(run())
    assert data == b"x" * 65000
    assert rejected == {}  # 64 kB fits: nothing truncated


def test_recvmmsg_counts_a_datagram_larger_than_its_slot_and_reads_on():
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.setsockopt(socket.SOL_SOCKET, 35, 1)  # SO_TIMESTAMPNS (Linux; Python lacks the name)
    rx.bind(("127.0.0.1", 0))
    rx.setblocking(False)
    m = recvmmsg.MmsgReceiver(rx, slots=4, max_datagram=1000)
    with pytest.raises(BlockingIOError):
        m.receive()
    wait_for_kernel_rx_stamps()  # the kernel turns receive stamping on asynchronously
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    t0 = time.time_ns()
    send_each_arrived(tx, rx, (b"a" * 10, b"b" * 1500, b"c" * 1000, b"d", b"e" * 7, b"f"))
    t1 = time.time_ns()
    first = m.receive()
    second = m.receive(limit=1)
    third = m.receive()
    assert (first[0], first[2]) == ([b"a" * 10, b"c" * 1000, b"d"], 1)  # 4 slots: one truncated
    assert (second[0], second[2], third[0], third[2]) == ([b"e" * 7], 0, [b"f"], 0)
    stamps = first[1] + second[1] + third[1]
    assert None not in stamps  # each stamped by the kernel
    kernel_ns = [t for t in stamps if t is not None]
    assert all(t0 - 1_000_000 <= t <= t1 + 1_000_000 for t in kernel_ns)
    assert kernel_ns == sorted(kernel_ns)
    tx.close()
    rx.close()


@pytest.mark.parametrize("step_s", [-3600.0, 2.5])
def test_a_realtime_step_while_datagrams_wait_moves_no_stamp(tmp_path, step_s):
    """The host's realtime clock steps (NTP) while the loop is blocked: the datagrams that
    arrived before the step are read after it. Their kernel stamps are still converted to their
    arrival times (the fake host clock of the simulated devices stands in for the step).

    The datagrams come one at a time, each known to have arrived (or to have been read) before
    the next: 10 read before the step; then, the loop held, 10 arrived before the step, the step,
    5 after it; 5 more once the loop reads again. Each stamp must lie between its send and its
    arrival seen (or its read): never a step away."""
    path = tmp_path / "host_clock"

    clock = fake_host_clock(path, [])

    async def run():
        t = BatchUdpTransport(0, host="127.0.0.1", coalesce_s=0.005, host_clock=clock)
        await t.open()
        wait_for_kernel_rx_stamps()
        tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        to = ("127.0.0.1", t.port)
        bounds: list[tuple[int, int]] = []
        got: list[Chunk] = []

        async def one_read(k: int) -> None:  # the loop reads it: arrival before the read
            t0 = time.monotonic_ns()
            tx.sendto(k.to_bytes(4, "little"), to)
            got.append(await asyncio.wait_for(t.read(), 5))
            bounds.append((t0, time.monotonic_ns()))

        for k in range(10):
            await one_read(k)
        # the loop held (no await) from here to the reads below: the socket's queue fills
        sock = t._sock
        assert sock is not None  # (open)
        held = [k.to_bytes(4, "little") for k in range(10, 20)]
        bounds += send_each_arrived(tx, sock, held, to)
        at = time.monotonic_ns() + 2_000_000  # the step, 2 ms after the last arrival ...
        step_host_clock(path, at, round(step_s * 1e9))
        wait_until(lambda: time.monotonic_ns() > at + 2_000_000, 5, "2 ms past the step")
        bounds += send_each_arrived(tx, sock, [k.to_bytes(4, "little") for k in range(20, 25)], to)
        assert queued_bytes(sock) > 0  # ... and 2 ms before the next arrival; all still unread
        got += [await asyncio.wait_for(t.read(), 5) for _ in range(15)]
        for k in range(25, 30):
            await one_read(k)
        tx.close()
        await t.close()
        return bounds, got, t.stamps

    bounds, got, stamps = asyncio.run(run())
    assert [int.from_bytes(d, "little") for d, _ in got] == list(range(30))
    # at arrival (1 ms: the offset's reads), none a step away
    off = [
        (h - lo, hi - h)
        for (lo, hi), (_, h) in zip(bounds, got, strict=True)
        if not lo - 1_000_000 <= h <= hi + 1_000_000
    ]
    assert not off, off
    assert stamps.steps == 1
    assert stamps.repaired == 10
    assert stamps.unknown == 0
