"""The leap-second table (IERS leap-seconds.list: steps, expiry, SHA-1), installing a newer one,
the inserted second 23:59:60 both ways, and the GPS week rollover of device dates."""

from __future__ import annotations

import datetime as dt

import pytest

from calib.core import frames, gpstime
from calib.core.gpstime import BUILTIN, LeapTable, parse_leap_seconds_list, unroll_week_rollover

NS = 1_000_000_000
UTC = dt.UTC

# The numbers of IERS's leap-seconds.list updated 2026-01-06 (tzdata 2026b): '#$' last update,
# '#@' expiry, '#h' SHA-1, then NTP seconds and TAI − UTC (the comments do not enter the hash).
IERS_2026 = """\
#	File expires on 28 December 2026
#$	3976686858
#@	4007404800
2272060800	10	# 1 Jan 1972
2287785600	11	# 1 Jul 1972
2303683200	12	# 1 Jan 1973
2335219200	13	# 1 Jan 1974
2366755200	14	# 1 Jan 1975
2398291200	15	# 1 Jan 1976
2429913600	16	# 1 Jan 1977
2461449600	17	# 1 Jan 1978
2492985600	18	# 1 Jan 1979
2524521600	19	# 1 Jan 1980
2571782400	20	# 1 Jul 1981
2603318400	21	# 1 Jul 1982
2634854400	22	# 1 Jul 1983
2698012800	23	# 1 Jul 1985
2776982400	24	# 1 Jan 1988
2840140800	25	# 1 Jan 1990
2871676800	26	# 1 Jan 1991
2918937600	27	# 1 Jul 1992
2950473600	28	# 1 Jul 1993
2982009600	29	# 1 Jul 1994
3029443200	30	# 1 Jan 1996
3076704000	31	# 1 Jul 1997
3124137600	32	# 1 Jan 1999
3345062400	33	# 1 Jan 2006
3439756800	34	# 1 Jan 2009
3550089600	35	# 1 Jul 2012
3644697600	36	# 1 Jul 2015
3692217600	37	# 1 Jan 2017
#h	2e101270 4e6749f8 2f1792b7 14a0c188 36bb19d6
"""


@pytest.fixture(autouse=True)
def builtin_table():
    with gpstime.leap_table_scope():
        yield


def test_the_builtin_table_is_iers_leap_seconds_list_with_its_expiry():
    t = parse_leap_seconds_list(IERS_2026, "leap-seconds.list")
    assert t.steps == BUILTIN.steps and t.steps[-1] == (dt.date(2017, 1, 1), 18)
    assert (
        (t.expires, t.updated)
        == (dt.date(2026, 12, 28), dt.date(2026, 1, 6))
        == (
            BUILTIN.expires,
            BUILTIN.updated,
        )
    )
    assert not t.expired_at_unix_ns(int(dt.datetime(2026, 12, 27, 23, 59, tzinfo=UTC).timestamp()) * NS)
    assert t.expired_at_unix_ns(int(dt.datetime(2026, 12, 28, tzinfo=UTC).timestamp()) * NS)
    assert t.as_dict()["gps_minus_utc_s"] == 18 and t.as_dict()["expires"] == "2026-12-28"


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (("3692217600\t37", "3692217600\t38"), r"the '#h' SHA-1 does not match"),
        (("#@\t4007404800\n", ""), r"no '#@' \(expiry\) line"),
        (("2571782400\t20", "2571782400\tx"), r"leap-seconds.list:14: .*expected '<NTP seconds> <TAI−UTC>'"),
    ],
)
def test_a_damaged_or_incomplete_list_is_refused(edit, message):
    with pytest.raises(ValueError, match=message):
        parse_leap_seconds_list(IERS_2026.replace(*edit), "leap-seconds.list")


def _with_2027_leap_second() -> LeapTable:
    return LeapTable(
        BUILTIN.steps + ((dt.date(2027, 7, 1), 19),), dt.date(2027, 12, 28), dt.date(2027, 1, 7), "newer"
    )


def test_a_newer_consistent_table_is_installed_and_converts_with_its_leap_second():
    before = frames.utc_fields_to_gps_ns(2027, 7, 1, 0)
    assert gpstime.use_leap_table(_with_2027_leap_second())
    assert gpstime.leap_table().source == "newer" and gpstime.table_generation() > 0
    assert frames.utc_fields_to_gps_ns(2027, 7, 1, 0) == before + NS
    assert (
        frames.utc_fields_to_gps_ns(2027, 6, 30, 0)
        == frames.utc_fields_to_gps_ns(2027, 6, 29, 0) + 86_400 * NS
    )
    assert frames.leap_seconds_at_utc(dt.datetime(2027, 7, 1, tzinfo=UTC)) == 19
    assert not gpstime.use_leap_table(BUILTIN)  # older: kept out, no error
    rewritten = LeapTable(
        BUILTIN.steps[:-1] + ((dt.date(2017, 7, 1), 18),), dt.date(2028, 1, 1), dt.date(2027, 1, 1), "bad"
    )
    with pytest.raises(ValueError, match="bad contradicts the one in use"):
        gpstime.use_leap_table(rewritten)


def test_the_inserted_second_is_23_59_60_both_ways_and_gps_time_runs_on():
    """GPS instants every 0.25 s across the end of 2016 (GPS − UTC 17 → 18 s): the UTC fields
    read 23:59:59.75, 23:59:60.00 … 23:59:60.75, then 00:00:00.00 of 2017-01-01, and go back to
    the same GPS instants."""
    start = frames.utc_fields_to_gps_ns(2016, 12, 31, 86_399 * NS)
    seen = []
    for k in range(12):
        g = start + k * NS // 4
        date, tod = frames.gps_ns_to_utc_fields(g)
        assert frames.utc_fields_to_gps_ns(date.year, date.month, date.day, tod) == g
        seen.append((date.isoformat(), tod / NS))
    assert seen[3:9] == [
        ("2016-12-31", 86_399.75),
        ("2016-12-31", 86_400.0),
        ("2016-12-31", 86_400.25),
        ("2016-12-31", 86_400.5),
        ("2016-12-31", 86_400.75),
        ("2017-01-01", 0.0),
    ]
    # a device that believes another count: its fields, undone with its count, give the instant
    date, tod = frames.gps_ns_to_utc_fields(start, gps_minus_utc_s=19)
    assert frames.utc_fields_to_gps_ns(date.year, date.month, date.day, tod, gps_minus_utc_s=19) == start


def test_a_gps_week_rollover_moves_a_date_by_whole_1024_week_eras_toward_the_reference():
    day = (dt.date(2026, 12, 2) - dt.date(1970, 1, 1)).days
    assert unroll_week_rollover(day - 7168, day) == (day, 1)  # the 1024-week bug: 2007-04-18
    assert unroll_week_rollover(day - 2 * 7168 + 3, day) == (day + 3, 2)
    assert unroll_week_rollover(day - 3000, day) == (day - 3000, 0)  # 8 years back: a real date
    assert unroll_week_rollover(day - 7168, None) == (day - 7168, 0)  # no reference: untouched
