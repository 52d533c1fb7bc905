"""One block of the live mount watch, as the worker process runs it: the block's navigation
becomes a :class:`~calib.core.trajectory.Trajectory` in the site's LGF (with the INS σ), its
kept returns a :class:`~calib.io.bundle.ScanPoints` (``pass_id`` = line id), and
:func:`calib.watch.block.estimate_block` adjusts the boresight correction — exactly what
:func:`calib.watch.runner.run_watch` does offline for each block.

Nothing here raises: a block that cannot be estimated (no navigation, no returns, an error in
the estimator) comes back as a :class:`~calib.watch.block.BlockEstimate` whose ``status`` says
why, which the sequential test takes as no evidence.

The daemon runs it in a worker process (:mod:`acquire.watch.solver`).
"""

from __future__ import annotations

import time
import traceback
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from acquire.watch.buffers import nav_rows, select_points
from acquire.watch.lines import Line
from calib.boresight.errormodel import ErrorModel
from calib.core import frames
from calib.core.georef import Mount
from calib.core.trajectory import Trajectory, TrajectoryError
from calib.io.bundle import ScanPoints
from calib.watch.block import BlockEstimate, WatchOptions, estimate_block


@dataclass(frozen=True)
class WatchModel:
    """What every block is estimated with: the calibrated mount, the site's LGF, wall azimuth,
    observation sigmas and POS error model."""

    mount: Mount
    frame: frames.LocalFrame
    wall_azimuth_rad: float
    sigmas: dict
    error_model: ErrorModel
    options: WatchOptions = field(default_factory=WatchOptions)
    max_gap_s: float = 1.0  # the trajectory's: returns in a longer navigation gap are dropped


NAV_MARGIN_S = 1.0  # navigation kept on both sides of a block's lines


@dataclass(frozen=True)
class BlockJob:
    """A closed block: its lines and the buffers' arrays when it closed (snapshots: the
    selection runs in the worker process, off the event loop)."""

    lines: tuple[Line, ...]
    nav_chunks: list  # NavBuffer.snapshot()
    point_chunks: list  # PointBuffer.snapshot()
    closed_mono_ns: int = 0
    family: int = 0  # the block's (calib.watch.runner.BlockCutter)

    @property
    def line_ids(self) -> tuple[int, ...]:
        return tuple(ln.id for ln in self.lines)

    def nav(self) -> np.ndarray:
        t0 = min(ln.t_start_s for ln in self.lines) - NAV_MARGIN_S
        t1 = max(ln.t_end_s for ln in self.lines) + NAV_MARGIN_S
        return nav_rows(self.nav_chunks, t0, t1)

    def points(self):
        """(line id, GPS s, range, angle) of the returns inside the lines."""
        return select_points(self.point_chunks, [(ln.id, ln.t_start_s, ln.t_end_s) for ln in self.lines])


def _fill(sig: np.ndarray, t: np.ndarray) -> np.ndarray | None:
    """The per-epoch σ with the epochs that lack some interpolated in time; None when fewer
    than half the epochs carry all six."""
    good = np.all(np.isfinite(sig) & (sig > 0), axis=1)
    if good.all():
        return sig
    if good.sum() < max(2, 0.5 * good.size):
        return None
    out = sig.copy()
    for j in range(sig.shape[1]):
        out[~good, j] = np.interp(t[~good], t[good], sig[good, j])
    return out


def block_trajectory(nav: np.ndarray, frame: frames.LocalFrame, max_gap_s: float = 1.0) -> Trajectory:
    """The trajectory of a block's INS epochs (rows of :class:`~acquire.watch.buffers.NavBuffer`)
    in ``frame``; :class:`TrajectoryError` when it has fewer than two usable epochs."""
    ok = np.all(np.isfinite(nav[:, :7]), axis=1)
    nav = nav[ok]
    if nav.shape[0] < 2:
        raise TrajectoryError(f"{nav.shape[0]} usable INS epochs")
    sig = _fill(nav[:, 7:13], nav[:, 0])
    return Trajectory.from_geodetic(
        nav[:, 0],
        nav[:, 1],
        nav[:, 2],
        nav[:, 3],
        nav[:, 4:7],
        frame,
        sigma_p_m=None if sig is None else sig[:, :3],
        sigma_rpy_rad=None if sig is None else sig[:, 3:],
        max_gap_s=max_gap_s,
        name="watch block",
    )


def block_identity(job: BlockJob, model: WatchModel) -> dict:
    """The fields of a :class:`BlockEstimate` that name the block (times, lines, headings)."""
    lines = job.lines
    return dict(
        t_start_gps_s=lines[0].t_start_s if lines else float("nan"),
        t_end_gps_s=lines[-1].t_end_s if lines else float("nan"),
        pass_ids=job.line_ids,
        headings_deg=tuple(
            float(np.degrees(frames.wrap_2pi(ln.heading_rad - model.wall_azimuth_rad))) for ln in lines
        ),
    )


def run_block(job: BlockJob, model: WatchModel) -> BlockEstimate:
    """The estimate of one block (module docstring); never raises."""
    clock = time.perf_counter()
    empty = block_identity(job, model)
    try:
        traj = block_trajectory(job.nav(), model.frame, model.max_gap_s)
    except TrajectoryError as e:
        return BlockEstimate(**empty, status=f"no trajectory ({e})")
    except Exception as e:  # noqa: BLE001 — as below
        return _failed(empty, e)
    try:
        line_id, t, r, a = job.points()
        keep = ~traj.uncovered(t + model.mount.time_offset_s)
        points = ScanPoints(line_id[keep], t[keep], r[keep], a[keep], np.zeros(int(keep.sum()), np.float32))
        if len(points) == 0:
            return BlockEstimate(**empty, status="no returns in the range window")
        est = estimate_block(
            points,
            traj,
            model.mount,
            model.sigmas,
            model.error_model,
            model.wall_azimuth_rad,
            model.options,
        )
    except Exception as e:  # noqa: BLE001 — a block that fails is no evidence, never a crash
        return _failed(empty, e)
    return replace(est, runtime_s=time.perf_counter() - clock)


def _failed(identity: dict, e: Exception) -> BlockEstimate:
    """A block that failed, its status naming the error and where it was raised."""
    where = traceback.extract_tb(e.__traceback__)[-1]
    return BlockEstimate(
        **identity, status=f"failed ({type(e).__name__}: {e}; {Path(where.filename).name}:{where.lineno})"
    )
