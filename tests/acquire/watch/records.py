"""Record streams for the mount watch's tests (not a test module): the ``nav`` / ``profile`` /
``event`` records a daemon tap hands over, made from a simulation or from a synthetic track."""

from __future__ import annotations

import math

import numpy as np

from calib.core import frames
from calib.core.trajectory import Trajectory
from calib.io.bundle import ScanPoints
from drivers.hydrins.nav import NavRecord
from drivers.zf.codec import Profile

NS = 1_000_000_000
SIG = (0.02, 0.02, 0.03, math.radians(0.01), math.radians(0.01), math.radians(0.02))


def nav_record(
    t_s: float, lat: float, lon: float, h: float, rpy, v_ne=(math.nan, math.nan), sig=SIG
) -> NavRecord:
    return NavRecord(
        source="test",
        gps_ns=round(t_s * NS),
        lat_deg=float(lat),
        lon_deg=float(lon),
        height_m=float(h),
        roll_rad=float(rpy[0]),
        pitch_rad=float(rpy[1]),
        heading_rad=float(rpy[2]),
        v_north_m_s=float(v_ne[0]),
        v_east_m_s=float(v_ne[1]),
        sigma_north_m=sig[0],
        sigma_east_m=sig[1],
        sigma_down_m=sig[2],
        sigma_roll_rad=sig[3],
        sigma_pitch_rad=sig[4],
        sigma_heading_rad=sig[5],
    )


def nav_stream(traj: Trajectory, step: int = 1) -> list[tuple[float, str, NavRecord]]:
    """``(t, "nav", record)`` for every ``step``-th epoch of a trajectory."""
    lat, lon, h = traj.geodetic()
    t = traj.t_gps_s
    v = np.gradient(traj.p_lgf_m, t, axis=0)
    sig = (
        np.hstack([traj.sigma_p_m, traj.sigma_rpy_rad])
        if traj.has_sigmas
        else np.tile(np.asarray(SIG), (t.size, 1))
    )
    return [
        (float(t[i]), "nav", nav_record(t[i], lat[i], lon[i], h[i], traj.rpy_rad[i], v[i, :2], tuple(sig[i])))
        for i in range(0, t.size, step)
    ]


def profile(t_ns: np.ndarray, range_m: np.ndarray, angle_rad: np.ndarray, counter: int = 0) -> Profile:
    n = t_ns.size
    return Profile(
        counter,
        np.asarray(t_ns, np.int64),
        np.asarray(angle_rad, float),
        np.asarray(range_m, float),
        np.zeros(n, np.uint16),
        packets_received=1,
        packet_count=1,
    )


def profile_stream(points: ScanPoints, rate_hz: float) -> list[tuple[float, str, Profile]]:
    """The returns cut into profiles of ``1/rate_hz`` s, ``(t of the last return, "profile",
    profile)``."""
    t = points.t_gps_s
    order = np.argsort(t, kind="stable")
    t = t[order]
    k = np.floor((t - t[0]) * rate_hz).astype(np.int64)
    cuts = np.flatnonzero(np.diff(k)) + 1
    out = []
    for n, idx in enumerate(np.split(order, cuts)):
        tt = points.t_gps_s[idx]
        t_ns = np.rint(tt * 1e9).astype(np.int64)
        out.append(
            (float(tt[-1]), "profile", profile(t_ns, points.range_m[idx], points.scan_angle_rad[idx], n))
        )
    return out


def mark_stream(points: ScanPoints, margin_s: float = 0.3) -> list[tuple[float, str, dict]]:
    """``pass_start`` / ``pass_end`` events around each pass of ``points``."""
    out = []
    for pid in points.pass_ids():
        t = points.t_gps_s[points.pass_id == pid]
        out.append((float(t.min()) - margin_s, "event", {"event": "pass_start", "pass_id": pid}))
        out.append((float(t.max()) + margin_s, "event", {"event": "pass_end", "pass_id": pid}))
    return out


def merged(*streams) -> list[tuple[str, object, int]]:
    """The streams in time order as tap items ``(kind, record, gps_ns)`` (at one time: nav,
    then events, then profiles)."""
    rank = {"nav": 0, "event": 1, "profile": 2}
    items = sorted((x for s in streams for x in s), key=lambda x: (x[0], rank[x[1]]))
    return [(kind, rec, round(t * NS)) for t, kind, rec in items]


def track(
    frame: frames.LocalFrame,
    legs: list[tuple[float, float, float]],
    t0_s: float = 1.4e9,
    rate_hz: float = 10.0,
    turn_rate_deg_s: float = 12.0,
) -> list[tuple[float, str, NavRecord]]:
    """A synthetic vessel track: ``legs`` of (heading °, speed m/s, duration s), joined by turns at
    ``turn_rate_deg_s`` (at the same speed) — ``(t, "nav", record)`` at ``rate_hz``."""
    out = []
    t, p, h = t0_s, np.zeros(3), math.radians(legs[0][0])
    dt = 1.0 / rate_hz

    def emit(speed: float) -> None:
        nonlocal t, p
        v = speed * np.array([math.cos(h), math.sin(h), 0.0])
        lat, lon, hh = frame.to_geodetic(p[None, :])
        out.append((t, "nav", nav_record(t, lat[0], lon[0], hh[0], (0.0, 0.0, h % (2 * math.pi)), v[:2])))
        p = p + v * dt
        t += dt

    for heading, speed, duration in legs:
        target = math.radians(heading)
        step = math.radians(turn_rate_deg_s) * dt
        while abs(frames.wrap_pi(target - h)) > step:  # turn to starboard
            h += step
            emit(speed)
        h = target
        for _ in range(round(duration * rate_hz)):
            emit(speed)
    return out


def write_result(path, boresight_deg, extras: dict | None = None):
    """A calibration ``result.json`` with this boresight (canonical roll, pitch, yaw, degrees)
    and these extras (``{name: value}``), as ``mls calib run`` writes it (the fields the
    history and the watch read)."""
    import json
    from pathlib import Path

    r, p, y = (float(x) for x in boresight_deg)
    doc = {
        "boresight_deg": {"roll": r, "pitch": p, "yaw": y},
        "sigma_deg": {"roll": 0.002, "pitch": 0.002, "yaw": 0.004},
        "sigma_scaled_deg": {"roll": 0.002, "pitch": 0.002, "yaw": 0.004},
        "sigma_realistic_deg": {"roll": 0.004, "pitch": 0.004, "yaw": 0.008},
        "correlation": [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        "sigma0_squared": 1.0,
        "n_points": 100000,
        "software_version": "test",
        "extras": {k: {"value": v, "sigma": 0.0} for k, v in (extras or {}).items()},
    }
    path = Path(path)
    path.write_text(json.dumps(doc))
    return path
