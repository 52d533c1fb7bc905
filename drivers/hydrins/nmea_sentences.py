"""Hydrins NMEA sentences: one typed record per sentence and the parsers of their fields.

A typed record exists for ``$--ZDA``, ``$--GGA``, ``$--RMC``, ``$--HDT``, ``$--VTG`` and the
``$PIXSE`` block (``ATITUD``, ``POSITI``, ``SPEED_``, ``HEAVE_``, ``TIME__``, ``STDHRP``,
``STDPOS``, ``STDSPD``, ``ALGSTS``, ``STATUS``, ``HT_STS``) and ``$PMLS,GPSUTC``; any other valid
sentence is a generic :class:`Sentence`. Empty fields are missing values (NaN/None), never zeros; anything else must
parse or the sentence is rejected. :func:`checksum` is the NMEA checksum.

The typed sentence records carry the **native** values of the wire (degrees, iXblue signs:
pitch + bow down, sway + port, heave + up, speed east/north/up, longitude 0–360). They are
the decode view; nothing else in the project should use them for geometry.

``$PMLS,GPSUTC,<s>`` (:class:`GpsUtcOffset`) is this project's documented stand-in — like the
PPS1 datagram and ZFP1 — for the GPS − UTC offset a GNSS-aided INS knows (the PHINS standard
block carries none): the whole seconds the INS subtracts from GPS time to make its UTC tags
(ZDA, TIME__), sent once a second before the ZDA. RMC's two-digit year is 19yy from 80 on
(the GPS epoch), 20yy below.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import reduce
from operator import xor

from drivers.hydrins.timeofday import parse_hhmmss_ns

NAN = math.nan
KNOT_M_S = 1852.0 / 3600.0

# ---------------------------------------------------------------------------------------------
# Typed sentence records (native wire values; see the module docstring).
# ---------------------------------------------------------------------------------------------


@dataclass(slots=True)
class Sentence:
    """Any valid sentence without a typed record: ``kind`` is e.g. 'GSA', 'PSXN', 'PIXSE,UTMWGS'."""

    talker: str
    kind: str
    fields: list[str]
    host_ns: int | None = None


@dataclass(slots=True)
class Zda:
    talker: str
    time_of_day_ns: int | None
    day: int | None
    month: int | None
    year: int | None
    host_ns: int | None = None


@dataclass(slots=True)
class Gga:
    talker: str
    time_of_day_ns: int | None
    lat_deg: float
    lon_deg: float
    quality: int | None
    n_satellites: int | None
    hdop: float
    altitude_msl_m: float
    geoid_separation_m: float
    dgps_age_s: float
    host_ns: int | None = None


@dataclass(slots=True)
class Rmc:
    talker: str
    time_of_day_ns: int | None
    valid: bool | None
    lat_deg: float
    lon_deg: float
    speed_m_s: float
    course_deg: float
    day: int | None
    month: int | None
    year: int | None
    host_ns: int | None = None


@dataclass(slots=True)
class Hdt:
    talker: str
    heading_deg: float
    host_ns: int | None = None


@dataclass(slots=True)
class Vtg:
    talker: str
    course_true_deg: float
    course_magnetic_deg: float
    speed_m_s: float
    mode: str | None
    host_ns: int | None = None


@dataclass(slots=True)
class PixseAtitud:
    """Roll (+ port up) and pitch (+ bow down, iXblue native) in degrees."""

    roll_deg: float
    pitch_deg: float
    host_ns: int | None = None


@dataclass(slots=True)
class PixsePositi:
    lat_deg: float
    lon_deg: float  # 0–360 as sent
    altitude_m: float
    host_ns: int | None = None


@dataclass(slots=True)
class PixseSpeed:
    east_m_s: float
    north_m_s: float
    up_m_s: float
    host_ns: int | None = None


@dataclass(slots=True)
class PixseHeave:
    """Surge (+ bow), sway (+ port), heave (+ up), iXblue native, metres."""

    surge_m: float
    sway_m: float
    heave_m: float
    host_ns: int | None = None


@dataclass(slots=True)
class PixseTime:
    time_of_day_ns: int | None
    host_ns: int | None = None


@dataclass(slots=True)
class PixseStdhrp:
    heading_deg: float
    roll_deg: float
    pitch_deg: float
    host_ns: int | None = None


@dataclass(slots=True)
class PixseStdpos:
    north_m: float
    east_m: float
    altitude_m: float
    host_ns: int | None = None


@dataclass(slots=True)
class PixseStdspd:
    north_m_s: float
    east_m_s: float
    up_m_s: float
    host_ns: int | None = None


@dataclass(slots=True)
class PixseAlgsts:
    """INS algorithm status words 1 (LSB) and 2 (MSB)."""

    status1: int | None
    status2: int | None
    host_ns: int | None = None


@dataclass(slots=True)
class PixseStatus:
    """INS system status words 1 (LSB) and 2 (MSB)."""

    status1: int | None
    status2: int | None
    host_ns: int | None = None


@dataclass(slots=True)
class GpsUtcOffset:
    """``$PMLS,GPSUTC,<s>``: GPS − UTC in whole seconds, as the INS applies it to its UTC tags."""

    gps_minus_utc_s: int | None
    host_ns: int | None = None


@dataclass(slots=True)
class PixseHtSts:
    """INS high-level (user) status word."""

    status: int | None
    host_ns: int | None = None


# ---------------------------------------------------------------------------------------------
# Field parsers: empty → missing, anything else must parse or the sentence is rejected.
# ---------------------------------------------------------------------------------------------


def _f(s: str) -> float:
    return float(s) if s else NAN


def _i(s: str) -> int | None:
    return int(s) if s else None


def _hex(s: str) -> int | None:
    if not s:
        return None
    value = int(s, 16)
    if not 0 <= value <= 0xFFFFFFFF:
        raise ValueError(f"status word {s!r} is not 32-bit hex")
    return value


def _tod(s: str) -> int | None:
    return parse_hhmmss_ns(s) if s else None


def _latlon(value: str, hemisphere: str) -> float:
    if not value:
        return NAN
    v = float(value)
    deg = int(v // 100.0)
    result = deg + (v - 100.0 * deg) / 60.0
    if hemisphere in ("S", "W"):
        return -result
    if hemisphere not in ("N", "E", ""):
        raise ValueError(f"hemisphere {hemisphere!r}")
    return result


def _pad(f: list[str], n: int) -> list[str]:
    return f if len(f) >= n else f + [""] * (n - len(f))


def _p_zda(t, f, h):
    f = _pad(f, 5)
    return Zda(t, _tod(f[1]), _i(f[2]), _i(f[3]), _i(f[4]), h)


def _p_gga(t, f, h):
    f = _pad(f, 14)
    return Gga(
        t,
        _tod(f[1]),
        _latlon(f[2], f[3]),
        _latlon(f[4], f[5]),
        _i(f[6]),
        _i(f[7]),
        _f(f[8]),
        _f(f[9]),
        _f(f[11]),
        _f(f[13]),
        h,
    )


def _p_rmc(t, f, h):
    f = _pad(f, 10)
    date = f[9]
    if date and (len(date) != 6 or not date.isdigit()):
        raise ValueError(f"RMC date {date!r}")
    yy = int(date[4:6]) if date else 0
    day, month, year = (
        (int(date[0:2]), int(date[2:4]), (1900 if yy >= 80 else 2000) + yy) if date else (None,) * 3
    )
    valid = {"A": True, "V": False}.get(f[2])
    kn = _f(f[7])
    return Rmc(
        t,
        _tod(f[1]),
        valid,
        _latlon(f[3], f[4]),
        _latlon(f[5], f[6]),
        kn * KNOT_M_S,
        _f(f[8]),
        day,
        month,
        year,
        h,
    )


def _p_hdt(t, f, h):
    f = _pad(f, 2)
    return Hdt(t, _f(f[1]), h)


def _p_vtg(t, f, h):
    f = _pad(f, 10)
    if f[2] in ("T", ""):  # NMEA 2.3+: value,unit pairs
        kn, mode = _f(f[5]), f[9] or None
        return Vtg(t, _f(f[1]), _f(f[3]), kn * KNOT_M_S, mode, h)
    return Vtg(t, _f(f[1]), _f(f[2]), _f(f[3]) * KNOT_M_S, None, h)  # NMEA 1.5


def _p3(cls):
    def parse(t, f, h):
        f = _pad(f, 5)
        return cls(_f(f[2]), _f(f[3]), _f(f[4]), h)

    return parse


def _p_atitud(t, f, h):
    f = _pad(f, 4)
    return PixseAtitud(_f(f[2]), _f(f[3]), h)


def _p_time(t, f, h):
    f = _pad(f, 3)
    return PixseTime(_tod(f[2]), h)


def _p_words(cls):
    def parse(t, f, h):
        f = _pad(f, 4)
        return cls(_hex(f[2]), _hex(f[3]), h)

    return parse


def _p_htsts(t, f, h):
    f = _pad(f, 3)
    return PixseHtSts(_hex(f[2]), h)


def _p_gpsutc(t, f, h):
    f = _pad(f, 3)
    value = _i(f[2])
    if value is not None and not 0 <= value <= 255:
        raise ValueError(f"GPS − UTC {value} s")
    return GpsUtcOffset(value, h)


STANDARD_PARSERS = {"ZDA": _p_zda, "GGA": _p_gga, "RMC": _p_rmc, "HDT": _p_hdt, "VTG": _p_vtg}
PIXSE_PARSERS = {
    "ATITUD": _p_atitud,
    "POSITI": _p3(PixsePositi),
    "SPEED_": _p3(PixseSpeed),
    "HEAVE_": _p3(PixseHeave),
    "TIME__": _p_time,
    "STDHRP": _p3(PixseStdhrp),
    "STDPOS": _p3(PixseStdpos),
    "STDSPD": _p3(PixseStdspd),
    "ALGSTS": _p_words(PixseAlgsts),
    "STATUS": _p_words(PixseStatus),
    "HT_STS": _p_htsts,
}
PMLS_PARSERS = {"GPSUTC": _p_gpsutc}


def checksum(body: bytes) -> int:
    """NMEA checksum: XOR of the bytes between ``$``/``!`` and ``*``."""
    return reduce(xor, body, 0)
