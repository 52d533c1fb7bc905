"""Crash-safe session logs: MCAP segments written from a bounded queue (docs/architecture.md §4).

A session is one directory per acquisition run, ``<root>/YYYYmmddTHHMMSSZ_<vessel>/``, holding
``seg-000001.mcap``, ``seg-000002.mcap``, … (message encodings: :mod:`acquire.log.schema`).

Producers call :meth:`SessionWriter.submit` (one record) or :meth:`SessionWriter.submit_batch`
(records already stamped with their GPS time: the daemon's hot path hands over a few
milliseconds' worth at once), which never block: they stamp the per-channel sequence counter and
put the records on a queue bounded in records (``queue_size``); what does not fit is dropped,
counted, and the ``log_queue_overflow`` alarm raised (the sequence gap shows the loss in the
log). One writer thread drains the queue into the current segment (the segment side:
:mod:`acquire.log.segments`; names and options: :mod:`acquire.log.session`).

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
- free space is checked every ``disk_check_s`` and every 64 MiB written, a segment open or not
  (:mod:`acquire.log.diskspace`): the ``disk_low`` alarm, warning below ``disk_warning_bytes``
  and critical below ``disk_critical_bytes``, with the minutes left at the current write rate,
  comes before the disk is full; it clears with hysteresis;
- the session directory holds ``session.lock`` (flock, with the writer's pid) while a writer
  owns it; an unfinished segment of a session nobody holds is salvaged by
  :mod:`acquire.log.recover` (at daemon start and by ``mls logs recover``).
"""

from __future__ import annotations

import datetime as _dt
import fcntl
import os
import queue
import re
import threading
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

from acquire.alarms import WARNING, AlarmBook
from acquire.log.diskspace import DiskWatch
from acquire.log.schema import RAW
from acquire.log.segments import SegmentIO, SegmentLog, WriterStats
from acquire.log.session import LOCK_NAME, LogError, SessionOptions, fsync_dir, session_name

NS_PER_S = 1_000_000_000


class Clock(Protocol):
    def to_gps(self, host_ns: int) -> Any: ...


_STOP = object()
_ROTATE = object()


class SessionWriter(SegmentLog):
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
        super().__init__(
            vessel,
            options or SessionOptions(),
            alarms if alarms is not None else AlarmBook(),
            channel_metadata,
            io_factory,
            monotonic_ns,
        )
        self.root = Path(root)
        self.clock = clock
        self._start_utc = start_utc
        self._queue: queue.SimpleQueue = queue.SimpleQueue()  # lists of records, and _ROTATE/_STOP
        self._queued = 0  # records in the queue (under _seq_lock): the bound is in records
        self._seq: dict[str, int] = {}
        self._seq_lock = threading.Lock()
        self._last_drop_ns: int | None = None
        self._heartbeat_ns = self._now()
        self._thread: threading.Thread | None = None
        self._lock_fd: int | None = None
        o = self.options
        self._disk = DiskWatch(o.disk_warning_bytes, o.disk_critical_bytes, o.disk_check_s, self.alarms)

    # -- producer side ----------------------------------------------------------------------

    def start(self) -> Path:
        """Create and lock the session directory, open the first segment, start the thread."""
        self.root.mkdir(parents=True, exist_ok=True)
        start = self._start_utc or _dt.datetime.now(_dt.UTC)
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
        self._lock_fd = os.open(d / LOCK_NAME, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC | os.O_NOFOLLOW, 0o640)
        fcntl.flock(self._lock_fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        os.write(self._lock_fd, f"{os.getpid()}\n".encode())
        now = self._now()
        if not self._open_segment(now):
            self._fail_open(now)
        self._thread = threading.Thread(target=self._run, name="mls-sessionlog", daemon=True)
        self._thread.start()
        return d

    def submit(
        self,
        topic: str,
        payload: bytes | dict,
        *,
        host_ns: int,
        device_ns: int | None = None,
        log_time_ns: int | None = None,
        clock_state: str | None = None,
    ) -> bool:
        """Queue one record; never blocks. Returns False when it was dropped (queue full).

        ``payload``: the exact received bytes (raw channels) or a JSON-able dict (must not be
        mutated afterwards). ``log_time_ns``/``clock_state`` default to the clock model's
        estimate at ``host_ns``.
        """
        if log_time_ns is None:
            if self.clock is not None:
                est = self.clock.to_gps(host_ns)
                log_time_ns = est.gps_ns
                clock_state = getattr(est, "record_state", None) or getattr(est.state, "value", est.state)
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
                    items.append(
                        (
                            topic,
                            seq,
                            payload,
                            int(host_ns),
                            device_ns,
                            int(log_time_ns),
                            clock_state or "UNLOCKED",
                            now,
                        )
                    )
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
            self.alarms.raise_now(
                "log_queue_overflow",
                "log",
                now,
                severity=WARNING,
                message=f"log queue full ({self.options.queue_size}): {total} records dropped",
            )
        return len(items)

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

    def _maintain(self, now: int) -> None:
        o = self.options
        written = self._closed_bytes + (self._io.pos if self._io is not None else 0)
        if self._disk.due(now, written):
            free = self._free_bytes()
            self._disk.update(now, written, free, self.root)
            if free is not None:
                self._stats.free_bytes = free
            self._stats.disk_minutes_left = self._disk.minutes_left
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
            self.alarms.clear_now(
                "log_queue_overflow",
                "log",
                now,
                message=f"log queue drained; {total} records dropped in total",
            )

    def _resumed(self, now: int) -> None:
        paused_s = (now - (self._failed_since or now)) / NS_PER_S
        lost = sum(self._lost_at_failure.values())
        note = dict(self._failure_note or {})
        note.update(
            {
                "event": "log_write_failed",
                "resumed_segment": self._stats.segment,
                "paused_s": round(paused_s, 3),
                "records_lost": dict(self._lost_at_failure),
            }
        )
        self.alarms.clear_now(
            "disk_write_failed",
            "log",
            now,
            message=f"writing resumed in {self._stats.segment} after {paused_s:.1f} s; {lost} records lost",
        )
        self._lost_at_failure = Counter()
        self._failed_since = None
        self._failure_note = None
        self.submit("/events", note, host_ns=now)  # logged in the new segment
