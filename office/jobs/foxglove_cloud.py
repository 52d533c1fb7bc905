"""The Foxglove export's profiles: the /lidar/raw datagrams decoded again and georeferenced, and
their returns gathered into decimated point clouds (:mod:`office.jobs.foxglove`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from office.jobs import foxglove_frames as ff

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

    def ready(self, final: bool = False):
        """The clouds of the complete windows, in time order: ``(gps_ns, origin, packed, n)``."""
        for k in sorted(self.pending):
            if not final and (k + 1) * self.period_ns + LATE_NS > self.newest_ns:
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


def decode_profiles(
    session: Path, to_gps: ff.HostToGps, protocol: str, clouds: Clouds, counts: dict, progress
):
    """Feed every return of /lidar/raw to ``clouds``, counting datagrams (``packets``, ``bad``)
    and ``out_of_range`` returns in ``counts``; yields after each datagram that brought returns
    (the caller writes the windows that made ready)."""
    from acquire.log.profiles import iter_packets
    from calib.io.bundle import SCANNER_RANGE_M
    from drivers.zf.zfp1 import RANGE_UNIT_M

    def receipt_ns(env) -> int:  # re-timed while the clock model was unlocked
        return to_gps.gps_ns(env.host_ns, env.log_time_ns) if env.clock == "UNLOCKED" else env.log_time_ns

    lo, hi = SCANNER_RANGE_M
    counts.update(packets=0, bad=0, unsynced=0, out_of_range=0)
    for _, pk, i, t in iter_packets(session, protocol, counts, receipt_ns, progress):
        r_m = pk.range_01mm.astype(np.float64) * RANGE_UNIT_M
        hit = pk.range_01mm > 0
        inside = hit & (r_m >= lo) & (r_m <= hi)
        counts["out_of_range"] += int((hit & ~inside).sum())
        if not inside.any():
            continue
        ang = np.radians(np.mod((pk.angle0_udeg + i * pk.dangle_udeg) * 1e-6, 360.0))
        clouds.add(t[inside], r_m[inside], ang[inside], pk.intensity[inside].astype(np.float32))
        yield


# -- writing ------------------------------------------------------------------------------------
