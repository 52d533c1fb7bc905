"""The ``udp-batch`` transport on real sockets: every datagram in order with kernel receive
stamps, reading paused (not dropping) while the consumer lags, truncation counted."""

from __future__ import annotations

import asyncio
import socket
import time

import pytest

from drivers.transport import create_transport

pytestmark = pytest.mark.integration


async def _send(port: int, payloads: list[bytes]) -> tuple[int, int]:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    t0 = time.monotonic_ns()
    for p in payloads:
        s.sendto(p, ("127.0.0.1", port))
    t1 = time.monotonic_ns()
    s.close()
    return t0, t1


def test_bursts_arrive_complete_in_order_with_kernel_stamps_and_a_lagging_reader_pauses():
    async def run():
        t = create_transport({"kind": "udp-batch", "host": "127.0.0.1", "port": 0, "max_chunks": 64,
                              "coalesce_s": 0.005})  # fmt: skip
        await t.open()
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
