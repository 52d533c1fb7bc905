"""The Foxglove export's profiles: the /lidar/raw datagrams decoded again and handed to the
point clouds (:class:`acquire.foxglove.clouds.Clouds`) of :mod:`office.jobs.foxglove`."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from acquire.foxglove import frames as ff
from acquire.foxglove.clouds import Clouds


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
