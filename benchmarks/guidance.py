"""Live target hits: profiler points per second that :func:`acquire.guidance.targethits.target_hits` handles
on one core at the full Z+F rate, against the peer measured in the same run — georeferencing
every return and testing it against the targets (what the gate avoids).

    .venv/bin/python benchmarks/guidance.py [--seconds S] [--repeat N]

The stream is the montreal site at the full point rate (5080 points per profile, 200 profiles/s,
1.016 Mpts/s) sailing pass 1 through its capture window, every point of every profile present
(no return = NaN range, as the profiler sends them); the scene around the targets is a 40 m ×
8 m quay wall and a quay top, so a realistic share of the points are returns. The goal is ≥ 1
Mpts/s with room to spare (the daemon has other work).
"""

from __future__ import annotations

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import _onecore  # noqa: F401  (first: BLAS on one thread)

# the project root first: benchmarks/acquire.py would otherwise shadow the acquire package
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402


def _stream(seconds: float):
    from dataclasses import replace

    from calib.core.geometry import Rectangle
    from calib.sim.motion import MotionModel, Wave, sail
    from calib.sim.scenario import ScannerModel
    from calib.sim.scenariofile import load_scenario
    from calib.sim.scene import Scene
    from calib.sim.simulate import scan
    from calib.survey.passplan import plan_site

    sc = load_scenario("montreal")
    site = sc.site()
    frame = site.frame()
    plan = plan_site(site, track_down_m=1.65)
    first = replace(plan, passes=plan.passes[:1])
    motion = MotionModel(roll=Wave(np.radians(1.5), 4.0), pitch=Wave(np.radians(0.5), 5.5))
    run = sail(first, motion, 1.3e9, frame, np.random.default_rng(0))
    traj = run.trajectory
    targets = site.target_rectangles(frame)
    w = sc.water_azimuth_rad
    c = np.mean([t.center_m for t in targets], axis=0)
    back = np.array([np.cos(w), np.sin(w), 0.0])
    wall = Rectangle.from_orientation("wall", c - 0.05 * back, 40.0, 8.0, np.pi / 2, w, 0.25)
    top = Rectangle.from_orientation(
        "top", c - 0.05 * back - 4.0 * back + [0, 0, -4.0], 40.0, 8.0, 0.0, w, 0.3
    )
    scene = Scene((*targets, wall, top), ("target", "target", "wall", "ground"))
    scanner = ScannerModel()  # full rate, full circle
    c0, c1 = run.capture_times[1]
    t0 = 0.5 * (c0 + c1) - 0.5 * seconds
    ret = scan(scanner, scene, traj, site.mount, t0, t0 + seconds)
    # every point of every profile, NaN where nothing returned
    K = scanner.points_per_360
    rate = scanner.profile_rate_hz
    n_prof = int(seconds * rate)
    t = t0 + np.arange(n_prof * K) / (rate * K)
    rho = np.full(t.size, np.nan)
    alpha = (np.arange(t.size) % K) * (2 * np.pi / K)
    slot = np.rint((ret.t_gps_s - t0) * rate * K).astype(np.int64)
    ok = (slot >= 0) & (slot < t.size)
    rho[slot[ok]] = ret.range_true_m[ok]
    prof = np.repeat(np.arange(n_prof), K)
    t_prof = t0 + (np.arange(n_prof) + 0.5) / rate
    return site, traj, Scene(tuple(targets), ("target",) * 2), t, rho, alpha, prof, t_prof


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--seconds",
        type=float,
        default=5.0,
        help="seconds of profiler stream (centred on the capture window)",
    )
    ap.add_argument("--repeat", type=int, default=3, help="timed runs (the best is reported)")
    args = ap.parse_args()

    from acquire.guidance.targethits import target_hits
    from calib.core.georef import georeference

    site, traj, targets, t, rho, alpha, prof, t_prof = _stream(args.seconds)
    n = t.size
    returns = int(np.isfinite(rho).sum())
    mount = site.mount
    best_gate = best_all = np.inf
    hits = None
    for _ in range(args.repeat):
        t_a = time.perf_counter()
        hits = target_hits(t, rho, alpha, prof, t_prof, traj, mount, targets)
        best_gate = min(best_gate, time.perf_counter() - t_a)
    counts_all = None
    for _ in range(args.repeat):
        t_a = time.perf_counter()
        fin = np.flatnonzero(np.isfinite(rho))
        p = georeference(t[fin], rho[fin], alpha[fin], traj, mount)
        counts_all = [
            int(np.sum((np.abs(r.signed_distance(p)) <= 0.15) & r.contains(p))) for r in targets.rectangles
        ]
        best_all = min(best_all, time.perf_counter() - t_a)
    rate_gate, rate_all = n / best_gate, n / best_all
    print(
        f"stream: {args.seconds:g} s at the full Z+F rate, {n:,} points, {returns:,} returns; "
        f"gated {hits.n_gated:,}"
    )
    print(f"hits per target: gate {hits.counts(2).tolist()}, georeference-all {counts_all}")
    print(
        f"target_hits (gate, then georeference): {best_gate:7.3f} s "
        f"{rate_gate / 1e6:7.2f} Mpts/s = {rate_gate / 1.016e6:5.1f}× real time (goal ≥ 1×)"
    )
    print(f"georeference every return + test:      {best_all:7.3f} s {rate_all / 1e6:7.2f} Mpts/s")
    print(f"ratio gate / georeference-all: {rate_gate / rate_all:.2f}")


if __name__ == "__main__":
    main()
