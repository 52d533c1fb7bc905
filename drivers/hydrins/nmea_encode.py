"""Hydrins NMEA encoders for the emulators: a canonical NavRecord → the PHINS standard block.

:func:`encode_sentence` (a body → a checksummed sentence), :func:`encode_epoch` (a canonical
NavRecord → the PHINS standard block, in the order HEHDT, ATITUD, POSITI, SPEED_, HEAVE_,
TIME__, STDHRP, STDPOS, STDSPD, ALGSTS, STATUS, HT_STS), :func:`encode_zda` and
:func:`encode_gps_utc` (``$PMLS,GPSUTC``). ``gps_minus_utc_s`` makes UTC tags with a count of
the caller's (a device that believes another one) instead of the leap-second table's.
"""

from __future__ import annotations

import math

from calib.core.frames import attitude_to_ixblue, gps_ns_to_utc_fields
from drivers.hydrins.nav import NavRecord
from drivers.hydrins.nmea_sentences import NAN, checksum
from drivers.hydrins.timeofday import format_hhmmss, utc_time_of_day_ns


def encode_sentence(body: str, start: str = "$") -> bytes:
    """``'PIXSE,ATITUD,1.000,2.000'`` → ``b'$PIXSE,ATITUD,1.000,2.000*hh\\r\\n'``."""
    raw = body.encode("ascii")
    return b"%s%s*%02X\r\n" % (start.encode("ascii"), raw, checksum(raw))


def _fmt(value: float, spec: str) -> str:
    return "" if value is None or value != value else format(value, spec)


def _deg(value_rad: float, spec: str = ".3f") -> str:
    return _fmt(math.degrees(value_rad), spec) if value_rad == value_rad else ""


def _neg(value: float) -> float:
    return -value if value == value else value


def _word(value: int | None) -> str:
    return "" if value is None else f"{value & 0xFFFFFFFF:08X}"


def encode_epoch(nav: NavRecord, talker: str = "HE", gps_minus_utc_s: int | None = None) -> bytes:
    """A canonical NavRecord → the PHINS standard block (iXblue signs and units on the wire).

    TIME__ carries the UTC time of day of ``nav.gps_ns`` when it is set, else
    ``nav.time_of_day_ns``; missing values become empty fields.
    """
    roll, pitch, _ = attitude_to_ixblue(nav.roll_rad, nav.pitch_rad, 0.0)
    lon = nav.lon_deg % 360.0 if nav.lon_deg == nav.lon_deg else NAN
    tod: int | None
    if nav.gps_ns is not None:
        tod = utc_time_of_day_ns(nav.gps_ns, gps_minus_utc_s)
    else:
        tod = nav.time_of_day_ns
    words_a = nav.algorithm_status or (None, None)
    words_s = nav.system_status or (None, None)
    bodies = [
        f"{talker}HDT,{_deg(nav.heading_rad)},T",
        f"PIXSE,ATITUD,{_deg(float(roll))},{_deg(float(pitch))}",
        f"PIXSE,POSITI,{_fmt(nav.lat_deg, '.8f')},{_fmt(lon, '.8f')},{_fmt(nav.height_m, '.3f')}",
        f"PIXSE,SPEED_,{_fmt(nav.v_east_m_s, '.3f')},{_fmt(nav.v_north_m_s, '.3f')},{_fmt(_neg(nav.v_down_m_s), '.3f')}",
        f"PIXSE,HEAVE_,{_fmt(nav.surge_m, '.3f')},{_fmt(_neg(nav.sway_m), '.3f')},{_fmt(_neg(nav.heave_m), '.3f')}",
        f"PIXSE,TIME__,{format_hhmmss(tod, 6) if tod is not None else ''}",
        f"PIXSE,STDHRP,{_deg(nav.sigma_heading_rad)},{_deg(nav.sigma_roll_rad)},{_deg(nav.sigma_pitch_rad)}",
        f"PIXSE,STDPOS,{_fmt(nav.sigma_north_m, '.2f')},{_fmt(nav.sigma_east_m, '.2f')},{_fmt(nav.sigma_down_m, '.2f')}",
        f"PIXSE,STDSPD,{_fmt(nav.sigma_v_north_m_s, '.3f')},{_fmt(nav.sigma_v_east_m_s, '.3f')},{_fmt(nav.sigma_v_down_m_s, '.3f')}",
        f"PIXSE,ALGSTS,{_word(words_a[0])},{_word(words_a[1])}",
        f"PIXSE,STATUS,{_word(words_s[0])},{_word(words_s[1])}",
        f"PIXSE,HT_STS,{_word(nav.user_status)}",
    ]
    return b"".join(encode_sentence(b) for b in bodies)


def encode_zda(
    gps_ns: int, talker: str = "GP", decimals: int = 2, gps_minus_utc_s: int | None = None
) -> bytes:
    """``$--ZDA`` for a GPS instant (UTC on the wire, 23:59:60 in an inserted second; local zone 00,00)."""
    date, tod = gps_ns_to_utc_fields(gps_ns, gps_minus_utc_s)
    return encode_sentence(
        f"{talker}ZDA,{format_hhmmss(tod, decimals)},{date.day:02d},{date.month:02d},{date.year:04d},00,00"
    )


def encode_gps_utc(gps_minus_utc_s: int) -> bytes:
    """``$PMLS,GPSUTC,<s>``: the GPS − UTC the device applies (this project's stand-in sentence)."""
    return encode_sentence(f"PMLS,GPSUTC,{int(gps_minus_utc_s):d}")
