"""Line guidance, the pure functions: cross-track error sign and value, heading wrap, speed, the
capture window, live target hits against the simulator's exact labels, pre-survey checks and pass
acceptance with reasons on constructed geometry. The guidance state is tested in
``test_guidance_state.py``."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from acquire.guidance.acceptance import AcceptanceTolerances, PassWindow, evaluate_pass
from acquire.guidance.lines import (
    GuidanceSettings,
    course_over_ground,
    heading_error,
    in_capture,
    line_offsets,
    speed_over_ground,
)
from acquire.guidance.prechecks import disk_needed_bytes, prechecks
from acquire.guidance.targethits import target_hits
from calib.core import frames
from calib.core.geometry import Rectangle
from calib.core.georef import Mount
from calib.core.trajectory import Trajectory
from calib.sim.scenario import ScannerModel
from calib.sim.scenariofile import load_scenario
from calib.sim.scene import Scene
from calib.sim.simulate import scan
from calib.survey.passplan import PlannedPass, plan_site
from drivers.hydrins.nav import NavRecord, status_words

FRAME = frames.LocalFrame(45.5065, -73.5518, -24.5)


def _line(
    heading_deg: float, start=(0.0, 0.0), length_m=100.0, capture=(40.0, 60.0), speed=2.0, pid=1
) -> PlannedPass:
    h = math.radians(heading_deg)
    s = np.array([start[0], start[1], 0.0])
    d = np.array([math.cos(h), math.sin(h), 0.0])
    return PlannedPass(
        pid,
        1,
        0.0,
        h % (2 * math.pi),
        s,
        s + length_m * d,
        s + 50 * d,
        speed,
        capture[0],
        capture[1],
        "starboard",
        20.0,
    )


# -- geometry ---------------------------------------------------------------------------------


def test_xte_is_positive_to_starboard_with_the_exact_value():
    north = _line(0.0)
    along, xte = line_offsets([[10.0, 3.0, 0.0], [10.0, -3.0, 0.0], [-5.0, 0.0, 1.0]], north)
    assert along.tolist() == pytest.approx([10.0, 10.0, -5.0], abs=1e-12)
    assert xte.tolist() == pytest.approx([3.0, -3.0, 0.0], abs=1e-12)  # east of a north line
    east = _line(90.0, start=(5.0, 5.0))
    along, xte = line_offsets([[7.0, 15.0, 0.0]], east)  # 2 m north of an eastward line: port
    assert along[0] == pytest.approx(10.0, abs=1e-12) and xte[0] == pytest.approx(-2.0, abs=1e-12)
    sw = _line(225.0)
    # heading 225°: starboard points north-west
    p = 20.0 * np.array([-math.sqrt(0.5), -math.sqrt(0.5), 0]) + 4.0 * np.array(
        [math.sqrt(0.5), -math.sqrt(0.5), 0]
    )
    along, xte = line_offsets(p, sw)
    assert (along[0], xte[0]) == pytest.approx((20.0, 4.0), abs=1e-12)


@settings(max_examples=60, deadline=None)
@given(
    st.floats(0, 360), st.floats(-500, 500), st.floats(-50, 50), st.floats(-100, 100), st.floats(-100, 100)
)
def test_xte_and_progress_recover_a_constructed_offset(heading_deg, along_m, xte_m, n0, e0):
    line = _line(heading_deg, start=(n0, e0))
    h = line.heading_rad
    p = (
        line.start_lgf_m
        + along_m * np.array([math.cos(h), math.sin(h), 0])
        + xte_m * np.array([-math.sin(h), math.cos(h), 0])
        + [0, 0, 3.0]
    )
    a, x = line_offsets(p, line)
    assert a[0] == pytest.approx(along_m, abs=1e-9)
    assert x[0] == pytest.approx(xte_m, abs=1e-9)


def test_heading_error_wraps_across_north_and_south():
    d = np.degrees(heading_error(np.radians([359.0, 1.0, 180.0, 0.0, 90.0, 271.0]), np.radians(1.0)))
    assert d.tolist() == pytest.approx([-2.0, 0.0, 179.0, -1.0, 89.0, -90.0], abs=1e-9)
    assert math.degrees(heading_error(math.radians(1.0), math.radians(359.0))) == pytest.approx(2.0)
    # exactly opposite: +180° (the interval is (−180°, 180°])
    assert math.degrees(heading_error(math.radians(0.0), math.radians(180.0))) == pytest.approx(180.0)


def test_speed_course_and_capture_window():
    assert speed_over_ground(3.0, 4.0) == pytest.approx(5.0)
    assert math.degrees(course_over_ground(0.0, -2.0)) == pytest.approx(270.0)
    assert math.degrees(course_over_ground(-1.0, 0.0)) == pytest.approx(180.0)
    line = _line(30.0, capture=(40.0, 60.0))
    assert in_capture([39.9, 40.0, 50.0, 60.0, 60.1], line).tolist() == [False, True, True, True, False]


# -- live target hits ---------------------------------------------------------------------------


def test_target_hits_match_exact_ray_casting_and_gate_most_points_out():
    """A vessel sails north past a vertical and a 45° target hanging on a wall 15 m to
    starboard; the simulator's exact ray casting labels every return. With the mount the
    returns were made with, the gated hits are exactly the returns on the targets."""
    t1 = Rectangle.from_orientation("T1", [-1.75, 15.0, -5.0], 1.23, 1.22, np.pi / 2, np.pi * 1.5)
    t2 = Rectangle.from_orientation("T2", [1.75, 14.7, -5.0], 1.23, 0.76, np.pi / 4, np.pi * 1.5)
    wall = Rectangle.from_orientation("wall", [0.0, 15.03, -5.0], 8.0, 4.0, np.pi / 2, np.pi * 1.5, 0.25)
    scene = Scene((t1, t2, wall), ("target", "target", "wall"))
    t = 1.3e9 + np.arange(0.0, 10.0001, 0.05)
    s = t - t[0]
    p = np.column_stack([-10 + 2.0 * s, np.zeros_like(s), np.zeros_like(s)])
    rpy = np.column_stack(
        [
            np.radians(1.5) * np.sin(2 * np.pi * s / 4),
            np.zeros_like(s),
            np.radians(0.3) * np.sin(2 * np.pi * s / 9),
        ]
    )
    traj = Trajectory(t, p, rpy, FRAME)
    mount = Mount(lever_arm_m=[0.3, 0.8, -1.6], boresight_rad=np.radians([0.2, 1.2, 0.15]))
    scanner = ScannerModel(point_rate_scale=0.05)
    ret = scan(scanner, scene, traj, mount, t[0] + 0.5, t[-1] - 0.5)
    rate = scanner.effective_profile_rate_hz
    k = np.floor((ret.t_gps_s - ret.t_gps_s[0]) * rate).astype(np.int64)
    uniq, which = np.unique(k, return_inverse=True)
    t_prof = ret.t_gps_s[0] + (uniq + 0.5) / rate
    # add no-returns (NaN) in between: never hits
    n = ret.t_gps_s.size
    rho = np.concatenate([ret.range_true_m, np.full(50, np.nan)])
    alpha = np.concatenate([ret.alpha_rad, np.full(50, 0.3)])
    tt = np.concatenate([ret.t_gps_s, np.full(50, ret.t_gps_s[n // 2])])
    pi = np.concatenate([which, np.full(50, which[n // 2])])
    targets = Scene((t1, t2), ("target", "target"))
    hits = target_hits(
        tt,
        rho,
        alpha,
        pi,
        t_prof,
        traj,
        mount,
        targets,
        settings=GuidanceSettings(hit_plane_tolerance_m=0.01),
    )
    truth = ret.surface
    assert np.bincount(truth, minlength=3)[:2].min() > 100  # both targets well covered
    assert np.bincount(truth, minlength=3)[2] > 100  # and the wall around them
    on_target = np.sort(ret.t_gps_s[truth < 2])
    assert hits.t_gps_s.size == on_target.size
    assert np.array_equal(np.sort(hits.t_gps_s), on_target)
    assert hits.counts(2).tolist() == np.bincount(truth[truth < 2], minlength=2).tolist()
    assert hits.n_points == n + 50
    # the gate georeferences the targets' neighbourhood only, not the whole wall
    assert on_target.size <= hits.n_gated < 0.8 * n
    # with the a-priori mount (boresight 0) the counts stay close to the truth
    apriori = target_hits(
        tt, rho, alpha, pi, t_prof, traj, replace(mount, boresight_rad=np.zeros(3)), targets
    )
    ratio = apriori.counts(2) / hits.counts(2)
    assert np.all((ratio > 0.8) & (ratio < 1.25)), ratio


def test_target_hits_of_an_empty_batch():
    traj = Trajectory(np.array([0.0, 1.0]), np.zeros((2, 3)), np.zeros((2, 3)), FRAME)
    scene = Scene((Rectangle.from_orientation("T", [0, 15, -5], 1, 1, np.pi / 2, 0.0),), ("target",))
    h = target_hits([], [], [], [], [], traj, Mount(), scene)
    assert h.n_points == 0 and h.counts(1).tolist() == [0]


# -- pre-survey checks ------------------------------------------------------------------------


def _nav(**flags) -> NavRecord:
    base = dict(
        navigation=True,
        fine_alignment=True,
        gps_received=True,
        gps_valid=True,
        utc_detected=True,
        pps_detected=True,
    )
    base.update(flags)
    alg, sys_ = status_words(**base)
    return NavRecord(
        "nmea",
        gps_ns=1,
        lat_deg=45.5,
        lon_deg=-73.5,
        height_m=0.0,
        roll_rad=0.0,
        pitch_rad=0.0,
        heading_rad=0.0,
        sigma_north_m=0.02,
        sigma_east_m=0.02,
        algorithm_status=alg,
        system_status=sys_,
    )


GOOD = dict(
    clock={"state": "LOCKED", "last_edge_age_s": 0.3, "jitter_rms_us": 1.5},
    latency={
        "ins": {"latency_mean_ms": 10.0, "latency_p99_ms": 12.0, "pps_flag": True},
        "profiler": {"latency_mean_ms": 2.0, "latency_p99_ms": 3.0, "pps_flag": True},
    },
    bands_ms={"ins": (0.0, 30.0), "profiler": (0.0, 20.0)},
    free_bytes=50 * 10**9,
    needed_bytes=10 * 10**9,
    mount_configured=True,
    n_targets=2,
)


def _checks(nav=None, **over):
    kw = {**GOOD, **over}
    return {c.name: c for c in prechecks(nav if nav is not None else _nav(), **kw)}


def test_prechecks_all_green_with_reasons():
    c = _checks()
    assert set(c) == {
        "ins_navigating",
        "gnss_fix",
        "pps_locked",
        "clock_locked",
        "latency_in_band",
        "disk_space",
        "mount_targets",
    }
    assert all(x.ok for x in c.values()), {k: x.detail for k, x in c.items()}
    assert c["gnss_fix"].detail == "fix, σh 0.03 m"
    assert c["latency_in_band"].detail == "in band, max 10.0 ms"
    assert c["disk_space"].detail == "50 GB free ≥ 10 GB"
    assert c["pps_locked"].detail == "INS, clock, 2 devices"


@pytest.mark.parametrize(
    ("nav_flags", "over", "name", "detail"),
    [
        ({"fine_alignment": False, "alignment": True}, {}, "ins_navigating", "aligning"),
        ({"navigation": False}, {}, "ins_navigating", "not navigating"),
        ({"dead_reckoning": True}, {}, "ins_navigating", "dead reckoning"),
        ({"gps_valid": False, "gps_received": False}, {}, "gnss_fix", "no GNSS data"),
        ({"gps_valid": False}, {}, "gnss_fix", "GNSS not valid"),
        ({"utc_detected": False}, {}, "gnss_fix", "fix, INS not on UTC"),
        ({"pps_detected": False}, {}, "pps_locked", "no PPS: INS"),
        (
            {},
            {"clock": {"state": "HOLDOVER", "last_edge_age_s": 4.2, "error_bound_us": 35.0}},
            "pps_locked",
            "no PPS: last edge 4.2 s ago",
        ),
        (
            {},
            {"clock": {"state": "HOLDOVER", "last_edge_age_s": 4.2, "error_bound_us": 35.0}},
            "clock_locked",
            "HOLDOVER, ±35 µs",
        ),
        (
            {},
            {
                "latency": {
                    "ins": {"latency_mean_ms": 10.0, "latency_p99_ms": 12.0},
                    "profiler": {"latency_mean_ms": 15.0, "latency_p99_ms": 27.0},
                }
            },
            "latency_in_band",
            "profiler 27.0>20 ms",
        ),
        ({}, {"latency": {"ins": {"latency_mean_ms": None}}}, "latency_in_band", "ins no data"),
        (
            {},
            {"latency": {"profiler": {"pps_flag": False, "latency_mean_ms": 2.0}}},
            "pps_locked",
            "no PPS: profiler",
        ),
        ({}, {"free_bytes": 3 * 10**9}, "disk_space", "3.0 GB free < 10 GB"),
        ({}, {"mount_configured": False, "n_targets": 1}, "mount_targets", "no mount, 1 target (need 2)"),
    ],
)
def test_prechecks_name_each_failure(nav_flags, over, name, detail):
    c = _checks(_nav(**nav_flags), **over)
    assert c[name].ok is False
    assert c[name].detail == detail
    assert sum(not x.ok for x in c.values()) == (2 if name == "clock_locked" or "last edge" in detail else 1)


def test_prechecks_name_each_device_that_is_not_connected_with_its_error():
    c = _checks(devices={"ins": "[Errno 2] No such file or directory: '/dev/ttyUSB9'", "profiler": None})
    assert c["devices_connected"].ok is False and c["devices_connected"].label == "Devices"
    assert c["devices_connected"].detail == "ins: [Errno 2] No such file or directory: '/dev/ttyUSB9'"
    assert sum(not x.ok for x in c.values()) == 1
    c = _checks(devices={"ins": None, "profiler": "[Errno 98] Address already in use"})
    assert c["devices_connected"].detail == "profiler: [Errno 98] Address already in use"
    c = _checks(devices={"ins": None, "profiler": None})
    assert c["devices_connected"].ok is True and c["devices_connected"].detail == "2 connected"


def test_prechecks_without_data_are_unknown_not_green():
    c = {x.name: x for x in prechecks(None, None)}
    assert c["ins_navigating"].ok is None and c["clock_locked"].ok is None
    assert c["latency_in_band"].ok is None and c["disk_space"].ok is None
    assert c["mount_targets"].ok is False


def test_disk_needed_for_the_planned_passes():
    plan = plan_site(load_scenario("montreal").site())
    # six 60 m lines at 2 m/s (30 s each) + five 120 s turns, at 1 MB/s, margin 2
    assert disk_needed_bytes(plan, rate_bytes_s=1e6, turn_s=120.0, margin=2.0) == (
        (6 * 30 + 5 * 120) * 2 * 10**6
    )


# -- pass acceptance ----------------------------------------------------------------------------


def _window(**over) -> PassWindow:
    t = 1000.0 + np.arange(0.0, 5.0, 0.02)
    n = t.size
    ones = np.ones(n)
    base = dict(
        pass_id=3,
        planned_speed_mps=2.0,
        capture_m=(40.0, 50.0),
        completed=True,
        exit_reason="",
        t_enter_gps_s=t[0],
        t_exit_gps_s=t[-1] + 0.02,
        t_gps_s=t,
        along_m=40.0 + 2.0 * (t - t[0]),
        xte_m=0.3 * np.sin(t),
        heading_error_rad=np.radians(1.0) * ones,
        speed_mps=2.0 + 0.1 * np.sin(t),
        navigation=ones,
        dead_reckoning=0 * ones,
        ins_pps=ones,
        utc=ones,
        profile_t_gps_s=np.arange(t[0], t[-1] + 0.02, 0.005),
        profiles_incomplete=0,
        profiles_pps_unlocked=0,
        hits={"T1": 800, "T2": 150},
        clock_states=("LOCKED",),
    )
    base.update(over)
    return PassWindow(**base)


def test_a_good_pass_is_accepted_with_statistics():
    v = evaluate_pass(_window())
    assert v.accepted and v.reasons == ()
    assert v.stats["max_xte_m"] == pytest.approx(0.3, abs=0.01)
    assert v.stats["max_heading_error_deg"] == pytest.approx(1.0)
    assert v.stats["hits"] == {"T1": 800, "T2": 150}
    assert v.stats["max_nav_gap_s"] == pytest.approx(0.02, abs=1e-6)


def _during(t0, t1, inside: float, outside: float) -> np.ndarray:
    """A status flag over the window: ``inside`` for t0 ≤ t < t1, else ``outside``."""
    t = _window().t_gps_s
    return np.where((t >= t0) & (t < t1), inside, outside)


@pytest.mark.parametrize(
    ("over", "reason"),
    [
        ({"xte_m": np.full(250, 2.5)}, "cross-track error up to 2.50 m (tolerance 2 m)"),
        (
            {"xte_m": np.concatenate([np.zeros(249), [-2.2]])},
            "cross-track error up to 2.20 m (tolerance 2 m)",
        ),
        ({"heading_error_rad": np.full(250, np.radians(-7.24))}, "heading error up to 7.2° (tolerance 5°)"),
        ({"speed_mps": np.linspace(1.2, 2.1, 250)}, "speed 1.20–2.10 m/s, planned 2 ± 0.5 m/s"),
        ({"hits": {"T1": 800, "T2": 40}}, "too few target points (T2: 40 points; need 100)"),
        (
            {
                "completed": False,
                "exit_reason": "left the line (XTE +11.0 m)",
                "along_m": np.linspace(40.0, 46.5, 250),
            },
            "capture window not completed: left the line (XTE +11.0 m) at 6.5 of 10.0 m",
        ),
        ({"navigation": _during(1001.0, 1002.0, 0.0, 1.0)}, "INS not navigating for 1.0 s of the window"),
        ({"ins_pps": np.full(250, np.nan)}, "INS status (PPS) not reported"),
        ({"dead_reckoning": _during(1001.0, 1001.5, 1.0, 0.0)}, "INS in dead reckoning for 0.5 s"),
        ({"clock_states": ("HOLDOVER", "LOCKED")}, "clock HOLDOVER during the window (must stay LOCKED)"),
        ({"clock_states": ()}, "clock state unknown during the window (must stay LOCKED)"),
        ({"profiles_incomplete": 3}, "3 profile(s) incomplete (packets lost)"),
        ({"profiles_pps_unlocked": 12}, "profiler PPS not locked in 12 profile(s)"),
        (
            {
                "profile_t_gps_s": np.concatenate(
                    [np.arange(1000.0, 1002.0, 0.005), np.arange(1002.795, 1005.0, 0.005)]
                )
            },
            "profiler data gap of 0.80 s (limit 0.5 s)",
        ),
    ],
)
def test_each_failed_condition_is_a_reason(over, reason):
    v = evaluate_pass(_window(**over))
    assert not v.accepted
    assert v.reasons == (reason,)


def test_an_ins_gap_and_several_reasons_together():
    w = _window()
    keep = (w.t_gps_s < 1001.0) | (w.t_gps_s > 1001.7)
    arrays = {
        k: getattr(w, k)[keep]
        for k in (
            "t_gps_s",
            "along_m",
            "xte_m",
            "heading_error_rad",
            "speed_mps",
            "navigation",
            "dead_reckoning",
            "ins_pps",
            "utc",
        )
    }
    v = evaluate_pass(replace(w, **arrays, hits={"T1": 5, "T2": 150}, profiles_incomplete=1))
    assert not v.accepted
    # the last sample before the gap is at 1000.98 s, the first after it at 1001.72 s
    assert v.reasons == (
        "INS data gap of 0.74 s (limit 0.5 s)",
        "1 profile(s) incomplete (packets lost)",
        "too few target points (T1: 5 points; need 100)",
    )
    tight = AcceptanceTolerances(max_xte_m=0.1, min_points_per_target=10)
    v2 = evaluate_pass(_window(), tight)
    assert v2.reasons == ("cross-track error up to 0.30 m (tolerance 0.1 m)",)
