"""A block of the mount watch on the simulator's production survey of a harbour front: the
correction is zero within its σ without an event, finds a step on the angle that moved, and a
block that sees nothing — one heading, no returns, no patch — is no evidence."""

from __future__ import annotations

import math

import numpy as np
import pytest

from calib.sim.production import MountEvent, ProductionSpec, simulate_production
from calib.watch.block import WatchOptions, estimate_block, site_error_model, site_sigmas
from calib.watch.runner import Block, BlockCutter, run_watch

DEG = math.pi / 180.0


def calibrated(sim):
    return sim.mount_true.with_boresight(np.radians(sim.truth["mount_calibrated"]))


def block_of(sim, ids, options=WatchOptions()):
    pts = sim.points.select(np.isin(sim.points.pass_id, ids))
    site = sim.site
    return estimate_block(
        pts, sim.trajectory_observed, calibrated(sim), site_sigmas(site), site_error_model(site),
        site.wall_azimuth_rad, options,
    )  # fmt: skip


@pytest.fixture(scope="module")
def steady():
    return simulate_production("montreal", ProductionSpec(n_lines=3, line_length_m=250.0), seed=11)


@pytest.fixture(scope="module")
def stepped():
    # the mount moved before the survey began: every line sees the step
    ev = MountEvent(t_s=0.0, step_rad=np.radians([0.15, -0.15, 0.0]))
    return simulate_production(
        "montreal", ProductionSpec(n_lines=2, line_length_m=250.0, mount_event=ev), seed=12
    )


def test_a_steady_mount_gives_a_correction_within_its_sigma(steady):
    b = block_of(steady, [1, 2])
    assert b.ok, b.status
    assert sorted(round(h) % 360 for h in b.headings_deg) == [0, 180]
    assert len(b.patches) >= 20
    sigma_deg = b.sigma_rad / DEG
    assert sigma_deg[0] < 0.02 and sigma_deg[1] < 0.03  # roll and pitch resolved
    z = b.delta_rad / b.sigma_rad
    assert np.all(np.abs(z[:2]) < 4.0), (b.delta_rad / DEG, sigma_deg)
    # the report names the lines the patches came from
    assert {p for u in b.patches for p in u.pass_ids} == {1, 2}
    assert b.as_dict()["status"] == "ok"


def test_the_harbour_piles_are_tie_cylinders_of_the_block(steady):
    """The piles are not dropped as curved patches: the block chooses several as cylinders, each
    where the simulator put a pile (axis within 3 cm)."""
    b = block_of(steady, [1, 2])
    assert b.ok, b.status
    cyls = [u for u in b.patches if u.name.startswith("cyl_")]
    assert len(cyls) >= 3, [u.name for u in b.patches]
    piles = np.array([c.center_m[:2] for c in steady.scene.cylinders])
    for u in cyls:
        assert np.min(np.hypot(*(piles - np.array(u.center_lgf_m[:2])).T)) < 0.03, u


def test_an_angle_the_block_does_not_resolve_is_held_and_carries_no_correlation(steady):
    # lines 1 and 2 are sailed at one offset: yaw is not resolved (only ranges that differ tell
    # it from the scene); it is held at the calibrated value while roll and pitch are solved
    b = block_of(steady, [1, 2])
    free = block_of(steady, [1, 2], WatchOptions(max_sigma_rad=np.inf))
    # judged at the calibrated mount, where the watch tests: yaw there is not resolved
    assert b.held == (False, False, True) and free.held == (False, False, False)
    assert b.sigma_rad[2] > WatchOptions().max_sigma_rad
    assert np.all(b.cov_rad2[2, :2] == 0.0) and np.all(b.cov_rad2[:2, 2] == 0.0)
    assert b.delta_rad[2] == 0.0  # held at the calibrated value: no evidence either way
    assert free.cov_rad2[2, :2].any()  # left free, yaw is correlated with roll and pitch
    # held, roll and pitch are conditional on yaw: their σ no larger, their values within 4σ
    assert np.all(b.sigma_rad[:2] <= free.sigma_rad[:2] * 1.01)  # (the variance factors differ a little)
    assert np.all(np.abs(b.delta_rad[:2]) < 4.0 * b.sigma_rad[:2]), b.delta_rad / DEG


def test_a_step_of_roll_and_pitch_is_found(stepped):
    b = block_of(stepped, [1, 2])
    assert b.ok, b.status
    found = b.delta_rad[:2] / DEG
    sig = b.sigma_rad[:2] / DEG
    assert np.all(np.abs(found - [0.15, -0.15]) < 4 * sig + 0.01), (found, sig)
    # far from the calibrated mount (σ includes the patch groups' dispersion, up to ~1.5× the model's)
    assert np.all(np.abs(found) > 5 * sig)


def test_one_heading_and_an_empty_window_are_no_evidence(steady):
    one = block_of(steady, [1])
    assert not one.ok and one.status == "lines of one heading"
    assert one.delta_rad is None and np.all(np.isinf(one.sigma_rad))
    empty = block_of(steady, [1, 2], WatchOptions(min_range_m=0.3, max_range_m=0.5))
    assert not empty.ok and "no returns" in empty.status


def test_a_line_that_sees_no_patch_raises_no_alarm(steady):
    # line 2 sees only what lies beyond the watch's range window: its block has no evidence
    pts = steady.points
    keep = (pts.pass_id != 2) | (pts.range_m > WatchOptions().max_range_m)
    assert np.count_nonzero(keep & (pts.pass_id == 2)) > 100
    sim_pts = pts.select(keep)
    site = steady.site
    run = run_watch(
        sim_pts, steady.trajectory_observed, calibrated(steady), site_sigmas(site), site_error_model(site),
        site.wall_azimuth_rad,
    )  # fmt: skip
    assert run.alarm is None
    assert [(b.pass_ids, b.status) for b in run.blocks] == [
        ((1, 2), "lines of one heading"),
        ((2, 3), "lines of one heading"),
    ]
    assert run.test.statistic.max() == 0.0


def test_every_line_closes_a_block_with_the_one_before_and_families_share_no_line():
    c = BlockCutter(WatchOptions())
    got = [c.add(i, h) for i, h in ((1, 0.0), (2, math.pi), (3, 0.0), (4, math.pi))]
    assert got == [None, Block((1, 2), 0), Block((2, 3), 1), Block((3, 4), 0)]
    # two lines of one heading: the next line of the other heading takes the later one only
    assert c.add(5, math.pi) is None and c.pending == [5]  # 4 and 5: one heading
    assert c.add(6, 0.0) == Block((5, 6), 0) and c.add(7, math.pi) == Block((6, 7), 1)
    # lines of one heading: a line that leaves the window in no block is dropped
    assert [c.add(i, math.pi) for i in (8, 9, 10)] == [None, None, None]
    assert c.dropped == 0 and c.pending == [8, 9, 10]
    assert c.add(11, math.pi) is None and c.dropped == 1 and c.kept == [9, 10, 11]
    # a block whose first line is in both families' last blocks is not formed
    d = BlockCutter(WatchOptions())
    assert [d.add(i, h) for i, h in ((1, 0.0), (2, math.pi), (3, 0.0))] == [
        None,
        Block((1, 2), 0),
        Block((2, 3), 1),
    ]
    assert d.add(4, 0.1) is None and d.add(5, math.pi) == Block((4, 5), 1)
    # three lines to span the heading: a line at 60° between lines at 0° and 120°
    e = BlockCutter(WatchOptions())
    assert [e.add(i, np.radians(h)) for i, h in ((1, 0.0), (2, 60.0), (3, 120.0))] == [
        None,
        None,
        Block((1, 2, 3), 0),
    ]
    f = BlockCutter(WatchOptions(max_lines_per_block=2))
    assert [f.add(i, np.radians(h)) for i, h in ((1, 0.0), (2, 60.0), (3, 120.0))] == [None, None, None]
    assert f.dropped == 1
    with pytest.raises(ValueError, match="max_lines_per_block"):
        WatchOptions(max_lines_per_block=1)


def test_a_feature_its_own_points_leave_free_is_dropped_not_the_block():
    """Two short, sparse lines and a mount 0.3° off: a pile seen on too narrow an arc leaves its
    radius and centre free (the normal equations singular along them); the block drops it, names
    it, and solves on the rest instead of giving up."""
    sim = simulate_production(
        "montreal", ProductionSpec(n_lines=2, line_length_m=150.0, rate_scale=0.005), seed=23
    )
    off = sim.mount_true.with_boresight(
        np.asarray(sim.mount_true.boresight_rad) + np.radians([0.3, -0.25, 0.35])
    )
    site = sim.site
    b = estimate_block(
        sim.points, sim.trajectory_observed, off, site_sigmas(site), site_error_model(site),
        site.wall_azimuth_rad, WatchOptions(max_patches=120, prior_sigma_rad=np.radians(5.0), max_sigma_rad=np.radians(0.5)),
    )  # fmt: skip
    assert b.ok, b.status
    assert b.undetermined_features and all(n.startswith("cyl_") for n in b.undetermined_features)
    assert not set(b.undetermined_features) & {u.name for u in b.patches}
    assert b.as_dict()["undetermined_features"] == list(b.undetermined_features)
