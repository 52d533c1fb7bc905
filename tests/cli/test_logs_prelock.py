"""``mls logs info`` on a session whose first records were stamped before the PPS lock with a host
clock 41 days behind GPS (issue 26): the span is GPS time only, the host-time records are counted
apart, and the on-disk marks stay readable the old way (UNLOCKED)."""

from __future__ import annotations

import json

from typer.testing import CliRunner

from acquire.log.read import iter_messages
from acquire.log.schema import FLAG_HOLDOVER, FLAG_HOST_TIME, FLAG_LOCKED, RAW_HEADER, decode, encode_json
from acquire.log.session import SessionOptions
from acquire.log.sessionlog import SessionWriter
from acquire.timing.clock import HOST_TIME_STATE, ClockModel, ClockState, GpsEstimate
from acquire.timing.timekeeper import ClockCache
from cli.app import app

NS = 1_000_000_000
GPS0 = 1_400_000_000 * NS
HOST_BEHIND_NS = 41 * 86_400 * NS  # the host clock 41 days behind GPS
LOCK_HOST_NS = 10 * NS  # the PPS fit from here on


class Clock:
    """Before LOCK_HOST_NS: no PPS fit, the host's clock (41 days behind); then LOCKED."""

    def to_gps(self, host_ns):
        if host_ns < LOCK_HOST_NS:
            return GpsEstimate(GPS0 - HOST_BEHIND_NS + host_ns, ClockState.UNLOCKED, None)
        return GpsEstimate(GPS0 + host_ns, ClockState.LOCKED, 1000)


def _session(tmp_path):
    w = SessionWriter(tmp_path, "survey-1", SessionOptions(flush_s=0.05, compression="none"), clock=Clock())
    sd = w.start()
    for i in range(200):  # INS at 10 Hz over 20 s: 100 before the lock, 100 after
        host = i * NS // 10
        w.submit("/ins/raw", b"$PIXSE,TIME__,120000.000*1F\r\n", host_ns=host)
        w.submit("/ins/nav", {"i": i}, host_ns=host)
    w.close()
    return sd


def test_info_spans_gps_time_and_counts_the_records_before_the_lock(tmp_path):
    sd = _session(tmp_path)
    runner = CliRunner()
    r = runner.invoke(app, ["logs", "info", str(sd), "--json"])
    assert r.exit_code == 0, r.output
    info = json.loads(r.output)
    first, last = info["span_ns"]
    assert (first, last) == (GPS0 + LOCK_HOST_NS, GPS0 + 199 * NS // 10)  # 9.9 s, not 41 days
    assert info["host_time_messages"] == 200
    for topic in ("/ins/raw", "/ins/nav"):
        ch = info["channels"][topic]
        assert ch["messages"] == 200 and ch["host_time"] == 100 and ch["unlocked"] == 100
        assert ch["gaps"] == [] and ch["missing"] == 0
    r = runner.invoke(app, ["logs", "info", str(sd)], env={"COLUMNS": "250"})
    assert r.exit_code == 0, r.output
    assert "(9.9 s of GPS time)" in r.output
    assert "200 message(s) stamped before the PPS lock carry the host's clock" in r.output
    assert "200 before the PPS lock (host time)" in r.output


def test_the_marks_decode_and_an_older_reader_sees_unlocked(tmp_path):
    sd = _session(tmp_path)
    envs = list(iter_messages(sd))
    raw = [e for e in envs if e.topic == "/ins/raw"]
    nav = [e for e in envs if e.topic == "/ins/nav"]
    assert [e.host_time for e in raw] == [True] * 100 + [False] * 100
    assert [e.host_time for e in nav] == [True] * 100 + [False] * 100
    assert {e.clock for e in raw[:100] + nav[:100]} == {"UNLOCKED"}
    # an older reader of the raw header: bit0/bit1 only -> UNLOCKED; bit2 (device tag) untouched
    head = RAW_HEADER.pack(1, FLAG_HOST_TIME, RAW_HEADER.size, 1, 0, 0)
    assert not head[1] & (FLAG_LOCKED | FLAG_HOLDOVER | 0x04)
    # an older JSON reader reads the keys it knows; an older file has no mark: GPS time
    new = json.loads(encode_json(1, 5, None, HOST_TIME_STATE, {"a": 1}))
    assert new == {
        "seq": 1,
        "host_ns": 5,
        "device_ns": None,
        "clock": "UNLOCKED",
        "time_base": "host",
        "data": {"a": 1},
    }
    old = b'{"seq":1,"host_ns":5,"device_ns":null,"clock":"UNLOCKED","data":{}}'
    assert decode("/ins/nav", "json", 7, 7, old).host_time is False
    old_raw = RAW_HEADER.pack(1, 0, RAW_HEADER.size, 1, 5, 0) + b"x"
    env = decode("/ins/raw", "mls.raw.v1", 7, 7, old_raw)
    assert env.host_time is False and env.clock == "UNLOCKED" and env.payload == b"x"


def test_the_clock_cache_says_host_time_until_the_first_pps_fit():
    clock = ClockModel(coarse_offset_ns=-HOST_BEHIND_NS)
    cache = ClockCache(clock)
    assert cache.estimate(0) == (-HOST_BEHIND_NS, HOST_TIME_STATE)
    clock.add_edge(NS, 1_400_000_000)
    cache.invalidate()
    assert cache.estimate(NS)[1] == "UNLOCKED"  # a PPS fit (too few edges to lock): GPS time
