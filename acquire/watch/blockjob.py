"""One block of the live mount watch, as the worker thread runs it: the block's navigation
becomes a :class:`~calib.core.trajectory.Trajectory` in the site's LGF (with the INS σ), its
kept returns a :class:`~calib.io.bundle.ScanPoints` (``pass_id`` = line id), and
:func:`calib.watch.block.estimate_block` adjusts the boresight correction — exactly what
:func:`calib.watch.runner.run_watch` does offline for each block.

Nothing here raises: a block that cannot be estimated (no navigation, no returns, an error in
the estimator) comes back as a :class:`~calib.watch.block.BlockEstimate` whose ``status`` says
why, which the sequential test takes as no evidence.

:func:`in_daemon_thread` runs the job off the daemon's event loop in a *daemon* thread: the
loop only awaits a future, and a daemon stopping mid-estimate does not wait for it (a block
takes seconds; ``asyncio.to_thread``'s executor is joined at exit). The thread runs at a lower
priority (:data:`WORKER_NICE`): on a loaded machine the acquisition's threads get the CPU first.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import threading
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field, replace

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
WORKER_NICE = 10  # the block solves run this much nicer than the acquisition


@dataclass(frozen=True)
class BlockJob:
    """A closed block: its lines and the buffers' arrays when it closed (snapshots: the
    selection runs in the worker thread, off the event loop)."""

    lines: tuple[Line, ...]
    nav_chunks: list  # NavBuffer.snapshot()
    point_chunks: list  # PointBuffer.snapshot()
    closed_mono_ns: int = 0

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


def run_block(job: BlockJob, model: WatchModel) -> BlockEstimate:
    """The estimate of one block (module docstring); never raises."""
    clock = time.perf_counter()
    lines = job.lines
    empty = dict(
        t_start_gps_s=lines[0].t_start_s if lines else float("nan"),
        t_end_gps_s=lines[-1].t_end_s if lines else float("nan"),
        pass_ids=job.line_ids,
        headings_deg=tuple(
            float(np.degrees(frames.wrap_2pi(ln.heading_rad - model.wall_azimuth_rad))) for ln in lines
        ),
    )
    try:
        traj = block_trajectory(job.nav(), model.frame, model.max_gap_s)
    except TrajectoryError as e:
        return BlockEstimate(**empty, status=f"no trajectory ({e})")
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
        return BlockEstimate(
            **empty,
            status=f"failed ({type(e).__name__}: {e})",
            extra={"traceback": traceback.format_exc(limit=-4)},
        )
    return replace(est, runtime_s=time.perf_counter() - clock)


def in_daemon_thread(fn: Callable, *args, nice: int = WORKER_NICE) -> asyncio.Future:
    """``fn(*args)`` in a new daemon thread, ``nice`` steps below the daemon's priority; a future
    of the running loop gets its result (or its exception). Cancelling the future abandons the
    thread's result."""
    loop = asyncio.get_running_loop()
    fut: asyncio.Future = loop.create_future()

    def settle(ok: bool, value) -> None:
        if fut.done():
            return
        if ok:
            fut.set_result(value)
        else:
            fut.set_exception(value)

    def target() -> None:
        if nice:  # background work: the acquisition's threads first (Linux: per thread)
            with contextlib.suppress(AttributeError, OSError):
                tid = threading.get_native_id()
                os.setpriority(os.PRIO_PROCESS, tid, os.getpriority(os.PRIO_PROCESS, tid) + nice)
        try:
            ok, value = True, fn(*args)
        except BaseException as e:  # noqa: BLE001 — handed to the awaiting task
            ok, value = False, e
        try:
            loop.call_soon_threadsafe(settle, ok, value)
        except RuntimeError:  # the loop has closed (the daemon stopped): nobody waits
            pass

    threading.Thread(target=target, name="mount-watch-block", daemon=True).start()
    return fut
