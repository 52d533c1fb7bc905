"""Helpers shared by the session-log tests (not a test module)."""

from __future__ import annotations

from pathlib import Path

from acquire.log.recover import scan_segment, segment_paths
from acquire.log.schema import Envelope, decode
from tests.waiting import wait_until


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
    wait_until(cond, timeout_s, what, between=poll)


def wait_flushed(w, submitted: int, timeout_s: float = 10.0) -> None:
    """Wait until the writer ``w`` has taken the ``submitted`` records (all it was given so far)
    and written them in complete chunks: what a chunk boundary needs, without a sleep."""
    wait_for(
        lambda: w.stats().messages_written >= submitted and w._unflushed_since is None,
        timeout_s,
        f"{submitted} records written in complete chunks",
    )


class FakeMonotonic:
    """A monotonic clock (ns) for the writer's ``monotonic_ns``: it moves only when told."""

    def __init__(self, start_ns: int = 1_000 * 1_000_000_000):
        self.ns = start_ns

    def __call__(self) -> int:
        return self.ns

    def advance(self, seconds: float) -> int:
        self.ns += round(seconds * 1e9)
        return self.ns


def writer_caught_up(w, clock: FakeMonotonic, timeout_s: float = 10.0) -> None:
    """Wait until the writer thread of ``w`` (on ``clock``) has begun a round after this call:
    whatever it was doing then is done. The clock moves 1 ns, so that the round's heartbeat
    (``_heartbeat_ns``, the clock at the top of each round; a round is at most 0.1 s) tells."""
    clock.ns += 1
    t = clock.ns
    wait_for(lambda: w._heartbeat_ns >= t, timeout_s, "the writer thread to begin a new round")
