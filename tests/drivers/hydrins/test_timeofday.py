"""Resolving a time-of-day tag's date from a hint: the nearest of the three days around it, with
the leap-second count of that day's midnight."""

from __future__ import annotations

import datetime as _dt

from hypothesis import given
from hypothesis import strategies as st

from calib.core.frames import utc_fields_to_gps_ns
from drivers.hydrins.timeofday import DAY_NS, resolve_gps_ns, utc_date_ns
from tests.drivers.helpers import PROPERTY

NS = 1_000_000_000


def _reference(tod_ns: int, hint_ns: int) -> int:
    """The definition, by dates: each candidate day's UTC midnight + the tag, nearest to the hint."""
    day = hint_ns // DAY_NS
    best = min((day - 1, day, day + 1), key=lambda d: abs(d * DAY_NS + tod_ns - hint_ns))
    date = _dt.date(1970, 1, 1) + _dt.timedelta(days=best)
    return utc_fields_to_gps_ns(date.year, date.month, date.day, tod_ns)


@PROPERTY
@given(
    st.integers(0, DAY_NS - 1),
    st.integers(utc_date_ns(1999, 1, 1), utc_date_ns(2030, 1, 1)),
    st.integers(-12 * 3600 * NS, 12 * 3600 * NS),
)
def test_resolve_is_the_nearest_day_by_dates(tod_ns, day_ns, offset_ns):
    hint = day_ns // DAY_NS * DAY_NS + tod_ns + offset_ns  # the tag's instant, seen from ±12 h
    assert resolve_gps_ns(tod_ns, hint) == _reference(tod_ns, hint)


def test_across_midnight_and_a_leap_second():
    # 2016-12-31 23:59:59 read just after midnight of the leap second (GPS − UTC 17 → 18 s)
    hint = utc_date_ns(2017, 1, 1) + 2 * NS
    assert resolve_gps_ns(86_399 * NS, hint) == utc_fields_to_gps_ns(2016, 12, 31, 86_399 * NS)
    assert resolve_gps_ns(1 * NS, hint) == utc_fields_to_gps_ns(2017, 1, 1, NS)
    assert resolve_gps_ns(1 * NS, hint) - resolve_gps_ns(86_399 * NS, hint) == 3 * NS  # 23:59:60 between
    # an exact tie (12 h either way) goes to the earlier day, as the date rule says
    assert resolve_gps_ns(0, utc_date_ns(2024, 5, 17) + 12 * 3600 * NS) == utc_fields_to_gps_ns(
        2024, 5, 17, 0
    )
