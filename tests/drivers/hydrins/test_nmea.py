"""Hydrins NMEA: sentence decoding, the canonical epoch record, the date rule, the encoders."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from calib.core.frames import utc_fields_to_gps_ns
from drivers.hydrins.nav import NavRecord, status_words
from drivers.hydrins.nmea_decode import NmeaDecoder, NmeaNavAssembler
from drivers.hydrins.nmea_encode import encode_epoch, encode_sentence, encode_zda
from drivers.hydrins.nmea_sentences import PixseAtitud, PixseTime, Sentence, checksum
from drivers.hydrins.timeofday import utc_date_ns
from tests.drivers.helpers import PROPERTY

# A PHINS standard block (as documented in iXblue drivers), checksums recomputed by encode_sentence.
BLOCK = b"".join(
    encode_sentence(s)
    for s in [
        "HEHDT,116.581,T",
        "PIXSE,ATITUD,-1.641,-0.490",
        "PIXSE,POSITI,53.10245714,8.83994382,-0.115",
        "PIXSE,SPEED_,-0.802,-1.243,0.000",
        "PIXSE,UTMWGS,U,32,489284.019,5883680.109,-0.115",
        "PIXSE,HEAVE_,0.100,-0.200,0.014",
        "PIXSE,TIME__,003356.016693",
        "PIXSE,STDHRP,1.997,0.082,0.101",
        "PIXSE,STDPOS,20563.20,18004.65,50.00",
        "PIXSE,STDSPD,19.747,13.032,10.002",
        "PIXSE,ALGSTS,00000045,00004000",
        "PIXSE,STATUS,00000000,00000A00",
        "PIXSE,HT_STS,FFFD5551",
    ]
)


def test_checksum_is_xor_between_dollar_and_star():
    assert encode_sentence("HEHDT,116.581,T") == b"$HEHDT,116.581,T*25\r\n"  # published example
    assert checksum(b"PIXSE,ATITUD,-1.641,-0.490") == 0x6D


def test_typed_pixse_sentences_keep_native_values():
    recs = NmeaDecoder().feed(BLOCK, host_ns=42)
    assert len(recs) == 13 and all(r.host_ns == 42 for r in recs)
    att = recs[1]
    assert isinstance(att, PixseAtitud) and (att.roll_deg, att.pitch_deg) == (-1.641, -0.490)
    assert isinstance(recs[4], Sentence) and recs[4].kind == "PIXSE,UTMWGS"
    assert isinstance(recs[6], PixseTime) and recs[6].time_of_day_ns == (33 * 60 + 56) * 10**9 + 16_693_000
    assert (recs[10].status1, recs[10].status2) == (0x45, 0x4000)
    assert recs[12].status == 0xFFFD5551


def test_block_assembles_into_one_canonical_record():
    asm = NmeaNavAssembler(utc_clock=lambda: utc_date_ns(2024, 5, 17) + 3_600 * 10**9)
    (nav,) = asm.feed(BLOCK, host_ns=1000)
    assert nav.source == "nmea" and nav.host_ns == 1000
    assert math.degrees(nav.heading_rad) == pytest.approx(116.581)
    assert math.degrees(nav.roll_rad) == pytest.approx(-1.641)
    assert math.degrees(nav.pitch_rad) == pytest.approx(+0.490)  # iXblue bow-down → canonical bow-up
    assert (nav.lat_deg, nav.lon_deg, nav.height_m) == (53.10245714, 8.83994382, -0.115)
    assert (nav.v_north_m_s, nav.v_east_m_s, nav.v_down_m_s) == (-1.243, -0.802, -0.0)
    assert (nav.surge_m, nav.sway_m, nav.heave_m) == (0.100, 0.200, -0.014)  # FRD: sway + stbd, heave + down
    assert math.degrees(nav.sigma_heading_rad) == pytest.approx(1.997)
    assert (nav.sigma_north_m, nav.sigma_east_m, nav.sigma_down_m) == (20563.20, 18004.65, 50.00)
    assert (nav.sigma_v_north_m_s, nav.sigma_v_east_m_s, nav.sigma_v_down_m_s) == (19.747, 13.032, 10.002)
    assert nav.navigation and not nav.alignment and nav.fine_alignment and not nav.dead_reckoning
    assert nav.utc_detected and nav.pps_detected  # status word 2 = 0xA00: bits 9 and 11
    assert nav.date_source == "host"
    assert nav.gps_ns == utc_fields_to_gps_ns(2024, 5, 17, nav.time_of_day_ns)


def test_missing_sentences_leave_nan_and_none_never_zero():
    asm = NmeaNavAssembler(utc_clock=None)
    (nav,) = asm.feed(
        encode_sentence("HEHDT,,T") + encode_sentence("PIXSE,ATITUD,,") + encode_sentence("PIXSE,HT_STS,")
    )
    assert math.isnan(nav.heading_rad) and math.isnan(nav.roll_rad) and math.isnan(nav.lat_deg)
    assert (
        nav.user_status is None
        and nav.navigation is None
        and nav.gps_ns is None
        and nav.time_of_day_ns is None
    )


def test_time_is_not_resolved_when_the_ins_is_not_on_utc():
    body = BLOCK.replace(
        encode_sentence("PIXSE,STATUS,00000000,00000A00"), encode_sentence("PIXSE,STATUS,00000000,00000000")
    )
    (nav,) = NmeaNavAssembler(utc_clock=lambda: utc_date_ns(2024, 5, 17)).feed(body)
    assert nav.utc_detected is False and nav.time_of_day_ns is not None and nav.gps_ns is None


@pytest.mark.parametrize(
    ("zda_time", "time_tag", "expected_day"),
    [
        ("235959.50", "235959.900000", 31),
        ("000000.20", "235959.900000", 31),
        ("235959.90", "000000.100000", 1),
    ],
)
def test_date_from_zda_across_midnight(zda_time, time_tag, expected_day):
    day = 31 if zda_time.startswith("23") else 1
    month = 12 if day == 31 else 1
    year = 2023 if day == 31 else 2024
    zda = encode_sentence(f"GPZDA,{zda_time},{day:02d},{month:02d},{year},00,00")
    asm = NmeaNavAssembler(utc_clock=None)
    (nav,) = asm.feed(
        zda + encode_sentence(f"PIXSE,TIME__,{time_tag}") + encode_sentence("PIXSE,HT_STS,00000000")
    )
    ey, em = (2023, 12) if expected_day == 31 else (2024, 1)
    assert nav.date_source == "zda"
    assert nav.gps_ns == utc_fields_to_gps_ns(ey, em, expected_day, nav.time_of_day_ns)


def test_host_date_picks_the_nearest_day():
    hint = utc_date_ns(2024, 3, 1) + 5 * 10**9  # host says 00:00:05 on 1 March
    asm = NmeaNavAssembler(utc_clock=lambda: hint)
    (nav,) = asm.feed(
        encode_sentence("PIXSE,TIME__,235958.000000") + encode_sentence("PIXSE,HT_STS,00000000")
    )
    assert nav.gps_ns == utc_fields_to_gps_ns(2024, 2, 29, nav.time_of_day_ns)  # the tag is from yesterday
    assert nav.date_source == "host"


def test_epoch_closes_on_repeat_when_block_has_no_ht_sts():
    asm = NmeaNavAssembler(utc_clock=None)
    out = asm.feed(encode_sentence("HEHDT,10.0,T") + encode_sentence("PIXSE,ATITUD,1.0,2.0"))
    assert out == []
    (first,) = asm.feed(encode_sentence("HEHDT,11.0,T"))
    assert math.degrees(first.heading_rad) == pytest.approx(10.0)
    (second,) = asm.flush()
    assert math.degrees(second.heading_rad) == pytest.approx(11.0) and math.isnan(second.roll_rad)


def test_rejections_are_counted_by_reason_and_garbage_is_skipped():
    good = encode_sentence("HEHDT,1.5,T")
    bad = bytearray(good)
    bad[8] ^= 0x01  # corrupt a digit: checksum no longer matches
    stream = (
        b"\x00\xffnoise"
        + bytes(bad)
        + b"$HEHDT,1.5,T\r\n"
        + b"$HEHDT,x,T*"
        + b"%02X\r\n" % checksum(b"HEHDT,x,T")
        + good
    )
    dec = NmeaDecoder()
    recs = dec.feed(stream)
    assert len(recs) == 1 and recs[0].heading_deg == 1.5
    assert dict(dec.stats.rejected) == {"bad_checksum": 1, "missing_checksum": 1, "bad_field": 1}
    assert dec.stats.skipped_bytes == len(b"\x00\xffnoise")


def test_sentence_split_across_reads_and_overlong_garbage():
    dec = NmeaDecoder()
    s = encode_sentence("PIXSE,ATITUD,0.5,-0.25")
    assert [dec.feed(s[i : i + 1], host_ns=100 + i) for i in range(len(s) - 2)] == [[]] * (len(s) - 2)
    (rec,) = dec.feed(s[-2:-1], host_ns=999)  # CR ends the sentence, the LF that follows is nothing
    assert rec.pitch_deg == -0.25 and dec.feed(s[-1:]) == []
    assert rec.host_ns == 100  # stamped with the chunk of its first byte
    assert dec.feed(b"x" * 5000) == [] and dec.stats.skipped_bytes == 5000
    assert len(dec.feed(s)) == 1


def test_line_noise_before_a_sentence_does_not_date_it():
    """Noise read well before a sentence (no line end between them) is skipped with it; the
    sentence keeps the stamp of the chunk that brought its ``$``."""
    s = encode_sentence("PIXSE,ATITUD,0.5,-0.25")
    dec = NmeaDecoder()
    assert dec.feed(b"\x01\x7fnoise", host_ns=1_000) == []
    (rec,) = dec.feed(s, host_ns=9_000)
    assert rec.host_ns == 9_000
    assert dec.feed(b"\x02noise" + s[:5], host_ns=20_000) == []  # the start came with the noise
    (rec,) = dec.feed(s[5:], host_ns=29_000)
    assert rec.host_ns == 20_000
    assert dec.feed(b"noise", host_ns=30_000) == [] and dec.feed(b"more", host_ns=31_000) == []
    assert dec.feed(s[:3], host_ns=35_000) == []
    (rec,) = dec.feed(s[3:], host_ns=39_000)
    assert rec.host_ns == 35_000


def test_flush_decodes_a_last_line_without_terminator():
    dec = NmeaDecoder()
    assert dec.feed(encode_sentence("HEHDT,2.0,T")[:-2]) == []
    (rec,) = dec.flush()
    assert rec.heading_deg == 2.0


def test_encode_zda_round_trip():
    gps_ns = utc_fields_to_gps_ns(2025, 7, 4, (12 * 3600 + 34 * 60 + 56) * 10**9 + 780_000_000)
    (z,) = NmeaDecoder().feed(encode_zda(gps_ns))
    assert (z.year, z.month, z.day, z.time_of_day_ns) == (
        2025,
        7,
        4,
        (12 * 3600 + 34 * 60 + 56) * 10**9 + 780_000_000,
    )


finite = st.floats(allow_nan=False, allow_infinity=False)


@st.composite
def nav_records(draw):
    tod_ns = draw(st.integers(0, 86_399_999_999)) // 1000 * 1000  # TIME__ carries µs
    algo, system = status_words(
        navigation=draw(st.booleans()),
        fine_alignment=draw(st.booleans()),
        utc_detected=True,
        pps_detected=draw(st.booleans()),
    )
    maybe = lambda lo, hi: st.one_of(st.just(math.nan), st.floats(lo, hi))  # noqa: E731
    return NavRecord(
        "nmea",
        gps_ns=utc_fields_to_gps_ns(2024, 6, 1, tod_ns),
        lat_deg=draw(maybe(-89.9, 89.9)),
        lon_deg=draw(maybe(-180.0, 179.999)),
        height_m=draw(maybe(-100.0, 1000.0)),
        roll_rad=draw(maybe(-1.0, 1.0)),
        pitch_rad=draw(maybe(-1.0, 1.0)),
        heading_rad=draw(maybe(0.0, 6.28)),
        v_north_m_s=draw(maybe(-20.0, 20.0)),
        v_east_m_s=draw(maybe(-20.0, 20.0)),
        v_down_m_s=draw(maybe(-5.0, 5.0)),
        surge_m=draw(maybe(-5.0, 5.0)),
        sway_m=draw(maybe(-5.0, 5.0)),
        heave_m=draw(maybe(-5.0, 5.0)),
        sigma_heading_rad=draw(maybe(0.0, 0.1)),
        sigma_north_m=draw(maybe(0.0, 100.0)),
        sigma_v_down_m_s=draw(maybe(0.0, 1.0)),
        algorithm_status=algo,
        system_status=system,
        user_status=draw(st.integers(0, 2**32 - 1)),
    )


def _close(a: float, b: float, tol: float) -> bool:
    """Equal within ``tol`` (half the sentence's last digit: a value exactly half-way, such as
    0.125 written with two decimals, is off by ``tol`` plus the float's own rounding)."""
    return (math.isnan(a) and math.isnan(b)) or abs(a - b) <= tol * (1 + 1e-9)


@PROPERTY
@given(nav_records())
def test_encode_epoch_decode_round_trip(nav):
    asm = NmeaNavAssembler(utc_clock=lambda: utc_date_ns(2024, 6, 1) + 43_200 * 10**9)
    (back,) = asm.feed(encode_epoch(nav))
    deg = math.radians(0.0005)
    assert back.gps_ns == nav.gps_ns and back.date_source == "host"
    assert _close(back.lat_deg, nav.lat_deg, 5e-9) and _close(back.lon_deg, nav.lon_deg, 5e-9)
    assert _close(back.height_m, nav.height_m, 5e-4)
    for name in ("roll_rad", "pitch_rad", "sigma_heading_rad"):
        assert _close(getattr(back, name), getattr(nav, name), deg), name
    h_back, h = back.heading_rad, nav.heading_rad
    assert (math.isnan(h) and math.isnan(h_back)) or abs(math.remainder(h_back - h, 2 * math.pi)) <= deg
    for name in (
        "v_north_m_s",
        "v_east_m_s",
        "v_down_m_s",
        "surge_m",
        "sway_m",
        "heave_m",
        "sigma_v_down_m_s",
    ):
        assert _close(getattr(back, name), getattr(nav, name), 5e-4), name
    assert _close(back.sigma_north_m, nav.sigma_north_m, 5e-3)
    assert (back.algorithm_status, back.system_status, back.user_status) == (
        nav.algorithm_status,
        nav.system_status,
        nav.user_status,
    )
    assert (back.navigation, back.fine_alignment, back.pps_detected) == (
        nav.navigation,
        nav.fine_alignment,
        nav.pps_detected,
    )


def _epoch_at(k: int) -> NavRecord:
    """Epoch k of a 200 Hz stream on UTC, roll a function of k."""
    n = NavRecord("nmea")
    n.gps_ns = 1_400_000_000 * 10**9 + k * 5_000_000
    n.lat_deg, n.lon_deg, n.height_m = 45.5, -73.55, 10.0
    n.roll_rad, n.pitch_rad, n.heading_rad = math.radians(0.01 * k), 0.01, 1.0
    n.system_status = (0, 1 << 9)
    return n


def test_an_epoch_that_lost_its_time_is_not_dated_by_a_zda_of_another_instant():
    """A line dropping bytes (a reader stalled behind a full pty): epoch 0 loses its tail with
    TIME__, then epochs 1–9 are lost, and the ZDA of the next second follows."""
    zda_ns = _epoch_at(200).gps_ns
    stream = (
        encode_zda(_epoch_at(-200).gps_ns)
        + encode_epoch(_epoch_at(-1))
        + encode_epoch(_epoch_at(0))[:120]
        + encode_zda(zda_ns)
        + encode_epoch(_epoch_at(200))
    )
    asm = NmeaNavAssembler(utc_clock=None)
    out = asm.feed(stream) + asm.flush()
    assert [n.gps_ns for n in out] == [_epoch_at(-1).gps_ns, zda_ns]
    assert asm.stats.rejected == {"epoch_without_time": 1}
    # a stream without TIME__ is still dated by its ZDA (the time of last resort)
    asm = NmeaNavAssembler(utc_clock=None)
    (nav,) = asm.feed(encode_zda(zda_ns) + encode_sentence("HEHDT,57.3,T")) + asm.flush()
    assert nav.gps_ns == zda_ns and asm.stats.rejected == {}


def test_an_epoch_is_stamped_with_its_own_sentences_not_the_zda_read_before_it():
    """The ZDA follows the PPS edge on its own schedule and often arrives a little before the
    next block (read in a chunk of its own): the epoch's receive stamp is its block's."""
    asm = NmeaNavAssembler(utc_clock=None)
    out = asm.feed(encode_epoch(_epoch_at(-1)), host_ns=1_000)
    out += asm.feed(encode_zda(_epoch_at(0).gps_ns), host_ns=2_000)
    out += asm.feed(encode_epoch(_epoch_at(1)), host_ns=3_000)
    assert [(n.host_ns, n.gps_ns) for n in out] == [
        (1_000, None),
        (3_000, _epoch_at(1).gps_ns),
    ]  # (no date yet)
    # a ZDA alone (a stream of time messages only) is still stamped by its own arrival
    (nav,) = asm.feed(encode_zda(_epoch_at(200).gps_ns), host_ns=4_000) + asm.flush()
    assert nav.host_ns == 4_000


@PROPERTY
@given(st.lists(st.tuples(st.floats(0, 1), st.integers(0, 12)), min_size=1, max_size=30))
def test_a_stream_losing_bytes_never_mixes_epochs(cuts):
    """Whatever byte ranges are lost (a partial write, then whole writes dropped), every record
    is one epoch's: its attitude is the attitude of the epoch at its time."""
    writes, k = [], 0
    while k < 400:
        if k % 200 == 0:
            writes.append(encode_zda(_epoch_at(k).gps_ns))
        writes.append(encode_epoch(_epoch_at(k)))
        k += 1
    stream, i = b"", 0
    for j, w in enumerate(writes):
        cut = cuts[j % len(cuts)]
        if j % 7 == 3 and i <= j:  # a partial write; the next `skip` writes are lost
            stream += w[: int(cut[0] * len(w))]
            i = j + 1 + cut[1]
        elif j >= i:
            stream += w
    asm = NmeaNavAssembler(utc_clock=None)
    out = [n for n in asm.feed(stream) + asm.flush() if n.gps_ns is not None]
    assert out
    for n in out:
        k, rest = divmod(n.gps_ns - _epoch_at(0).gps_ns, 5_000_000)
        assert rest == 0
        assert math.isnan(n.roll_rad) or abs(math.degrees(n.roll_rad) - 0.01 * k) < 1e-6, k
