"""The mount watch over a recorded survey: lines grouped into blocks, each block estimated and
fed to the sequential test, in time order — what the daemon does live, line by line, and what
``mls watch`` and the benchmark run offline.

:class:`BlockCutter` is the grouping both use: lines are added as they end; a block closes as
soon as its lines span :attr:`WatchOptions.min_heading_spread_deg` in heading (two lines sailed
in opposite directions, usually), so blocks never share a line and their estimates are
independent but for the POS errors' correlation across the turn between them.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from calib.boresight.errormodel import ErrorModel
from calib.core import frames
from calib.core.georef import Mount
from calib.core.trajectory import Trajectory
from calib.io.bundle import ScanPoints
from calib.watch.block import BlockEstimate, WatchOptions, block_ready, estimate_block
from calib.watch.sequential import MountAlarm, MountTest, WatchDesign


@dataclass
class BlockCutter:
    """Groups lines into blocks as they end.

    Roll and pitch need two headings; heading (yaw) needs two *distances* from the scene: a yaw
    change turns the scan plane about the vertical, which moves a point along the wall by its
    horizontal range times the change — the same world shift from either heading, so only lines
    at different offsets tell it from the scene. A block therefore closes when its headings span
    :attr:`WatchOptions.min_heading_spread_deg` and its lines lie
    :attr:`WatchOptions.min_offset_spread_m` apart across the track, or when it holds
    :attr:`WatchOptions.max_lines_per_block` lines (a survey at one offset: yaw stays unseen).
    A line given without its position counts as at the others' offset."""

    options: WatchOptions = field(default_factory=WatchOptions)
    pending: list[tuple[int, float, np.ndarray | None]] = field(default_factory=list)

    def add(self, line_id: int, heading_rad: float, position_ne_m=None) -> tuple[int, ...] | None:
        """Add a finished line (its relative heading and mean north/east position); the ids of
        a block when this line closes one."""
        pos = None if position_ne_m is None else np.asarray(position_ne_m, float)[:2]
        self.pending.append((int(line_id), float(heading_rad), pos))
        o = self.options
        if not block_ready([h for _, h, _ in self.pending], o):
            return None
        if self.offset_spread_m() >= o.min_offset_spread_m or len(self.pending) >= o.max_lines_per_block:
            ids = tuple(i for i, _, _ in self.pending)
            self.pending = []
            return ids
        return None

    def offset_spread_m(self) -> float:
        """The largest distance of a pending line's position across another's track."""
        best = 0.0
        for _, h, p in self.pending:
            if p is None:
                continue
            n = np.array([-np.sin(h), np.cos(h)])  # across the track (the relative frame: any rotation)
            for _, _, q in self.pending:
                if q is not None:
                    best = max(best, abs(float((q - p) @ n)))
        return best


def line_geometry(
    points: ScanPoints, trajectory: Trajectory, wall_azimuth_rad: float
) -> dict[int, tuple[float, np.ndarray]]:
    """Each line's mean heading relative to the wall (radians) and mean north/east position in
    the same relative frame (m), from the trajectory at its returns (every 50th suffices)."""
    out = {}
    c, s = np.cos(-wall_azimuth_rad), np.sin(-wall_azimuth_rad)
    for pid in points.pass_ids():
        t = points.t_gps_s[points.pass_id == pid][::50]
        poses = trajectory.interpolate(t)
        yaw = poses.rpy_rad[:, 2]
        mean = np.arctan2(np.mean(np.sin(yaw)), np.mean(np.cos(yaw)))
        ne = poses.p_lgf_m[:, :2].mean(axis=0)
        out[int(pid)] = (
            float(frames.wrap_2pi(mean - wall_azimuth_rad)),
            np.array([c * ne[0] - s * ne[1], s * ne[0] + c * ne[1]]),
        )
    return out


@dataclass
class WatchRun:
    blocks: list[BlockEstimate]
    test: MountTest
    alarm: MountAlarm | None
    states: list[dict]  # the test's published state after each block
    line_order: list[int]


def run_watch(
    points: ScanPoints,
    trajectory: Trajectory,
    mount: Mount,
    sigmas: dict,
    model: ErrorModel,
    wall_azimuth_rad: float,
    options: WatchOptions = WatchOptions(),
    design: WatchDesign = WatchDesign(),
    progress: Callable[[int, int, BlockEstimate], None] | None = None,
) -> WatchRun:
    """The watch over every line of ``points`` (``pass_id`` = line id), lines in the order they
    were sailed (their first return's time)."""
    ids = points.pass_ids()
    first = {int(p): float(points.t_gps_s[points.pass_id == p].min()) for p in ids}
    order = sorted(first, key=first.__getitem__)
    geometry = line_geometry(points, trajectory, wall_azimuth_rad)
    cutter = BlockCutter(options)
    groups = [g for g in (cutter.add(i, *geometry[i]) for i in order) if g is not None]
    test = MountTest(design)
    states = []
    for k, g in enumerate(groups):
        blk = estimate_block(
            points.select(np.isin(points.pass_id, g)),
            trajectory,
            mount,
            sigmas,
            model,
            wall_azimuth_rad,
            options,
        )
        test.update(blk)
        states.append(test.state())
        if progress is not None:
            progress(k + 1, len(groups), blk)
    return WatchRun(test.blocks, test, test.alarm, states, order)
