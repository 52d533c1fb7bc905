"""The mount watch's consumer on synthetic record streams: lines cut by heading and by the pass
marks, the decimation budget and the memory bound, blocks estimated in the worker process and
their agreement with the offline reference (:func:`calib.watch.runner.run_watch`), what is
published (the ``mount`` topic, the ``mount`` checklist section, ``/events``), the alarm raised
once, and bad records ignored."""

from __future__ import annotations

import asyncio
import math
import re

import numpy as np
import pytest

from acquire.alarms import AlarmBook
from acquire.daemon.consumers import ChecklistPublisher
from acquire.watch.blockjob import WatchModel, block_trajectory
from acquire.watch.buffers import PointBuffer, nav_rows
from acquire.watch.consumer import MAX_WAITING_BLOCKS, NAV_KEEP_S, MountWatchConsumer
from acquire.watch.lines import LineCutter
from calib.boresight.pipeline import CalibrationOptions, error_model
from calib.core import frames
from calib.watch.block import site_sigmas
from calib.watch.runner import run_watch
from tests.acquire.watch.records import (
    NS,
    mark_stream,
    merged,
    nav_record,
    nav_stream,
    profile,
    profile_stream,
    track,
)
from tests.waiting import wait_until_async

FRAME = frames.LocalFrame(45.5, -73.55, 0.0)


@pytest.fixture(scope="module")
def montreal():
    from calib.sim.simulate import simulate

    return simulate("montreal", 0)


def _model(sim, boresight_offset_deg=(0.0, 0.0, 0.0)) -> WatchModel:
    """The watch of ``sim`` with the true boresight as the calibration (plus an offset)."""
    site = sim.site
    true = np.radians([sim.truth["boresight_deg"][a] for a in ("roll", "pitch", "yaw")])
    return WatchModel(
        mount=site.mount.with_boresight(true + np.radians(boresight_offset_deg)),
        frame=site.reference,
        wall_azimuth_rad=site.wall_azimuth_rad,
        sigmas=site_sigmas(site),
        error_model=error_model(CalibrationOptions(), site)[0],
    )


def _plain_model() -> WatchModel:
    from calib.boresight.errormodel import ErrorModel
    from calib.core.georef import Mount

    return WatchModel(
        mount=Mount(np.zeros(3), np.zeros(3), np.zeros(3)),
        frame=FRAME,
        wall_azimuth_rad=0.0,
        sigmas={},
        error_model=ErrorModel("gauss_markov", 60.0),
    )


class Recorder:
    """What a consumer publishes: status topics, checklist sections, /events, alarms."""

    def __init__(self) -> None:
        self.topics: list[tuple[str, dict]] = []
        self.events: list[dict] = []
        self.alarms = AlarmBook()
        self.checklist = ChecklistPublisher(lambda topic, data: self.topics.append((topic, data)))

    def consumer(self, model: WatchModel, **kw) -> MountWatchConsumer:
        return MountWatchConsumer(
            model,
            publish=lambda topic, data: self.topics.append((topic, data)),
            alarms=self.alarms,
            log_event=self.events.append,
            **kw,
        )

    def last(self, topic: str) -> dict:
        return [d for t, d in self.topics if t == topic][-1]


def _play(consumer: MountWatchConsumer, items, checklist) -> None:
    """Run the consumer over ``items`` as a daemon tap would hand them; after each record that
    queued a block, wait for the worker (a survey's lines take minutes, a block seconds)."""

    def busy() -> bool:
        task = consumer._task
        return (
            bool(consumer.waiting) or consumer.running is not None or (task is not None and not task.done())
        )

    async def tap():
        for item in items:
            yield item
            await wait_until_async(lambda: not busy(), 120, "the block solve", interval_s=0.005)

    asyncio.run(asyncio.wait_for(consumer.run(tap(), checklist), 120))


# -- lines ------------------------------------------------------------------------------------


def _feed_nav(cutter: LineCutter, stream) -> list:
    lines = []
    for _, _, rec in stream:
        speed = math.hypot(rec.v_north_m_s, rec.v_east_m_s)
        lines += cutter.on_nav(rec.gps_ns / NS, rec.heading_rad, speed)
    return lines


def test_lines_are_cut_by_heading_at_the_turns_and_short_runs_are_ignored():
    stream = track(FRAME, [(30.0, 2.0, 60.0), (210.0, 2.0, 45.0), (300.0, 2.0, 10.0), (30.0, 2.0, 30.0)])
    cutter = LineCutter(min_line_s=20.0)
    lines = _feed_nav(cutter, stream)
    assert [round(math.degrees(ln.heading_rad)) for ln in lines] == [30, 210]
    assert [ln.ended_by for ln in lines] == ["turn", "turn"]
    # the line takes in the turns' first and last 10° (< 1 s at 12°/s)
    assert lines[0].duration_s == pytest.approx(60.0, abs=1.0)
    assert lines[1].duration_s == pytest.approx(45.0, abs=2.0)
    assert all(ln.source == "heading" and ln.pass_id is None for ln in lines)
    assert cutter.ignored >= 1 and cutter.open_since_s is not None  # the 10 s leg; the last is open
    # a stop ends a line, a gap in the navigation too
    cutter = LineCutter(min_line_s=20.0)
    t0 = stream[0][0]
    lines = [ln for k in range(300) for ln in cutter.on_nav(t0 + 0.1 * k, 0.0, 2.0)]
    lines += cutter.on_nav(t0 + 30.1, 0.0, 0.1)
    assert [ln.ended_by for ln in lines] == ["stop"]
    lines = [ln for k in range(300) for ln in cutter.on_nav(t0 + 40 + 0.1 * k, 0.0, 2.0)]
    lines += cutter.on_nav(t0 + 80.0, 0.0, 2.0)
    assert [ln.ended_by for ln in lines] == ["gap"]


def test_a_slow_curve_leaves_the_course_of_the_lines_first_min_line_s():
    """The reference course is the mean of a line's first ``min_line_s``: a heading creeping at 0.5°/s ends the line once
    10° off it, where a running mean would follow the curve for ever."""
    cutter = LineCutter(min_line_s=20.0)
    heading = [0.0] * 200 + [math.radians(0.05 * k) for k in range(1, 1200)]  # 10 Hz
    lines = [ln for k, h in enumerate(heading) for ln in cutter.on_nav(1e9 + 0.1 * k, h, 2.0)]
    assert [ln.ended_by for ln in lines][:1] == ["turn"]
    assert lines[0].duration_s == pytest.approx(40.0, abs=0.5)  # 20 s straight, then 20 s to 10°


def test_a_long_line_is_closed_at_max_line_s_and_the_next_starts_at_once():
    cutter = LineCutter(min_line_s=20.0, max_line_s=100.0)
    lines = [ln for k in range(2500) for ln in cutter.on_nav(1e9 + 0.1 * k, 1.0, 2.0)]
    assert [ln.ended_by for ln in lines] == ["max_line", "max_line"]
    assert lines[1].t_start_s == pytest.approx(lines[0].t_end_s, abs=0.11)


def test_the_pass_marks_cut_the_lines_once_there_is_one():
    stream = track(FRAME, [(30.0, 2.0, 60.0), (210.0, 2.0, 60.0)])
    cutter = LineCutter(min_line_s=20.0)
    t0 = stream[0][0]
    lines = []
    for k, (t, _, rec) in enumerate(stream):  # 10 Hz
        if k == 50:
            assert cutter.on_mark("pass_start", 11) == [] and cutter.mode == "marks"
            assert cutter.on_mark("pass_start", "eleven") == []  # no pass id: nothing changes
        if k == 500:
            lines += cutter.on_mark("pass_end", 12)  # not the open pass: ignored
            lines += cutter.on_mark("pass_end", 11)
        if k == 900:
            lines += cutter.on_mark("pass_start", 12)
        lines += cutter.on_nav(t, rec.heading_rad, 2.0)
    lines += cutter.on_mark("pass_start", 13)  # 12 has no pass_end: it ends where 13 starts
    assert [(ln.pass_id, ln.ended_by, ln.source) for ln in lines] == [
        (11, "pass_end", "marks"),
        (12, "pass_start", "marks"),
    ]
    assert lines[0].t_start_s == pytest.approx(t0 + 4.9) and lines[0].duration_s == pytest.approx(45.0)
    assert math.degrees(lines[0].heading_rad) == pytest.approx(30.0, abs=0.01)
    assert math.degrees(lines[1].heading_rad) == pytest.approx(210.0, abs=1.0)  # a turn of 15 s, then 210°


# -- decimation and memory --------------------------------------------------------------------


def test_the_returns_are_thinned_to_the_budget_and_the_range_window():
    buf = PointBuffer(5000, 2.0, 60.0)
    rng = np.random.default_rng(1)
    n, rate, seconds = 1000, 200.0, 10.0
    t0 = 1_400_000_000 * NS
    for k in range(int(rate * seconds)):
        r = rng.uniform(0.5, 100.0, n)  # about 60 % inside the window
        r[::7] = np.nan  # no return
        t = t0 + round(k / rate * NS) + np.arange(n) * 4000
        assert buf.add(t, r, np.linspace(0, 2 * np.pi, n, endpoint=False)) <= n
    assert buf.kept == pytest.approx(5000 * seconds, rel=0.02) and buf.seen == n * rate * seconds
    (t, r, a), *_ = buf.snapshot()
    assert np.all((r >= 2.0) & (r <= 60.0)) and np.all(np.diff(t) >= 0)
    # the angles kept move from profile to profile (a comb with a rotating phase)
    assert np.unique(np.round(a, 6)).size > 0.5 * n
    # past max_points the stored returns and the budget are halved
    small = PointBuffer(5000, 2.0, 60.0, max_points=20_000)
    for k in range(int(rate * seconds)):
        small.add(t0 + round(k / rate * NS) + np.arange(n) * 4000, np.full(n, 10.0), np.zeros(n))
    assert small.halvings >= 1 and len(small) <= 20_000 and small.scale < 1.0
    small.trim_before(1e12)  # emptied: the full budget again
    assert len(small) == 0 and small.scale > 0.4


def test_a_block_without_returns_is_no_evidence_and_the_buffers_keep_only_what_is_needed():
    rec = Recorder()
    c = rec.consumer(_plain_model(), min_line_s=20.0)
    items = merged(track(FRAME, [(0.0, 2.0, 40.0), (180.0, 2.0, 40.0), (0.0, 2.0, 5.0)]))
    _play(c, items, rec.checklist)
    st = rec.last("mount")
    assert st["blocks"] == 1 and st["blocks_ok"] == 0 and st["alarm"] is None
    assert st["last_block_status"]["status"] == "no returns in the range window"
    assert st["last_block_status"]["lines"] == [1, 2]
    assert st["state"] == "waiting" and st["verdict"].startswith("waiting for a pair of opposite lines")
    assert st["lines"]["mode"] == "heading" and st["lines"]["closed"] == 2
    assert rec.last("checklist")["mount"]["ok"] is None
    assert not rec.alarms.drain()
    assert [e["status"] for e in rec.events] == ["no returns in the range window"]
    # what is kept: the navigation from the first line a later block may take (2 s before it);
    # no return (none lies in the range window)
    assert c.blocks.kept == [1, 2] and c.points.kept == 0
    assert nav_rows(c.nav.snapshot())[0, 0] >= c.lines[1].t_start_s - NAV_KEEP_S
    assert st["counters"]["nav_ignored"] == 0


# -- blocks in the thread, publication, alarm --------------------------------------------------


def test_a_block_whose_estimate_fails_says_where_and_the_watch_goes_on(monkeypatch):
    rec = Recorder()
    c = rec.consumer(_plain_model(), min_line_s=20.0)
    # a corrupt buffer snapshot: the worker process fails on it, in buffers.py
    monkeypatch.setattr(c.points, "snapshot", lambda: [(0.0, 0.0, 0.0)])
    _play(
        c,
        merged(track(FRAME, [(0.0, 2.0, 40.0), (180.0, 2.0, 40.0), (0.0, 2.0, 40.0), (180.0, 2.0, 5.0)])),
        rec.checklist,
    )
    st = rec.last("mount")
    assert st["blocks"] == 2 and st["blocks_ok"] == 0 and st["alarm"] is None  # both blocks: no evidence
    assert re.fullmatch(
        r"failed \(ValueError: [^;]*; buffers\.py:\d+\)", st["last_block_status"]["status"]
    ), st["last_block_status"]


def _montreal_items(sim, marks=True):
    streams = [
        nav_stream(sim.trajectory_observed),
        profile_stream(sim.points, sim.scenario.scanner.profile_rate_hz),
    ]
    if marks:
        streams.append(mark_stream(sim.points))
    return merged(*streams)


def test_blocks_run_in_the_worker_process_and_agree_with_the_offline_watch(montreal):
    import threading

    sim = montreal
    model = _model(sim)
    rec = Recorder()
    c = rec.consumer(model, max_points_per_s=2_000_000, min_line_s=1.0)
    threads = []
    real = c.take

    def take(block, family):
        threads.append(threading.current_thread().name)
        real(block, family)

    c.take = take
    _play(c, _montreal_items(sim), rec.checklist)
    # the offline reference over the same passes (the session's whole trajectory)
    ref = run_watch(
        sim.points,
        sim.trajectory_observed,
        model.mount,
        model.sigmas,
        model.error_model,
        model.wall_azimuth_rad,
    )
    n, n_ok = len(ref.blocks), sum(b.ok for b in ref.blocks)
    assert n >= 2 and n_ok >= 1
    assert threads == ["MainThread"] * n  # the test and the publication in the loop's thread
    st = rec.last("mount")
    assert st["blocks"] == n and st["lines"]["mode"] == "marks" and st["lines"]["closed"] == 6
    assert [b["lines"] for b in rec.events] == [list(b.pass_ids) for b in ref.blocks]
    for blk, ev in zip(ref.blocks, rec.events):
        assert ev["status"] == blk.status
        if blk.ok:
            d_ref, s_ref = np.degrees(blk.delta_rad), np.degrees(blk.sigma_rad)
            assert np.all(np.abs(np.asarray(ev["delta_deg"]) - d_ref) <= 0.2 * s_ref + 1e-4), (
                ev,
                d_ref,
                s_ref,
            )
            assert ev["patches"] == len(blk.patches)
    # steady: a verdict with the three angles, no alarm, the checklist section ok
    assert st["state"] == "steady" and st["verdict"].startswith("mount steady: roll ")
    assert f"({n_ok} block" in st["verdict"] and st["alarm"] is None and st["patches"] > 0
    assert rec.last("checklist")["mount"] == {
        "ok": True,
        "verdict": st["verdict"],
        "blocks": n,
        "blocks_ok": n_ok,
        "statistic": pytest.approx(max(st["statistic"]), abs=1e-3),
        "alarm": None,
    }
    assert not rec.alarms.drain()
    assert st["worker"] == {"busy": False, "running_lines": None, "waiting": 0, "behind": False}
    assert st["schema"] == "mls.mount/1" and st["design"]["shift_deg"] == pytest.approx(0.1)


def test_a_shifted_mount_raises_mount_shift_once_and_it_stays(montreal):
    sim = montreal
    rec = Recorder()
    # the calibration is 0.5° off in roll: as if the mount had rolled by −0.5° since
    c = rec.consumer(_model(sim, (0.5, 0.0, 0.0)), max_points_per_s=2_000_000, min_line_s=1.0)
    _play(c, _montreal_items(sim), rec.checklist)
    events = rec.alarms.drain()
    assert [(e.action, e.alarm.name, e.alarm.device, e.alarm.severity) for e in events] == [
        ("raise", "mount_shift", "mount", "critical")
    ]
    msg = events[0].alarm.message  # MountAlarm.message(): the angle, its size with σ, since when
    assert "roll -0." in msg and "since" in msg
    msg = rec.alarms.get("mount_shift", "mount").message  # refined by the later blocks, not raised again
    assert msg == rec.last("mount")["alarm"]["message"]
    assert rec.alarms.is_active("mount_shift", "mount")
    st = rec.last("mount")
    assert st["state"] == "shift" and st["alarm"]["angles"][0] == "roll"
    assert abs(st["alarm"]["size_deg"][0] + 0.5) < 3 * st["alarm"]["sigma_deg"][0] + 0.01
    assert st["verdict"] == f"MOUNT SHIFT: {msg.removeprefix('mount shift: ')} — recalibrate the mount"
    section = rec.last("checklist")["mount"]
    assert section["ok"] is False and section["alarm"] == msg
    assert st["blocks"] >= 2  # the blocks go on, the alarm is raised once


def test_blocks_that_pile_up_behind_the_worker_are_skipped_and_said(montreal):
    rec = Recorder()
    c = rec.consumer(_plain_model(), min_line_s=20.0)
    items = merged(track(FRAME, [(0.0, 2.0, 25.0), (180.0, 2.0, 25.0)] * 4 + [(0.0, 2.0, 5.0)]))
    for kind, record, gps_ns in items:  # fed without the run loop: nothing takes the blocks
        c.feed(kind, record, gps_ns)
    st = c.state()
    assert st["worker"]["waiting"] == MAX_WAITING_BLOCKS and st["worker"]["behind"] is True
    assert st["counters"]["blocks_skipped"] == 7 - MAX_WAITING_BLOCKS  # 8 lines: 7 blocks
    # the waiting blocks hold their own data; the buffers what the cutter may still take
    assert [(job.line_ids, job.family) for job in c.waiting] == [((6, 7), 1), ((7, 8), 0)]
    assert c.blocks.kept == [6, 7, 8]
    assert nav_rows(c.nav.snapshot())[0, 0] >= c.lines[6].t_start_s - NAV_KEEP_S


def test_bad_records_are_counted_and_ignored(montreal):
    rec = Recorder()
    c = rec.consumer(_plain_model(), min_line_s=20.0)
    good = track(FRAME, [(0.0, 2.0, 30.0)])
    bad_nav = nav_record(good[-1][0] + 1, math.nan, 0.0, 0.0, (0, 0, 0))
    no_time = nav_record(0.0, 45.5, -73.55, 0.0, (0, 0, 0))
    no_time.gps_ns = None
    late = good[5][2]  # not after the last epoch
    t_ns = np.arange(10, dtype=np.int64) + round(good[-1][0] * NS)
    bad_profile = profile(t_ns, np.full(10, 5.0), np.zeros(10))
    bad_profile.range_m = np.full(10, 5, np.int64)  # wrong dtype
    invalid_time = profile(t_ns, np.full(10, 5.0), np.zeros(10))
    invalid_time.time_valid = False
    items = merged(good) + [
        ("nav", bad_nav, 0),
        ("nav", no_time, 0),
        ("nav", late, 0),
        ("nav", "$GPZDA,garbage", 0),
        ("nav", None, None),
        ("profile", bad_profile, 0),
        ("profile", invalid_time, 0),
        ("profile", b"\x00\x01", 0),
        ("event", "pass_start", 0),
        ("event", {"event": "pass_start", "pass_id": "x"}, 0),
        ("event", {"event": "pass_end"}, 0),
        ("event", {"event": "alarm", "name": "mount_shift"}, 0),
        ("weird", object(), 0),
    ]
    _play(c, items, rec.checklist)
    counters = c.state()["counters"]
    assert counters["nav_ignored"] == 5 and counters["profiles_ignored"] == 3
    assert counters["events_ignored"] == 1 and c.cutter.mode == "heading"
    assert c.cutter.open_since_s is not None  # the good line is still open


def test_the_block_trajectory_carries_the_ins_sigma_and_fills_missing_epochs():
    rows = []
    for k, (_, _, r) in enumerate(track(FRAME, [(0.0, 2.0, 5.0)])):
        sig = (math.nan,) * 6 if k % 5 == 0 else (0.02, 0.02, 0.03, 1e-4, 1e-4, 2e-4)
        rows.append((r.gps_ns / NS, r.lat_deg, r.lon_deg, r.height_m, 0.0, 0.0, r.heading_rad, *sig))
    traj = block_trajectory(np.array(rows), FRAME)
    assert traj.has_sigmas and np.allclose(traj.sigma_p_m[:, 2], 0.03)
    assert np.allclose(traj.p_lgf_m[:, 0], 2.0 * (traj.t_gps_s - traj.t_gps_s[0]), atol=1e-3)
    rows = [r[:7] + (math.nan,) * 6 for r in rows]  # no σ at all: the site's
    assert not block_trajectory(np.array(rows), FRAME).has_sigmas
