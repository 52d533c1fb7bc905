"""Applanix SBET trajectories and their SMRMSG accuracy files (POSPac post-processed output).

Both are headerless sequences of little-endian float64 records:

- **SBET** (17 × 8 = 136 bytes): time (GPS seconds of the week), latitude, longitude (rad),
  height (m, ellipsoidal), x/y/z velocity (m/s, wander frame), roll, pitch, platform heading,
  wander angle (rad), x/y/z body acceleration (m/s²), x/y/z body angular rate (rad/s).
  True heading = platform heading − wander angle. Roll + starboard down, pitch + bow up, heading
  clockwise from north: the project's canonical convention (docs/architecture.md §3).
- **SMRMSG** (10 × 8 = 80 bytes): time (seconds of the week), north/east/down position RMS (m),
  north/east/down velocity RMS (m/s), roll/pitch/heading RMS (arc-minutes). Usually at a lower
  rate than the SBET, and records may come out of time order.

Times are seconds of the GPS week; the week itself is not in the files, so the caller gives it
(or a GPS time near the data, from which it is inferred). A trajectory that crosses the end of a
week wraps from 604800 to 0; the wrap is undone.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from calib.core import frames
from calib.core.errors import CalibError, read_file
from calib.core.trajectory import Trajectory, TrajectoryError

SBET_FIELDS = (
    "time_sow",
    "lat_rad",
    "lon_rad",
    "height_m",
    "vel_x_mps",
    "vel_y_mps",
    "vel_z_mps",
    "roll_rad",
    "pitch_rad",
    "platform_heading_rad",
    "wander_rad",
    "acc_x_mps2",
    "acc_y_mps2",
    "acc_z_mps2",
    "rate_x_radps",
    "rate_y_radps",
    "rate_z_radps",
)
SMRMSG_FIELDS = (
    "time_sow",
    "sigma_north_m",
    "sigma_east_m",
    "sigma_down_m",
    "sigma_vel_north_mps",
    "sigma_vel_east_mps",
    "sigma_vel_down_mps",
    "sigma_roll_arcmin",
    "sigma_pitch_arcmin",
    "sigma_heading_arcmin",
)
#: One record each; ``np.zeros(n, SBET_DTYPE)`` makes n records to fill.
SBET_DTYPE = np.dtype([(name, "<f8") for name in SBET_FIELDS])
SMRMSG_DTYPE = np.dtype([(name, "<f8") for name in SMRMSG_FIELDS])
assert SBET_DTYPE.itemsize == 136
assert SMRMSG_DTYPE.itemsize == 80

_WEEK_S = frames.SECONDS_PER_WEEK
_ARCMIN_RAD = np.pi / (180.0 * 60.0)


class SbetError(CalibError, ValueError):
    """An SBET or SMRMSG file is unreadable or inconsistent (the message names the file)."""


# -- records ------------------------------------------------------------------------------------


def _read_records(path: str | Path, dtype: np.dtype, kind: str) -> np.ndarray:
    assert dtype.names is not None  # a structured record dtype (SBET_DTYPE, SMRMSG_DTYPE)
    path = Path(path)
    raw = read_file(path, SbetError, expected=f"an {kind} file")
    if len(raw) % dtype.itemsize:
        raise SbetError(
            f"{path}: size {len(raw)} bytes is not a multiple of the {kind} record size "
            f"({dtype.itemsize} bytes = {len(dtype.names)} float64); the file is truncated or "
            f"not an {kind} file"
        )
    records = np.frombuffer(raw, dtype=dtype).copy()
    for name in dtype.names:
        bad = ~np.isfinite(records[name])
        if bad.any():
            i = int(np.argmax(bad))
            raise SbetError(
                f"{path}: record {i} (byte {i * dtype.itemsize}): {name} is "
                f"{float(records[name][i])!r}, expected a finite number"
            )
    bad = (records["time_sow"] < 0) | (records["time_sow"] > _WEEK_S)
    if bad.any():
        i = int(np.argmax(bad))
        t = float(records["time_sow"][i])
        raise SbetError(
            f"{path}: record {i}: time {t!r} s is not a GPS second of the week "
            f"(0 … {_WEEK_S}); not an {kind} file?"
        )
    return records


def read_sbet(path: str | Path) -> np.ndarray:
    """All records of an SBET file as a structured array with fields :data:`SBET_FIELDS`."""
    records = _read_records(path, SBET_DTYPE, "SBET")
    bad = (np.abs(records["lat_rad"]) > np.pi / 2) | (np.abs(records["lon_rad"]) > 2 * np.pi)
    if bad.any():
        i = int(np.argmax(bad))
        lat, lon = float(records["lat_rad"][i]), float(records["lon_rad"][i])
        raise SbetError(
            f"{path}: record {i}: latitude {lat!r} rad, longitude {lon!r} rad are "
            f"out of range; not an SBET file?"
        )
    return records


def write_sbet(path: str | Path, records: np.ndarray) -> None:
    """Write SBET records (a structured array of :data:`SBET_DTYPE`)."""
    Path(path).write_bytes(_checked(records, SBET_DTYPE).tobytes())


def read_smrmsg(path: str | Path) -> np.ndarray:
    """All records of an SMRMSG file, in file order (fields :data:`SMRMSG_FIELDS`)."""
    records = _read_records(path, SMRMSG_DTYPE, "SMRMSG")
    for name in SMRMSG_FIELDS[1:]:
        v = records[name]
        bad = v < 0
        if bad.any():
            i = int(np.argmax(bad))
            raise SbetError(f"{path}: record {i}: {name} is {float(v[i])!r}, expected ≥ 0")
    return records


def write_smrmsg(path: str | Path, records: np.ndarray) -> None:
    """Write SMRMSG records (a structured array of :data:`SMRMSG_DTYPE`)."""
    Path(path).write_bytes(_checked(records, SMRMSG_DTYPE).tobytes())


def _checked(records, dtype: np.dtype) -> np.ndarray:
    records = np.asarray(records)
    if records.dtype != dtype:  # structured casts go by position, not by name: refuse them
        raise ValueError(f"records must have dtype {dtype}, got {records.dtype}")
    return records


# -- GPS week -----------------------------------------------------------------------------------


def infer_week(first_sow: float, near_gps_s: float) -> int:
    """The GPS week that puts a file starting at ``first_sow`` closest to ``near_gps_s`` (e.g.
    the first point's time); right when the two are less than half a week apart, also when the
    file starts in the week before the point (or after it)."""
    return int(round((float(near_gps_s) - float(first_sow)) / _WEEK_S))


def sow_to_gps_seconds(sow, week: int, start_sow: float) -> np.ndarray:
    """Seconds of the week → GPS seconds, for data that start at ``start_sow`` in ``week`` and
    last less than half a week: times more than half a week before the start belong to the next
    week (a file that crosses the end of a week wraps to 0)."""
    sow = np.asarray(sow, dtype=float)
    wrapped = sow < start_sow - _WEEK_S / 2
    return week * float(_WEEK_S) + sow + np.where(wrapped, float(_WEEK_S), 0.0)


# -- trajectories -------------------------------------------------------------------------------


def read_sbet_trajectory(
    path: str | Path,
    frame: frames.LocalFrame | None = None,
    max_gap_s: float = 1.0,
    week: int | None = None,
    *,
    near_gps_s: float | None = None,
    smrmsg_path: str | Path | None = None,
) -> Trajectory:
    """A :class:`Trajectory` from an SBET file (and its SMRMSG sigmas when given).

    ``week``: the GPS week of the first record; when None it is inferred from ``near_gps_s``
    (a GPS time near the data, e.g. the first point's), and one of the two must be given.
    ``frame``: the LGF; default the mean position. SMRMSG sigmas are interpolated linearly to
    the SBET epochs; an SBET epoch farther than ``max_gap_s`` outside the SMRMSG's time span is an
    error.
    """
    path = Path(path)
    rec = read_sbet(path)
    if rec.size < 2:
        raise SbetError(f"{path}: {rec.size} records, a trajectory needs at least 2")
    start_sow = float(rec["time_sow"][0])
    if week is None:
        if near_gps_s is None:
            raise SbetError(
                f"{path}: SBET times are seconds of the GPS week; give the week, or "
                f"a GPS time near the data to infer it from"
            )
        week = infer_week(start_sow, near_gps_s)
    t = sow_to_gps_seconds(rec["time_sow"], week, start_sow)
    heading = frames.wrap_2pi(rec["platform_heading_rad"] - rec["wander_rad"])
    rpy = np.stack([rec["roll_rad"], rec["pitch_rad"], heading], axis=1)
    sig_p = sig_a = None
    if smrmsg_path is not None:
        sig_p, sig_a = _sigmas_at(Path(smrmsg_path), t, week, start_sow, max_gap_s)
    try:
        return Trajectory.from_geodetic(
            t,
            np.degrees(rec["lat_rad"]),
            np.degrees(rec["lon_rad"]),
            rec["height_m"],
            rpy,
            frame,
            sigma_p_m=sig_p,
            sigma_rpy_rad=sig_a,
            max_gap_s=max_gap_s,
            name=str(path),
        )
    except TrajectoryError as e:
        raise SbetError(f"{e} (epochs are the file's records, counted from 0)") from None


def _sigmas_at(path: Path, t: np.ndarray, week: int, start_sow: float, max_gap_s: float):
    """SMRMSG position (m) and attitude (rad) sigmas, sorted by time and interpolated to t."""
    rec = read_smrmsg(path)
    if rec.size == 0:
        raise SbetError(f"{path}: no records")
    ts = sow_to_gps_seconds(rec["time_sow"], week, start_sow)
    order = np.argsort(ts, kind="stable")
    ts, rec = ts[order], rec[order]
    keep = np.concatenate([[True], np.diff(ts) > 0])  # drop repeated epochs
    ts, rec = ts[keep], rec[keep]
    outside = (t < ts[0] - max_gap_s) | (t > ts[-1] + max_gap_s)
    if outside.any():
        raise SbetError(
            f"{path}: covers t = {ts[0]:.3f} … {ts[-1]:.3f} s but the SBET runs "
            f"{t[0]:.3f} … {t[-1]:.3f} s; {int(outside.sum())} SBET epochs are more than "
            f"{max_gap_s:g} s outside it"
        )

    def at(name):
        return np.interp(t, ts, rec[name])

    sig_p = np.stack([at("sigma_north_m"), at("sigma_east_m"), at("sigma_down_m")], axis=1)
    sig_a = (
        np.stack([at("sigma_roll_arcmin"), at("sigma_pitch_arcmin"), at("sigma_heading_arcmin")], axis=1)
        * _ARCMIN_RAD
    )
    return sig_p, sig_a


def sbet_records(traj: Trajectory, wander_rad=0.0) -> tuple[np.ndarray, int]:
    """(SBET records, GPS week) of a trajectory: time, position and attitude (with the given
    wander angle); velocities, accelerations and angular rates are left 0."""
    week, _ = frames.gps_seconds_to_week_sow(float(traj.t_gps_s[0]))
    lat, lon, h = traj.geodetic()
    rec = np.zeros(traj.t_gps_s.size, SBET_DTYPE)
    rec["time_sow"] = np.mod(traj.t_gps_s, _WEEK_S)
    rec["lat_rad"], rec["lon_rad"], rec["height_m"] = np.radians(lat), np.radians(lon), h
    rec["roll_rad"], rec["pitch_rad"] = traj.rpy_rad[:, 0], traj.rpy_rad[:, 1]
    rec["wander_rad"] = wander_rad
    rec["platform_heading_rad"] = frames.wrap_pi(traj.rpy_rad[:, 2] + rec["wander_rad"])
    return rec, week


def smrmsg_records(traj: Trajectory) -> np.ndarray:
    """SMRMSG records of a trajectory's sigmas (velocity RMS left 0)."""
    sig_p, sig_rpy = traj.sigma_p_m, traj.sigma_rpy_rad
    if sig_p is None or sig_rpy is None:  # not traj.has_sigmas
        raise ValueError(f"{traj.name}: the trajectory carries no sigmas")
    rec = np.zeros(traj.t_gps_s.size, SMRMSG_DTYPE)
    rec["time_sow"] = np.mod(traj.t_gps_s, _WEEK_S)
    for j, name in enumerate(("sigma_north_m", "sigma_east_m", "sigma_down_m")):
        rec[name] = sig_p[:, j]
    for j, name in enumerate(("sigma_roll_arcmin", "sigma_pitch_arcmin", "sigma_heading_arcmin")):
        rec[name] = sig_rpy[:, j] / _ARCMIN_RAD
    return rec
