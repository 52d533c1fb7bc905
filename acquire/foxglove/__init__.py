"""The vessel in Foxglove (docs/architecture.md §8): the channels of ``mls export --foxglove`` and
their messages (:mod:`~acquire.foxglove.channels`, :mod:`~acquire.foxglove.frames`), the point
clouds gathered from the profiler's returns (:mod:`~acquire.foxglove.clouds`), and the daemon's
live server of the same channels (:mod:`~acquire.foxglove.live`, ``web.foxglove_port``).

The office's MCAP export (:mod:`office.jobs.foxglove`) and the live server log the very same
messages: one set of builders, two sinks (a file, a WebSocket server).
"""
