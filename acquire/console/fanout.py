"""The console's sink of the status bus: every publication to each WebSocket client, encoded once.

A client first receives a snapshot (the retained topics and the latest ``clock`` and ``metrics``,
as the status socket's), then every publication live. Each client has a bounded queue: a client
that does not keep up loses the messages that do not fit (counted, per client and in total) and
gets a fresh snapshot once it has caught up, so a slow screen is never waited for and never
left showing a stale retained topic. Nothing here blocks the daemon's loop.
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import Mapping
from dataclasses import dataclass, field

from acquire.log.schema import dumps
from acquire.status.bus import LATEST_ALSO, SNAPSHOT_END

CLIENT_QUEUE = 512  # frames queued per client before it drops


def frame(topic: str, payload: bytes) -> str:
    """One WebSocket text frame ``{"topic": …, "data": …}`` from a bus payload (JSON bytes)."""
    return (b'{"topic":' + dumps(topic) + b',"data":' + payload + b"}").decode()


@dataclass(eq=False)
class ConsoleClient:
    """One connected page: its queue, what it lost, whether it needs a new snapshot."""

    queue: asyncio.Queue[str | None]
    dropped: int = 0
    resync: bool = False


@dataclass
class ConsoleSink:
    """A :class:`acquire.status.bus.Sink` fanning out to the console's WebSocket clients."""

    client_queue: int = CLIENT_QUEUE
    latest: dict[str, str] = field(default_factory=dict)  # topic → its latest frame (snapshot)
    clients: set[ConsoleClient] = field(default_factory=set)
    offered: int = 0
    dropped: int = 0  # frames not queued for a client that lagged
    served: int = 0

    def seed(self, retained: Mapping[str, dict]) -> None:
        """The bus's retained topics published before the sink was added."""
        for topic, data in retained.items():
            self.latest.setdefault(topic, frame(topic, dumps(data)))

    def offer(self, topic: str, payload: bytes, retain: bool, qos: int) -> None:
        text = frame(topic, payload)
        self.offered += 1
        if retain or topic in LATEST_ALSO:
            self.latest[topic] = text
        for c in self.clients:
            self._put(c, text)

    def push(self, topic: str, data: dict) -> None:
        """A console-only message (not on the bus: e.g. the acknowledged alarms), kept for the
        snapshot too."""
        self.offer(topic, dumps(data), True, 0)

    def _put(self, c: ConsoleClient, text: str) -> None:
        try:
            c.queue.put_nowait(text)
        except asyncio.QueueFull:
            c.dropped += 1
            self.dropped += 1
            c.resync = True

    def snapshot(self) -> list[str]:
        """The snapshot frames, then the end-of-snapshot marker."""
        end = json.dumps({"topic": SNAPSHOT_END, "data": {"retained": len(self.latest)}})
        return [*self.latest.values(), end]

    def connect(self) -> ConsoleClient:
        """A new client, its queue holding the snapshot."""
        frames = self.snapshot()
        c = ConsoleClient(asyncio.Queue(max(self.client_queue, len(frames) + 1)))
        for text in frames:
            c.queue.put_nowait(text)
        self.clients.add(c)
        self.served += 1
        return c

    def disconnect(self, c: ConsoleClient) -> None:
        self.clients.discard(c)

    async def next_frame(self, c: ConsoleClient) -> str | None:
        """The client's next frame (None: the console closes). A client that lagged gets the
        snapshot again once its queue is empty."""
        if c.resync and c.queue.empty():
            c.resync = False
            for text in self.snapshot():
                self._put(c, text)
        return await c.queue.get()

    def close_all(self) -> None:
        """Tell every client the console closes (after what is queued for it)."""
        for c in self.clients:
            try:
                c.queue.put_nowait(None)
            except asyncio.QueueFull:
                c.queue.get_nowait()
                c.queue.put_nowait(None)

    def stats(self) -> dict:
        return {
            "clients": len(self.clients),
            "served": self.served,
            "offered": self.offered,
            "dropped": self.dropped,
        }
