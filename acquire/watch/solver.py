"""The mount watch's block solves in a process of their own (:class:`BlockSolver`).

A block takes seconds of numpy and scipy, much of it holding the interpreter's lock; in a
thread of the daemon it stalled the event loop by up to 2 s on a loaded 2-core machine (worse
when that thread runs nicer than the loop: it holds the lock while it waits for the CPU). So one
long-lived worker process, started with ``spawn`` (never ``fork`` from a threaded daemon) and
:data:`WORKER_NICE` steps nicer than the daemon, takes one ``(BlockJob, WatchModel)`` at a time
over a pipe and sends back the :class:`~calib.watch.block.BlockEstimate`
(:func:`~acquire.watch.blockjob.run_block`, which never raises). The daemon's loop awaits a
thread that only sends and waits on the pipe.

A worker that dies (killed, out of memory) fails its block with a status naming the exit code
— no evidence for the test, never a crash — and the next block starts a new one. :meth:`close`
ends it at once (the daemon does not wait for a solve when it stops); a worker whose daemon
died ends when the pipe closes.
"""

from __future__ import annotations

import asyncio
import contextlib
import multiprocessing
import os
import threading
from typing import TYPE_CHECKING

from acquire.watch.blockjob import BlockJob, WatchModel, block_identity, run_block
from calib.watch.block import BlockEstimate

if TYPE_CHECKING:
    from multiprocessing.connection import Connection
    from multiprocessing.context import SpawnProcess

WORKER_NICE = 10  # the block solves run this much nicer than the acquisition


def _serve(conn, nice: int) -> None:  # the worker process
    if nice:
        with contextlib.suppress(OSError):
            os.nice(nice)
    while True:
        try:
            job, model = conn.recv()
        except (EOFError, OSError):  # the daemon closed the pipe (or died)
            return
        conn.send(run_block(job, model))


class BlockSolver:
    """One worker process for the block solves (module docstring)."""

    def __init__(self, nice: int = WORKER_NICE) -> None:
        self.nice = nice
        self.started = 0  # worker processes started (more than one: a worker died)
        self._proc: SpawnProcess | None = None
        self._conn: Connection | None = None  # the parent's end of the pipe to the worker
        self._lock = threading.Lock()  # one block at a time on the pipe

    def start(self) -> None:
        """Start the worker now, if it is not running (its imports take a second or two)."""
        with self._lock:
            self._ensure()

    def _ensure(self) -> None:
        if self._proc is not None and self._proc.is_alive():
            return
        self._stop()
        ctx = multiprocessing.get_context("spawn")
        parent, child = ctx.Pipe()
        proc = ctx.Process(target=_serve, args=(child, self.nice), name="mls-mount-watch", daemon=True)
        proc.start()
        child.close()
        self._proc, self._conn = proc, parent
        self.started += 1

    def solve_blocking(self, job: BlockJob, model: WatchModel) -> BlockEstimate:
        """The block's estimate from the worker (blocking: the caller's thread waits)."""
        with self._lock:
            self._ensure()
            proc, conn = self._proc, self._conn
            assert proc is not None, "_ensure started the worker"
            assert conn is not None, "_ensure opened its pipe"
            try:
                conn.send((job, model))
                return conn.recv()
            except (EOFError, OSError):
                proc.join(timeout=1.0)
                code = proc.exitcode
                self._stop()
                return BlockEstimate(
                    **block_identity(job, model),
                    status=f"failed (the solver process ended, exit code {code}; a new one takes the next block)",
                )

    async def solve(self, job: BlockJob, model: WatchModel) -> BlockEstimate:
        """:meth:`solve_blocking` off the event loop."""
        return await asyncio.to_thread(self.solve_blocking, job, model)

    def close(self) -> None:
        """End the worker at once (a solve under way is abandoned: its caller gets a failed block)."""
        proc = self._proc
        if proc is not None and proc.is_alive():
            proc.kill()
        with self._lock:
            self._stop()

    def _stop(self) -> None:
        if self._conn is not None:
            self._conn.close()
        if self._proc is not None:
            if self._proc.is_alive():
                self._proc.kill()
            self._proc.join(timeout=5.0)
        self._proc = self._conn = None
