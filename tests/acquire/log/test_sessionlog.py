"""Session logs: encodings, rotation, flush period, queue overflow, scan/salvage of torn files."""

from __future__ import annotations

import errno
import math
import os
import re
import shutil
import threading
from pathlib import Path

import pytest
from mcap.reader import make_reader
from mcap.stream_reader import StreamReader
from mcap.writer import MCAP0_MAGIC

from acquire.alarms import AlarmBook
from acquire.log.read import iter_messages
from acquire.log.recover import (
    SegmentScan,
    is_locked,
    recover_segment,
    salvage_root,
    salvage_session,
    scan_segment,
    segment_closed,
    segment_paths,
    session_info,
)
from acquire.log.schema import FormatError, channel_kind, decode
from acquire.log.segments import SegmentIO
from acquire.log.session import LogError, SessionOptions
from acquire.log.sessionlog import SessionWriter
from acquire.timing.clock import ClockState, GpsEstimate
from tests.acquire.logutil import (
    FakeMonotonic,
    payload,
    read_session,
    wait_flushed,
    wait_for,
    writer_caught_up,
)

NS = 1_000_000_000
GPS_OFFSET_NS = 1_400_000_000 * NS


class FixedClock:
    def __init__(self, state=ClockState.LOCKED):
        self.state = state

    def to_gps(self, host_ns):
        return GpsEstimate(host_ns + GPS_OFFSET_NS, self.state, 1000)


def test_round_trip_keeps_exact_bytes_times_sequence_and_clock_flags(tmp_path):
    clock = FixedClock()
    w = SessionWriter(
        tmp_path,
        "survey-1",
        SessionOptions(flush_s=0.2),
        clock=clock,
        channel_metadata={"/ins/raw": {"protocol": "nmea"}},
    )
    sd = w.start()
    assert re.fullmatch(r"\d{8}T\d{6}Z_survey-1", sd.name)
    host = 10 * NS
    for i in range(1, 51):
        w.submit("/ins/raw", payload(i, 100 + i), host_ns=host + i, device_ns=GPS_OFFSET_NS + i)
        w.submit("/lidar/raw", payload(i, 1400), host_ns=host + i)
        w.submit("/ins/nav", {"i": i, "roll_rad": math.nan, "v": [1, 2.5]}, host_ns=host + i)
    clock.state = ClockState.HOLDOVER
    w.submit("/can/events", b"\x00\x01\x02", host_ns=host + 100)
    w.submit(
        "/events",
        {"event": "mark", "text": "T1"},
        host_ns=host + 101,
        log_time_ns=123,
        clock_state="UNLOCKED",
    )
    w.close()
    msgs = read_session(sd)
    by_topic = {}
    for m in msgs:
        by_topic.setdefault(m.topic, []).append(m)
    assert {t: len(v) for t, v in by_topic.items()} == {
        "/ins/raw": 50,
        "/lidar/raw": 50,
        "/ins/nav": 50,
        "/can/events": 1,
        "/events": 1,
    }
    for i, m in enumerate(by_topic["/ins/raw"], start=1):
        assert m.payload == payload(i, 100 + i) and m.seq == i and m.host_ns == host + i
        assert m.device_ns == GPS_OFFSET_NS + i == m.publish_time_ns
        assert m.log_time_ns == host + i + GPS_OFFSET_NS and m.clock == "LOCKED"
    lidar = by_topic["/lidar/raw"][7]
    assert lidar.device_ns is None and lidar.publish_time_ns == lidar.log_time_ns
    nav = by_topic["/ins/nav"][0]
    assert nav.payload == {"i": 1, "roll_rad": None, "v": [1, 2.5]}  # NaN → null
    assert by_topic["/can/events"][0].clock == "HOLDOVER"
    ev = by_topic["/events"][0]
    assert ev.log_time_ns == 123 and ev.clock == "UNLOCKED" and ev.payload["text"] == "T1"
    # the standard MCAP reader agrees (indexed, readable by any MCAP tool)
    with open(segment_paths(sd)[0], "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary.statistics.message_count == 152
        topics = {c.topic: c for c in summary.channels.values()}
        assert topics["/ins/raw"].metadata["protocol"] == "nmea"
        assert topics["/ins/nav"].message_encoding == "json"
        assert summary.schemas[topics["/ins/nav"].schema_id].encoding == "jsonschema"
        assert len(list(reader.iter_messages())) == 152
    assert not is_locked(sd)


def test_rotation_by_size_and_time_keeps_sequences_contiguous(tmp_path):
    clock = FakeMonotonic()  # the writer's clock: time passes when the test says
    w = SessionWriter(
        tmp_path,
        "v",
        SessionOptions(rotate_bytes=60_000, rotate_s=0.4, flush_s=0.1, compression="none"),
        monotonic_ns=clock,
    )
    sd = w.start()
    for i in range(400):
        w.submit("/lidar/raw", payload(i, 500), host_ns=NS + i * 1_000_000)
        if i % 100 == 0:
            clock.advance(0.25)
            wait_flushed(w, i + 1)  # the writer saw the time pass (a flush is due)
    segments = w.stats().segments
    clock.advance(0.5)  # an idle stretch longer than rotate_s: rotation by time
    wait_for(lambda: w.stats().segments > segments, what="the rotation by time")
    w.submit("/status", {"state": "running"}, host_ns=2 * NS)
    w.close()
    info = session_info(sd)
    assert len(info.segments) >= 4
    assert all(s.state == "complete" for s in info.segments)
    reasons = [s.end_reason for s in info.segments]
    assert reasons[-1] == "shutdown" and set(reasons[:-1]) == {"rotation"}
    assert any(s.bytes > 60_000 for s in info.segments)  # some closed by size
    lidar = info.channels["/lidar/raw"]
    assert (lidar.messages, lidar.seq_first, lidar.seq_last) == (400, 1, 400)
    assert lidar.missing == lidar.duplicates == lidar.backwards == 0


def test_records_reach_the_file_within_the_flush_period(tmp_path):
    clock = FakeMonotonic()  # the writer's clock: the flush period passes when the test says
    w = SessionWriter(tmp_path, "v", SessionOptions(flush_s=0.3, fsync_s=5.0), monotonic_ns=clock)
    sd = w.start()
    w.submit("/ins/raw", b"$PIXSE,HEAVE_,0.0,0.0,0.0*2A\r\n", host_ns=5)
    seg = segment_paths(sd)[0]
    writer_caught_up(w, clock)  # a round of the writer since: the flush is not due, nothing in the file
    assert [r for r in scan_segment(seg, SegmentScan(seg, 0)) if type(r).__name__ == "Message"] == []
    clock.advance(0.3)  # the flush period
    wait_flushed(w, 1)
    assert not segment_closed(seg)  # still open ...
    scan = SegmentScan(seg, 0)
    msgs = [r for r in scan_segment(seg, scan) if type(r).__name__ == "Message"]
    assert len(msgs) == 1 and msgs[0].data.endswith(b"*2A\r\n")  # ... and the record is there
    assert scan.problem is None and not scan.footer
    ok, why = w.health()
    assert ok, why
    w.close()
    assert w.health() == (False, "log writer thread is not running")


def test_full_queue_drops_with_count_alarm_and_a_visible_sequence_gap(tmp_path):
    alarms = AlarmBook()
    w = SessionWriter(tmp_path, "v", SessionOptions(queue_size=10), alarms=alarms)
    accepted = [w.submit("/ins/raw", b"x", host_ns=i) for i in range(25)]  # thread not started
    assert accepted == [True] * 10 + [False] * 15
    assert w.stats().dropped == {"/ins/raw": 15}
    a = alarms.get("log_queue_overflow", "log")
    assert a.active and "15 records dropped" in a.message
    sd = w.start()
    w.submit("/ins/raw", b"y", host_ns=100)
    w.close()
    ch = session_info(sd).channels["/ins/raw"]
    assert (ch.messages, ch.missing, ch.missing_ranges) == (11, 15, [(11, 25)])


def test_a_batch_is_queued_in_order_up_to_the_room_left_and_a_bad_one_queues_nothing(tmp_path):
    alarms = AlarmBook()
    w = SessionWriter(tmp_path, "v", SessionOptions(queue_size=5), alarms=alarms)
    rec = [("/lidar/raw" if i % 2 else "/ins/raw", bytes([i]), i, None, 1000 + i, "LOCKED") for i in range(4)]
    with pytest.raises(TypeError, match="JSON channel"):  # checked before any is counted
        w.submit_batch(rec + [("/events", b"x", 9, None, 9, "LOCKED")])
    assert w.submit_batch(rec) == 4 and w.stats().queue_depth == 4
    assert w.submit_batch(rec[:3]) == 1  # room for one: two dropped, counted, alarm
    assert w.stats().dropped == {"/lidar/raw": 1, "/ins/raw": 1}
    assert alarms.get("log_queue_overflow", "log").active
    sd = w.start()
    w.close()
    msgs = list(iter_messages(sd, {"/ins/raw", "/lidar/raw"}))
    assert [(m.topic, m.payload, m.seq, m.log_time_ns) for m in msgs] == [
        ("/ins/raw", b"\x00", 1, 1000),
        ("/lidar/raw", b"\x01", 1, 1001),
        ("/ins/raw", b"\x02", 2, 1002),
        ("/lidar/raw", b"\x03", 2, 1003),
        ("/ins/raw", b"\x00", 3, 1000),
    ]  # then seq 3 and 4 dropped


def test_bad_topics_and_payloads_are_refused():
    w = SessionWriter("/nonexistent-not-started", "v")
    with pytest.raises(ValueError, match="/lidar/xyz"):
        w.submit("/lidar/xyz", b"", host_ns=0)
    with pytest.raises(TypeError, match="raw channel"):
        w.submit("/ins/raw", {"a": 1}, host_ns=0)
    with pytest.raises(TypeError, match="JSON channel"):
        w.submit("/status", b"x", host_ns=0)
    assert channel_kind("/can/aux") == "raw"
    with pytest.raises(ValueError, match="vessel name"):
        SessionWriter("/tmp", "bad/name")
    with pytest.raises(ValueError, match="flush_s"):
        SessionOptions(flush_s=2.0)
    with pytest.raises(FormatError, match="shorter than its header"):
        decode("/ins/raw", "mls.raw.v1", 0, 0, b"\x01")


def _segment_with_chunks(tmp_path) -> tuple[Path, list[int]]:
    """A complete segment of 5 chunks of 40 messages; returns it and each chunk's end offset."""
    clock = FakeMonotonic()  # frozen while a group is submitted: no flush in the middle of one
    w = SessionWriter(tmp_path, "v", SessionOptions(flush_s=0.05, compression="lz4"), monotonic_ns=clock)
    sd = w.start()
    for c in range(5):
        for i in range(40):
            seq = c * 40 + i + 1
            w.submit("/ins/raw", payload(seq, 64), host_ns=seq)
        clock.advance(0.05)
        wait_flushed(w, 40 * (c + 1))  # one flush (one chunk) per group
    w.close()
    seg = segment_paths(sd)[0]
    ends = []
    scan = SegmentScan(seg, 0)
    for rec in scan_segment(seg, scan):
        if type(rec).__name__ == "Message" and rec.sequence % 40 == 0:
            ends.append(scan.good_bytes)  # the chunk holding it ended here
    assert len(ends) == 5, ends
    return seg, ends


def test_salvage_of_a_file_torn_anywhere_keeps_exactly_the_complete_chunks(tmp_path):
    seg, chunk_ends = _segment_with_chunks(tmp_path / "src")
    size = seg.stat().st_size
    cuts = sorted(
        {
            9,
            50,
            *range(chunk_ends[0] - 3, chunk_ends[0] + 4),
            chunk_ends[2] + 1,
            (chunk_ends[3] + chunk_ends[4]) // 2,
            chunk_ends[4] + 5,
            size - 1,
        }
    )
    for cut in cuts:
        d = tmp_path / f"cut{cut}"
        d.mkdir()
        torn = d / "seg-000001.mcap"
        torn.write_bytes(seg.read_bytes()[:cut])
        assert not segment_closed(torn)
        report = salvage_session(d)[0]
        expected = 40 * sum(1 for e in chunk_ends if e <= cut)
        assert report.messages == expected, (cut, report)
        assert report.good_bytes + report.torn_bytes == cut
        assert report.torn_bytes < chunk_ends[0]  # never more than one record lost
        if cut not in chunk_ends and cut > 8:
            assert report.problem and "torn" in report.problem
        assert Path(report.original).read_bytes() == seg.read_bytes()[:cut]  # original kept
        info = session_info(d)
        assert info.segments[0].state == "complete"
        assert info.segments[0].recovery["torn_bytes"] == str(report.torn_bytes)
        ch = info.channels.get("/ins/raw")
        if expected:
            assert (ch.messages, ch.seq_first, ch.seq_last, ch.missing) == (expected, 1, expected, 0)
        msgs = read_session(d)
        assert [m.payload for m in msgs] == [payload(s, 64) for s in range(1, expected + 1)]
        assert salvage_session(d) == []  # nothing left to do


def test_salvage_stops_at_a_corrupt_chunk_and_reports_it(tmp_path):
    seg, chunk_ends = _segment_with_chunks(tmp_path / "src")
    data = bytearray(seg.read_bytes())
    data[chunk_ends[2] - 100] ^= 0xFF  # inside the third chunk's compressed data
    d = tmp_path / "bad"
    d.mkdir()
    (d / "seg-000001.mcap").write_bytes(bytes(data[: chunk_ends[4] + 10]))
    report = recover_segment(d / "seg-000001.mcap", keep_original=False)
    assert report.messages == 80
    assert "corrupt chunk record" in report.problem and report.original is None
    assert not (d / "seg-000001.mcap.torn").exists()


def test_an_interrupted_recovery_is_completed(tmp_path):
    seg, chunk_ends = _segment_with_chunks(tmp_path / "src")
    d = tmp_path / "s"
    d.mkdir()
    # crash between the two renames: only the .torn original and a stale .recovering exist
    (d / "seg-000001.mcap.torn").write_bytes(seg.read_bytes()[: chunk_ends[1] + 3])
    (d / "seg-000001.mcap.recovering").write_bytes(b"half")
    (report,) = salvage_session(d)
    assert report.messages == 80
    assert sorted(p.name for p in d.iterdir()) == ["seg-000001.mcap", "seg-000001.mcap.torn"]


def test_a_session_held_by_a_writer_is_not_salvaged(tmp_path):
    w = SessionWriter(tmp_path, "v")
    sd = w.start()
    assert is_locked(sd)
    with pytest.raises(LogError, match=f"running daemon \\(pid {os.getpid()}\\)"):
        salvage_session(sd)
    w.close()
    assert salvage_session(sd) == []
    shutil.rmtree(sd)


def test_salvage_root_recovers_idle_sessions_and_leaves_a_live_one_alone(tmp_path):
    seg, chunk_ends = _segment_with_chunks(tmp_path / "src")
    root = tmp_path / "root"
    crashed = root / "20250101T000000Z_v"
    crashed.mkdir(parents=True)
    (crashed / "seg-000001.mcap").write_bytes(seg.read_bytes()[: chunk_ends[2] + 7])
    (root / "not-a-session").mkdir()
    live = SessionWriter(root, "v")
    live_dir = live.start()
    try:
        reports = salvage_root(root)
        assert list(reports) == [crashed.name]
        assert reports[crashed.name][0].messages == 120
        assert not segment_closed(segment_paths(live_dir)[0])  # the live segment untouched
    finally:
        live.close()


def test_a_hung_fsync_makes_the_writer_unhealthy(tmp_path):
    release = threading.Event()

    class HangingFsync(SegmentIO):
        def fsync(self):
            if self.pos > 2000:  # (not the segment's creation)
                release.wait(10)
            super().fsync()

    w = SessionWriter(
        tmp_path,
        "v",
        SessionOptions(flush_s=0.05, fsync_s=0.1, stall_s=0.3, compression="none"),
        io_factory=HangingFsync,
    )
    w.start()
    try:
        w.submit("/ins/raw", payload(1, 3000), host_ns=1)
        wait_for(lambda: not w.health()[0], what="the writer to be unhealthy")
        ok, why = w.health()
        assert not ok and why.startswith("log writer stalled for")
    finally:
        release.set()
    wait_for(lambda: w.health() == (True, "log writer ok"), what="the writer to be healthy again")
    w.close()


class _OneFailure(SegmentIO):
    """ENOSPC once, at the first write (after arming) that ``where`` selects: half of it is written
    (a short write), then the error; every other write succeeds (the reserve file makes room)."""

    where = None  # callable(data, first_byte, previous_first_byte) -> bool; None: disarmed
    fired: list = []

    def __init__(self, path):
        super().__init__(path)
        self.prev = b""  # first byte of the previous write (the record it began with)

    def write(self, data):
        head, prev = bytes(data[:1]), self.prev
        self.prev = head
        if type(self).where is not None and type(self).where(bytes(data), head, prev):
            type(self).where = None
            type(self).fired.append((self.path.name, self.pos, head))
            self.pos += os.write(self.fd, memoryview(data)[: len(data) // 2])
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return super().write(data)


_OP = {"chunk": 0x06, "message_index": 0x07, "metadata": 0x0C, "data_end": 0x0F, "footer": 0x02}


@pytest.mark.parametrize(
    ("where", "lost_in_segment"),
    [
        ("chunk", True),  # the last chunk itself fails: its 80 records are lost (and only those)
        ("message_index", False),  # the chunk is in the file, its index write fails
        ("metadata", False),  # the chunk is flushed, then the segment-end metadata fails
        ("data_end", False),  # ... then finish(): Data End
        ("summary", False),  # ... the summary section
        ("footer", False),  # ... the footer
        ("magic", False),  # ... the closing magic
        ("index_of_a_full_chunk", False),  # a chunk filled up in add_message, its index write fails
    ],
)
def test_a_write_failure_counts_as_lost_exactly_the_records_the_segment_does_not_hold(
    tmp_path, where, lost_in_segment
):
    """ENOSPC injected on purpose at each write of a segment's end (on a frozen clock, so that
    nothing is flushed by time: the close's own flush writes the last chunk, then one write
    fails). ``records_lost`` (stats, alarm, /events) must equal the records a salvage cannot
    read, whichever write failed."""
    op = _OP.get("message_index" if where == "index_of_a_full_chunk" else where)
    _OneFailure.fired = []
    preds = {
        "summary": lambda d, h, prev: prev == b"\x0f",  # the write that follows Data End
        "magic": lambda d, h, prev: d == MCAP0_MAGIC,
    }
    now = FakeMonotonic(1_000 * NS)
    alarms = AlarmBook()
    chunk_bytes = 8_000 if where == "index_of_a_full_chunk" else 1024 * 1024
    w = SessionWriter(
        tmp_path,
        "v",
        SessionOptions(flush_s=1.0, fsync_s=1e6, retry_s=1.0, compression="none", chunk_bytes=chunk_bytes),
        alarms=alarms,
        io_factory=_OneFailure,
        monotonic_ns=now,
    )
    sd = w.start()
    _OneFailure.where = preds.get(where) or (lambda d, h, prev: h == bytes([op]))
    n = 40
    for i in range(1, n + 1):
        w.submit("/lidar/raw", payload(i, 500), host_ns=i)
        w.submit("/ins/nav", {"i": i}, host_ns=i)
    w.rotate()  # close seg-000001 (its flush writes the chunk), open seg-000002
    wait_for(lambda: alarms.is_active("disk_write_failed", "log"), what="the failure")
    assert _OneFailure.fired and _OneFailure.fired[0][0] == "seg-000001.mcap"
    wait_for(lambda: w.stats().queue_depth == 0 and w.stats().state == "failed", what="drained")
    writer_caught_up(w, now)  # the last records taken are handled (counted lost, if they are)
    at_failure = sum(w.stats().lost.values())
    for i in range(n + 1, n + 6):  # while paused: lost, counted
        w.submit("/lidar/raw", payload(i, 500), host_ns=i)
    wait_for(lambda: sum(w.stats().lost.values()) == at_failure + 5, what="the paused records")
    now.advance(2)  # the retry: a new segment
    wait_for(lambda: not alarms.is_active("disk_write_failed", "log"), what="writing to resume")
    for i in range(n + 6, n + 11):
        w.submit("/lidar/raw", payload(i, 500), host_ns=i)
    w.close()
    stats = w.stats()

    first = segment_paths(sd)[0]
    scan = SegmentScan(first, 0)
    held = [r for r in scan_segment(first, scan) if type(r).__name__ == "Message"]
    assert scan.footer and not scan.indexed and scan.problem is None, scan  # closed cleanly
    with open(first, "rb") as f:  # a valid MCAP for any reader
        assert len(list(make_reader(f).iter_messages())) == len(held)
    msgs = read_session(sd)
    seqs = {t: {m.seq for m in msgs if m.topic == t} for t in ("/lidar/raw", "/ins/nav")}
    missing = {
        "/lidar/raw": set(range(1, n + 11)) - seqs["/lidar/raw"],
        "/ins/nav": set(range(1, n + 1)) - seqs["/ins/nav"],
    }
    for topic in missing:
        assert len(missing[topic]) == stats.lost[topic], (where, topic, missing[topic], stats.lost)
    if where == "index_of_a_full_chunk":  # the chunk that filled up is whole in the file
        assert len(held) > 0 and held[-1].sequence == max(m.seq for m in msgs[: len(held)])
    elif lost_in_segment:
        assert missing == {"/lidar/raw": set(range(1, n + 6)), "/ins/nav": set(range(1, n + 1))}
    else:  # every record before the failure is in the file: only the paused ones are lost
        assert len(held) == 2 * n
        assert missing == {"/lidar/raw": set(range(n + 1, n + 6)), "/ins/nav": set()}
    (event,) = [m.payload for m in msgs if m.topic == "/events"]
    assert event["event"] == "log_write_failed" and event["segment"] == first.name
    assert event["records_lost"] == {t: c for t, c in stats.lost.items() if c}
    assert f"{sum(stats.lost.values())} records lost" in alarms.get("disk_write_failed", "log").message


def _write_synchronously(root: Path, records: list, batch: int, one_by_one: bool, monkeypatch) -> Path:
    """The writer's own code without its thread: start (no thread), write the records as the
    thread would, in batches of ``batch``, and close the segment."""
    from types import SimpleNamespace

    import acquire.log.sessionlog as sessionlog

    class NoThread:
        def __init__(self, **kw):
            pass

        def start(self):
            pass

    w = SessionWriter(
        root, "same", SessionOptions(chunk_bytes=20_000, rotate_bytes=150_000, compression="none")
    )
    with monkeypatch.context() as m:
        m.setattr(sessionlog, "threading", SimpleNamespace(Thread=NoThread))
        d = w.start()
    for a in range(0, len(records), batch):
        part = records[a : a + batch]
        if one_by_one:
            for r in part:
                w._write(r)
        else:
            w._write_all(part)
    w._close_segment(w._now(), "shutdown")
    os.close(w._lock_fd)
    return d


def _segments(d: Path) -> list:
    out = []
    for path in segment_paths(d):
        with open(path, "rb") as f:
            reader = make_reader(f)
            messages = [
                (c.topic, m.log_time, m.publish_time, m.sequence, m.data)
                for _, c, m in reader.iter_messages(log_time_order=False)
            ]
            s = reader.get_summary()
            chunks = [
                (c.message_start_time, c.message_end_time, c.uncompressed_size) for c in s.chunk_indexes
            ]
            out.append((messages, chunks, s.statistics.message_count))
        # every record but the segment's metadata (its opening time): chunks, message indexes,
        # statistics, summary offsets
        with open(path, "rb") as f:
            out.append(
                [r for r in StreamReader(f, emit_chunks=True).records if type(r).__name__ != "Metadata"]
            )
    return out


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_runs_of_raw_records_are_written_as_one_by_one(tmp_path, monkeypatch, seed):
    """The writer's run path (the profiler's datagrams) gives the segments, chunks, messages and
    counters of writing each record on its own: chunk ends and rotations fall mid-run."""
    import random

    rng = random.Random(seed)
    records, seqs = [], {}
    for k in range(3000):
        topic = rng.choice(["/lidar/raw"] * 12 + ["/ins/raw", "/ins/nav", "/can/events"])
        seq = seqs[topic] = seqs.get(topic, 0) + 1
        host = 10 * NS + k * 1000
        data = {"k": k} if topic == "/ins/nav" else payload(k, rng.randrange(0, 1400))
        records.append(
            (
                topic,
                seq,
                data,
                host,
                rng.choice([None, host + 5]),
                rng.choice([host + GPS_OFFSET_NS, 0, -3]),
                rng.choice(["LOCKED", "HOLDOVER", "UNLOCKED"]),
                host,
            )
        )
    batch = rng.randrange(50, 400)
    a = _write_synchronously(tmp_path / "a", records, batch, True, monkeypatch)
    b = _write_synchronously(tmp_path / "b", records, batch, False, monkeypatch)
    want, got = _segments(a), _segments(b)
    assert len(want) >= 6 and sum(len(c) for _, c, _ in want[::2]) > 20  # rotations and chunks to get right
    assert got == want
    assert sum(len(m) for m, _, _ in got[::2]) == len(records)
