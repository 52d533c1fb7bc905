"""The writer thread's segments of a session log (see :mod:`acquire.log.sessionlog`): records
into the open MCAP segment, chunk completion, fsync, rotation, and ending a segment after a
failed write or fsync."""

from __future__ import annotations

import datetime as _dt
import errno
import os
import socket
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any, cast

from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.records import DataEnd, Footer
from mcap.writer import MCAP0_MAGIC

from acquire.alarms import CRITICAL, AlarmBook
from acquire.log import diskspace
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
from acquire.log.session import COMPRESSIONS, RESERVE_NAME, SessionOptions, fsync_dir

NS_PER_S = 1_000_000_000
# what ends a segment that cannot be finished normally: Data End + Footer without summary + magic
_rb = RecordBuilder()
DataEnd(0).write(_rb)
Footer(summary_start=0, summary_offset_start=0, summary_crc=0).write(_rb)
MINIMAL_END = _rb.end() + MCAP0_MAGIC
del _rb
_CHUNK_OPCODE = bytes([Opcode.CHUNK])


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
    free_bytes: int | None = None  # free space of the session's file system (at the last check)
    disk_minutes_left: float | None = None  # free space / write rate (disk_low)

    def as_dict(self) -> dict:
        return {
            "state": self.state,
            "segment": self.segment,
            "segments": self.segments,
            "messages_written": self.messages_written,
            "bytes_written": self.bytes_written,
            "dropped": dict(self.dropped),
            "lost": dict(self.lost),
            "failures": self.failures,
            "last_error": self.last_error,
            "queue_depth": self.queue_depth,
            "free_bytes": self.free_bytes,
            "disk_minutes_left": self.disk_minutes_left,
        }


def _errtext(e: OSError) -> str:
    code = errno.errorcode.get(e.errno, str(e.errno)) if e.errno else type(e).__name__
    return f"{code}: {e.strerror or e}"


def _message(seq: int, device_ns: int | None, log_time_ns: int, head: bytes, data: bytes) -> tuple:
    """A record as :meth:`SegmentWriter.add_run` takes it: (log time, publish time, sequence,
    head, data); the publish time is the device's stamp when it has one, times before the GPS
    epoch are 0, the sequence its low 32 bits."""
    publish = device_ns if device_ns is not None else log_time_ns
    return (
        log_time_ns if log_time_ns > 0 else 0,
        publish if publish > 0 else 0,
        seq & 0xFFFFFFFF,
        head,
        data,
    )


class SegmentLog:
    """Writes records into the session's segments, on the writer thread: the open segment's
    channels and chunk, fsync and rotation by size, and ending a segment after a failed write
    or fsync (writing pauses; :class:`~acquire.log.sessionlog.SessionWriter` retries). The
    segments are created in ``session_dir``, set before the first one opens."""

    def __init__(
        self,
        vessel: str,
        options: SessionOptions,
        alarms: AlarmBook,
        channel_metadata: dict[str, dict[str, str]] | None,
        io_factory: Callable[[Path], SegmentIO],
        monotonic_ns: Callable[[], int],
    ):
        self.vessel = vessel
        self.options = options
        self.alarms = alarms
        self.channel_metadata = {k: dict(v) for k, v in (channel_metadata or {}).items()}
        self._io_factory = io_factory
        self._now = monotonic_ns
        self._kinds: dict[str, str] = {}  # topic → channel kind
        self._stats = WriterStats()
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

    def _kind(self, topic: str) -> str:
        """The channel kind of a topic (ValueError for one not in docs/architecture.md §4), remembered."""
        return self._kinds.get(topic) or self._kinds.setdefault(topic, channel_kind(topic))

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
        mcap, io = self._mcap, self._io
        # _write_all makes runs only into an open segment
        assert mcap is not None
        assert io is not None
        room = mcap.chunk_room()
        assert room is not None  # segments are always chunked (_open_segment)
        rotate_room = self.options.rotate_bytes - io.pos - self._chunk_bytes
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
                self._schema_id = self._mcap.register_schema(
                    ENVELOPE_SCHEMA_NAME, "jsonschema", ENVELOPE_SCHEMA
                )
            cid = self._mcap.register_channel(topic, JSON_ENCODING, self._schema_id, md)
        self._channels[topic] = cid
        return cid

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
        assert self.session_dir is not None
        return diskspace.free_bytes(self.session_dir)

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
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_CLOEXEC | os.O_NOFOLLOW, 0o640)
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
            self._stats.last_error = (
                f"{path.name}: not opened, {free / 2**20:.1f} MiB free on the "
                f"log file system (at least "
                f"{self.options.min_free_bytes / 2**20:.1f} MiB needed)"
            )
            return False
        try:
            self._ensure_reserve()
            io = self._io_factory(path)
            # the Writer is annotated to take a file, but uses only write, tell and flush
            mcap = SegmentWriter(
                cast(IO[Any], _ChunkWatch(io, self._chunk_written)),
                chunk_size=self.options.chunk_bytes,
                compression=COMPRESSIONS[self.options.compression],
            )
            from acquire import __version__

            mcap.start(profile="", library=f"marine-mls {__version__}")
            mcap.add_metadata(
                "mls.session",
                {
                    "vessel": self.vessel,
                    "session": self.session_dir.name,
                    "segment": str(self._index + 1),
                    "software": __version__,
                    "host": socket.gethostname(),
                    "opened_utc": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
                },
            )
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
        self._failure_note = {"segment": name, "operation": op, "error": _errtext(err), "segment_end": closed}
        self.alarms.raise_now(
            "disk_write_failed",
            "log",
            now,
            severity=CRITICAL,
            message=f"{self._stats.last_error}; segment {closed}; writing paused, "
            f"retrying every {self.options.retry_s:g} s",
        )

    def _fail_open(self, now: int) -> None:
        self._stats.state = "failed"
        self._stats.failures += 1
        self._failed_since = now
        self._next_retry_ns = now + int(self.options.retry_s * NS_PER_S)
        self._failure_note = {
            "segment": None,
            "operation": "open",
            "error": self._stats.last_error,
            "segment_end": None,
        }
        self.alarms.raise_now(
            "disk_write_failed",
            "log",
            now,
            severity=CRITICAL,
            message=f"{self._stats.last_error}; retrying every {self.options.retry_s:g} s",
        )
