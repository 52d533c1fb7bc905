"""The drivers on real device bytes (tests/data/real): every file decodes, values are right."""

from __future__ import annotations

import functools
import math
import operator
import re
from collections import Counter

import numpy as np
import pytest

from drivers.capture.files import FileDecoder, split_stamped_line
from drivers.capture.pcapng import CaptureReader, udp_datagrams
from drivers.hydrins.nmea_decode import NmeaDecoder, NmeaNavAssembler
from drivers.hydrins.nmea_sentences import Gga, Hdt, Vtg, Zda
from drivers.hydrins.stdbin_decode import StdbinDecoder
from drivers.hydrins.stdbin_records import StdbinFrame
from drivers.timing import fit_clock, unwrap_time_of_day_ns
from tests.drivers.helpers import real_dir, real_file


def _stdbin_files():
    return sorted(p.name for p in real_dir("ixblue-stdbin").iterdir() if p.suffix in (".log", ".pcapng"))


@pytest.mark.parametrize("name", _stdbin_files())
def test_every_stdbin_file_decodes_with_zero_checksum_errors(name):
    path = real_file("ixblue-stdbin", name)
    dec = StdbinDecoder()
    if path.suffix == ".pcapng":
        reader = CaptureReader(path)
        grams = list(udp_datagrams(reader, port=8200))
        assert grams and not reader.stats.rejected
        frames = [f for g in grams for f in dec.feed(g.payload, g.timestamp_ns)]
        assert len(frames) == len(grams)  # one frame per datagram
    else:
        frames = dec.feed(path.read_bytes()) + dec.flush()
    assert frames and all(isinstance(f, StdbinFrame) for f in frames)
    assert dec.stats.rejected_total == 0 and dec.stats.skipped_bytes == 0
    assert sum(f.telegram_size for f in frames) == dec.stats.bytes_in
    expected_version = int(name.split("_V")[1][0])  # log_STDBIN_V3_old.log, stdbin_V5_2Hz.pcapng
    assert {f.protocol_version for f in frames} == {expected_version}


def test_stdbin_v2_log_gives_the_readme_values():
    (frame,) = StdbinDecoder().feed(real_file("ixblue-stdbin", "log_STDBIN_V2.log").read_bytes())
    assert frame.heading_deg == pytest.approx(209.982, abs=1e-4)
    assert frame.roll_deg == pytest.approx(0.016, abs=1e-6)
    assert frame.pitch_deg == pytest.approx(0.206, abs=1e-6)
    assert frame.system_date == {"day": 1, "month": 1, "year": 2006}
    assert frame.validity_time_100us == 9215311
    assert (
        frame.telegram_size == 286 and frame.protocol_version == 2 and frame.extended_navigation_mask is None
    )


def test_stdbin_v3_log_external_blocks_and_status_bits():
    frames = StdbinDecoder().feed(real_file("ixblue-stdbin", "log_STDBIN_V3.log").read_bytes())
    assert len(frames) == 17
    assert [f.counter for f in frames] == list(range(frames[0].counter, frames[0].counter + 17))
    f = frames[0]
    # values published with the iXblue decoder's test of this file
    assert f.blocks["gnss1"]["latitude_deg"] == pytest.approx(48.89909998575846, abs=1e-12)
    assert f.blocks["gnss1"]["gnss_quality"] == 4 and f.blocks["gnss2"]["gnss_id"] == 1
    assert f.blocks["utc"]["validity_time_100us"] == 566980000
    assert f.blocks["usbl1"]["beacon_id"].rstrip(b"\0") == b"ABC"
    assert f.blocks["depth"]["depth_m"] == -102.0
    assert f.blocks["dvl_ground_speed1"]["speed_of_sound_m_s"] == 1400.0
    assert f.blocks["lbl1"]["range_m"] == 238.0
    assert f.system_date == {"day": 14, "month": 3, "year": 2019}
    assert f.blocks["ins_system_status"]["status2"] == 0x8EFF
    nav = f.to_nav()
    assert nav.utc_detected is True and nav.pps_detected is True  # system status 2 bits 9, 11
    assert nav.navigation is False and nav.alignment is True  # algorithm status 1 = 0x81013112
    assert nav.date_source == "system_date"
    assert nav.gps_ns is not None
    # canonical: iXblue pitch −0.521° (bow down) → +0.521° bow up
    assert math.degrees(nav.pitch_rad) == pytest.approx(0.521, abs=1e-5)
    assert math.degrees(nav.roll_rad) == pytest.approx(0.809, abs=1e-5)


@pytest.mark.parametrize(
    "name",
    [
        "log_STDBIN_V2.log",
        "log_STDBIN_V3.log",
        "log_STDBIN_V3_old.log",
        "log_STDBIN_V4.log",
        "log_STDBIN_V5.log",
    ],
)
def test_stdbin_real_frames_reencode_byte_exact(name):
    from drivers.hydrins.stdbin_encode import encode_frame

    data = real_file("ixblue-stdbin", name).read_bytes()
    frames = StdbinDecoder().feed(data)
    assert b"".join(encode_frame(f) for f in frames) == data


def test_pcapng_clock_drift_and_jitter_of_the_ins():
    """README: the INS clock drifts about −35 ppm against the capture host, ~0.2 ms jitter."""
    fits = []
    for name in ("stdbin_V2_2Hz.pcapng", "stdbin_V3_2Hz.pcapng", "stdbin_V5_2Hz.pcapng"):
        dec = StdbinDecoder()
        host, device = [], []
        for g in udp_datagrams(CaptureReader(real_file("ixblue-stdbin", name)), port=8200):
            for f in dec.feed(g.payload, g.timestamp_ns):
                host.append(f.host_ns)
                device.append(f.validity_time_100us * 100_000)
        fit = fit_clock(host, unwrap_time_of_day_ns(device))
        assert fit.n_outliers == 0 and fit.span_s > 12
        assert -45.0 < fit.drift_ppm < -25.0, name
        assert 0.1e-3 < fit.jitter_p2p_s < 0.4e-3, name
        assert fit.jitter_rms_s < 0.15e-3, name
        fits.append(fit.drift_ppm)
    assert np.mean(fits) == pytest.approx(-35.0, abs=3.0)


def test_nbp1406_zda_latency_against_logged_receive_time():
    """README: $INZDA arrives about 115 ms after its own time tag with σ ≈ 0.35 ms."""
    fd = FileDecoder(real_file("openrvdas-nbp1406", "NBP1406_s330-2014-08-01"), "nmea")
    zda = [r for r in fd if isinstance(r, Zda)]
    assert len(zda) == 625
    fit = fit_clock([z.host_ns for z in zda], unwrap_time_of_day_ns([z.time_of_day_ns for z in zda]))
    assert (fit.offset_s % 86400) == pytest.approx(0.115, abs=0.001)
    assert fit.jitter_rms_s == pytest.approx(0.35e-3, abs=0.05e-3)
    assert abs(fit.drift_ppm) < 2.0


NBP_COUNTS = {
    "NBP1406_gyr1-2014-08-01": {"HEHDT": 5000},
    "NBP1406_s330-2014-08-01": {
        "PSXN": 1875,
        "INZDA": 625,
        "INGGA": 625,
        "INVTG": 625,
        "INRMC": 625,
        "INHDT": 625,
    },
    "NBP1406_seap-2014-08-01": {"PSXN": 2142, "GPZDA": 715, "GPGGA": 715, "GPVTG": 714, "GPHDT": 714},
}


@pytest.mark.parametrize("name", sorted(NBP_COUNTS))
def test_nbp1406_logs_parse_every_sentence(name):
    path = real_file("openrvdas-nbp1406", name)
    dec = NmeaDecoder()
    lines = path.read_bytes().splitlines()
    for line in lines:
        stamp, payload = split_stamped_line(line)
        assert stamp is not None
        dec.feed(payload + b"\r\n", stamp)
    assert dec.stats.rejected_total == 0 and dec.stats.skipped_bytes == 0
    assert dict(dec.counts) == NBP_COUNTS[name]
    assert dec.stats.records == len(lines)


GPSD_COUNTS = {
    "hemi.log": {"GPHDT": 215, "GPGGA": 215, "GPVTG": 215, "GPZDA": 108},
    "rst39.log": {"PASHR": 100, "GPGGA": 40, "GPRMC": 4, "GPHDT": 4, "GPZDA": 4},
    "saab-r4.log": {
        "PFEC": 12,
        "AIVDO": 12,
        "GPZDA": 12,
        "GPGLL": 12,
        "GPGGA": 12,
        "GPVTG": 12,
        "GPRMC": 12,
        "GPDTM": 12,
        "HEHDT": 12,
        "HEROT": 12,
        "AIVDM": 2,
    },
    "skytraq-PX1172RH_DS.log": {
        "PSTI": 54,
        "GNGSA": 36,
        "GAGSV": 15,
        "GPGSV": 12,
        "GPGGA": 9,
        "GNGLL": 9,
        "GNRMC": 9,
        "GNVTG": 9,
        "GNZDA": 9,
        "GNTHS": 9,
        "GNHDT": 9,
        "GBGSV": 9,
        "GLGSV": 6,
    },
}


@pytest.mark.parametrize("name", sorted(p.name for p in real_dir("gpsd").glob("*.log")))
def test_gpsd_captures_parse_with_no_valid_sentence_rejected(name):
    data = real_file("gpsd", name).read_bytes()
    dec = NmeaDecoder()
    recs = dec.feed(data) + dec.flush()
    sentence_lines = [ln for ln in data.splitlines() if ln[:1] in (b"$", b"!")]
    assert dec.stats.rejected_total == 0
    assert len(recs) == len(sentence_lines) == sum(dec.counts.values())
    # only comment and JSON lines are skipped
    other = sum(len(ln.strip()) for ln in data.splitlines() if ln[:1] not in (b"$", b"!"))
    assert dec.stats.skipped_bytes == other
    if name in GPSD_COUNTS:
        assert {k: dec.counts[k] for k in GPSD_COUNTS[name]} == GPSD_COUNTS[name]
        assert sum(dec.counts.values()) == sum(GPSD_COUNTS[name].values()) or name == "saab-r4.log"


def _checksummed_sentence_ids(data: bytes) -> Counter:
    """Sentence ids of the lines that carry a valid NMEA checksum, counted with a regex (independent
    of the decoder); JSON, comment and unchecksummed lines do not count."""
    ids: Counter = Counter()
    for m in re.finditer(rb"^[$!]([A-Z0-9]+)(,[^*\r\n]*)?\*([0-9A-Fa-f]{2})\r?$", data, re.M):
        body = m.group(0)[1 : m.group(0).rindex(b"*")]
        if functools.reduce(operator.xor, body, 0) == int(m.group(3), 16):
            ids[m.group(1).decode()] += 1
    return ids


@pytest.mark.parametrize("name", sorted(GPSD_COUNTS))
def test_gpsd_counts_per_sentence_type_match_a_regex_count_of_the_file(name):
    data = real_file("gpsd", name).read_bytes()
    expected = _checksummed_sentence_ids(data)
    dec = NmeaDecoder()
    dec.feed(data)
    dec.flush()
    assert dict(dec.counts) == dict(expected)
    if name != "saab-r4.log":  # saab-r4's table lists the types of interest only
        assert dict(expected) == GPSD_COUNTS[name]
    else:
        assert {k: expected[k] for k in GPSD_COUNTS[name]} == GPSD_COUNTS[name]


def test_skytraq_dual_antenna_heading_sentences_are_counted():
    """The skytraq capture's reason to be here: $GNHDT and $GNTHS, behind leading JSON lines."""
    dec = NmeaDecoder()
    dec.feed(real_file("gpsd", "skytraq-PX1172RH_DS.log").read_bytes())
    dec.flush()
    assert dec.counts["GNHDT"] == dec.counts["GNTHS"] == dec.counts["GNZDA"] == 9
    assert dec.stats.rejected_total == 0


def test_gpsd_empty_fields_are_missing_not_zero():
    """hemi.log mixes sentences with every field empty and filled ones: empty → NaN/None."""
    dec = NmeaDecoder()
    n_empty = n_full = 0
    for line in real_file("gpsd", "hemi.log").read_bytes().splitlines():
        (rec,) = dec.feed(line + b"\r\n") or [None]
        fields = line.split(b"*")[0].split(b",")
        if isinstance(rec, Hdt):
            assert math.isnan(rec.heading_deg) == (fields[1] == b"")
        elif isinstance(rec, Gga):
            empty = fields[2] == b""
            n_empty += empty
            n_full += not empty
            assert math.isnan(rec.lat_deg) == empty and math.isnan(rec.altitude_msl_m) == (fields[9] == b"")
            assert (rec.time_of_day_ns is None) == (fields[1] == b"")
            assert (rec.n_satellites is None) == (fields[7] == b"")
            if not empty:
                assert rec.lat_deg == pytest.approx(42 + float(fields[2][2:]) / 60, abs=1e-12)
                assert rec.lon_deg < 0 and rec.geoid_separation_m == float(fields[11])
    assert n_empty > 10 and n_full > 10
    zda = [r for r in NmeaDecoder().feed(real_file("gpsd", "hemi.log").read_bytes()) if isinstance(r, Zda)]
    assert (zda[0].year, zda[0].month, zda[0].day) == (2018, 9, 7)
    assert zda[0].time_of_day_ns == (19 * 3600 + 39 * 60 + 13) * 10**9


def test_seapath_epochs_assemble_with_zda_dates():
    asm = NmeaNavAssembler(utc_clock=None)
    navs = asm.feed(real_file("openrvdas-nbp1406", "NBP1406_seap-2014-08-01").read_bytes()) + asm.flush()
    assert len(navs) >= 700
    dated = [n for n in navs if n.gps_ns is not None]
    assert len(dated) >= 700 and {n.date_source for n in dated} == {"zda"}
    first = dated[0]
    # 2014-08-01 00:00:00.70 UTC = GPS 1090886416.70 s (16 leap seconds)
    assert first.gps_ns == 1090886416_700_000_000
    assert first.lat_deg == pytest.approx(-(22 + 0.112071 / 60), abs=1e-9)
    assert math.degrees(first.heading_rad) == pytest.approx(218.83, abs=1e-9)
    assert first.height_ref == "geoid" and math.isnan(first.roll_rad)


def test_nbp1406_empty_fields_are_missing_not_zero():
    """Which fields the NBP1406 Seapath logs leave empty, every line: ZDA local zone (both logs;
    the Zda record has no zone field, and the sentence still decodes whole), GGA DGPS age (both)
    and geoid separation (seap; s330 fills it, 4.67 m), VTG magnetic course (seap). Empty → NaN."""
    empty = Counter()
    for name in ("NBP1406_seap-2014-08-01", "NBP1406_s330-2014-08-01"):
        dec = NmeaDecoder()
        for line in real_file("openrvdas-nbp1406", name).read_bytes().splitlines():
            stamp, payload = split_stamped_line(line)
            recs = dec.feed(payload + b"\r\n", stamp)
            f = payload.split(b"*")[0].split(b",")
            kind = f[0][3:]  # b"$GPZDA" → b"ZDA"
            if kind not in (b"ZDA", b"GGA", b"VTG"):
                continue
            (rec,) = recs
            if kind == b"ZDA":
                assert isinstance(rec, Zda) and f[5:] == [b"", b""]
                assert None not in (rec.time_of_day_ns, rec.day, rec.month, rec.year) and rec.year == 2014
                empty[name, "zda_zone"] += 1
                continue
            if kind == b"GGA":
                assert isinstance(rec, Gga)
                checks = {
                    "gga_geoid_separation": (rec.geoid_separation_m, f[11]),
                    "gga_dgps_age": (rec.dgps_age_s, f[13]),
                }
            else:
                assert isinstance(rec, Vtg) and rec.course_true_deg == float(f[1]) and f[4] == b"M"
                checks = {"vtg_course_magnetic": (rec.course_magnetic_deg, f[3])}
            for field, (value, raw) in checks.items():
                if raw == b"":
                    assert math.isnan(value), (name, field, line)
                    empty[name, field] += 1
                else:
                    assert value == float(raw), (name, field, line)
                    empty[name, field] += 0
        assert dec.stats.rejected_total == 0
    assert dict(empty) == {
        ("NBP1406_seap-2014-08-01", "zda_zone"): 715,
        ("NBP1406_seap-2014-08-01", "gga_geoid_separation"): 715,
        ("NBP1406_seap-2014-08-01", "gga_dgps_age"): 715,
        ("NBP1406_seap-2014-08-01", "vtg_course_magnetic"): 714,
        ("NBP1406_s330-2014-08-01", "zda_zone"): 625,
        ("NBP1406_s330-2014-08-01", "gga_geoid_separation"): 0,
        ("NBP1406_s330-2014-08-01", "gga_dgps_age"): 625,
        ("NBP1406_s330-2014-08-01", "vtg_course_magnetic"): 0,
    }
