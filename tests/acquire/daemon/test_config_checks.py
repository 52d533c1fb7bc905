"""The vessel config's checks across fields (issue 26): ports two devices would both listen on,
the vessel name's length, a second ins device — each naming file:line — and ``mls acquire
--check`` test-binding the ports and showing a UDP PPS source with its port."""

from __future__ import annotations

import socket

import pytest
from typer.testing import CliRunner

from acquire.daemon.config import VesselConfigError, parse_vessel_config
from cli.app import app
from tests.acquire.daemon_util import free_port


def _config(devices: str, vessel: str = "survey-1") -> str:
    return f"vessel: {vessel}\ndevices:\n{devices}session: {{directory: logs}}\n"


INS = "  - {name: ins, kind: ins, protocol: stdbin, transport: {type: tcp, host: 10.0.0.2, port: 8110}}\n"
ZF = "  - {name: zf, kind: profiler, protocol: zfp1, transport: {type: udp, host: 0.0.0.0, port: 3000}}\n"


def _pps(host: str, port: int) -> str:
    return (
        f"  - {{name: pps, kind: pps, source: {{type: udp, host: {host}, port: {port}}}, time_device: ins}}\n"
    )


def _errors(text: str) -> list[str]:
    with pytest.raises(VesselConfigError) as exc:
        parse_vessel_config(text, source="v.yaml")
    return exc.value.errors


def test_a_pps_source_on_the_profilers_udp_port_names_both_devices_and_lines():
    (err,) = _errors(_config(INS + ZF + _pps("127.0.0.1", 3000)))
    assert err.startswith("v.yaml:5:71: "), err
    assert "devices[2].source.port: udp port 3000 of device 'pps' (127.0.0.1)" in err
    assert "is also the port of device 'zf' (0.0.0.0, at v.yaml:4)" in err


def test_the_same_port_on_two_distinct_addresses_is_no_collision():
    text = _config(INS + ZF.replace("0.0.0.0", "192.168.1.5") + _pps("127.0.0.1", 3000))
    assert parse_vessel_config(text).device("pps").source.udp_port == 3000


def test_a_vessel_name_longer_than_64_characters_is_refused_with_its_line():
    (err,) = _errors(_config(INS, vessel="a" * 300))
    assert err.startswith("v.yaml:1:9: vessel: got 'aaa")
    assert "at most 64 characters (got 300)" in err
    assert parse_vessel_config(_config(INS, vessel="b" * 64)).vessel == "b" * 64
    (err,) = _errors(_config(INS, vessel="survey/1"))
    assert "v.yaml:1:9: vessel" in err and "letters, digits" in err


def test_two_ins_devices_are_one_error_naming_both_lines():
    second = INS.replace("name: ins", "name: ins2").replace("10.0.0.2", "10.0.0.3")
    (err,) = _errors(_config(INS + second))
    assert err.startswith(
        "v.yaml:4:5: devices[1]: a second ins device ('ins2'; the first, 'ins', at v.yaml:3)"
    )
    assert "one /ins/raw channel" in err


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _write(tmp_path, text: str):
    path = tmp_path / "vessel.yaml"
    path.write_text(text)
    return path


def test_check_shows_a_udp_pps_source_with_its_port(tmp_path):
    port = _free_udp_port()
    path = _write(tmp_path, _config(INS + _pps("127.0.0.1", port)))
    r = CliRunner().invoke(app, ["acquire", "--config", str(path), "--check"], env={"COLUMNS": "200"})
    assert r.exit_code == 0, r.output
    assert f"udp PPS 127.0.0.1:{port}" in r.output and "None" not in r.output


def test_check_fails_naming_the_device_whose_port_another_process_holds(tmp_path):
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as holder:
        holder.bind(("127.0.0.1", 0))
        port = holder.getsockname()[1]
        path = _write(tmp_path, _config(INS + _pps("127.0.0.1", port)))
        r = CliRunner().invoke(app, ["acquire", "--config", str(path), "--check"], env={"COLUMNS": "200"})
    assert r.exit_code == 1, r.output
    assert f"device 'pps': cannot bind udp 127.0.0.1:{port}" in r.output
    assert "1 port(s) cannot be bound" in r.output


def test_check_names_the_console_or_foxglove_port_another_process_holds(tmp_path):
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as holder:
        holder.bind(("127.0.0.1", 0))
        holder.listen()
        port = holder.getsockname()[1]
        web_port = free_port(socket.SOCK_STREAM)
        text = _config(INS) + f"web: {{port: {web_port}, foxglove_port: {port}}}\n"
        r = CliRunner().invoke(app, ["acquire", "--config", str(_write(tmp_path, text)), "--check"])
    assert r.exit_code == 1, r.output
    assert f"web.foxglove_port (Foxglove live): cannot bind tcp 127.0.0.1:{port}" in r.output
    assert "web.port" not in r.output  # the console's port is free
    assert "1 port(s) cannot be bound" in r.output


def test_check_refuses_a_session_root_others_can_write_and_makes_none(tmp_path):
    port = _free_udp_port()
    path = _write(tmp_path, _config(INS + _pps("127.0.0.1", port)))
    r = CliRunner().invoke(app, ["acquire", "--config", str(path), "--check"], env={"COLUMNS": "200"})
    assert r.exit_code == 0, r.output
    assert not (tmp_path / "logs").exists()  # a check makes nothing; the daemon makes the root
    (tmp_path / "logs").mkdir()
    (tmp_path / "logs").chmod(0o777)
    r = CliRunner().invoke(app, ["acquire", "--config", str(path), "--check"], env={"COLUMNS": "200"})
    assert r.exit_code == 1, r.output
    assert f"{path}: " in r.output and "session root" in r.output and str(tmp_path / "logs") in r.output
