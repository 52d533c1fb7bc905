"""Simulator throughput: simulated returns per second on one core, with 20 rectangles in the
scene, and its ratio to the georeferencing throughput (``calib.core.georef.georeference`` on the
same number of points) measured in the same run.

    .venv/bin/python benchmarks/simulate.py [--repeat N]

The scene is the montreal scenario at the full Z+F point rate with its quay wall widened to
40 m × 8 m and 17 more panels on it (20 rectangles); the scanner records its default angular
windows toward the wall on the two parallel passes. The simulation timed is the whole of ``calib.sim.simulate.simulate``
(plan, motion, ray casting, noise, observed trajectory).
"""

from __future__ import annotations

import argparse  # noqa: E402
import time  # noqa: E402

import _onecore  # noqa: F401  (first: BLAS on one thread)
import numpy as np  # noqa: E402


def _scenario():
    from calib.sim.scenariofile import load_scenario

    panels = [
        {
            "name": f"P{i:02d}",
            "along_m": -17.0 + 2.0 * i + (2.0 if i >= 8 else 0.0),
            "out_m": 0.05,
            "up_m": 4.0 + (i % 3),
            "size_m": [1.0, 1.0],
            "inclination_deg": 90.0,
        }
        for i in range(17)
    ]
    overrides = {
        "scanner.point_rate_scale": 1.0,
        "scene.surfaces": [
            {
                "name": "quay_wall",
                "kind": "wall",
                "along_m": 0.0,
                "out_m": 0.0,
                "up_m": 4.0,
                "size_m": [40.0, 8.0],
                "reflectivity": 0.25,
            }
        ]
        + [dict(p, kind="other") for p in panels],
        "site.capture_margin_m": 15.0,
        "site.passes": [{"id": 1, "relative_heading_deg": 0.0}, {"id": 2, "relative_heading_deg": 180.0}],
    }
    return load_scenario("montreal", overrides)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3, help="timed runs (the best is reported)")
    args = ap.parse_args()

    from calib.core.georef import georeference
    from calib.sim.simulate import simulate

    sc = _scenario()
    n_rect = len(sc.surfaces)
    simulate(sc, seed=0)  # warm-up (imports, pyproj)
    best_sim, res = np.inf, None
    for i in range(args.repeat):
        t0 = time.perf_counter()
        res = simulate(sc, seed=i)
        best_sim = min(best_sim, time.perf_counter() - t0)
    n = len(res.points)
    pts = res.points
    best_geo = np.inf
    for _ in range(args.repeat):
        t0 = time.perf_counter()
        georeference(pts.t_gps_s, pts.range_m, pts.scan_angle_rad, res.trajectory_observed, res.site.mount)
        best_geo = min(best_geo, time.perf_counter() - t0)
    sim_rate, geo_rate = n / best_sim, n / best_geo
    print(f"scene: {n_rect} rectangles; {n:,} returns in {len(res.plan.passes)} passes")
    print(f"simulate:     {best_sim:8.3f} s  {sim_rate / 1e6:8.2f} M returns/s (goal ≥ 2 M/s)")
    print(f"georeference: {best_geo:8.3f} s  {geo_rate / 1e6:8.2f} M points/s")
    print(f"ratio simulate / georeference: {sim_rate / geo_rate:.2f}")


if __name__ == "__main__":
    main()
