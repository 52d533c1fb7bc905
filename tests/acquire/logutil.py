"""Helpers shared by the session-log tests (not a test module)."""

from __future__ import annotations

import time
from pathlib import Path

from acquire.log.recover import scan_segment, segment_paths
from acquire.log.schema import Envelope, decode


def read_session(session_dir: Path) -> list[Envelope]:
    """Every message of every segment, decoded, in file order (checks the MCAP sequence)."""
    out = []
    for path in segment_paths(session_dir):
        channels = {}
        for rec in scan_segment(path):
            kind = type(rec).__name__
            if kind == "Channel":
                channels[rec.id] = rec
            elif kind == "Message":
                ch = channels[rec.channel_id]
                env = decode(ch.topic, ch.message_encoding, rec.log_time, rec.publish_time, rec.data)
                assert env.seq & 0xFFFFFFFF == rec.sequence
                out.append(env)
    return out


def payload(seq: int, n: int) -> bytes:
    """Deterministic binary payload with every byte value (zeros, '$', newlines)."""
    return bytes((seq * 31 + k * 7) % 256 for k in range(n))


def wait_for(cond, timeout_s: float = 10.0, what: str = "condition", poll=None) -> None:
    """Poll ``cond`` (calling ``poll`` between tries) until true; fail after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if cond():
            return
        if poll is not None:
            poll()
        time.sleep(0.01)
    raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")
