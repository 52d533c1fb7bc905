"""Reading a session's messages back (export, replay, tests): every segment in order, decoded.

:func:`iter_messages` walks the segments of a session with :func:`acquire.log.recover.
scan_segment` (so an unfinished segment yields every complete message before its torn tail)
and yields :class:`~acquire.log.schema.Envelope` records of the requested topics, in file
order. :func:`channel_metadata` gives each topic's channel metadata (``protocol`` of the raw
channels). :func:`session_summary` reads the ``session.json`` the daemon writes at start.
:func:`raw_channels` gives what a replay of the raw channels needs to know of a session.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

from acquire.errors import AcquireError
from acquire.log.recover import scan_segment, segment_paths
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
    return paths


def iter_messages(
    session_dir: str | Path, topics: Iterable[str] | None = None, progress=None
) -> Iterator[Envelope]:
    """Every message of ``topics`` (all when None), decoded, segment after segment.

    ``progress(done_bytes, total_bytes)`` is called after each segment.
    """
    wanted = None if topics is None else set(topics)
    paths = _segments(Path(session_dir))
    total = sum(p.stat().st_size for p in paths)
    done = 0
    for path in paths:
        channels = {}
        for rec in scan_segment(path):
            kind = type(rec).__name__
            if kind == "Channel":
                if wanted is None or rec.topic in wanted:
                    channels[rec.id] = rec
            elif kind == "Message":
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
            if type(rec).__name__ == "Channel":  # anywhere in a segment: read it all
                out.setdefault(rec.topic, dict(rec.metadata))
    return out


def session_summary(session_dir: str | Path) -> dict:
    """The daemon's ``session.json`` (vessel, mount, devices); {} when absent."""
    p = Path(session_dir) / "session.json"
    try:
        return json.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        return {}
    except json.JSONDecodeError as e:
        raise SessionReadError(f"{p}:{e.lineno}:{e.colno}: not valid JSON ({e.msg})") from None


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
    pairs_host, pairs_gps = [], []
    for env in iter_messages(session_dir):
        counts[env.topic] = counts.get(env.topic, 0) + 1
        if not is_raw_topic(env.topic):
            continue
        first = env.host_ns if first is None else min(first, env.host_ns)
        last = env.host_ns if last is None else max(last, env.host_ns)
        if env.clock == "LOCKED" and len(pairs_host) < 100_000:
            pairs_host.append(env.host_ns)
            pairs_gps.append(env.log_time_ns)
    if first is None:
        raise LogError(f"{session_dir}: no /ins/raw, /lidar/raw, /pps or /can/<name> message to replay")
    gps_fit = None
    if len(pairs_host) >= 2:
        h = np.asarray(pairs_host, np.int64)
        g = np.asarray(pairs_gps, np.int64)
        slope, intercept = np.polyfit((h - first) / 1e9, (g - g[0]) / 1e9, 1)
        gps_fit = (int(g[0]) + round(intercept * 1e9), float(slope))
    return RawChannels(session_dir, channels, counts, first, last, gps_fit)
