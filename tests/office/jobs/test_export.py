"""``office.jobs.export`` on a synthetic session written with the session writer: passes from the
event marks or from the site's pass plan, points decoded again (synced and unsynced packets,
duplicated datagrams), the mount of the session's vessel config, and the refusals."""

from __future__ import annotations

import json
import math
import textwrap

import numpy as np
import pytest

from acquire.log.session import SessionOptions
from acquire.log.sessionlog import SessionWriter
from calib.core import frames
from calib.io.bundle import read_bundle
from calib.io.sbet import read_sbet
from calib.io.site import parse_site
from calib.survey.passplan import plan_site
from drivers.zf.zfp1 import encode_profile
from office.jobs.export import ExportError, ExportOptions, export_session, passes_from_events
from office.jobs.sessionread import fill_sigmas

NS = 1_000_000_000
G0 = 1_400_000_000 * NS  # GPS ns at the start of the session
H0 = 10_000 * NS  # its host monotonic time
SITE = textwrap.dedent("""\
    reference: {lat_deg: 45.5, lon_deg: -73.55, height_m: 0.0}
    mount: {lever_arm_m: [0, 0, 0], nominal_deg: [0, 0, 0], boresight_apriori_deg: [0, 0, 0]}
    wall_azimuth_deg: 30.0
    standoff_m: 15.0
    targets:
      - {name: T1, center: {lat_deg: 45.5, lon_deg: -73.55, height_m: -5.0}, size_m: [1.2, 1.2],
         inclination_deg: 90.0, facing_azimuth_deg: 300.0, reflectivity: 0.9}
    passes:
      - {id: 1, relative_heading_deg: 0.0, length_m: 40.0, speed_mps: 2.0}
      - {id: 2, relative_heading_deg: 180.0, length_m: 40.0, speed_mps: 2.0}
    """)
DT_NS = 1000  # ZFP1 point period of the synthetic profiles


def _track(site):
    """10 Hz epochs: pass 1's line, a 20-s transit off the lines, pass 2's line (reversed)."""
    plan = plan_site(site)
    p1, p2 = plan.by_id(1), plan.by_id(2)
    segs = []
    for line in (p1, None, p2):
        if line is None:
            a = segs[-1][0][-1]
            b = p2.start_lgf_m
            mid = (a + b) / 2 + np.array([30.0, -30.0, 0.0])  # well away from both lines
            pts = np.concatenate(
                [
                    a + np.linspace(0, 1, 101)[:, None] * (mid - a),
                    mid + np.linspace(0, 1, 101)[1:, None] * (b - mid),
                ]
            )
            h = np.full(len(pts), math.radians(120.0))  # across the lines
        else:
            s = np.arange(0.0, line.length_m, 0.2)
            pts = line.position_at(s)
            h = np.full(len(pts), line.heading_rad)
        segs.append((pts, h))
    p = np.concatenate([s[0] for s in segs])
    heading = np.concatenate([s[1] for s in segs])
    n1 = len(segs[0][0])
    n2 = len(segs[0][0]) + len(segs[1][0])
    return p, heading, (0, n1 - 1), (n2, len(p) - 1)


def _write_session(tmp, marks: bool):
    site = parse_site(SITE)
    p, heading, pass1, pass2 = _track(site)
    lat, lon, h = site.reference.to_geodetic(p)
    w = SessionWriter(tmp / "sessions", "synth", SessionOptions(flush_s=0.2))
    session = w.start()
    t = G0 + np.arange(len(p)) * 100_000_000
    sent = []
    for k in range(len(p)):
        host = H0 + int(t[k] - G0)
        nav = {
            "lat_deg": float(lat[k]),
            "lon_deg": float(lon[k]),
            "height_m": float(h[k]),
            "roll_deg": 0.5,
            "pitch_deg": -0.2,
            "heading_deg": math.degrees(heading[k]),
            "sigma_north_m": 0.02,
            "sigma_east_m": 0.02,
            "sigma_down_m": 0.03,
            "sigma_roll_deg": 0.01,
            "sigma_pitch_deg": 0.01,
            "sigma_heading_deg": 0.02,
            "time_gps_ns": int(t[k]),
            "time_source": "device",
        }
        if k == 10:  # an epoch whose STDPOS/STDHRP were lost
            nav = {key: v for key, v in nav.items() if not key.startswith("sigma_")}
        if k == 20:  # an epoch that lost its STATUS, timed by the clock model while unlocked
            nav.update(time_gps_ns=int(t[k]) + 700_000_000, time_source="clock")
            w.submit("/ins/nav", nav, host_ns=host, log_time_ns=nav["time_gps_ns"], clock_state="UNLOCKED")
        else:
            w.submit(
                "/ins/nav",
                nav,
                host_ns=host,
                device_ns=int(t[k]),
                log_time_ns=int(t[k]),
                clock_state="LOCKED",
            )
        r = np.full(20, 100_000, np.uint32)
        r[::5] = 0  # no returns
        locked = k != 30  # one profile without a PPS-locked time tag
        (d,) = encode_profile(
            k, int(t[k]), DT_NS, 0, 1_000_000, r, np.full(20, 900, np.uint16), pps_locked=locked
        )
        log_time = int(t[k]) + 5_000_000  # received 5 ms after its first point
        for _ in range(2 if k == 40 else 1):  # a duplicated datagram
            w.submit("/lidar/raw", d, host_ns=host + 5_000_000, log_time_ns=log_time, clock_state="LOCKED")
        sent.append((k, int(t[k]), log_time, locked))
    if marks:
        for kind, pid, k in (
            ("pass_start", 1, pass1[0]),
            ("pass_end", 1, pass1[1]),
            ("pass_start", 2, pass2[0]),
        ):  # no end for pass 2
            w.submit(
                "/events",
                {"event": kind, "pass_id": pid, "source": "mqtt"},
                host_ns=H0 + int(t[k] - G0),
                log_time_ns=int(t[k]),
                clock_state="LOCKED",
            )
    w.close()
    (session / "session.json").write_text(
        json.dumps(
            {
                "mount": {
                    "lever_arm_m": [0.35, 0.85, -1.65],
                    "nominal_deg": [0.0, 0.0, 90.0],
                    "boresight_apriori_deg": [0.1, 0.2, 0.3],
                }
            }
        )
    )
    return session, site, t, pass1, pass2, sent


@pytest.mark.parametrize("marks", [True, False])
def test_export_takes_passes_from_marks_or_the_plan_and_decodes_every_return(tmp_path, marks):
    session, site, t, pass1, pass2, sent = _write_session(tmp_path, marks)
    (tmp_path / "site.yaml").write_text(SITE)
    res = export_session(
        session,
        tmp_path / "bundle",
        ExportOptions(site_file=tmp_path / "site.yaml", sbet_path=tmp_path / "t.sbet"),
    )
    assert res.pass_source == ("events" if marks else "plan")
    assert [w.pass_id for w in res.passes] == [1, 2]
    w1, w2 = res.passes
    assert (w1.start_gps_ns, w1.end_gps_ns) == (t[pass1[0]], t[pass1[1]])
    assert w2.start_gps_ns == t[pass2[0]] and w2.end_gps_ns == t[-1]
    if marks:
        assert res.warnings[0] == "pass 2 has no pass_end: it runs to the end of the session"
    b = read_bundle(res.bundle)
    assert np.allclose(np.degrees(b.site.mount.boresight_rad), [0.1, 0.2, 0.3])  # session.json
    assert np.allclose(b.site.mount.lever_arm_m, [0.35, 0.85, -1.65])
    # every epoch at its own time, the one the unlocked clock misplaced by 0.7 s included
    np.testing.assert_allclose(b.trajectory.t_gps_s, frames.gps_ns_to_seconds(t), rtol=0, atol=1e-6)
    assert b.trajectory.has_sigmas
    assert (
        "1 INS epochs were timed by the clock model (INS not on UTC + PPS), 1 of them, received "
        "while the clock was unlocked, through the INS time tags around them"
    ) in res.warnings
    assert (
        f"1 of {len(t)} INS epochs had no sigmas: interpolated from the neighbouring epochs" in res.warnings
    )
    assert np.allclose(b.trajectory.sigma_p_m, [0.02, 0.02, 0.03])
    # expected: 16 returns per profile whose points fall inside a pass, no duplicate
    exp_t, exp_pid = [], []
    for _k, t0, log_time, locked in sent:
        i = np.arange(20)
        tt = t0 + i * DT_NS if locked else log_time - (19 - i) * DT_NS
        keep = i % 5 != 0
        for w in res.passes:
            inside = keep & (tt >= w.start_gps_ns) & (tt <= w.end_gps_ns)
            exp_t += list(tt[inside])
            exp_pid += [w.pass_id] * int(inside.sum())
    pts = b.points
    assert len(pts) == len(exp_t) == res.points
    order = np.lexsort((np.array(exp_t), np.array(exp_pid)))
    np.testing.assert_allclose(pts.t_gps_s, frames.gps_ns_to_seconds(np.array(exp_t)[order]), atol=1e-6)
    assert np.allclose(pts.range_m, 10.0) and set(np.round(np.degrees(pts.scan_angle_rad))) <= set(range(20))
    assert res.packets == len(sent) and res.packets_unsynced == 1
    assert len(read_sbet(tmp_path / "t.sbet")) == len(t)
    assert (tmp_path / "t.smrmsg").exists()


def test_plan_passes_follow_the_heading_of_the_line():
    site = parse_site(SITE)
    p, heading, pass1, pass2 = _track(site)
    t = G0 + np.arange(len(p)) * 100_000_000
    from calib.core.trajectory import Trajectory
    from office.jobs.export import passes_from_plan

    traj = Trajectory(
        t / 1e9, p, np.column_stack([np.zeros((len(p), 2)), heading]), site.reference, max_gap_s=1.0
    )
    # pass 2 is pass 1's line sailed the other way: only the heading tells them apart
    back = Trajectory(
        t / 1e9,
        p,
        np.column_stack([np.zeros((len(p), 2)), frames.wrap_2pi(heading + math.pi)]),
        site.reference,
        max_gap_s=1.0,
    )
    ids = [w.pass_id for w in passes_from_plan(traj, site, t, ExportOptions())]
    assert ids == [1, 2]
    assert [w.pass_id for w in passes_from_plan(back, site, t, ExportOptions())] == [2, 1]
    short = passes_from_plan(traj, site, t, ExportOptions(min_pass_s=25.0))
    assert short == []  # the 20-s lines are shorter than asked


def test_marks_without_their_partner_and_unlocked_marks_are_reported():
    ev = [
        (10 * NS, "clock", {"event": "pass_end", "pass_id": 4, "source": "mqtt"}),
        (20 * NS, "ins", {"event": "pass_start", "pass_id": 1, "source": "can:marks"}),
        (30 * NS, "ins", {"event": "pass_start", "pass_id": 2, "source": "can:marks"}),
        (40 * NS, "clock", {"event": "pass_end", "pass_id": 2, "source": "can:marks"}),
        (45 * NS, "clock", {"event": "mark", "text": "buoy"}),
    ]
    windows, warnings = passes_from_events(ev, 99 * NS)
    assert [(w.pass_id, w.start_gps_ns, w.end_gps_ns) for w in windows] == [
        (1, 20 * NS, 30 * NS),
        (2, 30 * NS, 40 * NS),
    ]
    assert warnings == [
        "2 pass marks were logged while the clock model was UNLOCKED: timed from the "
        "INS time tags around them",
        "pass_end of pass 4 without its pass_start: ignored",
        "pass 1 has no pass_end: it ends where pass 2 starts",
    ]


def test_export_refusals_name_the_problem(tmp_path):
    session, *_ = _write_session(tmp_path, marks=False)
    with pytest.raises(ExportError, match="no site file in the session .* --site site.yaml"):
        export_session(session, tmp_path / "b")
    (session / "site.yaml").write_text(SITE)
    with pytest.raises(ExportError, match="no pass_start/pass_end marks in /events .* --passes plan"):
        export_session(session, tmp_path / "b", ExportOptions(passes="events"))
    with pytest.raises(ExportError, match="passes 'marks': expected one of auto, events, plan"):
        ExportOptions(passes="marks")
    with pytest.raises(ExportError, match="no such session directory"):
        export_session(tmp_path / "nope", tmp_path / "b")


def test_missing_sigmas_are_interpolated_unless_most_are_missing():
    t_ns = np.arange(6, dtype=np.int64) * 100_000_000
    sig = np.tile(np.arange(6.0)[:, None] + 1.0, (1, 6))  # 1 … 6, growing with time
    sig[2, 0] = np.nan  # a lost sentence
    sig[5] = np.nan  # the last epoch: held at its neighbour's
    filled, n = fill_sigmas(t_ns, sig)
    assert n == 2 and filled[2, 0] == 3.0 and np.all(filled[5] == 5.0)
    assert np.array_equal(filled[[0, 1, 3, 4]], sig[[0, 1, 3, 4]])
    assert fill_sigmas(t_ns, np.full((6, 6), 0.1)) == (pytest.approx(np.full((6, 6), 0.1)), 0)
    sig[:4] = np.nan  # two epochs of six carry sigmas: none is written
    assert fill_sigmas(t_ns, sig) == (None, 0)
