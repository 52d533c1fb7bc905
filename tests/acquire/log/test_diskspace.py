"""Low free disk is an alarm before it is ENOSPC: ``disk_low`` while a segment is open, with the
free space and the minutes left at the write rate, escalated, de-escalated and cleared with
hysteresis (acquire/log/diskspace.py)."""

from __future__ import annotations

import re
import threading

import pytest

from acquire.alarms import AlarmBook
from acquire.log import diskspace
from acquire.log.session import SessionOptions
from acquire.log.sessionlog import SessionWriter
from tests.acquire.logutil import payload, wait_for

MiB, GiB = 2**20, 2**30


class FakeDisk:
    """What :func:`acquire.log.diskspace.free_bytes` reports, set by the test; counts calls."""

    def __init__(self, free: int):
        self.free = free
        self.calls = 0
        self.lock = threading.Lock()

    def __call__(self, path) -> int:
        with self.lock:
            self.calls += 1
            return self.free


def test_disk_low_is_raised_while_a_segment_is_open_then_escalates_and_clears(tmp_path, monkeypatch):
    disk = FakeDisk(50 * GiB)
    monkeypatch.setattr(diskspace, "free_bytes", disk)
    alarms = AlarmBook()
    opts = SessionOptions(
        flush_s=0.1,
        fsync_s=0.2,
        rotate_s=3600.0,
        compression="none",
        disk_warning_bytes=1 * GiB,
        disk_critical_bytes=256 * MiB,
        disk_check_s=0.1,
    )
    w = SessionWriter(tmp_path, "v", opts, alarms=alarms)
    w.start()
    seq = 0

    def produce() -> None:
        nonlocal seq
        for _ in range(5):
            seq += 1
            w.submit("/lidar/raw", payload(seq, 1000), host_ns=seq)

    try:
        wait_for(lambda: w.stats().messages_written > 50, poll=produce, what="data flowing")
        assert not alarms.is_active("disk_low", "log")
        segment = w.stats().segment
        calls = disk.calls

        disk.free = 900 * MiB  # below the warning threshold, no segment opens meanwhile
        wait_for(lambda: alarms.is_active("disk_low", "log"), poll=produce, what="the warning")
        a = alarms.get("disk_low", "log")
        assert a.severity == "warning" and "900.0 MiB free" in a.message and "below 1.00 GiB" in a.message
        assert w.stats().segment == segment and w.stats().state == "writing"  # checked while open
        assert disk.calls > calls
        wait_for(
            lambda: "min left at" in alarms.get("disk_low", "log").message,
            poll=produce,
            what="the minutes left at the write rate",
        )
        m = re.search(r"about (\d+) min left at ([\d.]+) MiB/s", alarms.get("disk_low", "log").message)
        minutes, rate_mib = float(m.group(1)), float(m.group(2))
        assert rate_mib > 0 and minutes == pytest.approx(900 / rate_mib / 60, rel=0.3, abs=1)
        st = w.stats()
        assert st.free_bytes == 900 * MiB and st.disk_minutes_left is not None

        disk.free = 200 * MiB  # below the critical threshold: raised again as critical
        wait_for(lambda: alarms.get("disk_low", "log").severity == "critical", poll=produce, what="critical")
        assert "200.0 MiB free" in alarms.get("disk_low", "log").message

        disk.free = 1060 * MiB  # above both thresholds, not by 10 %: back to a warning, still active
        wait_for(
            lambda: alarms.get("disk_low", "log").severity == "warning", poll=produce, what="de-escalation"
        )
        assert alarms.is_active("disk_low", "log")

        disk.free = 2 * GiB  # room again
        wait_for(lambda: not alarms.is_active("disk_low", "log"), poll=produce, what="the clear")
        assert "2.00 GiB free on the log file system" in alarms.get("disk_low", "log").message
        assert w.stats().segment == segment  # one segment all along: no open ever checked it
    finally:
        w.close()
    events = [(e.action, e.alarm.severity) for e in alarms.drain() if e.alarm.name == "disk_low"]
    assert events == [("raise", "warning"), ("raise", "critical"), ("clear", "warning")]


def test_disk_low_without_writes_says_so_and_zero_disables_it(tmp_path, monkeypatch):
    monkeypatch.setattr(diskspace, "free_bytes", FakeDisk(100 * MiB))
    alarms = AlarmBook()
    w = SessionWriter(tmp_path / "a", "v", SessionOptions(disk_check_s=0.05), alarms=alarms)
    w.start()
    try:
        wait_for(
            lambda: "nothing being written" in getattr(alarms.get("disk_low", "log"), "message", ""),
            what="an idle writer's alarm",
        )
        assert alarms.get("disk_low", "log").severity == "critical"  # defaults: 10 GiB, 2 GiB
    finally:
        w.close()
    off = AlarmBook()
    w = SessionWriter(
        tmp_path / "b",
        "v",
        SessionOptions(disk_check_s=0.05, disk_warning_bytes=0, disk_critical_bytes=0),
        alarms=off,
    )
    w.start()
    wait_for(lambda: w.stats().free_bytes == 100 * MiB, what="a check")
    w.close()
    assert off.get("disk_low", "log") is None
    with pytest.raises(ValueError, match="critical ≤ warning"):
        SessionOptions(disk_warning_bytes=MiB, disk_critical_bytes=2 * MiB)
