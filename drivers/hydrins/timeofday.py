"""Time-of-day tags → full GPS time: resolving the date an INS sentence leaves out.

``$PIXSE,TIME__`` and the STDBIN validity time carry only the time of day. The date comes from a
*hint*: a full UTC instant known to be within ±12 h of the tag (the last ZDA sentence, the
STDBIN system date, or the host's UTC clock). Of the three candidate days around the hint, the
one that puts the tag nearest to the hint wins, so a tag of 23:59:59 read just after midnight
goes to the previous day.
"""

from __future__ import annotations

import datetime as _dt
from functools import lru_cache

from calib.core.frames import leap_seconds_at_gps_ns, utc_fields_to_gps_ns

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
    """Nanoseconds since midnight → ``'hhmmss.fff'`` with ``decimals`` digits (truncated)."""
    s, ns = divmod(int(time_of_day_ns), NS_PER_S)
    hh, rem = divmod(s, 3600)
    mm, ss = divmod(rem, 60)
    text = f"{hh:02d}{mm:02d}{ss:02d}"
    if decimals:
        text += "." + f"{ns:09d}"[:decimals]
    return text


def utc_date_ns(year: int, month: int, day: int) -> int:
    """UTC midnight of a date, ns since the Unix epoch (the hint scale)."""
    return (_dt.date(year, month, day) - _UNIX_EPOCH).days * DAY_NS


def resolve_gps_ns(time_of_day_ns: int, hint_utc_ns: int) -> int:
    """UTC time of day + a UTC instant within ±12 h (ns since the Unix epoch) → GPS ns."""
    day = hint_utc_ns // DAY_NS
    err = day * DAY_NS + time_of_day_ns - hint_utc_ns  # of the hint's own day; the nearest wins
    best, best_err = day - 1, abs(err - DAY_NS)  # (ties: the earlier day)
    if abs(err) < best_err:
        best, best_err = day, abs(err)
    if abs(err + DAY_NS) < best_err:
        best = day + 1
    return _gps_midnight_ns(best) + time_of_day_ns


@lru_cache(maxsize=16)
def _gps_midnight_ns(day: int) -> int:
    """GPS ns of UTC midnight ``day`` days after the Unix epoch (the day's leap-second count is
    that of its midnight, as for :func:`calib.core.frames.utc_fields_to_gps_ns`)."""
    date = _UNIX_EPOCH + _dt.timedelta(days=day)
    return utc_fields_to_gps_ns(date.year, date.month, date.day, 0)


def utc_time_of_day_ns(gps_ns: int) -> int:
    """GPS ns → UTC nanoseconds since midnight (the GPS epoch is a UTC midnight)."""
    gps_ns = int(gps_ns)
    return (gps_ns - leap_seconds_at_gps_ns(gps_ns) * NS_PER_S) % DAY_NS
