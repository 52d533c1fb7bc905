"""``acquire.daemon.devices.InsDevice``: how an INS epoch gets its GPS time in the daemon."""

from __future__ import annotations

import datetime as dt
from types import SimpleNamespace

from acquire.daemon.configschema import DeviceConfig
from acquire.daemon.consumers import ConsumerHub
from acquire.daemon.devices import STATUS_HOLD_NS, InsDevice
from acquire.timing.latency import LatencyLimits
from calib.core.frames import utc_to_gps_ns
from drivers.hydrins.nmea_encode import encode_epoch
from tests.acquire.fakedevices import nav_at

NS = 1_000_000_000
G0 = utc_to_gps_ns(dt.datetime.now(dt.UTC)) // NS * NS  # today: NMEA dates from the host
CLOCK_NS = 777  # what the (unlocked) clock model answers: nowhere near the INS time


def _device():
    submitted = []
    ctx = SimpleNamespace(
        submit=lambda topic, payload, **kw: submitted.append((topic, payload)),
        gps_ns=lambda host_ns: CLOCK_NS,
        timekeeper=SimpleNamespace(on_time=lambda gps_s, host_ns: None),
        monitor=SimpleNamespace(observe=lambda *a, **kw: None),
        hub=ConsumerHub(),
    )
    no_gaps = LatencyLimits(gap_ns=10 * STATUS_HOLD_NS)
    dev = InsDevice(DeviceConfig("ins", "ins", protocol="nmea", latency=no_gaps), ctx)
    return dev, submitted


def _without_status(block: bytes) -> bytes:
    """An epoch whose tail (STDHRP … HT_STS, the STATUS sentence among them) was lost."""
    return block[: block.index(b"$PIXSE,STDHRP")]


def test_an_epoch_that_lost_its_status_keeps_the_ins_time_of_the_status_before():
    dev, submitted = _device()
    host0 = 50 * NS
    epochs = [(k, G0 + k * 10_000_000, host0 + k * 10_000_000) for k in range(4)]
    for k, gps, host in epochs:
        block = encode_epoch(nav_at(gps, k))
        for nav in dev._decode(_without_status(block) if k == 2 else block, host):
            dev._nav(nav)
    for nav in dev.decoder.flush():
        dev._nav(nav)
    navs = [p for t, p in submitted if t == "/ins/nav"]
    assert [n["time_source"] for n in navs] == ["device"] * 4
    assert [n["time_gps_ns"] for n in navs] == [g for _, g, _ in epochs]
    assert navs[2]["utc_detected"] is None  # the record itself says what was received


def test_a_status_older_than_the_hold_is_not_trusted():
    dev, submitted = _device()
    host0 = 50 * NS
    for k, host in ((0, host0), (1, host0 + STATUS_HOLD_NS + 1)):
        block = encode_epoch(nav_at(G0 + host - host0, k))
        for nav in dev._decode(_without_status(block) if k == 1 else block, host):
            dev._nav(nav)
    for nav in dev.decoder.flush():
        dev._nav(nav)
    navs = [p for t, p in submitted if t == "/ins/nav"]
    assert [(n["time_source"], n["time_gps_ns"]) for n in navs] == [("device", G0), ("clock", CLOCK_NS)]


def test_seen_many_reports_the_gaps_seen_one_by_one_would():
    def device():
        events = []
        ctx = SimpleNamespace(
            log_event=lambda data, host_ns: events.append((data, host_ns)),
            clock=SimpleNamespace(
                to_gps=lambda h: SimpleNamespace(gps_ns=h + 5, state=SimpleNamespace(value="LOCKED"))
            ),
            submit=None,
            hub=ConsumerHub(),
        )
        dev = InsDevice(DeviceConfig("ins", "ins", protocol="nmea", latency=LatencyLimits(gap_ns=NS)), ctx)
        return dev, events

    stamps = [10 * NS + k * 10_000_000 for k in range(50)]
    stamps = stamps[:20] + [s + 3 * NS for s in stamps[20:35]] + [s + 5 * NS for s in stamps[35:]]  # two gaps
    one, ev_one = device()
    many, ev_many = device()
    for h in stamps:
        one.seen(h)
    for burst in (
        stamps[:7],
        stamps[7:21],
        stamps[21:36],
        stamps[36:],
    ):  # a gap inside a burst, one at its start
        many.seen_many(burst)
    assert ev_many == ev_one and len(ev_one) == 2 and ev_one[0][0]["event"] == "data_gap"
    assert (many.gaps, many.last_host_ns) == (one.gaps, one.last_host_ns) == (2, stamps[-1])
