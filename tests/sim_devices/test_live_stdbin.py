"""The INS emulator in STDBIN (V4) on a real pty, at 200 Hz and speed 2, with garbage and bad
checksums: frames decode to the observed trajectory (float32 quantization), dated by their
system-date block, and the faults hit exactly their windows."""

from __future__ import annotations

import json

import pytest

from drivers.hydrins.stdbin_decode import StdbinDecoder
from sim_devices.faults import parse_faults
from sim_devices.ins import InsSettings
from tests.sim_devices.checks import assert_nav_matches
from tests.sim_devices.harness import capture, slack

pytestmark = [pytest.mark.integration, pytest.mark.xdist_group("sim_devices_live")]

FAULTS = """\
faults:
  - {at_s: 0.5, kind: garbage, bytes: 64}
  - {at_s: 1.0, kind: bad_checksum, duration_s: 0.2}
"""


@pytest.fixture(scope="module")
def cap(short_sim, tmp_path_factory):
    return capture(
        short_sim,
        tmp_path_factory.mktemp("stdbin"),
        start=3.0,
        duration_s=2.0,
        speed=2.0,
        devices=("ins",),
        faults=parse_faults(FAULTS),
        ins=InsSettings(protocol="stdbin", stdbin_version=4, rate_hz=200.0, latency_s=0.002),
    )


def test_stdbin_frames_are_the_trajectory_except_in_the_bad_checksum_window(cap):
    assert cap.stats["ins"]["status"] == "finished"
    faults = {f["kind"]: f for f in json.loads((cap.run.run_dir / "faults.json").read_text())["faults"]}
    bad = faults["bad_checksum"]
    track = cap.run.feed.ins
    assert len(track) == 400 and track.period_ns == 5_000_000
    k_of = {int(g): k for k, g in enumerate(track.gps_ns)}
    got = [n.gps_ns for n in cap.nav]
    expected = [int(g) for g in track.gps_ns if not bad["start_gps_ns"] <= g < bad["end_gps_ns"]]
    assert got == expected  # 40 frames of the window missing, no other
    assert cap.nav_stats.rejected["bad_checksum"] == cap.stats["ins"]["stats"]["corrupted"] == 40
    for nav in cap.nav:
        assert nav.source == "stdbin" and nav.date_source == "system_date"
        assert_nav_matches(nav, track, k_of[nav.gps_ns], "stdbin")
        assert nav.navigation and nav.utc_detected and nav.pps_detected


def test_stdbin_garbage_is_skipped_when_scheduled(cap):
    f = next(
        f
        for f in json.loads((cap.run.run_dir / "faults.json").read_text())["faults"]
        if f["kind"] == "garbage"
    )
    dec = StdbinDecoder()
    before = None  # bytes skipped before the first whole frame: the reader may open the pty in
    for host_ns, data in cap.chunks:  # the middle of one (pyserial flushes the input at open)
        dec.feed(data, host_ns)
        if before is None and dec.stats.records:
            before = dec.stats.skipped_bytes
        if before is not None and dec.stats.skipped_bytes - before > 1:
            break
    # ±1: a chunk's trailing 'I'/'A' (a possible frame start) is held back, not yet counted as
    # skipped, until the next chunk shows what it was
    assert abs(dec.stats.skipped_bytes - before - 64) <= 1
    assert 0 <= host_ns - f["start_host_ns"] <= slack(cap, "ins")
