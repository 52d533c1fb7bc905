"""The scene the model does not describe: a quay wall that is not flat and moored hulls moving in
the swell between and during the lines raise no alarm and leave the corrections within their σ;
the hulls' patches are dropped as moving."""

from __future__ import annotations

import numpy as np
import pytest

from calib.sim.harbour import HULL_PREFIX
from calib.sim.production import ProductionSpec, simulate_production
from calib.watch.block import site_error_model, site_sigmas
from calib.watch.runner import run_watch
from calib.watch.sequential import MountTest


@pytest.fixture(scope="module")
def rough_run():
    spec = ProductionSpec(n_lines=5, line_length_m=250.0, wavy_wall=True, moving_hulls=True)
    sim = simulate_production("montreal", spec, seed=21)
    site = sim.site
    mount = sim.mount_true.with_boresight(np.radians(sim.truth["mount_calibrated"]))
    run = run_watch(
        sim.points,
        sim.trajectory_observed,
        mount,
        site_sigmas(site),
        site_error_model(site),
        site.wall_azimuth_rad,
    )
    return sim, run


def test_a_wavy_wall_and_moving_hulls_raise_no_alarm(rough_run):
    sim, run = rough_run
    assert run.alarm is None
    ok = [b for b in run.blocks if b.ok]
    assert len(ok) == len(run.blocks) == 4  # every line after the first closes a block
    for b in ok:
        d, cov, seen = MountTest().usable(b)
        assert seen[0]  # roll always; pitch only where planar patches see it (no verdict else)
        z = d[seen] / np.sqrt(np.diag(cov)[seen])
        assert np.all(np.abs(z) < 4.0), (b.pass_ids, z)


def test_the_hulls_patches_do_not_carry_the_estimate(rough_run):
    sim, run = rough_run
    # which surface each chosen patch lies on: the nearest true point's surface
    names = sim.scene.names
    from scipy.spatial import cKDTree

    tree = cKDTree(sim.p_true_lgf_m)
    on_hull = 0
    for b in run.blocks:
        for p in b.patches:
            _, i = tree.query(p.center_lgf_m)
            on_hull += names[sim.surface_index[i]].startswith(HULL_PREFIX)
    dropped = sum(len(b.moved_patches) for b in run.blocks)
    total = sum(len(b.patches) for b in run.blocks)
    assert on_hull <= 0.1 * total, (on_hull, total, dropped)
