"""What the Foxglove export (:mod:`office.jobs.foxglove`) puts in its messages, without the SDK.

Frames. The project works in NED (the LGF) and FRD (the body, docs/architecture.md §3); Foxglove's
3-D panel draws +z up, so the export hands it right-handed z-up frames:

- ``lgf_enu`` (:data:`WORLD_FRAME`): the LGF turned to east, north, up, same origin:
  ``p_enu = NED_TO_ENU · p_ned`` (x east, y north, z up);
- ``vessel`` (:data:`VESSEL_FRAME`): the body frame turned to FLU (x bow, y port, z up),
  ``v_flu = FRD_TO_FLU · v_frd``; its pose in ``lgf_enu`` is ``R = NED_TO_ENU · R_b^n ·
  FRD_TO_FLU`` and ``t = NED_TO_ENU · p^n``;
- ``scanner`` (:data:`SCANNER_FRAME`): the scanner frame S itself (scan plane = its y–z plane),
  placed in ``vessel`` by the mount: ``R = FRD_TO_FLU · R_S^b``, ``t = FRD_TO_FLU · a^b``.

Both flips are proper rotations (determinant +1), so every transform is a rotation Foxglove
accepts. Quaternions are (x, y, z, w), Foxglove's order.

Times. :class:`HostToGps` re-times a record logged while the clock model was UNLOCKED (its log
time is the free-running system clock's) through the GPS − host offsets of the records logged
LOCKED or in HOLDOVER around it (linear in host time between them, the nearest one's offset
beyond them); with none, the record keeps its log time. :func:`gps_to_unix_ns` turns a GPS time
into the file's time base, UTC as Unix ns (what Foxglove reads): ``gps_ns + (GPS_EPOCH_UNIX_S −
(GPS − UTC)) · 1e9``, GPS − UTC from the project's leap-second table at that instant (18 s since
2017-01-01); an inserted second (23:59:60.x), which Unix time cannot name, is held at
23:59:59.999999999 so that times never go back.

Messages: :func:`log_entry` (an ``/events`` record → Log level, name, text), :func:`clock_values`
and :func:`latency_values` (the plottable numbers of ``/clock`` and ``/latency`` records) with
their JSON schemas, :func:`pack_cloud` (the packed bytes of a point cloud).
"""

from __future__ import annotations

import json

import numpy as np

from calib.core.frames import leap_seconds_at_gps_ns
from calib.core.gpstime import GPS_EPOCH_UNIX_S, NS_PER_S, leap_table

WORLD_FRAME = "lgf_enu"
VESSEL_FRAME = "vessel"
SCANNER_FRAME = "scanner"

#: NED → ENU (x east, y north, z up) and FRD → FLU (x bow, y port, z up); each is its own inverse
NED_TO_ENU = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
FRD_TO_FLU = np.diag([1.0, -1.0, -1.0])


def enu_from_ned(p_ned_m: np.ndarray) -> np.ndarray:
    """(n, 3) NED → (n, 3) ENU, same origin."""
    p = np.asarray(p_ned_m, dtype=float)
    return np.column_stack([p[:, 1], p[:, 0], -p[:, 2]])


def quaternion_xyzw(r: np.ndarray) -> np.ndarray:
    """Rotation matrices (n, 3, 3) or (3, 3) → unit quaternions (n, 4) or (4,), (x, y, z, w), w ≥ 0."""
    from scipy.spatial.transform import Rotation

    q = Rotation.from_matrix(r).as_quat()  # scalar last
    return q * np.where(q[..., 3:] < 0, -1.0, 1.0)


def vessel_pose_enu(p_lgf_m: np.ndarray, r_b_n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The ``vessel`` frame in ``lgf_enu`` at each epoch: translation (n, 3) m, quaternion (n, 4)."""
    r = NED_TO_ENU @ np.asarray(r_b_n) @ FRD_TO_FLU
    return enu_from_ned(p_lgf_m), quaternion_xyzw(r)


def scanner_pose_flu(lever_arm_m: np.ndarray, r_s_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The ``scanner`` frame (S) in ``vessel`` (FLU): translation (3,) m, quaternion (4,)."""
    return FRD_TO_FLU @ np.asarray(lever_arm_m, float), quaternion_xyzw(FRD_TO_FLU @ np.asarray(r_s_b))


# -- times --------------------------------------------------------------------------------------


class HostToGps:
    """Host monotonic ns → GPS ns, from (host_ns, gps_ns) pairs of records logged LOCKED or in
    HOLDOVER (module docstring)."""

    def __init__(self, host_ns: list[int], gps_ns: list[int]) -> None:
        h = np.asarray(host_ns, dtype=np.int64)
        off = np.asarray(gps_ns, dtype=np.int64) - h
        order = np.argsort(h, kind="stable")
        self.host, self.offset = h[order], off[order]

    def gps_ns(self, host_ns: int, log_time_ns: int) -> int:
        """GPS time of a host stamp; ``log_time_ns`` when there is no pair to go by."""
        if not self.host.size:
            return log_time_ns
        base = int(self.offset[0])  # interpolate the small differences: float64 keeps them exact
        rel = np.interp(float(host_ns), self.host.astype(float), (self.offset - base).astype(float))
        return host_ns + base + round(float(rel))


def gps_to_unix_ns(gps_ns: int) -> tuple[int, int]:
    """GPS ns → (UTC as Unix ns, the GPS − UTC seconds used), by the leap-second table in use;
    inside an inserted second the last nanosecond before it (module docstring)."""
    gps_ns = int(gps_ns)
    leap = leap_seconds_at_gps_ns(gps_ns)
    unix_ns = gps_ns + (GPS_EPOCH_UNIX_S - leap) * NS_PER_S
    if leap_table().leap_second_at_gps_ns(gps_ns):  # 23:59:60.x reads as 00:00:00.x: hold it
        unix_ns -= unix_ns % NS_PER_S + 1
    return unix_ns, leap


# -- log messages -------------------------------------------------------------------------------

#: Foxglove Log levels by name (foxglove.messages.LogLevel)
LEVELS = ("UNKNOWN", "DEBUG", "INFO", "WARNING", "ERROR", "FATAL")
_SEVERITY_LEVEL = {"info": "INFO", "warning": "WARNING", "critical": "ERROR"}
_WARNING_EVENTS = {"disconnected", "data_gap", "host_clock_step"}
_SKIP_KEYS = {"event", "device", "traceback"}


def _short(v) -> str:
    text = v if isinstance(v, str) else json.dumps(v, separators=(",", ":"), default=str)
    return text if len(text) <= 160 else text[:157] + "..."


def log_entry(data: dict) -> tuple[str, str, str]:
    """An ``/events`` record → (Log level name, name, message).

    Alarms: raised at the level of their severity (info INFO, warning WARNING, critical ERROR),
    cleared at INFO; name = the alarm's device. Clock states: INFO when it locks, WARNING
    otherwise; name ``clock``. Failures (``*_failed``, ``internal_error``) ERROR; disconnections
    and data gaps WARNING; everything else (session start/end, connections, pass marks,
    rotations) INFO. Name: the event's device, else its source, else ``daemon``.
    """
    event = str(data.get("event", "?"))
    if event == "alarm":
        raised = data.get("action") == "raise"
        severity = str(data.get("severity", "warning"))
        level = _SEVERITY_LEVEL.get(severity, "WARNING") if raised else "INFO"
        what = f"raised ({severity})" if raised else "cleared"
        return (
            level,
            str(data.get("device", "daemon")),
            f"alarm {data.get('name')} {what}: {data.get('message')}",
        )
    if event == "clock_state":
        to = data.get("to")
        level = "INFO" if to == "LOCKED" else "WARNING"
        bound = data.get("error_bound_us")
        extra = f" (error bound {bound} us)" if bound is not None else ""
        return level, "clock", f"clock {data.get('from')} -> {to}{extra}"
    if event.endswith("_failed") or event == "internal_error":
        level = "ERROR"
    elif event in _WARNING_EVENTS:
        level = "WARNING"
    else:
        level = "INFO"
    name = str(data.get("device") or data.get("source") or "daemon")
    fields = [
        f"{k}={_short(v)}"
        for k, v in data.items()
        if k not in _SKIP_KEYS and not k.endswith("_host_ns") and v is not None
    ]
    return level, name, event + (": " + ", ".join(fields) if fields else "")


# -- plottable numbers --------------------------------------------------------------------------

CLOCK_STATE_CODE = {"UNLOCKED": 0, "HOLDOVER": 1, "LOCKED": 2}
_NUM = {"type": ["number", "null"]}
_INT = {"type": ["integer", "null"]}

CLOCK_SCHEMA = {
    "title": "mls.ClockPlot",
    "type": "object",
    "description": "The daemon's clock model (/clock of the session), as numbers to plot",
    "properties": {
        "state": {"enum": list(CLOCK_STATE_CODE)},
        "state_code": {"type": "integer", "description": "0 UNLOCKED, 1 HOLDOVER, 2 LOCKED"},
        "error_bound_us": _NUM,
        "drift_ppm": _NUM,
        "jitter_rms_us": _NUM,
        "jitter_max_us": _NUM,
        "offset_drift_us": {
            **_NUM,
            "description": "GPS - host offset minus that of the first LOCKED record (null: UNLOCKED)",
        },
        "last_edge_age_s": _NUM,
        "edges_in_window": _INT,
        "steps": _INT,
        "pps_time_latency_ms": _NUM,
    },
}


def _num(v) -> float | None:
    return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else None


def _int(v) -> int | None:
    return int(v) if isinstance(v, int) and not isinstance(v, bool) else None


def clock_values(data: dict, locked_offset_ns: int | None) -> dict:
    """A ``/clock`` record → :data:`CLOCK_SCHEMA`'s numbers (``locked_offset_ns``: the offset of
    the session's first LOCKED record, None when it never locked)."""
    state = str(data.get("state", "UNLOCKED"))
    off = _int(data.get("offset_ns"))
    drift = None
    if state != "UNLOCKED" and off is not None and locked_offset_ns is not None:
        drift = (off - locked_offset_ns) / 1e3
    pps_doc = data.get("pps")
    pps = pps_doc if isinstance(pps_doc, dict) else {}
    return {
        "state": state if state in CLOCK_STATE_CODE else "UNLOCKED",
        "state_code": CLOCK_STATE_CODE.get(state, 0),
        "error_bound_us": _num(data.get("error_bound_us")),
        "drift_ppm": _num(data.get("drift_ppm")),
        "jitter_rms_us": _num(data.get("jitter_rms_us")),
        "jitter_max_us": _num(data.get("jitter_max_us")),
        "offset_drift_us": drift,
        "last_edge_age_s": _num(data.get("last_edge_age_s")),
        "edges_in_window": _int(data.get("edges_in_window")),
        "steps": _int(data.get("steps")),
        "pps_time_latency_ms": _num(pps.get("time_latency_ms")),
    }


LATENCY_NUMBERS = (
    "latency_mean_ms",
    "latency_sigma_ms",
    "latency_p99_ms",
    "latency_max_ms",
    "baseline_ms",
    "drift_ppm",
    "drift_sigma_ppm",
    "rate_hz",
    "last_age_s",
)
LATENCY_COUNTS = ("n", "records")


def latency_schema(devices: list[str]) -> dict:
    """The JSON schema of the ``/latency`` messages: one object per device."""
    device = {
        "type": "object",
        "properties": {
            "sync": {"type": ["string", "null"]},
            **{k: _NUM for k in LATENCY_NUMBERS},
            **{k: _INT for k in LATENCY_COUNTS},
        },
    }
    return {
        "title": "mls.LatencyPlot",
        "type": "object",
        "description": "Per-device latency of the session's /latency (GPS time of receipt - device tag)",
        "properties": {name: device for name in devices},
    }


def latency_values(data: dict) -> dict:
    """A ``/latency`` record → device → its numbers (:func:`latency_schema`)."""
    out = {}
    for name, d in sorted(data.items()):
        if not isinstance(d, dict):
            continue
        sync = d.get("sync")
        out[str(name)] = {
            "sync": sync if isinstance(sync, str) else None,
            **{k: _num(d.get(k)) for k in LATENCY_NUMBERS},
            **{k: _int(d.get(k)) for k in LATENCY_COUNTS},
        }
    return out


# -- point clouds -------------------------------------------------------------------------------

#: the packed point: x, y, z (m, relative to the cloud's origin, in ``lgf_enu``) and intensity
POINT_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4")])


def pack_cloud(p_enu_m: np.ndarray, intensity: np.ndarray) -> tuple[np.ndarray, bytes]:
    """Points (n, 3) ENU m and their intensities → (origin (3,) m, packed bytes): the origin is the
    points' mean rounded to the metre (the cloud's pose), the packed coordinates float32 offsets
    from it (a few µm steps at survey distances, where absolute float32 would step by mm)."""
    p = np.asarray(p_enu_m, dtype=float)
    origin = np.round(p.mean(axis=0)) if len(p) else np.zeros(3)
    rec = np.empty(len(p), POINT_DTYPE)
    d = p - origin
    rec["x"], rec["y"], rec["z"] = d[:, 0], d[:, 1], d[:, 2]
    rec["intensity"] = intensity
    return origin, rec.tobytes()
