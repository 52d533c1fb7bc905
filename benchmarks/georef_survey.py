"""Whole-survey georeferencing (``mls georef``): points/s end to end, speed-up on a local Dask
cluster, peak memory per worker.

Sessions: ``mls sim session`` (montreal, lines back and forth along the quay, the daemon's own
format) at ``--rate-scale`` of the Z+F rate — the scaled-down equivalent of a production session
(at 0.1: ≈ 3.3 M returns a minute instead of ≈ 33 M; the work per return is the same; the
chunks are 2 s / rate-scale long, so that a task holds the returns of the default 2-s chunk at
the full rate, and a worker the same memory). The
longer session goes through ``run_georef`` (the library call of ``mls georef``, line tiles, LAZ)
in-process, and on a ``LocalCluster`` of 1 and then 2 worker processes (each cluster warmed
with one task first, so that the workers' imports are not timed; the plan — reading the
navigation — is timed, it runs in this process); each case runs ``--repeat`` times and the
fastest counts (a shared 2-core VM varies by ±15 % from run to run). Every run's tiles are compared byte for byte
with the in-process run's. The shorter session runs on 2 workers again, to show that the peak
memory per worker does not grow with the survey's length.

Figures: returns read/s and points written/s (wall time of the whole job: plan, chunks, LAZ
compression), speed-up 2 workers / 1 worker (goal ≥ 1.8 on the 2-core machine in three
consecutive runs, issue 29: ``--speedup-runs 3`` measures it three times in a row),
peak resident memory per worker process (goal ≤ 1.5 GB at both lengths).

Against the format and the sensor, from the in-process run (one core; CPU time of this process,
steadier than wall time on a loaded machine): the LAZ ceiling — laspy + lazrs (one thread)
writing the very points of that run's tiles again, measured in the same run — and the ratio of
``mls georef``'s points written per CPU second to it (goal ≥ 0.75); and the seconds of one core
``mls georef`` needs per survey second at the Z+F 9012's full rate, 1.016 M points/s with every
point a return (CPU seconds per return read × 1.016 M; goal ≤ 0.25 s).

    .venv/bin/python benchmarks/georef_survey.py [--minutes 10 5] [--rate-scale 0.1] [--quick]
"""

from __future__ import annotations

import argparse
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import _onecore  # noqa: F401  (first: BLAS on one thread)

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

GOAL_SPEEDUP = 1.8
GOAL_PEAK_MB = 1536.0
GOAL_CEILING_RATIO = 0.75
GOAL_CORE_S_PER_SURVEY_S = 0.25
ZF_FULL_RATE_PER_S = 1.016e6


def make_session(root: Path, minutes: float, rate_scale: float) -> Path:
    t = time.perf_counter()
    subprocess.run(
        [
            str(ROOT / ".venv/bin/mls"),
            "sim",
            "session",
            "--out",
            str(root),
            "--minutes",
            f"{minutes:g}",
            "--rate-scale",
            f"{rate_scale:g}",
        ],
        check=True,
        stdout=subprocess.DEVNULL,
    )
    (session,) = [p for p in root.iterdir() if p.is_dir()]
    print(
        f"  session {minutes:g} min at rate-scale {rate_scale:g}: {session.name} ({time.perf_counter() - t:.0f} s)"
    )
    return session


def _warm(_):
    import office.deliver.chunkjob  # noqa: F401
    import office.deliver.tiles  # noqa: F401

    return 0


def run(session: Path, out: Path, workers: int | None, chunk_s: float, repeat: int):
    """The fastest of ``repeat`` runs (a shared 2-core VM varies by ±15 % from run to run)."""
    from office.deliver.engine import run_georef
    from office.deliver.executors import DaskExecutor, InProcess
    from office.deliver.options import GeorefOptions

    best = None
    best_cpu = float("inf")
    for _ in range(repeat):
        shutil.rmtree(out, ignore_errors=True)
        ex = DaskExecutor(workers=workers) if workers else InProcess()
        try:
            if workers:
                for k in range(4 * workers):
                    ex.submit(_warm, k)
                list(ex.results())
            t, cpu = time.perf_counter(), time.process_time()
            res = run_georef(session, out, GeorefOptions(chunk_s=chunk_s), executor=ex)
            wall = time.perf_counter() - t
            best_cpu = min(best_cpu, time.process_time() - cpu)
        finally:
            ex.close()
        if not workers:
            res.peak_rss_mb = {0: resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0}
        if best is None or wall < best[1]:
            best = (res, wall)
    assert best is not None
    return (*best, best_cpu)


def laz_ceiling(tiles: Path, scratch: Path) -> tuple[int, float, float]:
    """(points, CPU s, wall s) of laspy + lazrs (one thread) writing the points of the LAZ files
    in ``tiles`` again (read beforehand, not timed): the format's own limit on one core."""
    import laspy

    scratch.mkdir(parents=True, exist_ok=True)
    n, cpu, wall = 0, 0.0, 0.0
    for p in sorted(tiles.glob("*.laz")):
        las = laspy.read(p)
        t, c = time.perf_counter(), time.process_time()
        las.write(scratch / p.name, do_compress=True, laz_backend=laspy.LazBackend.Lazrs)
        cpu += time.process_time() - c
        wall += time.perf_counter() - t
        n += len(las.points)
        (scratch / p.name).unlink()
    return n, cpu, wall


def speedup_again(session: Path, tmp: Path, chunk_s: float, repeat: int) -> float:
    """The 2-worker speed-up measured once more (1 worker, then 2)."""
    _, w1, _ = run(session, tmp / "o-1", 1, chunk_s, repeat)
    _, w2, _ = run(session, tmp / "o-2", 2, chunk_s, repeat)
    return w1 / w2


def row(label: str, res, wall: float) -> str:
    returns = res.counters.get("returns", 0)
    peak = max(res.peak_rss_mb.values())
    return (
        f"  {label:<22} {wall:7.1f} s  {returns / wall / 1e6:6.2f} M returns/s  "
        f"{res.n_points / wall / 1e6:6.2f} M points/s  peak/worker {peak:6.0f} MB  "
        f"({res.n_points:,} points in {len(res.files)} files; plan / tasks / last tiles "
        + " / ".join(f"{res.stage_s[k]:.1f}" for k in ("plan", "tasks", "last tiles"))
        + " s)"
    )


def same_bytes(a: Path, b: Path) -> bool:
    fa, fb = sorted(p.name for p in a.glob("*.laz")), sorted(p.name for p in b.glob("*.laz"))
    return fa == fb and all((a / n).read_bytes() == (b / n).read_bytes() for n in fa)


def against_format_and_sensor(ref, cpu_s: float, tmp: Path, repeat: int) -> tuple[float, float]:
    """Print the LAZ ceiling measured now on the in-process run's tiles, ``mls georef``'s ratio
    to it (points per CPU second) and its core seconds per survey second at the Z+F's full rate;
    return (ratio, core seconds per survey second)."""
    best = min((laz_ceiling(ref.out_dir, tmp / "ceiling") for _ in range(repeat)), key=lambda c: c[1])
    n, cpu_laz, wall_laz = best
    ours = ref.n_points / cpu_s
    ceiling = n / cpu_laz
    ratio = ours / ceiling
    returns = ref.counters.get("returns", 0)
    core_s = cpu_s / returns * ZF_FULL_RATE_PER_S if returns else float("nan")
    print(
        f"  LAZ ceiling (laspy + lazrs writing the same {n:,} points, one core): {ceiling / 1e6:.2f} M points/s "
        f"of CPU ({n / wall_laz / 1e6:.2f} M/s wall)"
    )
    print(
        f"  mls georef in-process: {ours / 1e6:.2f} M points/s of CPU ({cpu_s:.1f} s CPU for the whole job); "
        f"ratio to the ceiling {ratio:.2f} (goal ≥ {GOAL_CEILING_RATIO})"
    )
    print(
        f"  one core per survey second at the Z+F full rate ({ZF_FULL_RATE_PER_S / 1e6:.3f} M points/s, every "
        f"point a return): {core_s:.3f} s (goal ≤ {GOAL_CORE_S_PER_SURVEY_S}: ratio "
        f"{core_s / GOAL_CORE_S_PER_SURVEY_S:.2f}; {returns:,} returns read)"
    )
    return ratio, core_s


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--minutes", type=float, nargs=2, default=[10.0, 5.0], metavar=("LONG", "SHORT"))
    ap.add_argument("--rate-scale", type=float, default=0.1)
    ap.add_argument("--quick", action="store_true", help="4- and 2-minute sessions")
    ap.add_argument("--repeat", type=int, default=2, help="runs of each timed case (the fastest counts)")
    ap.add_argument(
        "--speedup-runs",
        type=int,
        default=1,
        help="measure the 2-worker speed-up this many times in a row (the goal: in three consecutive runs)",
    )
    a = ap.parse_args()
    long_min, short_min = (4.0, 2.0) if a.quick else a.minutes
    with tempfile.TemporaryDirectory(prefix="georef-bench-") as tmp_name:
        tmp = Path(tmp_name)
        print(f"mls georef on simulated sessions (rate-scale {a.rate_scale:g} of the Z+F rate)")
        long_s = make_session(tmp / "long", long_min, a.rate_scale)
        short_s = make_session(tmp / "short", short_min, a.rate_scale)
        # the default chunk (2 s) holds at the full rate what 2 s / rate-scale holds here: the same
        # returns per task, so the same memory per worker and the same share of per-task overhead
        chunk_s = 2.0 / a.rate_scale
        print(f"  chunks of {chunk_s:g} s (the returns of the default 2-s chunk at the full rate)")
        ref, w0, cpu0 = run(long_s, tmp / "o-in", None, chunk_s, a.repeat)
        print(row(f"{long_min:g} min in-process", ref, w0))
        ratio, core_s = against_format_and_sensor(ref, cpu0, tmp, a.repeat)
        one, w1, _ = run(long_s, tmp / "o-1", 1, chunk_s, a.repeat)
        print(row(f"{long_min:g} min 1 worker", one, w1))
        two, w2, _ = run(long_s, tmp / "o-2", 2, chunk_s, a.repeat)
        print(row(f"{long_min:g} min 2 workers", two, w2))
        short, ws, _ = run(short_s, tmp / "o-s", 2, chunk_s, 1)
        print(row(f"{short_min:g} min 2 workers", short, ws))
        identical = same_bytes(tmp / "o-in", tmp / "o-1") and same_bytes(tmp / "o-in", tmp / "o-2")
        speedups = [
            w1 / w2,
            *(speedup_again(long_s, tmp, chunk_s, a.repeat) for _ in range(a.speedup_runs - 1)),
        ]
        peak_long, peak_short = max(two.peak_rss_mb.values()), max(short.peak_rss_mb.values())
        met = sum(s >= GOAL_SPEEDUP for s in speedups)
        print(
            f"  speed-up 2 workers / 1 worker: {', '.join(f'{s:.3f}×' for s in speedups)} (goal ≥ {GOAL_SPEEDUP}: "
            f"met in {met} of {len(speedups)} consecutive runs; ratio of the least {min(speedups) / GOAL_SPEEDUP:.3f})"
        )
        print(f"  1 worker / in-process time: {w1 / w0:.2f}")
        print(
            f"  peak memory per worker: {peak_long:.0f} MB ({long_min:g} min), {peak_short:.0f} MB "
            f"({short_min:g} min); goal ≤ {GOAL_PEAK_MB:.0f} MB: ratio {max(peak_long, peak_short) / GOAL_PEAK_MB:.2f}"
        )
        print(f"  tiles byte-identical across in-process, 1 and 2 workers: {'yes' if identical else 'NO'}")
        shutil.rmtree(tmp, ignore_errors=True)
    ok = (
        min(speedups) >= GOAL_SPEEDUP
        and max(peak_long, peak_short) <= GOAL_PEAK_MB
        and identical
        and ratio >= GOAL_CEILING_RATIO
        and core_s <= GOAL_CORE_S_PER_SURVEY_S
    )
    print("  goals: " + ("met" if ok else "NOT met"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
