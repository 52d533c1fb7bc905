"""Reading a session's messages back (export, replay, tests): every segment in order, decoded.

:func:`iter_messages` walks the segments of a session with :func:`acquire.log.recover.
scan_segment` (so an unfinished segment yields every complete message before its torn tail)
and yields :class:`~acquire.log.schema.Envelope` records of the requested topics, in file
order. :func:`channel_metadata` gives each topic's channel metadata (``protocol`` of the raw
channels). :func:`session_summary` reads the ``session.json`` the daemon writes at start.
:func:`raw_channels` gives what a replay of the raw channels needs to know of a session.
:func:`session_losses` lists the segments that did not end normally (unfinished with a torn
tail, salvaged after a crash, a salvage interrupted) and the time span lost with each, so that
what reads a session (``mls export``) can say what it is missing.
"""

from __future__ import annotations

import json
import struct
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, replace
from pathlib import Path

from mcap.records import Channel, Message

from acquire.errors import AcquireError
from acquire.log.indexed import indexed_messages
from acquire.log.recover import SegmentScan, scan_segment, segment_closed, segment_paths
from acquire.log.schema import Envelope, decode


class SessionReadError(AcquireError, ValueError):
    """A session directory that cannot be read (the message names the file)."""


def _segments(session_dir: Path) -> list[Path]:
    session_dir = Path(session_dir)
    if not session_dir.is_dir():
        raise SessionReadError(f"{session_dir}: no such session directory")
    paths = segment_paths(session_dir)
    if not paths:
        raise SessionReadError(f"{session_dir}: no segments (seg-NNNNNN.mcap)")
    for p in paths:
        if not p.is_file():
            raise SessionReadError(f"{p}: is a directory, expected an MCAP segment file")
    return paths


def iter_messages(
    session_dir: str | Path, topics: Iterable[str] | None = None, progress=None
) -> Iterator[Envelope]:
    """Every message of ``topics`` (all when None), decoded, segment after segment, in file order:
    through a closed segment's index when topics are named (:mod:`acquire.log.indexed`), else
    by a scan that stops at a torn tail.

    ``progress(done_bytes, total_bytes)`` is called after each segment.
    """
    wanted = None if topics is None else set(topics)
    paths = _segments(Path(session_dir))
    total = sum(p.stat().st_size for p in paths)
    done = 0
    for path in paths:
        fast = None if wanted is None else indexed_messages(path, wanted)
        if fast is not None:  # closed normally: only the wanted channels' records are read
            for m in fast:
                yield decode(m.topic, m.encoding, m.log_time, m.publish_time, m.data)
            done += path.stat().st_size
            if progress is not None:
                progress(done, total)
            continue
        channels: dict[int, Channel] = {}
        for rec in scan_segment(path):
            if isinstance(rec, Channel):
                if wanted is None or rec.topic in wanted:
                    channels[rec.id] = rec
            elif isinstance(rec, Message):
                ch = channels.get(rec.channel_id)
                if ch is not None:
                    yield decode(ch.topic, ch.message_encoding, rec.log_time, rec.publish_time, rec.data)
        done += path.stat().st_size
        if progress is not None:
            progress(done, total)


def channel_metadata(session_dir: str | Path) -> dict[str, dict[str, str]]:
    """topic → channel metadata, over every segment (the first seen wins)."""
    out: dict[str, dict[str, str]] = {}
    for path in _segments(Path(session_dir)):
        for rec in scan_segment(path):  # the writer registers a channel at its first message,
            if isinstance(rec, Channel):  # anywhere in a segment: read it all
                out.setdefault(rec.topic, dict(rec.metadata))
    return out


def session_summary(session_dir: str | Path) -> dict:
    """The daemon's ``session.json`` (vessel, mount, devices); {} when absent."""
    p = Path(session_dir) / "session.json"
    try:
        doc = json.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        return {}
    except IsADirectoryError:
        raise SessionReadError(f"{p}: is a directory, expected a JSON file") from None
    except UnicodeDecodeError as e:
        raise SessionReadError(f"{p}: not UTF-8 text ({e.reason} at byte {e.start})") from None
    except json.JSONDecodeError as e:
        raise SessionReadError(f"{p}:{e.lineno}:{e.colno}: not valid JSON ({e.msg})") from None
    if not isinstance(doc, dict):
        raise SessionReadError(
            f"{p}: got a JSON {type(doc).__name__}, expected an object (vessel, mount, devices)"
        )
    return doc


def is_raw_topic(topic: str) -> bool:
    """The raw device channels a replay re-emits: ``/ins/raw``, ``/lidar/raw``, ``/pps`` and
    ``/can/<name>``."""
    return topic in ("/ins/raw", "/lidar/raw", "/pps") or topic.startswith("/can/")


@dataclass(frozen=True)
class RawChannels:
    """A session's raw channels as a replay sees them (:func:`raw_channels`)."""

    path: Path
    channels: dict[str, dict[str, str]]  # raw topic → channel metadata
    counts: dict[str, int]  # messages per topic (every topic of the session)
    first_host_ns: int  # receive stamps of the first and last raw message
    last_host_ns: int
    gps_fit: tuple[int, float] | None  # (GPS ns at first_host_ns, GPS ns per host ns)

    @property
    def name(self) -> str:
        return self.path.name


def raw_channels(session_dir: str | Path) -> RawChannels:
    """The raw channels of a recorded session, their message counts, the receive stamps of
    their first and last message, and the recorded clock model as a straight line host → GPS
    time (least squares over up to 100 000 messages logged with the clock LOCKED; None with
    fewer than 2). ``LogError`` when the session has no segments or no raw message."""
    import numpy as np

    from acquire.log.session import LogError

    session_dir = Path(session_dir)
    if not (session_dir.is_dir() and segment_paths(session_dir)):
        raise LogError(f"{session_dir}: no session segments (seg-NNNNNN.mcap) there")
    metadata = channel_metadata(session_dir)
    channels = {t: m for t, m in metadata.items() if is_raw_topic(t)}
    counts: dict[str, int] = {}
    first = last = None
    pairs_host: list[int] = []
    pairs_gps: list[int] = []
    for env in iter_messages(session_dir):
        counts[env.topic] = counts.get(env.topic, 0) + 1
        if not is_raw_topic(env.topic):
            continue
        first = env.host_ns if first is None else min(first, env.host_ns)
        last = env.host_ns if last is None else max(last, env.host_ns)
        if env.clock == "LOCKED" and len(pairs_host) < 100_000:
            pairs_host.append(env.host_ns)
            pairs_gps.append(env.log_time_ns)
    if first is None or last is None:  # (set together, by the first raw message)
        raise LogError(f"{session_dir}: no /ins/raw, /lidar/raw, /pps or /can/<name> message to replay")
    gps_fit = None
    if len(pairs_host) >= 2:
        h = np.asarray(pairs_host, np.int64)
        g = np.asarray(pairs_gps, np.int64)
        slope, intercept = np.polyfit((h - first) / 1e9, (g - g[0]) / 1e9, 1)
        gps_fit = (int(g[0]) + round(intercept * 1e9), float(slope))
    return RawChannels(
        path=session_dir,
        channels=channels,
        counts=counts,
        first_host_ns=first,
        last_host_ns=last,
        gps_fit=gps_fit,
    )


# -- what a session lost ------------------------------------------------------------------------

#: a torn chunk's header (opcode, length, message start and end time) is read back only when it
#: is plausible: its times within this long of the last complete message's, its end after it
_CHUNK_HEAD, _CHUNK_OPCODE, _PLAUSIBLE_NS = struct.Struct("<BQQQ"), 0x06, 600 * 1_000_000_000


@dataclass(frozen=True)
class SegmentLoss:
    """A segment that did not end normally, and what is known of the messages it lost."""

    segment: str  # seg-NNNNNN.mcap
    state: str  # "unfinished" (torn tail still there) | "recovered" | "recovery interrupted"
    torn_bytes: int
    problem: str | None  # why its scan stopped (a torn record …); None: only the footer missing
    last_ns: int | None  # log time of its last complete message (None: none)
    until_ns: int | None  # the next log time known (None: unknown), from until_source:
    until_source: str | None  # "next segment" (its first message) | "torn chunk" (its header)

    def describe(self) -> str:
        """One line: the segment, what happened to it, the time span lost."""
        state = {
            "unfinished": "is unfinished",
            "recovered": "was salvaged after a crash",
            "recovery interrupted": f"is missing: only {self.segment}.torn is there (a salvage was "
            "interrupted; run `mls logs recover` on the session)",
        }[self.state]
        how = ", ".join(
            x for x in (f"{self.torn_bytes} torn bytes" if self.torn_bytes else "", self.problem or "") if x
        )
        if self.state == "unfinished" and (self.problem or "").startswith("not an MCAP file"):
            # bytes of something else, not a segment the writer cut short
            state, how = (
                "is not an MCAP file",
                f"its {self.torn_bytes} bytes do not start with the MCAP magic",
            )
        head = f"{self.segment} {state}" + (f" ({how})" if how else "")
        if self.last_ns is None:
            span = "none of its messages is in the export"
        elif self.until_ns is None:
            span = f"messages after {_utc(self.last_ns)} are lost (how long the recording went on is unknown)"
        elif self.until_source == "next segment":
            span = (
                f"no message between {_utc(self.last_ns)} and {_utc(self.until_ns)} "
                f"({(self.until_ns - self.last_ns) / 1e9:.3f} s lost)"
            )
        else:
            span = (
                f"messages after {_utc(self.last_ns)} are lost, at least up to {_utc(self.until_ns)} "
                f"({(self.until_ns - self.last_ns) / 1e9:.3f} s: the torn chunk)"
            )
        return f"{head}: {span}"


def _utc(gps_ns: int) -> str:
    from calib.core.frames import gps_ns_to_utc

    return gps_ns_to_utc(gps_ns).strftime("%Y-%m-%d %H:%M:%S.%f")[:-3] + " UTC"


def session_losses(session_dir: str | Path) -> list[SegmentLoss]:
    """The segments of a session that did not end normally, in order (:class:`SegmentLoss`):
    unfinished ones (no footer: a crash, a power cut, a failed fsync), salvaged ones (their
    ``mls.recovery`` record) and ones whose salvage was interrupted (only the ``.torn`` original
    left). Reads closed segments' summaries only; scans an unfinished segment whole."""
    session_dir = Path(session_dir)
    paths = _segments(session_dir)
    found: list[tuple[int, SegmentLoss]] = []
    for i, path in enumerate(paths):
        loss = _recovered(path) if segment_closed(path) else _unfinished(path)
        if loss is not None:
            found.append((i, loss))
    out = []
    for i, loss in found:
        nxt = next((t for p in paths[i + 1 :] if (t := _first_log_ns(p)) is not None), None)
        if nxt is not None and loss.last_ns is not None:
            loss = replace(loss, until_ns=nxt, until_source="next segment")
        out.append(loss)
    for torn in sorted(session_dir.glob("seg-*.mcap.torn")):
        name = torn.name[: -len(".torn")]
        if not (session_dir / name).exists():
            out.append(SegmentLoss(name, "recovery interrupted", 0, None, None, None, None))
    return sorted(out, key=lambda loss: loss.segment)


def _unfinished(path: Path) -> SegmentLoss:
    scan = SegmentScan(path, 0)
    last = None
    for rec in scan_segment(path, scan):
        if isinstance(rec, Message):
            last = rec.log_time if last is None else max(last, rec.log_time)
    until = _torn_chunk_end(path, scan.good_bytes, last) if scan.torn_bytes else None
    return SegmentLoss(
        path.name,
        "unfinished",
        scan.torn_bytes,
        scan.problem,
        last,
        until,
        None if until is None else "torn chunk",
    )


def _recovered(path: Path) -> SegmentLoss | None:
    """The loss of a closed segment that :func:`~acquire.log.recover.recover_segment` wrote (its
    ``mls.recovery`` record), from the summary; None for a segment closed normally."""
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        if summary is None or not any(m.name == "mls.recovery" for m in summary.metadata_indexes):
            return None
        rec = next(m for m in reader.iter_metadata() if m.name == "mls.recovery").metadata
        stats = summary.statistics
    last = stats.message_end_time if stats is not None and stats.message_count else None
    good, torn = int(rec.get("good_bytes", 0)), int(rec.get("torn_bytes", 0))
    original = path.with_name(path.name + ".torn")
    until = _torn_chunk_end(original, good, last) if torn and original.is_file() else None
    problem = rec.get("problem")
    return SegmentLoss(
        path.name,
        "recovered",
        torn,
        None if problem == "no footer" else problem,
        last,
        until,
        None if until is None else "torn chunk",
    )


def _torn_chunk_end(path: Path, offset: int, last_ns: int | None) -> int | None:
    """The end time a torn chunk at ``offset`` announces in its header, when it is there and
    plausible (its times within :data:`_PLAUSIBLE_NS` of ``last_ns``, its end after it); else
    None: random bytes where a header should be are not read as times."""
    if last_ns is None:
        return None
    with open(path, "rb") as f:
        f.seek(offset)
        head = f.read(_CHUNK_HEAD.size)
    if len(head) < _CHUNK_HEAD.size:
        return None
    opcode, _length, start, end = _CHUNK_HEAD.unpack(head)
    if opcode != _CHUNK_OPCODE or not (start <= end and last_ns < end <= last_ns + _PLAUSIBLE_NS):
        return None
    return end if abs(start - last_ns) <= _PLAUSIBLE_NS else None


def _first_log_ns(path: Path) -> int | None:
    """Log time of a segment's first message (reads its first chunk only)."""
    for rec in scan_segment(path):
        if isinstance(rec, Message):
            return rec.log_time
    return None
