"""A line's heading relative to the wall, from a draw of its returns
(:func:`calib.extraction.points.line_headings`): the same as from every return, to a few
thousandths of a degree, and exactly that for a line with fewer returns than the draw."""

from __future__ import annotations

import math

import numpy as np

from calib.extraction.points import HEADING_SAMPLES, line_headings, pass_headings
from calib.sim.production import ProductionSpec, simulate_production


def test_a_lines_heading_from_a_draw_of_its_returns_is_its_heading_at_every_return():
    sim = simulate_production("montreal", ProductionSpec(n_lines=2, line_length_m=150.0), seed=5)
    pts, traj, wall, offset_s = sim.points, sim.trajectory_observed, sim.site.wall_azimuth_rad, 0.002
    yaw = traj.interpolate(pts.t_gps_s + offset_s).rpy_rad[:, 2]
    every = pass_headings(yaw, pts.pass_id, wall)
    drawn = line_headings(pts, traj, wall, offset_s)
    assert sorted(drawn) == sorted(every) and np.bincount(pts.pass_id).max() > 10 * HEADING_SAMPLES
    gap_deg = [math.degrees(abs(math.remainder(drawn[p] - every[p], 2 * math.pi))) for p in every]
    assert 0.0 < max(gap_deg) < 0.02, gap_deg  # a draw, not every return, and close
    first = np.flatnonzero(pts.pass_id == pts.pass_id[0])[: HEADING_SAMPLES // 2]
    whole = pass_headings(yaw[first], pts.pass_id[first], wall)
    assert line_headings(pts.select(first), traj, wall, offset_s) == whole
