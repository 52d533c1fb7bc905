"""PPS: gpsd's labelling rule, the UDP datagram, the RFC 2783 ioctl structs, the three sources."""

from __future__ import annotations

import asyncio
import errno
import os
import socket
import struct
import termios
import time

import pytest

from drivers.base import DriverError
from drivers.pps import (
    PPS_FETCH,
    KernelPpsSource,
    PpsEdge,
    PpsLabeler,
    SerialLinePpsSource,
    create_pps_source,
    decode_pps_datagram,
    encode_pps_datagram,
    gps_second_of,
    pack_pps_fdata,
    unpack_pps_fdata,
)

S = 1_000_000_000


def edge(t_s: float, seq: int, source: str = "udp") -> PpsEdge:
    return PpsEdge(int(t_s * S), source, seq)


def test_pulse_is_labelled_by_a_time_message_within_1_1_s():
    lab = PpsLabeler()
    assert lab.add_edge(edge(100.0, 1)) == []
    (e,) = lab.add_time(1_400_000_000, int(100.115 * S))
    assert e.gps_s == 1_400_000_000 and e.sequence == 1 and e.host_ns == 100 * S
    lab.add_edge(edge(101.0, 2))
    (e,) = lab.add_time(1_400_000_001, int(102.09 * S))  # 1.09 s later: still within 1.1 s
    assert e.sequence == 2
    assert lab.stats.records == 2 and not lab.stats.events


def test_late_time_message_leaves_the_pulse_unlabelled():
    lab = PpsLabeler()
    lab.add_edge(edge(200.0, 1))
    assert lab.add_time(7, int(201.2 * S)) == []  # 1.2 s: too late
    assert lab.stats.events["unlabelled"] == 1 and lab.stats.events["time_without_edge"] == 1


def test_duplicates_are_dropped_and_counted():
    lab = PpsLabeler()
    lab.add_edge(edge(10.0, 1))
    lab.add_edge(edge(10.0, 1))  # same sequence again (UDP duplicate)
    lab.add_edge(edge(10.2, 2))  # a glitch 0.2 s after the pulse
    (e,) = lab.add_time(50, int(10.1 * S))
    assert e.sequence == 1
    assert (
        lab.add_time(50, int(10.3 * S)) == []
    )  # a second message for the same second (e.g. ZDA after TIME__)
    assert lab.stats.events["duplicate_edge"] == 2
    lab.add_edge(edge(11.0, 3))
    assert lab.add_time(49, int(11.1 * S)) == []  # going back in time
    assert lab.stats.events["non_monotonic"] == 1


def test_missed_message_then_next_second_labels_only_the_latest_pulse():
    lab = PpsLabeler()
    lab.add_edge(edge(0.0, 1))
    lab.add_edge(edge(1.0, 2))
    (e,) = lab.add_time(61, int(1.1 * S))
    assert e.sequence == 2 and lab.stats.events["unlabelled"] == 1


def test_gps_second_of_a_time_tag():
    assert gps_second_of(1_400_000_000_999_999_999) == 1_400_000_000


def test_udp_datagram_format():
    dg = encode_pps_datagram(5, 123_456_789)
    assert dg == b"PPS1" + struct.pack("<Qq", 5, 123_456_789) and len(dg) == 20
    assert decode_pps_datagram(dg, "emu") == PpsEdge(123_456_789, "emu", 5)
    with pytest.raises(DriverError, match="expected 20"):
        decode_pps_datagram(dg[:-1])
    with pytest.raises(DriverError, match="magic"):
        decode_pps_datagram(b"XXXX" + dg[4:])


def test_pps_fetch_ioctl_number_and_struct_layout():
    assert PPS_FETCH == 0xC00870A4  # _IOWR('p', 0xa4, struct pps_fdata *) on 64-bit Linux
    buf = pack_pps_fdata(1.5)
    assert len(buf) == 64  # sizeof(struct pps_fdata)
    assert struct.unpack_from("=qiI", buf, 48) == (1, 500_000_000, 0)  # timeout at offset 48
    assert struct.unpack_from("=qiI", pack_pps_fdata(None), 48)[2] == 1  # PPS_TIME_INVALID: wait forever
    kernel = bytearray(64)
    struct.pack_into("=II", kernel, 0, 42, 41)
    struct.pack_into("=qiI", kernel, 8, 1_700_000_000, 123_456_789, 0)  # assert_tu
    struct.pack_into("=qiI", kernel, 24, 1_700_000_000, 623_456_789, 0)  # clear_tu
    struct.pack_into("=i", kernel, 40, 0x1011)
    f = unpack_pps_fdata(kernel)
    assert (f.assert_sequence, f.clear_sequence, f.current_mode) == (42, 41, 0x1011)
    assert (
        f.assert_realtime_ns == 1_700_000_000_123_456_789 and f.clear_realtime_ns == 1_700_000_000_623_456_789
    )


def test_kernel_source_turns_fetches_into_monotonic_edges(tmp_path):
    """A stand-in for the kernel: the ioctl fills pps_fdata like Linux does."""
    dev = tmp_path / "pps0"
    dev.write_bytes(b"")
    calls = []

    def fake_ioctl(fd, request, buf, mutate):
        assert request == PPS_FETCH and mutate and len(buf) == 64
        calls.append(struct.unpack_from("=qiI", buf, 48))
        n = len(calls)
        if n > 3:
            time.sleep(0.01)
            raise OSError(errno.ETIMEDOUT, "timeout")
        real = time.clock_gettime_ns(time.CLOCK_REALTIME) - 5_000_000  # the pulse was 5 ms ago
        struct.pack_into("=II", buf, 0, {1: 1, 2: 2, 3: 2}[n], 0)  # the 3rd fetch repeats sequence 2
        struct.pack_into("=qiI", buf, 8, real // S, real % S, 0)
        return 0

    async def run():
        src = KernelPpsSource(str(dev), ioctl=fake_ioctl, timeout_s=0.05)
        async with src:
            a = await asyncio.wait_for(src.get(), 2)
            b = await asyncio.wait_for(src.get(), 2)
            await asyncio.sleep(0.05)
            return a, b, src._queue.qsize()

    a, b, left = asyncio.run(run())
    assert (a.sequence, b.sequence, left) == (1, 2, 0)  # the repeated sequence is not a new pulse
    assert calls[0] == (0, 50_000_000, 0)
    lag = time.monotonic_ns() - b.host_ns
    assert 5_000_000 <= lag < 2 * S and b.realtime_ns is not None


def test_serial_line_source_on_a_pty_reports_that_tiocmiwait_is_unsupported():
    master, slave = os.openpty()
    try:
        path = os.ttyname(slave)

        async def run():
            async with SerialLinePpsSource(path) as src:
                return await asyncio.wait_for(src.get(), 2)

        with pytest.raises(DriverError, match="TIOCMIWAIT/TIOCMGET on .*not a UART"):
            asyncio.run(run())
    finally:
        os.close(master)
        os.close(slave)


def test_serial_line_source_counts_rising_dcd_edges():
    """TIOCMIWAIT/TIOCMGET played by a fake: DCD goes up, down, up → two pulses."""
    master, slave = os.openpty()
    levels = iter([0, termios.TIOCM_CD, 0, termios.TIOCM_CD])
    waits = []

    def fake_ioctl(fd, request, arg):
        if request == termios.TIOCMGET:
            return struct.pack("i", next(levels, termios.TIOCM_CD))
        assert request == termios.TIOCMIWAIT and arg == termios.TIOCM_CD
        waits.append(1)
        if len(waits) > 3:
            time.sleep(0.02)
            raise OSError(errno.EIO, "gone")
        return 0

    async def run():
        async with SerialLinePpsSource(os.ttyname(slave), ioctl=fake_ioctl) as src:
            a = await asyncio.wait_for(src.get(), 2)
            b = await asyncio.wait_for(src.get(), 2)
            with pytest.raises(DriverError, match="TIOCMIWAIT"):
                await asyncio.wait_for(src.get(), 2)
            return a, b

    try:
        a, b = asyncio.run(run())
    finally:
        os.close(master)
        os.close(slave)
    assert (a.sequence, b.sequence) == (1, 2) and a.host_ns < b.host_ns


def test_udp_source_on_loopback():
    async def run():
        src = create_pps_source({"kind": "udp", "host": "127.0.0.1", "port": 0, "name": "emu"})
        async with src:
            tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            t = time.monotonic_ns()
            tx.sendto(b"junk", ("127.0.0.1", src.port))
            tx.sendto(encode_pps_datagram(9, t), ("127.0.0.1", src.port))
            e = await asyncio.wait_for(src.get(), 2)
            tx.close()
            return e, src.stats

    e, stats = asyncio.run(run())
    assert e.sequence == 9 and e.source == "emu" and stats.rejected["bad_datagram"] == 1


def test_registry_errors_name_the_kind():
    with pytest.raises(DriverError, match="pps.kind 'gps'"):
        create_pps_source({"kind": "gps"})
    with pytest.raises(DriverError, match="serial-line"):
        create_pps_source({"kind": "serial-line", "port": "/dev/null", "baud": 9600})
