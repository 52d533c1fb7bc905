"""Conventions of calib.core.frames (docs/architecture.md §3): attitude, foreign conventions, geodesy, GPS time."""

from __future__ import annotations

import datetime as dt

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from calib.core import frames

UTC = dt.UTC
D = np.radians
angle = st.floats(-np.pi, np.pi, allow_nan=False)
small_pitch = st.floats(-D(89.0), D(89.0), allow_nan=False)


# -- attitude ------------------------------------------------------------------------------------


def test_heading_90_maps_body_forward_to_east():
    R = frames.attitude_matrix(0.0, 0.0, D(90.0))
    np.testing.assert_allclose(R @ [1, 0, 0], [0, 1, 0], atol=1e-15)  # bow → east
    np.testing.assert_allclose(R @ [0, 1, 0], [-1, 0, 0], atol=1e-15)  # starboard → south
    np.testing.assert_allclose(R @ [0, 0, 1], [0, 0, 1], atol=1e-15)  # down stays down


def test_positive_pitch_is_bow_up_and_positive_roll_is_starboard_down():
    bow = frames.attitude_matrix(0.0, D(10.0), 0.0) @ [1, 0, 0]
    assert bow[2] == pytest.approx(-np.sin(D(10.0)), abs=1e-15)  # NED: negative down = up
    starboard = frames.attitude_matrix(D(10.0), 0.0, 0.0) @ [0, 1, 0]
    assert starboard[2] == pytest.approx(np.sin(D(10.0)), abs=1e-15)


def test_rotation_zyx_is_rz_ry_rx():
    r, p, y = 0.3, -0.2, 2.1
    np.testing.assert_allclose(
        frames.rotation_zyx(r, p, y), frames.rot_z(y) @ frames.rot_y(p) @ frames.rot_x(r), atol=1e-15
    )


def test_thesis_matrix_hand_computed_case_equals_converted_canonical():
    # Thesis (NWU, iXblue signs): R = Rz(−h)·Ry(p)·Rx(r), here r = 90°, p = 30°, h = 90°.
    #   Rz(−90°) = [[0, 1, 0], [−1, 0, 0], [0, 0, 1]]
    #   Ry(30°)  = [[√3/2, 0, 1/2], [0, 1, 0], [−1/2, 0, √3/2]]
    #   Rz(−90°)·Ry(30°) = [[0, 1, 0], [−√3/2, 0, −1/2], [−1/2, 0, √3/2]]
    #   Rx(90°) has columns [1, 0, 0], [0, 0, 1], [0, −1, 0], so ·Rx(90°) keeps column 0,
    #   moves column 2 to column 1 and −column 1 to column 2:
    c = np.sqrt(3.0) / 2.0
    thesis_by_hand = np.array([[0.0, 0.0, -1.0], [-c, -0.5, 0.0], [-0.5, c, 0.0]])
    np.testing.assert_allclose(frames.thesis_matrix(D(90), D(30), D(90)), thesis_by_hand, atol=1e-15)
    # In NED/FRD (flip y and z on both sides: element (i, j) times f_i·f_j, f = (1, −1, −1)):
    canonical_by_hand = np.array([[0.0, 0.0, 1.0], [c, -0.5, 0.0], [0.5, c, 0.0]])
    np.testing.assert_allclose(
        frames.FLIP_YZ @ thesis_by_hand @ frames.FLIP_YZ, canonical_by_hand, atol=1e-15
    )
    # … which is the canonical matrix of (roll, −pitch, heading) = (90°, −30°, 90°)
    np.testing.assert_allclose(frames.rotation_zyx(D(90), D(-30), D(90)), canonical_by_hand, atol=1e-15)


def test_montreal_boresight_thesis_to_canonical():
    thesis = D([0.208, -1.245, 0.149])
    canonical = np.array(frames.boresight_from_thesis(*thesis))
    np.testing.assert_allclose(np.degrees(canonical), [0.208, 1.245, 0.149], atol=1e-12)
    np.testing.assert_allclose(
        frames.FLIP_YZ @ frames.thesis_matrix(*thesis) @ frames.FLIP_YZ,
        frames.rotation_zyx(*canonical),
        atol=1e-15,
    )
    np.testing.assert_allclose(frames.boresight_to_thesis(*canonical), thesis, atol=1e-15)


def test_ixblue_attitude_negates_pitch_only():
    r, p, h = frames.attitude_from_ixblue(0.1, 0.2, 3.0)
    assert (float(r), float(p), float(h)) == (0.1, -0.2, 3.0)
    assert tuple(map(float, frames.attitude_to_ixblue(r, p, h))) == (0.1, 0.2, 3.0)


def test_mount_matrix_composes_boresight_after_nominal():
    bs, nom = D([0.2, 1.2, 0.1]), D([0.0, -20.0, 180.0])
    np.testing.assert_allclose(
        frames.mount_matrix(bs, nom), frames.rotation_zyx(*bs) @ frames.rotation_zyx(*nom), atol=1e-15
    )


def test_scanner_vector_angles():
    v = frames.scanner_vector([10.0] * 4, D([0.0, 90.0, 180.0, 270.0]))
    np.testing.assert_allclose(v, [[0, 10, 0], [0, 0, 10], [0, -10, 0], [0, 0, -10]], atol=1e-14)


def test_small_rotation_is_first_order_of_exact():
    v = np.array([1e-4, -2e-4, 3e-4])
    err = frames.small_rotation(v) - frames.rotation_from_vector(v)
    assert np.abs(err).max() < 1e-7  # second order: |v|²/2 ≈ 7e-8
    np.testing.assert_allclose(frames.skew(v) @ [1.0, 2.0, 3.0], np.cross(v, [1.0, 2.0, 3.0]), atol=1e-18)


def test_wrap():
    np.testing.assert_allclose(frames.wrap_pi([np.pi, -np.pi, 3 * np.pi / 2]), [np.pi, np.pi, -np.pi / 2])
    np.testing.assert_allclose(frames.wrap_2pi([-0.1, 2 * np.pi]), [2 * np.pi - 0.1, 0.0])


@settings(max_examples=150, deadline=None)
@given(angle, small_pitch, angle)
def test_rotation_is_orthonormal_and_euler_round_trips(r, p, y):
    R = frames.rotation_zyx(r, p, y)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-14)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-14)
    r2, p2, y2 = frames.euler_zyx_from_matrix(R)
    assert float(frames.wrap_pi(r2 - r)) == pytest.approx(0.0, abs=1e-9)
    assert float(p2) == pytest.approx(p, abs=1e-9)
    assert 0.0 <= float(y2) < 2 * np.pi
    assert float(frames.wrap_pi(y2 - y)) == pytest.approx(0.0, abs=1e-9)


@settings(max_examples=150, deadline=None)
@given(
    st.lists(st.floats(-1.0, 1.0), min_size=3, max_size=3).filter(lambda v: np.linalg.norm(v) > 1e-6),
    st.floats(0.0, np.pi - 1e-4),
)
def test_rotation_vector_round_trip(axis, theta):
    v = np.asarray(axis) / np.linalg.norm(axis) * theta
    R = frames.rotation_from_vector(v)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-14)
    np.testing.assert_allclose(frames.vector_from_rotation(R), v, atol=1e-9)


# -- geodesy -------------------------------------------------------------------------------------


def test_lgf_is_ned():
    f = frames.LocalFrame(45.5, -73.55, -30.0)
    np.testing.assert_allclose(f.to_lgf([45.5], [-73.55], [70.0]), [[0, 0, -100.0]], atol=1e-8)
    # one arc-second north and east: M·dφ north and N·cos φ·dλ east, with the WGS84 radii of
    # curvature M (meridian) and N (prime vertical) at 45.5°
    a, e2, phi, arcsec = 6_378_137.0, 0.00669437999014, np.radians(45.5), np.radians(1 / 3600)
    w = 1.0 - e2 * np.sin(phi) ** 2
    north_m, east_m = a * (1 - e2) / w**1.5 * arcsec, a / np.sqrt(w) * np.cos(phi) * arcsec
    p = f.to_lgf([45.5 + 1 / 3600], [-73.55 + 1 / 3600], [-30.0])[0]
    assert p[0] == pytest.approx(north_m, abs=1e-3) and p[1] == pytest.approx(east_m, abs=1e-3)


def test_geodetic_lgf_geodetic_round_trip_below_0_1_mm_over_10_km():
    f = frames.LocalFrame(45.5, -73.55, -30.0)
    rng = np.random.default_rng(7)
    n = 2000
    north, east = rng.uniform(-10_000, 10_000, (2, n))
    lat = 45.5 + north / 111_000.0
    lon = -73.55 + east / (111_000.0 * np.cos(np.radians(45.5)))
    h = rng.uniform(-100.0, 500.0, n)
    p = f.to_lgf(lat, lon, h)
    assert np.abs(p[:, :2]).max() > 9_000  # the points do span ~10 km
    lat2, lon2, h2 = f.to_geodetic(p)
    m_per_deg_lat = 111_000.0
    err_m = np.sqrt(
        ((lat2 - lat) * m_per_deg_lat) ** 2
        + ((lon2 - lon) * m_per_deg_lat * np.cos(np.radians(lat))) ** 2
        + (h2 - h) ** 2
    )
    assert err_m.max() < 1e-4


def test_lgf_matches_ecef_difference():
    f = frames.LocalFrame(10.0, 20.0, 0.0)
    p_ecef = frames.geodetic_to_ecef([10.001], [20.002], [55.0])[0]
    d = p_ecef - f.origin_ecef_m
    np.testing.assert_allclose(
        f.to_lgf([10.001], [20.002], [55.0])[0], frames.ecef_to_ned_matrix(10.0, 20.0) @ d, atol=1e-9
    )


@pytest.mark.parametrize(
    ("lat", "lon", "epsg"),
    [(45.5, -73.55, 32618), (-33.9, 151.2, 32756), (0.0, 0.0, 32631), (60.0, 179.99, 32660)],
)
def test_utm_epsg(lat, lon, epsg):
    assert frames.utm_epsg(lat, lon) == epsg


# -- GPS time ------------------------------------------------------------------------------------


def test_leap_seconds():
    assert frames.leap_seconds_at_utc(dt.datetime(1980, 1, 6, tzinfo=UTC)) == 0
    assert frames.leap_seconds_at_utc(dt.datetime(1981, 6, 30, 23, 59, 59, tzinfo=UTC)) == 0
    assert frames.leap_seconds_at_utc(dt.datetime(1981, 7, 1, tzinfo=UTC)) == 1
    assert frames.leap_seconds_at_utc(dt.datetime(2016, 12, 31, 23, 59, 59, tzinfo=UTC)) == 17
    assert frames.leap_seconds_at_utc(dt.datetime(2017, 1, 1, tzinfo=UTC)) == 18
    assert frames.leap_seconds_at_utc(dt.datetime(2026, 1, 1, tzinfo=UTC)) == 18
    with pytest.raises(ValueError, match="naive datetime"):
        frames.leap_seconds_at_utc(dt.datetime(2020, 1, 1))


def test_utc_to_gps_week_1930_starts_2017_01_01():
    # GPS week 1930 began 2017-01-01 00:00:00 GPS (a Sunday); GPS − UTC was still 17 s then,
    # so that is 2016-12-31 23:59:43 UTC
    assert (dt.date(2017, 1, 1) - dt.date(1980, 1, 6)).days == 1930 * 7
    gps_ns = frames.utc_to_gps_ns(dt.datetime(2016, 12, 31, 23, 59, 43, tzinfo=UTC))
    assert gps_ns == 1930 * 604_800 * 10**9
    assert frames.gps_seconds_to_week_sow(gps_ns / 1e9) == (1930, 0.0)
    # one UTC second later the leap second has happened: 18 s
    gps_ns = frames.utc_to_gps_ns(dt.datetime(2017, 1, 1, 0, 0, 0, tzinfo=UTC))
    assert gps_ns == (1930 * 604_800 + 18) * 10**9


def test_week_rollover_2019():
    # week 2048 (the 10-bit rollover) began 2019-04-07 00:00:00 GPS = 2019-04-06 23:59:42 UTC
    gps_ns = 2048 * 604_800 * 10**9
    assert frames.gps_ns_to_utc(gps_ns) == dt.datetime(2019, 4, 6, 23, 59, 42, tzinfo=UTC)
    assert frames.leap_seconds_at_gps_ns(gps_ns) == 18


def test_utc_gps_round_trip_and_fields():
    for utc in [
        dt.datetime(1985, 3, 1, 12, 0, 0, 250_000, tzinfo=UTC),
        dt.datetime(2016, 12, 31, 23, 59, 59, 500_000, tzinfo=UTC),
        dt.datetime(2021, 8, 17, 14, 0, 1, 123_456, tzinfo=UTC),
    ]:
        assert frames.gps_ns_to_utc(frames.utc_to_gps_ns(utc)) == utc
    sod_ns = (14 * 3600 + 1) * 10**9 + 123_456_789
    assert frames.utc_fields_to_gps_ns(2021, 8, 17, sod_ns) == frames.utc_to_gps_ns(
        dt.datetime(2021, 8, 17, 14, 0, 1, 123_456, tzinfo=UTC), extra_ns=789
    )


def test_week_sow_and_las_time():
    week, sow = frames.gps_seconds_to_week_sow(np.array([2171 * 604_800 + 345_600.25]))
    assert week.tolist() == [2171] and sow.tolist() == [345_600.25]
    assert frames.week_sow_to_gps_seconds(week, sow).tolist() == [2171 * 604_800 + 345_600.25]
    assert float(frames.gps_seconds_to_las(1_313_244_018.5)) == 313_244_018.5
    assert float(frames.las_to_gps_seconds(313_244_018.5)) == 1_313_244_018.5


def test_ns_seconds_round_trip():
    ns = np.array([1_313_244_018_123_456_789, 0, 3_786_912_018_999_999_999], dtype=np.int64)
    s = frames.gps_ns_to_seconds(ns)
    back = frames.seconds_to_gps_ns(s)
    half_ulp_ns = np.spacing(s) / 2 * 1e9  # float64 seconds hold ~0.24 µs at 1.3e9 s
    assert np.all(np.abs(back - ns) <= half_ulp_ns + 1)
    assert frames.gps_ns_to_seconds(1_500_000_000) == 1.5
    assert frames.seconds_to_gps_ns(1.5) == 1_500_000_000
