"""Reading a few channels of a closed segment through its MCAP index (the fast path of
:func:`acquire.log.read.iter_messages` and of ``mls georef``'s chunks).

A segment that closed normally ends with a summary: its channels and, per chunk, the offset of
each channel's message index (MCAP spec: ChunkIndex, MessageIndex). :func:`indexed_messages`
reads only the chunks that hold a wanted channel within the time window, decompresses each
once, and cuts out exactly the indexed messages of the wanted channels — the other channels'
records (the profiler's datagrams, when the INS is wanted) are never parsed. The messages come
in file order, as a scan gives them. A segment without a summary (unfinished, torn, salvaged
without one) gives None: the caller scans it (:func:`acquire.log.recover.scan_segment`).
"""

from __future__ import annotations

import struct
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import NamedTuple

_RECORD_HEAD = struct.Struct("<BQ")  # opcode, length
_CHUNK_FIXED = struct.Struct("<QQQI")  # start, end, uncompressed size, uncompressed crc
_MESSAGE_FIXED = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time
_OP_CHUNK, _OP_MESSAGE_INDEX, _OP_MESSAGE = 0x06, 0x07, 0x05


class IndexedMessage(NamedTuple):
    topic: str
    encoding: str
    log_time: int
    publish_time: int
    data: bytes


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


def indexed_messages(
    path: str | Path, topics: Iterable[str], t0_ns: int | None = None, t1_ns: int | None = None
) -> Iterator[IndexedMessage] | None:
    """The messages of ``topics`` with log time in [t0, t1) in file order, through the segment's
    index; None when the segment has no summary (module docstring)."""
    from mcap.reader import make_reader

    f = open(path, "rb")
    try:
        summary = make_reader(f).get_summary()
    except Exception:  # noqa: BLE001 - no summary, torn footer: the caller scans
        summary = None
    if summary is None or not summary.chunk_indexes:
        f.close()
        return None
    wanted = {c.id: c for c in summary.channels.values() if c.topic in set(topics)}
    lo = -1 if t0_ns is None else t0_ns
    hi = 1 << 64 if t1_ns is None else t1_ns
    chunks = sorted(
        (
            ci
            for ci in summary.chunk_indexes
            if ci.message_end_time >= lo
            and ci.message_start_time < hi
            and wanted.keys() & ci.message_index_offsets.keys()
        ),
        key=lambda ci: ci.chunk_start_offset,
    )

    def generate() -> Iterator[IndexedMessage]:
        with f:
            for ci in chunks:
                entries: list[tuple[int, int]] = []  # (offset in the chunk, channel id)
                for cid in wanted.keys() & ci.message_index_offsets.keys():
                    body = _read_record(f, ci.message_index_offsets[cid], _OP_MESSAGE_INDEX)
                    n = struct.unpack_from("<I", body, 2)[0] // 16
                    pairs = struct.unpack_from(f"<{2 * n}Q", body, 6)
                    entries += [(pairs[2 * k + 1], cid) for k in range(n) if lo <= pairs[2 * k] < hi]
                if not entries:
                    continue
                body = _read_record(f, ci.chunk_start_offset, _OP_CHUNK)
                size = _CHUNK_FIXED.unpack_from(body, 0)[2]
                p = _CHUNK_FIXED.size
                (n_kind,) = struct.unpack_from("<I", body, p)
                kind = body[p + 4 : p + 4 + n_kind].decode()
                p += 4 + n_kind
                (n_records,) = struct.unpack_from("<Q", body, p)
                records = _decompress(kind, body[p + 8 : p + 8 + n_records], size)
                for offset, cid in sorted(entries):
                    op, length = _RECORD_HEAD.unpack_from(records, offset)
                    if op != _OP_MESSAGE:
                        raise ValueError(f"{path}: chunk at {ci.chunk_start_offset}: no message at {offset}")
                    _, _, log_time, publish_time = _MESSAGE_FIXED.unpack_from(records, offset + 9)
                    start = offset + 9 + _MESSAGE_FIXED.size
                    ch = wanted[cid]
                    yield IndexedMessage(
                        ch.topic,
                        ch.message_encoding,
                        log_time,
                        publish_time,
                        records[start : offset + 9 + length],
                    )

    return generate()
