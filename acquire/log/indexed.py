"""Reading a few channels of a closed segment through its MCAP index (the fast path of
:func:`acquire.log.read.iter_messages` and of ``mls georef``'s chunks).

A segment that closed normally ends with a summary: its channels and, per chunk, the offset of
each channel's message index (MCAP spec: ChunkIndex, MessageIndex). :func:`indexed_blocks`
reads only the chunks that hold a wanted channel within the time window, decompresses each
once, and locates exactly the indexed messages of the wanted channels in it — the other
channels' records (the profiler's datagrams, when the INS is wanted) are never parsed — with a
few numpy operations per chunk, not a parse per message (a chunk of profiler datagrams holds
thousands). :func:`indexed_messages` gives the same messages one by one. The messages come in
file order, as a scan gives them. A segment without a summary (unfinished, torn, salvaged
without one) gives None: the caller scans it (:func:`acquire.log.recover.scan_segment`).
"""

from __future__ import annotations

import functools
import os
import struct
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import NamedTuple

import numpy as np

_RECORD_HEAD = struct.Struct("<BQ")  # opcode, length
_CHUNK_FIXED = struct.Struct("<QQQI")  # start, end, uncompressed size, uncompressed crc
_MESSAGE_FIXED = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time
_OP_CHUNK, _OP_MESSAGE_INDEX, _OP_MESSAGE = 0x06, 0x07, 0x05
#: where a message's fields are, from the start of its record (opcode u8, length u64, then
#: channel id u16, sequence u32, log time u64, publish time u64, data)
_AT_LENGTH, _AT_LOG_TIME, _AT_PUBLISH_TIME = 1, 15, 23
_AT_DATA = _RECORD_HEAD.size + _MESSAGE_FIXED.size


class IndexedMessage(NamedTuple):
    topic: str
    encoding: str
    log_time: int
    publish_time: int
    data: bytes


class MessageBlock(NamedTuple):
    """The wanted messages of one MCAP chunk: ``records`` is the decompressed chunk, message k's
    data is ``records[data_start[k]:data_end[k]]`` (int64 arrays; file order)."""

    records: bytes
    channel_id: np.ndarray
    log_time: np.ndarray
    publish_time: np.ndarray
    data_start: np.ndarray
    data_end: np.ndarray


def segment_summary(path: str | Path):
    """The MCAP summary of a segment (``mcap.records`` Summary), None when it has none (not
    closed normally, a torn footer): parsed once per process while the file keeps its size and
    modification time (a job reads one segment's summary for each of its time chunks)."""
    st = os.stat(path)
    return _summary(os.path.abspath(path), st.st_size, st.st_mtime_ns)


@functools.lru_cache(maxsize=64)
def _summary(path: str, size: int, mtime_ns: int):
    """The summary of ``path`` as it is at (``size``, ``mtime_ns``): the cache's key."""
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        try:
            return make_reader(f).get_summary()
        except Exception:  # noqa: BLE001 - no summary, torn footer: None
            return None


def _decompress(kind: str, data: bytes, size: int) -> bytes:
    if kind == "":
        return data
    if kind == "zstd":
        import zstandard

        return zstandard.ZstdDecompressor().decompress(data, max_output_size=size)
    if kind == "lz4":
        import lz4.frame

        return lz4.frame.decompress(data)
    raise ValueError(f"MCAP chunk compression {kind!r} is not supported")


def _read_record(f, offset: int, opcode: int) -> bytes:
    f.seek(offset)
    head = f.read(_RECORD_HEAD.size)
    op, length = _RECORD_HEAD.unpack(head)
    if op != opcode:
        raise ValueError(f"MCAP record at {offset}: opcode {op:#x}, expected {opcode:#x}")
    return f.read(length)


def _uint_at(buf: np.ndarray, at: np.ndarray, dtype: str) -> np.ndarray:
    """The little-endian integers of ``dtype`` that start at the byte positions ``at`` of ``buf``
    (uint8), as int64."""
    width = np.dtype(dtype).itemsize
    return buf[at[:, None] + np.arange(width)].view(dtype).reshape(-1).astype(np.int64)


def _chunk_entries(f, ci, wanted: Iterable[int], lo: int, hi: int) -> tuple[np.ndarray, np.ndarray]:
    """(record offsets in the chunk, channel ids) of the wanted channels' messages of chunk
    ``ci`` with log time in [lo, hi), sorted by offset (file order)."""
    offsets: list[np.ndarray] = []
    channels: list[np.ndarray] = []
    for cid in sorted(set(wanted) & ci.message_index_offsets.keys()):
        body = _read_record(f, ci.message_index_offsets[cid], _OP_MESSAGE_INDEX)
        n = struct.unpack_from("<I", body, 2)[0] // 16
        pairs = np.frombuffer(body, "<u8", 2 * n, 6).reshape(n, 2)  # (log time, offset)
        t = pairs[:, 0]
        inside = np.ones(n, bool)
        if lo > 0:
            inside &= t >= lo
        if hi < 1 << 64:
            inside &= t < hi
        offsets.append(pairs[inside, 1].astype(np.int64))
        channels.append(np.full(int(inside.sum()), cid, np.int64))
    if not offsets:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    off, ch = np.concatenate(offsets), np.concatenate(channels)
    order = np.argsort(off, kind="stable")
    return off[order], ch[order]


def _chunk_records(f, ci) -> bytes:
    """The decompressed records of the chunk ``ci``."""
    body = _read_record(f, ci.chunk_start_offset, _OP_CHUNK)
    size = _CHUNK_FIXED.unpack_from(body, 0)[2]
    p = _CHUNK_FIXED.size
    (n_kind,) = struct.unpack_from("<I", body, p)
    kind = body[p + 4 : p + 4 + n_kind].decode()
    p += 4 + n_kind
    (n_records,) = struct.unpack_from("<Q", body, p)
    return _decompress(kind, body[p + 8 : p + 8 + n_records], size)


def _block(path, ci, records: bytes, offsets: np.ndarray, channel_id: np.ndarray) -> MessageBlock:
    """The messages at ``offsets`` of the decompressed chunk ``records``, checked to be messages."""
    buf = np.frombuffer(records, np.uint8)
    outside = offsets + _AT_DATA > buf.size
    if outside.any():
        raise ValueError(
            f"{path}: chunk at {ci.chunk_start_offset}: no message at {int(offsets[outside][0])}"
        )
    bad = buf[offsets] != _OP_MESSAGE
    if bad.any():
        raise ValueError(f"{path}: chunk at {ci.chunk_start_offset}: no message at {int(offsets[bad][0])}")
    return MessageBlock(
        records,
        channel_id,
        _uint_at(buf, offsets + _AT_LOG_TIME, "<u8"),
        _uint_at(buf, offsets + _AT_PUBLISH_TIME, "<u8"),
        offsets + _AT_DATA,
        offsets + _RECORD_HEAD.size + _uint_at(buf, offsets + _AT_LENGTH, "<u8"),
    )


def _channels(summary, topics: Iterable[str]) -> dict[int, tuple[str, str]]:
    topic_set = set(topics)
    return {c.id: (c.topic, c.message_encoding) for c in summary.channels.values() if c.topic in topic_set}


def _chunks_with(summary, wanted: dict[int, tuple[str, str]], lo: int, hi: int) -> list:
    """The chunk indexes of the chunks holding messages of ``wanted`` channels with log time in
    [lo, hi), in file order."""
    return sorted(
        (
            ci
            for ci in summary.chunk_indexes
            if ci.message_end_time >= lo
            and ci.message_start_time < hi
            and wanted.keys() & ci.message_index_offsets.keys()
        ),
        key=lambda ci: ci.chunk_start_offset,
    )


def topic_chunks(path: str | Path, topics: Iterable[str]) -> int | None:
    """How many MCAP chunks of the segment hold messages of ``topics``; None when the segment has
    no summary."""
    summary = segment_summary(path)
    if summary is None or not summary.chunk_indexes:
        return None
    return len(_chunks_with(summary, _channels(summary, topics), -1, 1 << 64))


def indexed_blocks(
    path: str | Path,
    topics: Iterable[str],
    t0_ns: int | None = None,
    t1_ns: int | None = None,
    chunks_of: slice | None = None,
) -> tuple[dict[int, tuple[str, str]], Iterator[MessageBlock]] | None:
    """(channel id → (topic, message encoding), the blocks of messages of ``topics`` with log
    time in [t0, t1), one per MCAP chunk, in file order) through the segment's index; None when
    the segment has no summary (module docstring). ``chunks_of``: only those of the MCAP chunks
    holding such messages (in file order), e.g. ``slice(0, 10)`` the first ten — for readers that
    share a segment's chunks out (:func:`topic_chunks` counts them)."""
    f = open(path, "rb")
    try:
        summary = segment_summary(path)
    except BaseException:
        f.close()
        raise
    if summary is None or not summary.chunk_indexes:
        f.close()
        return None
    wanted = _channels(summary, topics)
    lo = -1 if t0_ns is None else t0_ns
    hi = 1 << 64 if t1_ns is None else t1_ns
    chunks = _chunks_with(summary, wanted, lo, hi)
    if chunks_of is not None:
        chunks = chunks[chunks_of]

    def generate() -> Iterator[MessageBlock]:
        with f:
            for ci in chunks:
                offsets, channel_id = _chunk_entries(f, ci, wanted.keys(), lo, hi)
                if offsets.size:
                    yield _block(path, ci, _chunk_records(f, ci), offsets, channel_id)

    return wanted, generate()


def indexed_messages(
    path: str | Path, topics: Iterable[str], t0_ns: int | None = None, t1_ns: int | None = None
) -> Iterator[IndexedMessage] | None:
    """The messages of ``topics`` with log time in [t0, t1) in file order, through the segment's
    index (:func:`indexed_blocks`, one message at a time); None when the segment has no summary."""
    found = indexed_blocks(path, topics, t0_ns, t1_ns)
    if found is None:
        return None
    channels, blocks = found

    def generate() -> Iterator[IndexedMessage]:
        for b in blocks:
            rows = zip(
                b.channel_id.tolist(),
                b.log_time.tolist(),
                b.publish_time.tolist(),
                b.data_start.tolist(),
                b.data_end.tolist(),
                strict=True,
            )
            for cid, log_time, publish_time, start, end in rows:
                topic, encoding = channels[cid]
                yield IndexedMessage(topic, encoding, log_time, publish_time, b.records[start:end])

    return generate()
