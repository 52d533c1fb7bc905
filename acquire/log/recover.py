"""Reading, salvaging and summarizing session logs (``mls logs info`` / ``mls logs recover``).

:func:`scan_segment` walks a segment record by record without trusting anything after the first
problem: it yields every *complete* message (inside CRC-checked chunks) and stops at a torn or
corrupt record, reporting where (:class:`SegmentScan`). That is what a ``kill -9``, a power cut or
a full disk leaves: a segment without footer whose tail is a half-written chunk.

:func:`recover_segment` rewrites such a segment into a valid, indexed MCAP with the same
messages (same log/publish times, sequence numbers and bytes) plus an ``mls.recovery`` metadata
record naming the torn tail; the original is kept beside it as ``seg-NNNNNN.mcap.torn`` (the
swap is crash-safe: write ``.recovering``, fsync, rename the original, rename the new file,
fsync the directory); the new file gets the original's mode (and, where permitted, its owner
and group), so a salvage by root or at daemon start leaves a file the daemon's readers can read
as before. :func:`salvage_session` does that for every unfinished segment of a
session nobody is writing (``session.lock`` not held); :func:`salvage_root` for every session
under the log root (what the daemon runs at start-up).

:func:`session_info` summarizes a session: segments and their state, channels, message
counts, time span, gaps and sequence continuity across segments.
"""

from __future__ import annotations

import datetime as _dt
import fcntl
import io as _io
import os
import stat
import struct
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import BinaryIO, cast

from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, Footer, Message, Metadata, Schema
from mcap.stream_reader import breakup_chunk
from mcap.writer import MCAP0_MAGIC, CompressionType, Writer

from acquire.log.session import LOCK_NAME, SEGMENT_RE, LogError, fsync_dir

NS_PER_S = 1_000_000_000
_VALID_OPCODES = {int(o) for o in Opcode}
_HEAD = struct.Struct("<BQ")


@dataclass
class SegmentScan:
    """What a scan of one segment found."""

    path: Path
    size: int
    good_bytes: int = 0  # end of the last complete record
    footer: bool = False  # ends with Footer + magic (closed normally or after an error)
    indexed: bool = False  # the footer points at a summary (closed normally)
    problem: str | None = None  # why the scan stopped early

    @property
    def torn_bytes(self) -> int:  # (after a footer: bytes past its magic, normally none)
        return self.size - self.good_bytes

    @property
    def complete(self) -> bool:
        return self.footer and self.problem is None


#: the records a scan yields (a segment's data section, less its indexes and chunk framing)
ScanRecord = Schema | Channel | Message | Metadata


def scan_segment(path: Path, scan: SegmentScan | None = None) -> Iterator[ScanRecord]:
    """Yield the schemas, channels, messages and metadata of a segment's data section, in file
    order, stopping at the first torn or corrupt record. Fills ``scan`` as it goes."""
    path = Path(path)
    scan = scan if scan is not None else SegmentScan(path, 0)
    with open(path, "rb") as f:
        size = os.fstat(f.fileno()).st_size
        scan.size = size
        problem = _magic_problem(f.read(8))
        if problem is not None:
            scan.problem = problem
            return
        pos = scan.good_bytes = 8
        in_summary = False
        while True:
            head = f.read(_HEAD.size)
            if not head:
                return  # ends at a record boundary without footer: unfinished
            if len(head) < _HEAD.size:
                scan.problem = f"torn record header at byte {pos}"
                return
            opcode, length = _HEAD.unpack(head)
            problem = _head_problem(opcode, length, pos, size)
            if problem is not None:
                scan.problem = problem
                return
            body = f.read(length)
            try:
                if opcode == Opcode.FOOTER:
                    _end_at_footer(f, body, pos, length, scan)
                    return
                records = _body_records(opcode, body, length, in_summary)
            except Exception as e:  # bad CRC, undecompressable chunk, malformed body
                scan.problem = f"corrupt {Opcode(opcode).name.lower()} record at byte {pos} ({e})"
                return
            in_summary = in_summary or opcode == Opcode.DATA_END
            pos += _HEAD.size + length
            scan.good_bytes = pos
            yield from records


def _magic_problem(magic: bytes) -> str | None:
    """Why a segment's first 8 bytes are not the MCAP magic; None when they are."""
    if magic == MCAP0_MAGIC:
        return None
    if not magic:  # created, nothing written yet (a crash at once)
        return "empty file"
    if MCAP0_MAGIC.startswith(magic):
        return "torn MCAP magic at byte 0"
    return "not an MCAP file (bad magic)"


def _head_problem(opcode: int, length: int, pos: int, size: int) -> str | None:
    """Why the record announced at ``pos`` (``opcode``, ``length``) cannot be read in a file of
    ``size`` bytes (an unknown opcode, a body past the end); None when it can."""
    if opcode not in _VALID_OPCODES:
        return f"invalid record (opcode 0x{opcode:02x}) at byte {pos}"
    if length > size - pos - _HEAD.size:
        return (
            f"torn {Opcode(opcode).name.lower()} record at byte {pos} "
            f"({length} bytes announced, {size - pos - _HEAD.size} present)"
        )
    return None


def _body_records(opcode: int, body: bytes, length: int, in_summary: bool) -> list[ScanRecord]:
    """The records a record body carries: a chunk's (CRC-checked), a message, a schema or
    channel of the data section (their summary copies are skipped), a metadata record; none for
    the header, indexes, statistics, data end and attachments."""
    stream = ReadDataStream(_io.BytesIO(body))
    if opcode == Opcode.CHUNK:
        return _chunk_records(Chunk.read(stream))
    if opcode == Opcode.MESSAGE:
        return [Message.read(stream, length)]
    if opcode == Opcode.SCHEMA and not in_summary:
        return [Schema.read(stream)]
    if opcode == Opcode.CHANNEL and not in_summary:
        return [Channel.read(stream)]
    if opcode == Opcode.METADATA:
        return [Metadata.read(stream)]
    return []


def _chunk_records(chunk: Chunk) -> list[ScanRecord]:
    """A chunk's records, its CRC checked. ``breakup_chunk`` is annotated as returning any
    record, but it returns only the Schema, Channel and Message records of a chunk (mcap 1.6.0
    ``stream_reader``: it skips every other opcode)."""
    return cast(list[ScanRecord], breakup_chunk(chunk, validate_crc=True))


def _end_at_footer(f: BinaryIO, body: bytes, pos: int, length: int, scan: SegmentScan) -> None:
    """The Footer record at ``pos`` ends the segment: check the magic after it and fill
    ``scan`` (footer, indexed, good bytes; a problem for a missing magic or bytes after it)."""
    footer = Footer.read(ReadDataStream(_io.BytesIO(body)))
    if f.read(8) != MCAP0_MAGIC:
        scan.problem = f"torn or missing MCAP magic after the footer at byte {pos}"
        return
    scan.footer, scan.indexed = True, footer.summary_start != 0
    scan.good_bytes = end = pos + _HEAD.size + length + len(MCAP0_MAGIC)
    if end < scan.size:  # never written so by a writer: reported, not ignored
        scan.problem = f"torn tail of {scan.size - end} bytes after the footer at byte {pos}"


def segment_paths(session_dir: Path) -> list[Path]:
    return sorted(p for p in Path(session_dir).iterdir() if SEGMENT_RE.match(p.name))


def is_locked(session_dir: Path) -> bool:
    """True while a writer holds the session (its ``session.lock`` flock)."""
    lock = Path(session_dir) / LOCK_NAME
    if not lock.exists():
        return False
    fd = os.open(lock, os.O_RDONLY | os.O_CLOEXEC)
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        fcntl.flock(fd, fcntl.LOCK_UN)
        return False
    except BlockingIOError:
        return True
    finally:
        os.close(fd)


def segment_closed(path: Path) -> bool:
    """Quick check: the file ends with a Footer record and the magic (no full scan)."""
    size = path.stat().st_size
    if size < 8 + 8 + _HEAD.size + 20:
        return False
    with open(path, "rb") as f:
        f.seek(size - 8 - _HEAD.size - 20)
        tail = f.read()
    opcode, length = _HEAD.unpack_from(tail)
    return opcode == Opcode.FOOTER and length == 20 and tail[-8:] == MCAP0_MAGIC


# -- recovery ---------------------------------------------------------------------------------


@dataclass
class RecoveryReport:
    segment: str
    messages: int
    channels: dict[str, int]  # messages per topic
    good_bytes: int
    torn_bytes: int
    problem: str | None
    output: str  # the recovered file
    original: str | None  # where the original was kept (None: deleted)

    def as_dict(self) -> dict:
        return asdict(self)


def recover_segment(path: Path, keep_original: bool = True) -> RecoveryReport:
    """Rewrite an unfinished segment as a valid MCAP with every complete message."""
    path = Path(path)
    source = path
    torn_copy = path.with_name(path.name + ".torn")
    if not path.exists() and torn_copy.exists():  # a swap interrupted after the first rename
        source = torn_copy
    tmp = path.with_name(path.name + ".recovering")
    scan = SegmentScan(source, 0)
    st = os.stat(source)
    with open(tmp, "wb") as out:
        _same_owner_and_mode(out.fileno(), st)
        w = Writer(out, compression=CompressionType.ZSTD)
        w.start(profile="", library="marine-mls recover")
        counts = _copy_records(source, scan, w)
        w.add_metadata("mls.recovery", _recovery_record(path, scan, counts))
        w.finish()
        out.flush()
        os.fsync(out.fileno())
    _swap_in(path, tmp, torn_copy, source_is_path=source == path, keep_original=keep_original)
    return RecoveryReport(
        segment=path.name,
        messages=sum(counts.values()),
        channels=dict(counts),
        good_bytes=scan.good_bytes,
        torn_bytes=scan.torn_bytes,
        problem=scan.problem,
        output=str(path),
        original=str(torn_copy) if keep_original else None,
    )


def _copy_records(source: Path, scan: SegmentScan, w: Writer) -> Counter[str]:
    """Write every complete record of ``source`` (schemas, channels, metadata, messages with
    their times, sequence numbers and bytes) to ``w``; messages copied, per topic."""
    counts: Counter[str] = Counter()
    schema_ids: dict[int, int] = {}
    channel_ids: dict[int, int] = {}
    topics: dict[int, str] = {}
    for rec in scan_segment(source, scan):
        if isinstance(rec, Schema):
            schema_ids[rec.id] = w.register_schema(rec.name, rec.encoding, rec.data)
        elif isinstance(rec, Channel):
            channel_ids[rec.id] = w.register_channel(
                rec.topic, rec.message_encoding, schema_ids.get(rec.schema_id, 0), dict(rec.metadata)
            )
            topics[rec.id] = rec.topic
        elif isinstance(rec, Metadata):
            w.add_metadata(rec.name, dict(rec.metadata))
        elif isinstance(rec, Message) and rec.channel_id in channel_ids:
            w.add_message(
                channel_ids[rec.channel_id],
                log_time=rec.log_time,
                data=rec.data,
                publish_time=rec.publish_time,
                sequence=rec.sequence,
            )
            counts[topics[rec.channel_id]] += 1
    return counts


def _recovery_record(path: Path, scan: SegmentScan, counts: Counter[str]) -> dict[str, str]:
    """The ``mls.recovery`` metadata of a salvaged segment: its torn tail and what was kept."""
    return {
        "source": path.name,
        "good_bytes": str(scan.good_bytes),
        "torn_bytes": str(scan.torn_bytes),
        "problem": scan.problem or "no footer",
        "messages": str(sum(counts.values())),
        "recovered_utc": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
    }


def _swap_in(path: Path, tmp: Path, torn_copy: Path, *, source_is_path: bool, keep_original: bool) -> None:
    """Put the salvaged ``tmp`` in place of ``path`` crash-safely: the original becomes
    ``torn_copy`` first (unless a previous swap already moved it), then the directory is fsynced;
    the original is deleted afterwards unless kept."""
    if source_is_path:
        os.replace(path, torn_copy)
    os.replace(tmp, path)
    fsync_dir(path.parent)
    if not keep_original:
        torn_copy.unlink()
        fsync_dir(path.parent)


def _same_owner_and_mode(fd: int, st: os.stat_result) -> None:
    """Give the file ``fd`` the owner, group (best effort: only root may give a file away) and
    then the permission bits of ``st`` (after the chown, which may clear set-id bits)."""
    try:
        os.fchown(fd, st.st_uid, st.st_gid)
    except PermissionError:
        try:
            os.fchown(fd, -1, st.st_gid)
        except PermissionError:
            pass
    os.fchmod(fd, stat.S_IMODE(st.st_mode))


def unfinished_segments(session_dir: Path) -> list[Path]:
    """Segments without a footer, and segments whose recovery was interrupted."""
    session_dir = Path(session_dir)
    out = [p for p in segment_paths(session_dir) if not segment_closed(p)]
    for torn in session_dir.glob("seg-*.mcap.torn"):
        seg = torn.with_name(torn.name[: -len(".torn")])
        if not seg.exists():
            out.append(seg)
    return sorted(out)  # (a leftover .recovering file is simply rewritten)


def salvage_session(session_dir: Path, keep_original: bool = True) -> list[RecoveryReport]:
    session_dir = Path(session_dir)
    if is_locked(session_dir):
        raise LogError(
            f"{session_dir}: the session is being written by a running daemon "
            f"(pid {(session_dir / LOCK_NAME).read_text().strip() or '?'})"
        )
    return [recover_segment(p, keep_original) for p in unfinished_segments(session_dir)]


def session_dirs(root: Path) -> list[Path]:
    from acquire.log.session import SESSION_RE

    root = Path(root)
    if not root.is_dir():
        return []
    return sorted(p for p in root.iterdir() if p.is_dir() and SESSION_RE.match(p.name))


def salvage_root(root: Path) -> dict[str, list[RecoveryReport]]:
    """Salvage every session under ``root`` that no writer holds (daemon start-up)."""
    out: dict[str, list[RecoveryReport]] = {}
    for d in session_dirs(root):
        if is_locked(d):
            continue
        reports = salvage_session(d)
        if reports:
            out[d.name] = reports
    return out


# -- info -------------------------------------------------------------------------------------


@dataclass
class ChannelInfo:
    topic: str
    encoding: str
    messages: int = 0
    first_log_ns: int | None = None
    last_log_ns: int | None = None
    seq_first: int | None = None
    seq_last: int | None = None  # MCAP sequence (mod 2³²)
    missing: int = 0  # sequence numbers never seen
    duplicates: int = 0
    backwards: int = 0
    missing_ranges: list[tuple[int, int]] = field(default_factory=list)  # first few
    gaps: list[tuple[int, float]] = field(default_factory=list)  # (log_time before, seconds)
    unlocked: int = 0  # messages whose log_time came from an unlocked clock (JSON: read; raw: flag)
    # of those, stamped before any PPS fit: log_time is the host's clock, not GPS (schema's
    # host-time mark); counted here, kept out of first/last, the gaps and the span
    host_time: int = 0
    _period_ns: float | None = None


@dataclass
class SegmentInfo:
    name: str
    state: str  # complete | closed-after-error | unfinished | unreadable
    bytes: int
    messages: int
    first_log_ns: int | None
    last_log_ns: int | None
    torn_bytes: int
    problem: str | None
    recovery: dict | None  # the mls.recovery metadata of a recovered segment
    end_reason: str | None  # rotation | shutdown | requested (mls.segment_end)
    host_time: int = 0  # messages stamped in host time (before the PPS lock), outside first/last


@dataclass
class SessionInfo:
    session: str
    segments: list[SegmentInfo]
    channels: dict[str, ChannelInfo]

    @property
    def messages(self) -> int:
        return sum(c.messages for c in self.channels.values())

    @property
    def host_time_messages(self) -> int:
        """Messages stamped before the PPS lock (host time), outside :attr:`span_ns`."""
        return sum(c.host_time for c in self.channels.values())

    @property
    def span_ns(self) -> tuple[int | None, int | None]:
        """First and last GPS ``log_time`` (messages stamped in host time left out)."""
        firsts = [c.first_log_ns for c in self.channels.values() if c.first_log_ns is not None]
        lasts = [c.last_log_ns for c in self.channels.values() if c.last_log_ns is not None]
        return (min(firsts) if firsts else None, max(lasts) if lasts else None)

    def as_dict(self) -> dict:
        chans = {}
        for t, c in self.channels.items():
            d = asdict(c)
            d.pop("_period_ns")
            chans[t] = d
        return {
            "session": self.session,
            "messages": self.messages,
            "span_ns": list(self.span_ns),
            "host_time_messages": self.host_time_messages,
            "segments": [asdict(s) for s in self.segments],
            "channels": chans,
        }


def _unlocked(encoding: str, data: bytes) -> bool:
    from acquire.log.schema import FLAG_HOLDOVER, FLAG_LOCKED, RAW_ENCODING

    if encoding == RAW_ENCODING:
        return len(data) > 1 and not data[1] & (FLAG_LOCKED | FLAG_HOLDOVER)
    return b'"clock":"UNLOCKED"' in data


def session_info(
    session_dir: Path, gap_s: float = 1.0, progress: Callable[[int, int], None] | None = None
) -> SessionInfo:
    """Read every segment of a session (in order) and summarize it.

    A gap is a pause in a channel longer than ``max(gap_s, 5 × its typical period)``
    (``/events`` is sparse by nature and not checked). ``progress(done_bytes, total_bytes)``.
    """
    session_dir = Path(session_dir)
    if not session_dir.is_dir():
        raise LogError(f"{session_dir}: no such session directory")
    paths = segment_paths(session_dir)
    total = sum(p.stat().st_size for p in paths)
    done = 0
    channels: dict[str, ChannelInfo] = {}
    segments: list[SegmentInfo] = []
    gap_ns = gap_s * NS_PER_S
    for path in paths:
        segments.append(_segment_info(path, channels, gap_ns))
        done += segments[-1].bytes
        if progress is not None:
            progress(done, total)
    return SessionInfo(session_dir.name, segments, channels)


def _segment_info(path: Path, channels: dict[str, ChannelInfo], gap_ns: float) -> SegmentInfo:
    """Scan one segment: its summary, and its messages accounted in ``channels`` (topic →
    :class:`ChannelInfo`, shared by the segments of a session, new topics added)."""
    scan = SegmentScan(path, 0)
    topics: dict[int, ChannelInfo] = {}
    n, first, last, host_time = 0, None, None, 0
    recovery = end_reason = None
    for rec in scan_segment(path, scan):
        if isinstance(rec, Channel):
            topics[rec.id] = channels.setdefault(rec.topic, ChannelInfo(rec.topic, rec.message_encoding))
        elif isinstance(rec, Metadata):
            if rec.name == "mls.recovery":
                recovery = dict(rec.metadata)
            elif rec.name == "mls.segment_end":
                end_reason = rec.metadata.get("reason")
        elif isinstance(rec, Message):
            ci = topics.get(rec.channel_id)
            if ci is None:
                continue
            n += 1
            _account_sequence(ci, rec.sequence)
            if _unlocked(ci.encoding, rec.data):
                ci.unlocked += 1
            if _host_time(ci.encoding, rec.data):
                ci.host_time += 1  # not GPS time: out of the span and the gaps
                host_time += 1
                continue
            t = rec.log_time
            first = t if first is None else min(first, t)
            last = t if last is None else max(last, t)
            _account_time(ci, t, gap_ns)
    return SegmentInfo(
        name=path.name,
        state=_segment_state(scan),
        bytes=scan.size,
        messages=n,
        first_log_ns=first,
        last_log_ns=last,
        torn_bytes=scan.torn_bytes,
        problem=scan.problem,
        recovery=recovery,
        end_reason=end_reason,
        host_time=host_time,
    )


def _segment_state(scan: SegmentScan) -> str:
    """complete | closed-after-error | unfinished | unreadable (:class:`SegmentInfo`)."""
    if scan.footer:
        return "complete" if scan.indexed else "closed-after-error"
    if scan.problem and scan.good_bytes <= 8:
        return "unreadable"
    return "unfinished"


def _host_time(encoding: str, data: bytes) -> bool:
    """The writer's mark of a message stamped before any PPS fit (:mod:`acquire.log.schema`)."""
    from acquire.log.schema import FLAG_HOST_TIME, RAW_ENCODING

    if encoding == RAW_ENCODING:
        return len(data) > 1 and bool(data[1] & FLAG_HOST_TIME)
    return b'"time_base":"host"' in data


def _account_sequence(ci: ChannelInfo, seq: int) -> None:
    ci.messages += 1
    if ci.seq_last is None:
        ci.seq_first = seq
    else:
        delta = (seq - ci.seq_last) & 0xFFFFFFFF
        if delta == 0:
            ci.duplicates += 1
        elif delta >= 1 << 31:
            ci.backwards += 1
        elif delta > 1:
            ci.missing += delta - 1
            if len(ci.missing_ranges) < 20:
                ci.missing_ranges.append((ci.seq_last + 1, seq - 1))
    ci.seq_last = seq


def _account_time(ci: ChannelInfo, t: int, gap_ns: float) -> None:
    if ci.last_log_ns is not None and ci.topic != "/events":
        dt = t - ci.last_log_ns
        threshold = max(gap_ns, 5 * ci._period_ns) if ci._period_ns else None
        if threshold is not None and dt > threshold and len(ci.gaps) < 100:
            ci.gaps.append((ci.last_log_ns, dt / NS_PER_S))
        elif dt > 0:
            ci._period_ns = dt if ci._period_ns is None else 0.98 * ci._period_ns + 0.02 * dt
    ci.first_log_ns = t if ci.first_log_ns is None else min(ci.first_log_ns, t)
    ci.last_log_ns = t if ci.last_log_ns is None else max(ci.last_log_ns, t)
