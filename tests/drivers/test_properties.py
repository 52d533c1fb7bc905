"""Robustness properties of every decoder: random bytes, truncation, bit flips, garbage before frames.

No exception escapes a decoder; damaged frames are counted; a valid frame after garbage still
decodes. (Round trips of generated records live with each codec's tests.)
"""

from __future__ import annotations

import asyncio
import calendar
import datetime as dt
import struct
from collections import Counter

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from drivers.base import DriverError
from drivers.can import (
    EVENT_MARKER_ID,
    CanFrame,
    CanReader,
    EventMarker,
    can_frame_bytes,
    decode_event_marker,
    encode_event_marker,
    parse_can_frame,
)
from drivers.capture.files import split_stamped_line
from drivers.capture.pcapng import CaptureReader, PcapError, udp_datagrams
from drivers.hydrins.nmea_decode import NmeaDecoder, NmeaNavAssembler
from drivers.hydrins.stdbin_decode import StdbinDecoder, StdbinNavDecoder
from drivers.pps import PpsEdge, PpsLabeler, UdpPpsSource, decode_pps_datagram, encode_pps_datagram
from drivers.zf.assembler import ProfileAssembler
from drivers.zf.zfp1 import CRC_SIZE, HEADER_SIZE, ZfpError, decode_packet, encode_profile
from tests.drivers.helpers import PROPERTY, real_file

NMEA_FRAME = b"$PIXSE,POSITI,53.10245714,8.83994382,-0.115*71\r\n"
ZFP_FRAME = encode_profile(
    1, 10**18, 1000, 0, 70866, np.arange(40, dtype=np.uint32), np.arange(40, dtype=np.uint16)
)[0]


def _stdbin_frame() -> bytes:
    return real_file("ixblue-stdbin", "log_STDBIN_V2.log").read_bytes()


def stream_decoders():
    return [
        ("nmea", NmeaDecoder, NMEA_FRAME),
        ("nmea-nav", lambda: NmeaNavAssembler(utc_clock=None), NMEA_FRAME),
        ("stdbin", StdbinDecoder, _stdbin_frame()),
        ("stdbin-nav", lambda: StdbinNavDecoder(utc_clock=None), _stdbin_frame()),
    ]


def _decode_all(make, chunks):
    dec = make()
    out = []
    for c in chunks:
        out += dec.feed(c)
    out += dec.flush()
    return dec, out


@pytest.mark.parametrize(
    ("name", "make", "frame"), stream_decoders(), ids=lambda v: v if isinstance(v, str) else ""
)
@PROPERTY
@given(data=st.binary(max_size=2000), cuts=st.lists(st.integers(0, 2000), max_size=6))
def test_random_bytes_never_raise(name, make, frame, data, cuts):
    pieces, last = [], 0
    for c in sorted(cuts):
        pieces.append(data[last:c])
        last = c
    pieces.append(data[last:])
    dec, _ = _decode_all(make, pieces)
    assert dec.stats.bytes_in == len(data)


@pytest.mark.parametrize(
    ("name", "make", "frame"), stream_decoders(), ids=lambda v: v if isinstance(v, str) else ""
)
def test_truncation_at_every_offset_then_a_valid_frame(name, make, frame):
    complete = len(frame) - 2 if name.startswith("nmea") else len(frame)  # NMEA: CR already ends it
    for cut in range(complete):
        dec, out = _decode_all(make, [frame[:cut], frame])
        assert len(out) == 1, cut  # the truncated copy is dropped, the whole one decodes
        # and counted: its bytes are skipped (exactly those, not the whole frame's after it)
        s = dec.stats
        assert s.skipped_bytes == cut and (cut == 0) == (s.rejected_total + s.skipped_bytes == 0), cut
        if name.startswith("nmea"):  # the next '$' restarts the line: nothing to reject, all skipped
            assert s.rejected_total == 0, cut


@pytest.mark.parametrize(
    ("name", "make", "frame"), stream_decoders(), ids=lambda v: v if isinstance(v, str) else ""
)
@PROPERTY
@given(bit=st.integers(0, 10**6))
def test_single_bit_flip_is_rejected_and_the_next_frame_decodes(name, make, frame, bit):
    bit %= len(frame) * 8
    bad = bytearray(frame)
    bad[bit // 8] ^= 1 << (bit % 8)
    dec, out = _decode_all(make, [bytes(bad) + frame])
    # a flip either breaks the checksum (counted) or hits a byte outside the frame's checked part
    # (NMEA line ending); never two records, never a record from the damaged copy with the wrong data
    assert 1 <= len(out) <= 2
    if len(out) == 2:
        assert name.startswith("nmea") and (
            bit // 8 >= len(frame) - 2 or bad[bit // 8 : bit // 8 + 1] in (b"\r", b"\n")
        )
    else:
        assert dec.stats.rejected_total + dec.stats.skipped_bytes >= 1


@pytest.mark.parametrize(
    ("name", "make", "frame"), stream_decoders(), ids=lambda v: v if isinstance(v, str) else ""
)
@PROPERTY
@given(garbage=st.binary(max_size=600))
def test_valid_frame_after_garbage_decodes(name, make, frame, garbage):
    dec, out = _decode_all(make, [garbage + b"\n" + frame])
    assert len(out) >= 1
    if name == "stdbin":
        assert out[-1].validity_time_100us == 9215311
    elif name == "nmea":
        assert out[-1].lat_deg == 53.10245714


@PROPERTY
@given(data=st.binary(max_size=1600), flip=st.integers(0, 10**6), cut=st.integers(0, 2000))
def test_profile_assembler_never_raises(data, flip, cut):
    asm = ProfileAssembler()
    bad = bytearray(ZFP_FRAME)
    bad[flip % len(bad)] ^= 1 << (flip % 8)
    for dg in (data, bytes(bad), ZFP_FRAME[: cut % len(ZFP_FRAME)]):
        assert asm.feed(dg) == []
    (prof,) = asm.feed(ZFP_FRAME)
    assert prof.n_points == 40
    assert asm.stats.rejected_total == 3


# ZFP1 datagrams: truncation at every offset, every single-bit flip, each followed by a valid one.
ZFP_NEXT = encode_profile(
    2, 10**18 + 5_000_000, 1000, 0, 70866, np.arange(40, 80, dtype=np.uint32), np.arange(40, dtype=np.uint16)
)[0]


def _zfp_damaged_then_valid(bad: bytes):
    """(one-by-one assembler, batch assembler, profiles of each) after ``bad`` then ZFP_NEXT."""
    one, batch = ProfileAssembler(), ProfileAssembler()
    got_one = one.feed(bad) + one.feed(ZFP_NEXT)
    got_batch = [a.build() for a in batch.feed_batch([bad, ZFP_NEXT], [1, 2])[0]]
    return one, batch, got_one, got_batch


def _assert_rejected_then_decoded(bad: bytes, reason: str, where) -> None:
    one, batch, got_one, got_batch = _zfp_damaged_then_valid(bad)
    for asm, got in ((one, got_one), (batch, got_batch)):
        assert dict(asm.stats.rejected) == {reason: 1}, (where, dict(asm.stats.rejected))
        assert len(got) == 1 and got[0].profile_counter == 2 and got[0].complete, where
        assert np.array_equal(got[0].range_m, np.arange(40, 80) * 1e-4), where
        assert asm.stats.records == 1 and not asm.stats.events, where
        assert asm.stats.bytes_in == len(bad) + len(ZFP_NEXT), where


def test_zfp_datagram_truncated_at_every_offset_is_rejected_then_the_next_decodes():
    for cut in range(len(ZFP_FRAME)):
        _assert_rejected_then_decoded(
            ZFP_FRAME[:cut], "short" if cut < HEADER_SIZE + CRC_SIZE else "size_mismatch", cut
        )


def test_zfp_datagram_every_single_bit_flip_is_rejected_then_the_next_decodes():
    """CRC-32 catches every single-bit error; the fields checked before it name the reason."""
    reasons = Counter()
    for bit in range(len(ZFP_FRAME) * 8):
        bad = bytearray(ZFP_FRAME)
        bad[bit // 8] ^= 1 << (bit % 8)
        byte = bit // 8
        # magic (bytes 0-3), header_size (4-5) and n_points (36-37) are checked before the CRC
        reason = (
            "bad_magic"
            if byte < 4
            else "bad_header_size"
            if byte < 6
            else "size_mismatch"
            if byte in (36, 37)
            else "bad_crc"
        )
        with pytest.raises(ZfpError) as exc:
            decode_packet(bytes(bad))
        assert exc.value.reason == reason, bit
        _assert_rejected_then_decoded(bytes(bad), reason, bit)
        reasons[reason] += 1
    assert reasons == {
        "bad_magic": 32,
        "bad_header_size": 16,
        "size_mismatch": 16,
        "bad_crc": len(ZFP_FRAME) * 8 - 64,
    }


@PROPERTY
@given(data=st.binary(max_size=40))
def test_small_datagram_decoders_raise_only_driver_errors(data):
    for decode in (decode_pps_datagram, lambda d: decode_event_marker(CanFrame(0x6E0, d, 0, 0.0))):
        try:
            decode(data)
        except DriverError:
            pass


@PROPERTY
@given(
    seq=st.integers(0, 2**64 - 1),
    host=st.integers(-(2**63), 2**63 - 1),
    kind=st.sampled_from(["pass_start", "pass_end", "mark"]),
    pass_id=st.integers(0, 65535),
)
def test_small_datagram_round_trips(seq, host, kind, pass_id):
    assert decode_pps_datagram(encode_pps_datagram(seq, host)).sequence == seq
    m = decode_event_marker(CanFrame(0x6E0, encode_event_marker(kind, pass_id, seq), 5, 0.0))
    assert (m.kind, m.pass_id, m.sequence) == (kind, pass_id, seq & 0xFFFFFFFF)


@PROPERTY
@given(
    events=st.lists(st.tuples(st.booleans(), st.integers(0, 5_000_000_000), st.integers(0, 50)), max_size=60)
)
def test_pps_labeler_never_raises_and_labels_increase(events):
    lab = PpsLabeler()
    labels = []
    t = 0
    for is_edge, step, n in events:
        t += step
        if is_edge:
            lab.add_edge(__import__("drivers.pps", fromlist=["PpsEdge"]).PpsEdge(t, "x", n))
        else:
            labels += [e.gps_s for e in lab.add_time(n, t)]
    assert labels == sorted(set(labels))


@PROPERTY
@given(data=st.binary(max_size=300))
def test_capture_reader_raises_only_pcap_errors(data):
    for head in (b"", b"\x0a\x0d\x0d\x0a", b"\xd4\xc3\xb2\xa1"):
        try:
            list(udp_datagrams(CaptureReader(head + data)))
        except PcapError:
            pass
        except Exception as exc:  # struct.error and friends would be a defect
            if not isinstance(exc, PcapError):
                raise


# ---------------------------------------------------------------------------------------------
# PPS datagrams: truncation at every offset, every single-bit flip.
# ---------------------------------------------------------------------------------------------

PPS_DG = encode_pps_datagram(0x0123_4567_89AB_CDEF, 1_234_567_890_123_456_789)


def _pps_udp_source_feed(datagrams):
    """Hand datagrams to a real UdpPpsSource's protocol (no network between): (edges, stats)."""

    async def run():
        src = UdpPpsSource("127.0.0.1", 0, "emu")
        edges = []
        async with src:
            proto = src._transport.get_protocol()
            for dg in datagrams:
                proto.datagram_received(dg, ("127.0.0.1", 9))
                while not src._queue.empty():
                    edges.append(src._queue.get_nowait())
        return edges, src.stats

    return asyncio.run(run())


def test_pps_datagram_truncated_at_every_offset_is_rejected_and_counted():
    for cut in range(len(PPS_DG)):
        with pytest.raises(DriverError, match=f"PPS datagram of {cut} bytes: expected {len(PPS_DG)}"):
            decode_pps_datagram(PPS_DG[:cut])
    edges, stats = _pps_udp_source_feed(
        [PPS_DG[:cut] for cut in range(len(PPS_DG))] + [PPS_DG, PPS_DG + b"\0"]
    )
    assert [e.sequence for e in edges] == [0x0123_4567_89AB_CDEF]
    assert stats.rejected["bad_datagram"] == len(PPS_DG) + 1 and stats.records == 1


def test_pps_datagram_every_single_bit_flip():
    """PPS1 has no checksum: a flip in the magic is rejected, a flip elsewhere decodes to a
    different edge (exactly that bit of the sequence or of the stamp) — nothing else."""
    good = decode_pps_datagram(PPS_DG)
    flipped, n_magic = [], 0
    for bit in range(len(PPS_DG) * 8):
        bad = bytearray(PPS_DG)
        bad[bit // 8] ^= 1 << (bit % 8)
        flipped.append(bytes(bad))
        if bit < 32:
            n_magic += 1
            with pytest.raises(DriverError, match="magic"):
                decode_pps_datagram(bytes(bad))
            continue
        e = decode_pps_datagram(bytes(bad))
        k = bit - 32
        if k < 64:
            assert e.sequence == good.sequence ^ (1 << k) and e.host_ns == good.host_ns
        else:
            expect = (good.host_ns & (2**64 - 1)) ^ (1 << (k - 64))
            assert e.host_ns == expect - (2**64 if expect >= 2**63 else 0) and e.sequence == good.sequence
    edges, stats = _pps_udp_source_feed(flipped + [PPS_DG])
    assert stats.rejected["bad_datagram"] == n_magic == 32
    assert len(edges) == len(flipped) - 32 + 1 and edges[-1] == PpsEdge(good.host_ns, "emu", good.sequence)


# ---------------------------------------------------------------------------------------------
# CAN: event markers through a CanReader's decoder hook, SocketCAN frame records.
# ---------------------------------------------------------------------------------------------


def _marker_reader():
    return CanReader(None, {EVENT_MARKER_ID: decode_event_marker}), f"0x{EVENT_MARKER_ID:x}"


def test_event_marker_truncated_at_every_offset_is_rejected_and_counted():
    good = encode_event_marker("pass_end", 513, 70000)
    reader, key = _marker_reader()
    for cut in range(len(good)):
        assert reader.decode(CanFrame(0x6E0, good[:cut], cut, 0.0)).decoded is None
    assert reader.stats.rejected[key] == len(good)
    assert reader.decode(CanFrame(0x6E0, good, 99, 0.0)).decoded == EventMarker("pass_end", 513, 70000, 99)


def test_event_marker_every_single_bit_flip():
    """No CRC in the payload (CAN has its own): format and kind flips are rejected unless the kind
    lands on another valid code; pass id and sequence flips decode to exactly that change."""
    good = encode_event_marker("pass_start", 0x0203, 0x0A0B0C0D)
    reader, key = _marker_reader()
    rejected = 0
    for bit in range(len(good) * 8):
        bad = bytearray(good)
        bad[bit // 8] ^= 1 << (bit % 8)
        m = reader.decode(CanFrame(0x6E0, bytes(bad), bit, 0.0)).decoded
        byte = bit // 8
        if byte == 0 or (byte == 1 and bad[1] not in (1, 2, 3)):
            assert m is None, bit
            rejected += 1
        elif byte == 1:
            assert m.kind in ("pass_end", "mark") and (m.pass_id, m.sequence) == (0x0203, 0x0A0B0C0D)
        elif byte < 4:
            assert m.pass_id == 0x0203 ^ (1 << (bit - 16)) and m.sequence == 0x0A0B0C0D
        else:
            assert m.sequence == 0x0A0B0C0D ^ (1 << (bit - 32)) and m.pass_id == 0x0203
    assert reader.stats.rejected[key] == rejected and rejected > 8
    assert reader.decode(CanFrame(0x6E0, good, 1, 0.0)).decoded.kind == "pass_start"


CAN_RECORDS = [
    (0x6E0, encode_event_marker("mark", 1, 2), False),
    (0x1ABCDE, b"\x01\x02\x03", True),
    (0x123, bytes(range(48)), False),
]


@pytest.mark.parametrize(("arb", "data", "ext"), CAN_RECORDS)
def test_can_frame_record_truncated_at_every_offset_is_rejected(arb, data, ext):
    raw = can_frame_bytes(arb, data, ext)
    for cut in range(len(raw)):
        with pytest.raises(DriverError, match=f"CAN frame record of {cut} bytes"):
            parse_can_frame(raw[:cut])
    assert parse_can_frame(raw) == (arb, data, ext)


@pytest.mark.parametrize(("arb", "data", "ext"), CAN_RECORDS)
def test_can_frame_record_every_single_bit_flip(arb, data, ext):
    """The record has no checksum: a flip changes the id, the flags, the length or the data (or
    falls in padding); a length beyond the data or a standard id beyond 11 bits is rejected."""
    raw = can_frame_bytes(arb, data, ext)
    cap = 8 if len(raw) == 16 else 64
    data_at = 8
    for bit in range(len(raw) * 8):
        bad = bytearray(raw)
        bad[bit // 8] ^= 1 << (bit % 8)
        byte = bit // 8
        try:
            got = parse_can_frame(bytes(bad))
        except DriverError:
            n = bad[4]
            can_id = int.from_bytes(bad[:4], "little")
            assert n > cap or (not can_id & 0x80000000 and can_id & 0x1FFFFFFF > 0x7FF), bit
            continue
        g_arb, g_data, g_ext = got
        if byte < 4:  # the id word: id bits, EFF flag, RTR/ERR flags (ignored)
            assert g_data == data
        elif byte == 4:
            assert g_arb == arb and g_ext == ext and len(g_data) == bad[4] <= cap
            assert g_data[: min(len(data), len(g_data))] == data[: len(g_data)]
        elif byte < data_at:  # flags / padding
            assert got == (arb, data, ext)
        elif byte - data_at < len(data):
            assert g_arb == arb and g_ext == ext and len(g_data) == len(data) and g_data != data
        else:  # padding behind the data
            assert got == (arb, data, ext)


@PROPERTY
@given(ext=st.booleans(), arb=st.integers(0, 0x1FFFFFFF), data=st.binary(max_size=64))
def test_can_frame_record_round_trip(ext, arb, data):
    arb = arb if ext else arb & 0x7FF
    assert parse_can_frame(can_frame_bytes(arb, data, ext)) == (arb, data, ext)


@PROPERTY
@given(
    raw=st.one_of(
        st.binary(max_size=100), st.binary(min_size=16, max_size=16), st.binary(min_size=72, max_size=72)
    ),
    n=st.one_of(st.none(), st.integers(0, 70)),
    small_id=st.booleans(),
)
def test_can_frame_record_random_bytes_raise_only_driver_errors(raw, n, small_id):
    """Random records (some with a plausible length byte and an 11-bit id, so some parse)."""
    raw = bytearray(raw)
    if n is not None and len(raw) > 4:
        raw[4] = n
    if small_id and len(raw) > 3:
        raw[1], raw[2], raw[3] = raw[1] & 0x07, 0, raw[3] & 0xE0  # id < 0x800, flag bits kept
    raw = bytes(raw)
    try:
        arb, data, ext = parse_can_frame(raw)
    except DriverError:
        return
    assert len(raw) in (16, 72) and len(data) == raw[4] <= len(raw) - 8
    assert arb <= (0x1FFFFFFF if ext else 0x7FF) and ext == bool(raw[3] & 0x80)
    assert data == raw[8 : 8 + len(data)]
    assert parse_can_frame(can_frame_bytes(arb, data, ext)) == (arb, data, ext)  # what it accepts re-encodes


# ---------------------------------------------------------------------------------------------
# Stamped log lines (``ISO8601Z <payload>``, as OpenRVDAS writes them).
# ---------------------------------------------------------------------------------------------

_STAMP_LIKE = st.from_regex(rb"\A\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d(\.\d{0,11})?Z? ?", fullmatch=True)


@PROPERTY
@given(head=st.one_of(st.just(b""), _STAMP_LIKE), tail=st.binary(max_size=200))
def test_split_stamped_line_random_bytes_never_raise(head, tail):
    """The function has no error: a line without a valid stamp comes back whole, unstamped."""
    line = head + tail
    stamp, payload = split_stamped_line(line)
    if stamp is None:
        assert payload == line
    else:
        assert line.endswith(b" " + payload) and line[:4].isdigit()


@PROPERTY
@given(
    when=st.datetimes(min_value=dt.datetime(1, 1, 1), max_value=dt.datetime(9999, 12, 31, 23, 59, 59)),
    frac=st.one_of(st.none(), st.text("0123456789", min_size=1, max_size=9)),
    zulu=st.booleans(),
    payload=st.binary(max_size=100),
)
def test_split_stamped_line_round_trip(when, frac, zulu, payload):
    stamp = when.replace(microsecond=0).isoformat() + ("." + frac if frac else "") + ("Z" if zulu else "")
    ns, rest = split_stamped_line(stamp.encode() + b" " + payload)
    assert rest == payload
    assert ns == calendar.timegm(when.timetuple()) * 10**9 + int((frac or "").ljust(9, "0"))


# ---------------------------------------------------------------------------------------------
# pcapng: a real capture cut at many offsets and with flipped bits.
# ---------------------------------------------------------------------------------------------

PCAPNG_FILES = ["stdbin_V2_2Hz.pcapng", "stdbin_V3_2Hz.pcapng", "stdbin_V5_2Hz.pcapng"]


def _blocks(data: bytes) -> list[int]:
    """End offsets of the capture's blocks (little-endian pcapng, as these files are)."""
    ends, pos = [], 0
    while pos + 8 <= len(data):
        pos += struct.unpack_from("<I", data, pos + 4)[0]
        ends.append(pos)
    assert pos == len(data)
    return ends


def _read(data: bytes):
    """(datagrams, reader stats, error): iterate until the reader stops or raises."""
    reader = CaptureReader(data)
    grams, err = [], None
    try:
        for g in udp_datagrams(reader):
            grams.append(g)
    except PcapError as e:
        err = e
    return grams, reader.stats, err


def _stdbin_of(grams):
    dec = StdbinDecoder()
    return [f for g in grams for f in dec.feed(g.payload, g.timestamp_ns)], dec


@pytest.fixture(scope="module", params=PCAPNG_FILES)
def capture(request):
    data = real_file("ixblue-stdbin", request.param).read_bytes()
    grams, stats, err = _read(data)
    assert err is None and not stats.rejected and grams
    ends = _blocks(data)
    # datagrams complete by the end of each block
    complete = {end: len(_read(data[:end])[0]) for end in ends}
    return data, grams, ends, complete


def _intact(ends, complete, offset):
    """Datagrams in blocks that end at or before ``offset``."""
    return max([complete[e] for e in ends if e <= offset], default=0)


def test_pcapng_cut_at_many_offsets_keeps_every_whole_record(capture):
    """Every offset of the section and interface headers, of the first and last packet blocks'
    headers, one byte either side of every block boundary, and every 37th offset elsewhere."""
    data, grams, ends, complete = capture
    near = {o for e in [0, *ends[:6], *ends[-4:]] for o in range(e - 8, e + 32)}
    near |= {o for e in ends for o in (e - 1, e, e + 1)}
    offsets = sorted(
        o for o in set(range(ends[1])) | near | set(range(0, len(data), 37)) if 0 <= o < len(data)
    )
    for cut in offsets:
        got, stats, err = _read(data[:cut])
        if cut < 4:
            assert isinstance(err, PcapError) and got == []
            continue
        assert err is None, cut  # a capture cut short ends the iteration; nothing raises
        k = _intact(ends, complete, cut)
        assert got == grams[:k], cut
        assert (stats.rejected["truncated"] == 1) == (cut not in ends), cut
        frames, dec = _stdbin_of(got)
        assert len(frames) == k and dec.stats.rejected_total == 0


@PROPERTY
@given(bit=st.integers(0, 10**7), cut=st.integers(0, 10**7))
def test_pcapng_random_cuts_and_bit_flips(capture, bit, cut):
    data, grams, ends, complete = capture
    bit %= len(data) * 8
    bad = bytearray(data)
    bad[bit // 8] ^= 1 << (bit % 8)
    bad = bytes(bad[: max(bit // 8 + 1, cut % (len(data) + 1))])
    got, stats, err = _read(bad)  # raises nothing but PcapError (checked in _read)
    k = _intact(ends, complete, bit // 8)
    assert got[:k] == grams[:k]  # every record before the damage still comes out
    frames, dec = _stdbin_of(got)  # and the damaged payloads do not break the decoder
    assert len(frames) >= k


def test_pcapng_every_bit_of_the_block_headers(capture):
    """Block type and length words of the first blocks: the fields that steer the reader."""
    data, grams, ends, complete = capture
    for start in [0, *ends[:5]]:
        for bit in range(start * 8, (start + 8) * 8):
            bad = bytearray(data)
            bad[bit // 8] ^= 1 << (bit % 8)
            got, stats, err = _read(bytes(bad))
            k = _intact(ends, complete, start)
            assert got[:k] == grams[:k], bit
            _stdbin_of(got)


def test_pcapng_damaged_block_lengths(capture):
    """A block length rewritten to every multiple of 4 from 12 to its true size (the block
    then ends early, and the reader parses what follows as the next block): only PcapError may
    escape; a block too short for its fixed fields is counted, not a struct.error."""
    data, grams, ends, complete = capture
    for start in ends[:4]:  # the interface block and the first packet blocks
        true_len = struct.unpack_from("<I", data, start + 4)[0]
        for n in range(12, true_len, 4):
            bad = bytearray(data)
            struct.pack_into("<I", bad, start + 4, n)
            got, stats, err = _read(bytes(bad))
            k = _intact(ends, complete, start)
            assert got[:k] == grams[:k], (start, n)
            btype = struct.unpack_from("<I", data, start)[0]
            if (btype == 6 and n < 12 + 20) or (btype == 1 and n < 12 + 8):  # EPB / IDB fixed fields
                assert stats.rejected["short_block"] == 1, (start, n)
            _stdbin_of(got)
