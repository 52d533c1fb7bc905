"""The Foxglove channels of the vessel, in one SDK context, and their messages:

============== ======================== =========================================================
topic          schema                   content
============== ======================== =========================================================
/vessel/fix    foxglove.LocationFix     an INS epoch: latitude, longitude, ellipsoidal height;
                                        position covariance (ENU, diagonal) from its sigmas when
                                        it has them; frame ``vessel``
/tf            foxglove.FrameTransform  ``lgf_enu`` → ``vessel`` (the INS pose) and ``vessel`` →
                                        ``scanner`` (the mount)
/lidar/points  foxglove.PointCloud      the profiler's returns georeferenced in ``lgf_enu``, one
                                        cloud per window (:mod:`acquire.foxglove.clouds`):
                                        x, y, z, intensity float32
/log           foxglove.Log             the /events records: alarms at their severity, clock
                                        states, connections, gaps, pass marks, failures
/clock         mls.ClockPlot (JSON)     the clock model's numbers
/latency       mls.LatencyPlot (JSON)   per device latency mean/σ/p99/max, drift, rate
============== ======================== =========================================================

:class:`Channels` takes every message's GPS ns and logs it at its UTC Unix ns
(:func:`acquire.foxglove.frames.gps_to_unix_ns`), the message's timestamp the same number; it
counts the messages and the GPS − UTC seconds used. Where they go is the context's sink: an MCAP
file (:mod:`office.jobs.foxglove`) or the live WebSocket server (:mod:`acquire.foxglove.live`).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from acquire.foxglove import frames as ff
from acquire.log.schema import dumps

NS_PER_S = 1_000_000_000

TOPIC_FIX, TOPIC_TF, TOPIC_POINTS = "/vessel/fix", "/tf", "/lidar/points"
TOPIC_LOG, TOPIC_CLOCK, TOPIC_LATENCY = "/log", "/clock", "/latency"
TOPICS = (TOPIC_FIX, TOPIC_TF, TOPIC_POINTS, TOPIC_LOG, TOPIC_CLOCK, TOPIC_LATENCY)
SCHEMAS = {
    TOPIC_FIX: "foxglove.LocationFix",
    TOPIC_TF: "foxglove.FrameTransform",
    TOPIC_POINTS: "foxglove.PointCloud",
    TOPIC_LOG: "foxglove.Log",
    TOPIC_CLOCK: "mls.ClockPlot",
    TOPIC_LATENCY: "mls.LatencyPlot",
}


def _stamp(unix_ns: int):
    from foxglove.messages import Timestamp

    return Timestamp(unix_ns // NS_PER_S, unix_ns % NS_PER_S)


def _vector3(v):
    from foxglove.messages import Vector3

    return Vector3(x=float(v[0]), y=float(v[1]), z=float(v[2]))


def _point_fields() -> list:
    from foxglove.messages import PackedElementField, PackedElementFieldNumericType

    f32 = PackedElementFieldNumericType.Float32
    dtype_fields, names = ff.POINT_DTYPE.fields, ff.POINT_DTYPE.names
    assert dtype_fields is not None and names is not None  # a structured dtype: fields in order
    return [PackedElementField(name=name, offset=dtype_fields[name][1], type=f32) for name in names]


def _covariance_enu(sig_ned_m) -> list[float] | None:
    """The diagonal ENU position covariance (row-major 3 × 3) of NED σ, None when unknown."""
    sig = np.asarray(sig_ned_m, float)
    if not (np.all(np.isfinite(sig)) and np.all(sig > 0)):
        return None
    cov = [0.0] * 9
    cov[0], cov[4], cov[8] = float(sig[1]) ** 2, float(sig[0]) ** 2, float(sig[2]) ** 2
    return cov


class Channels:
    """The six channels in the SDK ``context`` (its sink decides where they go); ``devices``: the
    device names of the ``/latency`` schema."""

    def __init__(self, context: Any, devices: list[str]) -> None:
        import foxglove
        from foxglove import channels as fc

        c = context
        self.fix = fc.LocationFixChannel(TOPIC_FIX, context=c)
        self.tf = fc.FrameTransformChannel(TOPIC_TF, context=c)
        self.points = fc.PointCloudChannel(TOPIC_POINTS, context=c)
        self.log = fc.LogChannel(TOPIC_LOG, context=c)
        self.clock = foxglove.Channel(TOPIC_CLOCK, schema=ff.CLOCK_SCHEMA, context=c)
        self.latency = foxglove.Channel(TOPIC_LATENCY, schema=ff.latency_schema(devices), context=c)
        self.counts = dict.fromkeys(TOPICS, 0)
        self.first_ns: int | None = None  # the first and last message, GPS ns
        self.last_ns: int | None = None
        self.leaps: set[int] = set()  # the GPS − UTC seconds used

    def _count(self, topic: str, t_ns: int) -> int:
        """Count a message at GPS ``t_ns``; its UTC Unix ns."""
        self.counts[topic] += 1
        self.first_ns = t_ns if self.first_ns is None else min(self.first_ns, t_ns)
        self.last_ns = t_ns if self.last_ns is None else max(self.last_ns, t_ns)
        unix_ns, leap = ff.gps_to_unix_ns(t_ns)
        self.leaps.add(leap)
        return unix_ns

    def transform(self, t_ns: int, parent: str, child: str, xyz, q) -> None:
        from foxglove.messages import FrameTransform, Quaternion

        u = self._count(TOPIC_TF, t_ns)
        msg = FrameTransform(
            timestamp=_stamp(u),
            parent_frame_id=parent,
            child_frame_id=child,
            translation=_vector3(xyz),
            rotation=Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])),
        )
        self.tf.log(msg, log_time=u)

    def fix_msg(self, t_ns: int, lat_deg: float, lon_deg: float, h_m: float, sig_ned_m) -> None:
        from foxglove.messages import LocationFix, LocationFixPositionCovarianceType

        cov = _covariance_enu(sig_ned_m)
        kind = LocationFixPositionCovarianceType
        u = self._count(TOPIC_FIX, t_ns)
        msg = LocationFix(
            timestamp=_stamp(u),
            frame_id=ff.VESSEL_FRAME,
            latitude=float(lat_deg),
            longitude=float(lon_deg),
            altitude=float(h_m),
            position_covariance=cov or [0.0] * 9,
            position_covariance_type=kind.Unknown if cov is None else kind.DiagonalKnown,
        )
        self.fix.log(msg, log_time=u)

    def cloud(self, t_ns: int, origin, packed: bytes) -> None:
        from foxglove.messages import PointCloud, Pose, Quaternion

        u = self._count(TOPIC_POINTS, t_ns)
        msg = PointCloud(
            timestamp=_stamp(u),
            frame_id=ff.WORLD_FRAME,
            pose=Pose(position=_vector3(origin), orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)),
            point_stride=ff.POINT_DTYPE.itemsize,
            fields=_point_fields(),
            data=packed,
        )
        self.points.log(msg, log_time=u)

    def event(self, t_ns: int, data: dict) -> None:
        """An ``/events`` record as a Log message (:func:`acquire.foxglove.frames.log_entry`)."""
        from foxglove.messages import Log, LogLevel

        level, name, text = ff.log_entry(data)
        u = self._count(TOPIC_LOG, t_ns)
        msg = Log(timestamp=_stamp(u), level=getattr(LogLevel, level.title()), message=text, name=name)
        self.log.log(msg, log_time=u)

    def clock_msg(self, t_ns: int, data: dict, locked_offset_ns: int | None) -> None:
        """A ``/clock`` record's numbers (:func:`acquire.foxglove.frames.clock_values`)."""
        u = self._count(TOPIC_CLOCK, t_ns)
        self.clock.log(dumps(ff.clock_values(data, locked_offset_ns)), log_time=u)

    def latency_msg(self, t_ns: int, data: dict) -> None:
        """A ``/latency`` record's numbers (:func:`acquire.foxglove.frames.latency_values`)."""
        u = self._count(TOPIC_LATENCY, t_ns)
        self.latency.log(dumps(ff.latency_values(data)), log_time=u)

    def record(self, t_ns: int, topic: str, data: dict, locked_offset_ns: int | None) -> None:
        """A session record of ``/events``, ``/clock`` or ``/latency`` (others are not drawn)."""
        if topic == "/events":
            self.event(t_ns, data)
        elif topic == "/clock":
            self.clock_msg(t_ns, data, locked_offset_ns)
        elif topic == "/latency":
            self.latency_msg(t_ns, data)
