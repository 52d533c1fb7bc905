"""The fast paths ``mls georef`` reads and encodes through, against the plain ones they replace:
a session's datagrams located a MCAP chunk at a time (:func:`acquire.log.indexed.indexed_blocks`)
against one message at a time and against a scan, the navigation's JSON envelopes parsed a chunk
at a time (:func:`office.jobs.sessionread.nav_messages`) against ``iter_messages``, the pass ids
of time-ordered returns, the LAS scan angle, and a tile's bounds taken from laspy's header."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from typer.testing import CliRunner

from acquire.log.indexed import indexed_blocks, indexed_messages, segment_summary
from acquire.log.read import iter_messages
from calib.core import frames
from calib.io.laz import SCAN_ANGLE_UNIT_DEG
from cli.app import app
from office.deliver import chunkjob, lasrecords, sources
from office.deliver.sources import ChunkSpec, Returns
from office.jobs.sessionread import NAV_TOPICS, nav_messages

ARGS = ["--minutes", str(1 / 6), "--rate-scale", "0.01", "--rotate-s", "10"]
ARGS += ["--set", "site.pass_length_m=10", "--set", "motion.pass_gap_s=2"]


@pytest.fixture(scope="module")
def session(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("georef-fast")
    res = CliRunner().invoke(app, ["sim", "session", "--out", str(out), *ARGS], env={"COLUMNS": "250"})
    assert res.exit_code == 0, res.output
    (path,) = [p for p in out.iterdir() if p.is_dir()]
    return path


def _messages(seg: Path, topics: list[str], lo: int | None = None, hi: int | None = None) -> list:
    found = indexed_messages(seg, topics, lo, hi)
    assert found is not None  # a segment closed normally
    return list(found)


def test_blocks_give_the_messages_one_by_one_gives(session):
    for seg in sorted(session.glob("seg-*.mcap")):
        every = list(_messages(seg, ["/lidar/raw", *NAV_TOPICS]))
        assert len(every) > 100
        t = [m.log_time for m in every]
        lo, hi = t[len(t) // 4], t[3 * len(t) // 4]
        for topics in (["/lidar/raw"], list(NAV_TOPICS), ["/lidar/raw", "/ins/nav"]):
            want = [m for m in every if m.topic in topics and lo <= m.log_time < hi]
            assert list(_messages(seg, topics, lo, hi)) == want
            found = indexed_blocks(seg, topics, lo, hi)
            assert found is not None
            channels, blocks = found
            got = []
            for b in blocks:
                for cid, lt, pt, a, z in zip(
                    b.channel_id, b.log_time, b.publish_time, b.data_start, b.data_end, strict=True
                ):
                    topic, encoding = channels[int(cid)]
                    got.append((topic, encoding, int(lt), int(pt), b.records[a:z]))
            assert got == [tuple(m) for m in want]


def test_a_chunk_reads_the_same_datagrams_as_a_scan(session, monkeypatch):
    seg = sorted(session.glob("seg-*.mcap"))[0]
    summary = segment_summary(seg)
    assert summary is not None
    assert segment_summary(seg) is summary
    t0, t1 = int(summary.statistics.message_start_time), int(summary.statistics.message_end_time) + 1
    spec = ChunkSpec(0, t0, t1, segment=str(seg))
    log_t, grams = sources._datagrams(spec)
    scan_t, scan_grams = sources._scanned_datagrams(seg, t0, t1)
    assert log_t.size > 100
    assert np.array_equal(log_t, scan_t)
    assert [bytes(g) for g in grams] == [bytes(g) for g in scan_grams]
    indexed = sources.read_session_chunk(spec)
    monkeypatch.setattr("acquire.log.indexed.indexed_blocks", lambda *a, **k: None)
    scanned = sources.read_session_chunk(spec)
    for name in ("t_gps_ns", "range_m", "scan_angle_rad", "intensity"):
        assert getattr(indexed, name).tobytes() == getattr(scanned, name).tobytes()
    assert indexed.counters == scanned.counters


def test_navigation_messages_are_those_of_iter_messages(session):
    def read(fn):
        seen: list[tuple[float, float | None]] = []
        return list(fn(seen.append)), seen

    plain, plain_progress = read(
        lambda p: [
            (e.topic, e.log_time_ns, e.host_ns, e.clock, e.payload)
            for e in iter_messages(session, set(NAV_TOPICS), lambda d, t: p((d, t)))
        ]
    )
    fast, fast_progress = read(lambda p: nav_messages(session, lambda d, t: p((d, t))))
    assert len(fast) > 100
    assert fast == plain
    assert fast_progress == plain_progress


def test_navigation_falls_back_to_decode_on_a_chunk_it_cannot_parse(session, monkeypatch):
    import office.jobs.sessionread as sessionread

    plain = list(nav_messages(session, None))

    def unparsable(_):
        raise ValueError("not one JSON array")

    monkeypatch.setattr(sessionread, "json", SimpleNamespace(loads=unparsable))
    assert list(nav_messages(session, None)) == plain  # one by one through schema.decode


def _plain_pass_ids(t: np.ndarray, lines: np.ndarray) -> np.ndarray:
    k = np.searchsorted(lines[:, 1], t, side="right") - 1
    inside = (k >= 0) & (t <= lines[np.maximum(k, 0), 2])
    return np.where(inside, lines[np.maximum(k, 0), 0], -1)


def test_pass_ids_of_time_ordered_returns_are_the_searched_ones():
    rng = np.random.default_rng(7)
    for _ in range(500):
        n, m = int(rng.integers(0, 80)), int(rng.integers(1, 6))
        t = rng.integers(0, 100, n).astype(np.int64)
        if rng.random() < 0.8:
            t.sort()
        starts = np.sort(rng.integers(-10, 110, m))  # overlapping lines, equal starts too
        lines = np.stack([rng.integers(1, 9, m), starts, starts + rng.integers(-5, 40, m)], axis=1)
        r = Returns(t, np.zeros(n), np.zeros(n), np.zeros(n, np.uint16))
        assert np.array_equal(chunkjob._pass_ids(r, lines.astype(np.int64)), _plain_pass_ids(t, lines))


def test_scan_angle_units_are_those_of_wrap_pi():
    rng = np.random.default_rng(8)
    edges = [0.0, np.pi / 2, np.pi, 1.5 * np.pi, 2 * np.pi, -0.0, 1e-30, -np.pi, -3.0, 9.0, np.nan]
    for a in (rng.uniform(0, 2 * np.pi, 200_000), rng.uniform(-10, 10, 1000), np.array(edges)):
        f4 = a.astype(np.float32)
        with np.errstate(invalid="ignore"):
            nadir = np.degrees(frames.wrap_pi(np.pi / 2 - f4.astype(float)))
            want = np.round(nadir / SCAN_ANGLE_UNIT_DEG).astype(np.int16)
            got = lasrecords.scan_angle_units(f4)
        assert np.array_equal(got, want)
        d = np.pi / 2 - f4.astype(float)
        assert lasrecords._wrap_pi_in_place(d.copy()).tobytes() == frames.wrap_pi(d).tobytes()


def test_unsynced_packets_are_timed_from_their_receipt(monkeypatch):
    from drivers.zf.codec import FLAG_PPS_LOCKED, FLAG_TIME_VALID
    from drivers.zf.zfp1 import encode_packet

    synced = FLAG_PPS_LOCKED | FLAG_TIME_VALID
    t0, dt, n = 1_300_000_000_000_000_000, 10_000, 50
    grams, log_t, want = [], [], []
    for k, flags in enumerate([synced, FLAG_TIME_VALID, synced, 0, synced]):
        rng = np.arange(1, n + 1, dtype=np.uint32) * 1000
        rng[::7] = 0  # misses
        start = t0 + k * n * dt
        received = start + (n - 1) * dt + 12_345  # the last point's time, plus a latency
        grams.append(
            encode_packet(
                flags=flags,
                profile_counter=k,
                packet_index=0,
                packet_count=1,
                t0_ns=start,
                dt_ns=dt,
                angle0_udeg=1000 * k,
                dangle_udeg=100,
                range_01mm=rng,
                intensity=np.full(n, 7, np.uint16),
            )
        )
        log_t.append(received)
        i = np.flatnonzero(rng > 0)
        want.append(start + i * dt if flags == synced else received - (n - 1 - i) * dt)
    monkeypatch.setattr(sources, "_datagrams", lambda spec: (np.array(log_t, np.int64), grams))
    r = sources.read_session_chunk(ChunkSpec(0, 0, 1, segment="unused"))
    assert r.counters["unsynced_packets"] == 2
    assert np.array_equal(r.t_gps_ns, np.sort(np.concatenate(want), kind="stable"))


def _nav_message(rng, k: int):
    """A random /ins/nav or /events message: synced or timed by the (sometimes unlocked) clock,
    now and then without a pose or a sigma."""
    if rng.random() < 0.1:
        return (
            "/events",
            1000 + k,
            2000 + k,
            str(rng.choice(["LOCKED", "UNLOCKED"])),
            {"kind": "mark", "k": k},
        )
    d = {"time_gps_ns": 10_000 + 7 * k, "time_source": str(rng.choice(["ins", "clock"]))}
    d.update(
        {name: float(rng.normal()) for name in ("lat_deg", "lon_deg", "height_m", "roll_deg", "pitch_deg")}
    )
    d["heading_deg"] = None if rng.random() < 0.05 else float(rng.normal())
    d.update({f"sigma_{n}": float(rng.random()) for n in ("north_m", "east_m", "down_m", "roll_deg")})
    d["sigma_pitch_deg"] = None if rng.random() < 0.2 else 0.01
    return ("/ins/nav", 1000 + k, 2000 + 5 * k, str(rng.choice(["LOCKED", "UNLOCKED"])), d)


@pytest.mark.parametrize("seed", range(5))
def test_navigation_read_in_pieces_is_the_navigation_read_at_once(seed):
    """Cut anywhere, the pieces of a run of messages joined are the piece of the whole run (the
    unlocked epochs' rows renumbered), so the plan may read them on several workers."""
    from office.jobs.sessionread import _collect, _join

    rng = np.random.default_rng(seed)
    messages = [_nav_message(rng, k) for k in range(300)]
    whole = _collect(messages)
    assert whole.unlocked_rows.size > 10 and whole.raw_events and whole.t_ns.size > 200
    cuts = sorted(rng.choice(np.arange(1, len(messages)), 4, replace=False).tolist())
    bounds = [0, *cuts, len(messages)]
    joined = _join([_collect(messages[a:b]) for a, b in zip(bounds[:-1], bounds[1:], strict=True)])
    for name in (
        "t_ns",
        "values",
        "from_clock",
        "unlocked_rows",
        "unlocked_host_ns",
        "sync_host_ns",
        "sync_t_ns",
    ):
        assert np.array_equal(getattr(joined, name), getattr(whole, name), equal_nan=name == "values"), name
    assert joined.raw_events == whole.raw_events


def test_a_session_s_navigation_read_by_a_mapper_is_the_same(session):
    from office.jobs.sessionread import read_nav_and_events

    calls = []

    def mapper(fn, items):
        calls.append(len(items))
        return [fn(x) for x in items]

    nav, events = read_nav_and_events(session, None)
    nav_m, events_m = read_nav_and_events(session, None, mapper)
    assert calls and calls[0] > len(list(session.glob("seg-*.mcap")))  # in pieces
    assert events_m == events
    for name, value in vars(nav).items():
        assert np.array_equal(getattr(nav_m, name), value, equal_nan=True), name
