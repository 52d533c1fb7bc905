"""Adjustment speed: 1,300 / 100 k / 1 M points on one core, and the ratio to the
dense textbook Gauss–Helmert solution (B n × 8n, Q 8n × 8n) at 1,300 points in the same run.

Goals: ≤ 20 ms for 1,300 points (the thesis reports 532 s in C++), ≤ 1 s for 100 k, ≤ 10 s for
1 M. Run: ``make bench`` or ``.venv/bin/python benchmarks/adjust.py``.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import _onecore  # noqa: F401  (first: BLAS on one thread)

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from calib.boresight.adjust import adjust  # noqa: E402
from calib.boresight.errormodel import ErrorModel  # noqa: E402
from calib.boresight.observations import AdjustOptions  # noqa: E402
from calib.core.georef import Mount  # noqa: E402
from tests.calib import synth  # noqa: E402
from tests.calib.boresight.test_adjust_dense import textbook_adjustment  # noqa: E402

TRUTH = np.radians([0.208, 1.245, 0.149])


def tiled(base, n, seed):
    """n observations: the base geometry repeated, each copy with fresh per-point noise."""
    idx = (
        (np.arange(n) * len(base)) // n
        if n <= len(base)
        else np.tile(np.arange(len(base)), -(-n // len(base)))[:n]
    )
    obs = base.select(idx)
    # keep passes contiguous and times non-decreasing within a pass
    order = np.lexsort((obs.t_gps_s, obs.pass_index))
    obs = obs.select(order)
    obs.point_ids = np.arange(n)
    rng = np.random.default_rng(seed)
    obs.l = obs.l + rng.standard_normal(obs.l.shape) * obs.sigma_l
    return obs


def best_of(fn, repeat):
    best = np.inf
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return best, out


def main():
    base, planes, _ = synth.observations(
        Mount(boresight_rad=TRUTH), synth.montreal_planes(), points_per_plane_per_pass=1100, noise=False
    )
    solve_only = AdjustOptions(outliers="none", jackknife=False, error_model=ErrorModel("white"))
    full = AdjustOptions()
    print(f"{'points':>9} {'solve (formal σ)':>18} {'full (outliers, realistic σ, jackknife)':>42}")
    rows = {}
    for n, repeat in ((1300, 20), (100_000, 3), (1_000_000, 1)):
        obs = tiled(base, n, seed=n)
        t_solve, res = best_of(lambda obs=obs: adjust(obs, Mount(), planes, solve_only), repeat)
        t_full, _ = best_of(lambda obs=obs: adjust(obs, Mount(), planes, full), max(1, repeat // 3))
        rows[n] = (t_solve, res)
        print(f"{n:>9} {t_solve * 1e3:>15.1f} ms {t_full * 1e3:>39.1f} ms")
    obs = tiled(base, 1300, seed=1300)
    t0 = time.perf_counter()
    textbook_adjustment(obs, planes, iterations=4)
    t_dense = time.perf_counter() - t0
    t_fast = rows[1300][0]
    print(f"dense textbook Gauss–Helmert, 1,300 points, 4 iterations: {t_dense:.2f} s")
    print(
        f"ratio dense / O(n) at 1,300 points: {t_dense / t_fast:,.0f}×  "
        f"(thesis, C++: 532 s → ratio to ours {532.0 / t_fast:,.0f}×)"
    )
    goals = {1300: 0.020, 100_000: 1.0, 1_000_000: 10.0}
    for n, goal in goals.items():
        print(
            f"goal {n:>9} points ≤ {goal:g} s: {'met' if rows[n][0] <= goal else 'NOT met'} "
            f"({rows[n][0]:.3f} s)"
        )


if __name__ == "__main__":
    main()
