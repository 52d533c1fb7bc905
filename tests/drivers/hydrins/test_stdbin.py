"""Hydrins STDBIN: framing, resynchronization, versions, answers, the canonical view, the encoder."""

from __future__ import annotations

import math
import struct

import pytest
from hypothesis import given
from hypothesis import strategies as st

from calib.core.frames import utc_fields_to_gps_ns
from drivers.base import DriverError
from drivers.hydrins.nav import NavRecord, status_words
from drivers.hydrins.stdbin_decode import StdbinDecoder, StdbinNavDecoder
from drivers.hydrins.stdbin_encode import encode_answer, encode_frame, encode_nav
from drivers.hydrins.stdbin_format import BLOCK_SIZES, NAVIGATION_BLOCKS
from drivers.hydrins.stdbin_records import StdbinAnswer, StdbinFrame
from tests.drivers.helpers import PROPERTY, real_file


@pytest.fixture(scope="module")
def v2() -> bytes:
    return real_file("ixblue-stdbin", "log_STDBIN_V2.log").read_bytes()


@pytest.fixture(scope="module")
def v3() -> bytes:
    return real_file("ixblue-stdbin", "log_STDBIN_V3.log").read_bytes()


def test_block_table_matches_the_real_frame_sizes(v2):
    # V2 frame: mask 0x03e3ffff → 261 bytes of blocks + 21 header + 4 checksum = 286
    mask = struct.unpack_from(">I", v2, 3)[0]
    total = sum(BLOCK_SIZES[NAVIGATION_BLOCKS[b][0]] for b in range(32) if mask >> b & 1)
    assert total == 261 and len(v2) == 21 + total + 4


def test_frame_split_at_every_offset_decodes_once(v2):
    for cut in range(1, len(v2)):
        dec = StdbinDecoder()
        assert dec.feed(v2[:cut], host_ns=1) == []
        (frame,) = dec.feed(v2[cut:], host_ns=2)
        assert frame.validity_time_100us == 9215311
        assert frame.host_ns == 1  # the stamp of the chunk that brought the first byte
        assert dec.stats.rejected_total == 0 and dec.stats.skipped_bytes == 0


def test_garbage_before_and_between_frames_is_skipped(v2, v3):
    dec = StdbinDecoder()
    garbage = b"IXAN\x00garbage IX\x09"  # contains false starts
    frames = dec.feed(garbage + v2 + b"\xff" * 7 + v3)
    assert len(frames) == 18
    assert dec.stats.rejected_total >= 1  # the false starts were rejected, not decoded
    assert dec.stats.skipped_bytes == len(garbage) + 7


def test_bad_checksum_is_counted_and_the_next_frame_decodes(v2):
    bad = bytearray(v2)
    bad[40] ^= 0x10
    dec = StdbinDecoder()
    (frame,) = dec.feed(bytes(bad) + v2)
    assert frame.heading_deg == pytest.approx(209.982, abs=1e-4)
    assert dec.stats.rejected["bad_checksum"] == 1


def test_unknown_version_is_counted(v2):
    bad = bytearray(v2)
    bad[2] = 9
    dec = StdbinDecoder()
    assert dec.feed(bytes(bad)) == []
    assert dec.stats.rejected["unknown_version"] == 1


def test_unknown_navigation_bit_v5_still_delivers_known_and_external_blocks():
    # bit 31 of the navigation mask is not in the table: V5's navigation size locates the external data
    frame = StdbinFrame(
        5,
        7,
        1234,
        {
            "attitude_heading": {"heading_deg": 10.0, "roll_deg": 1.0, "pitch_deg": 2.0},
            "utc": {"validity_time_100us": 1230, "source": 1},
        },
    )
    raw = bytearray(encode_frame(frame))
    nav_size = struct.unpack_from(">H", raw, 15)[0]
    extra = b"\xab" * 6
    raw = (
        raw[:3]
        + struct.pack(">I", 1 | 1 << 31)
        + raw[7:15]
        + struct.pack(">HH", nav_size + 6, len(raw) + 6)
        + raw[19 : 27 + 12]
        + extra
        + raw[27 + 12 : -4]
    )
    raw += struct.pack(">I", sum(raw) & 0xFFFFFFFF)
    dec = StdbinDecoder()
    (back,) = dec.feed(bytes(raw))
    assert back.blocks["attitude_heading"]["heading_deg"] == 10.0
    assert back.blocks["utc"] == {"validity_time_100us": 1230, "source": 1}
    assert dec.stats.events["unknown_block"] == 1


def test_answer_frames():
    payload = b"$PIXSE,CONFIG,OK"
    dec = StdbinDecoder()
    (ans,) = dec.feed(encode_answer(payload, 3))
    assert isinstance(ans, StdbinAnswer) and ans.payload == payload and ans.protocol_version == 3
    with pytest.raises(DriverError, match="answer version"):
        encode_answer(payload, 2)


def test_encoder_rejects_bad_blocks_with_clear_errors():
    with pytest.raises(DriverError, match="'nope' is unknown"):
        encode_frame(StdbinFrame(3, 0, 0, {"nope": {}}))
    with pytest.raises(DriverError, match=r"missing field\(s\) \['pitch_deg'\]"):
        encode_frame(StdbinFrame(3, 0, 0, {"attitude_heading": {"heading_deg": 1.0, "roll_deg": 1.0}}))
    with pytest.raises(DriverError, match="needs version >= 3"):
        encode_frame(StdbinFrame(2, 0, 0, {"vehicle_position": {}}))


def test_nav_decoder_gives_canonical_records(v3):
    navs = StdbinNavDecoder(utc_clock=None).feed(v3)
    assert len(navs) == 17 and all(n.source == "stdbin" and n.date_source == "system_date" for n in navs)
    gps_s = [n.gps_ns / 1e9 for n in navs]
    assert all(0.9 < b - a < 1.1 for a, b in zip(gps_s, gps_s[1:]))  # 1 Hz
    assert -180.0 <= navs[0].lon_deg < 180.0


def test_host_date_when_the_frame_has_no_system_date():
    tod_100us = (10 * 3600) * 10_000
    frame = StdbinFrame(
        3, 1, tod_100us, {"attitude_heading": {"heading_deg": 1.0, "roll_deg": 0.0, "pitch_deg": 0.0}}
    )
    from drivers.hydrins.timeofday import utc_date_ns

    dec = StdbinNavDecoder(utc_clock=lambda: utc_date_ns(2022, 2, 2) + 9 * 3600 * 10**9)
    (nav,) = dec.feed(encode_frame(frame))
    assert nav.date_source == "host" and nav.gps_ns == utc_fields_to_gps_ns(2022, 2, 2, 10 * 3600 * 10**9)


maybe = lambda lo, hi: st.one_of(st.just(math.nan), st.floats(lo, hi))  # noqa: E731


@st.composite
def nav_records(draw):
    tod_ns = draw(st.integers(0, 863_999_999)) * 100_000
    algo, system = status_words(
        navigation=draw(st.booleans()), utc_detected=True, pps_detected=draw(st.booleans())
    )
    return NavRecord(
        "stdbin",
        gps_ns=utc_fields_to_gps_ns(2023, 11, 30, tod_ns),
        lat_deg=draw(st.floats(-89.0, 89.0)),
        lon_deg=draw(st.floats(-180.0, 179.99)),
        height_m=draw(maybe(-50.0, 500.0)),
        height_ref=draw(st.sampled_from(["geoid", "ellipsoid"])),
        roll_rad=draw(maybe(-1.0, 1.0)),
        pitch_rad=draw(maybe(-1.0, 1.0)),
        heading_rad=draw(st.floats(0.0, 6.28)),
        v_north_m_s=draw(maybe(-10.0, 10.0)),
        v_down_m_s=draw(maybe(-2.0, 2.0)),
        heave_m=draw(maybe(-3.0, 3.0)),
        sway_m=draw(maybe(-3.0, 3.0)),
        sigma_roll_rad=draw(maybe(0.0, 0.01)),
        sigma_east_m=draw(maybe(0.0, 50.0)),
        algorithm_status=(algo[0], algo[1], 0, 0),
        system_status=(system[0], system[1], 0),
        user_status=draw(st.integers(0, 2**32 - 1)),
    )


@PROPERTY
@given(nav_records(), st.sampled_from([2, 3, 4, 5]), st.integers(0, 2**32 - 1))
def test_encode_nav_decode_round_trip(nav, version, counter):
    dec = StdbinDecoder()
    (frame,) = dec.feed(encode_nav(nav, version=version, counter=counter))
    assert (frame.protocol_version, frame.counter) == (version, counter)
    back = frame.to_nav()
    assert back.gps_ns == nav.gps_ns and back.date_source == "system_date"
    assert back.height_ref == nav.height_ref
    f32 = 1e-6
    for name in ("roll_rad", "pitch_rad", "v_north_m_s", "v_down_m_s", "heave_m", "sway_m", "sigma_roll_rad"):
        a, b = getattr(back, name), getattr(nav, name)
        assert (math.isnan(a) and math.isnan(b)) or abs(a - b) <= f32 * max(1.0, abs(b)), name
    assert abs(math.remainder(back.heading_rad - nav.heading_rad, 2 * math.pi)) < 1e-6
    assert back.lat_deg == nav.lat_deg and abs(back.lon_deg - nav.lon_deg) < 1e-9
    assert (back.algorithm_status, back.system_status, back.user_status) == (
        nav.algorithm_status,
        nav.system_status,
        nav.user_status,
    )


@pytest.mark.parametrize("last", [b"I", b"A"])
def test_a_frame_ending_in_a_sync_letter_counts_no_negative_skip(last):
    """A frame whose checksum ends in 'I' or 'A' at the end of a chunk is consumed; nothing is
    held back as a possible frame start and the skip count never goes negative."""
    algo, system = status_words(navigation=True, utc_detected=True, pps_detected=True)
    nav = NavRecord(
        "stdbin",
        gps_ns=utc_fields_to_gps_ns(2023, 11, 30, 0),
        lat_deg=45.5,
        lon_deg=-73.5,
        heading_rad=1.0,
        algorithm_status=(algo[0], algo[1], 0, 0),
        system_status=(system[0], system[1], 0),
    )
    frame = next(f for c in range(100_000) if (f := encode_nav(nav, version=3, counter=c))[-1:] == last)
    dec = StdbinDecoder()
    (out,) = dec.feed(frame)
    assert dec.stats.skipped_bytes == 0 and dec._buf == b""
    (again,) = dec.feed(b"\x00" + frame)  # the next chunk: one garbage byte, then a frame
    assert again.counter == out.counter and dec.stats.skipped_bytes == 1
