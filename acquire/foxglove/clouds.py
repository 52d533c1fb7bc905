"""Point clouds for Foxglove: returns gathered into windows of GPS time, each window's returns
sorted by time, those the trajectory does not cover left out, then every k-th kept (k =
ceil(n / cap)), georeferenced (:func:`calib.core.georef.georeference`) and packed
(:func:`acquire.foxglove.frames.pack_cloud`). The MCAP export feeds it a whole session; the live
server (:mod:`acquire.foxglove.live`) the daemon's profiles as they come, with the trajectory of
the last seconds."""

from __future__ import annotations

import numpy as np

from acquire.foxglove import frames as ff

#: a window's cloud is written once the returns have gone this far past its end (packets arrive
#: a little out of order); a return for a window already written is left out and counted
LATE_NS = 1_000_000_000


class Clouds:
    """Returns gathered into 1/rate windows of GPS time; a window is ready once the returns have
    gone :data:`LATE_NS` past its end, or at the end."""

    def __init__(self, period_ns: int, cap: int, traj, mount) -> None:
        self.period_ns, self.cap, self.traj, self.mount = period_ns, cap, traj, mount
        self.pending: dict[int, list[tuple]] = {}
        self.written_upto = -(2**62)  # windows up to this index are written
        self.newest_ns = -(2**62)
        self.late = self.uncovered = self.returns = self.points = 0

    def add(self, t_ns: np.ndarray, range_m: np.ndarray, angle_rad: np.ndarray, inten: np.ndarray) -> None:
        k = t_ns // self.period_ns
        late = k <= self.written_upto
        if late.any():
            self.late += int(late.sum())
            keep = ~late
            t_ns, range_m, angle_rad, inten, k = (
                t_ns[keep],
                range_m[keep],
                angle_rad[keep],
                inten[keep],
                k[keep],
            )
        for kk in np.unique(k):
            sel = k == kk
            self.pending.setdefault(int(kk), []).append((t_ns[sel], range_m[sel], angle_rad[sel], inten[sel]))
        if t_ns.size:
            self.newest_ns = max(self.newest_ns, int(t_ns.max()))

    def _complete(self, k: int) -> bool:
        return (k + 1) * self.period_ns + LATE_NS <= self.newest_ns

    def due(self) -> bool:
        """Whether a window is complete (:meth:`ready` would give a cloud or drop a window)."""
        return bool(self.pending) and self._complete(min(self.pending))

    def ready(self, final: bool = False):
        """The clouds of the complete windows, in time order: ``(gps_ns, origin, packed, n)``."""
        for k in sorted(self.pending):
            if not final and not self._complete(k):
                break
            self.written_upto = k
            cloud = self._cloud(self.pending.pop(k))
            if cloud is not None:
                yield cloud

    def _cloud(self, parts: list[tuple]):
        from calib.core import frames
        from calib.core.georef import georeference

        t, rng, ang, inten = (np.concatenate([p[j] for p in parts]) for j in range(4))
        order = np.argsort(t, kind="stable")
        t, rng, ang, inten = t[order], rng[order], ang[order], inten[order]
        t_s = frames.gps_ns_to_seconds(t)
        covered = ~self.traj.uncovered(t_s)
        self.uncovered += int((~covered).sum())
        if not covered.any():
            return None
        last_ns = int(t[-1])
        t_s, rng, ang, inten = t_s[covered], rng[covered], ang[covered], inten[covered]
        step = -(-t_s.size // self.cap)
        self.returns += t_s.size
        t_s, rng, ang, inten = t_s[::step], rng[::step], ang[::step], inten[::step]
        p_enu = ff.enu_from_ned(georeference(t_s, rng, ang, self.traj, self.mount))
        origin, packed = ff.pack_cloud(p_enu, inten)
        self.points += t_s.size
        return last_ns, origin, packed, int(t_s.size)
