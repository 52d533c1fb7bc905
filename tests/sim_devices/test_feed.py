"""The scenario cut into device streams, without transports: the profile grid derived from the
simulator's returns, the INS epochs, and the bytes each emulator encodes decoded back by the
drivers' codecs (at the full Z+F rate too)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from calib.sim.simulate import simulate
from drivers.hydrins.nmea_decode import NmeaNavAssembler
from drivers.hydrins.stdbin_decode import StdbinNavDecoder
from drivers.zf.assembler import ProfileAssembler
from sim_devices.clock import TruthClock
from sim_devices.faults import parse_faults
from sim_devices.feed import FeedError, make_feed, run_window, seconds_to_ns, shift_to_now
from sim_devices.ins import InsEmulator, InsSettings
from sim_devices.profiler import ProfilerEmulator, ProfilerSettings, packet_layout
from tests.sim_devices.checks import assert_nav_matches, assert_profile_matches, profile_bounds

NS = 1_000_000_000


def test_every_return_of_the_scenario_lands_on_the_profile_grid(short_sim):
    feed = make_feed(short_sim)
    g = feed.grid
    assert g.ret_point.size == len(short_sim.points) and g.returns_outside == 0
    assert np.array_equal(np.sort(g.ret_point), np.arange(len(short_sim.points)))
    profiles = np.repeat(np.arange(len(g)), np.diff(g.ret_offsets))
    t = g.start_ns[profiles] + np.rint(g.ret_slot * g.dt_ns).astype(np.int64)
    # float64 seconds near 1.2e9 resolve 0.24 µs: the simulator's own times carry that rounding
    assert np.max(np.abs(t - seconds_to_ns(short_sim.points.t_gps_s[g.ret_point]))) <= 300
    angle = g.ret_slot * (2 * np.pi / g.points_per_360)
    assert np.allclose(angle, short_sim.points.scan_angle_rad[g.ret_point], atol=1e-12)  # no angle noise here
    # profiles back to back: one period apart within a pass's grid, never overlapping at a re-phase
    step = np.diff(g.start_ns)
    assert np.all(step >= g.period_ns - 1) and np.all(step < 2 * g.period_ns)
    assert np.sum(np.abs(step - g.period_ns) > 1) == len(short_sim.plan.passes) - 1
    assert g.runs == ((812, 982), (1428, 1598))  # montreal's windows 320–358° and 182–220°, 1606 pts/360°


def test_the_grid_survives_scan_angle_noise_but_not_noise_beyond_half_a_step():
    noisy = simulate("montreal", 1, overrides=["site.pass_length_m=20", "motion.pass_gap_s=2"])
    g = make_feed(noisy).grid  # σ 0.005° against a 0.224° step
    assert g.ret_point.size == len(noisy.points)
    d = (
        np.remainder(
            g.ret_slot * (2 * np.pi / g.points_per_360) - noisy.points.scan_angle_rad[g.ret_point] + np.pi,
            2 * np.pi,
        )
        - np.pi
    )
    assert np.degrees(np.abs(d)).max() < 0.05  # the encoder angle; the noise stays off the wire
    wild = simulate(
        "montreal",
        1,
        overrides=["site.pass_length_m=20", "motion.pass_gap_s=2", "noise.scanner.sigma_scan_angle_deg=0.5"],
    )
    with pytest.raises(FeedError, match=r"pass 1: only \d+% of the scan angles sit on the encoder grid"):
        make_feed(wild)


def test_run_windows(short_sim):
    t0 = seconds_to_ns(short_sim.trajectory_true.t_gps_s[0])
    assert run_window(short_sim, 2.5, 1.0) == (t0 + 2_500_000_000, t0 + 3_500_000_000)
    assert run_window(short_sim, "pass:2")[0] == t0 + 12 * NS
    with pytest.raises(
        FeedError, match=r"start 'pass:9': expected pass:N with N one of \[1, 2, 3, 4, 5, 6\]"
    ):
        run_window(short_sim, "pass:9")
    with pytest.raises(FeedError, match=r"duration 80 s from 0 s runs past the scenario's end \(70 s\)"):
        run_window(short_sim, 0, 80.0)
    with pytest.raises(FeedError, match="INS rate 300 Hz"):
        make_feed(short_sim, 0, 1.0, ins_rate_hz=300)
    feed = make_feed(short_sim, 0, 1.0, time_shift="now")
    assert feed.time_shift_ns % NS == 0 and feed.start_gps_ns == t0 + feed.time_shift_ns
    assert abs(shift_to_now(t0) - feed.time_shift_ns) <= NS


def _clock(feed) -> TruthClock:
    return TruthClock(0, feed.start_gps_ns)


@pytest.mark.parametrize("protocol", ["nmea", "stdbin"])
def test_ins_bytes_decode_to_the_observed_trajectory(short_sim, protocol):
    feed = make_feed(short_sim, 2.0, 1.0, time_shift=0)
    track = feed.ins
    # the INS epochs are the observed (POS) trajectory, interpolated
    poses = short_sim.trajectory_observed.interpolate(track.gps_ns / 1e9)
    assert np.allclose(track.rpy_rad, poses.rpy_rad) and np.allclose(track.sigma_p_m, poses.sigma_p_m)
    emu = InsEmulator(
        track, InsSettings(protocol=protocol), [], feed.start_gps_ns, feed.end_gps_ns, "/nonexistent"
    )
    dec = NmeaNavAssembler(utc_clock=None) if protocol == "nmea" else StdbinNavDecoder(utc_clock=None)
    from drivers.hydrins.nmea_encode import encode_zda

    navs = dec.feed(encode_zda(feed.start_gps_ns)) if protocol == "nmea" else []
    for k in range(len(track)):
        navs += dec.feed(emu.nav_bytes(k))
    navs += dec.flush()
    assert len(navs) == len(track) == 100 and dec.stats.rejected_total == 0
    for k, nav in enumerate(navs):
        assert_nav_matches(nav, track, k, protocol)
        assert nav.navigation and nav.fine_alignment and not nav.dead_reckoning and nav.pps_detected


def test_ins_status_follows_alignment_and_gnss_outage(short_sim):
    feed = make_feed(short_sim, 2.0, 2.0, time_shift=0)
    plan = parse_faults(
        "faults:\n  - {at_s: 1.5, kind: gnss_outage, duration_s: 0.2, position_drift_m_s: 1.0}\n"
    )
    emu = InsEmulator(
        feed.ins,
        InsSettings(alignment_s=0.5),
        plan.for_device("ins"),
        feed.start_gps_ns,
        feed.end_gps_ns,
        "/nonexistent",
    )
    dec = NmeaNavAssembler(utc_clock=lambda: (feed.start_gps_ns - 18 * NS) + 315_964_800 * NS)
    navs = []
    for k in range(len(feed.ins)):
        navs += dec.feed(emu.nav_bytes(k))
    t = (np.array([n.gps_ns for n in navs]) - feed.start_gps_ns) / NS
    aligning = np.array([n.alignment for n in navs])
    outage = np.array([n.dead_reckoning for n in navs])
    assert np.array_equal(aligning, t < 0.5) and np.array_equal([n.navigation for n in navs], t >= 0.5)
    assert np.array_equal(outage, (t >= 1.5) & (t < 1.7 - 1e-9))
    assert not any(n.gps_valid for n in np.array(navs)[outage])
    last = np.flatnonzero(outage)[-1]
    north = math.radians(navs[last].lat_deg - feed.ins.lat_deg[last]) * 6_367_000
    assert north == pytest.approx(0.19, abs=0.002)  # 1 m/s for 0.19 s


def _round_trip(feed, faults=None):
    emu = ProfilerEmulator(feed.grid, ProfilerSettings(), faults or [], feed.start_gps_ns)
    asm = ProfileAssembler()
    profiles = []
    for _, _, datagram in emu.packets(_clock(feed)):
        profiles += asm.feed(datagram)
    return profiles + asm.flush(), asm.stats


def test_profiler_datagrams_decode_to_the_scenario_returns_at_the_full_rate():
    full = simulate(
        "montreal",
        0,
        overrides=[
            "site.pass_length_m=20",
            "site.passes=[{id: 1, relative_heading_deg: 0}]",
            "noise.scanner.sigma_scan_angle_deg=0",
            "scanner.point_rate_scale=1",
            "scanner.angular_windows_deg=[]",
        ],
    )
    feed = make_feed(full, 4.0, 0.5, time_shift=7 * NS)
    g = feed.grid
    assert (g.profile_rate_hz, g.points_per_360, len(g)) == (200.0, 5080, 99)  # wholly inside the window
    assert len(packet_layout(g.runs)) == 23  # 5080 points, 226 per 1400-byte packet
    profiles, stats = _round_trip(feed)
    assert [p.profile_counter for p in profiles] == list(range(99))
    assert all(p.complete and p.n_points == 5080 for p in profiles) and stats.rejected_total == 0
    checked = sum(assert_profile_matches(p, g, full.points, 7 * NS) for p in profiles)
    assert checked == g.ret_point.size > 10_000
    t_tol, a_tol = profile_bounds(g)
    assert t_tol <= 60 and a_tol <= math.radians(35e-6)  # ZFP1's integer steps along a 226-point packet


def test_profiler_clock_faults_shift_the_time_stamps_only(short_sim):
    feed = make_feed(short_sim, 3.0, 1.0, time_shift=0)
    plan = parse_faults(
        "faults:\n  - {at_s: 0.2, kind: profiler_clock_offset, duration_s: 0.3}\n"
        "  - {at_s: 0.6, kind: profiler_clock_drift, drift_ppm: -500, duration_s: 0.2}\n"
    )
    profiles, _ = _round_trip(feed, plan.for_device("profiler"))
    g = feed.grid
    for p in profiles:
        t = (int(g.start_ns[p.profile_counter]) - feed.start_gps_ns) / NS
        err = 0
        if 0.2 <= t < 0.5:
            err = NS
        elif 0.6 <= t < 0.8:
            err = round(-500e-6 * (t - 0.6) * NS)
        assert_profile_matches(p, g, short_sim.points, 0, clock_error_ns=err)
        assert p.pps_locked is not (0.6 <= t < 0.8)


def test_profiler_datagrams_leave_in_bursts_never_early_at_most_burst_s_late(short_sim):
    feed = make_feed(short_sim, 3.0, 2.0, time_shift=0)  # a few datagrams a profile: bursts of 20 ms
    emu = ProfilerEmulator(feed.grid, ProfilerSettings(burst_s=0.02), [], feed.start_gps_ns)
    clock = _clock(feed)
    now = [0]
    sent, waits = [], []

    class Pacer:
        def wait_until(self, t_ns):
            waits.append(t_ns)
            now[0] = max(now[0], t_ns)
            return True

    class Link:
        def send(self, payload, gps_ns):
            sent.append((now[0], payload))

    emu.link = Link()
    assert emu.run(clock, Pacer(), type("T", (), {"record": lambda self, a, b: None})())
    due = [(h, d) for h, _, d in emu.packets(clock)]
    assert [d for _, d in sent] == [d for _, d in due] and emu.counts["packets"] == len(due) > 100
    late_ns = np.array([s for s, _ in sent]) - np.array([h for h, _ in due])
    assert late_ns.min() >= 0 and late_ns.max() <= 20_000_000
    assert len(waits) < len(due) / 2  # one wake-up per burst, not per datagram
    with pytest.raises(ValueError, match="burst_s"):
        ProfilerSettings(burst_s=0.5)
