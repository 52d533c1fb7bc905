"""The mount watch over a recorded survey: lines grouped into blocks, each block estimated and
fed to the sequential test, in time order — what the daemon does live, line by line, and what
``mls watch`` and the benchmark run offline.

:class:`BlockCutter` is the grouping both use: every line that ends closes a block with the
lines just before it, as soon as they span :attr:`WatchOptions.min_heading_spread_deg` in
heading — usually the line and the one sailed back before it. So a mount change is seen in the
first pair of lines sailed wholly after it, wherever in the survey it falls: at most about two
lines after the line it happened in. Consecutive blocks share a line, so they are dealt into
:data:`FAMILIES` interleaved families in which blocks never share a line (the sequential test
runs one CUSUM per family: within a family blocks are independent but for the POS errors'
correlation across the turns between them).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from calib.boresight.errormodel import ErrorModel
from calib.core.georef import Mount
from calib.core.trajectory import Trajectory
from calib.extraction.points import line_headings
from calib.io.bundle import ScanPoints
from calib.watch.block import BlockEstimate, WatchOptions, block_ready, estimate_block
from calib.watch.sequential import FAMILIES, MountAlarm, MountTest, WatchDesign


@dataclass(frozen=True)
class Block:
    """The lines of a block, in the order sailed, and its family (0 or 1)."""

    line_ids: tuple[int, ...]
    family: int


@dataclass
class BlockCutter:
    """Cuts blocks from lines as they end (module docstring).

    A block is the shortest run of the latest lines, ending with the one just added and at most
    :attr:`WatchOptions.max_lines_per_block` long, whose headings span
    :attr:`WatchOptions.min_heading_spread_deg`. It joins a family whose last block ended before
    its first line (of two, the one that ended later: the families then alternate); when
    neither has, the block is not formed. Lines sailed one after another at different offsets
    also give yaw (a yaw change turns the scan plane about the vertical, which moves a point
    along the wall by its horizontal range times the change: only lines at different distances
    tell that from the scene); those at one offset give roll and pitch."""

    options: WatchOptions = field(default_factory=WatchOptions)
    recent: list[tuple[int, int, float]] = field(default_factory=list)  # (number, id, heading)
    last_end: list[int] = field(default_factory=lambda: [-1] * FAMILIES)  # a family's last line
    used: set[int] = field(default_factory=set)  # numbers of the recent lines in some block
    added: int = 0
    dropped: int = 0  # lines that left the window without being in any block

    def add(self, line_id: int, heading_rad: float) -> Block | None:
        """Add a finished line (its heading, relative to the wall); the block it closes."""
        o = self.options
        n = self.added
        self.added += 1
        self.recent.append((n, int(line_id), float(heading_rad)))
        while len(self.recent) > o.max_lines_per_block:
            old = self.recent.pop(0)[0]
            if old not in self.used:
                self.dropped += 1
            self.used.discard(old)
        for k in range(2, len(self.recent) + 1):
            run = self.recent[-k:]
            if not block_ready([h for _, _, h in run], o):
                continue
            free = [f for f in range(FAMILIES) if self.last_end[f] < run[0][0]]
            if not free:
                return None
            f = max(free, key=lambda i: self.last_end[i])
            self.last_end[f] = n
            self.used.update(m for m, _, _ in run)
            return Block(tuple(i for _, i, _ in run), f)
        return None

    @property
    def pending(self) -> list[int]:
        """The ids of the recent lines no block has taken yet (waiting for a partner)."""
        return [i for m, i, _ in self.recent if m not in self.used]

    @property
    def kept(self) -> list[int]:
        """The ids of the lines a later block may still take."""
        return [i for _, i, _ in self.recent]


@dataclass
class WatchRun:
    blocks: list[BlockEstimate]
    families: list[int]  # each block's (BlockCutter)
    test: MountTest
    alarm: MountAlarm | None
    states: list[dict]  # the test's published state after each block
    line_order: list[int]


#: the watch's options and test design when the caller gives none (frozen, shared)
_DEFAULT_OPTIONS = WatchOptions()
_DEFAULT_DESIGN = WatchDesign()


def run_watch(
    points: ScanPoints,
    trajectory: Trajectory,
    mount: Mount,
    sigmas: dict,
    model: ErrorModel,
    wall_azimuth_rad: float,
    options: WatchOptions = _DEFAULT_OPTIONS,
    design: WatchDesign = _DEFAULT_DESIGN,
    progress: Callable[[int, int, BlockEstimate], None] | None = None,
) -> WatchRun:
    """The watch over every line of ``points`` (``pass_id`` = line id), lines in the order they
    were sailed (their first return's time)."""
    ids = points.pass_ids()
    first = {int(p): float(points.t_gps_s[points.pass_id == p].min()) for p in ids}
    order = sorted(first, key=first.__getitem__)
    headings = line_headings(points, trajectory, wall_azimuth_rad)
    cutter = BlockCutter(options)
    groups = [g for g in (cutter.add(i, headings[i]) for i in order) if g is not None]
    test = MountTest(design)
    states = []
    for k, g in enumerate(groups):
        blk = estimate_block(
            points.select(np.isin(points.pass_id, g.line_ids)),
            trajectory,
            mount,
            sigmas,
            model,
            wall_azimuth_rad,
            options,
        )
        test.update(blk, g.family)
        states.append(test.state())
        if progress is not None:
            progress(k + 1, len(groups), blk)
    return WatchRun(test.blocks, test.families, test, test.alarm, states, order)
