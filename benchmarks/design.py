"""Design study wall time: the full marine sweep (``mls design --scenario montreal``: visibility
criteria of the eight errors, every σ sweep, the recommendation search, tables, figures and
summary) on ``--jobs`` processes, against a peer measured in the same run: the naive cost of
one simulation + prediction of the montreal site (every model) per configuration, on one core.

    .venv/bin/python benchmarks/design.py [--jobs 2]

Goal: the full marine sweep in ≤ 60 s on the 2-core machine.
"""

from __future__ import annotations

import argparse  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402

import _onecore  # noqa: F401  (first: BLAS on one thread)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--jobs", type=int, default=2, help="worker processes of the study")
    ap.add_argument("--peer-repeat", type=int, default=5, help="timed peer runs (best is used)")
    args = ap.parse_args()

    from calib.design.layouts import default_spec, layouts
    from calib.design.prediction import Sigmas, predict, prepare
    from calib.design.scenes import design_scenario
    from calib.design.study import run_study
    from calib.design.summary import write_study
    from calib.sim.scenariofile import load_scenario

    base = load_scenario("montreal")
    spec = default_spec(base)
    n_configs = len(layouts(base, spec)) + len(spec.errors) * len(spec.criteria_inclinations_deg)

    # the peer: one simulation + prediction of the montreal site, all models, one core
    sigmas = Sigmas.of_scenario(base)
    scene = design_scenario(base, [s for s in base.surfaces if s.kind == "target"])
    best_peer = float("inf")
    for i in range(args.peer_repeat + 1):
        t0 = time.perf_counter()
        sim, obs, planes = prepare(scene, sigmas, i)
        predict(obs, sim.mount_true, planes, sigmas.correlation_time_s)
        if i:  # the first run warms up imports and caches
            best_peer = min(best_peer, time.perf_counter() - t0)
    peer = best_peer * n_configs

    with tempfile.TemporaryDirectory() as out:
        t0 = time.perf_counter()
        result = run_study(base, spec, jobs=args.jobs)
        t_study = time.perf_counter() - t0
        t1 = time.perf_counter()
        files = write_study(result, out, jobs=args.jobs)
        t_write = time.perf_counter() - t1
    total = t_study + t_write
    print(
        f"full marine sweep (montreal, {n_configs} configurations, {len(result.sigma)} "
        f"predictions, {len(files)} files) on {args.jobs} processes: {total:.1f} s "
        f"(study {t_study:.1f} s, tables/figures/summary {t_write:.1f} s); goal ≤ 60 s: "
        f"{'met' if total <= 60 else 'NOT met'}"
    )
    print(
        f"peer: one simulation + prediction of montreal {best_peer * 1e3:.0f} ms × {n_configs} "
        f"configurations = {peer:.1f} s on one core"
    )
    print(f"ratio full sweep / peer: {total / peer:.2f}")


if __name__ == "__main__":
    main()
