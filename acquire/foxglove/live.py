"""Foxglove live: with ``web.foxglove_port`` the daemon serves the channels of ``mls export
--foxglove`` (:mod:`acquire.foxglove.channels`) on the Foxglove SDK's WebSocket server, so an
engineer on the ship's network opens the vessel live in Foxglove (``ws://HOST:PORT``, or
``wss://`` with the console's ``web.tls``).

:class:`LiveFeed` turns the daemon's records into the messages, at the rates a screen needs:

- every INS epoch to the next pose, at most ``pose_rate_hz`` (default 10 Hz): ``/vessel/fix``
  and ``/tf`` ``lgf_enu`` → ``vessel`` in the site's LGF (its reference point, else its targets'
  centre; without a site file the first epoch's position), the mount ``vessel`` → ``scanner``
  again every second (a client that connects later gets it too);
- the profiler's returns (0.3…119 m) gathered into clouds of 1/``cloud_rate_hz`` s
  (:class:`~acquire.foxglove.clouds.Clouds`, a cloud once the returns are 1 s past its window),
  georeferenced with the vessel config's mount by the trajectory of the last
  :data:`NAV_KEEP_S` s; each profile thinned beforehand to the share that keeps a window under
  ``max_points_per_cloud`` at the previous window's rate, so the cost stays bounded at the Z+F's
  full rate; without a mount in the vessel config there are no clouds (said once on ``/log``);
- every ``/events`` entry on ``/log``; the bus's ``clock`` on ``/clock`` and the latency of its
  ``metrics`` on ``/latency``.

Nothing is built while no client is subscribed to a channel (the SDK's ``has_sinks``). The
consumer (:class:`acquire.foxglove.daemon.FoxgloveConsumer`) runs the server in the daemon's process (its threads are
the SDK's), takes the record stream through its tap and the bus through a sink, and stops the
server when the supervisor stops it; a port that cannot be bound fails the consumer as any
(``consumer_failed``, retried with a back-off): the acquisition goes on.
"""

from __future__ import annotations

import json
import logging
import math
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np

from acquire.foxglove import frames as ff
from acquire.foxglove.channels import Channels
from acquire.foxglove.clouds import Clouds

log = logging.getLogger("mls.acquire")

NS_PER_S = 1_000_000_000
NAV_KEEP_S = 10.0  # the trajectory the clouds are georeferenced with: the last seconds of epochs
MOUNT_EVERY_NS = NS_PER_S  # the mount's transform, again for clients that connect later


@dataclass(frozen=True, kw_only=True)
class LiveOptions:
    """What :class:`LiveFeed` draws: its LGF (None: the first epoch's position), the mount
    (None: no clouds), the ``/latency`` devices, and the rates."""

    frame: Any = None  # calib.core.frames.LocalFrame
    mount: Any = None  # calib.core.georef.Mount
    devices: tuple[str, ...] = ()
    pose_rate_hz: float = 10.0
    cloud_rate_hz: float = 2.0
    max_points_per_cloud: int = 50_000


class LiveFeed:
    """The daemon's records → the channels' messages (module docstring)."""

    def __init__(self, channels: Channels, options: LiveOptions) -> None:
        self.ch = channels
        self.options = options
        self.frame = options.frame
        m = options.mount  # the scanner in the vessel frame: the mount's transform, fixed
        self.scanner_pose = None if m is None else ff.scanner_pose_flu(m.lever_arm_m, m.r_s_b)
        self.nav: deque[tuple[float, ...]] = deque()  # (GPS s, lat, lon, h, roll, pitch, heading)
        period_ns = round(NS_PER_S / options.cloud_rate_hz)
        self.clouds = Clouds(period_ns, options.max_points_per_cloud, None, options.mount)
        self.pose_period_ns = round(NS_PER_S / options.pose_rate_hz)
        self.last_pose_ns = -(2**62)
        self.last_mount_ns = -(2**62)
        self.now_ns: int | None = None  # the newest GPS time seen
        self.locked_offset_ns: int | None = None
        self.stride = 1  # every k-th return of a profile kept (from the last window's rate)
        self._window: tuple[int, int] = (-1, 0)  # (window index, returns seen in it)
        self.said_no_mount = False

    # -- the record stream -------------------------------------------------------------------

    def feed(self, kind: str, record: Any, gps_ns: int | None) -> None:
        if gps_ns is not None:
            self.now_ns = gps_ns if self.now_ns is None else max(self.now_ns, gps_ns)
        if kind == "nav":
            self.on_nav(record)
        elif kind == "profile":
            self.on_profile(record)
        elif kind == "event" and self.now_ns is not None:
            self.ch.event(gps_ns if gps_ns is not None else self.now_ns, dict(record))

    def on_nav(self, rec) -> None:
        t_ns = rec.gps_ns
        row = (rec.lat_deg, rec.lon_deg, rec.height_m, rec.roll_rad, rec.pitch_rad, rec.heading_rad)
        if t_ns is None or not all(math.isfinite(v) for v in row):
            return
        if self.nav and t_ns / 1e9 <= self.nav[-1][0]:
            return  # not after the last epoch
        self.nav.append((t_ns / 1e9, *row))
        while self.nav[-1][0] - self.nav[0][0] > NAV_KEEP_S:  # bounded whatever is subscribed
            self.nav.popleft()
        if self.frame is None:
            from calib.core import frames

            self.frame = frames.LocalFrame(rec.lat_deg, rec.lon_deg, rec.height_m)
        if t_ns - self.last_pose_ns >= self.pose_period_ns:
            self.last_pose_ns = t_ns
            self._pose(t_ns, rec)

    def _pose(self, t_ns: int, rec) -> None:
        from calib.core import frames

        ch = self.ch
        if self.scanner_pose is not None and t_ns - self.last_mount_ns >= MOUNT_EVERY_NS:
            self.last_mount_ns = t_ns
            ch.transform(t_ns, ff.VESSEL_FRAME, ff.SCANNER_FRAME, *self.scanner_pose)
        if ch.tf.has_sinks():
            p = self.frame.to_lgf([rec.lat_deg], [rec.lon_deg], [rec.height_m])
            r = frames.rotation_zyx(rec.roll_rad, rec.pitch_rad, rec.heading_rad)
            xyz, q = ff.vessel_pose_enu(p, r[None])
            ch.transform(t_ns, ff.WORLD_FRAME, ff.VESSEL_FRAME, xyz[0], q[0])
        sig = (rec.sigma_north_m, rec.sigma_east_m, rec.sigma_down_m)
        ch.fix_msg(t_ns, rec.lat_deg, rec.lon_deg, rec.height_m, sig)

    def on_profile(self, prof) -> None:
        if self.options.mount is None:
            self._say_no_mount()
            return
        if not self.ch.points.has_sinks():
            return
        t, r, a, i = _returns(prof)
        if t.size == 0:
            return
        self._count_window(t)
        s = self.stride
        self.clouds.add(t[::s], r[::s], a[::s], i[::s])
        self._flush_clouds()

    def _count_window(self, t_ns: np.ndarray) -> None:
        """The returns of the current window; at a new window, the stride that keeps the next one
        under the cap at this one's rate."""
        k = int(t_ns[-1]) // self.clouds.period_ns
        window, seen = self._window
        if k != window:
            if window >= 0:
                self.stride = max(1, math.ceil(seen / self.options.max_points_per_cloud))
            window, seen = k, 0
        self._window = (window, seen + int(t_ns.size))

    def _flush_clouds(self) -> None:
        if not self.clouds.due():
            return  # no trajectory built for a profile that completes no window
        traj = self._trajectory()
        if traj is None:
            return
        self.clouds.traj = traj
        for t_ns, origin, packed, _n in self.clouds.ready():
            self.ch.cloud(t_ns, origin, packed)

    def _trajectory(self):
        """The last :data:`NAV_KEEP_S` s of epochs as a trajectory (None: fewer than two)."""
        from calib.core.trajectory import Trajectory

        if len(self.nav) < 2:
            return None
        a = np.array(self.nav)
        return Trajectory.from_geodetic(a[:, 0], a[:, 1], a[:, 2], a[:, 3], a[:, 4:7], self.frame)

    def _say_no_mount(self) -> None:
        if not self.said_no_mount and self.now_ns is not None:
            self.said_no_mount = True
            self.ch.event(
                self.now_ns, {"event": "foxglove_no_clouds", "reason": "no mount in the vessel config"}
            )

    # -- the status bus ----------------------------------------------------------------------

    def offer(self, topic: str, payload: bytes, retain: bool, qos: int) -> None:
        """A bus publication (:class:`acquire.status.bus.Sink`): ``clock`` and ``metrics``."""
        if topic == "clock":
            self.on_clock(json.loads(payload))
        elif topic == "metrics" and self.now_ns is not None and self.ch.latency.has_sinks():
            latency = json.loads(payload).get("latency")
            if isinstance(latency, dict):
                self.ch.latency_msg(self.now_ns, latency)

    def on_clock(self, doc: dict) -> None:
        if self.locked_offset_ns is None and doc.get("state") == "LOCKED":
            off = doc.get("offset_ns")
            self.locked_offset_ns = off if isinstance(off, int) else None
        t_ns = doc.get("gps_ns")
        if isinstance(t_ns, int) and t_ns > 0:
            self.ch.clock_msg(t_ns, doc, self.locked_offset_ns)


def _returns(prof) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A profile's returns inside the range window: GPS ns, range m, scan angle rad, intensity."""
    r = np.asarray(prof.range_m, float)
    from calib.io.bundle import SCANNER_RANGE_M

    lo, hi = SCANNER_RANGE_M
    keep = np.isfinite(r) & (r >= lo) & (r <= hi)
    return (
        np.asarray(prof.gps_ns, np.int64)[keep],
        r[keep],
        np.asarray(prof.scan_angle_rad, float)[keep],
        np.asarray(prof.intensity, np.float32)[keep],
    )
