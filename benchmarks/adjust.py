"""Adjustment speed: 1,300 / 100 k / 1 M points on one core, and the ratio to the
dense textbook Gauss–Helmert solution (B n × 8n, Q 8n × 8n) at 1,300 points in the same run.

Thesis estimator (white weights; the table's first part). Goals: ≤ 20 ms for 1,300 points (the
thesis reports 532 s in C++), ≤ 1 s for 100 k, ≤ 10 s for 1 M.

GLS (the default estimator: POS errors as Gauss–Markov processes estimated jointly, O(n)),
solve only (no outlier tests, no jackknife), on the realistic problem with tie patches: the two
montreal targets plus 30 patch planes of the quay wall (1 × 1 m, on the wall's plane, spread
along it and over its height), six passes, τ 10 s. Goals: ≤ 30 ms for 1,300 points, ≤ 2 s for
100 k, ≤ 20 s for 1 M; each figure is printed with its ratio to the goal and to the thesis
estimator on the same observations measured in the same run.

Run: ``make bench`` or ``.venv/bin/python benchmarks/adjust.py``.
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
from calib.core.geometry import Rectangle  # noqa: E402
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
    solve_only = AdjustOptions(
        outliers="none", jackknife=False, error_model=ErrorModel("white"), estimator="thesis"
    )
    full = AdjustOptions(estimator="thesis")
    print("thesis estimator (white weights)")
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
    gls_timing()


def tie_patch_planes(n_patches=30):
    """The montreal targets plus ``n_patches`` 1 × 1 m patches on the wall's plane (east = 15 m,
    facing west) spread 24 m along it and 3 m over its height: targets + tie patches."""
    az = np.radians(270.0)
    half = np.linspace(3.0, 14.0, n_patches // 2)  # clear of the targets (|along| ≤ 2.1 m)
    along = np.concatenate([-half[::-1], half, [0.0] * (n_patches % 2)])
    up = -5.0 + 1.5 * np.sin(np.arange(n_patches) * 2.1)  # 3.5 … 6.5 m above the scanner
    up[len(half) * 2 :] = -7.0  # an odd patch: below the targets
    patches = [
        Rectangle.from_orientation(f"P{i}", [a, 15.0, u], 1.0, 1.0, np.radians(90.0), az)
        for i, (a, u) in enumerate(zip(along, up))
    ]
    return synth.montreal_planes() + patches


def _gls_row(obs, planes, gls, thesis, goal, repeat, label):
    t_gls, res = best_of(lambda: adjust(obs, Mount(), planes, gls), repeat)
    t_th, _ = best_of(lambda: adjust(obs, Mount(), planes, thesis), repeat)
    err = np.degrees(np.abs(res.boresight_rad - TRUTH)).max()
    print(
        f"{label:>9} {t_gls * 1e3:>8.1f} ms {goal:>7g}s {t_gls / goal:>9.2f} {t_th * 1e3:>8.1f} ms "
        f"{t_gls / t_th:>11.2f}  {'met' if t_gls <= goal else 'NOT met'}"
        f"  (|error| max {err:.4f}°, {res.iterations} iterations)"
    )


def gls_timing():
    model = ErrorModel("gauss_markov", 10.0)
    gls = AdjustOptions(outliers="none", jackknife=False, error_model=model, estimator="gls")
    thesis = AdjustOptions(outliers="none", jackknife=False, error_model=model, estimator="thesis")
    base2, planes2, _ = synth.observations(
        Mount(boresight_rad=TRUTH), synth.montreal_planes(), points_per_plane_per_pass=1100, noise=False
    )
    print("\nGLS (Gauss–Markov POS errors, τ 10 s), solve only, the 2 targets, 6 passes, one core")
    print(f"{'points':>9} {'GLS':>11} {'goal':>8} {'GLS/goal':>9} {'thesis':>11} {'GLS/thesis':>11}  goal")
    _gls_row(tiled(base2, 1300, seed=1300), planes2, gls, thesis, 0.030, 10, "1300")
    rects = tie_patch_planes()
    base, planes, _ = synth.observations(
        Mount(boresight_rad=TRUTH), rects, points_per_plane_per_pass=200, noise=False
    )
    goals = {1300: 0.030, 100_000: 2.0, 1_000_000: 20.0}
    print(
        f"\nGLS (Gauss–Markov POS errors, τ 10 s), solve only, {len(planes)} planes "
        f"(2 targets + {len(planes) - 2} tie patches), 6 passes, one core"
    )
    print(f"{'points':>9} {'GLS':>11} {'goal':>8} {'GLS/goal':>9} {'thesis':>11} {'GLS/thesis':>11}  goal")
    for n, repeat in ((1300, 10), (100_000, 2), (1_000_000, 1)):
        _gls_row(tiled(base, n, seed=n + 1), planes, gls, thesis, goals[n], repeat, str(n))


if __name__ == "__main__":
    main()
