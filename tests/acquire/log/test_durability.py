"""Durability of the session logs: kill -9 at random times, a full disk, a failed fsync."""

from __future__ import annotations

import errno
import os
import random
import select
import signal
import struct
import subprocess
import sys
import time
import warnings
from collections import defaultdict
from pathlib import Path

import pytest

from acquire.alarms import AlarmBook
from acquire.log.recover import salvage_session, segment_paths, session_info, unfinished_segments
from acquire.log.segments import SegmentIO
from acquire.log.session import SessionOptions
from acquire.log.sessionlog import SessionWriter
from tests.acquire.logutil import payload, read_session, wait_for

NS = 1_000_000_000
WRITER = Path(__file__).parents[1] / "writer_proc.py"

pytestmark = pytest.mark.integration


def _start_writer(root: Path, ledger: Path, flush_s: float, rotate_bytes: int):
    proc = subprocess.Popen(
        [sys.executable, str(WRITER), str(root), str(ledger), str(flush_s), str(rotate_bytes)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    ready, _, _ = select.select([proc.stdout], [], [], 30.0)
    line = proc.stdout.readline() if ready else ""
    if not line.startswith("READY "):
        proc.kill()
        _, err = proc.communicate()
        raise AssertionError(f"writer process did not start: {line!r} {err}")
    return proc, Path(line.split(maxsplit=1)[1].strip())


def test_kill_9_at_random_times_keeps_every_record_older_than_the_flush_period(tmp_path):
    flush_s = 0.5
    rng = random.Random(1234)
    torn_total = 0
    for trial in range(5):
        root = tmp_path / f"trial{trial}"
        ledger = tmp_path / f"ledger{trial}.txt"
        proc, session = _start_writer(root, ledger, flush_s, rotate_bytes=400_000)
        wait_for(lambda ledger=ledger: ledger.exists() and ledger.stat().st_size > 0, what="first records")
        select.select([], [], [], rng.uniform(0.6, 2.4))
        kill_ns = time.monotonic_ns()
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(10)
        proc.stdout.close()  # type: ignore[union-attr]
        proc.stderr.close()  # type: ignore[union-attr]
        assert proc.returncode == -signal.SIGKILL

        segs_before = segment_paths(session)
        # the segment being written is unfinished; the rotated ones were closed (a kill between
        # a rotation's close and the next open leaves none unfinished)
        unfinished = [p.name for p in unfinished_segments(session)]
        assert unfinished in ([segs_before[-1].name], []), (trial, unfinished)
        torn = b""
        if trial % 2:  # what a power cut adds: the start of a chunk whose pages did not all land
            torn = struct.pack("<BQ", 0x06, 50_000) + bytes(rng.randrange(256) for _ in range(1234))
            with open(segs_before[-1], "ab") as f:
                f.write(torn)
        reports = salvage_session(session)
        expected = [segs_before[-1].name] if unfinished or torn else []
        assert [r.segment for r in reports] == expected, (trial, unfinished, reports)
        for r in reports:
            assert r.good_bytes + r.torn_bytes == os.path.getsize(r.original)
            if torn:  # reported whether it follows a torn chunk or (rarely) a complete footer
                assert r.torn_bytes == len(torn) and r.problem.startswith("torn "), r
            torn_total += r.torn_bytes

        msgs = read_session(session)
        present = defaultdict(list)
        for m in msgs:
            present[m.topic].append(m.seq)
            if m.topic == "/lidar/raw":
                assert m.payload == payload(m.seq, 1400)
            elif m.topic == "/ins/raw":
                assert m.payload == payload(m.seq, 80 + m.seq % 50)
            else:
                assert m.payload["seq"] == m.seq
        for topic, seqs in present.items():  # exactly once, contiguous, in order
            assert seqs == list(range(1, len(seqs) + 1)), (trial, topic)
        emitted = [ln.split() for ln in ledger.read_text().splitlines()]
        due = [
            (t, int(s))
            for t, s, ts in (e for e in emitted if len(e) == 3)
            if int(ts) < kill_ns - int(flush_s * NS)
        ]
        assert len(due) > 100, (trial, len(due))
        missing = [(t, s) for t, s in due if s > len(present[t])]
        assert missing == [], (trial, missing[:5])
        info = session_info(session)
        assert all(s.state == "complete" for s in info.segments)
        assert all(c.missing == c.duplicates == c.backwards == 0 for c in info.channels.values())
    print(f"5 kill -9 trials: torn tail bytes reported in total: {torn_total}")


class _InjectedDisk:
    """Fallback when tmpfs cannot be mounted: ENOSPC from the segment file wrapper."""

    kind = "injected ENOSPC (tmpfs mount not permitted)"

    def __init__(self, root: Path):
        self.root = root
        self.budget: int | None = None  # bytes the "disk" still accepts; None: unlimited
        disk = self

        class FullIO(SegmentIO):
            def write(self, data):
                if disk.budget is not None:
                    if len(data) > disk.budget:
                        n = os.write(self.fd, memoryview(data)[: disk.budget])  # a short write
                        self.pos += n
                        disk.budget = 0
                        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
                    disk.budget -= len(data)
                return super().write(data)

            def truncate(self, size):
                # the writer releases its reserve file, then cuts the torn tail: both free space
                if disk.budget is not None:
                    disk.budget += self.pos - size + SessionOptions().reserve_bytes
                super().truncate(size)

        self.io_factory = FullIO

    def fill(self, leave_bytes: int) -> None:
        self.budget = leave_bytes

    def free(self) -> None:
        self.budget = None


class _TmpfsDisk:
    kind = "tmpfs"

    def __init__(self, root: Path):
        self.root = root
        self.io_factory = SegmentIO
        self.filler = root / "filler"

    def fill(self, leave_bytes: int) -> None:
        st = os.statvfs(self.root)
        size = st.f_bavail * st.f_frsize - leave_bytes
        fd = os.open(self.filler, os.O_WRONLY | os.O_CREAT, 0o600)
        try:
            os.posix_fallocate(fd, 0, size)
        finally:
            os.close(fd)

    def free(self) -> None:
        self.filler.unlink()


@pytest.fixture
def small_disk(tmp_path):
    mnt = tmp_path / "fs"
    mnt.mkdir()
    r = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=3m,mode=0755", "tmpfs", str(mnt)], capture_output=True, text=True
    )
    if r.returncode != 0:
        warnings.warn(f"tmpfs mount failed ({r.stderr.strip()}); disk full is injected instead", stacklevel=2)
        yield _InjectedDisk(mnt)
        return
    try:
        yield _TmpfsDisk(mnt)
    finally:
        subprocess.run(["umount", "-l", str(mnt)], check=False)


def test_disk_full_closes_the_segment_cleanly_raises_an_alarm_and_resumes(small_disk, capsys):
    alarms = AlarmBook()
    opts = SessionOptions(
        flush_s=0.1,
        fsync_s=0.2,
        retry_s=0.2,
        rotate_bytes=250_000,
        compression="none",
        min_free_bytes=600_000,
    )
    w = SessionWriter(small_disk.root, "v", opts, alarms=alarms, io_factory=small_disk.io_factory)
    session = w.start()
    seq = 0

    def produce(n=1):
        nonlocal seq
        for _ in range(n):
            seq += 1
            w.submit("/lidar/raw", payload(seq, 2000), host_ns=seq)

    produce(300)  # ~600 kB: two rotations
    wait_for(lambda: w.stats().segments >= 3, what="two rotations")
    small_disk.fill(leave_bytes=150_000)
    wait_for(
        lambda: alarms.is_active("disk_write_failed", "log"),
        20.0,
        "the disk-full alarm",
        poll=lambda: produce(20),
    )
    failed = w.stats()
    assert failed.state == "failed" and "ENOSPC" in failed.last_error
    alarm = alarms.get("disk_write_failed", "log")
    assert alarm.severity == "critical" and "closed cleanly" in alarm.message
    failed_segment = failed.last_error.split(":")[0]
    produce(50)  # dropped and counted while paused: submit never blocks
    wait_for(lambda: w.stats().queue_depth == 0, what="the paused writer to drain")
    assert w.health()[0] and "paused" in w.health()[1]
    small_disk.free()
    wait_for(
        lambda: not alarms.is_active("disk_write_failed", "log"),
        20.0,
        "writing to resume",
        poll=lambda: produce(5),
    )
    produce(100)
    w.close()
    stats = w.stats()
    assert "resumed in seg-" in alarms.get("disk_write_failed", "log").message

    info = session_info(session)
    states = {s.name: s.state for s in info.segments}
    assert states.pop(failed_segment) == "closed-after-error"  # a valid MCAP without index
    assert set(states.values()) == {"complete"}  # earlier segments intact, later ones complete
    names = [s.name for s in info.segments]
    assert names.index(failed_segment) >= 2 and names.index(failed_segment) < len(names) - 1
    msgs = read_session(session)  # every segment reads, every message decodes
    lidar = [m for m in msgs if m.topic == "/lidar/raw"]
    assert all(m.payload == payload(m.seq, 2000) for m in lidar)
    ch = info.channels["/lidar/raw"]
    assert ch.duplicates == ch.backwards == 0 and ch.seq_first == 1 and ch.seq_last == seq
    assert ch.missing == stats.lost["/lidar/raw"] + stats.dropped["/lidar/raw"] > 50
    events = [m.payload for m in msgs if m.topic == "/events"]
    assert len(events) == 1 and events[0]["event"] == "log_write_failed"
    assert events[0]["segment"] == failed_segment and "ENOSPC" in events[0]["error"]
    assert events[0]["records_lost"]["/lidar/raw"] == stats.lost["/lidar/raw"]
    with capsys.disabled():
        print(f"\n[disk full test ran on: {small_disk.kind}]")


def test_failed_fsync_abandons_the_segment_without_another_write_and_resumes(tmp_path):
    state = {"fail": False, "failed_size": None}

    class FlakyFsync(SegmentIO):
        def fsync(self):
            if state["fail"]:
                state["fail"] = False
                state["failed_size"] = os.fstat(self.fd).st_size
                raise OSError(errno.EIO, os.strerror(errno.EIO))
            super().fsync()

    alarms = AlarmBook()
    w = SessionWriter(
        tmp_path,
        "v",
        SessionOptions(flush_s=0.1, fsync_s=0.2, retry_s=0.2),
        alarms=alarms,
        io_factory=FlakyFsync,
    )
    session = w.start()
    for i in range(1, 201):
        w.submit("/ins/raw", payload(i, 100), host_ns=i)
    wait_for(lambda: w.stats().messages_written == 200, what="200 records written")
    state["fail"] = True
    wait_for(lambda: alarms.get("disk_write_failed", "log") is not None, what="the fsync alarm")
    a = alarms.get("disk_write_failed", "log")
    assert "fsync failed (EIO" in a.message and "abandoned without further writes" in a.message
    wait_for(lambda: not alarms.is_active("disk_write_failed", "log"), what="resume")
    for i in range(201, 301):
        w.submit("/ins/raw", payload(i, 100), host_ns=i)
    w.close()
    first = segment_paths(session)[0]
    assert first.stat().st_size == state["failed_size"]  # not a byte written after the failure
    info = session_info(session)
    assert [s.state for s in info.segments] == ["unfinished", "complete"]
    (report,) = salvage_session(session)
    assert report.segment == first.name and report.messages >= 200
    msgs = [m for m in read_session(session) if m.topic == "/ins/raw"]
    assert [m.seq for m in msgs] == list(range(1, 301))
