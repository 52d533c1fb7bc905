"""The guidance inside the daemon: the vessel config's ``guidance`` section (defaults,
validation with one clear error per bad field), :func:`acquire.guidance.daemon.make_guidance`
(the site's plan, the vessel's mount, an LGF without a site reference, a site that gives no
plan), the config the simulated devices write, and a supervisor with fake devices publishing
the guidance section of the ``checklist`` topic on the status socket and MQTT."""

from __future__ import annotations

import asyncio
import math
import subprocess
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from acquire.daemon.config import VesselConfigError, load_vessel_config, parse_vessel_config
from acquire.daemon.configschema import GuidanceConfig
from acquire.daemon.supervisor import Supervisor
from acquire.guidance.acceptance import AcceptanceTolerances
from acquire.guidance.daemon import GuidanceSetupError, guidance_consumer, make_guidance, tolerances
from acquire.status.bus import read_snapshot
from calib.sim.simulate import simulate
from tests.acquire.daemon_util import MLS, MqttCollector, free_port
from tests.acquire.fakedevices import FakeDevices
from tests.waiting import wait_until, wait_until_async

NS = 1_000_000_000


@pytest.fixture(scope="module")
def site_file(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("site") / "site.yaml"
    simulate("montreal", 0).site.dump(path)
    return path


def _vessel(site: Path | None, extra: str = "", ins_port: int | None = None) -> str:
    return (
        textwrap.dedent(f"""\
        vessel: guide-1
        devices:
          - {{name: ins, kind: ins, protocol: nmea, transport: {{type: udp, host: 127.0.0.1, port: {ins_port or 7001}}}}}
        session: {{directory: sessions}}
        mount: {{lever_arm_m: [0.1, 0.2, -1.0], nominal_deg: [0, 0, 90], boresight_apriori_deg: [0.5, 0, 0]}}
        """)
        + (f"site_file: {site}\n" if site else "")
        + extra
    )


def test_guidance_section_defaults_are_the_acceptance_defaults(site_file):
    cfg = parse_vessel_config(_vessel(site_file))
    assert cfg.guidance == GuidanceConfig()
    assert tolerances(cfg.guidance) == AcceptanceTolerances()
    cfg = parse_vessel_config(
        _vessel(
            site_file,
            "guidance: {max_xte_m: 1.5, max_heading_error_deg: 8, "
            "min_points_per_target: 40, period_s: 0.25}\n",
        )
    )
    tol = tolerances(cfg.guidance)
    assert tol.max_xte_m == 1.5 and tol.min_points_per_target == 40
    assert tol.max_heading_error_rad == pytest.approx(math.radians(8.0))
    assert cfg.guidance.period_s == 0.25 and cfg.guidance.max_gap_s == 0.5


def test_the_shipped_example_documents_the_defaults(site_file, tmp_path):
    """systemd/vessel.example.yaml's commented guidance section, switched on, is the default."""
    import re

    from tests.acquire.daemon_util import ROOT

    text = (ROOT / "systemd" / "vessel.example.yaml").read_text()
    text = text.replace("# site_file: site.yaml", f"site_file: {site_file}")
    block = re.search(r"^# guidance:.*?(?=\n\n|\Z)", text, flags=re.M | re.S)  # that section only
    assert block is not None
    text = text.replace(block[0], re.sub(r"^# (guidance:|  \w)", r"\1", block[0], flags=re.M))
    path = tmp_path / "vessel.yaml"
    path.write_text(text)
    assert "\nguidance:" in text and load_vessel_config(path).guidance == GuidanceConfig()


def test_guidance_section_errors_name_the_line_the_key_and_what_was_expected(site_file):
    text = _vessel(
        site_file,
        textwrap.dedent("""\
        guidance:
          max_xte_m: -1
          max_heading_error_deg: 120
          min_points_per_target: 2.5
          profile_rate_hz: fast
          colour: red
        """),
    )
    with pytest.raises(VesselConfigError) as e:
        parse_vessel_config(text, source="v.yaml")
    errs = e.value.errors
    line = {k: i + 1 for i, ln in enumerate(text.splitlines()) for k in (ln.strip().split(":")[0],)}
    assert errs == [
        f"v.yaml:{line['max_xte_m']}:14: guidance.max_xte_m: got -1, expected a number > 0",
        f"v.yaml:{line['max_heading_error_deg']}:26: guidance.max_heading_error_deg: got 120, "
        f"expected a number ≤ 90",
        f"v.yaml:{line['min_points_per_target']}:26: guidance.min_points_per_target: got 2.5, "
        f"expected an integer",
        f"v.yaml:{line['profile_rate_hz']}:20: guidance.profile_rate_hz: got 'fast', expected a "
        f"finite number",
        f"v.yaml:{line['colour']}:11: guidance.colour: unknown key 'colour'; allowed keys here: enabled, "
        f"max_gap_s, max_heading_error_deg, max_speed_error_mps, max_xte_m, min_points_per_target, "
        f"period_s, points_per_360, profile_rate_hz",
    ]
    with pytest.raises(VesselConfigError) as e:
        parse_vessel_config(_vessel(None, "guidance: {max_xte_m: 1.0}\n"), source="v.yaml")
    assert e.value.errors == [
        "v.yaml:6:11: guidance: the guidance needs the site's targets and "
        "pass plan: add site_file (or set guidance.enabled: false)"
    ]
    # disabled: no site needed, and no consumer
    cfg = parse_vessel_config(_vessel(None, "guidance: {enabled: false}\n"))
    assert guidance_consumer(cfg, sup=None) is None


def test_make_guidance_plans_the_site_with_the_vessels_mount(site_file, tmp_path):
    cfg = parse_vessel_config(
        _vessel(site_file, "guidance: {profile_rate_hz: 63.25, points_per_360: 1606}\n")
    )
    g = make_guidance(cfg)
    assert [round(math.degrees(p.relative_heading_rad)) for p in g.plan.passes] == [0, 180, 45, 225, 315, 135]
    assert g.target_names == ["T1", "T2"]
    np.testing.assert_allclose(g.mount.lever_arm_m, [0.1, 0.2, -1.0])  # the vessel config's
    np.testing.assert_allclose(np.degrees(g.mount.boresight_rad), [0.5, 0, 0])
    assert g.scanner.profile_rate_hz == 63.25 and g.thin_step == 1  # ~100 k points/s
    assert make_guidance(parse_vessel_config(_vessel(site_file))).thin_step == 10  # the full Z+F rate
    # a site without a reference point: the LGF at the targets' mean centre
    text = site_file.read_text().split("\n")
    start = next(i for i, ln in enumerate(text) if ln.startswith("reference:"))
    end = next(i for i in range(start + 1, len(text)) if not text[i].startswith(" "))
    bare = tmp_path / "bare.yaml"
    bare.write_text("\n".join(text[:start] + text[end:]))
    g2 = make_guidance(parse_vessel_config(_vessel(bare)))
    centre = np.mean([r.center_m for r in g2.scene.rectangles], axis=0)
    assert np.abs(centre).max() < 1e-6
    # a standoff the wall forbids: no plan, and the error names the site file
    tight = tmp_path / "tight.yaml"
    tight.write_text(site_file.read_text().replace("standoff_m: 15.0", "standoff_m: 2.0"))
    with pytest.raises(
        GuidanceSetupError,
        match=rf"site_file {tight}: no pass plan: pass 1: .*less than "
        r"the safe distance 5 m; increase standoff_m",
    ):
        make_guidance(parse_vessel_config(_vessel(tight)))
    vfile = tmp_path / "tight-vessel.yaml"
    vfile.write_text(_vessel(tight))
    r = subprocess.run(
        [*MLS, "acquire", "--config", str(vfile)], capture_output=True, text=True, cwd=tmp_path, timeout=60
    )
    assert r.returncode == 2 and f"mls acquire: site_file {tight}: no pass plan: pass 1" in r.stderr
    vfile.write_text(_vessel(site_file, "guidance: {max_xte_m: 1.5, min_points_per_target: 40}\n"))
    r = subprocess.run(
        [*MLS, "acquire", "--config", str(vfile), "--check"],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        timeout=60,
    )
    assert r.returncode == 0, r.stderr
    assert (
        f"guidance: 6 passes around 2 targets (T1, T2) of {site_file}; accepted within 1.5 m "
        f"XTE, 5° heading, ±0.5 m/s, ≥ 40 points per target, gaps ≤ 0.5 s"
    ) in " ".join(r.stdout.split())


def test_simulated_devices_write_a_guidance_section_matched_to_their_profiler(site_file):
    from sim_devices.vesselconfig import vessel_config

    locations = {"ins": {"link": "/tmp/run/ins", "protocol": "nmea"}}
    sim = simulate("montreal", 0)
    sc = sim.scenario.scanner
    cfg = vessel_config(
        vessel="v",
        run_dir=Path("/tmp/run"),
        locations=locations,
        profiler_rate_hz=sc.effective_profile_rate_hz,
        profiler_points_per_360=sc.effective_points_per_360,
        site=sim.site,
        site_file=str(site_file),
    )
    # 0.1 of the full Z+F point rate: 10 % of the 100 points, at least 20
    assert cfg["guidance"] == {
        "min_points_per_target": 20,
        "profile_rate_hz": 63.2456,
        "points_per_360": 1606,
    }
    full = vessel_config(
        vessel="v",
        run_dir=Path("/tmp/run"),
        locations=locations,
        profiler_rate_hz=200.0,
        profiler_points_per_360=5080,
        site=sim.site,
        site_file=str(site_file),
    )["guidance"]
    assert full["min_points_per_target"] == 100
    import yaml

    parsed = parse_vessel_config(yaml.safe_dump(cfg))
    assert parsed.guidance.min_points_per_target == 20 and parsed.guidance.points_per_360 == 1606


@pytest.mark.integration
@pytest.mark.xdist_group("daemon-fake")
def test_the_daemon_publishes_the_guidance_on_the_socket_and_mqtt(site_file, tmp_path, mosquitto):
    from acquire.timing.timekeeper import coarse_gps_offset_ns

    prof, pps = free_port(), free_port()
    cfg_path = tmp_path / "vessel.yaml"
    cfg_path.write_text(
        textwrap.dedent(f"""\
        vessel: guide-1
        devices:
          - {{name: ins, kind: ins, protocol: nmea, transport: {{type: serial, port: {tmp_path}/ins, baud: 115200}},
             latency: {{band_ms: [0.0, 20.0], rate_hz: 50.0, gap_s: 0.5}}}}
          - {{name: profiler, kind: profiler, protocol: zfp1, transport: {{type: udp, host: 127.0.0.1, port: {prof}}},
             latency: {{band_ms: [0.0, 60.0], rate_hz: 20.0, gap_s: 0.5}}}}
          - {{name: pps, kind: pps, source: {{type: udp, host: 127.0.0.1, port: {pps}}}, time_device: ins,
             time_messages: [ZDA]}}
        session: {{directory: sessions, flush_s: 0.2}}
        status: {{socket: status.sock, period_s: 0.5}}
        mqtt: {{host: 127.0.0.1, port: {mosquitto.port}, topic_prefix: guidetest}}
        mount: {{lever_arm_m: [0.35, 0.85, -1.65], nominal_deg: [0, 0, 0], boresight_apriori_deg: [0, 0, 0]}}
        site_file: {site_file}
        guidance: {{max_xte_m: 1.5, min_points_per_target: 40, period_s: 0.25}}
        """)
    )
    cfg = load_vessel_config(cfg_path)
    gps0 = (time.monotonic_ns() + coarse_gps_offset_ns()) // NS * NS + 300_000_000
    fake = FakeDevices(tmp_path / "ins", prof, pps, seconds=6.0, gps0_ns=gps0)
    mqtt = MqttCollector(mosquitto.host, mosquitto.port, "guidetest/guide-1/#").start()
    out = {}

    async def scenario():
        sup = Supervisor(cfg)
        consumer = guidance_consumer(cfg, sup)
        sup.consumers.append(consumer)
        task = asyncio.create_task(sup.run())
        await wait_until_async(
            lambda: sup.state == "running" or task.done(), 30, "the daemon to run", interval_s=0.02
        )
        assert not task.done(), task
        fake.start()
        await asyncio.to_thread(fake.join, 30)
        out["snapshot"] = await asyncio.to_thread(read_snapshot, cfg.status.socket)
        out["records"] = consumer.records
        sup.request_stop("test")
        out["rc"] = await task

    try:
        asyncio.run(asyncio.wait_for(scenario(), 60))
        # the daemon's last message on MQTT, after every checklist it published
        wait_until(
            lambda: any(
                isinstance(m.data, dict) and m.data.get("state") == "stopped" for m in mqtt.topic("status")
            ),
            10,
            "the final status on MQTT",
        )
    finally:
        fake.close()
        mqtt.stop()
    assert out["rc"] == 0
    snap = out["snapshot"]["checklist"]
    g = snap["guidance"]
    assert set(snap) == {"presurvey", "guidance"} and g["schema"] == "mls.checklist/1"
    assert g["vessel_name"] == "sim-montreal" and len(g["plan"]["passes"]) == 6
    assert g["tolerances"]["max_xte_m"] == 1.5 and g["tolerances"]["min_points_per_target"] == 40
    checks = {c["name"]: c for c in g["prechecks"]}
    assert list(checks) == [
        "devices_connected",
        "ins_navigating",
        "gnss_fix",
        "pps_locked",
        "clock_locked",
        "latency_in_band",
        "disk_space",
        "mount_targets",
    ]
    for name in (
        "devices_connected",
        "ins_navigating",
        "gnss_fix",
        "pps_locked",
        "clock_locked",
        "mount_targets",
    ):
        assert checks[name]["ok"] is True, checks[name]
    assert checks["mount_targets"]["detail"] == "mount, 2 targets"
    assert checks["devices_connected"]["detail"] == "3 connected"
    assert checks["clock_locked"]["detail"].startswith("LOCKED")
    # the fake vessel lies ~700 m from the site, heading 57°: pass 1 is the next line
    assert g["active"]["pass_id"] == 1 and g["active"]["state"] == "approach"
    assert 500 < g["active"]["range_to_targets_m"] < 1500
    assert g["vessel"]["lat_deg"] == pytest.approx(45.5, abs=1e-3)
    assert g["sigma"]["current"]["passes"] == [] and len(g["sigma"]["ranking"]) == 6
    n_nav = len(fake.epochs)
    assert out["records"] >= n_nav  # every nav record (and the profiles) went through the tap
    assert g["counters"]["nav_without_time"] == 0
    # MQTT: the retained checklist topic carries the same sections
    msgs = mqtt.topic("checklist")
    assert msgs and msgs[-1].topic == "guidetest/guide-1/checklist"
    last = msgs[-1].data
    assert last["guidance"]["schema"] == "mls.checklist/1" and "presurvey" in last
    assert last["guidance"]["plan"] == g["plan"]
    assert any(
        m.data["guidance"]["prechecks"]
        and all(c["ok"] for c in m.data["guidance"]["prechecks"] if c["name"] != "latency_in_band")
        for m in msgs
        if "guidance" in m.data
    )
