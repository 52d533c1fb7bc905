"""Direct georeferencing throughput on one core, against the memory-bandwidth floor.

A realistic stream: the Z+F Profiler at 1.016 Mpts/s (200 profiles/s × 5080 points, 360°),
10 M points (~9.8 s), a 200 Hz trajectory with wave motion (roll, pitch, yaw and heave), a mount
with lever arm, nominal rotation, boresight and scanner offsets. The peer is a plain numpy copy
of the same input (time, range, scan angle) and output (3 coordinates) arrays into preallocated
buffers, timed in the same run: the least any implementation has to move through memory.

    .venv/bin/python benchmarks/georef.py [--points N] [--repeat R]

Prints points/s of ``calib.core.georef.georeference`` and the ratio of its time to the copy's
(goal: ≥ 20 M points/s and ≤ 10× the copy).
"""

from __future__ import annotations

import argparse  # noqa: E402
import time  # noqa: E402

import _onecore  # noqa: F401  (first: BLAS on one thread)
import numpy as np  # noqa: E402

from calib.core import frames  # noqa: E402
from calib.core.georef import Mount, georeference  # noqa: E402
from calib.core.trajectory import Trajectory  # noqa: E402

POINT_RATE_HZ = 1.016e6
PROFILE_RATE_HZ = 200.0
TRAJECTORY_RATE_HZ = 200.0
T0_GPS_S = 1_313_000_000.0  # 2021-08-17


def wave_trajectory(duration_s: float) -> Trajectory:
    """2 m/s along a quay, heading 30°, with roll/pitch/yaw swell and heave."""
    t = T0_GPS_S + np.arange(-1.0, duration_s + 1.0, 1.0 / TRAJECTORY_RATE_HZ)
    dt = t - T0_GPS_S
    w = 2.0 * np.pi / 6.0  # 6 s swell
    rpy = np.stack(
        [
            np.radians(3.0) * np.sin(w * dt),
            np.radians(1.0) * np.sin(1.3 * w * dt + 0.4),
            np.radians(30.0) + np.radians(0.5) * np.sin(0.7 * w * dt),
        ],
        axis=1,
    )
    heading = rpy[0, 2]
    p = np.stack(
        [
            2.0 * np.cos(heading) * dt,
            2.0 * np.sin(heading) * dt,
            0.2 * np.sin(w * dt + 1.0),
        ],
        axis=1,
    )
    return Trajectory(t, p, rpy, frames.LocalFrame(45.5, -73.55, -30.0), name="waves")


def profiler_stream(n: int, rng: np.random.Generator):
    """Times, ranges and scan angles of a 360° profiler (5080 points per profile)."""
    i = np.arange(n)
    per_profile = int(round(POINT_RATE_HZ / PROFILE_RATE_HZ))
    t = T0_GPS_S + i / POINT_RATE_HZ
    alpha = (i % per_profile) * (2.0 * np.pi / per_profile)
    rho = rng.uniform(1.0, 120.0, n)
    return t, rho, alpha


def best_times(repeat: int, *fns) -> list[float]:
    """Best wall time of each function over ``repeat`` rounds, run in turn within each round so
    that they see the same load on a shared machine."""
    best = [np.inf] * len(fns)
    for _ in range(repeat):
        for i, fn in enumerate(fns):
            start = time.perf_counter()
            fn()
            best[i] = min(best[i], time.perf_counter() - start)
    return best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=10_000_000)
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args()
    n = args.points

    rng = np.random.default_rng(20210817)
    t, rho, alpha = profiler_stream(n, rng)
    traj = wave_trajectory(n / POINT_RATE_HZ)
    mount = Mount(
        lever_arm_m=[0.42, -0.31, -1.85],
        nominal_rad=np.radians([0.0, -2.0, 0.5]),
        boresight_rad=np.radians([0.208, 1.245, 0.149]),
        range_offset_m=0.004,
        scan_angle_offset_rad=np.radians(0.003),
        time_offset_s=0.0005,
    )
    out = np.empty((3, n)).T
    t_c, rho_c, alpha_c, out_c = (
        np.empty_like(t),
        np.empty_like(rho),
        np.empty_like(alpha),
        np.empty((3, n)).T,
    )

    def georef():
        georeference(t, rho, alpha, traj, mount, out=out)

    def copy():
        np.copyto(t_c, t)
        np.copyto(rho_c, rho)
        np.copyto(alpha_c, alpha)
        np.copyto(out_c, out)

    georef()  # warm-up: first touch of the output pages, caches
    copy()
    t_georef, t_copy = best_times(args.repeat, georef, copy)

    print(f"points: {n:,}  trajectory epochs: {traj.t_gps_s.size:,} ({TRAJECTORY_RATE_HZ:g} Hz)")
    print(f"georeference : {t_georef * 1e3:8.1f} ms  {n / t_georef / 1e6:7.1f} M points/s")
    print(
        f"numpy copy   : {t_copy * 1e3:8.1f} ms  {n / t_copy / 1e6:7.1f} M points/s "
        f"(inputs + outputs: {2 * 6 * 8 * n / t_copy / 1e9:.1f} GB/s)"
    )
    print(f"ratio georeference / copy: {t_georef / t_copy:.1f}×  (goal: ≥ 20 M points/s and ≤ 10×)")


if __name__ == "__main__":
    main()
