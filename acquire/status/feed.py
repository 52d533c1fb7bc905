"""Client side of the daemon's status bus: the local socket or MQTT as one async stream of
``(topic, data)`` (what ``mls checklist`` and ``mls plan --follow`` read).

Topics are the status bus's (``status``, ``sensors/<name>``, ``checklist``, ``mount``,
``clock``, ``metrics``, ``alarms``), without the MQTT ``<prefix>/<vessel>/`` part. Besides them a feed
yields its own link events on the topic :data:`LINK`: ``{"up": bool, "detail": str}``. A lost
connection is retried with back-off until the consumer stops iterating.
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path

LINK = "_link"
SNAPSHOT_END = "_snapshot_end"  # as acquire.status.bus sends it


def guidance_of(checklist: dict | None) -> dict:
    """The guidance message inside a ``checklist`` topic: the topic itself when it is one
    (``schema`` key), else its ``guidance`` section (the daemon publishes named sections)."""
    c = checklist or {}
    return c if "schema" in c else (c.get("guidance") or {})


def parse_host_port(text: str, default_port: int = 1883) -> tuple[str, int]:
    """``"host:port"`` or ``"host"`` → (host, port); ValueError naming the text otherwise."""
    host, sep, port = text.rpartition(":")
    if not sep:
        host, port = text, str(default_port)
    if not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(f"{text!r}: expected HOST:PORT, e.g. 127.0.0.1:1883")
    return host, int(port)


@dataclass
class SocketFeed:
    """JSON lines from the daemon's local status socket (:mod:`acquire.status.bus`)."""

    path: Path
    retry_min_s: float = 0.2
    retry_max_s: float = 5.0

    def describe(self) -> str:
        return f"socket {self.path}"

    async def __aiter__(self) -> AsyncIterator[tuple[str, dict]]:
        delay = self.retry_min_s
        while True:
            try:
                reader, writer = await asyncio.open_unix_connection(str(self.path), limit=1 << 22)
            except OSError as e:
                yield LINK, {"up": False, "detail": f"{self.path}: {e.strerror or e}"}
                await asyncio.sleep(delay)
                delay = min(2 * delay, self.retry_max_s)
                continue
            delay = self.retry_min_s
            yield LINK, {"up": True, "detail": str(self.path)}
            try:
                while True:
                    line = await reader.readline()
                    if not line:
                        break
                    try:
                        msg = json.loads(line)
                        topic, data = str(msg["topic"]), msg["data"]
                    except (ValueError, KeyError, TypeError):
                        continue  # a line we cannot read is skipped, never fatal
                    yield topic, data
            except (OSError, asyncio.IncompleteReadError, ValueError) as e:
                yield LINK, {"up": False, "detail": f"{self.path}: {e}"}
            else:
                yield LINK, {"up": False, "detail": f"{self.path}: the daemon closed the link"}
            finally:
                writer.close()
            await asyncio.sleep(delay)


@dataclass
class MqttFeed:
    """The status topics from an MQTT broker (``<prefix>/<vessel>/#``; vessel ``+`` = any)."""

    host: str
    port: int = 1883
    prefix: str = "mls"
    vessel: str = "+"
    username: str | None = None
    password: str | None = None
    retry_min_s: float = 0.5
    retry_max_s: float = 10.0

    def describe(self) -> str:
        return f"mqtt {self.host}:{self.port} {self.prefix}/{self.vessel}"

    async def __aiter__(self) -> AsyncIterator[tuple[str, dict]]:
        import aiomqtt

        delay = self.retry_min_s
        depth = len(self.prefix.split("/")) + 1  # prefix parts + the vessel
        while True:
            try:
                async with aiomqtt.Client(
                    self.host, self.port, username=self.username, password=self.password
                ) as client:
                    await client.subscribe(f"{self.prefix}/{self.vessel}/#", qos=1)
                    delay = self.retry_min_s
                    yield LINK, {"up": True, "detail": self.describe()}
                    async for message in client.messages:
                        parts = str(message.topic).split("/")
                        topic = "/".join(parts[depth:])
                        try:
                            data = json.loads(message.payload or b"{}")
                        except (ValueError, TypeError):
                            continue
                        if topic and isinstance(data, dict):
                            yield topic, data
            except aiomqtt.MqttError as e:
                yield LINK, {"up": False, "detail": f"{self.host}:{self.port}: {e}"}
            await asyncio.sleep(delay)
            delay = min(2 * delay, self.retry_max_s)
