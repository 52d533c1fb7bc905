"""Time-of-day tags → full GPS time: resolving the date an INS sentence leaves out.

``$PIXSE,TIME__`` and the STDBIN validity time carry only the time of day. The date comes from a
*hint*: a full UTC instant known to be within ±12 h of the tag (the last ZDA sentence, the
STDBIN system date, or the host's UTC clock). Of the three candidate days around the hint, the
one that puts the tag nearest to the hint wins, so a tag of 23:59:59 read just after midnight
goes to the previous day.

GPS − UTC is the table's count at the tag's own UTC midnight (:mod:`calib.core.gpstime`), so
tags on either side of a midnight where a leap second is inserted date correctly, and the
inserted second itself is 23:59:60.x (86 400 s + x) of the day that ends with it — in both
directions (:func:`utc_time_of_day_ns` writes it so for the emulators). A device that says which
GPS − UTC it applies (``gps_minus_utc_s``) has its tags undone with its own count instead.
Device dates go through :func:`device_date_ns`, which undoes a GPS week rollover
(:func:`calib.core.gpstime.unroll_week_rollover`) against a reference date.
"""

from __future__ import annotations

import datetime as _dt
from functools import lru_cache

from calib.core.frames import gps_ns_to_utc_fields, utc_fields_to_gps_ns
from calib.core.gpstime import GPS_EPOCH_DATE, table_generation, unroll_week_rollover

NS_PER_S = 1_000_000_000
DAY_NS = 86_400 * NS_PER_S
_UNIX_EPOCH = _dt.date(1970, 1, 1)


def parse_hhmmss_ns(text: str) -> int:
    """``'hhmmss[.fff…]'`` → nanoseconds since midnight (exact, no float rounding).

    Raises ValueError naming the text when it is not a time of day (seconds up to 60 are
    accepted for a leap second).
    """
    if len(text) < 6 or (len(text) > 6 and text[6] != "."):
        raise ValueError(f"time of day {text!r}: expected hhmmss[.fff]")
    hh, mm, ss = int(text[0:2]), int(text[2:4]), int(text[4:6])
    frac = text[7:]
    if hh > 23 or mm > 59 or ss > 60 or not text[0:6].isdigit() or (frac and not frac.isdigit()):
        raise ValueError(f"time of day {text!r}: expected hhmmss[.fff]")
    ns = int((frac + "000000000")[:9]) if frac else 0
    return (hh * 3600 + mm * 60 + ss) * NS_PER_S + ns


def format_hhmmss(time_of_day_ns: int, decimals: int) -> str:
    """Nanoseconds since midnight → ``'hhmmss.fff'`` with ``decimals`` digits (truncated);
    86 400 s and beyond (an inserted leap second) → ``'235960.fff'``."""
    s, ns = divmod(int(time_of_day_ns), NS_PER_S)
    if s >= 86_400:  # an inserted leap second: 23:59:60
        hh, mm, ss = 23, 59, s - 86_340
    else:
        hh, rem = divmod(s, 3600)
        mm, ss = divmod(rem, 60)
    text = f"{hh:02d}{mm:02d}{ss:02d}"
    if decimals:
        text += "." + f"{ns:09d}"[:decimals]
    return text


def utc_date_ns(year: int, month: int, day: int) -> int:
    """UTC midnight of a date, ns since the Unix epoch (the hint scale)."""
    return (_dt.date(year, month, day) - _UNIX_EPOCH).days * DAY_NS


def device_date_ns(year: int, month: int, day: int, reference_utc_ns: int | None) -> tuple[int, int]:
    """A device's UTC date → (its midnight in ns since the Unix epoch, 1024-week eras it was
    moved by): a date more than half an era (9.8 years) from ``reference_utc_ns`` (the host's
    UTC time, or a recording's receive time; None: never moved) is a GPS week rollover and is
    moved by whole eras toward it. Raises ValueError for an impossible date."""
    days = (_dt.date(year, month, day) - _UNIX_EPOCH).days
    if reference_utc_ns is None:
        return days * DAY_NS, 0
    days, eras = unroll_week_rollover(days, int(reference_utc_ns) // DAY_NS)
    return days * DAY_NS, eras


def device_fields_to_gps_ns(
    year: int,
    month: int,
    day: int,
    time_of_day_ns: int,
    reference_utc_ns: int | None,
    gps_minus_utc_s: int | None = None,
) -> tuple[int, int]:
    """A device's UTC date and time of day → (GPS ns, 1024-week eras the date was moved by,
    see :func:`device_date_ns`); ``gps_minus_utc_s`` as for :func:`resolve_gps_ns`."""
    days, eras = (_dt.date(year, month, day) - _UNIX_EPOCH).days, 0
    if reference_utc_ns is not None:
        days, eras = unroll_week_rollover(days, int(reference_utc_ns) // DAY_NS)
    if gps_minus_utc_s is not None:
        return (days - _GPS_EPOCH_DAY) * DAY_NS + gps_minus_utc_s * NS_PER_S + time_of_day_ns, eras
    return _gps_midnight_ns(days, table_generation()) + time_of_day_ns, eras


def resolve_gps_ns(time_of_day_ns: int, hint_utc_ns: int, gps_minus_utc_s: int | None = None) -> int:
    """UTC time of day + a UTC instant within ±12 h (ns since the Unix epoch) → GPS ns;
    ``gps_minus_utc_s``: the device's own GPS − UTC instead of the table's."""
    day = hint_utc_ns // DAY_NS
    err = day * DAY_NS + time_of_day_ns - hint_utc_ns  # of the hint's own day; the nearest wins
    best, best_err = day - 1, abs(err - DAY_NS)  # (ties: the earlier day)
    if abs(err) < best_err:
        best, best_err = day, abs(err)
    if abs(err + DAY_NS) < best_err:
        best = day + 1
    if gps_minus_utc_s is not None:
        return (best - _GPS_EPOCH_DAY) * DAY_NS + gps_minus_utc_s * NS_PER_S + time_of_day_ns
    return _gps_midnight_ns(best, table_generation()) + time_of_day_ns


_GPS_EPOCH_DAY = (GPS_EPOCH_DATE - _UNIX_EPOCH).days


@lru_cache(maxsize=16)
def _gps_midnight_ns(day: int, generation: int) -> int:
    """GPS ns of UTC midnight ``day`` days after the Unix epoch (the day's leap-second count is
    that of its midnight, as for :func:`calib.core.frames.utc_fields_to_gps_ns`); cached per
    leap-second table (``generation``: :func:`calib.core.gpstime.table_generation`)."""
    date = _UNIX_EPOCH + _dt.timedelta(days=day)
    return utc_fields_to_gps_ns(date.year, date.month, date.day, 0)


def utc_time_of_day_ns(gps_ns: int, gps_minus_utc_s: int | None = None) -> int:
    """GPS ns → UTC nanoseconds since midnight (up to 86 401 s: 23:59:60.x in an inserted
    second); ``gps_minus_utc_s``: with this count instead of the table's."""
    return gps_ns_to_utc_fields(gps_ns, gps_minus_utc_s)[1]
