"""PPS: the labelling rule (any feeding order, ambiguous late messages), the UDP datagram, the
RFC 2783 ioctl structs, the three sources."""

from __future__ import annotations

import asyncio
import errno
import itertools
import os
import socket
import struct
import termios
import time

import pytest

from drivers.base import DriverError
from drivers.pps import (
    KernelPpsSource,
    PpsEdge,
    PpsLabeler,
    SerialLinePpsSource,
    UdpPpsSource,
    create_pps_source,
    decode_pps_datagram,
    encode_pps_datagram,
    gps_second_of,
)
from drivers.ppsfetch import PPS_FETCH, pack_pps_fdata, unpack_pps_fdata

S = 1_000_000_000


def edge(t_s: float, seq: int, source: str = "udp") -> PpsEdge:
    return PpsEdge(int(t_s * S), source, seq)


def test_pulse_is_labelled_by_a_time_message_within_1_1_s():
    lab = PpsLabeler()
    assert lab.add_edge(edge(100.0, 1)) == []
    (e,) = lab.add_time(1_400_000_000, int(100.115 * S))
    assert e.gps_s == 1_400_000_000 and e.sequence == 1 and e.host_ns == 100 * S
    lab.add_edge(edge(101.0, 2))
    # 1.09 s later: still within 1.1 s, decided once no pulse can come between (the stream ends)
    assert lab.add_time(1_400_000_001, int(102.09 * S)) == []
    (e,) = lab.flush()
    assert e.sequence == 2
    assert lab.stats.records == 2 and not lab.stats.events


def test_late_time_message_leaves_the_pulse_unlabelled():
    lab = PpsLabeler()
    lab.add_edge(edge(200.0, 1))
    assert lab.add_time(7, int(201.2 * S)) == [] and lab.flush() == []  # 1.2 s: too late
    assert lab.stats.events["unlabelled"] == 1 and lab.stats.events["time_without_edge"] == 1
    assert lab.take_dropped() == [(edge(200.0, 1), "unlabelled")]


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


def _interleavings(a: list, b: list):
    """Every merge of two sequences that keeps the order within each."""
    for slots in itertools.combinations(range(len(a) + len(b)), len(a)):
        ia, ib, out = iter(a), iter(b), []
        for k in range(len(a) + len(b)):
            out.append(next(ia) if k in slots else next(ib))
        yield out


def _feed(lab: PpsLabeler, records) -> list[tuple[int, int, int]]:
    out = []
    for r in records:
        out += lab.add_edge(r) if isinstance(r, PpsEdge) else lab.add_time(*r)
    out += lab.flush()
    return [(e.sequence, e.gps_s, e.host_ns) for e in out]


@pytest.mark.parametrize("warm", [0, 6], ids=["from-start", "latency-known"])
def test_labels_do_not_depend_on_the_order_pulses_and_messages_are_fed_in(warm):
    """Pulses 1 s apart (jittered), their ZDA 50 ms later, the 3rd ZDA missing and the 5th pulse
    lost: fed in each of the 126 interleavings of the two streams — as a stalled event loop
    hands over its backlog — the labels and the dropped pulses are the same, in host order."""
    g0 = 1_400_000_000
    h = [int((k + 0.00002 * (k % 3)) * S) for k in range(warm, warm + 6)]
    pulses = [PpsEdge(h[k], "pps", warm + k + 1) for k in range(6) if k != 4]
    messages = [(g0 + warm + k, h[k] + 50_000_000 + 300_000 * (k % 2)) for k in range(5) if k != 2]
    results = set()
    for order in _interleavings(pulses, messages):
        lab = PpsLabeler()
        for k in range(warm):  # the latency statistics of earlier, orderly seconds
            lab.add_edge(PpsEdge(k * S, "pps", k + 1))
            lab.add_time(g0 + k, k * S + 50_000_000)
        lab.flush()
        labels = _feed(lab, order)
        assert [h for *_, h in labels] == sorted(h for *_, h in labels)
        dropped = [(e.sequence, why) for e, why in lab.take_dropped()]
        results.add((tuple(labels), tuple(dropped)))
    assert len(results) == 1, results
    ((labels, dropped),) = results
    expected = [(warm + k + 1, g0 + warm + k) for k in (0, 1, 3)]
    assert [(q, g) for q, g, _ in labels] == expected
    assert dropped == ((warm + 3, "unlabelled"), (warm + 6, "unlabelled"))


def _warm(lab: PpsLabeler, seconds: int, g0: int = 1_000) -> None:
    for k in range(seconds):
        lab.add_edge(PpsEdge(k * S, "pps", k + 1))
        lab.add_time(g0 + k, k * S + 50_000_000 + 1_000_000 * (k % 2))


def test_a_time_message_800_ms_late_labels_nothing_and_is_counted_ambiguous():
    """ZDAs come 50 ms after their pulse; one comes 850 ms after it — 150 ms before the next
    pulse, where an early message of that pulse would be: it could belong to either, so
    neither is labelled by it (gpsd's rule would guess; a nearest-latency rule would take the
    next pulse, 1 s wrong)."""
    lab = PpsLabeler()
    _warm(lab, 6)
    lab.add_edge(PpsEdge(6 * S, "pps", 7))
    assert lab.add_time(1_006, 6 * S + 850_000_000) == []
    assert lab.add_edge(PpsEdge(7 * S, "pps", 8)) == []  # the late message is decided: nothing
    (e,) = lab.add_time(1_007, 7 * S + 50_000_000)
    assert (e.sequence, e.gps_s) == (8, 1_007)
    assert lab.stats.events["time_ambiguous"] == 1
    assert lab.last_ambiguous["gps_s"] == 1_006 and lab.last_ambiguous["latency_ns"] == 850_000_000
    assert abs(lab.last_ambiguous["expected_ns"] - 50_500_000) <= 500_000
    assert lab.last_ambiguous["tolerance_ns"] == 50_000_000
    assert [(d.sequence, why) for d, why in lab.take_dropped()] == [(7, "ambiguous")]


def test_a_lasting_latency_change_is_learnt_after_eight_ambiguous_messages():
    lab = PpsLabeler()
    _warm(lab, 6)
    got = []
    for k in range(6, 20):
        got += lab.add_edge(PpsEdge(k * S, "pps", k + 1))
        got += lab.add_time(1_000 + k, k * S + 700_000_000)  # from now on 700 ms after the pulse
    got += lab.flush()
    assert lab.stats.events["time_ambiguous"] == 8 and lab.stats.events["latency_relearned"] == 1
    assert [(e.sequence, e.gps_s) for e in got] == [(k + 1, 1_000 + k) for k in range(14, 20)]


def test_tick_judges_at_the_previous_tick_so_a_stall_does_not_expire_its_backlog():
    lab = PpsLabeler()
    _warm(lab, 6)
    lab.tick(6 * S)
    lab.add_edge(PpsEdge(6 * S + 10_000_000, "pps", 7))
    # the loop stalls 2 s right after the pulse: the next tick comes late, before the backlog
    assert lab.tick(8 * S + 50_000_000) == [] and lab.take_dropped() == []
    (e,) = lab.add_time(1_006, 6 * S + 60_000_000)  # the backlog: the pulse's ZDA
    assert (e.sequence, e.gps_s) == (7, 1_006)
    # a pulse with no message is dropped by the first tick judged 1.1 s after it
    lab.add_edge(PpsEdge(7 * S + 10_000_000, "pps", 8))
    lab.tick(8 * S + 300_000_000)
    assert lab.take_dropped() == []
    lab.tick(8 * S + 600_000_000)  # judged at 8.3 s: 1.29 s after the pulse
    assert [(d.sequence, why) for d, why in lab.take_dropped()] == [(8, "unlabelled")]


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
    fetched = {}  # fetch number → host monotonic ns just before and after its pulse's stamp

    def fake_ioctl(fd, request, buf, mutate):
        assert request == PPS_FETCH and mutate and len(buf) == 64
        calls.append(struct.unpack_from("=qiI", buf, 48))
        n = len(calls)
        if n > 4:
            # the kernel: no pulse, the fetch blocks until its timeout (shortened: the reader
            # thread would spin otherwise)
            time.sleep(0.01)
            raise OSError(errno.ETIMEDOUT, "timeout")
        t0 = time.monotonic_ns()
        real = time.clock_gettime_ns(time.CLOCK_REALTIME) - 5_000_000  # the pulse was 5 ms ago
        fetched[n] = (t0, time.monotonic_ns())
        # the 3rd fetch repeats sequence 2; the 4th is the next pulse
        struct.pack_into("=II", buf, 0, {1: 1, 2: 2, 3: 2, 4: 3}[n], 0)
        struct.pack_into("=qiI", buf, 8, real // S, real % S, 0)
        return 0

    async def run():
        src = KernelPpsSource(str(dev), ioctl=fake_ioctl, timeout_s=0.05)
        async with src:
            got = [await asyncio.wait_for(src.get(), 2) for _ in range(3)]
            return got, src._queue.qsize()

    (a, b, c), left = asyncio.run(run())
    # the repeated sequence is not a new pulse: the pulse after it comes next
    assert (a.sequence, b.sequence, c.sequence, left) == (1, 2, 3, 0)
    assert calls[0] == (0, 50_000_000, 0)
    lo, hi = fetched[2]  # the pulse's monotonic time, 5 ms before the fetch (1 ms: the offset's read)
    assert lo - 6_000_000 <= b.host_ns <= hi - 4_000_000 and b.realtime_ns is not None


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


def test_a_udp_pps_source_on_a_taken_port_fails_and_keeps_no_socket():
    def open_fds() -> int:
        return len(os.listdir("/proc/self/fd"))

    async def open_on(port: int) -> None:
        await UdpPpsSource("127.0.0.1", port, "emu").open()

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as holder:
        holder.bind(("127.0.0.1", 0))
        before = open_fds()
        with pytest.raises(OSError, match="Address already in use"):
            asyncio.run(open_on(holder.getsockname()[1]))
        assert open_fds() == before
