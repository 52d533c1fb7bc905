"""Taps on the daemon's record stream, for consumers such as operator guidance (docs/architecture.md §8).

The drivers hand every canonical record to :class:`ConsumerHub.publish` — ``("nav", NavRecord,
gps_ns)`` per INS epoch, ``("profile", Profile, gps_ns)`` per assembled profile, ``("event",
dict, gps_ns)`` per ``/events`` entry (pass marks, alarms, reconnects) — where ``gps_ns`` is the
record's GPS time (device tag when synced, else the clock model). Publishing never blocks: each
:class:`Tap` has its own bounded queue and a tap that does not keep up loses the newest items
(counted in ``tap.dropped``; the supervisor raises ``consumer_overflow``).

A consumer is an object with ``name`` and ``async def run(tap, checklist)``; the supervisor
runs each in its own task, restarts it (with a back-off) when it raises, and stops it at
shutdown::

    class Guidance:
        name = "guidance"
        kinds = ("nav", "profile", "event")       # optional: what the tap receives

        async def run(self, tap: Tap, checklist: ChecklistPublisher) -> None:
            async for kind, record, gps_ns in tap:
                ...                                # pure functions of acquire.guidance.lines
                checklist.publish("guidance", {"pass": 3, "cross_track_m": 1.2})

:class:`ChecklistPublisher` publishes the retained ``checklist`` status topic (socket and
MQTT): one document of named sections (the daemon's ``presurvey`` checks, a consumer's
``guidance``...), each replaced by its publisher; a publication that changes nothing is skipped.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from typing import Any, Protocol

KINDS = ("nav", "profile", "event")


class Tap:
    """One consumer's bounded view of the record stream: ``async for kind, rec, gps_ns in tap``."""

    def __init__(self, name: str, kinds: tuple[str, ...] = KINDS, maxsize: int = 2000) -> None:
        unknown = sorted(set(kinds) - set(KINDS))
        if unknown:
            raise ValueError(f"tap {name!r}: unknown record kinds {unknown}; expected {KINDS}")
        self.name = name
        self.kinds = frozenset(kinds)
        self.queue: asyncio.Queue = asyncio.Queue(maxsize)
        self.delivered = 0
        self.dropped = 0

    def offer(self, kind: str, record: Any, gps_ns: int | None) -> None:
        if kind not in self.kinds:
            return
        try:
            self.queue.put_nowait((kind, record, gps_ns))
        except asyncio.QueueFull:
            self.dropped += 1

    async def get(self) -> tuple[str, Any, int | None]:
        item = await self.queue.get()
        self.delivered += 1
        return item

    def __aiter__(self):
        return self._iter()

    async def _iter(self):
        while True:
            yield await self.get()


class ChecklistPublisher:
    """Publishes the retained ``checklist`` topic (a dict of sections) through a status-bus
    ``publish``."""

    def __init__(self, publish: Callable[[str, dict], None]) -> None:
        self._publish = publish
        self.sections: dict[str, dict] = {}
        self.published = 0

    def publish(self, section: str, data: dict) -> None:
        if self.sections.get(section) == data:
            return
        self.sections = {**self.sections, section: dict(data)}
        self.published += 1
        self._publish("checklist", self.sections)


class Consumer(Protocol):
    name: str

    async def run(self, tap: Tap, checklist: ChecklistPublisher) -> None: ...


class ConsumerHub:
    """Fans records out to the taps (never blocks)."""

    def __init__(self) -> None:
        self.taps: list[Tap] = []

    def subscribe(self, name: str, kinds: tuple[str, ...] = KINDS, maxsize: int = 2000) -> Tap:
        tap = Tap(name, kinds, maxsize)
        self.taps.append(tap)
        return tap

    def unsubscribe(self, tap: Tap) -> None:
        if tap in self.taps:
            self.taps.remove(tap)

    def publish(self, kind: str, record: Any, gps_ns: int | None) -> None:
        for tap in self.taps:
            tap.offer(kind, record, gps_ns)

    def wants(self, kind: str) -> bool:
        """Whether any tap takes ``kind`` (lets the drivers skip work nobody uses)."""
        return any(kind in t.kinds for t in self.taps)

    def status(self) -> dict:
        return {
            t.name: {"delivered": t.delivered, "dropped": t.dropped, "queued": t.queue.qsize()}
            for t in self.taps
        }
