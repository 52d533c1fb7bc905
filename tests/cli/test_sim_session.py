"""``mls sim session``: a 20-s survey written offline at 1 % of the Z+F point rate is a session
like the daemon's — closed, indexed segments (rotated every 10 s here), the daemon's channels and
encodings, its session files — that ``mls export`` turns into a bundle matching the simulation's
truth: the passes at the lines' times, every point inside them on the scene's surfaces when
georeferenced with the true trajectory and mount, the trajectory within the NMEA resolution of the
observed one, and as many returns on the wire as the simulator cast. Its datagrams are the
profiler emulator's own bytes; an existing session is replaced only with --force."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from acquire.log.read import channel_metadata, iter_messages, session_losses
from acquire.log.recover import segment_closed, segment_paths
from acquire.log.schema import CHANNELS, JSON_ENCODING, RAW_ENCODING
from cli.app import app
from drivers.zf.zfp1 import decode_packet
from office.jobs.export import ExportOptions, export_session
from office.simsession.lidar import pack_profiles
from office.simsession.record import SessionSpec, plan_session

ENV = {"COLUMNS": "250"}
NS = 1_000_000_000
# 8-s lines (16 m at 2 m/s) with 2-s turns: lines 1 and 2 lie inside the 20 s, line 3 starts at
# its end; the scanner's noise off, so that the truth check is exact to the wire's resolution
SETS = (
    "site.pass_length_m=16",
    "motion.pass_gap_s=2",
    "noise.scanner.sigma_range_m=0",
    "noise.scanner.beam_divergence_mrad=0",
)
ARGS = ["--minutes", str(1 / 3), "--rate-scale", "0.01", "--rotate-s", "10"]


def run(out: Path, *extra: str):
    sets = [a for s in SETS for a in ("--set", s)]
    return CliRunner().invoke(app, ["sim", "session", "--out", str(out), *ARGS, *sets, *extra], env=ENV)


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    out = tmp_path_factory.mktemp("sessions")
    res = run(out)
    assert res.exit_code == 0, res.output
    (path,) = [p for p in out.iterdir() if p.is_dir()]
    assert f"wrote {path}:" in res.output and "2 passes, 2 segments" in res.output
    return path


@pytest.fixture(scope="module")
def truth(tmp_path_factory):
    """The same survey sailed again (same seed): its true and observed trajectories, mount, scene."""
    spec = SessionSpec(out=tmp_path_factory.mktemp("plan"), minutes=1 / 3, rate_scale=0.01, overrides=SETS)
    return plan_session(spec)


@pytest.fixture(scope="module")
def exported(session, tmp_path_factory):
    bundle = tmp_path_factory.mktemp("bundle")
    return export_session(session, bundle, ExportOptions(require_complete=True))


def summary(session: Path) -> dict:
    return json.loads((session / "session.json").read_text())


def test_the_session_is_the_daemons_format(session):
    assert session.name == "20190709T140000Z_sim-montreal"  # the scenario's start, its vessel
    names = {p.name for p in session.iterdir()}
    assert {"seg-000001.mcap", "seg-000002.mcap", "session.json", "vessel.yaml", "site.yaml"} <= names
    assert session_losses(session) == []
    assert [p.name for p in segment_paths(session)] == ["seg-000001.mcap", "seg-000002.mcap"]
    assert all(segment_closed(p) for p in segment_paths(session))
    meta = channel_metadata(session)
    assert set(meta) == {
        "/ins/raw",
        "/ins/nav",
        "/lidar/raw",
        "/pps",
        "/can/marks",
        "/events",
        "/clock",
        "/latency",
    }
    assert meta["/ins/raw"]["protocol"] == "nmea" and meta["/lidar/raw"]["protocol"] == "zfp1"
    from mcap.reader import make_reader

    with open(segment_paths(session)[0], "rb") as f:
        channels = make_reader(f).get_summary().channels.values()
    for ch in channels:  # encodings as docs/architecture.md §4.5 says
        kind = CHANNELS.get(ch.topic, "raw")
        assert ch.message_encoding == (RAW_ENCODING if kind == "raw" else JSON_ENCODING), ch.topic
    doc = summary(session)
    assert doc["format"] == "marine-mls session v1" and doc["vessel"] == "sim-montreal"
    assert doc["mount"]["lever_arm_m"] == [0.35, 0.85, -1.65]
    sim = doc["simulation"]
    assert sim["rate_scale"] == 0.01 and sim["profiler"]["profile_rate_hz"] == pytest.approx(20.0)
    assert sim["profiler"]["points_per_360"] == 508  # 5080 × √0.01
    from acquire.daemon.config import load_vessel_config

    cfg = load_vessel_config(session / "vessel.yaml")  # the copy validates, its site beside it
    assert cfg.site_file == session / "site.yaml" and cfg.session.rotate_s == 10.0


def test_every_record_is_timed_by_the_truth_clock_and_locked(session):
    doc = summary(session)
    clock = doc["simulation"]["truth_clock"]
    t0, t_end = doc["simulation"]["window_gps_ns"]
    assert t_end - t0 == 20 * NS
    counts: dict[str, int] = {}
    for env in iter_messages(session):
        counts[env.topic] = counts.get(env.topic, 0) + 1
        assert env.clock == "LOCKED"
        assert env.log_time_ns == clock["gps_anchor_ns"] + env.host_ns - clock["host_anchor_ns"]
        if env.topic == "/lidar/raw":  # device time = the packet's t0, sent 0.5 ms after its last point
            pk = decode_packet(env.payload)
            assert env.device_ns == pk.t0_ns == env.publish_time_ns
            assert env.log_time_ns - (pk.t0_ns + pk.n_points * pk.dt_ns) in range(0, 600_000)
        elif env.topic == "/ins/nav":
            assert env.payload["time_source"] == "device" and env.device_ns == env.payload["time_gps_ns"]
            assert 3_000_000 <= env.log_time_ns - env.device_ns <= 3_600_000  # the INS latency + jitter
    assert counts["/ins/nav"] == 2000 and counts["/ins/raw"] == 2000 + 20  # 100 Hz epochs + ZDAs
    assert counts["/pps"] == 20 and counts["/can/marks"] == 4
    assert counts["/lidar/raw"] == doc["written"]["packets"] == 400 * 3  # 508 slots: 226 + 226 + 56
    events = [e.payload for e in iter_messages(session, ["/events"])]
    # (a file system with less than 10 GiB free gets the daemon's disk_low warning too)
    events = [e["event"] for e in events if not (e["event"] == "alarm" and e["name"] == "disk_low")]
    assert events == [
        "session_start",
        "simulated_session",
        "pass_start",
        "pass_end",
        "pass_start",
        "pass_end",
        "session_end",
    ]
    pps = [e.payload for e in iter_messages(session, ["/pps"])]
    assert all(p["accepted"] and p["reason"] == "accepted" for p in pps)
    assert [p["gps_s"] for p in pps] == list(range(t0 // NS, t_end // NS))


def test_export_gives_the_passes_and_points_of_the_truth(session, exported, truth):
    doc = summary(session)
    lines = {p["id"]: p["line_gps_s"] for p in json.loads((session / "truth.json").read_text())["passes"]}
    assert sorted(lines) == [1, 2] and exported.warnings == []
    for w in exported.passes:  # the marks at the lines' start and end
        assert w.source == "can:marks"
        assert abs(w.start_gps_ns / NS - lines[w.pass_id][0]) < 1e-6
        assert abs(w.end_gps_ns / NS - lines[w.pass_id][1]) < 1e-6
    want = {int(k): v for k, v in doc["written"]["returns_per_pass"].items()}
    assert exported.points_per_pass == want and sum(want.values()) > 80_000
    assert exported.epochs == 2000 and exported.epochs_from_clock == 0 and exported.packets_unsynced == 0
    from calib.core.georef import georeference
    from calib.io.bundle import read_bundle

    b = read_bundle(exported.bundle)
    p, sim = b.points, truth.sim
    win = {w.pass_id: (w.start_gps_ns / NS, w.end_gps_ns / NS) for w in exported.passes}
    lo = np.array([win[i][0] for i in p.pass_id])
    hi = np.array([win[i][1] for i in p.pass_id])
    assert np.all((p.t_gps_s >= lo - 1e-6) & (p.t_gps_s <= hi + 1e-6))
    # with the true trajectory and mount every point lies on a surface of the scene (range 0.1 mm)
    traj = replace(sim.trajectory_true, max_gap_s=np.inf)
    x = georeference(p.t_gps_s, p.range_m, p.scan_angle_rad, traj, sim.mount_true)
    dist = np.min(
        [np.abs(sim.scene.distance_m(np.full(len(x), j), x)) for j in range(len(sim.scene))], axis=0
    )
    assert dist.max() < 1e-4
    # the trajectory is the observed one (POS errors and all) to the NMEA resolution
    obs = replace(sim.trajectory_observed, max_gap_s=np.inf).interpolate(b.trajectory.t_gps_s)
    assert np.abs(b.trajectory.p_lgf_m - obs.p_lgf_m).max() < 1.5e-3  # 1e-8° lat/lon, 1 mm height
    d_att = np.angle(np.exp(1j * (b.trajectory.rpy_rad - obs.rpy_rad)))
    assert np.degrees(np.abs(d_att)).max() < 1e-3  # attitude to 0.001°
    assert np.allclose(np.diff(b.trajectory.t_gps_s), 0.01, atol=1e-6)  # 100 Hz


def test_the_returns_are_the_simulators(session, truth):
    from calib.sim.simulate import scan

    doc = summary(session)
    returns = points = 0
    for env in iter_messages(session, ["/lidar/raw"]):
        pk = decode_packet(env.payload)  # a valid ZFP1 packet (CRC and all) or it raises
        returns += int(np.count_nonzero(pk.range_01mm))
        points += pk.n_points
    assert returns == doc["written"]["returns"] and points == doc["written"]["points"] == 400 * 508
    # the simulator cast over the whole window at once (noise off: the range window is exact)
    lidar, sim = truth.lidar, truth.sim
    t0 = truth.t0_ns / NS
    cast = scan(
        truth.survey.scanner,
        sim.scene,
        replace(sim.trajectory_true, max_gap_s=np.inf),
        sim.mount_true,
        t0,
        t0 + (lidar.n_profiles + 0.5) / lidar.rate_hz,
    )
    sc = truth.survey.scanner
    inside = (cast.range_true_m >= sc.min_range_m) & (cast.range_true_m <= sc.max_range_m)
    assert returns == int(inside.sum()) > 100_000
    by_surface = json.loads((session / "truth.json").read_text())["survey"]["returns_by_surface"]
    assert sum(by_surface.values()) == returns and by_surface["T1"] > 0 and by_surface["T2"] > 0


def test_the_datagrams_are_the_profiler_emulators_bytes():
    from sim_devices.clock import TruthClock
    from sim_devices.feed import ProfileGrid
    from sim_devices.profiler import ProfilerEmulator, ProfilerSettings, packet_layout

    rng = np.random.default_rng(1)
    K, P, rate = 1606, 5, 63.245553203367585
    runs = ((3, 520), (700, 1606))  # two windows: a short packet ends each
    slots = [np.sort(rng.choice(np.arange(*runs[1]), 300, replace=False)) for _ in range(P)]
    r01 = [rng.integers(1, 2**32 - 1, s.size, dtype=np.uint32) for s in slots]
    i16 = [rng.integers(0, 65535, s.size, dtype=np.uint16) for s in slots]
    start = 1_246_716_018_000_000_000 + np.rint(np.arange(P) * 1e9 / rate).astype(np.int64)
    grid = ProfileGrid(
        rate,
        K,
        start,
        runs,
        np.cumsum([0] + [s.size for s in slots]),
        np.concatenate(slots),
        np.concatenate(r01),
        np.concatenate(i16),
        np.zeros(sum(s.size for s in slots), np.int64),
    )
    clock = TruthClock(3600 * NS, int(start[0]))
    want = list(ProfilerEmulator(grid, ProfilerSettings(), [], int(start[0])).packets(clock))
    ranges, inten = np.zeros((P, K), np.uint32), np.zeros((P, K), np.uint16)
    for p in range(P):
        ranges[p, slots[p]], inten[p, slots[p]] = r01[p], i16[p]
    got = pack_profiles(
        start, np.arange(P), ranges, inten, packet_layout(runs), grid.dt_ns, grid.dangle_udeg, clock, 500_000
    )
    assert len(got) == len(want) == P * len(packet_layout(runs))
    assert [bytes(v) for v in got.payloads] == [w[2] for w in want]
    assert got.host_ns.tolist() == [w[0] for w in want]
    assert got.t0_ns.tolist() == [decode_packet(w[2]).t0_ns for w in want]


def test_an_existing_session_is_replaced_only_with_force(tmp_path):
    extra = ("--rate-scale", "0.001", "--ins-protocol", "stdbin")
    first = run(tmp_path, *extra)
    assert first.exit_code == 0, first.output
    (path,) = list(tmp_path.iterdir())
    seg = path / "seg-000001.mcap"
    before = seg.stat().st_mtime_ns
    again = run(tmp_path, *extra)
    assert again.exit_code == 2
    assert f"{path}: the session exists; add --force to replace it" in " ".join(again.output.split())
    assert seg.stat().st_mtime_ns == before
    stray = path / "notes.txt"  # not a session's file: --force leaves the directory alone
    stray.write_text("mine")
    refused = run(tmp_path, *extra, "--force")
    assert refused.exit_code == 2 and "holds files a session does not (notes.txt)" in refused.output
    assert stray.exists() and seg.stat().st_mtime_ns == before
    stray.unlink()
    forced = run(tmp_path, *extra, "--force")
    assert forced.exit_code == 0, forced.output
    assert seg.stat().st_mtime_ns != before and session_losses(path) == []
    assert channel_metadata(path)["/ins/raw"]["protocol"] == "stdbin"
    nav = [e.payload for e in iter_messages(path, ["/ins/nav"])]
    assert len(nav) == 2000 and {n["time_source"] for n in nav} == {"device"}


def test_a_production_survey_is_refused_with_what_plays_it(tmp_path):
    res = CliRunner().invoke(
        app, ["sim", "session", "--scenario", "harbour", "--out", str(tmp_path), "--minutes", "0.1"], env=ENV
    )
    assert res.exit_code == 2, res.output
    text = " ".join(res.output.split())
    assert "'harbour' is a production survey" in text and "mls sim devices" in text
    assert list(tmp_path.iterdir()) == []
