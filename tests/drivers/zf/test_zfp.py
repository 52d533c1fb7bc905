"""ZFP1 packets and profile reassembly: layout, splitting, loss/reorder/duplicate counters, the codec seam."""

from __future__ import annotations

import struct
import zlib

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from drivers.base import DriverError
from drivers.zf.assembler import ProfileAssembler
from drivers.zf.codec import Packet, Profile
from drivers.zf.zfp1 import (
    HEADER_SIZE,
    ZFP1,
    ZfpError,
    decode_packet,
    encode_profile,
    points_per_packet,
)
from tests.drivers.helpers import PROPERTY

N = 5080  # points per profile of the Z+F 9012 (1.016 Mpts/s at 200 profiles/s)
DT = 984  # ns between points
DANGLE = 70866  # µdeg per point (360° / 5080)


def profile_datagrams(counter: int, seed: int = 0, n: int = N) -> tuple[list[bytes], np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed + counter)
    ranges = rng.integers(0, 3_000_000, n).astype(np.uint32)
    ranges[rng.random(n) < 0.1] = 0  # no return
    inten = rng.integers(0, 65536, n).astype(np.uint16)
    t0 = 1_400_000_000_000_000_000 + counter * 5_000_000
    return encode_profile(counter, t0, DT, -1_000_000, DANGLE, ranges, inten), ranges, inten


def test_header_layout_is_the_documented_one():
    (dg,) = encode_profile(
        7, 123456789, 1000, -5, 10, np.array([1, 0], np.uint32), np.array([9, 8], np.uint16)
    )
    assert len(dg) == HEADER_SIZE + 2 * 6 + 4 == 56
    magic, hsize, flags, counter, idx, count, t0, dt, a0, da, n, res = struct.unpack_from(
        "<4sHHIHHqIiiHH", dg
    )
    assert (magic, hsize, flags, counter, idx, count, t0, dt, a0, da, n, res) == (
        b"ZFP1",
        40,
        0b111,
        7,
        0,
        1,
        123456789,
        1000,
        -5,
        10,
        2,
        0,
    )
    assert struct.unpack_from("<IHIH", dg, 40) == (1, 9, 0, 8)
    assert int.from_bytes(dg[-4:], "little") == zlib.crc32(dg[:-4])


def test_profile_splits_into_datagrams_that_fit_the_payload():
    dgs, ranges, inten = profile_datagrams(3)
    assert len(dgs) == -(-N // points_per_packet(1400)) == 23
    assert all(len(d) <= 1400 for d in dgs)
    packets = [decode_packet(d) for d in dgs]
    assert [p.packet_index for p in packets] == list(range(23)) and all(p.packet_count == 23 for p in packets)
    assert [p.last for p in packets] == [False] * 22 + [True]
    assert np.array_equal(np.concatenate([p.range_01mm for p in packets]), ranges)
    per = points_per_packet(1400)
    assert (
        packets[1].t0_ns == packets[0].t0_ns + per * DT
        and packets[1].angle0_udeg == -1_000_000 + per * DANGLE
    )


def test_assembled_profile_has_per_point_time_angle_range():
    dgs, ranges, inten = profile_datagrams(5)
    asm = ProfileAssembler()
    out = [p for d in dgs for p in asm.feed(d, host_ns=99)]
    (prof,) = out
    assert prof.complete and prof.n_points == N and prof.host_ns == 99
    t0 = 1_400_000_000_000_000_000 + 5 * 5_000_000
    assert np.array_equal(prof.gps_ns, t0 + np.arange(N) * DT)
    assert np.allclose(np.degrees(prof.scan_angle_rad), (-1_000_000 + np.arange(N) * DANGLE) * 1e-6)
    assert np.array_equal(np.isnan(prof.range_m), ranges == 0)
    assert np.allclose(prof.range_m[ranges > 0], ranges[ranges > 0] * 1e-4)
    assert np.array_equal(prof.intensity, inten)
    assert asm.stats.records == 1 and not asm.stats.events and not asm.stats.rejected


def test_loss_reorder_duplicate_and_lost_profiles_are_counted():
    streams = [profile_datagrams(c, n=1000)[0] for c in range(6)]  # 5 packets each
    seq = []
    seq += streams[0]
    p1 = streams[1]
    seq += [p1[0], p1[2], p1[1], p1[3], p1[3], p1[4]]  # reordered + duplicate
    seq += streams[2][:2] + streams[2][3:]  # one packet lost
    # profile 3 never arrives
    seq += streams[4]
    seq += [streams[2][2]]  # the lost one arrives too late
    seq += streams[5]
    asm = ProfileAssembler()
    out = [p for d in seq for p in asm.feed(d)] + asm.flush()
    assert [p.profile_counter for p in out] == [0, 1, 2, 4, 5]
    assert [p.complete for p in out] == [True, True, False, True, True]
    assert out[2].packets_received == 4 and out[2].n_points == 1000 - points_per_packet(1400)
    ev = asm.stats.events
    assert ev["reordered"] == 1 and ev["duplicate"] == 1 and ev["packets_lost"] == 1
    assert ev["profiles_lost"] == 1 and ev["late"] == 1


def test_reorder_across_profile_boundary_within_window():
    a, b = profile_datagrams(10, n=500)[0], profile_datagrams(11, n=500)[0]
    seq = a[:-1] + b[:1] + a[-1:] + b[1:]
    asm = ProfileAssembler(window=2)
    out = [p for d in seq for p in asm.feed(d)]
    assert [(p.profile_counter, p.complete) for p in out] == [(10, True), (11, True)]
    assert asm.stats.events["reordered"] == 0  # in-order within each profile; 10 was still open


def test_counter_wraps_and_resets():
    asm = ProfileAssembler()
    out = []
    for c in (0xFFFFFFFE, 0xFFFFFFFF, 0, 1):
        out += [p for d in profile_datagrams(c, n=300)[0] for p in asm.feed(d)]
    assert [p.profile_counter for p in out] == [0xFFFFFFFE, 0xFFFFFFFF, 0, 1]
    assert not asm.stats.events
    out = [p for d in profile_datagrams(5000, n=300)[0] + profile_datagrams(2, n=300)[0] for p in asm.feed(d)]
    assert [p.profile_counter for p in out] == [5000, 2] and asm.stats.events["counter_reset"] == 1


@pytest.mark.parametrize(
    ("mutate", "reason"),
    [
        (lambda d: d[:30], "short"),
        (lambda d: b"XFP1" + d[4:], "bad_magic"),
        (lambda d: d[:4] + struct.pack("<H", 41) + d[6:], "bad_header_size"),
        (lambda d: d[:-10], "size_mismatch"),
        (lambda d: d[:50] + bytes([d[50] ^ 1]) + d[51:], "bad_crc"),
    ],
)
def test_invalid_datagrams_are_rejected_by_reason(mutate, reason):
    dg = profile_datagrams(1, n=200)[0][0]
    with pytest.raises(ZfpError) as exc:
        decode_packet(mutate(dg))
    assert exc.value.reason == reason
    asm = ProfileAssembler()
    assert asm.feed(mutate(dg)) == [] and asm.stats.rejected[reason] == 1


def test_codec_round_trip_from_a_profile_and_uniformity_check():
    dgs, _, _ = profile_datagrams(8, n=700)
    asm = ProfileAssembler()
    (prof,) = [p for d in dgs for p in asm.feed(d)]
    assert ZFP1.encode_profile(prof) == dgs
    bent = Profile(1, prof.gps_ns.copy(), prof.scan_angle_rad, prof.range_m, prof.intensity)
    bent.gps_ns[5] += 1000
    with pytest.raises(DriverError, match="not evenly spaced"):
        ZFP1.encode_profile(bent)


def test_the_assembler_takes_another_codec():
    """The seam: a vendor codec only has to produce Packets."""

    class TinyCodec:
        name = "tiny"

        def decode_packet(self, data: bytes) -> Packet:
            counter, index, count = data[0], data[1], data[2]
            r = np.frombuffer(data, dtype="<u4", offset=4)
            return Packet(
                3,
                counter,
                index,
                count,
                1000 * counter + 10 * index * r.size,
                10,
                0,
                1,
                r,
                np.zeros(r.size, np.uint16),
            )

        def encode_profile(self, profile, max_payload=1400):
            raise NotImplementedError

    asm = ProfileAssembler(codec=TinyCodec())
    out = asm.feed(bytes([4, 0, 2, 0]) + np.arange(1, 4, dtype="<u4").tobytes())
    out += asm.feed(bytes([4, 1, 2, 0]) + np.arange(4, 7, dtype="<u4").tobytes())
    (prof,) = out
    assert prof.profile_counter == 4 and np.array_equal(prof.gps_ns, 4000 + 10 * np.arange(6))
    assert np.allclose(prof.range_m, np.arange(1, 7) * 1e-4)


@PROPERTY
@given(
    n=st.integers(0, 3000),
    max_payload=st.integers(50, 9000),
    t0=st.integers(0, 2**62),
    dt=st.integers(0, 2**32 - 1),
    a0=st.integers(-(2**30), 2**30),
    da=st.integers(-1000, 1000),
)
def test_encode_decode_round_trip_any_split(n, max_payload, t0, dt, a0, da):
    rng = np.random.default_rng(n)
    ranges = rng.integers(0, 2**32, n, dtype=np.uint32)
    inten = rng.integers(0, 2**16, n, dtype=np.uint16)
    dgs = encode_profile(77, t0, dt, a0, da, ranges, inten, max_payload=max_payload)
    assert all(len(d) <= max(max_payload, 50) for d in dgs)
    asm = ProfileAssembler()
    (prof,) = [p for d in dgs for p in asm.feed(d)]
    assert prof.complete and prof.n_points == n
    assert np.array_equal(prof.gps_ns, t0 + np.arange(n, dtype=np.int64) * dt)
    assert np.array_equal(
        np.nan_to_num(prof.range_m / 1e-4).round().astype(np.uint64), ranges.astype(np.uint64)
    )
    assert np.array_equal(prof.intensity, inten)


def test_feed_assembled_is_feed_without_the_arrays_and_remembers_the_last_packet():
    streams = [profile_datagrams(c, n=1000)[0] for c in range(5)]
    seq = streams[0] + [streams[1][k] for k in (0, 2, 1, 3, 3, 4)] + streams[2][:2] + streams[2][3:]
    seq += [b"ZFP1 not a packet"] + streams[4] + [streams[2][2]]
    lazy, eager = ProfileAssembler(), ProfileAssembler()
    last = []
    got = []
    for d in seq:
        got += lazy.feed_assembled(d, host_ns=len(got))
        last.append(lazy.last_packet)
    want = [p for i, d in enumerate(seq) for p in eager.feed(d, host_ns=None)]
    got += lazy.flush_assembled()
    want += eager.flush()
    assert [
        (a.profile_counter, a.packet_count, a.packets_received, a.pps_locked, a.time_valid, a.t0_ns)
        for a in got
    ] == [
        (p.profile_counter, p.packet_count, p.packets_received, p.pps_locked, p.time_valid, int(p.gps_ns[0]))
        for p in want
    ]
    for a, p in zip(got, want):
        b = a.build()
        assert np.array_equal(b.gps_ns, p.gps_ns) and np.array_equal(b.range_m, p.range_m, equal_nan=True)
    assert lazy.stats.events == eager.stats.events and lazy.stats.rejected == eager.stats.rejected
    bad = seq.index(b"ZFP1 not a packet")
    assert last[bad] is None and last[bad + 1].profile_counter == 4 and last[0].packet_index == 0


def test_a_fractional_point_period_gives_each_packet_its_own_rounded_t0():
    """As the scanner (and the emulator) send it: 984.25 ns between points, each packet's t0 and
    angle0 rounded from its first point's exact values, dt rounded once."""
    per = points_per_packet(1400)
    n, dt_exact, t_base = 1000, 984.25, 1_400_000_000_000_000_000
    ranges, inten = np.arange(1, n + 1, dtype=np.uint32), np.zeros(n, np.uint16)
    dgs = []
    for s in range(0, n, per):
        dgs += encode_profile(
            9, t_base + round(s * dt_exact), 984, 7 * s, 7, ranges[s : s + per], inten[s : s + per]
        )
    dgs = [decode_packet(d) for d in dgs]  # re-label the single-packet profiles as one of 5 packets
    packets = [
        Packet(
            p.flags & ~4 | (4 if k == len(dgs) - 1 else 0),
            9,
            k,
            len(dgs),
            *[
                getattr(p, a)
                for a in ("t0_ns", "dt_ns", "angle0_udeg", "dangle_udeg", "range_01mm", "intensity")
            ],
        )
        for k, p in enumerate(dgs)
    ]
    from drivers.zf.assembler import build_profile

    prof = build_profile(9, packets, len(packets), 1)
    i = np.arange(n)
    assert np.array_equal(
        prof.gps_ns, t_base + np.round((i // per * per) * dt_exact).astype(np.int64) + (i % per) * 984
    )
    assert np.allclose(np.degrees(prof.scan_angle_rad) * 1e6, 7 * i)
    assert np.array_equal(prof.range_m, ranges * 1e-4)


def _flip(d: bytes, bit: int) -> bytes:
    b = bytearray(d)
    b[bit // 8 % len(b)] ^= 1 << bit % 8
    return bytes(b)


@PROPERTY
@given(st.lists(st.tuples(st.integers(0, 3), st.integers(0, 1 << 16)), min_size=1, max_size=12))
def test_scan_packets_accepts_exactly_what_parse_header_accepts(spoils):
    from drivers.zf.zfp1 import HEADER_DTYPE, parse_header, scan_packets

    good = profile_datagrams(0, n=1500)[0] + profile_datagrams(1, n=300)[0]
    batch = []
    for j, (kind, arg) in enumerate(spoils):
        d = good[j % len(good)]
        batch.append([d, _flip(d, arg), d[: arg % len(d)], bytes(arg % 97)][kind])
    heads = scan_packets(batch)
    parsed = []
    for d in batch:
        try:
            parsed.append(parse_header(d))
        except ZfpError:
            parsed = None
            break
    assert (heads is None) == (parsed is None)
    if heads is not None:
        assert heads.dtype == HEADER_DTYPE and [tuple(h) for h in heads.tolist()] == parsed


def _disturbed_stream(draw_ops, n_profiles: int) -> list[bytes]:
    """Five-packet profiles (some not PPS-locked, some with an empty packet) disturbed by ops."""
    out = []
    for c in range(n_profiles):
        rng = np.random.default_rng(c)
        ranges = rng.integers(1, 3_000_000, 1000).astype(np.uint32)
        if c % 4 == 1:
            ranges[:226] = 0  # the first packet has no returns: t0 comes from the second
        dgs = encode_profile(
            c, 10**18 + c * 5_000_000, DT, 0, DANGLE, ranges, np.zeros(1000, np.uint16), pps_locked=c % 5 != 3
        )
        out += dgs
    for kind, at in draw_ops:
        at %= len(out)
        if kind == 0:
            del out[at]
        elif kind == 1:
            out.insert(at, out[at])
        elif kind == 2 and at + 1 < len(out):
            out[at], out[at + 1] = out[at + 1], out[at]
        elif kind == 3:
            out.insert(at, b"ZFP1 garbage")
        elif kind == 4:
            out[at] = _flip(out[at], 8 * 20)
    return out


def _seen(profiles):
    return [
        (
            a.profile_counter,
            a.packet_count,
            a.packets_received,
            a.pps_locked,
            a.time_valid,
            a.t0_ns,
            a.host_ns,
        )
        for a in profiles
    ]


@PROPERTY
@given(
    st.lists(st.tuples(st.integers(0, 4), st.integers(0, 10**6)), max_size=6),
    st.lists(st.integers(1, 17), min_size=1, max_size=40),
    st.integers(4, 14),
)
def test_feed_batch_is_feeding_one_by_one(ops, sizes, n_profiles):
    stream = _disturbed_stream(ops, n_profiles)
    hosts = list(range(1000, 1000 + len(stream)))
    one, batched = ProfileAssembler(), ProfileAssembler()
    want, want_tags = [], []
    for d, h in zip(stream, hosts):
        want += one.feed_assembled(d, h)
        p = one.last_packet
        want_tags.append(p.t0_ns if p is not None and p.pps_locked and p.time_valid else None)
    got, tags, a, k = [], [], 0, 0
    while a < len(stream):
        b = a + sizes[k % len(sizes)]
        profiles, t = batched.feed_batch(stream[a:b], hosts[a:b])
        got += profiles
        tags += t
        p, q = batched.last_packet, one.last_packet if b >= len(stream) else None
        if q is not None:
            assert (p is None) == (q is None) and (
                p is None or (p.profile_counter, p.packet_index) == (q.profile_counter, q.packet_index)
            )
        a, k = b, k + 1
    want += one.flush_assembled()
    got += batched.flush_assembled()
    assert _seen(got) == _seen(want) and tags == want_tags
    for x, y in zip(got, want):
        bx, by = x.build(), y.build()
        assert np.array_equal(bx.gps_ns, by.gps_ns) and np.array_equal(bx.range_m, by.range_m, equal_nan=True)
    assert batched.stats.events == one.stats.events and batched.stats.rejected == one.stats.rejected
    assert (batched.stats.records, batched.stats.bytes_in) == (one.stats.records, one.stats.bytes_in)


def test_a_clean_stream_in_batches_is_not_decoded_datagram_by_datagram():
    stream = _disturbed_stream([], 20)
    asm = ProfileAssembler()
    calls = []
    decode = asm._decode
    asm._decode = lambda d: calls.append(d) or decode(d)
    profiles = []
    for a in range(0, len(stream), 7):
        profiles += asm.feed_batch(stream[a : a + 7], list(range(a, a + 7)))[0]
    assert [p.profile_counter for p in profiles] == list(range(20)) and all(
        p.packets_received == 5 for p in profiles
    )
    assert len(calls) <= 7 + len(stream) // 7 + 1  # the first batch one by one, then one decode a batch
    assert len(profiles[10].build().gps_ns) == 1000  # the points are still there when wanted
