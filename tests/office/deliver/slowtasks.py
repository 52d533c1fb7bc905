"""Tasks for the Dask tests, importable by the worker processes (not a test module)."""

from __future__ import annotations

import time

from office.deliver.chunkjob import ChunkDone, ChunkTask, process_chunk


def slow_process_chunk(task: ChunkTask) -> ChunkDone:
    """:func:`process_chunk` after 0.3 s: long enough that a worker killed meanwhile is busy."""
    time.sleep(0.3)
    return process_chunk(task)
