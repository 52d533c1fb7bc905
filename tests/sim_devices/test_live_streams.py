"""All four emulators at once on real transports (pty, UDP, CAN udp_multicast), at speed 4:
each stream decoded with ``drivers`` gives back the scenario truth within its quantization, at
the instants the truth clock schedules."""

from __future__ import annotations

import json

import numpy as np
import pytest

from drivers.hydrins.timeofday import utc_time_of_day_ns
from sim_devices.canbus import CanSettings
from sim_devices.clock import TruthClock
from sim_devices.ins import InsSettings
from sim_devices.profiler import packet_layout
from sim_devices.runner import free_udp_port
from tests.sim_devices.checks import assert_nav_matches, assert_profile_matches, serial_emissions
from tests.sim_devices.harness import capture, slack

pytestmark = [pytest.mark.realtime, pytest.mark.integration, pytest.mark.xdist_group("sim_devices_live")]

SPEED = 4.0
NS = 1_000_000_000


@pytest.fixture(scope="module")
def cap(short_sim, tmp_path_factory):
    """Scenario seconds 2.5–12.5: pass 1's capture (returns), its line end, pass 2's start."""
    return capture(
        short_sim,
        tmp_path_factory.mktemp("live"),
        start=2.5,
        duration_s=10.0,
        speed=SPEED,
        ins=InsSettings(latency_s=0.003, jitter_s=0.0005),
        can=CanSettings(port=free_udp_port()),
    )  # a port of its own: no other run's markers


def test_every_emulator_finished_and_the_truth_clock_file(cap):
    assert {n: s["status"] for n, s in cap.stats.items()} == dict.fromkeys(
        ("ins", "profiler", "pps", "can"), "finished"
    )
    clock = TruthClock.read(cap.run.run_dir / "truth_clock.json")
    assert clock == cap.clock and clock.speed == SPEED and clock.rate == SPEED
    assert clock.gps_anchor_ns == cap.run.feed.start_gps_ns
    where = json.loads((cap.run.run_dir / "devices.json").read_text())
    assert where["devices"]["ins"]["link"] == str(cap.run.run_dir / "ins")
    assert not (cap.run.run_dir / "ins").exists(), "the INS link outlived the run"


def _earliest_stamps(cap) -> tuple[list[int], list[int]]:
    """The earliest receive stamp of each NMEA epoch and of each ZDA: the scheduled instant of
    the emission whose byte starts the chunk that brought the record's first byte (the decoder
    stamps a record with that chunk's stamp). The emulator never sends before its schedule (its
    own timing errors are all ≥ 0) and a chunk is stamped once its first byte is there, so that
    bound holds. It is the record's own schedule, unless the reader, descheduled between stamping
    a chunk and reading it, also took in the record sent meanwhile: see
    :func:`tests.sim_devices.checks.serial_emissions`."""
    assert cap.stats["ins"]["timing"]["error_min_us"] >= 0, "the INS sent before its scheduled instant"
    ins, track = cap.run.spec.ins, cap.run.feed.ins
    zda_head = b"$GPZDA,"
    emissions = serial_emissions(cap.chunks, (b"$" + ins.talker.encode() + b"HDT,", zda_head))
    first_s = -(-cap.run.feed.start_gps_ns // NS)
    scheduled, k, s = [], 0, first_s  # jitter ≥ 0: host(t_k) + latency is an epoch's earliest
    for head, _, _ in emissions:
        if head == zda_head:
            scheduled.append(cap.clock.host_ns(s * NS) + round(ins.zda_delay_s * NS))
            s += 1
        else:
            scheduled.append(cap.clock.host_ns(int(track.gps_ns[k])) + round(ins.latency_s * NS))
            k += 1
    assert k == len(track) and s - first_s == len(cap.zda)
    earliest = [(head, scheduled[leader]) for head, _, leader in emissions]
    return [t for h, t in earliest if h != zda_head], [t for h, t in earliest if h == zda_head]


def test_ins_nmea_stream_is_the_observed_trajectory(cap):
    track = cap.run.feed.ins
    assert len(cap.nav) == len(track) == 1000
    assert cap.nav_stats.rejected_total == 0 and cap.nav_stats.skipped_bytes == 0
    latency, jitter = 3_000_000, 500_000
    earliest, _ = _earliest_stamps(cap)
    for k, nav in enumerate(cap.nav):
        assert_nav_matches(nav, track, k, "nmea")
        assert nav.date_source in ("zda", "host")  # the host's date before the first ZDA: right, as now
        assert nav.time_of_day_ns == utc_time_of_day_ns(nav.gps_ns)
        assert nav.navigation and nav.fine_alignment and not nav.alignment and not nav.dead_reckoning
        assert nav.gps_valid and nav.utc_detected and nav.pps_detected
        # it left at host(t_k) + latency + U(0, jitter), received within the slack; stamped no
        # earlier than the send of the first byte of its chunk (itself, when it starts its chunk)
        delay = nav.host_ns - cap.clock.host_ns(nav.gps_ns) - latency
        assert nav.host_ns >= earliest[k], f"epoch {k}: delay {delay} ns, before its chunk's first send"
        assert delay <= jitter + slack(cap, "ins"), f"epoch {k}: delay {delay} ns"
    assert {n.date_source for n in cap.nav[100:]} == {"zda"}


def test_zda_once_per_second_after_each_pps_edge(cap):
    seconds = list(range(-(-cap.run.feed.start_gps_ns // NS), -(-cap.run.feed.end_gps_ns // NS)))
    assert len(cap.zda) == len(seconds) == 10
    edges = {e.sequence: e.host_ns for _, e in cap.pps}
    _, earliest = _earliest_stamps(cap)
    for zda, s, seq, lowest in zip(cap.zda, seconds, range(1, 11), earliest):
        assert zda.time_of_day_ns == utc_time_of_day_ns(s * NS)
        after = zda.host_ns - edges[seq]
        # sent 50 ms after host(s) (the edge's stamp: host(s) ± its 80 µs jitter), stamped no
        # earlier than the send of the first byte of its chunk (itself, when it starts its chunk)
        assert zda.host_ns >= lowest, f"ZDA {s}: {after} ns after its edge, before its chunk's first send"
        assert after <= 50_000_000 + slack(cap, "ins"), f"ZDA {s}: {after} ns after its edge"


def test_profiler_stream_is_the_scenario_returns(cap, short_sim):
    grid = cap.run.feed.grid
    assert [p.profile_counter for p in cap.profiles] == list(range(len(grid)))
    assert all(p.complete and p.pps_locked and p.time_valid for p in cap.profiles)
    assert cap.assembler_stats.rejected_total == 0 and not cap.assembler_stats.events
    shift = cap.run.feed.time_shift_ns
    checked = sum(assert_profile_matches(p, grid, short_sim.points, shift) for p in cap.profiles)
    assert checked == grid.ret_point.size > 5000  # pass 1's returns
    t = short_sim.points.t_gps_s
    in_window = (t >= (cap.run.feed.start_gps_ns - shift) / NS) & (t < (cap.run.feed.end_gps_ns - shift) / NS)
    assert checked == int(in_window.sum())
    # a packet leaves 0.5 ms after its last point was measured: the first packets' arrivals
    first = {}
    for host_ns, data in cap.datagrams:
        first.setdefault(int.from_bytes(data[8:12], "little"), host_ns)
    s0, n = packet_layout(grid.runs)[0]
    for p in range(0, len(grid), 25):
        due = cap.clock.host_ns(int(grid.start_ns[p]) + round((s0 + n) * grid.dt_ns)) + 500_000
        assert -100_000 <= first[p] - due <= slack(cap, "profiler"), f"profile {p}"


def test_pps_stamps_are_the_truth_clock_at_each_gps_second(cap):
    edges = [e for _, e in cap.pps]
    sent = cap.stats["pps"]["stats"]["edges"]
    assert [e.sequence for e in edges] == [s["sequence"] for s in sent] == list(range(1, 11))
    first_s = -(-cap.run.feed.start_gps_ns // NS)
    stamps_off = []
    for (arrival, e), s in zip(cap.pps, sent):
        assert s["gps_s"] == first_s + e.sequence - 1 and e.host_ns == s["host_ns"]
        stamps_off.append(e.host_ns - cap.clock.host_ns(s["gps_s"] * NS))
        assert 0 <= arrival - e.host_ns <= slack(cap, "pps")
    assert np.all(np.abs(stamps_off) <= 4 * 20_000)  # jitter σ 20 µs, clipped at 4σ
    assert np.std(stamps_off) > 0  # jittered, not exact
    # at speed 4 the pulses are a quarter second apart on the host clock
    assert np.allclose(np.diff([e.host_ns for e in edges]), NS / SPEED, atol=200_000)


def test_can_markers_at_the_pass_ends(cap):
    marks = cap.run.feed.marks
    assert [(m.kind, m.pass_id) for m in marks] == [("pass_end", 1), ("pass_start", 2)]
    got = [f.decoded for f in cap.markers]
    assert [(g.kind, g.pass_id, g.sequence) for g in got] == [("pass_end", 1, 1), ("pass_start", 2, 2)]
    for f, m in zip(cap.markers, marks):
        assert 0 <= f.host_ns - cap.clock.host_ns(m.gps_ns) <= slack(cap, "can")
