"""Is the mount watch honest on fixed mounts whatever the line pattern (issue 24)?

Fixed-mount surveys with randomized geometry, each watched with the true boresight as its
calibration, as ``mls watch`` watches them (:func:`calib.watch.runner.run_watch`):

- **production** lines of the simulator's harbour front (:func:`calib.sim.production.simulate_production`),
  one to three offsets drawn in 10–55 m, speeds, line lengths, the wavy wall or not, the seed;
- **six-pass** calibration bundles: ``mls sim dataset --scenario montreal --seed N`` and, when
  the simulator has it, ``--scenario random --seed N`` (a tilted mount, any wall azimuth,
  standoffs 5–40 m, …);
- the six **foreign** bundles (``tests/data/foreign``: an independent simulator), once each.

Figures, against their goals: the surveys that raised ``mount_shift`` (goal 0); per angle the
RMS of the blocks' ``z = (Δ − truth)/σ`` over the angles given a verdict (goal 0.8–1.25), their
largest |z| and count; the blocks with no verdict, by reason.

    .venv/bin/python benchmarks/watch_honesty.py [--production 25] [--six-pass 25] [--seed 0]
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import tarfile
import tempfile
import time
from collections import Counter
from pathlib import Path

import _onecore  # noqa: F401  (first: BLAS on one thread)
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

GOAL_SHIFTS = 0
GOAL_Z_RMS = (0.8, 1.25)
ANGLES = ("roll", "pitch", "yaw")
FOREIGN = ROOT / "tests" / "data" / "foreign"


def production_run(seed: int):
    """A production survey of random geometry (fixed mount) and its watch."""
    from calib.sim.production import ProductionSpec, simulate_production

    rng = np.random.default_rng([seed, 24])
    offsets = tuple(float(x) for x in np.round(rng.uniform(10.0, 55.0, rng.integers(1, 4)), 1))
    lo = float(rng.uniform(1.2, 3.0))
    spec = ProductionSpec(
        n_lines=int(rng.integers(4, 7)),
        offsets_m=offsets,
        line_length_m=float(rng.uniform(150.0, 400.0)),
        speeds_mps=(lo, lo + float(rng.uniform(0.0, 1.5))),
        wavy_wall=bool(rng.random() < 0.3),
    )
    sim = simulate_production("montreal", spec, seed=1000 + seed)
    mount = sim.mount_true.with_boresight(np.radians(sim.truth["mount_calibrated"]))
    return _watch(sim.site, sim.points, sim.trajectory_observed, mount)


def bundle_run(bundle: Path):
    """The watch over a bundle (its passes as lines) with its truth.json boresight."""
    from calib.io.bundle import read_bundle

    b = read_bundle(bundle)
    t = json.loads((bundle / "truth.json").read_text())["boresight_deg"]
    mount = b.site.mount.with_boresight(np.radians([t["roll"], t["pitch"], t["yaw"]]))
    return _watch(b.site, b.points, b.trajectory, mount)


def _watch(site, points, trajectory, mount):
    from calib.watch.block import site_error_model, site_sigmas
    from calib.watch.runner import run_watch

    return run_watch(
        points, trajectory, mount, site_sigmas(site), site_error_model(site), site.wall_azimuth_rad
    )


def simulated_bundle(scenario: str, seed: int, tmp: Path) -> Path | None:
    """``mls sim dataset --scenario SCENARIO --seed SEED`` into ``tmp`` (None if refused)."""
    out = tmp / f"{scenario}-{seed}"
    mls = Path(sys.executable).with_name("mls")
    cmd = [str(mls), "sim", "dataset", "--scenario", scenario, "--seed", str(seed), "--out", str(out)]
    done = subprocess.run(cmd, capture_output=True, text=True)
    return out if done.returncode == 0 else None


def has_random_scenario() -> bool:
    try:
        import calib.sim.randomdraw  # noqa: F401
    except ImportError:
        return False
    return True


def block_z(run) -> list[tuple[int, float]]:
    """(angle, (Δ − truth)/σ) of every angle a block gives a verdict on; truth = 0 (the
    calibration is the true boresight)."""
    from calib.watch.sequential import MountTest

    out = []
    for b in run.blocks:
        d, cov, seen = MountTest().usable(b)
        out += [(int(i), float(d[i] / math.sqrt(cov[i, i]))) for i in np.flatnonzero(seen)]
    return out


def no_verdict_reasons(run) -> list[str]:
    """Why each block without an estimate has none (its status, numbers as N)."""
    import re

    return [re.sub(r"\d[\d.]*", "N", b.status.split(" (")[0]) for b in run.blocks if not b.ok]


def _link(b) -> tuple[float, float]:
    from scipy import stats

    from calib.watch.sequential import MountTest

    d, cov, seen = MountTest().usable(b)
    z = np.abs(d[seen] / np.sqrt(np.diag(cov)[seen])) if seen.any() else np.zeros(1)
    return float(stats.chi2.sf(b.link_chi2, b.link_df)), float(z.max())


class Tally:
    def __init__(self, name: str):
        self.name, self.surveys, self.shifts, self.blocks = name, 0, 0, 0
        self.z: list[tuple[int, float]] = []
        self.reasons: Counter = Counter()
        self.worst: list[tuple[float, str]] = []
        self.factors: list[float] = []  # the group test's χ²/df of the blocks with a verdict
        self.links: list[tuple[float, float]] = []  # (link χ² p-value, max |z|) of those blocks

    def add(self, label: str, run) -> None:
        self.surveys += 1
        self.shifts += run.alarm is not None
        self.blocks += len(run.blocks)
        z = block_z(run)
        self.z += z
        self.reasons.update(no_verdict_reasons(run))
        self.factors += [b.group_chi2 / b.group_df for b in run.blocks if b.ok and b.group_df]
        self.links += [_link(b) for b in run.blocks if b.ok and b.link_df]
        if z:
            self.worst.append((max(abs(v) for _, v in z), label))
        if run.alarm is not None:
            self.worst.append((math.inf, f"{label}: MOUNT SHIFT {run.alarm.message()}"))

    def report(self) -> bool:
        ok = self.shifts <= GOAL_SHIFTS
        print(f"\n## {self.name}: {self.surveys} surveys, {self.blocks} blocks")
        print(
            f"mount_shift: {self.shifts} (goal {GOAL_SHIFTS})  {'ok' if self.shifts <= GOAL_SHIFTS else 'FAIL'}"
        )
        for i, a in enumerate(ANGLES):
            z = np.array([v for j, v in self.z if j == i])
            if z.size == 0:
                print(f"  {a:5s}: no verdict in any block")
                continue
            rms = float(np.sqrt(np.mean(z**2)))
            good = GOAL_Z_RMS[0] <= rms <= GOAL_Z_RMS[1]
            ok &= good or z.size < 10
            print(
                f"  {a:5s}: z RMS {rms:.2f} (goal {GOAL_Z_RMS[0]}–{GOAL_Z_RMS[1]}) over {z.size} verdicts, "
                f"max |z| {np.max(np.abs(z)):.1f}, |z| > 3: {int(np.sum(np.abs(z) > 3))}  "
                f"{'ok' if good else ('few' if z.size < 10 else 'FAIL')}"
            )
        if self.factors:
            f = np.array(self.factors)
            print(
                f"  group test χ²/df: median {np.median(f):.2f}, 90 % {np.quantile(f, 0.9):.2f}, max {f.max():.2f}"
            )
        if self.links:
            lk = np.array(self.links)
            print(
                "  link test p-values: "
                + ", ".join(f"<{a:g}: {int(np.sum(lk[:, 0] < a))}" for a in (0.001, 0.01, 0.05, 0.2))
                + f" of {len(lk)}; blocks with max |z| > 3: p = "
                + ", ".join(f"{p:.3f}" for p in lk[lk[:, 1] > 3, 0])
            )
        for r, n in self.reasons.most_common():
            print(f"  no verdict ×{n}: {r}")
        for w, label in sorted(self.worst, reverse=True)[:3]:
            print(f"  worst: {label} (max |z| {w:.1f})")
        return ok


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--production", type=int, default=25, help="production surveys")
    ap.add_argument("--six-pass", type=int, default=25, help="six-pass bundles per scenario")
    ap.add_argument("--seed", type=int, default=0, help="first seed")
    ap.add_argument("--no-foreign", action="store_true")
    args = ap.parse_args()
    clock = time.perf_counter()
    tallies = []
    prod = Tally("production lines (harbour front, random offsets/speeds/lengths)")
    for s in range(args.seed, args.seed + args.production):
        prod.add(f"production seed {s}", production_run(s))
    tallies.append(prod)
    scenarios = ["montreal"] + (["random"] if has_random_scenario() else [])
    with tempfile.TemporaryDirectory() as tmp:
        for sc in scenarios:
            six = Tally(f"six-pass bundles ({sc})")
            for s in range(args.seed, args.seed + args.six_pass):
                b = simulated_bundle(sc, s, Path(tmp))
                if b is None:
                    six.reasons["bundle refused by the simulator"] += 1
                    continue
                six.add(f"{sc} seed {s}", bundle_run(b))
            tallies.append(six)
        if not args.no_foreign and FOREIGN.is_dir():
            foreign = Tally("foreign bundles (independent simulator)")
            for n in range(1, 7):
                with tarfile.open(FOREIGN / f"foreign-{n}.tar.gz") as tar:
                    tar.extractall(tmp, filter="data")
                foreign.add(f"foreign-{n}", bundle_run(Path(tmp) / f"foreign-{n}"))
            tallies.append(foreign)
    ok = all([t.report() for t in tallies])
    total = sum(t.shifts for t in tallies)
    print(
        f"\nall: mount_shift {total} over {sum(t.surveys for t in tallies)} fixed-mount surveys; "
        f"{time.perf_counter() - clock:.0f} s"
    )
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
