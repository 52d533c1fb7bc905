"""Every fault of a scripted timeline, on real transports at speed 1: each is observable in the
decoded stream exactly when ``faults.json`` schedules it (the records it touches are those of
its window, no others), and its onset on the host clock is within the emulator's timing error
plus the receive slack."""

from __future__ import annotations

import collections
import json
import math

import numpy as np
import pytest

from drivers.hydrins.nmea_decode import NmeaDecoder
from sim_devices.faults import load_faults
from sim_devices.ins import InsSettings
from sim_devices.profiler import packet_layout
from tests.sim_devices.checks import assert_nav_matches, profile_bounds
from tests.sim_devices.harness import capture, slack

# realtime: the emulators run at speed 1 on real transports, and the latency jump's epochs are
# checked against their scheduled delay (median within 5 ms): a reader descheduled for longer by
# parallel workers stamps them late, so the module runs in the serial phase, as test_live_streams
pytestmark = [pytest.mark.realtime, pytest.mark.integration, pytest.mark.xdist_group("sim_devices_live")]

NS = 1_000_000_000

FAULTS = """\
seed: 3
faults:
  # INS (NMEA at 100 Hz, latency 3 ms + U(0, 0.5 ms))
  - {at_s: 1.0, kind: garbage, bytes: 100}
  - {at_s: 1.5, kind: bad_checksum, duration_s: 0.3}
  - {at_s: 2.0, kind: ins_latency_jump, latency_s: 0.02, duration_s: 1.0}
  - {at_s: 3.2, kind: gnss_outage, duration_s: 1.5, position_drift_m_s: 0.05}
  - {at_s: 5.0, kind: serial_unplug, duration_s: 1.0}
  # profiler (63 profiles/s, 2 packets each)
  - {at_s: 1.0, kind: udp_loss, device: profiler, duration_s: 0.5}
  - {at_s: 2.0, kind: udp_duplicate, device: profiler, duration_s: 0.3}
  - {at_s: 2.6, kind: udp_reorder, device: profiler, duration_s: 0.3}
  - {at_s: 3.5, kind: profiler_clock_offset, offset_s: 1.0, duration_s: 1.0}
  - {at_s: 5.0, kind: profiler_clock_drift, drift_ppm: 2000, duration_s: 1.5}
  # PPS (pulses at 0.5, 1.5, ... s of the window)
  - {at_s: 2.0, kind: pps_loss, duration_s: 2.0}
  - {at_s: 5.0, kind: udp_duplicate, device: pps, duration_s: 1.0}
"""


@pytest.fixture(scope="module")
def cap(short_sim, tmp_path_factory):
    d = tmp_path_factory.mktemp("faults")
    (d / "faults.yaml").write_text(FAULTS)
    return capture(
        short_sim,
        d / "run",
        start=2.5,
        duration_s=7.5,
        faults=load_faults(d / "faults.yaml"),
        devices=("ins", "profiler", "pps"),
        ins=InsSettings(latency_s=0.003, jitter_s=0.0005),
    )


def window(cap, kind: str, device: str) -> dict:
    rows = [
        f
        for f in json.loads((cap.run.run_dir / "faults.json").read_text())["faults"]
        if f["kind"] == kind and f["device"] == device
    ]
    assert len(rows) == 1
    return rows[0]


def test_all_emulators_finished(cap):
    assert {n: s["status"] for n, s in cap.stats.items()} == dict.fromkeys(
        ("ins", "profiler", "pps"), "finished"
    )


# -- INS -----------------------------------------------------------------------------------------


def test_garbage_is_skipped_exactly_and_arrives_when_scheduled(cap):
    f = window(cap, "garbage", "ins")
    dec = NmeaDecoder()
    before = at_ns = None  # bytes skipped before the first whole sentence: the reader may open
    for host_ns, data in cap.chunks:  # the pty in the middle of one (pyserial flushes at open)
        dec.feed(data, host_ns)
        if before is None and dec.stats.records:
            before = dec.stats.skipped_bytes
        if at_ns is None and before is not None and dec.stats.skipped_bytes > before:
            at_ns = host_ns
    assert dec.stats.skipped_bytes - before == 100 and cap.nav_stats.skipped_bytes == dec.stats.skipped_bytes
    assert 0 <= at_ns - f["start_host_ns"] <= slack(cap, "ins")


def test_bad_checksums_remove_exactly_the_epochs_of_their_window(cap):
    f = window(cap, "bad_checksum", "ins")
    track = cap.run.feed.ins
    got = {n.gps_ns for n in cap.nav}
    in_window = (track.gps_ns >= f["start_gps_ns"]) & (track.gps_ns < f["end_gps_ns"])
    unplug = window(cap, "serial_unplug", "ins")
    before_unplug = track.gps_ns < unplug["start_gps_ns"] - 300_000_000  # unread bytes die with the pty
    assert in_window.sum() == 30
    assert not got & set(track.gps_ns[in_window].tolist())
    assert set(track.gps_ns[~in_window & before_unplug].tolist()) <= got
    corrupted = cap.stats["ins"]["stats"]["corrupted"]
    assert corrupted == 30 * 12 + 1  # 12 sentences per epoch, and the ZDA of the second inside
    assert cap.nav_stats.rejected == {"bad_checksum": corrupted}


def test_latency_jump_delays_exactly_the_epochs_of_its_window(cap):
    f = window(cap, "ins_latency_jump", "ins")
    delays = {n.gps_ns: n.host_ns - cap.clock.host_ns(n.gps_ns) for n in cap.nav}
    inside = [d for g, d in delays.items() if f["start_gps_ns"] <= g < f["end_gps_ns"]]
    before = [d for g, d in delays.items() if f["start_gps_ns"] - NS <= g < f["start_gps_ns"]]
    assert len(inside) == 100
    # 23–23.5 ms scheduled; a receive stamp is taken before the read, so a reader descheduled
    # between the two can stamp an epoch a little early: 13 ms separates the two latencies
    assert min(inside) >= 13_000_000
    assert 23_000_000 <= np.median(inside) <= 23_500_000 + 5_000_000
    assert 3_000_000 <= np.median(before) <= 3_500_000 + 5_000_000
    # an epoch before the window is late only when the reader was (a loaded machine: the epochs
    # sent meanwhile queue up and arrive in one chunk with it) or the emulator was (its own worst
    # timing error, in the slack); the jump itself never delays an epoch before its window
    sharing = collections.Counter(n.host_ns for n in cap.nav)  # epochs stamped by one chunk
    late = [
        (n.gps_ns - f["start_gps_ns"], delays[n.gps_ns], sharing[n.host_ns])
        for n in cap.nav
        if f["start_gps_ns"] - NS <= n.gps_ns < f["start_gps_ns"] and delays[n.gps_ns] >= 13_000_000
    ]
    alone = [x for x in late if x[2] < 2 and x[1] > 3_500_000 + slack(cap, "ins")]
    assert not alone, f"epochs before the window delayed alone (offset, delay, sharing): {alone}"
    assert len(late) <= 0.5 * len(before)


def test_gnss_outage_sets_dead_reckoning_for_exactly_its_epochs(cap):
    f = window(cap, "gnss_outage", "ins")
    track = cap.run.feed.ins
    k_of = {int(g): k for k, g in enumerate(track.gps_ns)}
    seen = 0
    for nav in cap.nav:
        outage = f["start_gps_ns"] <= nav.gps_ns < f["end_gps_ns"]
        assert (
            nav.dead_reckoning is outage
            and nav.gps_valid is (not outage)
            and nav.gps_received is (not outage)
        )
        assert nav.navigation and nav.utc_detected
        k = k_of[nav.gps_ns]
        if outage:
            seen += 1
            drift_m = 0.05 * (nav.gps_ns - f["start_gps_ns"]) / NS
            north_m = math.radians(nav.lat_deg - track.lat_deg[k]) * 6_367_000
            assert abs(north_m - drift_m) <= 0.002
            assert abs(nav.sigma_north_m - math.hypot(track.sigma_p_m[k, 0], drift_m)) <= 0.005
        else:
            assert_nav_matches(nav, track, k, "nmea")
    assert seen == 150


def test_unplug_closes_the_pty_and_replug_moves_the_link(cap):
    f = window(cap, "serial_unplug", "ins")
    kinds = [(e.kind, e.host_ns) for e in cap.serial_events if e.kind != "reconnect_failed"]
    assert [k for k, _ in kinds[:3]] == ["connected", "disconnected", "connected"]
    lost_at, back_at = kinds[1][1], kinds[2][1]
    assert 0 <= lost_at - f["start_host_ns"] <= slack(cap, "ins")
    assert 0 <= back_at - f["end_host_ns"] <= slack(cap, "ins") + 100_000_000  # + the reader's back-off
    got = sorted(n.gps_ns for n in cap.nav)
    assert not [g for g in got if f["start_gps_ns"] <= g < f["end_gps_ns"]]
    last_before = max(g for g in got if g < f["start_gps_ns"])
    first_after = min(g for g in got if g >= f["end_gps_ns"])
    assert f["start_gps_ns"] - last_before <= 300_000_000  # unread bytes die with the pty
    assert first_after - f["end_gps_ns"] <= 200_000_000  # reopened within the back-off
    applied = cap.stats["ins"]["stats"]["applied"]
    assert [a["kind"] for a in applied] == ["garbage", "unplugged", "replugged"]
    first_pty = json.loads((cap.run.run_dir / "devices.json").read_text())["devices"]["ins"]["pty"]
    assert cap.stats["ins"]["stats"]["plugs"] == 2 and cap.stats["ins"]["stats"]["unplugs"] == 1
    assert applied[2]["pty"].startswith("/dev/pts/")
    assert first_pty.startswith("/dev/pts/")


# -- profiler ------------------------------------------------------------------------------------


def _packets(cap):
    """Emission order of (profile, packet) with the truth GPS instant each leaves at."""
    grid = cap.run.feed.grid
    layout = packet_layout(grid.runs)
    out = []
    for p in range(len(grid)):
        for k, (s0, n) in enumerate(layout):
            out.append(((p, k), int(grid.start_ns[p]) + round((s0 + n) * grid.dt_ns)))
    return out


def _received(cap):
    return [(int.from_bytes(d[8:12], "little"), int.from_bytes(d[12:14], "little")) for _, d in cap.datagrams]


def test_udp_loss_drops_exactly_the_datagrams_of_its_window(cap):
    f = window(cap, "udp_loss", "profiler")
    got = set(_received(cap))
    lost = {key for key, g in _packets(cap) if f["start_gps_ns"] <= g < f["end_gps_ns"]}
    assert len(lost) >= 60
    assert got == {key for key, _ in _packets(cap)} - lost
    assert cap.stats["profiler"]["stats"]["lost"] == len(lost)
    ev = cap.assembler_stats.events
    assert ev["profiles_lost"] + ev["packets_lost"] > 0


def test_udp_duplicate_sends_twice_exactly_the_datagrams_of_its_window(cap):
    f = window(cap, "udp_duplicate", "profiler")
    rx = _received(cap)
    dup = {key for key, g in _packets(cap) if f["start_gps_ns"] <= g < f["end_gps_ns"]}
    twice = {key for key in set(rx) if rx.count(key) == 2}
    assert len(dup) >= 30 and twice == dup
    assert cap.assembler_stats.events["duplicate"] == len(dup)


def test_udp_reorder_swaps_exactly_the_datagrams_of_its_window(cap):
    f = window(cap, "udp_reorder", "profiler")
    lost = window(cap, "udp_loss", "profiler")
    expected, held = [], None
    for key, g in _packets(cap):  # the rule: held back, sent right after the next one
        if lost["start_gps_ns"] <= g < lost["end_gps_ns"]:
            continue
        if held is None and f["start_gps_ns"] <= g < f["end_gps_ns"]:
            held = key
            continue
        expected.append(key)
        if held is not None:
            expected.append(held)
            held = None
    rx = list(dict.fromkeys(_received(cap)))  # duplicates of the other window removed
    assert rx == expected
    assert cap.stats["profiler"]["stats"]["reordered"] >= 15  # pairs of the 0.3 s window
    assert cap.assembler_stats.events["reordered"] == cap.stats["profiler"]["stats"]["reordered"]


def _clock_offsets(cap):
    """(profile start GPS, decoded time − truth of every point, PPS-locked flag) per profile."""
    grid = cap.run.feed.grid
    K = grid.points_per_360
    for prof in cap.profiles:
        slots = np.rint(prof.scan_angle_rad / (2 * np.pi / K)).astype(np.int64)
        yield (
            int(grid.start_ns[prof.profile_counter]),
            prof.gps_ns - grid.point_gps_ns(prof.profile_counter, slots),
            prof,
        )


def test_profiler_clock_offset_and_drift_act_exactly_in_their_windows(cap):
    off = window(cap, "profiler_clock_offset", "profiler")
    drift = window(cap, "profiler_clock_drift", "profiler")
    t_tol, _ = profile_bounds(cap.run.feed.grid)
    n_off = n_drift = 0
    for start, err, prof in _clock_offsets(cap):
        if off["start_gps_ns"] <= start < off["end_gps_ns"]:
            want, locked = NS, True
            n_off += 1
        elif drift["start_gps_ns"] <= start < drift["end_gps_ns"]:
            want, locked = round(2000e-6 * (start - drift["start_gps_ns"])), False
            n_drift += 1
        else:
            want, locked = 0, True
        assert np.all(np.abs(err - want) <= t_tol), (
            f"profile {prof.profile_counter}: clock error {err[0]} ≠ {want}"
        )
        assert prof.pps_locked is locked
    assert n_off >= 60 and n_drift >= 90


# -- PPS -----------------------------------------------------------------------------------------


def test_pps_loss_and_duplicates_exactly_in_their_windows(cap):
    loss = window(cap, "pps_loss", "pps")
    dup = window(cap, "udp_duplicate", "pps")
    seconds = [round(cap.clock.gps_ns(e.host_ns) / NS) for _, e in cap.pps]
    first, last = -(-cap.run.feed.start_gps_ns // NS), -(-cap.run.feed.end_gps_ns // NS)
    lost = {s for s in range(first, last) if loss["start_gps_ns"] <= s * NS < loss["end_gps_ns"]}
    doubled = {s for s in range(first, last) if dup["start_gps_ns"] <= s * NS < dup["end_gps_ns"]}
    assert len(lost) == 2 and len(doubled) == 1
    assert sorted(seconds) == sorted([s for s in range(first, last) if s not in lost] + list(doubled))
    sequences = [e.sequence for _, e in cap.pps]
    assert sorted(set(sequences)) == list(range(1, last - first - len(lost) + 1))  # no advance while lost
