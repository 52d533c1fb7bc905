"""MQTT publisher of the status bus (aiomqtt), with last will, reconnects and optional commands.

Topics live under ``<prefix>/<vessel>/`` (docs/architecture.md §8; retain/QoS per topic in
:mod:`acquire.status.bus`). The connection carries the last will ``{"state":"lost"}`` on
``status`` (retained, QoS 1), so a subscriber learns when the daemon dies; a clean stop publishes
the caller's final status and disconnects (no will).

Nothing waits on the broker: :meth:`MqttPublisher.offer` only stores. Retained topics are
coalesced (the latest value wins, and all are published again after each reconnect — the broker
may have restarted without persistence); other messages go through a bounded queue that drops
the oldest when full (counted). One task owns the connection and reconnects with exponential
back-off.

Commands (``<base>/cmd/<name>``, JSON object payload) are accepted only when the config enables
them, and only this set; the result goes to ``<base>/cmd/result``::

    mark        {"text": str}        operator mark in /events
    pass_start  {"pass_id": int}     start of a calibration pass
    pass_end    {"pass_id": int}     end of a calibration pass
    rotate      {}                   start a new log segment

Every command may carry an ``"id"`` (any JSON scalar) echoed in the result.
"""

from __future__ import annotations

import asyncio
import inspect
import json
import logging
from collections import deque
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import Any

import aiomqtt

from acquire.log.schema import dumps

log = logging.getLogger(__name__)

LOST = b'{"state":"lost"}'
COMMANDS: dict[str, dict[str, type]] = {
    "mark": {"text": str},
    "pass_start": {"pass_id": int},
    "pass_end": {"pass_id": int},
    "rotate": {},
}
CommandHandler = Callable[[str, dict], tuple[bool, str] | Awaitable[tuple[bool, str]]]


@dataclass(frozen=True)
class MqttSettings:
    host: str
    port: int = 1883
    username: str | None = None
    password: str | None = None
    topic_prefix: str = "mls"
    commands_enabled: bool = False
    keepalive_s: int = 10
    queue_size: int = 1000  # non-retained messages waiting for the broker
    backoff_min_s: float = 0.5
    backoff_max_s: float = 30.0
    publish_timeout_s: float = 10.0


def check_command(name: str, args: Any) -> str | None:
    """None when ``name``/``args`` form a valid command, else the reason it is refused."""
    spec = COMMANDS.get(name)
    if spec is None:
        return f"unknown command {name!r}; accepted: {', '.join(COMMANDS)}"
    if not isinstance(args, dict):
        return f"{name}: payload must be a JSON object"
    unknown = sorted(set(args) - set(spec) - {"id"})
    if unknown:
        return f"{name}: unknown argument(s) {', '.join(unknown)}; accepted: {', '.join(spec) or 'none'}"
    for key, typ in spec.items():
        value = args.get(key)
        if not isinstance(value, typ) or isinstance(value, bool):
            return f"{name}: argument {key!r} must be {typ.__name__}, got {value!r}"
    return None


class MqttPublisher:
    """Status bus sink publishing to an MQTT broker; ``await run()`` in a task, ``stop()`` it."""

    def __init__(self, settings: MqttSettings, vessel: str, on_command: CommandHandler | None = None):
        self.settings = settings
        self.base = f"{settings.topic_prefix}/{vessel}"
        self.client_id = f"mls-acquire-{vessel}"
        self.on_command = on_command
        self._retained: dict[str, tuple[bytes, int]] = {}
        self._dirty: dict[str, None] = {}  # ordered set of retained topics to (re)publish
        self._queue: deque[tuple[str, bytes, int]] = deque()
        self._wake = asyncio.Event()
        self._stop = asyncio.Event()
        self._final: bytes | None = None
        self.connected = False
        self.connects = 0
        self.published = 0
        self.dropped = 0
        self.subscribed: list[str] = []
        self.last_error: str | None = None

    # -- sink -------------------------------------------------------------------------------

    def offer(self, topic: str, payload: bytes, retain: bool, qos: int) -> None:
        if retain:
            self._retained[topic] = (payload, qos)
            self._dirty[topic] = None
        else:
            if len(self._queue) >= self.settings.queue_size:
                self._queue.popleft()
                self.dropped += 1
            self._queue.append((topic, payload, qos))
        self._wake.set()

    # -- connection -------------------------------------------------------------------------

    async def run(self) -> None:
        """Connect, publish, reconnect with back-off; returns after :meth:`stop`."""
        s = self.settings
        backoff = s.backoff_min_s
        while not self._stop.is_set():
            connects = self.connects
            try:
                await self._session()
            except* (aiomqtt.MqttError, OSError) as group:
                err = group.exceptions[0]
                if self.last_error != str(err):
                    log.warning("MQTT %s:%d: %s; reconnecting", s.host, s.port, err)
                self.last_error = str(err)
            if self._stop.is_set():
                break
            if self.connects > connects:  # it was connected: start the back-off over
                backoff = s.backoff_min_s
            try:
                await asyncio.wait_for(self._stop.wait(), backoff)
            except TimeoutError:
                pass
            backoff = min(backoff * 2, s.backoff_max_s)

    async def stop(self, final_status: dict | None = None, timeout_s: float = 5.0) -> None:
        """Publish ``final_status`` on ``status`` (retained) if connected, then disconnect
        cleanly (the broker does not send the will)."""
        if final_status is not None:
            self._final = dumps(final_status)
            self._retained["status"] = (self._final, 1)
            self._dirty["status"] = None
        self._stop.set()
        self._wake.set()
        await asyncio.sleep(0)
        deadline = asyncio.get_running_loop().time() + timeout_s
        while self.connected and asyncio.get_running_loop().time() < deadline:
            await asyncio.sleep(0.02)

    async def _session(self) -> None:
        s = self.settings
        will = aiomqtt.Will(f"{self.base}/status", LOST, qos=1, retain=True)
        async with aiomqtt.Client(
            s.host,
            s.port,
            username=s.username,
            password=s.password,
            identifier=self.client_id,
            will=will,
            keepalive=s.keepalive_s,
            timeout=s.publish_timeout_s,
        ) as client:
            self.connected = True
            self.connects += 1
            self.last_error = None
            for topic in self._retained:  # the broker may have lost them
                self._dirty[topic] = None
            self.subscribed = []
            if s.commands_enabled:
                await client.subscribe(f"{self.base}/cmd/+", qos=1)
                self.subscribed.append(f"{self.base}/cmd/+")
            listener = asyncio.create_task(self._listen(client))
            publisher = asyncio.create_task(self._publish_loop(client))
            try:
                done, _ = await asyncio.wait({listener, publisher}, return_when=asyncio.FIRST_COMPLETED)
                for task in done:
                    task.result()  # re-raises the broker error that ended the session
            finally:
                for task in (listener, publisher):
                    task.cancel()
                await asyncio.gather(listener, publisher, return_exceptions=True)
                self.connected = False

    async def _publish_loop(self, client: aiomqtt.Client) -> None:
        timeout = self.settings.publish_timeout_s
        while True:
            while self._dirty or self._queue:
                if self._dirty:
                    topic = next(iter(self._dirty))
                    payload, qos = self._retained[topic]
                    del self._dirty[topic]
                    try:
                        await client.publish(
                            f"{self.base}/{topic}", payload, qos=qos, retain=True, timeout=timeout
                        )
                    except BaseException:
                        self._dirty[topic] = None  # publish it on the next connection
                        raise
                else:
                    topic, payload, qos = self._queue.popleft()
                    try:
                        await client.publish(f"{self.base}/{topic}", payload, qos=qos, timeout=timeout)
                    except BaseException:
                        self._queue.appendleft((topic, payload, qos))
                        raise
                self.published += 1
            if self._stop.is_set():
                return  # everything (including the final status) is out: disconnect cleanly
            self._wake.clear()
            await self._wake.wait()

    async def _listen(self, client: aiomqtt.Client) -> None:
        """Commands, when enabled; in any case this notices a lost connection while idle."""
        prefix = f"{self.base}/cmd/"
        async for message in client.messages:
            topic = str(message.topic)
            if not (self.settings.commands_enabled and topic.startswith(prefix)):
                continue
            name = topic[len(prefix) :]
            if name == "result":
                continue
            try:
                args = json.loads(message.payload or b"{}")
            except (ValueError, TypeError):
                args = None
            reason = check_command(name, args)
            if reason is None and self.on_command is None:
                reason = f"{name}: no handler for commands in this daemon"
            if reason is None:
                try:
                    result = self.on_command(name, {k: v for k, v in args.items() if k != "id"})
                    ok, text = await result if inspect.isawaitable(result) else result
                except Exception as e:  # a handler bug must not end the MQTT session
                    ok, text = False, f"{name}: failed: {e}"
            else:
                ok, text = False, reason
            reply = {"command": name, "ok": bool(ok), "message": text}
            if isinstance(args, dict) and "id" in args:
                reply["id"] = args["id"]
            self.offer("cmd/result", dumps(reply), False, 1)
