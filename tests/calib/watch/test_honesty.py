"""The watch on fixed mounts whose blocks are weak or whose data another simulator made: the
six-pass calibration pattern of the project's simulator (montreal, seed 3: the oblique pairs see
yaw only through a few patches of a low wall) and the foreign bundles (an independent simulator:
tilted mounts, other wall azimuths, standoffs 10–25 m, a POS τ not given), each watched with the
true boresight as its calibration. No ``mount_shift``; a block with a verdict is within a few σ
of the truth; a block that cannot be trusted is no verdict, with its reason."""

from __future__ import annotations

import json
import subprocess
import sys
import tarfile
from pathlib import Path

import numpy as np
import pytest

from calib.io.bundle import read_bundle
from calib.watch.block import site_error_model, site_sigmas
from calib.watch.runner import WatchRun, run_watch
from calib.watch.sequential import MountTest

#: one worker computes the module's costly fixtures once (spread over two, each computed them)
pytestmark = pytest.mark.xdist_group("watch-honesty")

FOREIGN = Path(__file__).resolve().parents[2] / "data" / "foreign"
MAX_Z = 4.0  # |Δ − truth| / σ of an angle with a verdict


def truth_run(bundle_dir: Path) -> WatchRun:
    """The watch over a bundle (its passes as lines) with the true boresight as calibration."""
    b = read_bundle(bundle_dir)
    t = json.loads((bundle_dir / "truth.json").read_text())["boresight_deg"]
    mount = b.site.mount.with_boresight(np.radians([t["roll"], t["pitch"], t["yaw"]]))
    site = b.site
    return run_watch(
        b.points, b.trajectory, mount, site_sigmas(site), site_error_model(site), site.wall_azimuth_rad
    )


def verdict_z(run: WatchRun) -> np.ndarray:
    """(Δ − truth)/σ of every angle a block gives a verdict on (truth = the calibration)."""
    out = []
    for b in run.blocks:
        d, cov, seen = MountTest().usable(b)
        out += list(d[seen] / np.sqrt(np.diag(cov)[seen]))
    return np.asarray(out)


@pytest.fixture(scope="module")
def montreal3(tmp_path_factory) -> WatchRun:
    out = tmp_path_factory.mktemp("mtl3") / "bundle"
    mls = Path(sys.executable).with_name("mls")
    cmd = [str(mls), "sim", "dataset", "--scenario", "montreal", "--seed", "3", "--out", str(out)]
    subprocess.run(cmd, check=True, capture_output=True)
    return truth_run(out)


def test_the_six_pass_pattern_raises_no_alarm_and_its_verdicts_hold(montreal3):
    run = montreal3
    assert run.alarm is None
    assert [b.pass_ids for b in run.blocks] == [(1, 2), (2, 3), (3, 4), (4, 5), (5, 6)]
    z = verdict_z(run)
    assert z.size >= 3 and np.all(np.abs(z) < MAX_Z), z
    # the pairs sailed back along one oblique track resolve no angle to 0.1° at the calibrated
    # mount: no verdict (their free yaw wandered to +3.8° and −3.4°, 0.4° σ, reported before)
    for b in run.blocks[2::2]:
        assert not b.ok and b.status.startswith("no verdict: no angle resolved to 0.100°"), b.status
        assert b.delta_rad is None and not MountTest().usable(b)[2].any()
    # lines 1–2, sailed there and back at one offset, resolve roll only
    assert run.blocks[0].held == (False, True, True)


def foreign_run(n: int, tmp_path: Path) -> WatchRun:
    with tarfile.open(FOREIGN / f"foreign-{n}.tar.gz") as tar:
        tar.extractall(tmp_path, filter="data")
    return truth_run(tmp_path / f"foreign-{n}")


@pytest.fixture(scope="module")
def foreign_runs(tmp_path_factory) -> dict[int, WatchRun]:
    return {n: foreign_run(n, tmp_path_factory.mktemp(f"foreign{n}")) for n in range(1, 7)}


@pytest.mark.slow
def test_no_foreign_bundle_with_a_true_calibration_raises_an_alarm(foreign_runs):
    for n, run in foreign_runs.items():
        assert run.alarm is None, (n, run.alarm.message())
        for b in run.blocks:
            assert b.ok or b.status.startswith(("no verdict", "not observable", "no tie patch")), b.status
        assert sum(b.ok for b in run.blocks) >= 3, n  # most blocks still give a verdict


@pytest.mark.slow
@pytest.mark.parametrize("n", range(1, 7))
def test_a_foreign_bundles_verdicts_are_within_their_sigma(n, foreign_runs):
    # linearized at the measured ranges the blocks of lines 2–3 were 4–6σ off on foreign-3, 4
    # and 6 (calib.boresight.gls; tests/calib/watch/test_linearization.py)
    z = verdict_z(foreign_runs[n])
    assert z.size >= 3 and np.all(np.abs(z) < MAX_Z), z


def production(seed: int):
    """A production survey of random geometry along the harbour front, fixed mount (the
    benchmark's draw, benchmarks/watch_honesty.py, with fewer and shorter lines)."""
    from calib.sim.production import ProductionSpec, simulate_production

    rng = np.random.default_rng([seed, 24])
    offsets = tuple(float(x) for x in np.round(rng.uniform(10.0, 55.0, rng.integers(1, 4)), 1))
    lo = float(rng.uniform(1.2, 3.0))
    spec = ProductionSpec(
        n_lines=4,
        offsets_m=offsets,
        line_length_m=float(rng.uniform(150.0, 250.0)),
        speeds_mps=(lo, lo + float(rng.uniform(0.0, 1.5))),
        wavy_wall=bool(rng.random() < 0.3),
    )
    return simulate_production("montreal", spec, seed=1000 + seed)


@pytest.mark.slow
def test_fixed_mount_production_surveys_of_random_geometry_are_honest():
    # the ≥ 50-survey version: benchmarks/watch_honesty.py
    zs = []
    for seed in (0, 1, 2):
        sim = production(seed)
        site = sim.site
        mount = sim.mount_true.with_boresight(np.radians(sim.truth["mount_calibrated"]))
        run = run_watch(
            sim.points, sim.trajectory_observed, mount, site_sigmas(site), site_error_model(site),
            site.wall_azimuth_rad,
        )  # fmt: skip
        assert run.alarm is None, (seed, run.alarm.message())
        zs.append(verdict_z(run))
    z = np.concatenate(zs)
    assert z.size >= 12 and np.all(np.abs(z) < MAX_Z), z
    rms = float(np.sqrt(np.mean(z**2)))
    assert 0.6 < rms < 1.4, rms  # a dozen or two of z: the benchmark holds the 0.8–1.25 goal
