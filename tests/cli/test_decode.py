"""``mls decode`` end to end through the CLI (typer's runner): JSON fields, summaries, timing, errors."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
from typer.testing import CliRunner

from cli.app import app
from drivers.zf.zfp1 import encode_profile
from tests.drivers.helpers import real_file

runner = CliRunner()


def _json_lines(output: str) -> list[dict]:
    return [json.loads(line) for line in output.splitlines() if line.startswith("{")]


def test_stdbin_json_has_the_native_field_names():
    res = runner.invoke(
        app, ["decode", str(real_file("ixblue-stdbin", "log_STDBIN_V2.log")), "--format", "stdbin", "--json"]
    )
    assert res.exit_code == 0, res.output
    (rec,) = _json_lines(res.stdout)
    for key in (
        "protocol_version",
        "counter",
        "validity_time_100us",
        "heading_deg",
        "roll_deg",
        "pitch_deg",
        "latitude_deg",
        "longitude_deg",
        "altitude_m",
        "system_date",
        "ins_algorithm_status",
        "ins_system_status",
        "ins_user_status",
        "utc_detected",
        "pps_detected",
    ):
        assert key in rec, key
    assert (
        rec["system_date"] == {"day": 1, "month": 1, "year": 2006} and rec["validity_time_100us"] == 9215311
    )
    assert abs(rec["heading_deg"] - 209.982) < 1e-4
    assert "summary: 1 records; 286 bytes; 0 rejected" in res.stderr


def test_pcapng_summary_and_timing():
    res = runner.invoke(
        app,
        [
            "decode",
            str(real_file("ixblue-stdbin", "stdbin_V5_2Hz.pcapng")),
            "-f",
            "pcapng",
            "--payload",
            "stdbin",
            "--port",
            "8200",
            "--timing",
        ],
    )
    assert res.exit_code == 0, res.output
    assert (
        "summary: 40 records; 15680 bytes; 0 rejected; capture: 40 packets, 40 UDP datagrams decoded"
        in res.stdout
    )
    assert "drift_ppm" in res.stdout and "-38.1" in res.stdout


def test_nmea_nav_records_in_degrees_at_the_edge():
    res = runner.invoke(
        app,
        [
            "decode",
            str(real_file("openrvdas-nbp1406", "NBP1406_seap-2014-08-01")),
            "-f",
            "nmea",
            "--nav",
            "--json",
        ],
    )
    assert res.exit_code == 0, res.output
    recs = _json_lines(res.stdout)
    assert len(recs) > 700 and recs[0]["type"] == "nav" and recs[0]["date_source"] == "zda"
    assert recs[0]["heading_deg"] == 218.83 and "heading_rad" not in recs[0]


def test_zfp_dump_and_rejections_reported(tmp_path):
    dgs = encode_profile(
        1, 10**18, 1000, 0, 100, np.arange(1, 501, dtype=np.uint32), np.zeros(500, np.uint16)
    )
    bad = bytearray(dgs[1])
    bad[60] ^= 0xFF
    path = tmp_path / "scan.zfp"
    path.write_bytes(b"junk" + dgs[0] + bytes(bad) + b"".join(dgs[2:]))
    res = runner.invoke(app, ["decode", str(path), "-f", "zfp", "--json"])
    assert res.exit_code == 0, res.output
    (prof,) = _json_lines(res.stdout)
    assert prof["type"] == "profile" and not prof["complete"] and prof["packets_received"] == len(dgs) - 1
    assert "1 rejected (bad_crc: 1)" in res.stderr and "packets_lost: 1" in res.stderr


def test_errors_are_clear():
    res = runner.invoke(app, ["decode", "/nonexistent.bin", "-f", "stdbin"])
    assert res.exit_code == 2 and "no such file" in res.output
    res = runner.invoke(app, ["decode", str(real_file("gpsd", "hemi.log")), "-f", "pcapng"])
    assert res.exit_code == 2 and "neither pcapng nor pcap" in res.output


def test_timing_offset_is_signed_not_wrapped_mod_one_day():
    """The V3 capture's INS tags run 6.6 ms ahead of the capture stamps: −0.0066 s, not the
    86399.993 s that ``offset % 86400`` printed."""
    res = runner.invoke(
        app,
        [
            "decode",
            str(real_file("ixblue-stdbin", "stdbin_V3_2Hz.pcapng")),
            "-f",
            "pcapng",
            "--port",
            "8200",
            "--timing",
        ],
        env={"COLUMNS": "120"},
    )
    assert res.exit_code == 0, res.output
    (line,) = [ln for ln in res.stdout.splitlines() if "offset_s" in ln]
    (value,) = re.findall(r"[-+]\d+\.\d+", line)
    assert float(value) == pytest.approx(-0.0066, abs=0.0002) and "86399" not in res.stdout


@pytest.mark.parametrize(
    ("fmt", "content"),
    [
        ("stdbin", "random"),
        ("zfp", "random"),
        ("nmea", "random"),
        ("stdbin", "empty"),
        ("nmea", "empty"),
    ],
)
def test_a_file_without_a_valid_record_fails_and_says_what_was_skipped(tmp_path, fmt, content):
    path = tmp_path / f"{content}.bin"
    data = (
        np.random.default_rng(7).integers(0, 256, 100_000, np.uint8).tobytes() if content == "random" else b""
    )
    path.write_bytes(data)
    res = runner.invoke(app, ["decode", str(path), "-f", fmt])
    assert res.exit_code == 2, res.output
    (line,) = [ln for ln in res.stderr.splitlines() if ln.startswith("error:")]
    assert f"{path}: no valid {fmt} record in {len(data)} bytes (" in line
    if content == "empty":
        assert line.endswith("(the file is empty)")
    else:
        assert re.search(r"\(\d+ bytes skipped", line), line


def test_a_capture_without_a_datagram_on_the_port_fails():
    path = real_file("ixblue-stdbin", "stdbin_V3_2Hz.pcapng")
    res = runner.invoke(app, ["decode", str(path), "-f", "pcapng", "--port", "9999"])
    assert res.exit_code == 2, res.output
    assert (
        f"error: {path}: no valid stdbin record in 17140 bytes (36 packets, 0 UDP datagrams to or "
        "from port 9999; skipped other_port: 36)"
    ) in res.stderr
