"""MQTT publisher of the status bus (aiomqtt, MQTT 5), with last will, reconnects, TLS and commands.

Topics live under ``<prefix>/<vessel>/`` (docs/architecture.md §8; retain/QoS per topic in
:mod:`acquire.status.bus`). The connection carries the last will ``{"state":"lost"}`` on
``status`` (retained, QoS 1), so a subscriber learns when the daemon dies; a clean stop publishes
the caller's final status and disconnects (no will).

Nothing waits on the broker: :meth:`MqttPublisher.offer` only stores. Retained topics are
coalesced (the latest value wins, and all are published again after each reconnect — the broker
may have restarted without persistence); other messages go through a bounded queue that drops
the oldest when full (counted). One task owns the connection and reconnects with exponential
back-off.

**TLS** (``MqttSettings.tls``): the broker's certificate is verified against ``ca_file``
(hostname too, unless ``verify_hostname`` is false), TLS 1.2 at least, optionally a client
certificate. A refused connection — certificate not verified, credentials or client id refused —
raises the alarm ``mqtt_refused`` (device ``mqtt``, critical) with the reason; the publisher
keeps retrying and clears it on the next connection.

**Client id**: ``mls-acquire-<vessel>-<pid>-<random>``, unique per daemon instance. A broker that
disconnects the daemon because another client connected with its id (MQTT 5 reason "session
taken over", mosquitto ≥ 2.0.15) raises ``mqtt_taken_over`` (warning); so does, with a broker that
closes silently, a fight over the id (:data:`FLAP_SESSIONS` sessions in :data:`FLAP_WINDOW_S`
each closed within ``stable_s`` of connecting). It clears once a connection has held ``stable_s``.

**Outage**: no connection to the broker for ``outage_alarm_s`` (from start-up, or since the last
session ended) raises ``mqtt_unreachable`` (warning, device ``mqtt``) with how long and the last
error; the status goes on on the local socket, the alarm says so. It clears on the next
connection (found within the back-off, ``backoff_max_s`` at most).

**Commands** (``<base>/cmd/<name>``, validated by :mod:`acquire.status.commands`) are accepted
only when the config enables them and :func:`command_policy` allows it (TLS with credentials,
or a broker on loopback, or ``commands_insecure_ok``). Every command is answered on
``<base>/cmd/result``: ``{"command", "ok", "message"[, "id"]}`` — accepted, refused as invalid,
or refused by the rate limit of its kind; refusals are also session events
(``command_refused``, through ``on_event``). Retained command messages (a replay by the broker at
every subscription) are ignored and counted (``commands_retained``); refusals beyond the reply
budget are dropped and counted (``commands_dropped``).
"""

from __future__ import annotations

import asyncio
import contextlib
import inspect
import ipaddress
import logging
import os
import secrets
import ssl
import time
from collections import deque
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import aiomqtt
from aiomqtt.exceptions import MqttConnectError
from paho.mqtt.subscribeoptions import SubscribeOptions

from acquire.alarms import CRITICAL, WARNING, AlarmBook
from acquire.log.schema import dumps
from acquire.status.commands import (
    COMMANDS,
    CommandLimiter,
    CommandRefused,
    check_command,
    command_id,
    parse_command,
)

__all__ = [
    "COMMANDS",
    "LOST",
    "MqttPublisher",
    "MqttSettings",
    "MqttTls",
    "check_command",
    "command_policy",
    "tls_context",
]

log = logging.getLogger(__name__)

LOST = b'{"state":"lost"}'
SESSION_TAKEN_OVER = 0x8E  # MQTT 5 DISCONNECT reason code
REFUSED_ALARM = ("mqtt_refused", "mqtt")
TAKEOVER_ALARM = ("mqtt_taken_over", "mqtt")
UNREACHABLE_ALARM = ("mqtt_unreachable", "mqtt")
FLAP_SESSIONS, FLAP_WINDOW_S = 3, 120.0  # this many short sessions in this window: a takeover fight
CommandHandler = Callable[[str, dict], tuple[bool, str] | Awaitable[tuple[bool, str]]]


@dataclass(frozen=True)
class MqttTls:
    ca_file: Path
    cert_file: Path | None = None  # client certificate (with key_file)
    key_file: Path | None = None
    verify_hostname: bool = True


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
    tls: MqttTls | None = None
    commands_insecure_ok: bool = False  # commands over plaintext to a remote broker
    outage_alarm_s: float = 30.0  # no connection this long: mqtt_unreachable


def tls_context(tls: MqttTls) -> ssl.SSLContext:
    """The client's TLS context: verify the broker against ``ca_file``, TLS ≥ 1.2.
    Raises ``OSError`` / ``ssl.SSLError`` for a file that cannot be read or used."""
    ctx = ssl.create_default_context(ssl.Purpose.SERVER_AUTH, cafile=str(tls.ca_file))
    ctx.minimum_version = ssl.TLSVersion.TLSv1_2
    ctx.check_hostname = tls.verify_hostname
    ctx.verify_mode = ssl.CERT_REQUIRED
    if tls.cert_file is not None:
        ctx.load_cert_chain(str(tls.cert_file), None if tls.key_file is None else str(tls.key_file))
    return ctx


def is_loopback(host: str) -> bool:
    if host.lower() in ("localhost", "localhost."):
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def command_policy(s: MqttSettings) -> str | None:
    """None when commands may be accepted over this connection, else why not: commands need
    TLS with credentials, or a broker on loopback, or ``commands_insecure_ok``."""
    if s.tls is not None and s.username is not None:
        return None
    if is_loopback(s.host) or s.commands_insecure_ok:
        return None
    missing = "credentials (credentials_file)" if s.tls is not None else "TLS (mqtt.tls)"
    return (
        f"commands from broker {s.host} (not on loopback) need TLS with credentials; {missing} "
        "missing. Add them, or set commands_insecure_ok: true to accept commands anyway"
    )


def _reason_code(err: BaseException) -> int | None:
    """The MQTT reason code behind an aiomqtt error (its cause chain), if any."""
    seen: set[int] = set()
    e: BaseException | None = err
    while e is not None and id(e) not in seen:
        seen.add(id(e))
        rc = getattr(e, "rc", None)
        if rc is not None:
            return int(getattr(rc, "value", rc))
        e = e.__cause__ or e.__context__
    return None


class MqttPublisher:
    """Status bus sink publishing to an MQTT broker; ``await run()`` in a task, ``stop()`` it.

    ``alarms``: the daemon's alarm book (``mqtt_refused``, ``mqtt_taken_over``,
    ``mqtt_unreachable``);
    ``on_event``: receives the session events of refused commands."""

    def __init__(
        self,
        settings: MqttSettings,
        vessel: str,
        on_command: CommandHandler | None = None,
        *,
        alarms: AlarmBook | None = None,
        on_event: Callable[[dict], None] | None = None,
        limiter: CommandLimiter | None = None,
    ):
        self.settings = settings
        self.base = f"{settings.topic_prefix}/{vessel}"
        self.client_id = f"mls-acquire-{vessel}-{os.getpid()}-{secrets.token_hex(3)}"
        self.on_command = on_command
        self.alarms = alarms
        self.on_event = on_event
        self.stable_s = 30.0  # a session that lasts this long is no takeover fight
        self.limiter = limiter or CommandLimiter()
        self.command_refusal = command_policy(settings) if settings.commands_enabled else None
        self._tls = tls_context(settings.tls) if settings.tls is not None else None
        self._retained: dict[str, tuple[bytes, int]] = {}
        self._dirty: dict[str, None] = {}  # ordered set of retained topics to (re)publish
        self._queue: deque[tuple[str, bytes, int]] = deque()
        self._wake = asyncio.Event()
        self._stop = asyncio.Event()
        self._final: bytes | None = None
        self._down = asyncio.Event()  # set while no broker session is up
        self._down.set()
        self.connects = 0
        self.published = 0
        self.dropped = 0
        self.subscribed: list[str] = []
        self.last_error: str | None = None
        self.takeovers = 0
        self._session_s: float | None = None  # how long the last session was connected
        self._down_since: float | None = None  # monotonic s since when not connected
        self._outage_timer: asyncio.TimerHandle | None = None
        self._short_sessions: deque[float] = deque()  # ends of sessions shorter than stable_s
        self.commands = {"accepted": 0, "refused": 0, "rate_limited": 0, "retained": 0, "dropped": 0}
        if self.command_refusal is not None:
            log.error("MQTT commands disabled: %s", self.command_refusal)

    @property
    def commands_active(self) -> bool:
        return self.settings.commands_enabled and self.command_refusal is None

    def metrics(self) -> dict:
        """Counters for the daemon's ``metrics`` topic."""
        return {
            "connected": self.connected,
            "connects": self.connects,
            "published": self.published,
            "dropped": self.dropped,
            "last_error": self.last_error,
            "takeovers": self.takeovers,
            "down_s": None if self._down_since is None else round(time.monotonic() - self._down_since, 1),
            "commands": dict(self.commands),
        }

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
        self._went_down()
        try:
            await self._sessions()
        finally:
            self._cancel_outage()

    async def _sessions(self) -> None:
        s = self.settings
        backoff = s.backoff_min_s
        while not self._stop.is_set():
            connects = self.connects
            try:
                await self._session()
            except* (aiomqtt.MqttError, OSError) as group:
                self._session_failed(group.exceptions[0])
            if self._stop.is_set():
                break
            if self.connects > connects:  # it was connected: start the back-off over
                backoff = s.backoff_min_s
            try:
                await asyncio.wait_for(self._stop.wait(), backoff)
            except TimeoutError:
                pass
            backoff = min(backoff * 2, s.backoff_max_s)

    def _session_failed(self, err: BaseException) -> None:
        s = self.settings
        text = str(err)
        if self.last_error != text:
            log.warning("MQTT %s:%d: %s; reconnecting", s.host, s.port, text)
        self.last_error = text
        if self._session_s is not None and _reason_code(err) == SESSION_TAKEN_OVER:
            self.takeovers += 1
            self._raise(
                TAKEOVER_ALARM,
                WARNING,
                f"MQTT session taken over: another client connected to {s.host}:{s.port} with "
                f"this daemon's client id {self.client_id}; reconnecting",
            )
        elif self._session_s is not None and self._flapping(self._session_s):
            self.takeovers += 1
            self._raise(
                TAKEOVER_ALARM,
                WARNING,
                f"MQTT connection to {s.host}:{s.port} closed by the broker {len(self._short_sessions)} "
                f"times in {FLAP_WINDOW_S:g} s, each within {self.stable_s:g} s of connecting: another "
                f"client may be using this daemon's client id {self.client_id} (session taken over, "
                "without an MQTT 5 reason from this broker), or the link is unstable",
            )
        elif isinstance(err, MqttConnectError) or (self._tls is not None and _is_tls_error(text)):
            self._raise(REFUSED_ALARM, CRITICAL, f"MQTT broker {s.host}:{s.port} refused: {text}; retrying")
        if self.alarms is not None and self.alarms.is_active(*UNREACHABLE_ALARM):
            self._outage_due()  # the message: how long now, the latest error

    # -- outage -----------------------------------------------------------------------------

    def _went_down(self) -> None:
        """Not connected from now: ``mqtt_unreachable`` once this lasts ``outage_alarm_s``."""
        self._down_since = time.monotonic()
        self._cancel_outage()
        self._outage_timer = asyncio.get_running_loop().call_later(
            self.settings.outage_alarm_s, self._outage_due
        )

    def _cancel_outage(self) -> None:
        if self._outage_timer is not None:
            self._outage_timer.cancel()
            self._outage_timer = None

    def _outage_over(self) -> None:
        """Connected: no outage, ``mqtt_unreachable`` cleared with how long it lasted."""
        self._cancel_outage()
        since, self._down_since = self._down_since, None
        if since is None or self.alarms is None or not self.alarms.is_active(*UNREACHABLE_ALARM):
            return
        s = self.settings
        message = f"MQTT broker {s.host}:{s.port} reachable again after {time.monotonic() - since:.0f} s"
        self.alarms.clear_now(*UNREACHABLE_ALARM, time.monotonic_ns(), message=message)

    def _outage_due(self) -> None:
        if self.connected or self._down_since is None or self._stop.is_set():
            return
        s = self.settings
        down_s = time.monotonic() - self._down_since
        self._raise(
            UNREACHABLE_ALARM,
            WARNING,
            f"MQTT broker {s.host}:{s.port} unreachable for {down_s:.0f} s (alarm after "
            f"{s.outage_alarm_s:g} s): {self.last_error or 'no connection yet'}; status on the local "
            "socket only; retrying",
        )

    def _flapping(self, session_s: float) -> bool:
        """Whether sessions keep ending soon after they start (a silent takeover fight)."""
        now = time.monotonic()
        if session_s < self.stable_s:
            self._short_sessions.append(now)
        while self._short_sessions and self._short_sessions[0] < now - FLAP_WINDOW_S:
            self._short_sessions.popleft()
        return len(self._short_sessions) >= FLAP_SESSIONS

    def _raise(self, key: tuple[str, str], severity: str, message: str) -> None:
        if self.alarms is not None:
            self.alarms.raise_now(*key, time.monotonic_ns(), message=message, severity=severity)

    @property
    def connected(self) -> bool:
        """Whether a broker session is up."""
        return not self._down.is_set()

    def _connected_now(self) -> None:
        self._down.clear()
        self.connects += 1
        self.last_error = None
        self._clear(REFUSED_ALARM)
        self._outage_over()

    def _clear(self, key: tuple[str, str]) -> None:
        if self.alarms is not None and self.alarms.is_active(*key):
            self.alarms.clear_now(*key, time.monotonic_ns(), message=f"MQTT connected as {self.client_id}")

    async def _stable(self) -> None:
        """After ``stable_s`` connected: the connection holds, a takeover is over."""
        await asyncio.sleep(self.stable_s)
        self._short_sessions.clear()
        self._clear(TAKEOVER_ALARM)

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
        with contextlib.suppress(TimeoutError):  # still connected after timeout_s: stop waiting
            await asyncio.wait_for(self._down.wait(), timeout_s)

    async def _session(self) -> None:
        s = self.settings
        will = aiomqtt.Will(f"{self.base}/status", LOST, qos=1, retain=True)
        self._session_s = None
        async with aiomqtt.Client(
            s.host,
            s.port,
            username=s.username,
            password=s.password,
            identifier=self.client_id,
            protocol=aiomqtt.ProtocolVersion.V5,
            will=will,
            keepalive=s.keepalive_s,
            timeout=s.publish_timeout_s,
            tls_context=self._tls,
        ) as client:
            self._connected_now()
            for topic in self._retained:  # the broker may have lost them
                self._dirty[topic] = None
            self.subscribed = []
            if self.commands_active:
                # noLocal: not our own results; retainAsPublished: see the retain flag of live messages
                opts = SubscribeOptions(qos=1, noLocal=True, retainAsPublished=True)
                await client.subscribe(f"{self.base}/cmd/+", options=opts)
                self.subscribed.append(f"{self.base}/cmd/+")
            started = time.monotonic()
            listener = asyncio.create_task(self._listen(client))
            publisher = asyncio.create_task(self._publish_loop(client))
            stable = asyncio.create_task(self._stable())
            try:
                done, _ = await asyncio.wait({listener, publisher}, return_when=asyncio.FIRST_COMPLETED)
                for task in done:
                    task.result()  # re-raises the broker error that ended the session
            finally:
                for task in (listener, publisher, stable):
                    task.cancel()
                await asyncio.gather(listener, publisher, stable, return_exceptions=True)
                self._down.set()
                self._session_s = time.monotonic() - started
                self._went_down()

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

    # -- commands ---------------------------------------------------------------------------

    async def _listen(self, client: aiomqtt.Client) -> None:
        """Commands, when enabled; in any case this notices a lost connection while idle."""
        prefix = f"{self.base}/cmd/"
        async for message in client.messages:
            topic = str(message.topic)
            if not (self.commands_active and topic.startswith(prefix)):
                continue
            name = topic[len(prefix) :]
            if name == "result":
                continue
            if message.retain:  # a replay of a stored command, or one that would be replayed
                self.commands["retained"] += 1
                log.warning("MQTT retained command on %s ignored (publish commands without retain)", topic)
                continue
            payload = bytes(message.payload) if isinstance(message.payload, bytes | bytearray) else b""
            await self._command(name, payload)

    async def _command(self, name: str, payload: bytes) -> None:
        """Validate, rate-limit, run and answer one command."""
        try:
            cmd = parse_command(name, payload)
        except CommandRefused as e:
            self._refuse(name, command_id(payload), str(e), "refused")
            return
        reason = self.limiter.allow(cmd.name)
        if reason is None and self.on_command is None:
            reason = f"{name}: no handler for commands in this daemon"
        if reason is not None:
            self._refuse(name, cmd.id, reason, "rate_limited" if "rate limited" in reason else "refused")
            return
        assert self.on_command is not None
        try:
            result = self.on_command(cmd.name, dict(cmd.args))
            ok, text = await result if inspect.isawaitable(result) else result
        except Exception as e:  # a handler bug must not end the MQTT session
            ok, text = False, f"{name}: failed: {e}"
        self.commands["accepted" if ok else "refused"] += 1
        self._reply(cmd.name, bool(ok), text, cmd.id)

    def _refuse(self, name: str, cmd_id: Any, reason: str, counter: str) -> None:
        self.commands[counter] += 1
        if not self.limiter.may_reply():
            self.commands["dropped"] += 1
            return
        short = name if name in COMMANDS else name[:40]
        if self.on_event is not None:
            self.on_event({"event": "command_refused", "source": "mqtt", "command": short, "reason": reason})
        self._reply(short, False, reason, cmd_id)

    def _reply(self, name: str, ok: bool, text: str, cmd_id: Any) -> None:
        reply: dict[str, Any] = {"command": name, "ok": ok, "message": text}
        if cmd_id is not None:
            reply["id"] = cmd_id
        self.offer("cmd/result", dumps(reply), False, 1)


def _is_tls_error(text: str) -> bool:
    """A TLS verification or protocol failure (not a transient network error)."""
    return any(k in text for k in ("certificate", "CERTIFICATE", "alert", "WRONG_VERSION", "ostname"))
