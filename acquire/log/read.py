"""Reading a session's messages back (export, replay, tests): every segment in order, decoded.

:func:`iter_messages` walks the segments of a session with :func:`acquire.log.recover.
scan_segment` (so an unfinished segment yields every complete message before its torn tail)
and yields :class:`~acquire.log.schema.Envelope` records of the requested topics, in file
order. :func:`channel_metadata` gives each topic's channel metadata (``protocol`` of the raw
channels). :func:`session_summary` reads the ``session.json`` the daemon writes at start.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Iterator
from pathlib import Path

from acquire.log.recover import scan_segment, segment_paths
from acquire.log.schema import Envelope, decode


class SessionReadError(ValueError):
    """A session directory that cannot be read (the message names the file)."""


def _segments(session_dir: Path) -> list[Path]:
    session_dir = Path(session_dir)
    if not session_dir.is_dir():
        raise SessionReadError(f"{session_dir}: no such session directory")
    paths = segment_paths(session_dir)
    if not paths:
        raise SessionReadError(f"{session_dir}: no segments (seg-NNNNNN.mcap)")
    return paths


def iter_messages(session_dir: str | Path, topics: Iterable[str] | None = None,
                  progress=None) -> Iterator[Envelope]:  # fmt: skip
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
