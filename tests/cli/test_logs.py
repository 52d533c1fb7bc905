"""`mls logs info` and `mls logs recover` on a session with a torn segment."""

from __future__ import annotations

import json

from typer.testing import CliRunner

from acquire.log.recover import SegmentScan, scan_segment, segment_paths
from acquire.log.session import SessionOptions
from acquire.log.sessionlog import SessionWriter
from acquire.timing.clock import ClockState, GpsEstimate
from cli.app import app
from tests.acquire.logutil import FakeMonotonic, wait_flushed

NS = 1_000_000_000
GPS0 = 1_400_000_000 * NS


class Clock:
    def to_gps(self, host_ns):
        return GpsEstimate(GPS0 + host_ns, ClockState.LOCKED, 1000)


def _session(tmp_path):
    """Two segments; INS at 100 Hz with a 3 s hole and 5 lost sequence numbers; the second
    segment is torn in its last chunk (as a crash leaves it)."""
    clock = FakeMonotonic()  # the writer's clock: a chunk ends when the test says
    w = SessionWriter(
        tmp_path,
        "survey-1",
        SessionOptions(flush_s=0.05, compression="none"),
        clock=Clock(),
        monotonic_ns=clock,
    )
    sd = w.start()
    t = submitted = 0
    for i in range(300):
        t += NS // 100 if i != 150 else 3 * NS
        if 200 <= i < 205:
            w._seq["/ins/raw"] += 1  # numbers taken but records lost (as a full queue does)
            continue
        w.submit("/ins/raw", b"$PIXSE,TIME__,120000.000*1F\r\n", host_ns=t)
        submitted += 1
        if i in (100, 120, 299):  # a chunk boundary
            clock.advance(0.05)
            wait_flushed(w, submitted)
        if i == 100:
            w.rotate()
    w.submit("/ins/raw", b"$PIXSE,TIME__,120001.000*1E\r\n", host_ns=t + NS)
    clock.advance(0.05)
    wait_flushed(w, submitted + 1)
    w.close()
    last = segment_paths(sd)[-1]
    scan = SegmentScan(last, 0)
    end_of_last_chunk = max(
        scan.good_bytes for rec in scan_segment(last, scan) if type(rec).__name__ == "Message"
    )
    # the footer, the summary and the last 20 bytes of the last chunk are gone
    last.write_bytes(last.read_bytes()[: end_of_last_chunk - 20])
    return sd


def test_info_then_recover_then_info(tmp_path):
    sd = _session(tmp_path)
    runner = CliRunner()
    r = runner.invoke(app, ["logs", "info", str(sd)], env={"COLUMNS": "200"})
    assert r.exit_code == 1, r.output
    assert "unfinished" in r.output and f"mls logs recover {sd}" in r.output
    assert "sequence 201–205 missing" in r.output
    r = runner.invoke(app, ["logs", "info", str(sd), "--json"])
    info = json.loads(r.output)
    ins = info["channels"]["/ins/raw"]
    assert ins["missing"] == 5 and ins["missing_ranges"] == [[201, 205]]
    assert len(ins["gaps"]) == 1 and abs(ins["gaps"][0][1] - 3.0) < 1e-6
    states = [s["state"] for s in info["segments"]]
    assert states == ["complete", "unfinished"]
    assert info["segments"][1]["problem"].startswith("torn chunk record")

    r = runner.invoke(app, ["logs", "recover", str(sd)], env={"COLUMNS": "200"})
    assert r.exit_code == 0, r.output
    assert "seg-000002.mcap" in r.output and "torn chunk record" in r.output
    assert (sd / "seg-000002.mcap.torn").exists()
    r = runner.invoke(app, ["logs", "info", str(sd), "--json"])
    after = json.loads(r.output)
    assert [s["state"] for s in after["segments"]] == ["complete", "complete"]
    assert after["segments"][1]["recovery"]["torn_bytes"] == str(info["segments"][1]["torn_bytes"])
    assert after["channels"]["/ins/raw"]["messages"] == info["channels"]["/ins/raw"]["messages"]
    r = runner.invoke(app, ["logs", "recover", str(sd)])
    assert r.exit_code == 0 and "nothing to recover" in r.output


def test_recover_refuses_a_session_being_written_and_info_a_missing_one(tmp_path):
    w = SessionWriter(tmp_path, "v")
    sd = w.start()
    try:
        r = CliRunner().invoke(app, ["logs", "recover", str(sd)])
        assert r.exit_code == 1 and "being written by a running daemon" in r.output
    finally:
        w.close()
    r = CliRunner().invoke(app, ["logs", "info", str(tmp_path / "nope")])
    assert r.exit_code == 2 and "no such session directory" in r.output
