"""The INS's UTC tags on the GPS time scale: through a leap second at 00:00 UTC (NMEA and
STDBIN, encoder and decoder), with the GPS − UTC the INS announces ($PMLS,GPSUTC), across a GPS
week rollover of its dates, and RMC's two-digit year."""

from __future__ import annotations

from dataclasses import replace

import pytest

from calib.core.frames import utc_fields_to_gps_ns
from drivers.hydrins.nav import NavRecord, status_words
from drivers.hydrins.nmea_decode import NmeaDecoder, NmeaNavAssembler
from drivers.hydrins.nmea_encode import encode_epoch, encode_gps_utc, encode_sentence, encode_zda
from drivers.hydrins.nmea_sentences import GpsUtcOffset
from drivers.hydrins.stdbin_decode import StdbinNavDecoder
from drivers.hydrins.stdbin_encode import encode_nav
from drivers.hydrins.timeofday import utc_date_ns

NS = 1_000_000_000
ALGO, SYSTEM = status_words(navigation=True, utc_detected=True, pps_detected=True)
NAV = NavRecord(
    "nmea", lat_deg=45.5, lon_deg=-73.5, height_m=1.0, algorithm_status=ALGO, system_status=SYSTEM
)


def _stream(gps_ns: list[int], leap: int | None = None, announce: bool = False) -> bytes:
    """An INS's NMEA: a ZDA at each whole second (announced GPS − UTC before it), epochs."""
    out = []
    for g in gps_ns:
        if g % NS == 0:
            out.append(
                (encode_gps_utc(leap if leap is not None else 18) if announce else b"")
                + encode_zda(g, gps_minus_utc_s=leap)
            )
        out.append(encode_epoch(replace(NAV, gps_ns=g), gps_minus_utc_s=leap))
    return b"".join(out)


def _decode_nmea(data: bytes, **kw) -> list[int]:
    asm = NmeaNavAssembler(utc_clock=None)
    navs = asm.feed(data, 0, **kw) + asm.flush()
    return [n.gps_ns for n in navs]


def test_nmea_through_the_leap_second_at_midnight_keeps_gps_time_running():
    """Epochs every 0.1 s from 23:59:58 UTC on 2016-12-31 to 00:00:02 UTC on 2017-01-01 — the
    inserted 23:59:60 between — come back at their GPS instants: no second lost or doubled."""
    start = utc_fields_to_gps_ns(2016, 12, 31, 86_398 * NS)
    gps = [start + k * NS // 10 for k in range(50)]
    data = _stream(gps)
    assert b"ZDA,235960.00,31,12,2016" in data and b"TIME__,235960.000000" in data
    assert _decode_nmea(data) == gps


def test_stdbin_through_the_leap_second_at_midnight_keeps_gps_time_running():
    start = utc_fields_to_gps_ns(2016, 12, 31, 86_398 * NS)
    gps = [start + k * NS // 10 for k in range(50)]
    data = b"".join(encode_nav(replace(NAV, source="stdbin", gps_ns=g), 3, k) for k, g in enumerate(gps))
    dec = StdbinNavDecoder(utc_clock=None)
    assert [n.gps_ns for n in dec.feed(data, 0) + dec.flush()] == gps


def test_an_ins_that_announces_another_gps_minus_utc_is_read_with_its_own_count():
    """An INS that believes GPS − UTC is 19 s (its UTC tags 1 s behind the table's) and says so:
    its tags are undone with 19 s, its GPS time comes back exact; not announced, it would be
    read with the table's 18 s, 1 s off."""
    start = utc_fields_to_gps_ns(2026, 5, 4, 36_000 * NS)
    gps = [start + k * NS // 4 for k in range(12)]
    asm = NmeaNavAssembler(utc_clock=None)
    navs = asm.feed(_stream(gps, leap=19, announce=True), 0) + asm.flush()
    assert [n.gps_ns for n in navs] == gps and asm.gps_minus_utc_s == 19
    assert _decode_nmea(_stream(gps, leap=19)) == [g - NS for g in gps]
    (rec,) = NmeaDecoder().feed(encode_gps_utc(19))
    assert rec == GpsUtcOffset(19, None)
    bad = NmeaDecoder()
    assert bad.feed(encode_sentence("PMLS,GPSUTC,-3")) == [] and bad.stats.rejected == {"bad_field": 1}


def test_a_zda_dated_1024_weeks_back_is_moved_to_the_reference_era():
    """A receiver with the week-rollover bug dates its ZDA 7168 days early: with a reference
    (the host's date) the epochs are dated in the right era and the rollover is counted;
    without one (a recording decoded offline) nothing is moved."""
    start = utc_fields_to_gps_ns(2026, 12, 2, 43_200 * NS)
    gps = [start + k * NS // 4 for k in range(8)]
    # the receiver's UTC: the right time of day (its GPS − UTC is today's 18 s), the date 1024 weeks early
    rolled = _stream([g - 7168 * 86_400 * NS for g in gps], leap=18)
    assert b"ZDA,120000.00,18,04,2007," in rolled
    asm = NmeaNavAssembler(utc_clock=None)
    navs = asm.feed(rolled, 0, utc_hint_ns=utc_date_ns(2026, 12, 2) + 43_000 * NS) + asm.flush()
    assert [n.gps_ns for n in navs] == gps and asm.stats.events["gps_week_rollover"] == 2
    assert _decode_nmea(rolled) == [g - 7168 * 86_400 * NS - 4 * NS for g in gps]  # 2007: 14 s


def test_a_stdbin_system_date_1024_weeks_back_is_moved_to_the_host_era():
    g = utc_fields_to_gps_ns(2026, 12, 2, 43_200 * NS)
    frame = encode_nav(replace(NAV, source="stdbin", gps_ns=g - 7168 * 86_400 * NS), 3, 0, gps_minus_utc_s=18)
    host_utc = utc_date_ns(2026, 12, 2) + 43_100 * NS
    (nav,) = StdbinNavDecoder(utc_clock=lambda: host_utc).feed(frame, 0)
    assert nav.gps_ns == g and nav.date_source == "system_date"
    (offline,) = StdbinNavDecoder(utc_clock=None).feed(frame, 0)
    assert offline.gps_ns == g - 7168 * 86_400 * NS - 4 * NS  # dated 2007 (GPS − UTC 14 s then)


@pytest.mark.parametrize(("yymmdd", "year"), [("040426", 2026), ("170499", 1999), ("060180", 1980)])
def test_rmc_two_digit_years_are_19yy_from_the_gps_epoch_on(yymmdd, year):
    body = f"GPRMC,120000.00,A,4530.0000,N,07330.0000,W,0.0,0.0,{yymmdd},,,A"
    (rmc,) = NmeaDecoder().feed(encode_sentence(body))
    assert rmc.year == year
