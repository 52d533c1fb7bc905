"""The session log's fast mcap writer writes the very bytes of the library's ``Writer``."""

from __future__ import annotations

import io
import random

import pytest
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from acquire.log.mcapwriter import SegmentWriter


def _write(cls, records, chunk_size: int, compression, head: int = 0) -> bytes:
    """``head``: SegmentWriter gets each record's first ``head`` bytes as its ``head`` prefix."""
    out = io.BytesIO()
    w = cls(out, chunk_size=chunk_size, compression=compression)
    w.start("mls-test", "mls")
    sid = w.register_schema("env", "jsonschema", b"{}")
    channels = [
        w.register_channel("/lidar/raw", "mls-raw", 0, {"k": "v"}),
        w.register_channel("/ins/nav", "json", sid, {}),
    ]
    for ch, log_time, publish, seq, data in records:
        if head:
            w.add_message(channels[ch], log_time, data[head:], publish, seq, head=data[:head])
        else:
            w.add_message(channels[ch], log_time=log_time, data=data, publish_time=publish, sequence=seq)
    w.finish()
    return out.getvalue()


@pytest.mark.parametrize("compression", [CompressionType.ZSTD, CompressionType.NONE], ids=["zstd", "none"])
@pytest.mark.parametrize("chunk_size", [1, 4096, 1 << 20], ids=["chunk-per-message", "4k", "1M"])
@pytest.mark.parametrize("head", [0, 24], ids=["whole", "head+data"])
def test_segment_writer_writes_the_bytes_of_the_library_writer(chunk_size, compression, head):
    rng = random.Random(7)
    records, t = [], 10**18
    for seq in range(1, 3000):
        t += rng.randrange(-50_000, 1_000_000)  # log times not sorted: the time ranges must agree
        records.append(
            (
                rng.randrange(2),
                max(t, 0),
                t + rng.randrange(1000),
                seq,
                bytes(rng.randrange(256) for _ in range(rng.randrange(0, 300))),
            )
        )
    records.append((0, 0, 0, 0, b""))  # log time 0, empty payload
    ours = _write(SegmentWriter, records, chunk_size, compression, head)
    assert ours == _write(Writer, records, chunk_size, compression)
    got = [
        (m.channel_id, m.log_time, m.publish_time, m.sequence, m.data)
        for _, _, m in make_reader(io.BytesIO(ours)).iter_messages(log_time_order=False)
    ]
    assert [(r[1], r[2], r[3], r[4]) for r in records] == [g[1:] for g in got]
    summary = make_reader(io.BytesIO(ours)).get_summary()
    assert summary.statistics.message_count == len(records)
    assert summary.statistics.message_start_time == 0


def test_without_chunking_it_is_the_library_method():
    records = [(0, 5, 6, 1, b"abc"), (1, 4, 4, 2, b"{}")]
    out = io.BytesIO()
    w = SegmentWriter(out, use_chunking=False)
    w.start("mls-test", "mls")
    ch = w.register_channel("/x", "raw", 0)
    for _, log_time, publish, seq, data in records:
        w.add_message(ch, log_time, data[1:], publish, seq, head=data[:1])
    w.finish()
    got = [
        (m.log_time, m.sequence, m.data)
        for _, _, m in make_reader(io.BytesIO(out.getvalue())).iter_messages()
    ]
    assert got == [(4, 2, b"{}"), (5, 1, b"abc")]


@pytest.mark.parametrize("chunk_size", [700, 4096, 1 << 20], ids=["small", "4k", "1M"])
def test_runs_cut_at_the_chunk_room_are_the_bytes_of_the_library_writer(chunk_size):
    rng = random.Random(11)
    records, t = [], 10**18
    for seq in range(1, 2000):
        t += rng.randrange(-50_000, 1_000_000)
        records.append(
            (0, max(t, 0), t + 7, seq, bytes(rng.randrange(256) for _ in range(rng.randrange(0, 300))))
        )
    out = io.BytesIO()
    w = SegmentWriter(out, chunk_size=chunk_size, compression=CompressionType.NONE)
    w.start("mls-test", "mls")
    w.register_schema("env", "jsonschema", b"{}")
    ch = w.register_channel("/lidar/raw", "mls-raw", 0, {"k": "v"})
    w.register_channel("/ins/nav", "json", 1, {})
    i = 0
    while i < len(records):  # runs of random length, cut where the chunk completes
        room, j, size = w.chunk_room(), i, 0
        while j < min(len(records), i + rng.randrange(1, 40)):
            size += 31 + len(records[j][4])
            j += 1
            if size > room:
                break
        w.add_run(ch, [(lt, pub, seq, data[:3], data[3:]) for _, lt, pub, seq, data in records[i:j]])
        i = j
    w.finish()
    assert out.getvalue() == _write(Writer, records, chunk_size, CompressionType.NONE)
