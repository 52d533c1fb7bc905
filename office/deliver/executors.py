"""Where ``mls georef``'s tasks run: in this process, or on a Dask cluster.

- :class:`InProcess` (no Dask option): the tasks one after the other, here.
- :class:`DaskExecutor`: ``workers=N`` starts a ``dask.distributed.LocalCluster`` of N worker
  processes (one thread each: the tasks are numpy- and LAZ-bound and hold the GIL in places),
  ``scheduler="tcp://host:8786"`` connects to a cluster that is already running (its workers
  must see the same output directory, e.g. a shared disk, and have marine-mls installed). A
  worker that dies is replaced by its nanny and its tasks run again elsewhere (they are
  idempotent: :mod:`office.deliver.chunkjob`); a task that kills
  :data:`ALLOWED_FAILURES` + 1 workers in a row fails the job with Dask's message.

Both take tasks with :meth:`submit` (also while :meth:`results` is being iterated: the engine
submits a line's tile as soon as its chunks are done) and yield the results as tasks finish.
"""

from __future__ import annotations

import os
from collections import deque
from collections.abc import Callable, Iterator
from typing import Any, Protocol

from office.deliver.options import GeorefError

ALLOWED_FAILURES = 3


class Executor(Protocol):
    """What the engine asks of an executor (module docstring)."""

    name: str
    workers: int

    def submit(self, fn: Callable[[Any], Any], item: Any) -> None: ...

    def results(self) -> Iterator[Any]: ...

    def close(self) -> None: ...


class InProcess:
    name = "in-process"
    workers = 1

    def __init__(self) -> None:
        self._queue: deque = deque()

    def submit(self, fn: Callable, item) -> None:
        self._queue.append((fn, item))

    def results(self) -> Iterator:
        while self._queue:
            fn, item = self._queue.popleft()
            yield fn(item)

    def close(self) -> None:
        pass


def _numbered(task: tuple[Callable, int, Any]) -> tuple[int, Any]:
    fn, k, item = task
    return k, fn(item)


def ordered_map(executor: Executor, fn: Callable[[Any], Any], items: list) -> list:
    """``[fn(x) for x in items]``, the calls run as ``executor``'s tasks (at once on a cluster);
    for an executor with no other task pending (the plan's, before the chunks)."""
    for k, item in enumerate(items):
        executor.submit(_numbered, (fn, k, item))
    done = dict(executor.results())
    return [done[k] for k in range(len(items))]


class DaskExecutor:
    def __init__(self, scheduler: str | None = None, workers: int | None = None, memory_limit: str = "auto"):
        import dask
        from distributed import Client, LocalCluster

        environ = dict(dask.config.get("distributed.nanny.pre-spawn-environ"))
        # Dask's 64 KiB trim threshold also fixes glibc's mmap threshold: every large numpy array
        # of a chunk is then mmapped and faulted in anew (measured: a worker 1.5 × slower per
        # chunk than this process); the BLAS stays on one thread
        environ.pop("MALLOC_TRIM_THRESHOLD_", None)
        dask.config.set(
            {
                "distributed.scheduler.allowed-failures": ALLOWED_FAILURES,
                "distributed.nanny.pre-spawn-environ": environ,
                # the worker's sampling profiler walks the task thread's stack every 10 ms under
                # the GIL: off (the tasks are long, numpy-bound and not diagnosed from Dask)
                "distributed.worker.profile.enabled": False,
                # fewer wake-ups of the worker, nanny and scheduler event loops: on two cores they
                # take their time from the tasks (tasks of seconds need no 20-ms ticks)
                "distributed.admin.tick.interval": "500ms",
                "distributed.admin.system-monitor.interval": "5s",
                "distributed.worker.memory.monitor-interval": "1s",
            }
        )
        self.cluster = None
        try:
            if scheduler and scheduler != "local":
                self.client = Client(scheduler, timeout="10s")
                self.name = f"dask {scheduler}"
            else:
                n = workers or os.cpu_count() or 1
                self.cluster = LocalCluster(
                    n_workers=n,
                    threads_per_worker=1,
                    processes=True,
                    # the scheduler serves HTTP even without a dashboard, on :8787 unless told:
                    # a second job on the machine then warns and moves; a free port from the start
                    dashboard_address=":0",
                    memory_limit=memory_limit,
                )
                self.client = Client(self.cluster)
                self.name = f"dask LocalCluster, {n} worker process{'es' if n > 1 else ''}"
        except OSError as e:
            self.close()
            raise GeorefError(f"--scheduler {scheduler or 'local'}: cannot reach the cluster ({e})") from None
        self.workers = len(self.client.scheduler_info().get("workers", {})) or (workers or 1)
        from distributed import as_completed

        self._pending = as_completed()

    def submit(self, fn: Callable, item) -> None:
        self._pending.add(self.client.submit(fn, item, pure=False))

    def results(self) -> Iterator:
        for fut in self._pending:  # (as_completed: futures added meanwhile are yielded too)
            yield fut.result()

    def worker_pids(self) -> list[int]:
        return sorted(self.client.run(os.getpid).values())

    def close(self) -> None:
        client = getattr(self, "client", None)
        if client is not None:
            client.close()
        if self.cluster is not None:
            self.cluster.close()
