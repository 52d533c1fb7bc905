"""Frames, angles and time: the project's conventions in one place (docs/architecture.md §3).

Navigation frame: local geodetic frame (LGF), NED tangent plane at a reference point, WGS84.
Body frame: FRD (x bow, y starboard, z down).
Attitude: ``R_b^n = Rz(heading) · Ry(pitch) · Rx(roll)`` (active, ZYX); roll + starboard down,
pitch + bow up, heading clockwise from true north.
Scanner frame S: scan plane is the y–z plane, ``r_S = ρ·[0, cos α, sin α]``.
Mount: ``R_S^b = R_bs · R_nom`` with ``R_bs = Rz(γ)·Ry(β)·Rx(α_b)`` the boresight.
Time: GPS time; int64 nanoseconds since the GPS epoch on disk and on the wire, float64 seconds
since the GPS epoch in arrays, adjusted standard GPS time (s − 1e9) in LAS; UTC ↔ GPS by IERS's
leap-second table, which expires (:mod:`calib.core.gpstime`), 23:59:60 included.

Everything here works in radians and SI units; degrees are converted at the edges with
``np.radians``/``np.degrees``.
"""

from __future__ import annotations

import datetime as _dt
from dataclasses import dataclass
from functools import cached_property
from typing import overload

import numpy as np
import numpy.typing as npt

from calib.core.gpstime import GPS_EPOCH_DATE, GPS_EPOCH_UNIX_S, leap_table

# ---------------------------------------------------------------------------------------------
# Elementary rotations (active), vectorized: an angle array of shape (...) gives (..., 3, 3).
# ---------------------------------------------------------------------------------------------


def _stack(rows, shape):
    return np.stack([np.stack(r, axis=-1) for r in rows], axis=-2).reshape(*shape, 3, 3)


def rot_x(angle_rad) -> np.ndarray:
    a = np.asarray(angle_rad, dtype=float)
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return _stack([[o, z, z], [z, c, -s], [z, s, c]], a.shape)


def rot_y(angle_rad) -> np.ndarray:
    a = np.asarray(angle_rad, dtype=float)
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return _stack([[c, z, s], [z, o, z], [-s, z, c]], a.shape)


def rot_z(angle_rad) -> np.ndarray:
    a = np.asarray(angle_rad, dtype=float)
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return _stack([[c, -s, z], [s, c, z], [z, z, o]], a.shape)


def rotation_zyx(roll_rad, pitch_rad, yaw_rad) -> np.ndarray:
    """``Rz(yaw) · Ry(pitch) · Rx(roll)`` computed in closed form, vectorized.

    This is the body→navigation attitude matrix ``R_b^n`` (yaw = heading), the boresight
    ``R_bs`` (small angles about body axes) and the nominal mount ``R_nom``.
    """
    r = np.asarray(roll_rad, dtype=float)
    p = np.asarray(pitch_rad, dtype=float)
    y = np.asarray(yaw_rad, dtype=float)
    r, p, y = np.broadcast_arrays(r, p, y)
    cr, sr = np.cos(r), np.sin(r)
    cp, sp = np.cos(p), np.sin(p)
    cy, sy = np.cos(y), np.sin(y)
    return _stack(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ],
        r.shape,
    )


def euler_zyx_from_matrix(R: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Inverse of :func:`rotation_zyx`: (roll, pitch, yaw) in radians, yaw in [0, 2π).

    Valid away from pitch = ±90° (never reached by a vessel or a boresight).
    """
    R = np.asarray(R, dtype=float)
    roll = np.arctan2(R[..., 2, 1], R[..., 2, 2])
    pitch = -np.arcsin(np.clip(R[..., 2, 0], -1.0, 1.0))
    yaw = wrap_2pi(np.arctan2(R[..., 1, 0], R[..., 0, 0]))
    return roll, pitch, yaw


def attitude_matrix(roll_rad, pitch_rad, heading_rad) -> np.ndarray:
    """``R_b^n`` for canonical attitude (FRD body → NED), see module docstring."""
    return rotation_zyx(roll_rad, pitch_rad, heading_rad)


# ---------------------------------------------------------------------------------------------
# Foreign conventions, converted at the edges.
# ---------------------------------------------------------------------------------------------

#: NWU ↔ NED (and iXblue body X bow/Y port/Z up ↔ FRD): a rotation of π about x.
FLIP_YZ = np.diag([1.0, -1.0, -1.0])


def attitude_from_ixblue(roll_rad, pitch_rad, heading_rad):
    """iXblue native attitude (pitch + bow down) → canonical (pitch + bow up)."""
    return (
        np.asarray(roll_rad, dtype=float),
        -np.asarray(pitch_rad, dtype=float),
        np.asarray(heading_rad, dtype=float),
    )


def attitude_to_ixblue(roll_rad, pitch_rad, heading_rad):
    """Canonical → iXblue native (the inverse of :func:`attitude_from_ixblue`)."""
    return attitude_from_ixblue(roll_rad, pitch_rad, heading_rad)


def thesis_matrix(r_rad, p_rad, h_rad) -> np.ndarray:
    """The thesis/MATLAB prototype matrix ``Rz(−h)·Ry(p)·Rx(r)`` in the NWU frame.

    The thesis builds both ``R_POS^LGF(r, p, h)`` and ``R_LiDAR^POS(α, β, γ)`` with this function
    (iXblue native signs). ``FLIP_YZ · thesis_matrix(r, p, h) · FLIP_YZ`` equals the canonical
    ``rotation_zyx(r, −p, h)``.
    """
    return rot_z(-np.asarray(h_rad, dtype=float)) @ rot_y(p_rad) @ rot_x(r_rad)


def boresight_from_thesis(roll_rad, pitch_rad, yaw_rad):
    """Thesis boresight (roll, pitch, yaw) → canonical (roll, −pitch, yaw)."""
    return attitude_from_ixblue(roll_rad, pitch_rad, yaw_rad)


def boresight_to_thesis(roll_rad, pitch_rad, yaw_rad):
    return attitude_from_ixblue(roll_rad, pitch_rad, yaw_rad)


# ---------------------------------------------------------------------------------------------
# Mount and small angles.
# ---------------------------------------------------------------------------------------------


def mount_matrix(boresight_rad, nominal_rad) -> np.ndarray:
    """``R_S^b = R_bs · R_nom``; both arguments are (roll, pitch, yaw) triples in radians."""
    return rotation_zyx(*boresight_rad) @ rotation_zyx(*nominal_rad)


def scanner_vector(range_m, scan_angle_rad) -> np.ndarray:
    """``r_S = ρ·[0, cos α, sin α]`` for arrays of shape (n,) → (n, 3)."""
    rho = np.asarray(range_m, dtype=float)
    a = np.asarray(scan_angle_rad, dtype=float)
    return np.stack([np.zeros_like(rho), rho * np.cos(a), rho * np.sin(a)], axis=-1)


def skew(v) -> np.ndarray:
    """Cross-product matrix ``[v]×`` (so ``skew(v) @ w == cross(v, w)``), vectorized."""
    v = np.asarray(v, dtype=float)
    z = np.zeros_like(v[..., 0])
    return _stack(
        [[z, -v[..., 2], v[..., 1]], [v[..., 2], z, -v[..., 0]], [-v[..., 1], v[..., 0], z]],
        v.shape[:-1],
    )


def small_rotation(v_rad) -> np.ndarray:
    """First-order rotation ``I + [v]×`` for a small rotation vector (linearization)."""
    return np.eye(3) + skew(v_rad)


def rotation_from_vector(v_rad) -> np.ndarray:
    """Exact rotation matrix of a rotation vector (axis × angle), Rodrigues, vectorized."""
    v = np.asarray(v_rad, dtype=float)
    theta = np.linalg.norm(v, axis=-1)
    K = skew(v)
    small = theta < 1e-8
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta**2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(safe)) / safe**2)
    return np.eye(3) + a[..., None, None] * K + b[..., None, None] * (K @ K)


def vector_from_rotation(R) -> np.ndarray:
    """Rotation vector of a rotation matrix (inverse of :func:`rotation_from_vector`), valid
    for every angle in [0, π] (near π the axis comes from the symmetric part of R)."""
    R = np.asarray(R, dtype=float)
    w = np.stack(
        [R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]],
        axis=-1,
    )
    cos_t = np.clip((np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    sin_t = 0.5 * np.linalg.norm(w, axis=-1)
    theta = np.arctan2(sin_t, cos_t)
    small = sin_t < 1e-12
    scale = np.where(small, 0.5, theta / (2.0 * np.where(small, 1.0, sin_t)))
    out = w * scale[..., None]
    near_pi = theta > np.pi - 1e-3
    if np.any(near_pi):
        # (R + Rᵀ)/2 = cos θ·I + (1 − cos θ)·n nᵀ: the largest column of n nᵀ gives the axis,
        # w = 2 sin θ·n its sign
        Rn = R[near_pi]
        c = cos_t[near_pi][..., None, None]
        S = ((Rn + np.swapaxes(Rn, -1, -2)) / 2.0 - c * np.eye(3)) / (1.0 - c)
        diag = np.einsum("...ii->...i", S)
        k = np.argmax(diag, axis=-1)
        col = np.take_along_axis(S, k[..., None, None], axis=-1)[..., 0]
        axis = col / np.linalg.norm(col, axis=-1, keepdims=True)
        sign = np.where(np.einsum("...i,...i->...", axis, w[near_pi]) < 0, -1.0, 1.0)
        out[near_pi] = axis * (sign * theta[near_pi])[..., None]
    return out


def wrap_pi(angle_rad):
    """Wrap to (−π, π]."""
    a = np.asarray(angle_rad, dtype=float)
    return np.pi - np.mod(np.pi - a, 2.0 * np.pi)


def wrap_2pi(angle_rad):
    """Wrap to [0, 2π)."""
    a = np.mod(np.asarray(angle_rad, dtype=float), 2.0 * np.pi)
    return np.where(a < 2.0 * np.pi, a, 0.0)[()]  # a tiny negative angle rounds up to 2π


# ---------------------------------------------------------------------------------------------
# Geodesy: geodetic (WGS84, ellipsoidal height) ↔ ECEF (pyproj) ↔ LGF (NED).
# ---------------------------------------------------------------------------------------------


class _Geocentric:
    """Lazily built pyproj transformers EPSG:4979 (lat, lon, h) ↔ EPSG:4978 (ECEF)."""

    _fwd = None
    _inv = None

    @classmethod
    def forward(cls):
        if cls._fwd is None:
            from pyproj import Transformer

            cls._fwd = Transformer.from_crs("EPSG:4979", "EPSG:4978", always_xy=True)
        return cls._fwd

    @classmethod
    def inverse(cls):
        if cls._inv is None:
            from pyproj import Transformer

            cls._inv = Transformer.from_crs("EPSG:4978", "EPSG:4979", always_xy=True)
        return cls._inv


def geodetic_to_ecef(lat_deg, lon_deg, height_m) -> np.ndarray:
    """(n,) arrays of WGS84 latitude, longitude (degrees) and ellipsoidal height → (n, 3) ECEF."""
    x, y, z = _Geocentric.forward().transform(
        np.asarray(lon_deg, dtype=float),
        np.asarray(lat_deg, dtype=float),
        np.asarray(height_m, dtype=float),
    )
    return np.stack([np.asarray(x), np.asarray(y), np.asarray(z)], axis=-1)


def ecef_to_geodetic(p_ecef_m) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    p = np.asarray(p_ecef_m, dtype=float)
    lon, lat, h = _Geocentric.inverse().transform(p[..., 0], p[..., 1], p[..., 2])
    return np.asarray(lat), np.asarray(lon), np.asarray(h)


def ecef_to_ned_matrix(lat_deg: float, lon_deg: float) -> np.ndarray:
    """``R_e^n``: rotates ECEF vectors into the NED frame at (lat, lon)."""
    lat, lon = np.radians(lat_deg), np.radians(lon_deg)
    sl, cl = np.sin(lat), np.cos(lat)
    so, co = np.sin(lon), np.cos(lon)
    return np.array(
        [
            [-sl * co, -sl * so, cl],
            [-so, co, 0.0],
            [-cl * co, -cl * so, -sl],
        ]
    )


@dataclass(frozen=True)
class LocalFrame:
    """The LGF: a NED tangent frame at a reference point (docs/architecture.md §3)."""

    lat_deg: float
    lon_deg: float
    height_m: float = 0.0

    @cached_property
    def origin_ecef_m(self) -> np.ndarray:
        return geodetic_to_ecef([self.lat_deg], [self.lon_deg], [self.height_m])[0]

    @cached_property
    def r_ecef_to_ned(self) -> np.ndarray:
        return ecef_to_ned_matrix(self.lat_deg, self.lon_deg)

    def to_lgf(self, lat_deg, lon_deg, height_m) -> np.ndarray:
        """Geodetic → (n, 3) NED metres relative to the reference point."""
        d = geodetic_to_ecef(lat_deg, lon_deg, height_m) - self.origin_ecef_m
        return d @ self.r_ecef_to_ned.T

    def to_geodetic(self, p_lgf_m) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(n, 3) NED metres → latitude, longitude (degrees), ellipsoidal height (m)."""
        p = np.asarray(p_lgf_m, dtype=float)
        return ecef_to_geodetic(p @ self.r_ecef_to_ned + self.origin_ecef_m)

    @classmethod
    def at_mean(cls, lat_deg, lon_deg, height_m) -> LocalFrame:
        """The thesis's default reference: the mean of the trajectory's coordinates."""
        return cls(float(np.mean(lat_deg)), float(np.mean(lon_deg)), float(np.mean(height_m)))

    def as_dict(self) -> dict:
        return {"lat_deg": self.lat_deg, "lon_deg": self.lon_deg, "height_m": self.height_m}


def utm_epsg(lat_deg: float, lon_deg: float) -> int:
    """EPSG code of the WGS84 UTM zone containing (lat, lon) (Norway/Svalbard exceptions ignored)."""
    zone = int(np.floor((lon_deg + 180.0) / 6.0)) % 60 + 1
    return (32600 if lat_deg >= 0 else 32700) + zone


# ---------------------------------------------------------------------------------------------
# GPS time.
# ---------------------------------------------------------------------------------------------

GPS_EPOCH = _dt.datetime(1980, 1, 6, tzinfo=_dt.UTC)
UNIX_EPOCH = _dt.datetime(1970, 1, 1, tzinfo=_dt.UTC)
NS_PER_S = 1_000_000_000
SECONDS_PER_WEEK = 604_800
#: LAS "adjusted standard GPS time" is GPS seconds minus this offset.
LAS_GPS_OFFSET_S = 1e9


def leap_seconds_at_utc(utc: _dt.datetime) -> int:
    """GPS − UTC in seconds at a UTC instant (18 since 2017-01-01), from the leap-second table
    in use (:func:`calib.core.gpstime.leap_table`: IERS's list, with an expiry date)."""
    d = _as_utc(utc) - UNIX_EPOCH
    return leap_table().gps_minus_utc_at_unix_ns((d.days * 86_400 + d.seconds) * NS_PER_S)


def leap_seconds_at_gps_ns(gps_ns: int) -> int:
    """GPS − UTC in seconds at a GPS instant (during an inserted second, the count before it)."""
    return leap_table().gps_minus_utc_at_gps_ns(gps_ns)


def _as_utc(d: _dt.datetime) -> _dt.datetime:
    if d.tzinfo is None:
        raise ValueError(f"naive datetime {d!r}: give an explicit UTC timezone")
    return d.astimezone(_dt.UTC)


def utc_to_gps_ns(utc: _dt.datetime, extra_ns: int = 0) -> int:
    """UTC datetime (microsecond resolution) + optional extra nanoseconds → GPS ns."""
    utc = _as_utc(utc)
    delta = utc - GPS_EPOCH
    ns = (delta.days * 86_400 + delta.seconds) * NS_PER_S + delta.microseconds * 1_000 + extra_ns
    return ns + leap_seconds_at_utc(utc) * NS_PER_S


def utc_fields_to_gps_ns(
    year: int, month: int, day: int, seconds_of_day_ns: int, gps_minus_utc_s: int | None = None
) -> int:
    """UTC date + nanoseconds of the day → GPS ns (what NMEA ZDA/TIME__ and STDBIN UTC give).

    The day's GPS − UTC is that of its midnight, so 23:59:60.5 (86 400.5 s) on a day that ends
    with a leap second is the GPS instant 0.5 s into the inserted second. ``gps_minus_utc_s``:
    the offset the device says it applied (its UTC tags are undone with it) instead of the
    table's."""
    days = (_dt.date(year, month, day) - GPS_EPOCH_DATE).days
    leap = leap_table().gps_minus_utc_at_unix_ns((days * 86_400 + GPS_EPOCH_UNIX_S) * NS_PER_S)
    if gps_minus_utc_s is not None:
        leap = gps_minus_utc_s
    return days * 86_400 * NS_PER_S + int(seconds_of_day_ns) + leap * NS_PER_S


def gps_ns_to_utc(gps_ns: int) -> _dt.datetime:
    """GPS ns → UTC datetime (truncated to the microsecond; an inserted second 23:59:60.x, which
    a datetime cannot hold, reads as 00:00:00.x of the next day — use :func:`gps_ns_to_utc_fields`)."""
    gps_ns = int(gps_ns)
    utc_ns = gps_ns - leap_seconds_at_gps_ns(gps_ns) * NS_PER_S
    return GPS_EPOCH + _dt.timedelta(microseconds=utc_ns // 1_000)


def gps_ns_to_utc_fields(gps_ns: int, gps_minus_utc_s: int | None = None) -> tuple[_dt.date, int]:
    """GPS ns → (UTC date, ns of that day), the inverse of :func:`utc_fields_to_gps_ns`: the
    inserted second at the end of a leap-second day is 23:59:60.x of that day (86 400 s + x).
    ``gps_minus_utc_s``: convert with this offset instead of the table's (a device that
    believes another count)."""
    gps_ns = int(gps_ns)
    table = leap_table()
    if gps_minus_utc_s is None:
        leap = table.gps_minus_utc_at_gps_ns(gps_ns)
        inserted = table.leap_second_at_gps_ns(gps_ns)
    else:
        leap, inserted = gps_minus_utc_s, False
    days, tod = divmod(gps_ns - leap * NS_PER_S, 86_400 * NS_PER_S)
    if inserted:  # the count steps at the next midnight: the second before it is 23:59:60
        days, tod = days - 1, tod + 86_400 * NS_PER_S
    return GPS_EPOCH_DATE + _dt.timedelta(days=days), tod


@overload
def gps_ns_to_seconds(gps_ns: int | np.integer) -> float: ...
@overload
def gps_ns_to_seconds(gps_ns: np.ndarray) -> np.ndarray: ...
@overload
def gps_ns_to_seconds(gps_ns: npt.ArrayLike) -> np.ndarray | float: ...


def gps_ns_to_seconds(gps_ns: npt.ArrayLike) -> np.ndarray | float:
    """int64 ns → float64 seconds since the GPS epoch (exact to ~0.1 µs in this century)."""
    if np.isscalar(gps_ns):
        # np.isscalar's TypeGuard widens to every numpy scalar and complex; an integer here
        return int(gps_ns) / NS_PER_S  # type: ignore[arg-type]
    a = np.asarray(gps_ns, dtype=np.int64)
    whole = a // NS_PER_S
    return whole.astype(np.float64) + (a - whole * NS_PER_S).astype(np.float64) / NS_PER_S


@overload
def seconds_to_gps_ns(gps_s: float) -> int: ...
@overload
def seconds_to_gps_ns(gps_s: np.ndarray) -> np.ndarray: ...
@overload
def seconds_to_gps_ns(gps_s: npt.ArrayLike) -> np.ndarray | int: ...


def seconds_to_gps_ns(gps_s: npt.ArrayLike) -> np.ndarray | int:
    """float64 seconds → int64 ns since the GPS epoch (rounded to the nearest ns)."""
    if np.isscalar(gps_s):
        # np.isscalar's TypeGuard widens to every numpy scalar and complex; a real number here
        return int(round(float(gps_s) * NS_PER_S))  # type: ignore[arg-type]
    s = np.asarray(gps_s, dtype=np.float64)
    whole = np.floor(s)
    return whole.astype(np.int64) * NS_PER_S + np.round((s - whole) * NS_PER_S).astype(np.int64)


def gps_seconds_to_week_sow(gps_s):
    """GPS seconds → (week, seconds of week)."""
    s = np.asarray(gps_s, dtype=float)
    week = np.floor(s / SECONDS_PER_WEEK)
    sow = s - week * SECONDS_PER_WEEK
    if week.ndim == 0:
        return int(week), float(sow)
    return week.astype(np.int64), sow


def week_sow_to_gps_seconds(week, sow):
    return np.asarray(week, dtype=float) * SECONDS_PER_WEEK + np.asarray(sow, dtype=float)


def gps_seconds_to_las(gps_s):
    """GPS seconds → LAS adjusted standard GPS time."""
    return np.asarray(gps_s, dtype=float) - LAS_GPS_OFFSET_S


def las_to_gps_seconds(adjusted_s):
    return np.asarray(adjusted_s, dtype=float) + LAS_GPS_OFFSET_S
