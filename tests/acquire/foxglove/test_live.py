"""Foxglove live (issue 28): the feed behind the SDK's real WebSocket server, a WebSocket client
subscribed to every channel it advertises. A vessel sails north past a scanner's returns; the
client must receive each channel, with the values the records carried: the fix, the vessel's pose
in the LGF, the mount, clouds whose points are the returns georeferenced independently (the whole
trajectory, :func:`calib.core.georef.georeference`), the events, the clock and the latency."""

from __future__ import annotations

import asyncio
import json
import time

import numpy as np
import pytest
from scipy.spatial import cKDTree

from acquire.foxglove import frames as ff
from acquire.foxglove.channels import TOPICS, Channels
from acquire.foxglove.live import LiveFeed, LiveOptions
from calib.core import frames
from calib.core.georef import Mount, georeference
from calib.core.trajectory import Trajectory
from drivers.hydrins.nav import NavRecord
from drivers.zf.codec import Profile
from tests.foxglove_client import FoxgloveClient

T0_NS = 1_400_000_000 * 10**9  # GPS ns, 2024
NAV_HZ, PROFILE_HZ, POINTS = 20, 50, 400
FRAME = frames.LocalFrame(45.5, -73.55, 0.0)
MOUNT = Mount(
    lever_arm_m=[0.5, -0.2, -1.5], nominal_rad=np.radians([0.0, 0.0, 90.0]), boresight_rad=[0.01, -0.02, 0.03]
)
CAP = 300  # points per cloud: the feed must thin the 400 × 25 returns of a 0.5-s window


class Vessel:
    """North at 2 m/s with a gentle roll; its epochs' geodetic positions in FRAME's LGF."""

    def __init__(self) -> None:
        self.epochs: list[NavRecord] = []

    def nav(self, k: int) -> NavRecord:
        t = k / NAV_HZ
        lat, lon, h = FRAME.to_geodetic(np.array([[2.0 * t, 5.0, -1.0]]))
        rec = NavRecord(
            "nmea",
            gps_ns=T0_NS + k * 10**9 // NAV_HZ,
            lat_deg=float(lat[0]),
            lon_deg=float(lon[0]),
            height_m=float(h[0]),
            roll_rad=0.02 * np.sin(t),
            pitch_rad=-0.01,
            heading_rad=0.05,
            v_north_m_s=2.0,
            v_east_m_s=0.0,
            sigma_north_m=0.02,
            sigma_east_m=0.03,
            sigma_down_m=0.05,
        )
        self.epochs.append(rec)
        return rec

    def trajectory(self) -> Trajectory:
        e = self.epochs
        rpy = [[r.roll_rad, r.pitch_rad, r.heading_rad] for r in e]
        t = [r.gps_ns / 1e9 for r in e]
        return Trajectory.from_geodetic(
            t, [r.lat_deg for r in e], [r.lon_deg for r in e], [r.height_m for r in e], rpy, FRAME
        )


def profile(j: int) -> Profile:
    t0 = T0_NS + j * 10**9 // PROFILE_HZ
    gps = t0 + np.arange(POINTS, dtype=np.int64) * (10**9 // PROFILE_HZ // POINTS)
    angle = np.linspace(0.0, 2 * np.pi, POINTS, endpoint=False)
    rng = 8.0 + 4.0 * np.abs(np.sin(angle))
    rng[::7] = np.nan  # no return
    rng[1::50] = 150.0  # beyond the window: left out
    return Profile(j, gps, angle, rng, np.full(POINTS, 1000 + j % 7, np.uint16))


def events_and_status(feed: LiveFeed, now_ns: int) -> None:
    feed.feed(
        "event",
        {
            "event": "alarm",
            "action": "raise",
            "name": "ins_silent",
            "device": "ins",
            "severity": "critical",
            "message": "no data",
        },
        now_ns,
    )
    clock = {"state": "LOCKED", "offset_ns": 123_456, "error_bound_us": 1.5, "gps_ns": now_ns, "pps": {}}
    feed.offer("clock", json.dumps(clock).encode(), False, 0)
    latency = {"ins": {"sync": "pps", "latency_mean_ms": 4.0, "n": 10}, "profiler": {"latency_mean_ms": 1.0}}
    feed.offer("metrics", json.dumps({"latency": latency, "cpu_s": 1.0}).encode(), False, 0)


async def sail(feed: LiveFeed, vessel: Vessel, port: int, deadline_s: float) -> FoxgloveClient:
    """Feed 0.1 s of the survey at a time until the client has every channel and 3 clouds."""
    client = await FoxgloveClient.connect(f"ws://127.0.0.1:{port}")
    end = time.monotonic() + deadline_s
    k = j = 0
    try:
        while time.monotonic() < end:
            await client.poll(0.05)
            if client.topics() == set(TOPICS) and len(client.messages["/lidar/points"]) >= 3:
                return client
            for _ in range(NAV_HZ // 10):
                rec = vessel.nav(k)
                feed.feed("nav", rec, rec.gps_ns)
                k += 1
            for _ in range(PROFILE_HZ // 10):
                p = profile(j)
                feed.feed("profile", p, int(p.gps_ns[-1]))
                j += 1
            if k % NAV_HZ == 0:
                events_and_status(feed, vessel.epochs[-1].gps_ns)
        raise AssertionError(f"in {deadline_s} s the client had only {sorted(client.topics())}")
    except BaseException:
        await client.close()
        raise


@pytest.fixture(scope="module")
def received():
    import foxglove

    context = foxglove.Context()
    feed = LiveFeed(
        Channels(context, ["ins", "profiler"]),
        LiveOptions(frame=FRAME, mount=MOUNT, max_points_per_cloud=CAP),
    )
    server = foxglove.start_server(host="127.0.0.1", port=0, context=context)
    vessel = Vessel()

    async def run():
        client = await sail(feed, vessel, server.port, deadline_s=60.0)
        await client.close()
        return client

    try:
        yield asyncio.run(run()), vessel, feed
    finally:
        server.stop()


def _transforms(client: FoxgloveClient, child: str) -> list[tuple[int, dict]]:
    return [(t, m) for t, m in client.messages["/tf"] if m["child_frame_id"] == child]


def test_every_channel_is_advertised_with_the_exports_schemas(received):
    from acquire.foxglove.channels import SCHEMAS

    client, _, _ = received
    advertised = {c["topic"]: c["schemaName"] for c in client.channels.values()}
    assert set(advertised) == set(TOPICS)
    for topic in ("/vessel/fix", "/tf", "/lidar/points", "/log"):
        assert advertised[topic] == SCHEMAS[topic]


def test_the_fix_and_the_pose_are_the_epochs_at_most_ten_per_second(received):
    client, vessel, _ = received
    by_time = {ff.gps_to_unix_ns(r.gps_ns)[0]: r for r in vessel.epochs}
    fixes = client.messages["/vessel/fix"]
    for log_ns, fix in fixes:
        rec = by_time[log_ns]
        assert (fix["latitude"], fix["longitude"], fix["altitude"]) == (
            rec.lat_deg,
            rec.lon_deg,
            rec.height_m,
        )
        assert fix["position_covariance"][:5:4] == pytest.approx([0.03**2, 0.02**2])  # ENU: east first
    times = np.array([t for t, _ in fixes])
    assert np.all(np.diff(times) >= 10**8 - 1)  # 20-Hz epochs, at most 10 poses a second
    poses = _transforms(client, ff.VESSEL_FRAME)
    assert poses
    traj = vessel.trajectory()
    for log_ns, tf in poses:
        rec = by_time[log_ns]
        p_ned = FRAME.to_lgf([rec.lat_deg], [rec.lon_deg], [rec.height_m])[0]
        xyz = [tf["translation"][a] for a in "xyz"]
        np.testing.assert_allclose(xyz, [p_ned[1], p_ned[0], -p_ned[2]], atol=1e-9)
        q = tf["rotation"]
        i = int(np.searchsorted(traj.t_gps_s, rec.gps_ns / 1e9))
        _, q_expected = ff.vessel_pose_enu(p_ned[None], traj.r_b_n[i : i + 1])
        np.testing.assert_allclose([q["x"], q["y"], q["z"], q["w"]], q_expected[0], atol=1e-12)


def test_the_mount_is_sent_again_every_second(received):
    client, _, _ = received
    mounts = _transforms(client, ff.SCANNER_FRAME)
    xyz, q = ff.scanner_pose_flu(MOUNT.lever_arm_m, MOUNT.r_s_b)
    assert len(mounts) >= 2
    for _, tf in mounts:
        np.testing.assert_allclose([tf["translation"][a] for a in "xyz"], xyz, atol=1e-12)
        np.testing.assert_allclose([tf["rotation"][a] for a in "xyzw"], q, atol=1e-12)
    assert np.all(np.diff([t for t, _ in mounts]) >= 10**9)


def test_the_clouds_are_the_returns_georeferenced_thinned_under_the_cap(received):
    client, vessel, feed = received
    traj = vessel.trajectory()
    profiles = [profile(j) for j in range(len(vessel.epochs) * PROFILE_HZ // NAV_HZ)]
    t = np.concatenate([p.gps_ns for p in profiles])
    r = np.concatenate([p.range_m for p in profiles])
    a = np.concatenate([p.scan_angle_rad for p in profiles])
    ok = np.isfinite(r) & (r <= 119.0) & ~traj.uncovered(t / 1e9)
    truth = ff.enu_from_ned(georeference(t[ok] / 1e9, r[ok], a[ok], traj, MOUNT))
    tree = cKDTree(truth)
    clouds = client.messages["/lidar/points"]
    for k, (_, msg) in enumerate(clouds):
        rec = np.frombuffer(msg["data"], ff.POINT_DTYPE)
        pos = msg["pose"]["position"]
        xyz = np.column_stack([rec["x"], rec["y"], rec["z"]]).astype(float) + [pos["x"], pos["y"], pos["z"]]
        assert 0 < len(rec) <= CAP, k
        dist, _ = tree.query(xyz)
        assert dist.max() < 2e-4, (k, dist.max())  # float32 offsets from the cloud's pose
        assert set(np.unique(rec["intensity"])) <= {float(1000 + i) for i in range(7)}
    assert feed.stride > 1  # 10,000 returns a window for a cap of 300


def test_events_clock_and_latency_reach_their_channels(received):
    client, _, _ = received
    logs = [m for _, m in client.messages["/log"]]
    alarm = next(m for m in logs if "ins_silent" in m["message"])
    assert (alarm["level"], alarm["name"]) == ("ERROR", "ins")
    clock = client.messages["/clock"][0][1]
    assert (clock["state"], clock["state_code"], clock["error_bound_us"]) == ("LOCKED", 2, 1.5)
    assert clock["offset_drift_us"] == 0.0  # the first LOCKED record is the zero
    latency = client.messages["/latency"][0][1]
    assert latency["ins"]["latency_mean_ms"] == 4.0 and latency["ins"]["sync"] == "pps"
    assert latency["profiler"]["latency_mean_ms"] == 1.0


def test_without_a_subscriber_no_cloud_is_built_and_without_a_mount_none_ever():
    import foxglove

    context = foxglove.Context()  # no sink at all: nobody subscribed
    feed = LiveFeed(Channels(context, []), LiveOptions(frame=FRAME, mount=MOUNT))
    vessel = Vessel()
    for k in range(40):
        rec = vessel.nav(k)
        feed.feed("nav", rec, rec.gps_ns)
    for j in range(100):
        feed.feed("profile", profile(j), None)
    assert feed.clouds.pending == {} and feed.clouds.returns == 0
    assert feed.ch.counts["/vessel/fix"] == 20  # the fix still counted: cheap, 10 Hz

    unmounted = LiveFeed(Channels(context, []), LiveOptions(frame=FRAME))
    unmounted.feed("nav", vessel.epochs[0], vessel.epochs[0].gps_ns)
    for j in range(10):
        unmounted.feed("profile", profile(j), None)
    assert unmounted.clouds.pending == {}
    assert unmounted.ch.counts["/log"] == 1  # said once: no mount in the vessel config
