"""Batching records from the event loop to the session writer (the daemon's record hot path).

The devices call :meth:`LogBatcher.submit` (the signature of
:meth:`acquire.log.sessionlog.SessionWriter.submit` for what they use): the record is stamped at
once — its ``log_time`` and clock state from the :class:`~acquire.timing.timekeeper.ClockCache` at the
host receive stamp — and appended to a list; every ``period_s`` (5 ms) of loop time, or when
``max_items`` are waiting, the list goes to the writer in one go
(:meth:`~acquire.log.sessionlog.SessionWriter.submit_batch`: one lock, one queue item). The writer
thread then wakes once per batch instead of once per datagram (at the full Z+F rate that is
~4600 thread wake-ups and GIL hand-overs per second saved), and the writer's queue still bounds
memory in records and counts drops (``log_queue_overflow``). Records keep their order across
topics; the delay (≤ 5 ms) is far below the chunk flush period. :meth:`submit_many` takes a
device's burst in one call; :meth:`flush` hands over what is waiting (shutdown).
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from typing import Any

from acquire.timing.timekeeper import ClockCache


class LogBatcher:
    def __init__(
        self,
        submit_batch: Callable[[list[tuple]], int],
        clock: ClockCache,
        period_s: float = 0.005,
        max_items: int = 1024,
    ) -> None:
        self._submit_batch = submit_batch
        self._clock = clock
        self.period_s = period_s
        self.max_items = max_items
        self._items: list[tuple] = []
        self._handle: asyncio.TimerHandle | None = None
        self.batches = 0
        self.records = 0

    def submit(self, topic: str, payload: Any, *, host_ns: int, device_ns: int | None = None) -> bool:
        gps_ns, state = self._clock.estimate(host_ns)
        self._items.append((topic, payload, host_ns, device_ns, gps_ns, state))
        self._appended()
        return True

    def submit_many(
        self, topic: str, payloads: list, host_ns: list[int], device_ns: list[int | None]
    ) -> None:
        """:meth:`submit` of each (payload, host stamp, device stamp), in order (a device's burst)."""
        estimate = self._clock.estimate
        items = self._items
        for payload, h, d in zip(payloads, host_ns, device_ns, strict=False):
            gps_ns, state = estimate(h)
            items.append((topic, payload, h, d, gps_ns, state))
        if items:
            self._appended()

    def _appended(self) -> None:
        """Hand over when ``max_items`` wait, else within ``period_s``."""
        if len(self._items) >= self.max_items:
            self.flush()
        elif self._handle is None:
            try:
                self._handle = asyncio.get_running_loop().call_later(self.period_s, self.flush)
            except RuntimeError:  # no loop (shutdown, tests): hand over at once
                self.flush()

    def flush(self) -> None:
        if self._handle is not None:
            self._handle.cancel()
            self._handle = None
        items, self._items = self._items, []
        if not items:
            return
        self._submit_batch(items)
        self.batches += 1
        self.records += len(items)
