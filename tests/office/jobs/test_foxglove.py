"""``office.jobs.foxglove`` (``mls export SESSION --foxglove OUT.mcap``) on a synthetic session
written with the session writer, read back with ``mcap`` and decoded with the protobuf
descriptors the file itself carries: every channel's schema and encoding, the message counts,
log times in UTC as Unix ns (the session's GPS times less GPS − UTC) and in order, the fixes at
the session's INS epochs, the poses in a z-up frame, the clouds where
:func:`calib.core.georef.georeference` puts the returns, the alarms as Log messages at their
severity's level, the clock and latency numbers; the refusal to overwrite, no half file after an
error, and the CLI.

:func:`check_foxglove_file` is the read-back check the demo's test (``test_demo.py``) runs on
the demo's session too."""

from __future__ import annotations

import datetime as dt
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from acquire.foxglove.channels import SCHEMAS, TOPICS
from acquire.foxglove.frames import gps_to_unix_ns
from acquire.log.session import SessionOptions
from acquire.log.sessionlog import SessionWriter
from calib.core import frames
from calib.core.georef import Mount, georeference
from calib.core.gpstime import GPS_EPOCH_UNIX_S
from calib.core.trajectory import Trajectory
from calib.io.outputs import OutputError
from drivers.zf.zfp1 import encode_profile
from office.jobs.export import ExportError
from office.jobs.foxglove import FoxgloveResult, export_foxglove
from tests.foxglove_wire import Descriptors
from tests.office.jobs.test_export import SITE

NS = 1_000_000_000
G0 = 1_400_000_000 * NS  # GPS ns of the first INS epoch: 2024-05-17T16:53:02Z
UNIX = (GPS_EPOCH_UNIX_S - 18) * NS  # GPS ns → UTC Unix ns in this era (GPS − UTC = 18 s)
H0 = 10_000 * NS  # its host monotonic time
REF = frames.LocalFrame(45.5, -73.55, 0.0)  # SITE's reference
N_EPOCHS = 300  # 10 Hz, 30 s
N_POINTS, DT_NS, DANGLE_UDEG = 40, 50_000, 9_000_000
FREE_RUN_NS = 3_200_000_000  # how far the unlocked clock model's log times are off
MOUNT = dict(
    lever_arm_m=[0.35, 0.85, -1.65], nominal_deg=[0.0, 0.0, 90.0], boresight_apriori_deg=[0.1, 0.2, 0.3]
)


# -- the read-back check ------------------------------------------------------------------------


@dataclass
class ReadBack:
    """A Foxglove export read back: topic → [(log_time_ns, decoded message)], file order."""

    messages: dict[str, list[tuple[int, dict]]]
    metadata: dict[str, str]

    def points(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Cloud k's points (n, 3) in lgf_enu (its pose + the packed offsets) and intensities."""
        msg = self.messages["/lidar/points"][k][1]
        rec = np.frombuffer(msg["data"], np.dtype([(n, "<f4") for n in ("x", "y", "z", "intensity")]))
        pos = msg["pose"]["position"]
        xyz = np.column_stack([rec["x"], rec["y"], rec["z"]]).astype(float) + [pos["x"], pos["y"], pos["z"]]
        return xyz, rec["intensity"].astype(float)


def _matrix(q: dict) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_quat([q["x"], q["y"], q["z"], q["w"]]).as_matrix()


def utc_unix_ns(gps_ns: int) -> int:
    """GPS ns → UTC Unix ns by calib's leap-second table (outside an inserted second)."""
    return int(gps_ns) + (GPS_EPOCH_UNIX_S - frames.leap_seconds_at_gps_ns(int(gps_ns))) * NS


def check_foxglove_file(path: Path, session: Path, result: FoxgloveResult | None = None) -> ReadBack:
    """Read a Foxglove export back and check what holds for any session: the six channels with
    their schemas and encodings, every message decoded with its schema, log times in order per
    channel and equal to the message timestamps, the counts and span (``result``'s), the fixes
    at the session's INS epochs (their log times: the epochs in UTC Unix ns, by calib's leap
    table), the poses (ENU translation of the fix, unit quaternion, the vessel upright), the
    clouds' layout and their points within the scanner's reach of the vessel, and every alarm of
    the session's /events as a Log at its severity's level."""
    from mcap.reader import make_reader

    from acquire.log.read import iter_messages

    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None
        channels = {c.id: c for c in summary.channels.values()}
        assert {c.topic for c in channels.values()} <= set(TOPICS)  # a channel without messages: absent
        decoders = {}
        for c in channels.values():
            schema = summary.schemas[c.schema_id]
            assert schema.name == SCHEMAS[c.topic], c.topic
            if schema.name.startswith("foxglove."):
                assert (c.message_encoding, schema.encoding) == ("protobuf", "protobuf"), c.topic
                decoders[c.id] = (Descriptors.parse(schema.data), f".{schema.name}")
            else:
                assert (c.message_encoding, schema.encoding) == ("json", "jsonschema"), c.topic
                assert json.loads(schema.data)["title"] == schema.name
                decoders[c.id] = None
        counts = dict.fromkeys(TOPICS, 0)
        counts |= {channels[i].topic: n for i, n in summary.statistics.channel_message_counts.items()}
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
        by_topic: dict[str, list[tuple[int, dict]]] = {t: [] for t in TOPICS}
        for _, channel, message in reader.iter_messages(log_time_order=False):
            dec = decoders[channel.id]
            msg = json.loads(message.data) if dec is None else dec[0].decode(dec[1], message.data)
            by_topic[channel.topic].append((message.log_time, msg))
    if result is not None:
        assert counts == result.messages
        first = min(t for v in by_topic.values() for t, _ in v[:1])
        assert first == result.start_unix_ns == utc_unix_ns(result.start_gps_ns)
        last = max(t for v in by_topic.values() for t, _ in v[-1:])
        assert last == result.end_unix_ns == utc_unix_ns(result.end_gps_ns)
    assert {t: len(v) for t, v in by_topic.items()} == counts
    for topic, msgs in by_topic.items():
        times = [t for t, _ in msgs]
        assert times == sorted(times), f"{topic}: log times out of order"
        if topic not in ("/clock", "/latency"):
            stamps = [m["timestamp"]["seconds"] * NS + m["timestamp"]["nanos"] for _, m in msgs]
            assert stamps == times, topic  # timestamp = log time
    meta = metadata["mls.session"]
    leaps = meta["gps_minus_utc_s"]
    assert meta["session"] == session.name and meta["time_base"] == (
        "UTC, Unix ns (leap seconds from the project's table: GPS − UTC = "
        f"{leaps.replace(' ', ', then ')} s during this session)"
    )
    ref = frames.LocalFrame(*(float(meta[f"lgf_reference_{k}"]) for k in ("lat_deg", "lon_deg", "height_m")))

    # the fixes: the session's INS epochs (those timed by the INS at their own time; those timed
    # by the clock model may be re-timed)
    epochs, clock_timed = {}, 0
    for d in (env.payload for env in iter_messages(session, {"/ins/nav"})):
        keys = ("time_gps_ns", "lat_deg", "lon_deg", "height_m", "roll_deg", "pitch_deg", "heading_deg")
        if any(d.get(k) is None for k in keys):
            continue
        clock_timed += d.get("time_source") == "clock"
        if d.get("time_source") != "clock":  # at the epoch's time in UTC Unix ns
            epochs.setdefault(utc_unix_ns(d["time_gps_ns"]), (d["lat_deg"], d["lon_deg"], d["height_m"]))
            assert str(frames.leap_seconds_at_gps_ns(d["time_gps_ns"])) in leaps.split()
    fixes = by_topic["/vessel/fix"]
    found = [epochs.get(t) for t, _ in fixes]
    assert len(epochs) <= len(fixes) <= len(epochs) + clock_timed
    assert sum(x is None for x in found) <= clock_timed
    for (_, m), want in zip(fixes, found):
        assert m["frame_id"] == "vessel"
        if want is not None:
            assert (m["latitude"], m["longitude"], m["altitude"]) == want
    # the poses: lgf_enu → vessel at every fix, the ENU of its position; vessel → scanner once
    tf = by_topic["/tf"]
    scanner = [m for _, m in tf if m["child_frame_id"] == "scanner"]
    assert len(scanner) == 1 and scanner[0]["parent_frame_id"] == "vessel"
    poses = [(t, m) for t, m in tf if m["child_frame_id"] == "vessel"]
    assert [t for t, _ in poses] == [t for t, _ in fixes]
    assert all(m["parent_frame_id"] == "lgf_enu" for _, m in poses)
    lat, lon, h = (np.array([m[k] for _, m in fixes]) for k in ("latitude", "longitude", "altitude"))
    ned = ref.to_lgf(lat, lon, h)
    xyz = np.array([[m["translation"][k] for k in "xyz"] for _, m in poses])
    np.testing.assert_allclose(xyz, ned[:, [1, 0, 2]] * [1, 1, -1], atol=1e-6)
    rot = np.array([_matrix(m["rotation"]) for _, m in poses])
    assert np.all(rot[:, 2, 2] > math.cos(math.radians(20)))  # the vessel's z axis is up: upright
    # the clouds: float32 x, y, z, intensity in lgf_enu, within the scanner's reach of the vessel
    lever = np.array([scanner[0]["translation"][k] for k in "xyz"])
    t_pose = np.array([t for t, _ in poses])
    rb, total = ReadBack(by_topic, metadata), 0
    for k, (t, m) in enumerate(by_topic["/lidar/points"]):
        assert m["frame_id"] == "lgf_enu" and m["point_stride"] == 16
        fields = [(f["name"], f["offset"], f["type"]) for f in m["fields"]]
        assert fields == [(n, 4 * i, "FLOAT32") for i, n in enumerate(("x", "y", "z", "intensity"))]
        assert len(m["data"]) % 16 == 0 and len(m["data"]) > 0
        p, inten = rb.points(k)
        j = int(np.clip(np.searchsorted(t_pose, t), 0, len(t_pose) - 1))
        origin = xyz[j] + rot[j] @ lever  # the scanner at the cloud's time
        dist = np.linalg.norm(p - origin, axis=1)
        assert np.all(np.isfinite(p)) and np.all(inten >= 0)
        assert dist.max() < 119.0 + 10.0, (k, dist.max())  # a window's motion at most 10 m
        total += len(p)
    if result is not None:
        assert total == result.points
    # the alarms: a Log each, at the level of its severity (cleared: INFO)
    logs = [(t, m["level"], m["name"], m["message"]) for t, m in by_topic["/log"]]
    level = {"info": "INFO", "warning": "WARNING", "critical": "ERROR"}
    for d in [e.payload for e in iter_messages(session, {"/events"}) if e.payload.get("event") == "alarm"]:
        raised = d["action"] == "raise"
        text = f"alarm {d['name']} " + (f"raised ({d['severity']})" if raised else "cleared")
        want = (level[d["severity"]] if raised else "INFO", d["device"], f"{text}: {d['message']}")
        assert want in [x[1:] for x in logs], (want, logs)
    # the numbers: the clock state and its code agree; latency per device
    code = {"UNLOCKED": 0, "HOLDOVER": 1, "LOCKED": 2}
    assert all(code[m["state"]] == m["state_code"] for _, m in by_topic["/clock"])
    assert all(isinstance(m, dict) and m for _, m in by_topic["/latency"])
    return rb


# -- a synthetic session ------------------------------------------------------------------------


@dataclass
class Synth:
    session: Path
    t_ns: np.ndarray  # INS epochs
    lat: np.ndarray
    lon: np.ndarray
    h: np.ndarray
    rpy_deg: np.ndarray
    returns: tuple  # every return sent: t_ns, range_m, angle_rad, intensity (duplicates once)
    clock: list  # (expected log time, data) of the /clock records
    events: list  # (expected log time, data)


def _track():
    t_s = np.arange(N_EPOCHS) * 0.1
    heading = np.radians(30.0 + 0.5 * np.sin(t_s))
    s = 2.0 * t_s
    p = np.column_stack([-20 + s * np.cos(heading), -10 + s * np.sin(heading), 0.1 * np.sin(t_s)])
    rpy = np.column_stack(
        [2.0 * np.sin(2 * np.pi * t_s / 5), 1.0 * np.cos(2 * np.pi * t_s / 5), np.degrees(heading)]
    )
    return p, rpy


def _alarm(action: str, name: str, device: str, severity: str, message: str) -> dict:
    return dict(event="alarm", action=action, name=name, device=device, severity=severity, message=message)


def write_session(tmp: Path) -> Synth:
    """30 s at 10 Hz: INS epochs (one without sigmas), a 40-point profile per epoch (five
    before the first epoch and one after the last, one unsynced, one duplicated, a 150-m
    return), 1-Hz /clock and /latency records (the first three logged UNLOCKED, their log
    times FREE_RUN_NS off), events and alarms; session.json's mount and SITE."""
    p, rpy = _track()
    lat, lon, h = REF.to_geodetic(p)
    opts = SessionOptions(flush_s=0.2, disk_warning_bytes=0, disk_critical_bytes=0)
    w = SessionWriter(tmp / "sessions", "synth", opts)
    session = w.start()
    t = G0 + np.arange(N_EPOCHS, dtype=np.int64) * 100_000_000
    sig = np.tile([0.02, 0.03, 0.05], (N_EPOCHS, 1))
    sig[7] = np.nan  # an epoch without its STDPOS

    def submit(topic, payload, gps_ns, unlocked=False, device_ns=None):
        log, state = (gps_ns + FREE_RUN_NS, "UNLOCKED") if unlocked else (gps_ns, "LOCKED")
        w.submit(
            topic, payload, host_ns=H0 + gps_ns - G0, device_ns=device_ns, log_time_ns=log, clock_state=state
        )

    keys = ("lat_deg", "lon_deg", "height_m", "roll_deg", "pitch_deg", "heading_deg")
    for k in range(N_EPOCHS):
        nav = dict(zip(keys, map(float, (lat[k], lon[k], h[k], *rpy[k]))))
        nav.update(time_gps_ns=int(t[k]), time_source="device")
        if np.isfinite(sig[k, 0]):
            nav.update(sigma_north_m=sig[k, 0], sigma_east_m=sig[k, 1], sigma_down_m=sig[k, 2])
        submit("/ins/nav", nav, int(t[k]) + 4_000_000, device_ns=int(t[k]))
    returns = []
    i = np.arange(N_POINTS)
    for k in range(-5, N_EPOCHS):  # profiles before the first epoch and after the last: uncovered
        t0 = int(G0 + k * 100_000_000 + 20_000_000)
        r = (50_000 + 1000 * i).astype(np.uint32)  # 5 … 8.9 m
        r[i % 7 == 0] = 0  # no returns
        if k == 50:
            r[3] = 1_500_000  # 150 m: beyond the scanner's window
        inten = (100 + i + max(k, 0)).astype(np.uint16)
        synced = k != 100  # one packet without a PPS-locked time tag
        (d,) = encode_profile(k % 65536, t0, DT_NS, 0, DANGLE_UDEG, r, inten, pps_locked=synced)
        recv = t0 + N_POINTS * DT_NS + 5_000_000
        for _ in range(2 if k == 120 else 1):  # a duplicated datagram
            submit("/lidar/raw", d, recv)
        tt = t0 + i * DT_NS if synced else recv - (N_POINTS - 1 - i) * DT_NS
        ok = (r > 0) & (r <= 1_190_000)
        returns.append((tt[ok], r[ok] * 1e-4, np.radians(i[ok] * 9.0), inten[ok].astype(float)))
    ret = tuple(np.concatenate([x[j] for x in returns]) for j in range(4))
    clock = []
    for j in range(-2, 31):  # 1 Hz; the first three logged UNLOCKED by a free-running clock
        gps, unlocked = G0 + j * NS + 300_000_000, j < 1
        data = dict(state="UNLOCKED" if unlocked else "LOCKED", jitter_rms_us=20.0, jitter_max_us=48.5)
        data.update(offset_ns=(G0 - H0) + (FREE_RUN_NS if unlocked else 10 * j), steps=0, last_edge_age_s=0.3)
        data.update(drift_ppm=None if unlocked else 0.1 * j, error_bound_us=None if unlocked else 15.0 + j)
        data.update(edges_in_window=max(j, 0), pps={"time_latency_ms": 52.0 + j})
        submit("/clock", data, gps, unlocked)
        clock.append((gps, data))
        same = dict(sync="ok", n=10 * j, latency_sigma_ms=1.5, latency_p99_ms=None, records=100 * j)
        latency = {
            name: dict(same, device=name, latency_mean_ms=base + 0.01 * j, rate_hz=rate)
            for name, base, rate in (("ins", 4.9, 100.0), ("profiler", 3.0, 10.0))
        }
        submit("/latency", latency, gps + 1_000_000, unlocked)
    marks = dict(pass_id=20240709001, source="can:marks")
    lock = {"event": "clock_state", "from": "UNLOCKED", "to": "LOCKED", "error_bound_us": 15.9}
    jump = _alarm("raise", "latency_jump", "profiler", "warning", "latency 28.1 ms, baseline 8.0 ms")
    events = [
        (G0 - 1_500_000_000, True, {"event": "session_start", "session": session.name, "pid": 1}),
        (G0 - 1_000_000_000, True, _alarm("raise", "data_gap", "ins", "critical", "no record for 0.58 s")),
        (G0 + 300_000_000, False, lock),
        (
            G0 + 500_000_000,
            False,
            _alarm("clear", "data_gap", "ins", "critical", "first record after 1.91 s"),
        ),
        (G0 + 5 * NS, False, {"event": "pass_start", **marks}),
        (G0 + 10 * NS, False, jump),
        (G0 + 12 * NS, False, _alarm("raise", "disk_low", "log", "info", "9.5 GiB free")),
        (G0 + 15 * NS, False, {"event": "consumer_failed", "consumer": "guidance", "error": "ValueError: x"}),
        (G0 + 16 * NS, False, {"event": "disconnected", "device": "profiler", "detail": "udp closed"}),
        (G0 + 20 * NS, False, {"event": "pass_end", **marks}),
        (G0 + 30 * NS, False, {"event": "session_end", "reason": "SIGTERM"}),
    ]
    for gps, unlocked, data in events:
        submit("/events", data, gps, unlocked)
    w.close()
    (session / "session.json").write_text(json.dumps({"vessel": "synth", "mount": MOUNT}))
    (session / "site.yaml").write_text(SITE)
    return Synth(session, t, lat, lon, h, rpy, ret, clock, [(g, d) for g, _, d in events])


@pytest.fixture(scope="module")
def synth(tmp_path_factory) -> Synth:
    return write_session(tmp_path_factory.mktemp("foxglove"))


def _expected_clouds(s: Synth, rate_hz: float, cap: int):
    """The clouds the export must write, computed here: returns in 1/rate windows of GPS time,
    sorted, those outside the trajectory left out, every k-th kept, georeferenced by calib."""
    rpy = np.radians(s.rpy_deg)
    traj = Trajectory.from_geodetic(frames.gps_ns_to_seconds(s.t_ns), s.lat, s.lon, s.h, rpy, REF)
    mount = Mount(MOUNT["lever_arm_m"], *np.radians([MOUNT["nominal_deg"], MOUNT["boresight_apriori_deg"]]))
    t, rng, ang, inten = s.returns
    period = round(NS / rate_hz)
    out = []
    for k in np.unique(t // period):
        sel = np.flatnonzero(t // period == k)
        sel = sel[np.argsort(t[sel], kind="stable")]
        last = int(t[sel[-1]])
        sel = sel[(t[sel] >= s.t_ns[0]) & (t[sel] <= s.t_ns[-1])]
        if not sel.size:
            continue
        sel = sel[:: math.ceil(sel.size / cap)]
        x_ned = georeference(frames.gps_ns_to_seconds(t[sel]), rng[sel], ang[sel], traj, mount)
        out.append((last, np.column_stack([x_ned[:, 1], x_ned[:, 0], -x_ned[:, 2]]), inten[sel]))
    return out


@pytest.mark.parametrize("cap", [50_000, 100])
def test_the_export_reads_back_with_its_schemas_and_the_session_s_values(synth, tmp_path, cap):
    s = synth
    out = tmp_path / "out" / "session.mcap"
    res = export_foxglove(s.session, out, cloud_rate_hz=2.0, max_points_per_cloud=cap)
    rb = check_foxglove_file(out, s.session, res)
    assert sorted(p.name for p in out.parent.iterdir()) == ["session.mcap"]  # no temporary left
    m = rb.messages
    # counts: every epoch, the mount once, every record
    clouds = _expected_clouds(s, 2.0, cap)
    counts = [N_EPOCHS, N_EPOCHS + 1, len(clouds), len(s.events), len(s.clock), len(s.clock)]
    assert res.messages == dict(zip(TOPICS, counts))
    assert res.epochs == N_EPOCHS and res.packets == N_EPOCHS + 5  # the duplicate once
    assert (res.start_gps_ns, res.end_gps_ns) == (G0 - 1_700_000_000, G0 + 30 * NS + 301_000_000)
    assert (res.start_unix_ns, res.end_unix_ns) == (res.start_gps_ns + UNIX, res.end_gps_ns + UNIX)
    # the times: UTC as Unix ns, the real date in Foxglove; GPS − UTC = 18 s in the metadata
    assert dt.datetime.fromtimestamp(m["/vessel/fix"][0][0] // NS, dt.UTC) == frames.gps_ns_to_utc(G0)
    meta = rb.metadata["mls.session"]  # time_base "…: GPS − UTC = 18 s during this session)"
    assert meta["gps_minus_utc_s"] == "18"
    # the fixes: the session's epochs, their sigmas as an ENU covariance
    fix = [x for _, x in m["/vessel/fix"]]
    assert [t for t, _ in m["/vessel/fix"]] == [int(g) + UNIX for g in s.t_ns]  # their epochs in UTC
    assert [(f["latitude"], f["longitude"], f["altitude"]) for f in fix] == list(zip(s.lat, s.lon, s.h))
    assert fix[0]["position_covariance_type"] == "DIAGONAL_KNOWN"
    np.testing.assert_allclose(fix[0]["position_covariance"], np.diag([0.03**2, 0.02**2, 0.05**2]).ravel())
    assert fix[7]["position_covariance_type"] == "UNKNOWN" and fix[7]["position_covariance"] == [0.0] * 9
    # the poses: R = NED→ENU · R_b^n · FRD→FLU, the bow along the heading, z up
    ned_to_enu, frd_to_flu = np.array([[0, 1, 0], [1, 0, 0], [0, 0, -1.0]]), np.diag([1.0, -1, -1])
    poses = [x for _, x in m["/tf"] if x["child_frame_id"] == "vessel"]
    rpy = np.radians(s.rpy_deg)
    for k in (0, 37, 299):
        r_b_n = frames.attitude_matrix(*rpy[k])
        np.testing.assert_allclose(_matrix(poses[k]["rotation"]), ned_to_enu @ r_b_n @ frd_to_flu, atol=1e-12)
        bow = _matrix(poses[k]["rotation"]) @ [1, 0, 0]  # its azimuth: the heading, from north
        assert math.degrees(math.atan2(bow[0], bow[1])) == pytest.approx(s.rpy_deg[k, 2], abs=3.0)
    (mount_tf,) = [x for t, x in m["/tf"] if x["child_frame_id"] == "scanner"]
    assert m["/tf"][0][1]["child_frame_id"] == "scanner" and m["/tf"][0][0] == s.t_ns[0] + UNIX
    np.testing.assert_allclose([mount_tf["translation"][k] for k in "xyz"], [0.35, -0.85, 1.65])
    r_s_b = frames.mount_matrix(np.radians(MOUNT["boresight_apriori_deg"]), np.radians(MOUNT["nominal_deg"]))
    np.testing.assert_allclose(_matrix(mount_tf["rotation"]), frd_to_flu @ r_s_b, atol=1e-12)
    # the clouds: where georeference puts the returns, at the time of their window's last return
    assert [t for t, _ in m["/lidar/points"]] == [c[0] + UNIX for c in clouds]
    for k, (_, xyz_want, inten_want) in enumerate(clouds):
        xyz, inten = rb.points(k)
        assert len(xyz) <= cap
        np.testing.assert_allclose(xyz, xyz_want, atol=1e-4)  # float32 offsets from a metre origin
        np.testing.assert_array_equal(inten, inten_want)
    n_returns = sum(len(c[1]) for c in clouds)
    assert res.points == n_returns and (res.returns == n_returns) == (cap == 50_000)
    if cap == 100:  # 5 profiles of 34 returns per window: every 2nd kept
        assert {len(rb.points(k)[0]) for k in range(1, len(clouds) - 1)} == {85}
    # warnings: the 150-m return, the returns outside the trajectory
    uncovered = int(np.sum((s.returns[0] < s.t_ns[0]) | (s.returns[0] > s.t_ns[-1])))
    assert res.warnings == [
        "1 returns outside the scanner's range window 0.3…119 m left out",
        f"{uncovered} returns outside the trajectory (before its first epoch, after its last, in a gap) left out",
    ]
    # the records: unlocked ones re-timed by the locked ones; the clock's numbers
    assert [t for t, _ in m["/clock"]] == [g + UNIX for g, _ in s.clock]
    c = [x for _, x in m["/clock"]]
    assert [x["state_code"] for x in c[:4]] == [0, 0, 0, 2]
    assert c[0]["offset_drift_us"] is None and c[3]["offset_drift_us"] == 0.0
    assert c[13]["offset_drift_us"] == pytest.approx(0.1) and c[13]["error_bound_us"] == 26.0
    assert c[13]["pps_time_latency_ms"] == 63.0
    lat_msgs = [x for _, x in m["/latency"]]
    assert lat_msgs[13]["ins"]["latency_mean_ms"] == pytest.approx(4.9 + 0.11)
    assert lat_msgs[13]["profiler"]["rate_hz"] == 10.0 and lat_msgs[13]["profiler"]["records"] == 1100
    # the events: at their (re-timed) time, alarms at their severity's level
    logs = [(t, x["level"], x["name"], x["message"]) for t, x in m["/log"]]
    assert [t for t, *_ in logs] == [g + UNIX for g, _ in s.events]
    assert [f"{lv} {name}" for _, lv, name, _ in logs] == [
        *("INFO daemon", "ERROR ins", "INFO clock", "INFO ins", "INFO can:marks", "WARNING profiler"),
        *("INFO log", "ERROR daemon", "WARNING profiler", "INFO can:marks", "INFO daemon"),
    ]
    assert logs[1][3] == "alarm data_gap raised (critical): no record for 0.58 s"
    assert logs[2][3] == "clock UNLOCKED -> LOCKED (error bound 15.9 us)"
    assert logs[4][3] == "pass_start: pass_id=20240709001, source=can:marks"
    assert meta["mount_lever_arm_m"] == "0.3500 0.8500 -1.6500"


def test_gps_to_unix_ns_subtracts_the_leap_seconds_and_holds_an_inserted_second():
    midnight = dt.datetime(2017, 1, 1, tzinfo=dt.UTC)  # GPS − UTC 17 → 18 s
    step, midnight = frames.utc_to_gps_ns(midnight), int(midnight.timestamp()) * NS
    got = [gps_to_unix_ns(step + d) for d in (-NS - 1, -NS, -1, 0, 7)]
    assert got == [(midnight - 1, 17)] * 3 + [(midnight, 18), (midnight + 7, 18)]  # 23:59:60 held
    assert gps_to_unix_ns(G0) == (G0 + UNIX, 18) and gps_to_unix_ns(0) == (GPS_EPOCH_UNIX_S * NS, 0)


def test_a_session_without_site_file_or_records_exports_in_the_trajectory_s_lgf(tmp_path):
    from tests.office.jobs.test_export import _write_session

    session, *_ = _write_session(tmp_path, marks=False)  # 601 epochs, 600 profiles, session.json's mount
    res = export_foxglove(session, tmp_path / "a.mcap", cloud_rate_hz=1.0)
    rb = check_foxglove_file(tmp_path / "a.mcap", session, res)
    assert [res.messages[t] for t in TOPICS] == [601, 602, 60, 0, 0, 0]
    assert res.points == 600 * 16  # 16 returns a profile; the last one after the last epoch
    meta = rb.metadata["mls.session"]
    assert meta["mount_lever_arm_m"] == "0.3500 0.8500 -1.6500" and meta["lgf_reference_height_m"] != "0.0"


def test_an_existing_file_bad_rates_and_errors_are_refused_and_leave_no_file(synth, tmp_path, monkeypatch):
    out = tmp_path / "s.mcap"
    out.write_bytes(b"keep")
    with pytest.raises(OutputError, match=r"s\.mcap: --foxglove: the file exists; add --force to replace it"):
        export_foxglove(synth.session, out)
    assert out.read_bytes() == b"keep"
    res = export_foxglove(synth.session, out, force=True, cloud_rate_hz=0.5)
    assert res.messages["/lidar/points"] == 15 and out.stat().st_size > 10_000  # 2-s windows over 30 s
    with pytest.raises(OutputError, match="names a file, but this is a directory"):
        export_foxglove(synth.session, tmp_path)

    import office.jobs.foxglove as fox

    def boom(*a, **k):
        raise KeyboardInterrupt  # Ctrl-C while the file is written

    monkeypatch.setattr(fox, "_metadata", boom)
    with pytest.raises(KeyboardInterrupt):
        export_foxglove(synth.session, tmp_path / "new.mcap")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.mcap"]  # no half file, no temporary
    with pytest.raises(ExportError, match="cloud rate 0.0 Hz: expected 0.01 … 1000"):
        export_foxglove(synth.session, tmp_path / "a.mcap", cloud_rate_hz=0.0)
    with pytest.raises(ExportError, match="no such session directory"):
        export_foxglove(tmp_path / "nope", tmp_path / "a.mcap")


def test_the_cli_writes_only_the_mcap_with_foxglove_alone(synth, tmp_path):
    from cli.app import app

    runner, out = CliRunner(), tmp_path / "cli.mcap"
    args = ["export", str(synth.session), "--foxglove", str(out), "--cloud-rate-hz", "1"]
    res = runner.invoke(app, args, env={"COLUMNS": "200"})
    assert res.exit_code == 0, res.output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cli.mcap"]
    text = " ".join(res.stdout.split())
    for topic, schema in SCHEMAS.items():
        assert f"{topic} │ {schema}" in text
    assert "/lidar/points │ foxglove.PointCloud │ 30" in text
    assert f"{2 * N_EPOCHS + 1 + 30 + 11 + 2 * 33:,} messages on 6 channels, 32.0 s from" in text
    rb = check_foxglove_file(out, synth.session)
    assert len(rb.messages["/lidar/points"]) == 30
    assert "warning: 1 returns outside the scanner's range window" in res.stderr
    again = runner.invoke(app, ["export", str(synth.session), "--foxglove", str(out)])
    assert again.exit_code == 1 and again.stderr.strip() == (
        f"error: {out}: --foxglove: the file exists; add --force to replace it"
    )
    none = runner.invoke(app, ["export", str(synth.session)])
    assert none.exit_code == 1 and "nothing to write: give --bundle DIR" in none.stderr
