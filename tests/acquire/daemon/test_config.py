"""Vessel config: the shipped example validates; every bad field is reported, each once."""

from __future__ import annotations

import os
import re
from pathlib import Path

import pytest

from acquire.daemon.config import VesselConfigError, load_vessel_config, parse_vessel_config

ROOT = Path(__file__).resolve().parents[3]
EXAMPLE = ROOT / "systemd" / "vessel.example.yaml"


def test_the_shipped_example_validates():
    cfg = load_vessel_config(EXAMPLE)
    assert cfg.vessel == "survey-1"
    assert [d.name for d in cfg.devices] == ["ins", "profiler", "pps", "marks"]
    ins = cfg.device("ins")
    assert (ins.kind, ins.protocol, ins.transport.type, ins.transport.baud) == (
        "ins",
        "nmea",
        "serial",
        115200,
    )
    assert ins.latency.band_ns == (0, 30_000_000) and ins.latency.rate_hz == 200.0
    assert ins.latency.gap_ns == 500_000_000
    pps = cfg.device("pps")
    assert pps.source.type == "kernel" and pps.source.device == "/dev/pps0"
    assert pps.time_device == "ins" and pps.time_messages == ("ZDA", "TIME__")
    assert cfg.device("profiler").transport.port == 3000
    assert cfg.devices_of("can")[0].transport.bitrate == 500_000
    assert cfg.session_dir == Path("/var/lib/mls/sessions")
    assert cfg.session.flush_s == 0.5 and cfg.session.rotate_bytes == 512 * 2**20
    assert cfg.clock.gate_floor_ns == 250_000 and cfg.clock.holdover_limit_ns == 200_000
    assert cfg.mqtt.topic_prefix == "mls" and cfg.mqtt.commands_enabled is False
    assert cfg.mount.nominal_deg == (0.0, 0.0, 90.0)
    assert cfg.status.socket == Path("/run/mls/status.sock")


BAD = """\
vessel: survey 1
colour: red
devices:
  - name: ins
    kind: ins
    protocol: nmea0183
    transport: {type: serial, port: ttyUSB0, baud: 11520}
    latency: {band_ms: [30, 0], gap_s: -1}
  - name: profiler
    kind: profiler
    protocol: zfp1
    transport: {type: serial, port: /dev/ttyS1, baud: 9600}
  - name: ins
    kind: lidar
  - name: pps
    kind: pps
    source: {type: kernel}
    time_device: profiler
  - name: udp
    kind: ins
    protocol: stdbin
    transport: {type: udp, host: 0.0.0.0, port: 70000}
session:
  directory: sessions
  flush_s: 2.0
  compression: gzip
mqtt:
  host: broker
  topic_prefix: mls/#
"""

EXPECTED = [
    (1, 9, "vessel", "'survey 1'", "a name of letters"),
    (2, 9, "colour", None, "unknown key 'colour'"),
    (6, 15, "devices[0].protocol", "'nmea0183'", "one of nmea, stdbin"),
    (7, 37, "devices[0].transport.port", "'ttyUSB0'", "an absolute path"),
    (7, 52, "devices[0].transport.baud", "11520", "one of 4800, 9600"),
    (8, 24, "devices[0].latency.band_ms", "[30, 0]", "low < high"),
    (8, 40, "devices[0].latency.gap_s", "-1", "a number > 0"),
    (12, 23, "devices[1].transport.type", "'serial'", "one of udp, tcp"),
    (13, 11, "devices[2].name", None, "device name 'ins' is used twice (first at devices[0].name)"),
    (14, 11, "devices[2].kind", "'lidar'", "one of ins, profiler, pps, can"),
    (17, 13, "devices[3].source", None, "missing required key 'device' for a kernel PPS source"),
    (15, 5, "devices[3].time_device", "'profiler'", "the name of an ins device (ins, udp)"),
    (19, 5, "devices[4]: a second ins", None, "('udp'; the first, 'ins', at bad.yaml:4)"),
    (22, 49, "devices[4].transport.port", "70000", "an integer between 1 and 65535"),
    (25, 12, "session.flush_s", "2.0", "a number ≤ 1"),
    (26, 16, "session.compression", "'gzip'", "one of zstd, lz4, none"),
    (29, 17, "mqtt.topic_prefix", "'mls/#'", "without wildcards"),
]


def test_every_bad_field_gets_one_error_naming_place_key_value_and_expectation():
    with pytest.raises(VesselConfigError) as exc:
        parse_vessel_config(BAD, source="bad.yaml", base_dir="/etc/mls")
    errors = exc.value.errors
    assert len(errors) == len(EXPECTED), "\n".join(errors)
    for line, col, key, value, expectation in EXPECTED:
        hits = [e for e in errors if e.startswith(f"bad.yaml:{line}:{col}: {key}")]
        assert len(hits) == 1, (key, errors)
        if value is not None:
            assert f"got {value}" in hits[0], hits[0]
        assert expectation in hits[0], hits[0]
    assert str(exc.value).startswith(f"bad.yaml: {len(EXPECTED)} errors:\n  bad.yaml:1:9: vessel")


def _minimal(**extra) -> str:
    text = (
        "vessel: v\ndevices:\n  - {name: ins, kind: ins, protocol: stdbin, "
        "transport: {type: tcp, host: 10.0.0.2, port: 8110}}\nsession: {directory: logs}\n"
    )
    return text + "".join(f"{k}: {v}\n" for k, v in extra.items())


def test_relative_paths_defaults_and_pps_default_time_messages(tmp_path):
    cfg = parse_vessel_config(_minimal(status="{socket: run/status.sock}"), base_dir=tmp_path)
    assert cfg.session_dir == tmp_path / "logs"
    assert cfg.status.socket == tmp_path / "run" / "status.sock"
    assert cfg.mqtt is None and cfg.mount is None and cfg.site_file is None
    text = _minimal().replace(
        "devices:\n",
        "devices:\n  - {name: pps, kind: pps, source: "
        "{type: udp, host: 127.0.0.1, port: 5600}, time_device: ins}\n",
    )
    pps = parse_vessel_config(text).device("pps")
    assert pps.source.udp_port == 5600 and pps.time_messages == ("validity_time",)


def test_missing_sections_and_unknown_device_keys_are_each_reported():
    with pytest.raises(VesselConfigError) as exc:
        parse_vessel_config("vessel: v\ndevices:\n  - {name: a, kind: ins, baudrate: 9600}\n")
    errs = exc.value.errors
    assert any("<top level>: missing required key 'session'" in e for e in errs)
    assert any("devices[0].baudrate: unknown key 'baudrate'" in e for e in errs)
    assert any("devices[0]: missing required key 'protocol' for a device of kind ins" in e for e in errs)
    assert any("devices[0]: missing required key 'transport' for a device of kind ins" in e for e in errs)
    assert len(errs) == 4, errs


def test_credentials_file_must_exist_and_not_be_world_readable(tmp_path):
    cred = tmp_path / "cred.yaml"
    cred.write_text("username: boat\npassword: s3cret\n")
    os.chmod(cred, 0o644)
    mqtt = "{host: broker, credentials_file: cred.yaml}"
    with pytest.raises(VesselConfigError, match=r"not readable by others .*-rw-r--r--.*chmod 600"):
        parse_vessel_config(_minimal(mqtt=mqtt), base_dir=tmp_path)
    os.chmod(cred, 0o600)
    cfg = parse_vessel_config(_minimal(mqtt=mqtt), base_dir=tmp_path)
    assert (cfg.mqtt.username, cfg.mqtt.password) == ("boat", "s3cret")
    with pytest.raises(VesselConfigError, match="readable credentials file"):
        parse_vessel_config(_minimal(mqtt="{host: b, credentials_file: nope.yaml}"), base_dir=tmp_path)


def test_site_file_is_checked_with_the_site_reader(tmp_path):
    with pytest.raises(VesselConfigError, match="an existing site file"):
        parse_vessel_config(_minimal(site_file="site.yaml"), base_dir=tmp_path)
    (tmp_path / "site.yaml").write_text("mount: {}\ntargets: []\nstandoff_m: -3\n")
    with pytest.raises(VesselConfigError, match=re.escape("standoff_m: got -3")):
        parse_vessel_config(_minimal(site_file="site.yaml"), base_dir=tmp_path)


def test_disk_low_thresholds_default_and_are_checked():
    s = parse_vessel_config(_minimal()).session
    assert (s.disk_warning_bytes, s.disk_critical_bytes) == (10 * 2**30, 2 * 2**30)
    assert load_vessel_config(EXAMPLE).session.disk_critical_bytes == 2 * 2**30
    text = _minimal().replace("{directory: logs}", "{directory: logs, disk_warning_mb: 500}")
    s = parse_vessel_config(text).session  # a lower warning lowers the default critical level
    assert (s.disk_warning_bytes, s.disk_critical_bytes) == (500 * 2**20, 100 * 2**20)
    text = _minimal().replace(
        "{directory: logs}", "{directory: logs, disk_warning_mb: 500, disk_critical_mb: 600}"
    )
    with pytest.raises(
        VesselConfigError,
        match=r"session.disk_critical_mb: got 600, expected a number ≤ disk_warning_mb \(500\)",
    ):
        parse_vessel_config(text)
