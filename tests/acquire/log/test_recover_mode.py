"""A recovered segment keeps the original's file mode (``mls logs recover`` and the salvage at
daemon start write a new file in its place)."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import pytest

from acquire.log.recover import recover_segment, salvage_root, salvage_session, segment_paths
from acquire.log.session import SessionOptions
from acquire.log.sessionlog import SessionWriter
from tests.acquire.logutil import payload, wait_flushed


def _torn_session(root: Path, name: str, mode: int) -> Path:
    """A session whose only segment lost its last bytes (a crash), with the given mode."""
    w = SessionWriter(root / "src", "v", SessionOptions(flush_s=0.05))
    sd = w.start()
    for i in range(1, 101):
        w.submit("/ins/raw", payload(i, 64), host_ns=i)
    wait_flushed(w, 100)
    w.close()
    data = segment_paths(sd)[0].read_bytes()
    d = root / name
    d.mkdir(parents=True)
    seg = d / "seg-000001.mcap"
    seg.write_bytes(data[: len(data) - 40])
    os.chmod(seg, mode)
    return seg


def _mode(p: Path) -> int:
    return stat.S_IMODE(p.stat().st_mode)


@pytest.mark.parametrize("mode", [0o640, 0o600, 0o444])
def test_mls_logs_recover_keeps_the_segment_mode(tmp_path, mode):
    old = os.umask(0o022)  # a recovering file would otherwise be 0o644
    try:
        seg = _torn_session(tmp_path, "20250101T000000Z_v", mode)
        (report,) = salvage_session(seg.parent)
    finally:
        os.umask(old)
    assert report.messages > 0
    assert _mode(seg) == mode and _mode(Path(report.original)) == mode
    st_new, st_old = seg.stat(), Path(report.original).stat()
    assert (st_new.st_uid, st_new.st_gid) == (st_old.st_uid, st_old.st_gid)


def test_salvage_at_start_and_an_interrupted_swap_keep_the_mode(tmp_path):
    old = os.umask(0o077)
    try:
        root = tmp_path / "root"
        a = _torn_session(root, "20250101T000000Z_v", 0o640)
        reports = salvage_root(root)
        assert list(reports) == [a.parent.name] and _mode(a) == 0o640
        # a swap interrupted after the first rename: the .torn original is the source
        b = _torn_session(tmp_path, "20250102T000000Z_v", 0o640)
        b.rename(b.with_name(b.name + ".torn"))
        recover_segment(b)
        assert _mode(b) == 0o640
    finally:
        os.umask(old)
