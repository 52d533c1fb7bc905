"""A block of the mount watch on the simulator's production survey of a harbour front: the
correction is zero within its σ without an event, finds a step on the angle that moved, and a
block that sees nothing — one heading, no returns, no patch — is no evidence."""

from __future__ import annotations

import math

import numpy as np
import pytest

from calib.sim.production import MountEvent, ProductionSpec, simulate_production
from calib.watch.block import WatchOptions, estimate_block, site_error_model, site_sigmas
from calib.watch.runner import BlockCutter, run_watch

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


def test_a_step_of_roll_and_pitch_is_found(stepped):
    b = block_of(stepped, [1, 2])
    assert b.ok, b.status
    found = b.delta_rad[:2] / DEG
    sig = b.sigma_rad[:2] / DEG
    assert np.all(np.abs(found - [0.15, -0.15]) < 4 * sig + 0.01), (found, sig)
    assert np.all(np.abs(found) > 8 * sig)  # far from the calibrated mount


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
    assert [(b.pass_ids, b.status) for b in run.blocks] == [((1, 2, 3), "lines of one heading")]
    assert run.test.statistic.max() == 0.0


def test_blocks_close_on_two_headings_and_two_offsets():
    c = BlockCutter(WatchOptions())
    assert c.add(1, 0.0, [0.0, -12.0]) is None
    assert c.add(2, math.pi, [0.0, -12.1]) is None  # back at the same offset: yaw unseen yet
    assert c.add(3, 0.0, [0.0, -20.0]) == (1, 2, 3)
    assert c.add(4, math.pi, [0.0, -20.0]) is None
    assert c.add(5, 0.0, [5.0, -30.0]) == (4, 5)
    # at one offset a block closes at three lines; without positions at two headings
    assert [c.add(i, h, [0.0, -12.0]) for i, h in ((6, 0.0), (7, math.pi), (8, 0.0))] == [
        None,
        None,
        (6, 7, 8),
    ]
    c2 = BlockCutter(WatchOptions(max_lines_per_block=2))
    assert c2.add(1, 0.0) is None and c2.add(2, math.pi) == (1, 2)
