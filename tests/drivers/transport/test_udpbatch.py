"""The ``udp-batch`` transport on real sockets: every datagram in order with kernel receive
stamps, reading paused (not dropping) while the consumer lags, truncation counted."""

from __future__ import annotations

import asyncio
import socket
import time

import pytest

from drivers.transport import recvmmsg
from drivers.transport.registry import create_transport
from tests.drivers.helpers import fake_host_clock

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
        await t.open()
        assert (t._mmsg is not None) == use_recvmmsg
        assert t.kernel_stamps and "kernel receive stamps" in t.describe()
        await asyncio.sleep(0.1)  # the kernel turns receive stamping on asynchronously
        payloads = [i.to_bytes(4, "little") * 300 for i in range(3000)]  # 1.2 kB each
        t0, t1 = await _send(t.port, payloads)
        await asyncio.sleep(0.2)  # the reader has paused at 64 waiting datagrams
        assert len(t._chunks) == 64
        got = []
        while len(got) < len(payloads):
            got.append(await asyncio.wait_for(t.read(), 5))
        t2 = time.monotonic_ns()
        assert [d for d, _ in got] == payloads
        stamps = [h for _, h in got]
        assert stamps == sorted(stamps)
        assert t0 - 1_000_000 <= stamps[0] and stamps[-1] <= t1 + 1_000_000 < t2  # at arrival, not at read
        assert t.stats.events.get("dropped_datagrams", 0) == 0 and t.stats.records == 3000
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.sendto(b"x" * 65000, ("127.0.0.1", t.port))
        s.sendto(b"after", ("127.0.0.1", t.port))
        s.close()
        data, _ = await asyncio.wait_for(t.read(), 5)
        await t.close()
        return data, t.stats.rejected

    data, rejected = asyncio.run(run())
    assert data == b"x" * 65000 and rejected == {}  # 64 kB fits: nothing truncated


def test_recvmmsg_counts_a_datagram_larger_than_its_slot_and_reads_on():
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.setsockopt(socket.SOL_SOCKET, 35, 1)  # SO_TIMESTAMPNS (Linux; Python lacks the name)
    rx.bind(("127.0.0.1", 0))
    rx.setblocking(False)
    m = recvmmsg.MmsgReceiver(rx, slots=4, max_datagram=1000)
    with pytest.raises(BlockingIOError):
        m.receive()
    time.sleep(0.1)  # the kernel turns receive stamping on asynchronously
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    t0 = time.time_ns()
    for p in (b"a" * 10, b"b" * 1500, b"c" * 1000, b"d", b"e" * 7, b"f"):
        tx.sendto(p, rx.getsockname())
    t1 = time.time_ns()
    time.sleep(0.05)
    first = m.receive()
    second = m.receive(limit=1)
    third = m.receive()
    assert (first[0], first[2]) == ([b"a" * 10, b"c" * 1000, b"d"], 1)  # 4 slots: one truncated
    assert (second[0], second[2], third[0], third[2]) == ([b"e" * 7], 0, [b"f"], 0)
    stamps = first[1] + second[1] + third[1]
    assert all(t0 - 1_000_000 <= t <= t1 + 1_000_000 for t in stamps) and stamps == sorted(stamps)
    tx.close()
    rx.close()


@pytest.mark.parametrize("step_s", [-3600.0, 2.5])
def test_a_realtime_step_while_datagrams_wait_moves_no_stamp(tmp_path, step_s):
    """The host's realtime clock steps (NTP) while the loop is blocked: the datagrams that
    arrived before the step are read after it. Their kernel stamps are still converted to their
    arrival times (the fake host clock of the simulated devices stands in for the step)."""

    async def run(t0: int):
        t = create_transport({"kind": "udp-batch", "host": "127.0.0.1", "port": 0, "coalesce_s": 0.005})
        await t.open()
        await asyncio.sleep(max(t0 - time.monotonic_ns(), 0) / 1e9)  # stamping on meanwhile
        sent: list[int] = []

        def sender():
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            for k in range(30):
                time.sleep(max(t0 + k * 10_000_000 - time.monotonic_ns(), 0) / 1e9)
                sent.append(time.monotonic_ns())
                s.sendto(k.to_bytes(4, "little"), ("127.0.0.1", t.port))
            s.close()

        loop = asyncio.get_running_loop()
        loop.call_later(0.08, time.sleep, 0.12)  # the loop stalls across the step (at 0.15 s)
        send = asyncio.create_task(asyncio.to_thread(sender))
        got = [await asyncio.wait_for(t.read(), 5) for _ in range(30)]
        await send
        await t.close()
        return sent, got, t.stamps

    t0 = time.monotonic_ns() + 200_000_000
    with fake_host_clock(tmp_path / "host_clock", [(t0 + 150_000_000, round(step_s * 1e9))]):
        sent, got, stamps = asyncio.run(run(t0))
    assert [int.from_bytes(d, "little") for d, _ in got] == list(range(30))
    errors = [h - s for s, (_, h) in zip(sent, got)]
    assert max(abs(e) for e in errors) < 3_000_000, errors  # at arrival, none a step away
    assert stamps.steps == 1 and stamps.repaired >= 3 and stamps.unknown == 0
