"""``mls plan``: the lines as GeoJSON (structure, properties, coordinates back to the
plan's LGF lines within 1 mm) and NMEA XTE/APB for an autopilot (valid checksums, decodable by
the project's NMEA decoder as generic sentences, the steering side and values)."""

from __future__ import annotations

import asyncio
import json
import math

import numpy as np
import pytest
from typer.testing import CliRunner

from acquire.guidance.autopilot import autopilot_sentences, steering
from acquire.guidance.autopilot_out import NmeaOutput, follow_daemon
from acquire.status.bus import StatusBus, StatusServer
from calib.sim.scenariofile import load_scenario
from calib.survey.passplan import plan_site
from calib.survey.planexport import FORMAT, plan_geojson
from cli.app import app
from drivers.hydrins.nmea_decode import NmeaDecoder
from drivers.hydrins.nmea_sentences import Sentence
from tests.waiting import wait_until_async

runner = CliRunner()


@pytest.fixture(scope="module")
def site():
    return load_scenario("montreal").site()


@pytest.fixture
def site_file(site, tmp_path):
    path = tmp_path / "site.yaml"
    site.dump(path)
    return path


def _decode(data: bytes) -> list[Sentence]:
    dec = NmeaDecoder()
    recs = dec.feed(data)
    assert dict(dec.stats.rejected) == {} and dec.stats.skipped_bytes == 0
    assert all(isinstance(r, Sentence) for r in recs)
    return recs


# -- GeoJSON ------------------------------------------------------------------------------------


def test_geojson_structure_and_properties(site):
    frame = site.frame()
    plan = plan_site(site)
    doc = plan_geojson(plan, frame, site.targets)
    assert doc["type"] == "FeatureCollection"
    assert doc["mls_plan"]["format"] == FORMAT
    assert doc["mls_plan"]["reference"] == frame.as_dict()
    feats = doc["features"]
    assert len(feats) == 2 * len(plan.passes) + len(site.targets)
    lines = [f for f in feats if f["properties"]["kind"] == "line"]
    caps = [f for f in feats if f["properties"]["kind"] == "capture"]
    tgts = [f for f in feats if f["properties"]["kind"] == "target"]
    assert [f["properties"]["pass_id"] for f in lines] == [1, 2, 3, 4, 5, 6]
    assert [f["properties"]["relative_heading_deg"] for f in lines] == [0, 180, 45, 225, 315, 135]
    for f, p in zip(lines, plan.passes):
        assert f["type"] == "Feature" and f["geometry"]["type"] == "LineString"
        coords = f["geometry"]["coordinates"]
        assert len(coords) == 2 and all(len(c) == 3 for c in coords)
        assert all(-180 <= c[0] <= 180 and -90 <= c[1] <= 90 for c in coords)
        pr = f["properties"]
        assert pr["order"] == p.order and pr["speed_mps"] == p.speed_mps
        assert pr["heading_deg"] == pytest.approx(math.degrees(p.heading_rad), abs=1e-6)
        assert pr["capture_window_s"] == pytest.approx(
            [p.capture_start_m / p.speed_mps, p.capture_end_m / p.speed_mps], abs=1e-3
        )
        assert pr["length_m"] == pytest.approx(p.length_m, abs=1e-4)
        assert pr["targets_side"] == p.targets_side
        assert pr["standoff_m"] == pytest.approx(site.standoff_m, abs=1e-3)
    assert [t["properties"]["name"] for t in tgts] == ["T1", "T2"]
    assert all(t["geometry"]["type"] == "Point" for t in tgts)
    assert all(c["properties"]["pass_id"] == lf["properties"]["pass_id"] for c, lf in zip(caps, lines))
    json.dumps(doc, allow_nan=False)  # strict JSON


def test_mls_plan_writes_geojson_that_round_trips_to_the_lgf_lines(site, site_file, tmp_path):
    out = tmp_path / "out" / "lines.geojson"
    res = runner.invoke(app, ["plan", str(site_file), "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert "calibration lines" in res.output and "capture window" in res.output
    doc = json.loads(out.read_text())
    frame = site.frame()
    plan = plan_site(site)
    by_id = {f["properties"]["pass_id"]: f for f in doc["features"] if f["properties"]["kind"] == "line"}
    caps = {f["properties"]["pass_id"]: f for f in doc["features"] if f["properties"]["kind"] == "capture"}
    for p in plan.passes:
        c = np.array(by_id[p.id]["geometry"]["coordinates"])
        back = frame.to_lgf(c[:, 1], c[:, 0], c[:, 2])
        assert np.max(np.abs(back - [p.start_lgf_m, p.end_lgf_m])) < 1e-3
        c = np.array(caps[p.id]["geometry"]["coordinates"])
        back = frame.to_lgf(c[:, 1], c[:, 0], c[:, 2])
        assert np.max(np.abs(back - p.position_at([p.capture_start_m, p.capture_end_m]))) < 1e-3
    for t, f in zip(site.targets, [f for f in doc["features"] if f["properties"]["kind"] == "target"]):
        assert f["geometry"]["coordinates"] == [t.lon_deg, t.lat_deg, t.height_m]


def test_mls_plan_options_change_the_capture_window(site_file, tmp_path):
    out = tmp_path / "a.geojson"
    res = runner.invoke(app, ["plan", str(site_file), "--out", str(out), "--capture-margin-m", "1"])
    assert res.exit_code == 0, res.output
    props = json.loads(out.read_text())["features"][0]["properties"]
    wide = runner.invoke(app, ["plan", str(site_file), "--out", str(out)])
    assert wide.exit_code == 0
    props3 = json.loads(out.read_text())["features"][0]["properties"]
    assert props3["capture_end_m"] - props3["capture_start_m"] == pytest.approx(
        props["capture_end_m"] - props["capture_start_m"] + 4.0, abs=1e-3
    )


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--nmea"], "--nmea needs --position"),
        (["--position", "45.5,-73.5"], "--position and --follow go with --nmea"),
        (["--nmea", "--position", "45.5"], "expected LAT,LON"),
        (["--nmea", "--position", "45.5,-73.5", "--talker", "gps"], "two capital letters"),
        (["--nmea", "--position", "45.5,-73.5", "--active-pass", "9"], "pass 9 is not in the plan"),
    ],
)
def test_mls_plan_usage_errors(site_file, args, message):
    res = runner.invoke(app, ["plan", str(site_file), *args])
    assert res.exit_code in (1, 2)
    assert message in " ".join(res.output.split())


def test_mls_plan_needs_a_reference_point(site, tmp_path):
    text = tmp_path / "s.yaml"
    site.dump(text)
    lines = [ln for ln in text.read_text().splitlines(keepends=True)]
    i = next(k for k, ln in enumerate(lines) if ln.startswith("reference:"))
    del lines[i : i + 4]
    text.write_text("".join(lines))
    res = runner.invoke(app, ["plan", str(text), "--out", str(tmp_path / "x.geojson")])
    assert res.exit_code == 1
    assert "needs the site's reference point" in " ".join(res.output.split())


# -- NMEA ---------------------------------------------------------------------------------------


def test_steering_side_values_and_flags(site):
    plan = plan_site(site)
    line = plan.by_id(3)
    h = line.heading_rad
    u = np.array([math.cos(h), math.sin(h), 0.0])
    s = np.array([-math.sin(h), math.cos(h), 0.0])
    st = steering(line.start_lgf_m + 10 * u + 2.0 * s, line)
    assert st.xte_m == pytest.approx(2.0) and st.steer == "L"
    # to starboard: steer left of the line's heading, by atan(2/20)
    assert math.degrees(st.heading_to_steer_rad) == pytest.approx(
        (math.degrees(h) - math.degrees(math.atan(0.1))) % 360, abs=1e-9
    )
    assert not st.arrived and not st.passed
    port = steering(line.start_lgf_m + 10 * u - 3.0 * s, line)
    assert port.xte_m == pytest.approx(-3.0) and port.steer == "R"
    assert math.degrees(port.heading_to_steer_rad) == pytest.approx(
        (math.degrees(h) + math.degrees(math.atan(0.15))) % 360, abs=1e-9
    )
    near_end = steering(line.end_lgf_m - 3 * u, line)
    assert near_end.arrived and not near_end.passed
    past = steering(line.end_lgf_m + 8 * u, line)
    assert past.passed and not past.arrived


def test_xte_and_apb_are_valid_nmea_decodable_as_generic_sentences(site):
    plan = plan_site(site)
    line = plan.by_id(2)
    h = line.heading_rad
    p = (
        line.start_lgf_m
        + 20 * np.array([math.cos(h), math.sin(h), 0])
        + 37.04 * np.array([-math.sin(h), math.cos(h), 0])
    )  # 0.02 NM to starboard
    data = b"".join(autopilot_sentences(p, line, talker="II"))
    xte, apb = _decode(data)
    assert (xte.talker, xte.kind) == ("II", "XTE")
    assert xte.fields[1:] == ["A", "A", "0.0200", "L", "N", "A"]
    assert (apb.talker, apb.kind) == ("II", "APB")
    f = apb.fields[1:]
    assert f[:7] == ["A", "A", "0.0200", "L", "N", "V", "V"]
    assert float(f[7]) == pytest.approx(math.degrees(h), abs=0.05) and f[8] == "T"
    assert f[9] == "L2"
    bearing = math.degrees(math.atan2(*(line.end_lgf_m - p)[[1, 0]])) % 360
    assert float(f[10]) == pytest.approx(bearing, abs=0.05) and f[11] == "T"
    steer = (math.degrees(h) - math.degrees(math.atan(37.04 / 20.0))) % 360
    assert float(f[12]) == pytest.approx(steer, abs=0.05) and f[13] == "T"
    assert f[14] == "A"
    invalid = b"".join(autopilot_sentences(p, line, valid=False))
    x2, a2 = _decode(invalid)
    assert x2.fields[1:] == ["V", "V", "", "", "N", "N"] and a2.fields[-1] == "N"


def test_mls_plan_nmea_once_from_a_position(site, site_file):
    frame = site.frame()
    plan = plan_site(site)
    line = plan.by_id(4)
    h = line.heading_rad
    p = (
        line.start_lgf_m
        + 30 * np.array([math.cos(h), math.sin(h), 0])
        - 5.0 * np.array([-math.sin(h), math.cos(h), 0])
    )
    lat, lon, _ = frame.to_geodetic(p[None])
    res = runner.invoke(
        app,
        [
            "plan",
            str(site_file),
            "--nmea",
            "--active-pass",
            "4",
            "--position",
            f"{lat[0]:.10f},{lon[0]:.10f}",
        ],
    )
    assert res.exit_code == 0, res.output
    xte, apb = _decode(res.stdout_bytes)
    assert xte.kind == "XTE" and apb.kind == "APB"
    assert float(xte.fields[3]) * 1852 == pytest.approx(5.0, abs=0.2) and xte.fields[4] == "R"
    assert apb.fields[10] == "L4"


def test_follow_emits_sentences_for_the_daemons_vessel_and_active_pass(site, tmp_path):
    """``mls plan --nmea --follow``: the vessel's position and active pass come from the
    daemon's ``checklist`` messages on its status socket; sentences go to a file."""
    frame = site.frame()
    plan = plan_site(site)
    line = plan.by_id(5)
    h = line.heading_rad
    positions = [
        line.start_lgf_m
        + a * np.array([math.cos(h), math.sin(h), 0])
        + x * np.array([-math.sin(h), math.cos(h), 0])
        for a, x in ((5, 1.0), (7, -2.0))
    ]
    out_path = tmp_path / "ap.nmea"

    async def main():
        server = StatusServer(tmp_path / "status.sock")
        await server.start()
        bus = StatusBus([server])
        out = NmeaOutput(str(out_path))
        task = asyncio.create_task(
            follow_daemon(tmp_path / "status.sock", plan, frame, None, out, "GP", 20.0)
        )
        await wait_until_async(lambda: server.clients == 1, 10, "the follower to connect")
        for i, p in enumerate(positions):
            lat, lon, _ = frame.to_geodetic(p[None])
            msg = {
                "schema": "mls.checklist/1",
                "active": {"pass_id": 5},
                "vessel": {"lat_deg": float(lat[0]), "lon_deg": float(lon[0])},
            }
            # the daemon publishes sections (presurvey, guidance); a bare message works too
            bus.publish("checklist", {"presurvey": {}, "guidance": msg} if i == 0 else msg)
            await wait_until_async(  # the XTE and APB of this position written
                lambda i=i: out_path.exists() and out_path.read_bytes().count(b"\n") >= 2 * (i + 1),
                10,
                f"the sentences of position {i + 1}",
            )
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
        out.close()
        await server.close()

    asyncio.run(main())
    recs = _decode(out_path.read_bytes())
    assert [r.kind for r in recs] == ["XTE", "APB", "XTE", "APB"]
    assert [r.fields[4] for r in recs[::2]] == ["L", "R"]
    assert [float(r.fields[3]) * 1852 for r in recs[::2]] == pytest.approx([1.0, 2.0], abs=0.2)
    assert recs[1].fields[10] == "L5"
