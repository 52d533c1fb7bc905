"""The truth clock (mapping, file) and the fault timeline (YAML validation with file:line:key
errors, windows, the schedule written to faults.json)."""

from __future__ import annotations

import json
import textwrap

import numpy as np
import pytest

from sim_devices.clock import TruthClock
from sim_devices.faults import KINDS, FaultError, FaultPlan, Timeline, load_faults, parse_faults
from sim_devices.feed import make_feed
from sim_devices.ins import InsSettings
from sim_devices.runner import DeviceRun, DevicesSpec

NS = 1_000_000_000
GPS0 = 1_400_000_000 * NS


def test_truth_clock_maps_host_to_gps_with_drift_and_speed(tmp_path):
    c = TruthClock(host_anchor_ns=5 * NS, gps_anchor_ns=GPS0, drift_ppm=35.0, speed=2.0)
    assert c.rate == pytest.approx(2.0 * (1 + 35e-6), rel=1e-15)
    # one host second later GPS has advanced 2 s and 70 µs
    assert c.gps_ns(6 * NS) - GPS0 == 2 * NS + 70_000
    for g in (GPS0, GPS0 + 123_456_789, GPS0 + 3600 * NS):
        assert abs(c.gps_ns(c.host_ns(g)) - g) <= 1
    g = GPS0 + np.arange(0, 10 * NS, 7_777_777, dtype=np.int64)
    assert np.array_equal(c.host_ns_array(g), [c.host_ns(int(x)) for x in g])
    h = c.host_ns_array(g)
    assert np.array_equal(c.gps_ns_array(h), [c.gps_ns(int(x)) for x in h])
    path = c.write(tmp_path / "truth_clock.json", window={"start_gps_ns": GPS0})
    assert TruthClock.read(path) == c
    d = json.loads(path.read_text())
    assert d["gps_minus_host_at_anchor_ns"] == GPS0 - 5 * NS and d["window"] == {"start_gps_ns": GPS0}
    with pytest.raises(ValueError, match="speed"):
        TruthClock(0, 0, speed=0.0)


ALL_KINDS = """\
seed: 7
faults:
  - {at_s: 5.0, kind: serial_unplug, duration_s: 2.0}
  - {at_s: 8.0, kind: garbage, bytes: 200}
  - {at_s: 9.0, kind: bad_checksum, duration_s: 0.5, probability: 0.5}
  - {at_s: 10.0, kind: udp_loss, device: profiler, duration_s: 1.0, probability: 0.2}
  - {at_s: 11.0, kind: udp_reorder, device: profiler, duration_s: 1.0}
  - {at_s: 12.0, kind: udp_duplicate, device: pps, duration_s: 3.0}
  - {at_s: 15.0, kind: pps_loss, duration_s: 3.0}
  - {at_s: 20.0, kind: profiler_clock_offset, offset_s: 1.0, duration_s: 5.0}
  - {at_s: 30.0, kind: profiler_clock_drift, drift_ppm: 100.0}
  - {at_s: 40.0, kind: ins_latency_jump, latency_s: 0.02, duration_s: 5.0}
  - {at_s: 41.0, kind: zda_late, delay_s: 0.8, duration_s: 2.0}
  - {at_s: 44.0, kind: leap_second, gps_minus_utc_s: 19, duration_s: 3.0}
  - {at_s: 48.0, kind: host_clock_step, step_s: -3600.5}
  - {at_s: 50.0, kind: gnss_outage}
"""


def test_a_timeline_with_every_kind_loads_with_defaults():
    plan = parse_faults(ALL_KINDS)
    assert {f.kind for f in plan.faults} == set(KINDS) and plan.seed == 7
    by = {f.kind: f for f in plan.faults}
    assert by["serial_unplug"].device == "ins" and by["serial_unplug"].end_s == 7.0
    assert by["garbage"].duration_s == 0.0 and by["garbage"].params == {"bytes": 200}
    assert by["udp_reorder"].params == {"probability": 1.0}
    assert by["profiler_clock_offset"].params == {"offset_s": 1.0, "pps_locked": True}
    assert by["profiler_clock_drift"].params == {"drift_ppm": 100.0, "pps_locked": False}
    assert by["profiler_clock_drift"].duration_s is None and by["gnss_outage"].end_s == float("inf")
    assert by["gnss_outage"].params == {"position_drift_m_s": 0.05}
    assert by["pps_loss"].where == "faults.yaml:9:5: faults[6]"
    assert by["zda_late"].device == "ins" and by["zda_late"].params == {"delay_s": 0.8}
    assert by["leap_second"].params == {"gps_minus_utc_s": 19} and by["leap_second"].end_s == 47.0
    step = by["host_clock_step"]
    assert (step.device, step.duration_s, step.params) == ("host", 0.0, {"step_s": -3600.5})
    t = Timeline(plan.for_device("profiler"), GPS0)
    assert t.active("udp_loss", GPS0 + 10 * NS) is by["udp_loss"]
    assert t.active("udp_loss", GPS0 + 11 * NS) is None  # half-open window
    assert t.started_at("profiler_clock_drift", GPS0 + 99 * NS) == GPS0 + 30 * NS
    rows = plan.schedule(GPS0, TruthClock(0, GPS0, speed=2.0))
    unplug = rows[0]
    assert (unplug["start_gps_ns"], unplug["end_gps_ns"]) == (GPS0 + 5 * NS, GPS0 + 7 * NS)
    assert (unplug["start_host_ns"], unplug["end_host_ns"]) == (2_500_000_000, 3_500_000_000)
    assert rows[-1]["end_gps_ns"] is None and rows[-1]["end_host_ns"] is None


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (
            "faults:\n  - {at_s: 1, kind: unplug}\n",
            r"faults.yaml:2:21: faults\[0\].kind: got 'unplug', expected one of bad_checksum, garbage",
        ),
        (
            "faults:\n  - {at_s: 1, kind: udp_loss, duration_s: 1}\n",
            r"faults.yaml:2:5: faults\[0\]: a udp_loss fault needs 'device' \(one of profiler, pps\)",
        ),
        (
            "faults:\n  - {at_s: 1, kind: udp_loss, device: ins, duration_s: 1}\n",
            r"faults\[0\].device: got 'ins', expected one of pps, profiler",
        ),
        (
            "faults:\n  - {at_s: 1, kind: bad_checksum}\n",
            r"faults\[0\]: a bad_checksum fault needs 'duration_s'",
        ),
        (
            "faults:\n  - at_s: 1\n    kind: udp_loss\n    device: pps\n    duration_s: 1\n    probability: 1.5\n",
            r"faults.yaml:6:18: faults\[0\].probability: got 1.5, expected a number ≤ 1",
        ),
        (
            "faults:\n  - {at_s: 1, kind: garbage, duration_s: 1}\n",
            r"faults\[0\].duration_s: not a key of a garbage fault; allowed: at_s, bytes, device, kind",
        ),
        (
            "faults:\n  - {at_s: 1, kind: pps_loss, offset_s: 1}\n",
            r"faults\[0\].offset_s: not a key of a pps_loss fault",
        ),
        ("faults:\n  - {at_s: -1, kind: pps_loss}\n", r"faults\[0\].at_s: got -1, expected a number ≥ 0"),
        (
            "faults:\n  - {at_s: 1, kind: profiler_clock_drift}\n",
            r"a profiler_clock_drift fault needs 'drift_ppm'",
        ),
        (
            "faults:\n  - {at_s: 1, kind: profiler_clock_drift, drift_ppm: 0}\n",
            r"drift_ppm: got 0, expected a non-zero drift in ppm",
        ),
        (
            "faults:\n  - {at_s: 1, kind: pps_loss, duration_s: 2}\n  - {at_s: 2, kind: pps_loss}\n",
            r"faults.yaml:3:5: faults\[1\]: pps_loss on pps at 2 s overlaps the one at faults\[0\] \(1 s to 3 s\)",
        ),
        (
            "fault:\n  - {at_s: 1, kind: pps_loss}\n",
            r"faults.yaml:2:3: fault: unknown key 'fault'; allowed keys here: faults, seed",
        ),
        ("faults: [\n", r"faults.yaml:2:1: not valid YAML"),
        ("faults:\n  - {at_s: 1, kind: zda_late}\n", r"faults\[0\]: a zda_late fault needs 'delay_s'"),
        (
            "faults:\n  - {at_s: 1, kind: zda_late, delay_s: 0}\n",
            r"faults.yaml:2:40: faults\[0\].delay_s: got 0, expected a number > 0",
        ),
        (
            "faults:\n  - {at_s: 1, kind: leap_second, gps_minus_utc_s: 18.5}\n",
            r"faults\[0\].gps_minus_utc_s: got 18.5, expected an integer",
        ),
        (
            "faults:\n  - {at_s: 1, kind: leap_second, gps_minus_utc_s: 300}\n",
            r"faults\[0\].gps_minus_utc_s: got 300, expected an integer ≤ 255",
        ),
        (
            "faults:\n  - {at_s: 1, kind: host_clock_step, step_s: 0.001}\n",
            r"step_s: got 0.001, expected a step of at least 0.01 s either way",
        ),
        (
            "faults:\n  - {at_s: 1, kind: host_clock_step, step_s: 5, duration_s: 1}\n",
            r"faults\[0\].duration_s: not a key of a host_clock_step fault; allowed: at_s, device, kind, step_s",
        ),
        (
            "faults:\n  - {at_s: 1, kind: host_clock_step, device: ins, step_s: 5}\n",
            r"faults\[0\].device: got 'ins', expected one of host",
        ),
    ],
)
def test_bad_timelines_name_file_line_and_key(text, message):
    with pytest.raises(FaultError, match=message):
        parse_faults(text)


def test_load_faults_names_a_missing_file(tmp_path):
    with pytest.raises(FaultError, match=r"nope.yaml: file not found"):
        load_faults(tmp_path / "nope.yaml")


def test_faults_outside_the_window_or_for_a_device_not_running_are_refused(short_sim, tmp_path):
    feed = make_feed(short_sim, start=2.5, duration_s=4.0)
    late = parse_faults("faults:\n  - {at_s: 4.5, kind: pps_loss}\n")
    with pytest.raises(
        FaultError, match=r"faults\[0\].at_s: got 4.5, expected < 4 \(the run window's length"
    ):
        DeviceRun(feed, DevicesSpec(run_dir=tmp_path), late)
    pps = parse_faults("faults:\n  - {at_s: 1, kind: pps_loss}\n")
    with pytest.raises(
        FaultError, match=r"faults\[0\]: the pps_loss fault is for the pps emulator, which is not running"
    ):
        DeviceRun(feed, DevicesSpec(run_dir=tmp_path, devices=("ins",)), pps)
    assert FaultPlan().schedule(feed.start_gps_ns) == []
    late_zda = parse_faults("faults:\n  - {at_s: 1, kind: zda_late, delay_s: 0.5}\n")
    with pytest.raises(FaultError, match=r"faults\[0\]: zda_late needs an NMEA INS"):
        DeviceRun(feed, DevicesSpec(run_dir=tmp_path, ins=InsSettings(protocol="stdbin")), late_zda)


def test_the_documented_example_timeline_is_valid():
    import sim_devices.faults as module

    doc = module.__doc__.split("\n\n")[1]  # the indented YAML example
    plan = parse_faults(textwrap.dedent(doc))
    assert {f.kind for f in plan.faults} == set(KINDS)
