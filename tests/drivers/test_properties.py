"""Robustness properties of every decoder: random bytes, truncation, bit flips, garbage before frames.

No exception escapes a decoder; damaged frames are counted; a valid frame after garbage still
decodes. (Round trips of generated records live with each codec's tests.)
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from drivers.base import DriverError
from drivers.can import CanFrame, decode_event_marker, encode_event_marker
from drivers.hydrins.nmea import NmeaDecoder, NmeaNavAssembler
from drivers.hydrins.stdbin import StdbinDecoder, StdbinNavDecoder
from drivers.pcapng import CaptureReader, PcapError, udp_datagrams
from drivers.pps import PpsLabeler, decode_pps_datagram, encode_pps_datagram
from drivers.zf.assembler import ProfileAssembler
from drivers.zf.zfp1 import encode_profile
from tests.drivers.helpers import PROPERTY, real_file

NMEA_FRAME = b"$PIXSE,POSITI,53.10245714,8.83994382,-0.115*71\r\n"
ZFP_FRAME = encode_profile(1, 10**18, 1000, 0, 70866, np.arange(40, dtype=np.uint32), np.arange(40, dtype=np.uint16))[0]


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


@pytest.mark.parametrize("name, make, frame", stream_decoders(), ids=lambda v: v if isinstance(v, str) else "")
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


@pytest.mark.parametrize("name, make, frame", stream_decoders(), ids=lambda v: v if isinstance(v, str) else "")
def test_truncation_at_every_offset_then_a_valid_frame(name, make, frame):
    complete = len(frame) - 2 if name.startswith("nmea") else len(frame)  # NMEA: CR already ends it
    for cut in range(complete):
        dec, out = _decode_all(make, [frame[:cut], frame])
        assert len(out) == 1, cut  # the truncated copy is dropped, the whole one decodes


@pytest.mark.parametrize("name, make, frame", stream_decoders(), ids=lambda v: v if isinstance(v, str) else "")
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
        assert name.startswith("nmea") and (bit // 8 >= len(frame) - 2 or bad[bit // 8 : bit // 8 + 1] in (b"\r", b"\n"))
    else:
        assert dec.stats.rejected_total + dec.stats.skipped_bytes >= 1


@pytest.mark.parametrize("name, make, frame", stream_decoders(), ids=lambda v: v if isinstance(v, str) else "")
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


@PROPERTY
@given(data=st.binary(max_size=40))
def test_small_datagram_decoders_raise_only_driver_errors(data):
    for decode in (decode_pps_datagram, lambda d: decode_event_marker(CanFrame(0x6E0, d, 0, 0.0))):
        try:
            decode(data)
        except DriverError:
            pass


@PROPERTY
@given(seq=st.integers(0, 2**64 - 1), host=st.integers(-(2**63), 2**63 - 1), kind=st.sampled_from(["pass_start", "pass_end", "mark"]), pass_id=st.integers(0, 65535))
def test_small_datagram_round_trips(seq, host, kind, pass_id):
    assert decode_pps_datagram(encode_pps_datagram(seq, host)).sequence == seq
    m = decode_event_marker(CanFrame(0x6E0, encode_event_marker(kind, pass_id, seq), 5, 0.0))
    assert (m.kind, m.pass_id, m.sequence) == (kind, pass_id, seq & 0xFFFFFFFF)


@PROPERTY
@given(events=st.lists(st.tuples(st.booleans(), st.integers(0, 5_000_000_000), st.integers(0, 50)), max_size=60))
def test_pps_labeler_never_raises_and_labels_increase(events):
    lab = PpsLabeler()
    labels = []
    t = 0
    for is_edge, dt, n in events:
        t += dt
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
