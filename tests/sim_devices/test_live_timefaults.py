"""The time faults of the emulators on real transports at speed 1 (a 5-s window): ``zda_late``
delays exactly the ZDAs of its seconds, ``leap_second`` makes the INS tag UTC with its own
GPS − UTC from its time on (and announce it, ``$PMLS,GPSUTC``), ``host_clock_step`` reaches a
process through the fake host clock (:class:`drivers.timing.FakeHostClock`) at its instant."""

from __future__ import annotations

import json
import re

import pytest

from calib.core.frames import utc_fields_to_gps_ns
from drivers.timing import FakeHostClock
from sim_devices.faults import load_faults
from sim_devices.ins import InsSettings
from tests.sim_devices.harness import capture, slack

pytestmark = [pytest.mark.integration, pytest.mark.xdist_group("sim_devices_live")]

NS = 1_000_000_000
FAULTS = """\
faults:
  - {at_s: 1.0, kind: zda_late, delay_s: 0.8, duration_s: 1.0}
  - {at_s: 2.5, kind: host_clock_step, step_s: -3600.0}
  - {at_s: 3.0, kind: leap_second, gps_minus_utc_s: 19}
"""


@pytest.fixture(scope="module")
def cap(short_sim, tmp_path_factory):
    d = tmp_path_factory.mktemp("timefaults")
    (d / "faults.yaml").write_text(FAULTS)
    return capture(
        short_sim,
        d / "run",
        start=2.5,
        duration_s=5.0,
        faults=load_faults(d / "faults.yaml"),
        devices=("ins", "pps"),
        ins=InsSettings(latency_s=0.003, jitter_s=0.0005, zda_delay_s=0.05),
    )


def window(cap, kind: str) -> dict:
    (row,) = [
        f for f in json.loads((cap.run.run_dir / "faults.json").read_text())["faults"] if f["kind"] == kind
    ]
    return row


def _seconds(cap) -> list[int]:
    """The whole GPS seconds of the window: one pulse and one ZDA each."""
    a, b = cap.run.feed.start_gps_ns, cap.run.feed.end_gps_ns
    return list(range(-(-a // NS) * NS, b, NS))


def test_zda_late_delays_exactly_the_zdas_of_its_seconds(cap):
    f = window(cap, "zda_late")
    assert {n: s["status"] for n, s in cap.stats.items()} == {"ins": "finished", "pps": "finished"}
    assert len(cap.zda) == len(_seconds(cap)) == 5
    inside = 0
    for z, second in zip(cap.zda, _seconds(cap)):
        late = f["start_gps_ns"] <= second < f["end_gps_ns"]
        delay = z.host_ns - cap.clock.host_ns(second) - (850_000_000 if late else 50_000_000)
        assert 0 <= delay <= slack(cap, "ins"), (second, delay)
        inside += late
    assert inside == 1


def test_leap_second_tags_utc_with_the_ins_count_and_announces_it(cap):
    f = window(cap, "leap_second")
    raw = b"".join(d for _, d in cap.chunks)
    announced = [int(v) for v in re.findall(rb"\$PMLS,GPSUTC,(\d+)\*", raw)]
    counts = [19 if s >= f["start_gps_ns"] else 18 for s in _seconds(cap)]
    assert counts == [18, 18, 18, 19, 19]
    # before the first epoch, before each ZDA, and before the first epoch tagged with 19
    assert announced == [18, 18, 18, 18, 19, 19, 19]
    for z, second, leap in zip(cap.zda, _seconds(cap), counts):
        assert utc_fields_to_gps_ns(z.year, z.month, z.day, z.time_of_day_ns, gps_minus_utc_s=leap) == second
        # read with the table's 18 s, a tag of the window is 1 s early
        assert utc_fields_to_gps_ns(z.year, z.month, z.day, z.time_of_day_ns) == second - (leap - 18) * NS
    # the decoder undoes each epoch's UTC tag with the count the INS announced: GPS time exact
    # (an epoch read with the wrong count would come back 1 s early, onto another epoch's time)
    got = [n.gps_ns for n in cap.nav]
    assert set(got) <= set(cap.run.feed.ins.gps_ns.tolist()) and len(set(got)) == len(got) >= 495
    assert sum(g >= f["start_gps_ns"] for g in got) >= 195


def test_host_clock_step_is_written_for_the_fake_host_clock_at_its_instant(cap):
    f = window(cap, "host_clock_step")
    assert f["device"] == "host" and f["step_s"] == -3600.0
    fake = FakeHostClock(str(cap.run.run_dir / "host_clock"))
    fake.offset_ns()  # reads the file
    assert fake.steps == [(f["start_host_ns"], -3600 * NS)]
    assert fake.step_at(f["start_host_ns"] - 1) == 0 and fake.step_at(f["start_host_ns"]) == -3600 * NS
