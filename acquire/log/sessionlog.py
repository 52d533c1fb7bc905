"""Crash-safe session logs: MCAP segments written from a bounded queue (DESIGN §4).

A session is one directory per acquisition run, ``<root>/YYYYmmddTHHMMSSZ_<vessel>/``, holding
``seg-000001.mcap``, ``seg-000002.mcap``, … (message encodings: :mod:`acquire.log.schema`).

Producers call :meth:`SessionWriter.submit` (one record) or :meth:`SessionWriter.submit_batch`
(records already stamped with their GPS time: the daemon's hot path hands over a few
milliseconds' worth at once), which never block: they stamp the per-channel sequence counter and
put the records on a queue bounded in records (``queue_size``); what does not fit is dropped,
counted, and the ``log_queue_overflow`` alarm raised (the sequence gap shows the loss in the
log). One writer thread drains the queue into the current segment.

Durability:

- chunk flush: a record is written to the file (a complete, CRC-checked MCAP chunk) no later
  than ``flush_s`` after it was submitted (the writer aims at ¾ of it);
- fsync of the segment every ``fsync_s`` and at segment close; fsync of the directory after a
  segment is created or closed;
- rotation to a new segment every ``rotate_s`` or ``rotate_bytes``;
- a failed write (ENOSPC, EIO) ends the segment: the file is truncated to the last complete
  record and closed with a Data End + Footer (a valid MCAP without summary; a small reserve
  file is released first so that there is room for those 50 bytes); a failed **fsync** ends the
  segment at once with no further write to it — the kernel may have dropped the dirty pages, so
  nothing written before can be trusted by retrying. Either way the ``disk_write_failed`` alarm
  is raised, records are dropped (and counted) while writing is paused, and every ``retry_s`` the
  writer tries a new segment; when writes succeed again it resumes there, clears the alarm and
  logs a ``log_write_failed`` event in ``/events``. The records counted lost by a failure are
  exactly those not in a chunk the file received whole (a chunk is one write; its message
  indexes, the summary and the footer that follow it carry no record), i.e. what a salvage of
  the segment cannot read;
- the session directory holds ``session.lock`` (flock, with the writer's pid) while a writer
  owns it; an unfinished segment of a session nobody holds is salvaged by
  :mod:`acquire.log.recover` (at daemon start and by ``mls logs recover``).
"""

from __future__ import annotations

import datetime as _dt
import errno
import fcntl
import os
import queue
import re
import socket
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Protocol

from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.records import DataEnd, Footer
from mcap.writer import MCAP0_MAGIC, CompressionType

from acquire.alarms import CRITICAL, WARNING, AlarmBook
from acquire.log.mcapwriter import MESSAGE_RECORD_BYTES, SegmentWriter
from acquire.log.schema import (
    ENVELOPE_SCHEMA,
    ENVELOPE_SCHEMA_NAME,
    JSON_ENCODING,
    RAW,
    RAW_ENCODING,
    channel_kind,
    encode_json,
    raw_head,
)

NS_PER_S = 1_000_000_000
SEGMENT_RE = re.compile(r"^seg-(\d{6})\.mcap$")
SESSION_RE = re.compile(r"^\d{8}T\d{6}Z_[A-Za-z0-9][A-Za-z0-9_.-]*$")
LOCK_NAME = "session.lock"
RESERVE_NAME = ".reserve"
COMPRESSIONS = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}
# what ends a segment that cannot be finished normally: Data End + Footer without summary + magic
_rb = RecordBuilder()
DataEnd(0).write(_rb)
Footer(summary_start=0, summary_offset_start=0, summary_crc=0).write(_rb)
MINIMAL_END = _rb.end() + MCAP0_MAGIC
del _rb
_CHUNK_OPCODE = bytes([Opcode.CHUNK])


class LogError(RuntimeError):
    """A session directory that cannot be used (locked by another writer, not creatable)."""


@dataclass(frozen=True)
class SessionOptions:
    rotate_s: float = 600.0
    rotate_bytes: int = 512 * 1024 * 1024
    flush_s: float = 0.5  # chunk flush period (≤ 1 s)
    fsync_s: float = 2.0
    queue_size: int = 50_000
    compression: str = "zstd"  # zstd | lz4 | none
    chunk_bytes: int = 1024 * 1024
    retry_s: float = 1.0  # after a write failure, try a new segment this often
    reserve_bytes: int = 64 * 1024  # released to close a segment on a full disk
    min_free_bytes: int = 16 * 1024 * 1024  # no new segment on a file system with less free
    stall_s: float = 10.0  # writer loop silent this long → unhealthy (watchdog)

    def __post_init__(self) -> None:
        if not 0 < self.flush_s <= 1.0:
            raise ValueError(f"flush_s={self.flush_s}: expected 0 < flush_s ≤ 1 s")
        if self.fsync_s <= 0 or self.rotate_s <= 0 or self.rotate_bytes <= 0:
            raise ValueError("fsync_s, rotate_s and rotate_bytes must be positive")
        if self.compression not in COMPRESSIONS:
            raise ValueError(f"compression {self.compression!r}: expected one of {sorted(COMPRESSIONS)}")


class SegmentIO:
    """The segment file: unbuffered, full writes (a short write is continued, never ignored),
    and the offset after the last complete write (``good``) for truncation after a failure."""

    def __init__(self, path: Path):
        self.path = path
        self.fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, 0o640)
        self.pos = 0
        self.good = 0

    def write(self, data) -> int:
        view = memoryview(data)
        while view:
            n = os.write(self.fd, view)
            self.pos += n
            view = view[n:]
        self.good = self.pos
        return len(data)

    def tell(self) -> int:
        return self.pos

    def flush(self) -> None:  # the mcap Writer calls this; there is no user-space buffer
        pass

    def fsync(self) -> None:
        os.fsync(self.fd)

    def truncate(self, size: int) -> None:
        os.ftruncate(self.fd, size)
        os.lseek(self.fd, size, os.SEEK_SET)
        self.pos = self.good = size

    def close(self) -> None:
        os.close(self.fd)


class _ChunkWatch:
    """The stream the mcap Writer writes to: passes everything to the segment file and calls
    ``on_chunk()`` after each Chunk record written whole. (The Writer emits a chunk as one write
    holding that record alone — its buffered records are written just before — and a chunk holds
    every message added since the previous one, so from then on those records are in the file.)"""

    def __init__(self, io: SegmentIO, on_chunk: Callable[[], None]):
        self.io, self.on_chunk = io, on_chunk

    def write(self, data) -> int:
        n = self.io.write(data)
        if data[:1] == _CHUNK_OPCODE:
            self.on_chunk()
        return n

    def tell(self) -> int:
        return self.io.tell()

    def flush(self) -> None:
        self.io.flush()


class Clock(Protocol):
    def to_gps(self, host_ns: int) -> Any: ...


@dataclass
class WriterStats:
    state: str = "idle"  # idle | writing | failed | closed
    segment: str | None = None
    segments: int = 0
    messages_written: int = 0
    bytes_written: int = 0  # file bytes of closed segments + the current one
    dropped: Counter = field(default_factory=Counter)  # queue full, by topic
    lost: Counter = field(default_factory=Counter)  # discarded by a write failure, by topic
    failures: int = 0
    last_error: str | None = None
    queue_depth: int = 0
    free_bytes: int | None = None  # free space of the session's file system (at the last fsync)

    def as_dict(self) -> dict:
        return {
            "state": self.state, "segment": self.segment, "segments": self.segments,
            "messages_written": self.messages_written, "bytes_written": self.bytes_written,
            "dropped": dict(self.dropped), "lost": dict(self.lost), "failures": self.failures,
            "last_error": self.last_error, "queue_depth": self.queue_depth,
            "free_bytes": self.free_bytes,
        }  # fmt: skip


def fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def session_name(vessel: str, start_utc: _dt.datetime) -> str:
    return f"{start_utc.astimezone(_dt.timezone.utc):%Y%m%dT%H%M%SZ}_{vessel}"


def _errtext(e: OSError) -> str:
    code = errno.errorcode.get(e.errno, str(e.errno)) if e.errno else type(e).__name__
    return f"{code}: {e.strerror or e}"


_STOP = object()
_ROTATE = object()


def _message(seq: int, device_ns: int | None, log_time_ns: int, head: bytes, data: bytes) -> tuple:
    """A record as :meth:`SegmentWriter.add_run` takes it: (log time, publish time, sequence,
    head, data); the publish time is the device's stamp when it has one, times before the GPS
    epoch are 0, the sequence its low 32 bits."""
    publish = device_ns if device_ns is not None else log_time_ns
    return (log_time_ns if log_time_ns > 0 else 0, publish if publish > 0 else 0,
            seq & 0xFFFFFFFF, head, data)  # fmt: skip


class SessionWriter:
    """Writes one session: bounded queue in, MCAP segments out (see the module docstring)."""

    def __init__(
        self,
        root: str | Path,
        vessel: str,
        options: SessionOptions | None = None,
        *,
        alarms: AlarmBook | None = None,
        clock: Clock | None = None,
        channel_metadata: dict[str, dict[str, str]] | None = None,
        start_utc: _dt.datetime | None = None,
        io_factory: Callable[[Path], SegmentIO] = SegmentIO,
        monotonic_ns: Callable[[], int] = time.monotonic_ns,
    ):
        if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9_.-]*", vessel):
            raise ValueError(f"vessel name {vessel!r}: expected letters, digits, '_', '.', '-'")
        self.root = Path(root)
        self.vessel = vessel
        self.options = options or SessionOptions()
        self.alarms = alarms if alarms is not None else AlarmBook()
        self.clock = clock
        self.channel_metadata = {k: dict(v) for k, v in (channel_metadata or {}).items()}
        self._start_utc = start_utc
        self._io_factory = io_factory
        self._now = monotonic_ns
        self._queue: queue.SimpleQueue = queue.SimpleQueue()  # lists of records, and _ROTATE/_STOP
        self._queued = 0  # records in the queue (under _seq_lock): the bound is in records
        self._kinds: dict[str, str] = {}  # topic → channel kind
        self._seq: dict[str, int] = {}
        self._seq_lock = threading.Lock()
        self._stats = WriterStats()
        self._last_drop_ns: int | None = None
        self._heartbeat_ns = self._now()
        self._thread: threading.Thread | None = None
        self._lock_fd: int | None = None
        self.session_dir: Path | None = None
        # segment state (writer thread only)
        self._io: SegmentIO | None = None
        self._mcap: SegmentWriter | None = None
        self._channels: dict[str, int] = {}
        self._schema_id = 0
        self._index = 0
        self._seg_opened_ns = 0
        self._closed_bytes = 0
        self._unflushed_since: int | None = None  # submit time of the oldest record not flushed
        self._unflushed: Counter = Counter()  # records not yet in a chunk written whole, by topic
        self._data_end: int | None = None  # end of the data records once the segment is finishing
        self._chunk_bytes = 0  # message bytes in the open chunk
        self._dirty_since_fsync = False
        self._last_fsync_ns = 0
        self._failed_since: int | None = None
        self._next_retry_ns = 0
        self._lost_at_failure: Counter = Counter()
        self._failure_note: dict | None = None

    # -- producer side ----------------------------------------------------------------------

    def start(self) -> Path:
        """Create and lock the session directory, open the first segment, start the thread."""
        self.root.mkdir(parents=True, exist_ok=True)
        start = self._start_utc or _dt.datetime.now(_dt.timezone.utc)
        for k in range(100):
            d = self.root / session_name(self.vessel, start + _dt.timedelta(seconds=k))
            try:
                d.mkdir()
                break
            except FileExistsError:
                continue
        else:
            raise LogError(f"{self.root}: cannot create a new session directory")
        fsync_dir(self.root)
        self.session_dir = d
        self._lock_fd = os.open(d / LOCK_NAME, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o640)
        fcntl.flock(self._lock_fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        os.write(self._lock_fd, f"{os.getpid()}\n".encode())
        now = self._now()
        if not self._open_segment(now):
            self._fail_open(now)
        self._thread = threading.Thread(target=self._run, name="mls-sessionlog", daemon=True)
        self._thread.start()
        return d

    def submit(self, topic: str, payload: bytes | dict, *, host_ns: int, device_ns: int | None = None,
               log_time_ns: int | None = None, clock_state: str | None = None) -> bool:  # fmt: skip
        """Queue one record; never blocks. Returns False when it was dropped (queue full).

        ``payload``: the exact received bytes (raw channels) or a JSON-able dict (must not be
        mutated afterwards). ``log_time_ns``/``clock_state`` default to the clock model's
        estimate at ``host_ns``.
        """
        if log_time_ns is None:
            if self.clock is not None:
                est = self.clock.to_gps(host_ns)
                log_time_ns, clock_state = est.gps_ns, getattr(est.state, "value", est.state)
            else:
                log_time_ns = host_ns
        return self.submit_batch([(topic, payload, host_ns, device_ns, log_time_ns, clock_state)]) == 1

    def submit_batch(self, records: list[tuple]) -> int:
        """Queue ``(topic, payload, host_ns, device_ns, log_time_ns, clock_state)`` records, in
        order; never blocks. Returns how many were queued: the rest did not fit (dropped,
        counted, alarm). Raises TypeError, queuing nothing, when a payload does not suit its
        channel."""
        for topic, payload, *_ in records:
            if self._kind(topic) == RAW:
                if not isinstance(payload, (bytes, bytearray, memoryview)):
                    raise TypeError(f"{topic} is a raw channel: payload must be bytes")
            elif not isinstance(payload, dict):
                raise TypeError(f"{topic} is a JSON channel: payload must be a dict")
        now = self._now()
        items: list[tuple] = []
        dropped: Counter | None = None
        with self._seq_lock:
            room = self.options.queue_size - self._queued
            seqs = self._seq
            for topic, payload, host_ns, device_ns, log_time_ns, clock_state in records:
                seq = seqs.get(topic, 0) + 1
                seqs[topic] = seq
                if len(items) < room:
                    items.append((topic, seq, payload, int(host_ns), device_ns, int(log_time_ns),
                                  clock_state or "UNLOCKED", now))  # fmt: skip
                else:
                    if dropped is None:
                        dropped = Counter()
                    dropped[topic] += 1
            self._queued += len(items)
        if items:
            self._queue.put(items)
        if dropped:
            self._stats.dropped.update(dropped)
            self._last_drop_ns = now
            total = sum(self._stats.dropped.values())
            self.alarms.raise_now("log_queue_overflow", "log", now, severity=WARNING,
                                  message=f"log queue full ({self.options.queue_size}): "
                                          f"{total} records dropped")  # fmt: skip
        return len(items)

    def _kind(self, topic: str) -> str:
        """The channel kind of a topic (ValueError for one not in DESIGN §4), remembered."""
        return self._kinds.get(topic) or self._kinds.setdefault(topic, channel_kind(topic))

    def rotate(self) -> None:
        """Ask for a new segment now (operator command, or a pass start)."""
        self._queue.put(_ROTATE)

    def close(self, timeout_s: float = 30.0) -> None:
        """Drain the queue, close the segment (fsync), release the session lock."""
        if self._thread is not None:
            self._queue.put(_STOP)
            self._thread.join(timeout_s)
            self._thread = None
        if self._lock_fd is not None:
            os.close(self._lock_fd)  # releases the flock
            self._lock_fd = None

    def stats(self) -> WriterStats:
        s = self._stats
        s.queue_depth = self._queued
        io = self._io
        s.bytes_written = self._closed_bytes + (io.pos if io is not None else 0)
        return s

    def health(self, now_ns: int | None = None) -> tuple[bool, str]:
        """Watchdog check: the writer thread is alive and its loop is progressing."""
        now = self._now() if now_ns is None else now_ns
        if self._thread is None or not self._thread.is_alive():
            return False, "log writer thread is not running"
        age_s = (now - self._heartbeat_ns) / NS_PER_S
        if age_s > self.options.stall_s:
            return False, f"log writer stalled for {age_s:.1f} s (a write or fsync hangs)"
        if self._stats.state == "failed":
            return True, f"log writing paused after an error: {self._stats.last_error}"
        return True, "log writer ok"

    # -- writer thread ----------------------------------------------------------------------

    def _run(self) -> None:
        stopping = False
        while True:
            self._heartbeat_ns = now = self._now()
            try:
                item = self._queue.get(timeout=self._wait_s(now))
            except queue.Empty:
                item = None
            pending, n = [], 0
            while item is not None:
                pending.append(item)
                if isinstance(item, list):
                    n += len(item)
                if n >= 2000:
                    break
                try:
                    item = self._queue.get_nowait()
                except queue.Empty:
                    break
            if n:
                with self._seq_lock:
                    self._queued -= n
            for it in pending:
                if it is _STOP:
                    stopping = True
                elif it is _ROTATE:
                    self._rotate(self._now(), "requested")
                else:
                    self._write_all(it)
            self._maintain(self._now())
            if stopping:  # everything submitted before close() was ahead of _STOP
                self._close_segment(self._now(), "shutdown")
                self._stats.state = "closed"
                return

    def _wait_s(self, now: int) -> float:
        wait = 0.1
        if self._unflushed_since is not None:
            wait = min(wait, (self._flush_deadline() - now) / NS_PER_S)
        return max(wait, 0.0)

    def _flush_deadline(self) -> int:
        assert self._unflushed_since is not None
        return self._unflushed_since + int(0.75 * self.options.flush_s * NS_PER_S)

    def _write_all(self, records: list) -> None:
        """:meth:`_write` of each record, in order; a run of records of one raw channel (the
        profiler's datagrams: ~23 k/s at ×5) goes to the segment as one run of messages."""
        i, n = 0, len(records)
        while i < n:
            topic = records[i][0]
            j = i + 1  # (a rotation gives the next segment channels of its own)
            if self._mcap is not None and topic in self._channels and self._kind(topic) == RAW:
                while j < n and records[j][0] == topic:
                    j += 1
            if j - i > 1:
                i = self._write_raw_run(records, i, j)
            else:
                self._write(records[i])
                i += 1

    def _write_raw_run(self, records: list, i: int, j: int) -> int:
        """Records ``i:j`` (one raw channel, already registered) as :meth:`_write` would write
        them, up to the record that completes the open chunk or makes the segment due for
        rotation; returns the index of the first record not written."""
        mcap = self._mcap
        room = mcap.chunk_room()  # segments are always chunked
        rotate_room = self.options.rotate_bytes - self._io.pos - self._chunk_bytes
        topic = records[i][0]
        messages, chunk_bytes, record_bytes = [], 0, 0
        for k in range(i, j):
            _, seq, payload, host_ns, device_ns, log_time_ns, clock_state, _ = records[k]
            head = raw_head(seq, host_ns, device_ns, clock_state)
            messages.append(_message(seq, device_ns, log_time_ns, head, payload))
            size = len(head) + len(payload)
            chunk_bytes += size
            record_bytes += MESSAGE_RECORD_BYTES + size
            if record_bytes > room or chunk_bytes >= rotate_room:
                break
        m = len(messages)
        self._adding(topic, m, chunk_bytes, records[i][7])
        try:
            mcap.add_run(self._channels[topic], messages)
        except OSError as e:  # the chunk the last one completed could not be written
            self._stats.messages_written += m - 1
            self._fail(e, "write", self._now())
            return i + m
        self._added(m)
        return i + m

    def _adding(self, topic: str, n: int, nbytes: int, submit_ns: int) -> None:
        """``n`` records of ``topic`` (``nbytes`` of message data) are about to be added, counted
        first: a chunk they complete holds them (:meth:`_chunk_written`)."""
        self._unflushed[topic] += n
        self._chunk_bytes += nbytes
        if self._unflushed_since is None:
            self._unflushed_since = submit_ns

    def _added(self, n: int) -> None:
        """``n`` records are in the segment's open chunk: rotate when it is due by size."""
        self._stats.messages_written += n
        self._dirty_since_fsync = True
        if self._io is not None and self._io.pos + self._chunk_bytes >= self.options.rotate_bytes:
            self._rotate(self._now(), "rotation")

    def _write(self, item) -> None:
        topic, seq, payload, host_ns, device_ns, log_time_ns, clock_state, submit_ns = item
        if self._mcap is None:
            self._stats.lost[topic] += 1
            self._lost_at_failure[topic] += 1
            return
        if self._kind(topic) == RAW:
            head, data = raw_head(seq, host_ns, device_ns, clock_state), payload
        else:
            head, data = b"", encode_json(seq, host_ns, device_ns, clock_state, payload)
        try:  # registering a channel may complete the open chunk (which does not hold this record)
            channel_id = self._channels.get(topic) or self._register(topic)
        except OSError as e:
            self._unflushed[topic] += 1
            self._fail(e, "write", self._now())
            return
        self._adding(topic, 1, len(head) + len(data), submit_ns)
        try:
            self._mcap.add_run(channel_id, [_message(seq, device_ns, log_time_ns, head, data)])
        except OSError as e:  # a chunk filled up and a write failed (the chunk's, or after it)
            self._fail(e, "write", self._now())
            return
        self._added(1)

    def _chunk_written(self) -> None:
        """A chunk reached the file whole: every record added so far is in the file."""
        self._unflushed.clear()
        self._unflushed_since = None
        self._chunk_bytes = 0

    def _register(self, topic: str) -> int:
        assert self._mcap is not None
        kind = self._kind(topic)
        md = {"mls.kind": kind, **self.channel_metadata.get(topic, {})}
        if kind == RAW:
            cid = self._mcap.register_channel(topic, RAW_ENCODING, 0, md)
        else:
            if not self._schema_id:
                self._schema_id = self._mcap.register_schema(ENVELOPE_SCHEMA_NAME, "jsonschema",
                                                             ENVELOPE_SCHEMA)  # fmt: skip
            cid = self._mcap.register_channel(topic, JSON_ENCODING, self._schema_id, md)
        self._channels[topic] = cid
        return cid

    def _maintain(self, now: int) -> None:
        o = self.options
        if self._mcap is None:
            if now >= self._next_retry_ns:
                if self._open_segment(now):
                    self._resumed(now)
                else:
                    self._next_retry_ns = now + int(o.retry_s * NS_PER_S)
            return
        if self._unflushed_since is not None and now >= self._flush_deadline():
            try:
                self._mcap.flush()  # completes the chunk: _chunk_written
            except OSError as e:
                self._fail(e, "write", now)
                return
        if self._dirty_since_fsync and now - self._last_fsync_ns >= o.fsync_s * NS_PER_S:
            if not self._fsync(now):
                return
        if now - self._seg_opened_ns >= o.rotate_s * NS_PER_S:
            self._rotate(now, "rotation")
        if self._last_drop_ns is not None and now - self._last_drop_ns >= 5 * NS_PER_S:
            self._last_drop_ns = None
            total = sum(self._stats.dropped.values())
            self.alarms.clear_now("log_queue_overflow", "log", now,
                                  message=f"log queue drained; {total} records dropped in total")  # fmt: skip

    def _fsync(self, now: int) -> bool:
        assert self._io is not None
        try:
            self._io.fsync()
        except OSError as e:
            self._fail(e, "fsync", now)
            return False
        self._dirty_since_fsync = False
        self._last_fsync_ns = now
        self._stats.free_bytes = self._free_bytes()
        return True

    def _free_bytes(self) -> int | None:
        try:
            st = os.statvfs(self.session_dir)  # type: ignore[arg-type]
        except OSError:
            return None
        return st.f_bavail * st.f_frsize

    def _rotate(self, now: int, reason: str) -> None:
        if self._mcap is None:
            return
        if self._close_segment(now, reason) and self._open_segment(now):
            return
        if self._mcap is None and self._stats.state != "failed":
            self._fail_open(now)

    # segment life cycle

    def _ensure_reserve(self) -> None:
        assert self.session_dir is not None
        path = self.session_dir / RESERVE_NAME
        if path.exists() and path.stat().st_size >= self.options.reserve_bytes:
            return
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_CLOEXEC, 0o640)
        try:
            os.posix_fallocate(fd, 0, self.options.reserve_bytes)
            os.fsync(fd)
        finally:
            os.close(fd)

    def _open_segment(self, now: int) -> bool:
        """Open the next segment; False (and nothing left behind) when the disk refuses."""
        assert self.session_dir is not None
        path = self.session_dir / f"seg-{self._index + 1:06d}.mcap"
        io = None
        free = self._free_bytes()
        self._stats.free_bytes = free
        if free is not None and free < self.options.min_free_bytes:
            self._stats.last_error = (f"{path.name}: not opened, {free / 2**20:.1f} MiB free on the "
                                      f"log file system (at least "
                                      f"{self.options.min_free_bytes / 2**20:.1f} MiB needed)")  # fmt: skip
            return False
        try:
            self._ensure_reserve()
            io = self._io_factory(path)
            mcap = SegmentWriter(_ChunkWatch(io, self._chunk_written), chunk_size=self.options.chunk_bytes,
                          compression=COMPRESSIONS[self.options.compression])  # fmt: skip
            from acquire import __version__

            mcap.start(profile="", library=f"marine-mls {__version__}")
            mcap.add_metadata("mls.session", {
                "vessel": self.vessel, "session": self.session_dir.name,
                "segment": str(self._index + 1), "software": __version__,
                "host": socket.gethostname(),
                "opened_utc": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
            })  # fmt: skip
            io.fsync()
            fsync_dir(self.session_dir)
        except OSError as e:
            self._stats.last_error = f"{path.name}: cannot open ({_errtext(e)})"
            if io is not None:
                try:
                    io.close()
                    path.unlink()
                except OSError:
                    pass
            return False
        self._index += 1
        self._io, self._mcap = io, mcap
        self._channels, self._schema_id = {}, 0
        self._data_end = None
        self._seg_opened_ns = self._last_fsync_ns = now
        self._dirty_since_fsync = False
        self._stats.state, self._stats.segment = "writing", path.name
        self._stats.segments += 1
        return True

    def _close_segment(self, now: int, reason: str) -> bool:
        """Finish the segment normally (summary, footer, fsync). On error: :meth:`_fail`."""
        if self._mcap is None or self._io is None:
            return True
        try:
            self._mcap.flush()  # the last chunk (_chunk_written)
            self._mcap.add_metadata("mls.segment_end", {"reason": reason})
            # what follows (Data End, summary, footer) holds no record: a failure from here on
            # cuts the file back to this point before ending it with Data End + Footer
            self._data_end = self._io.good
            self._mcap.finish()
        except OSError as e:
            self._fail(e, "write", now)
            return False
        if not self._fsync(now):
            return False
        io = self._io
        self._closed_bytes += io.pos
        self._mcap = self._io = None
        self._data_end = None
        try:
            io.close()
            assert self.session_dir is not None
            fsync_dir(self.session_dir)
        except OSError as e:
            self._fail(e, "fsync", now)
            return False
        return True

    def _fail(self, err: OSError, op: str, now: int) -> None:
        """End the segment after a failed write or fsync; pause writing; raise the alarm."""
        io, name = self._io, self._stats.segment
        closed = "left unfinished (salvaged at the next start)"
        if io is not None and op == "write":
            # the data up to the last complete write are whole records: cut there (or, when the
            # segment was being finished, where its data records end: no second Data End, no
            # half summary) and end the file with Data End + Footer; release the reserve so
            # that these bytes fit
            cut = io.good if self._data_end is None else min(io.good, self._data_end)
            try:
                assert self.session_dir is not None
                (self.session_dir / RESERVE_NAME).unlink(missing_ok=True)
                io.truncate(cut)
                io.write(MINIMAL_END)
                io.fsync()
                closed = f"closed cleanly at byte {io.pos} (no index)"
            except OSError:
                pass
        elif op == "fsync":
            closed = "abandoned without further writes (an fsync failure cannot be retried)"
        if io is not None:
            self._closed_bytes += io.pos
            try:
                io.close()
            except OSError:
                pass
        # lost: the records not in a chunk written whole (everything else reads after salvage)
        lost = Counter(self._unflushed)
        self._stats.lost.update(lost)
        self._lost_at_failure = Counter(lost)
        self._unflushed.clear()
        self._unflushed_since = None
        self._chunk_bytes = 0
        self._data_end = None
        self._mcap = self._io = None
        self._stats.state = "failed"
        self._stats.failures += 1
        self._stats.last_error = f"{name}: {op} failed ({_errtext(err)})"
        self._failed_since = now
        self._next_retry_ns = now + int(self.options.retry_s * NS_PER_S)
        self._failure_note = {"segment": name, "operation": op, "error": _errtext(err),
                              "segment_end": closed}  # fmt: skip
        self.alarms.raise_now(
            "disk_write_failed", "log", now, severity=CRITICAL,
            message=f"{self._stats.last_error}; segment {closed}; writing paused, "
                    f"retrying every {self.options.retry_s:g} s",
        )  # fmt: skip

    def _fail_open(self, now: int) -> None:
        self._stats.state = "failed"
        self._stats.failures += 1
        self._failed_since = now
        self._next_retry_ns = now + int(self.options.retry_s * NS_PER_S)
        self._failure_note = {"segment": None, "operation": "open",
                              "error": self._stats.last_error, "segment_end": None}  # fmt: skip
        self.alarms.raise_now("disk_write_failed", "log", now, severity=CRITICAL,
                              message=f"{self._stats.last_error}; retrying every "
                                      f"{self.options.retry_s:g} s")  # fmt: skip

    def _resumed(self, now: int) -> None:
        paused_s = (now - (self._failed_since or now)) / NS_PER_S
        lost = sum(self._lost_at_failure.values())
        note = dict(self._failure_note or {})
        note.update({"event": "log_write_failed", "resumed_segment": self._stats.segment,
                     "paused_s": round(paused_s, 3), "records_lost": dict(self._lost_at_failure)})  # fmt: skip
        self.alarms.clear_now("disk_write_failed", "log", now,
                              message=f"writing resumed in {self._stats.segment} after "
                                      f"{paused_s:.1f} s; {lost} records lost")  # fmt: skip
        self._lost_at_failure = Counter()
        self._failed_since = None
        self._failure_note = None
        self.submit("/events", note, host_ns=now)  # logged in the new segment
