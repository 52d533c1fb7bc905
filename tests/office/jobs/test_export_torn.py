"""A session whose segment did not end normally (a torn tail, as a crash or a power cut leaves it)
is exported with a warning naming the segment and the time span lost, or refused with
``--require-complete``; before and after ``mls logs recover``."""

from __future__ import annotations

import struct

import pytest
from typer.testing import CliRunner

from acquire.log.read import session_losses
from acquire.log.recover import SegmentScan, salvage_session, scan_segment, segment_paths
from acquire.log.session import SessionOptions
from acquire.log.sessionlog import SessionWriter
from acquire.timing.clock import ClockState, GpsEstimate
from calib.core import frames
from cli.app import app
from office.jobs.export import ExportError, ExportOptions, export_session
from tests.acquire.logutil import FakeMonotonic, wait_flushed
from tests.office.jobs.test_export import SITE, _write_session

NS = 1_000_000_000


def _utc(gps_ns: int) -> str:
    return frames.gps_ns_to_utc(gps_ns).strftime("%Y-%m-%d %H:%M:%S.%f")[:-3] + " UTC"


def _records(data: bytes) -> list[tuple[int, int, int]]:
    """(opcode, start, end) of the records of an MCAP file, in order."""
    out, pos = [], 8
    while pos + 9 <= len(data) - 8:
        opcode, length = struct.unpack_from("<BQ", data, pos)
        out.append((opcode, pos, pos + 9 + length))
        pos += 9 + length
    return out


def _last_log_ns(path) -> int:
    return max(rec.log_time for rec in scan_segment(path) if type(rec).__name__ == "Message")


def _later_chunk(tmp_path, after_ns: int) -> tuple[bytes, int]:
    """A chunk record the session writer wrote with five /ins/nav epochs 0.1…0.5 s after
    ``after_ns`` (in a session of its own), and its last log time."""
    w = SessionWriter(tmp_path / "later", "synth", SessionOptions(flush_s=0.2))
    sd = w.start()
    for k in range(1, 6):
        t = after_ns + k * NS // 10
        w.submit("/ins/nav", {"time_gps_ns": t}, host_ns=t, log_time_ns=t, clock_state="LOCKED")
    w.close()
    data = segment_paths(sd)[0].read_bytes()
    ((_, a, b),) = [r for r in _records(data) if r[0] == 0x06]
    return data[a:b], after_ns + 5 * NS // 10


@pytest.fixture
def torn_session(tmp_path):
    """The export test's session, its segment cut as a crash in the middle of writing a chunk
    leaves it: no summary, no footer, the first two thirds of a chunk of later epochs."""
    session, *_ = _write_session(tmp_path, marks=True)
    (session / "site.yaml").write_text(SITE)
    (seg,) = segment_paths(session)
    last_ns = _last_log_ns(seg)
    data = seg.read_bytes()
    data_end = max(b for op, _a, b in _records(data) if op == 0x06)  # after the last chunk
    chunk, chunk_end_ns = _later_chunk(tmp_path, last_ns)
    torn = chunk[: len(chunk) * 2 // 3]
    seg.write_bytes(data[:data_end] + torn)
    return session, seg.name, last_ns, chunk_end_ns, len(torn)


def test_a_torn_segment_is_exported_with_a_warning_naming_it_and_the_span_lost(tmp_path, torn_session):
    session, seg, last_ns, chunk_end_ns, torn = torn_session
    res = export_session(session, tmp_path / "bundle")
    lost = (
        f"{seg} is unfinished ({torn} torn bytes, torn chunk record at byte "
        f"{(session / seg).stat().st_size - torn} "
    )
    assert res.warnings[0].startswith(lost), res.warnings
    assert res.warnings[0].endswith(
        f"messages after {_utc(last_ns)} are lost, at least up to {_utc(chunk_end_ns)} "
        f"({(chunk_end_ns - last_ns) / 1e9:.3f} s: the torn chunk)"
    )
    assert res.points > 0 and res.epochs > 500  # the rest of the session is exported as before

    with pytest.raises(ExportError, match=r"incomplete session, not exported \(--require-complete\): " + seg):
        export_session(session, tmp_path / "b2", ExportOptions(require_complete=True))

    # salvaged (what the daemon does at start): still lost, still said; the span from the original
    salvage_session(session)
    res = export_session(session, tmp_path / "b3")
    assert res.warnings[0].startswith(f"{seg} was salvaged after a crash ({torn} torn bytes, torn chunk")
    assert res.warnings[0].endswith(f"at least up to {_utc(chunk_end_ns)} (0.500 s: the torn chunk)")
    with pytest.raises(ExportError, match="--require-complete"):
        export_session(session, tmp_path / "b4", ExportOptions(require_complete=True))


def test_mls_export_warns_or_refuses_with_require_complete(tmp_path, torn_session):
    session, seg, *_ = torn_session
    runner = CliRunner()
    r = runner.invoke(app, ["export", str(session), "--bundle", str(tmp_path / "b")], env={"COLUMNS": "300"})
    assert r.exit_code == 0, r.output
    assert f"warning: {seg} is unfinished" in r.stderr
    r = runner.invoke(app, ["export", str(session), "--bundle", str(tmp_path / "c"), "--require-complete"])
    assert r.exit_code == 1, r.output
    (line,) = r.stderr.splitlines()  # one line
    assert line.startswith(f"error: {session}: incomplete session, not exported (--require-complete): {seg}")
    assert not (tmp_path / "c" / "points.csv").exists()


class _Clock:
    def to_gps(self, host_ns):
        return GpsEstimate(1_400_000_000 * NS + host_ns, ClockState.LOCKED, 1000)


def test_a_segment_torn_before_the_next_one_loses_the_span_up_to_it(tmp_path):
    """An fsync failure abandons a segment and the writer goes on in a new one: the span lost
    runs from the torn segment's last complete message to the next segment's first."""
    clock = FakeMonotonic()  # the writer's clock: a chunk ends when the test says
    w = SessionWriter(
        tmp_path, "v", SessionOptions(flush_s=0.05, compression="none"), clock=_Clock(), monotonic_ns=clock
    )
    sd = w.start()
    for i in range(30):
        if i in (10, 20):  # a chunk boundary
            clock.advance(0.05)
            wait_flushed(w, i)
        if i == 20:
            w.rotate()
        w.submit("/ins/raw", b"$PIXSE,TIME__,120000.000*1F\r\n", host_ns=(i + 1) * NS // 10)
    clock.advance(0.05)
    wait_flushed(w, 30)
    w.close()
    first, second = segment_paths(sd)
    scan = SegmentScan(first, 0)
    ends = sorted({scan.good_bytes for rec in scan_segment(first, scan) if type(rec).__name__ == "Message"})
    first.write_bytes(first.read_bytes()[: ends[-1] - 20])  # its second chunk torn
    (loss,) = session_losses(sd)
    t10, t20 = (1_400_000_000 * NS + k * NS // 10 for k in (10, 21))
    assert (loss.segment, loss.state, loss.last_ns, loss.until_ns) == (first.name, "unfinished", t10, t20)
    assert loss.describe().endswith(f"no message between {_utc(t10)} and {_utc(t20)} (1.100 s lost)")
