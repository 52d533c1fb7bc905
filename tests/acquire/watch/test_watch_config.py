"""The vessel config's ``watch`` section: defaults, the calibration path relative to the config,
one clear error per bad field, what it needs (the calibrated mount, the site file), the shipped
example, and the calibrated mount the daemon watches (``mls acquire --check`` says it)."""

from __future__ import annotations

import math
import re
import subprocess
import textwrap
from pathlib import Path

import numpy as np
import pytest

from acquire.daemon.config import VesselConfigError, load_vessel_config, parse_vessel_config
from acquire.daemon.configschema import WatchConfig
from acquire.watch.daemon import design_of, mount_watch_consumer, watch_model
from tests.acquire.daemon_util import MLS, ROOT
from tests.acquire.watch.records import write_result


@pytest.fixture(scope="module")
def site_file(tmp_path_factory) -> Path:
    from calib.sim.simulate import simulate

    path = tmp_path_factory.mktemp("site") / "site.yaml"
    simulate("montreal", 0).site.dump(path)
    return path


def _vessel(site: Path | None, extra: str = "") -> str:
    return (
        textwrap.dedent("""\
        vessel: watch-1
        devices:
          - {name: ins, kind: ins, protocol: nmea, transport: {type: udp, host: 127.0.0.1, port: 7001}}
        session: {directory: sessions}
        mount: {lever_arm_m: [0.1, 0.2, -1.0], nominal_deg: [0, 0, 90], boresight_apriori_deg: [0.5, 0, 0]}
        """)
        + (f"site_file: {site}\n" if site else "")
        + extra
    )


def test_without_a_watch_section_there_is_no_watch(site_file):
    cfg = parse_vessel_config(_vessel(site_file))
    assert cfg.watch == WatchConfig() and not cfg.watch.active
    assert mount_watch_consumer(cfg, sup=None) is None
    cfg = parse_vessel_config(_vessel(site_file, "watch: {enabled: false}\n"))
    assert not cfg.watch.active and mount_watch_consumer(cfg, sup=None) is None


def test_the_calibration_is_relative_to_the_config_and_gives_the_calibrated_mount(site_file, tmp_path):
    (tmp_path / "calib").mkdir()
    write_result(
        tmp_path / "calib" / "result.json", (0.21, 1.25, 0.15), {"latency_s": 0.002, "range_offset_m": 0.01}
    )
    path = tmp_path / "vessel.yaml"
    path.write_text(
        _vessel(
            site_file,
            "watch: {calibration: calib, shift_deg: 0.2, false_alarms_per_hour: 0.1, min_line_s: 30}\n",
        )
    )
    cfg = load_vessel_config(path)
    w = cfg.watch
    assert w.calibration == tmp_path / "calib" / "result.json" and w.active  # a directory: its result.json
    assert (w.shift_deg, w.false_alarms_per_hour, w.min_line_s) == (0.2, 0.1, 30.0)
    assert (w.max_points_per_s, w.max_line_s) == (20_000, 900.0)
    model, info = watch_model(cfg)
    np.testing.assert_allclose(np.degrees(model.mount.boresight_rad), [0.21, 1.25, 0.15])
    np.testing.assert_allclose(model.mount.lever_arm_m, [0.1, 0.2, -1.0])  # the vessel config's
    np.testing.assert_allclose(np.degrees(model.mount.nominal_rad), [0, 0, 90])
    assert model.mount.time_offset_s == 0.002 and model.mount.range_offset_m == 0.01
    from calib.io.site import load_site

    site = load_site(site_file)
    assert model.frame == site.reference and model.wall_azimuth_rad == site.wall_azimuth_rad
    assert info["boresight_deg"] == pytest.approx([0.21, 1.25, 0.15])
    d = design_of(cfg)
    assert d.shift_rad == pytest.approx(math.radians(0.2)) and d.false_alarms_per_hour == 0.1
    # mls acquire --check says what the daemon will watch
    r = subprocess.run(
        [*MLS, "acquire", "--config", str(path), "--check"],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        timeout=60,
    )
    assert r.returncode == 0, r.stderr
    out = " ".join(r.stdout.split())
    assert "mount watch: calibrated boresight roll +0.2100°, pitch +1.2500°, yaw +0.1500°" in out
    assert "tuned to 0.2°, 0.1 false alarms per hour; 20000 returns/s kept; lines of 30–900 s" in out


def test_watch_section_errors_name_the_line_the_key_and_what_was_expected(site_file, tmp_path):
    write_result(tmp_path / "result.json", (0, 0, 0))
    (tmp_path / "broken.json").write_text('{"boresight_deg": {"roll": 0}}')
    text = _vessel(
        site_file,
        textwrap.dedent(f"""\
        watch:
          calibration: {tmp_path}/broken.json
          shift_deg: -0.1
          false_alarms_per_hour: often
          max_points_per_s: 50
          min_line_s: 30
          max_line_s: 20
          colour: red
        """),
    )
    with pytest.raises(VesselConfigError) as e:
        parse_vessel_config(text, source="v.yaml")
    errs = e.value.errors
    line = {ln.strip().split(":")[0]: i + 1 for i, ln in enumerate(text.splitlines())}
    assert errs == [
        f"v.yaml:{line['calibration']}:16: watch.calibration: got '{tmp_path}/broken.json', expected a "
        f"calibration result.json ({tmp_path}/broken.json: required field 'sigma_deg' is missing)",
        f"v.yaml:{line['shift_deg']}:14: watch.shift_deg: got -0.1, expected a number > 0",
        f"v.yaml:{line['false_alarms_per_hour']}:26: watch.false_alarms_per_hour: got 'often', expected a "
        f"finite number",
        f"v.yaml:{line['max_points_per_s']}:21: watch.max_points_per_s: got 50, expected an integer ≥ 100",
        f"v.yaml:{line['max_line_s']}:15: watch.max_line_s: got 20, expected a number ≥ 60",
        f"v.yaml:{line['colour']}:11: watch.colour: unknown key 'colour'; allowed keys here: calibration, enabled, "
        f"false_alarms_per_hour, max_line_s, max_points_per_s, min_line_s, shift_deg",
    ]
    with pytest.raises(VesselConfigError) as e:
        parse_vessel_config(
            _vessel(site_file, "watch: {max_line_s: 100, min_line_s: 200}\n"), source="v.yaml"
        )
    assert e.value.errors == [
        "v.yaml:7:8: watch: the mount watch needs the calibrated mount: add watch.calibration (a "
        "calibration result.json; or set watch.enabled: false)",
        "v.yaml:7:21: watch.max_line_s: got 100, expected a number > min_line_s (200)",
    ]
    with pytest.raises(VesselConfigError) as e:
        parse_vessel_config(
            _vessel(None, f"watch: {{calibration: {tmp_path}/nowhere.json}}\n"), source="v.yaml"
        )
    assert e.value.errors == [
        "v.yaml:6:8: watch: the mount watch needs the site's frame, wall azimuth and sigmas: add "
        "site_file (or set watch.enabled: false)",
        f"v.yaml:6:22: watch.calibration: got '{tmp_path}/nowhere.json', expected a calibration "
        f"result.json ({tmp_path}/nowhere.json not found)",
    ]


def test_the_shipped_example_documents_the_defaults(site_file, tmp_path):
    """systemd/vessel.example.yaml's commented watch section, switched on, is the default (with
    its calibration)."""
    text = (ROOT / "systemd" / "vessel.example.yaml").read_text()
    text = text.replace("# site_file: site.yaml", f"site_file: {site_file}")
    block = re.search(r"^# watch:.*?(?=\n\n|\Z)", text, flags=re.M | re.S)
    assert block is not None
    text = text.replace(block[0], re.sub(r"^# (watch:|  \w)", r"\1", block[0], flags=re.M))
    (tmp_path / "calib").mkdir()
    write_result(tmp_path / "calib" / "result.json", (0, 0, 0))
    path = tmp_path / "vessel.yaml"
    path.write_text(text)
    w = load_vessel_config(path).watch
    assert "\nwatch:" in text and w == WatchConfig(calibration=tmp_path / "calib" / "result.json")
