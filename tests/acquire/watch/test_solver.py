"""The block solves' worker process (:mod:`acquire.watch.solver`): a real spawned process, a
block that kills it, and the next block on a new one."""

from __future__ import annotations

import asyncio
import os
import re
import threading
from pathlib import Path

import numpy as np

from acquire.watch.blockjob import BlockJob, WatchModel
from acquire.watch.lines import Line
from acquire.watch.solver import BlockSolver
from calib.boresight.errormodel import ErrorModel
from calib.core import frames
from calib.core.georef import Mount
from tests.waiting import wait_until

MODEL = WatchModel(
    mount=Mount(np.zeros(3), np.zeros(3), np.zeros(3)),
    frame=frames.LocalFrame(45.5, -73.55, 0.0),
    wall_azimuth_rad=0.0,
    sigmas={},
    error_model=ErrorModel("gauss_markov", 60.0),
)
LINES = (
    Line(7, 100.0, 160.0, 0.0, None, "heading", "turn"),
    Line(8, 170.0, 230.0, np.pi, None, "heading", "turn"),
)


class _Exits:
    """Unpickled in the worker, it ends the process (a worker killed mid-block, as the kernel's
    OOM killer would)."""

    def __reduce__(self):
        return (os._exit, (3,))


def test_a_block_is_solved_in_another_process_and_a_dead_worker_fails_only_its_block():
    solver = BlockSolver()
    try:
        # no navigation: the worker answers with the block's status (nothing raised across)
        first = asyncio.run(solver.solve(BlockJob(LINES, [], []), MODEL))
        assert first.pass_ids == (7, 8)
        assert first.status.startswith("no trajectory")
        assert first.headings_deg == (0.0, 180.0)
        assert solver._proc is not None  # (the worker that answered)
        pid = solver._proc.pid
        assert pid != os.getpid()
        assert solver.started == 1
        # a block that ends the worker: failed, with the exit code; the next one gets a new worker
        dead = solver.solve_blocking(BlockJob(LINES, [_Exits()], []), MODEL)
        assert re.fullmatch(r"failed \(the solver process ended, exit code 3; .*\)", dead.status), dead.status
        assert dead.pass_ids == (7, 8)
        assert not dead.ok
        again = solver.solve_blocking(BlockJob(LINES, [], []), MODEL)
        assert again.status.startswith("no trajectory")
        assert solver.started == 2
        assert solver._proc is not None
        assert solver._proc.pid != pid
    finally:
        solver.close()
    assert solver._proc is None


def _a_long_solve(flag: str, fifo: str) -> None:
    """In the worker: says it has begun (``flag``), then waits on ``fifo``, a named pipe that
    the test holds open and never writes (the solve never ends while the test runs; the test
    lets go of it at its end); ``flag``.done if it ever ends."""
    Path(flag).write_text("busy")
    with open(fifo, "rb") as never_written:
        never_written.read(1)  # the long solve itself
    Path(flag + ".done").write_text("done")


class _LongSolve:
    """Unpickled in the worker, it keeps it busy until the test lets go (a long solve)."""

    def __init__(self, flag: Path, fifo: Path):
        self.flag, self.fifo = str(flag), str(fifo)

    def __reduce__(self):
        return (_a_long_solve, (self.flag, self.fifo))


def test_close_ends_the_worker_at_once_and_the_waiting_block_fails(tmp_path):
    fifo = tmp_path / "solve.fifo"
    os.mkfifo(fifo)
    held = os.open(fifo, os.O_RDWR)  # the solve's other end: open, never written
    try:
        _close_during_a_long_solve(tmp_path / "solving", fifo)
    finally:
        os.close(held)


def _close_during_a_long_solve(flag: Path, fifo: Path) -> None:
    solver = BlockSolver()
    solver.start()
    proc = solver._proc
    assert proc is not None  # (started)
    out: list = []
    waiting = threading.Thread(
        target=lambda: out.append(solver.solve_blocking(BlockJob(LINES, [_LongSolve(flag, fifo)], []), MODEL))
    )
    waiting.start()
    wait_until(flag.exists, 60, "the worker to begin the long solve")
    solver.close()
    waiting.join(10)
    assert not waiting.is_alive()
    assert not proc.is_alive()
    assert proc.exitcode == -9
    # at once: killed in the middle of the solve, not waited for (it would never end)
    assert not Path(f"{flag}.done").exists()
    assert out, out
    assert out[0].status.startswith("failed (the solver process ended, exit code -9"), out
    # a later block starts a new worker (a consumer restarted by the supervisor)
    later = solver.solve_blocking(BlockJob(LINES, [], []), MODEL)
    assert later.status.startswith("no trajectory")
    assert solver.started == 2
    solver.close()
