"""Status bus: the daemon's status to the local Unix socket and to MQTT (docs/architecture.md §8).

The daemon calls :meth:`StatusBus.publish` with a topic and a JSON-able dict. Topics (under
``<prefix>/<vessel>/`` in MQTT) and their delivery:

=============  ========  ===  ==================================================
topic          retained  QoS  content
=============  ========  ===  ==================================================
status         yes       1    daemon state, session, active alarms (will: lost)
sensors/<n>    yes       1    one device: connection, rate, latency, flags
checklist      yes       1    pre-survey checks and pass guidance
mount          yes       1    the mount watch: estimate, σ, test statistic, alarm
clock          no        0    clock model status (1 Hz)
metrics        no        0    latency statistics, writer counters (1 Hz)
alarms         no        1    each alarm raise/clear as it happens
=============  ========  ===  ==================================================

Sinks receive ``offer(topic, payload, retain, qos)`` and must never block: the local socket
(:class:`StatusServer`) and MQTT (:class:`acquire.status.mqtt.MqttPublisher`).

**Local socket** (the checklist's default link, ``mls status``): a stream of JSON lines
``{"topic": "...", "data": {...}}``. A client first receives a snapshot — the retained topics
and the latest ``clock`` and ``metrics`` — then a line
``{"topic": "_snapshot_end", "data": {"retained": n}}``, then every publication live. Each client
has a bounded queue; a client that does not keep up is disconnected (counted), never waited for.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import socket
import stat
import threading
import time
from pathlib import Path
from typing import Protocol

from acquire.log.schema import dumps

SNAPSHOT_END = "_snapshot_end"
LATEST_ALSO = ("clock", "metrics")  # not retained in MQTT, but part of the socket's snapshot
_POLICY: dict[str, tuple[bool, int]] = {
    "status": (True, 1),
    "sensors": (True, 1),
    "checklist": (True, 1),
    "mount": (True, 1),
    "clock": (False, 0),
    "metrics": (False, 0),
    "alarms": (False, 1),
}


def topic_policy(topic: str) -> tuple[bool, int]:
    """(retained, QoS) of a status topic; ValueError for a topic not in docs/architecture.md §8."""
    head, _, rest = topic.partition("/")
    if head in _POLICY and (bool(rest) == (head == "sensors")) and "/" not in rest:
        return _POLICY[head]
    raise ValueError(
        f"status topic {topic!r}: expected status, sensors/<name>, checklist, mount, clock, metrics or alarms"
    )


class Sink(Protocol):
    def offer(self, topic: str, payload: bytes, retain: bool, qos: int) -> None: ...


class StatusBus:
    """Fans each publication out to the sinks, encoded once."""

    def __init__(self, sinks: list[Sink] | tuple[Sink, ...] = ()):
        self.sinks: list[Sink] = list(sinks)
        self.retained: dict[str, dict] = {}  # latest data of each retained topic

    def add_sink(self, sink: Sink) -> None:
        self.sinks.append(sink)

    def publish(self, topic: str, data: dict) -> None:
        retain, qos = topic_policy(topic)
        if retain:
            self.retained[topic] = data
        payload = dumps(data)
        for sink in self.sinks:
            sink.offer(topic, payload, retain, qos)


class _Client:
    def __init__(self, writer: asyncio.StreamWriter, maxsize: int):
        self.writer = writer
        self.queue: asyncio.Queue[bytes | None] = asyncio.Queue(maxsize)
        self.task: asyncio.Task | None = None


class StatusServer:
    """JSON-lines status over a local Unix stream socket; any number of read-only clients."""

    def __init__(self, path: str | Path, client_queue: int = 256, mode: int = 0o660):
        self.path = Path(path)
        self.client_queue = client_queue
        self.mode = mode
        self._retained: dict[str, bytes] = {}
        self._clients: set[_Client] = set()
        self._server: asyncio.base_events.Server | None = None
        self._bound: tuple[int, int] | None = None  # (st_dev, st_ino) of the socket file it made
        self.clients_served = 0
        self.clients_dropped = 0  # disconnected for not keeping up

    async def start(self) -> None:
        """Bind the socket. Its directory must be safe (:func:`check_run_dir`); whatever is at its
        path must be this user's socket or stale plain file, never a symlink (:func:`check_own_entry`):
        :class:`UnsafeRunFile` otherwise."""
        from acquire.status.runfiles import UnsafeRunFile, check_own_entry, check_run_dir

        self.path.parent.mkdir(parents=True, exist_ok=True)
        check_run_dir(self.path.parent)
        if check_own_entry(self.path):
            if _socket_alive(self.path):
                raise RuntimeError(f"{self.path}: another daemon is serving status on this socket")
            self.path.unlink()  # stale, from a daemon that died
        self._server = await asyncio.start_unix_server(self._handle, path=str(self.path))
        st = os.lstat(self.path)
        if not stat.S_ISSOCK(st.st_mode):  # replaced since it was bound: chmod would follow it
            self._server.close()
            self._server = None
            raise UnsafeRunFile(f"{self.path}: replaced by another file while it was made: refused")
        self._bound = (st.st_dev, st.st_ino)
        os.chmod(self.path, self.mode)

    async def close(self, flush_s: float = 1.0) -> None:
        """Stop serving. Each client first gets up to ``flush_s`` to receive what is queued for
        it (the daemon's final status), then the rest are disconnected."""
        if self._server is not None:
            self._server.close()
        tasks = []
        for c in list(self._clients):
            try:
                c.queue.put_nowait(None)  # the end of its stream
                tasks.append(c.task)
            except asyncio.QueueFull:
                self._drop(c, counted=False)
        pending = [t for t in tasks if t is not None and t is not asyncio.current_task()]
        if pending:
            await asyncio.wait(pending, timeout=flush_s)
        for c in list(self._clients):
            self._drop(c, counted=False)
        if self._server is not None:
            with contextlib.suppress(Exception):
                await asyncio.wait_for(self._server.wait_closed(), 2.0)
            self._server = None
        self._unlink_own()

    def _unlink_own(self) -> None:
        """Remove the socket file if it is the one this server made: never another daemon's
        (a server that did not start, or whose path was taken over since, leaves it alone)."""
        bound, self._bound = self._bound, None
        if bound is None:
            return
        with contextlib.suppress(FileNotFoundError):
            st = os.lstat(self.path)
            if (st.st_dev, st.st_ino) == bound:
                self.path.unlink()

    async def __aenter__(self) -> StatusServer:
        await self.start()
        return self

    async def __aexit__(self, *exc) -> None:
        await self.close()

    @property
    def clients(self) -> int:
        return len(self._clients)

    def offer(self, topic: str, payload: bytes, retain: bool, qos: int) -> None:
        line = b'{"topic":' + dumps(topic) + b',"data":' + payload + b"}\n"
        if retain or topic in LATEST_ALSO:
            self._retained[topic] = line
        for c in list(self._clients):
            try:
                c.queue.put_nowait(line)
            except asyncio.QueueFull:
                self._drop(c, counted=True)

    def _drop(self, c: _Client, counted: bool) -> None:
        if c not in self._clients:
            return
        self._clients.discard(c)
        if counted:
            self.clients_dropped += 1
        if c.task is not None:
            c.task.cancel()
        c.writer.transport.abort()

    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        c = _Client(writer, max(self.client_queue, len(self._retained) + 1))
        c.task = asyncio.current_task()
        for retained in self._retained.values():
            c.queue.put_nowait(retained)
        c.queue.put_nowait(
            b'{"topic":"'
            + SNAPSHOT_END.encode()
            + b'","data":{"retained":'
            + str(len(self._retained)).encode()
            + b"}}\n"
        )
        self._clients.add(c)
        self.clients_served += 1
        try:
            while True:
                line = await c.queue.get()
                if line is None:  # the server closes: flush what was written, then hang up
                    self._clients.discard(c)
                    writer.close()
                    await writer.wait_closed()
                    return
                writer.write(line)
                await writer.drain()
        except (ConnectionError, asyncio.CancelledError):
            pass
        finally:
            self._clients.discard(c)
            writer.transport.abort()


def _socket_alive(path: Path) -> bool:
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(0.5)
    try:
        s.connect(str(path))
        return True
    except OSError:
        return False
    finally:
        s.close()


def read_snapshot(path: str | Path, timeout_s: float = 3.0) -> dict[str, dict]:
    """Connect to a status socket and return its snapshot (what ``mls status`` shows).
    Raises OSError (no daemon, timeout) or ConnectionError."""
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(timeout_s)
    try:
        s.connect(str(path))
        buf = b""
        out: dict[str, dict] = {}
        while True:
            chunk = s.recv(65536)
            if not chunk:
                raise ConnectionError(f"{path}: the daemon closed the connection")
            buf += chunk
            while b"\n" in buf:
                line, buf = buf.split(b"\n", 1)
                msg = json.loads(line)
                if msg["topic"] == SNAPSHOT_END:
                    return out
                out[msg["topic"]] = msg["data"]
    finally:
        s.close()


class StatusListener(threading.Thread):
    """A background thread reading every JSON line of a status socket, reconnecting while the
    daemon is away. :meth:`handle` gets each message (by default it keeps the latest message
    of each topic, :meth:`latest`); lines that are not a status message are skipped."""

    def __init__(self, path: str | Path, retry_s: float = 0.1):
        super().__init__(daemon=True, name="status-listener")
        self.path, self.retry_s = Path(path), retry_s
        self.connects = 0
        self._latest: dict[str, dict] = {}
        self._lock = threading.Lock()
        self._halt = threading.Event()

    def handle(self, received_ns: int, topic: str, data) -> None:
        """One message, ``received_ns`` its arrival (CLOCK_MONOTONIC)."""
        with self._lock:
            self._latest[topic] = data

    def latest(self, topic: str) -> dict | None:
        with self._lock:
            return self._latest.get(topic)

    def run(self) -> None:
        while not self._halt.is_set():
            s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            try:
                s.connect(str(self.path))
            except OSError:
                s.close()
                self._halt.wait(self.retry_s)
                continue
            self.connects += 1
            s.settimeout(0.2)
            buf = b""
            while not self._halt.is_set():
                try:
                    chunk = s.recv(1 << 20)
                except TimeoutError:
                    continue
                except OSError:
                    break
                if not chunk:
                    break
                now = time.monotonic_ns()
                *lines, buf = (buf + chunk).split(b"\n")
                for ln in lines:
                    try:
                        msg = json.loads(ln)
                        topic, data = str(msg["topic"]), msg["data"]
                    except (ValueError, KeyError, TypeError):
                        continue
                    self.handle(now, topic, data)
            s.close()

    def stop(self) -> None:
        self._halt.set()
        if self.is_alive():
            self.join(5.0)
