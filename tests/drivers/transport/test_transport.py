"""Transports on real pseudo-terminals and loopback sockets: stamps, unplug/replug, back-pressure."""

from __future__ import annotations

import asyncio
import os
import socket
import threading
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from drivers.base import DriverError
from drivers.transport.base import Chunk, TransportEvent
from drivers.transport.registry import TRANSPORTS, create_transport
from drivers.transport.serial_port import SerialTransport, _PortReader
from drivers.transport.udp import UdpTransport
from tests.waiting import wait_until, wait_until_async

pytestmark = pytest.mark.integration


class Pty:
    """A pseudo-terminal behind a stable symlink, like sim_devices' ``<run dir>/ins``."""

    def __init__(self, link: Path) -> None:
        self.link = link
        self.master: int | None = None
        self.slave_name: str | None = None
        self.plug()

    @property
    def fd(self) -> int:
        """The master side (the device's end) of the plugged pty."""
        assert self.master is not None, "the pty is unplugged"
        return self.master

    def plug(self) -> None:
        self.master, slave = os.openpty()
        self.slave_name = os.ttyname(slave)
        os.close(slave)  # the transport opens the slave by path
        tmp = self.link.with_suffix(".tmp")
        tmp.unlink(missing_ok=True)
        tmp.symlink_to(self.slave_name)
        tmp.replace(self.link)

    def unplug(self) -> None:
        """Close the pty and remove the link, as udev removes a by-id link: a link left pointing
        at ``/dev/pts/N`` would reach whichever pty takes that number next (another test's)."""
        if self.link.is_symlink() and os.readlink(self.link) == self.slave_name:
            self.link.unlink()
        os.close(self.fd)
        self.master = None

    def write(self, data: bytes) -> None:
        os.write(self.fd, data)


class HandedOver:
    """What a serial port's reader thread has read and handed to the event loop (which may be
    held), counted in that thread, with notice to a test waiting on ``changed``."""

    def __init__(self, reader: _PortReader) -> None:
        self.bytes = 0
        self.changed = threading.Condition()
        hand_over = reader._hand_over

        def counted(item: Chunk | str) -> None:
            with self.changed:
                self.bytes += len(item.data) if isinstance(item, Chunk) else 0
                self.changed.notify_all()
            hand_over(item)

        reader._hand_over = counted  # type: ignore[method-assign]  # (a test's tap on it)

    def reached(self, n: int) -> Callable[[], bool]:
        return lambda: self.bytes >= n


def queued_or_paused(t: SerialTransport, n: int) -> Callable[[], bool]:
    """The port's first ``n`` bytes are in the transport's queue, or its reader has paused."""
    reader = t._reader
    assert reader is not None  # (open: its reader thread runs)
    return lambda: t.stats.bytes_in == n or not reader._room.is_set()


async def read_until(t, n: int, timeout_s: float = 3.0) -> list[Chunk]:
    chunks, got = [], 0
    deadline = time.monotonic() + timeout_s
    while got < n:
        chunk = await asyncio.wait_for(t.read(), max(0.01, deadline - time.monotonic()))
        chunks.append(chunk)
        got += len(chunk.data)
    return chunks


def test_registry_has_the_three_kinds_and_names_bad_configs():
    assert {"serial", "udp", "tcp"} <= set(TRANSPORTS)
    with pytest.raises(DriverError, match=r"transport.kind 'can'"):
        create_transport({"kind": "can"})
    with pytest.raises(DriverError, match=r"transport \(udp\)"):
        create_transport({"kind": "udp", "prot": 1})


def test_serial_pty_bytes_are_stamped_and_survive_unplug_replug(tmp_path):
    pty = Pty(tmp_path / "ins")
    events: list[TransportEvent] = []

    async def run():
        t = create_transport(
            {
                "kind": "serial",
                "port": str(pty.link),
                "baudrate": 115200,
                "reconnect_min_s": 0.02,
                "reconnect_max_s": 0.1,
            },
            on_event=events.append,
        )
        assert isinstance(t, SerialTransport)
        async with t:
            assert t.connected
            before = time.monotonic_ns()
            pty.write(b"$HEHDT,1.0,T*00\r\n")
            first = await read_until(t, 17)
            pty.unplug()  # the emulator closes the pty (the slave reads EIO) and removes the link
            await wait_until_async(lambda: not t.connected, 10, "the unplug to be noticed")
            await wait_until_async(  # reconnect attempts fail: the old pty is gone
                lambda: any(e.kind == "reconnect_failed" for e in events), 10, "a failed reconnect attempt"
            )
            pty.plug()  # a new pty behind the same symlink
            await wait_until_async(lambda: t.connected, 10, "the reconnection")
            assert t.reconnects == 1
            assert t._serial is not None
            assert os.ttyname(t._serial.fileno()) == pty.slave_name  # the new pty, not another
            pty.write(b"after replug\n")
            second = await read_until(t, 13)
            return before, first, second

    before, first, second = asyncio.run(run())
    assert b"".join(c.data for c in first) == b"$HEHDT,1.0,T*00\r\n"
    assert before <= first[0].host_ns <= time.monotonic_ns()
    assert b"".join(c.data for c in second) == b"after replug\n"
    kinds = [e.kind for e in events]
    assert kinds[0] == "connected"
    assert "disconnected" in kinds
    assert kinds[-1] == "connected"
    assert kinds.index("disconnected") < len(kinds) - 1
    pty.unplug()


def test_serial_port_missing_at_start_is_reported_then_opened(tmp_path):
    link = tmp_path / "later"
    events: list[TransportEvent] = []

    async def run():
        t = SerialTransport(str(link), reconnect_min_s=0.02, reconnect_max_s=0.05, on_event=events.append)
        async with t:
            assert not t.connected
            pty = Pty(link)
            await wait_until_async(lambda: t.connected, 10, "the port to be opened")
            pty.write(b"hello")
            (chunk,) = await read_until(t, 5)
            pty.unplug()
            return chunk

    assert asyncio.run(run()).data == b"hello"
    assert events[0].kind == "disconnected"
    assert "cannot open" in events[0].detail
    assert events[-1].kind == "connected"


@pytest.mark.realtime  # the bound: reconnect_max_s (0.5 s) of a serial port, plus 0.25 s of a loaded machine's slack
def test_serial_port_that_appears_late_is_opened_within_half_a_second(tmp_path):
    """The default back-off of a serial port stops doubling at 0.5 s: an INS that shows up after
    a few seconds (the emulator starting, a USB adapter plugged in) is read at once."""
    link = tmp_path / "late"
    events: list[TransportEvent] = []

    async def run():
        t = SerialTransport(str(link), on_event=events.append)
        async with t:
            # ten failed attempts (0.1 + 0.2 + 0.4 + 0.5 … s): past where a 5 s cap would wait
            await wait_until_async(
                lambda: any(e.kind == "reconnect_failed" and "attempt 10:" in e.detail for e in events),
                60,
                "the 10th failed attempt to open the missing port",
            )
            pty = Pty(link)
            t0 = time.monotonic()
            await wait_until_async(lambda: t.connected, 10, "the port to be opened")
            waited_s = time.monotonic() - t0
            pty.unplug()
            return waited_s

    assert asyncio.run(run()) <= 0.5 + 0.25  # the cap, and a loaded machine's slack


def test_serial_slow_consumer_pauses_reading_without_losing_bytes(tmp_path):
    pty = Pty(tmp_path / "fast")

    async def run():
        t = SerialTransport(str(pty.link), max_chunks=4)
        async with t:
            reader = t._reader
            assert reader is not None  # (open: its reader thread runs)
            payload = bytes(range(256)) * 64  # 16 KiB in many small writes
            for i in range(0, len(payload), 256):
                pty.write(payload[i : i + 256])
                await wait_until_async(  # each write a chunk of its own in the queue, until it is full
                    queued_or_paused(t, i + 256),
                    10,
                    f"bytes {i}-{i + 256} to reach the queue (or the reader to pause)",
                    changed=t._ready,  # (set at each chunk queued)
                )
            await wait_until_async(  # the reader stops at 4 chunks waiting (unless it has read it all)
                lambda: not reader._room.is_set() or t.stats.bytes_in == len(payload),
                10,
                "the reader to pause",
            )
            assert len(t._chunks) <= 5  # paused: the rest waits in the kernel
            chunks = await read_until(t, len(payload))
            return payload, b"".join(c.data for c in chunks)

    sent, got = asyncio.run(run())
    assert got == sent
    pty.unplug()


@pytest.mark.realtime  # the reader thread must drain a pty of a few kB within milliseconds while the loop is held
def test_serial_bytes_are_read_and_stamped_while_the_event_loop_is_busy(tmp_path):
    """The port's reader thread: an event loop held all along (a long burst of profiler
    datagrams, the log writer holding the GIL) delays the decoding of serial bytes, not their
    reading nor their stamps. The device sends bursts of 2.8 kB, less than a pty holds, each
    once the reader thread has taken the last (a burst the thread did not take while the loop
    is held times the test out), and the thread keeps the pace of the INS at ×5 (700 kB/s)."""
    pty = Pty(tmp_path / "busy")
    os.set_blocking(pty.fd, False)

    async def run():
        t = SerialTransport(str(pty.link))
        async with t:
            assert t._reader is not None  # (open: its reader thread runs)
            handed = HandedOver(t._reader)
            writes: list[bytes] = []
            refused = 0
            start_ns = time.monotonic_ns()
            while len(writes) < 500:  # no await: the loop is blocked all along
                for _ in range(4):
                    piece = b"%06d," % len(writes) * 100  # 700 bytes
                    try:
                        n = os.write(pty.fd, piece)
                    except BlockingIOError:
                        refused += 1
                    else:
                        writes.append(piece[:n])
                        refused += n < len(piece)
                wait_until(
                    handed.reached(sum(map(len, writes))),
                    10,
                    f"the reader thread to take the {len(writes)} writes while the loop is held",
                    changed=handed.changed,
                )
            free_ns = time.monotonic_ns()
            chunks = await read_until(t, sum(map(len, writes)))
            return writes, refused, (start_ns, free_ns), chunks

    writes, refused, (start_ns, free_ns), chunks = asyncio.run(run())
    pty.unplug()
    assert refused == 0  # the pty never filled up
    assert b"".join(c.data for c in chunks) == b"".join(writes)
    assert len(writes) > 200
    stamped_busy = sum(len(c.data) for c in chunks if c.host_ns < free_ns)
    assert stamped_busy >= 0.9 * sum(map(len, writes))  # read (and stamped) while the loop was held
    taken_b_s = sum(map(len, writes)) / ((free_ns - start_ns) / 1e9)
    assert taken_b_s >= 700_000, f"{taken_b_s:.0f} B/s"  # (here: tens of MB/s, on a loaded machine too)


def test_udp_loopback_datagrams_and_large_receive_buffer():
    async def run():
        t = create_transport({"kind": "udp", "host": "127.0.0.1", "port": 0, "rcvbuf_bytes": 4 * 1024 * 1024})
        assert isinstance(t, UdpTransport)
        async with t:
            tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            for i in range(50):
                tx.sendto(b"ZFP1" + bytes([i]) * 100, ("127.0.0.1", t.port))
            chunks = [await asyncio.wait_for(t.read(), 2) for _ in range(50)]
            tx.close()
            return t.rcvbuf_bytes_granted, chunks

    granted, chunks = asyncio.run(run())
    assert granted >= 256 * 1024  # far above the 208 KiB default (the kernel may cap at rmem_max)
    assert [c.data[4] for c in chunks] == list(range(50))
    assert all(isinstance(c.host_ns, int) for c in chunks)
    assert chunks[0].host_ns <= chunks[-1].host_ns


def test_a_udp_port_in_use_is_the_last_error_until_it_is_freed():
    """The profiler's port bound by another process: the transport keeps retrying and says why
    (``last_error``), and binds it once it is free."""
    from drivers.transport.udp_batch import BatchUdpTransport

    other = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    other.bind(("127.0.0.1", 0))
    port = other.getsockname()[1]

    async def run():
        t = BatchUdpTransport(port, host="127.0.0.1", reconnect_min_s=0.02, reconnect_max_s=0.05)
        async with t:
            seen = (t.connected, t.last_error)
            other.close()
            await wait_until_async(lambda: t.connected, 10, "the freed port to be bound")
            return seen, t.last_error

    try:
        (connected, error), after = asyncio.run(run())
    finally:
        other.close()
    assert not connected
    assert error == "[Errno 98] Address already in use"
    assert after is None


def test_a_missing_serial_path_is_the_last_error_until_it_appears(tmp_path):
    link = tmp_path / "ttyUSB9"

    async def run():
        t = SerialTransport(str(link), reconnect_min_s=0.02, reconnect_max_s=0.05)
        async with t:
            seen = t.last_error
            pty = Pty(link)
            await wait_until_async(lambda: t.connected, 10, "the port to be opened")
            after = t.last_error
            pty.unplug()
            await wait_until_async(lambda: not t.connected, 10, "the unplug to be seen")
            return seen, after, t.last_error

    seen, after, unplugged = asyncio.run(run())
    assert f"No such file or directory: '{link}'" in seen
    assert after is None
    assert unplugged


def test_udp_drops_and_counts_when_the_consumer_lags():
    async def run():
        t = create_transport({"kind": "udp", "host": "127.0.0.1", "port": 0, "max_chunks": 10})
        assert isinstance(t, UdpTransport)
        async with t:
            tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            for _ in range(30):
                tx.sendto(b"x", ("127.0.0.1", t.port))
            await wait_until_async(  # every datagram handled: queued or dropped
                lambda: t.stats.records + t.stats.events["dropped_datagrams"] == 30, 10, "the 30 datagrams"
            )
            tx.close()
            return t.stats

    stats = asyncio.run(run())
    assert stats.records == 10
    assert stats.events["dropped_datagrams"] == 20


def test_tcp_client_reconnects_after_the_server_drops_it():
    events: list[TransportEvent] = []

    async def run():
        conns = []

        async def handle(reader, writer):
            conns.append(writer)
            writer.write(b"conn%d;" % len(conns))
            await writer.drain()

        server = await asyncio.start_server(handle, "127.0.0.1", 0)
        port = server.sockets[0].getsockname()[1]
        t = create_transport(
            {"kind": "tcp", "host": "127.0.0.1", "port": port, "reconnect_min_s": 0.02},
            on_event=events.append,
        )
        async with t:
            first = await read_until(t, 6)
            conns[0].close()
            second = await read_until(t, 6)
        for w in conns:  # (the server's side of each connection: closed, not left to the collector)
            w.close()
            await w.wait_closed()
        server.close()
        await server.wait_closed()
        return first, second, t.reconnects

    first, second, reconnects = asyncio.run(run())
    assert b"".join(c.data for c in first) == b"conn1;"
    assert b"".join(c.data for c in second) == b"conn2;"
    assert reconnects == 1
    assert [e.kind for e in events][:3] == ["connected", "disconnected", "connected"]


def test_ins_nmea_over_a_pty_end_to_end(tmp_path):
    """Emulator side encodes epochs, daemon side reads the pty and assembles canonical records."""
    from calib.core.frames import utc_fields_to_gps_ns
    from drivers.hydrins.nav import NavRecord, status_words
    from drivers.hydrins.nmea_decode import NmeaNavAssembler
    from drivers.hydrins.nmea_encode import encode_epoch, encode_zda

    algo, system = status_words(navigation=True, utc_detected=True, pps_detected=True)
    sent = [
        NavRecord(
            "nmea",
            gps_ns=utc_fields_to_gps_ns(2024, 1, 2, (k * 100 + 5_000) * 10**6),
            lat_deg=45.5,
            lon_deg=-73.55,
            height_m=3.0,
            roll_rad=0.01 * k,
            pitch_rad=-0.02,
            heading_rad=1.5,
            algorithm_status=algo,
            system_status=system,
            user_status=0,
        )
        for k in range(10)
    ]
    pty = Pty(tmp_path / "ins")

    async def run():
        asm = NmeaNavAssembler(utc_clock=None)
        got: list[NavRecord] = []
        async with SerialTransport(str(pty.link), baudrate=115200) as t:
            for nav in sent:
                assert nav.gps_ns is not None
                pty.write(encode_zda(nav.gps_ns) + encode_epoch(nav))
            while len(got) < len(sent):
                data, host_ns = await asyncio.wait_for(t.read(), 3)
                got += asm.feed(data, host_ns)
        return got, asm.stats

    got, stats = asyncio.run(run())
    pty.unplug()
    assert [g.gps_ns for g in got] == [s.gps_ns for s in sent]
    assert all(g.date_source == "zda" and g.pps_detected and g.host_ns is not None for g in got)
    # 0.001° on the wire
    assert all(abs(g.roll_rad - s.roll_rad) < 1e-5 for g, s in zip(got, sent, strict=True))
    assert stats.rejected_total == 0
