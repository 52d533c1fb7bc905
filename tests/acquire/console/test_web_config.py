"""The vessel config's ``web`` section: defaults, one error per bad field naming file:line:column
and the key, HTTPS required off loopback, the operator token's file kept private."""

from __future__ import annotations

import dataclasses
import textwrap

import pytest

from acquire.console.daemon import console_consumer
from acquire.console.server import ConsoleRefused
from acquire.daemon.config import VesselConfigError, parse_vessel_config
from acquire.daemon.configschema import WebConfig
from acquire.daemon.supervisor import Supervisor
from acquire.foxglove.daemon import foxglove_consumer
from tests.mosquitto import make_test_pki

BASE = textwrap.dedent("""\
    vessel: v1
    devices:
      - {name: ins, kind: ins, protocol: nmea, transport: {type: udp, host: 127.0.0.1, port: 7001}}
    session: {directory: sessions}
    """)


def _token(tmp_path, text: str = "token: abcdefghijklmnop\n", mode: int = 0o600):
    path = tmp_path / "web-token.yaml"
    path.write_text(text)
    path.chmod(mode)
    return path


def test_no_section_no_console_and_an_empty_one_is_the_defaults(tmp_path):
    assert parse_vessel_config(BASE).web is None
    web = parse_vessel_config(BASE + "web: {}\n").web
    assert web == WebConfig()
    assert web.host == "127.0.0.1"
    assert web.token is None


def test_the_token_comes_from_a_private_credentials_file_and_is_never_shown(tmp_path):
    _token(tmp_path)
    cfg = parse_vessel_config(
        BASE + "web: {port: 9000, credentials_file: web-token.yaml}\n", base_dir=tmp_path
    )
    assert cfg.web is not None
    assert cfg.web.token == "abcdefghijklmnop"
    assert cfg.web.port == 9000
    assert "abcdefghijklmnop" not in repr(cfg)


def test_each_bad_field_is_an_error_naming_the_line_and_the_key(tmp_path):
    _token(tmp_path, mode=0o644)
    text = BASE + textwrap.dedent("""\
        web:
          host: 0.0.0.0
          port: 70000
          credentials_file: web-token.yaml
          foxglove_port: 0
          colour: red
        """)
    with pytest.raises(VesselConfigError) as e:
        parse_vessel_config(text, source="v.yaml", base_dir=tmp_path)
    errs = e.value.errors
    assert errs[0].startswith(
        "v.yaml:6:9: web.host: got '0.0.0.0', not loopback: the console is served over HTTPS"
    )
    assert errs[1] == "v.yaml:7:9: web.port: got 70000, expected an integer between 1 and 65535"
    assert errs[2].startswith(
        "v.yaml:8:21: web.credentials_file: got 'web-token.yaml', expected a credentials file not readable by others"
    )
    assert errs[3] == "v.yaml:9:18: web.foxglove_port: got 0, expected an integer ≥ 1"
    assert errs[4].startswith("v.yaml:10:11: web.colour: unknown key 'colour'")
    assert len(errs) == 5


def test_a_short_token_and_a_port_shared_with_foxglove_are_refused(tmp_path):
    _token(tmp_path, "token: short\n")
    text = BASE + "web: {port: 8480, foxglove_port: 8480, credentials_file: web-token.yaml}\n"
    with pytest.raises(VesselConfigError) as e:
        parse_vessel_config(text, source="v.yaml", base_dir=tmp_path)
    assert any("a token of at least 16 characters" in err for err in e.value.errors)
    assert any("web.foxglove_port: got 8480, the console's own port" in err for err in e.value.errors)


def test_off_loopback_with_tls_the_console_is_configured(tmp_path):
    pki = make_test_pki(tmp_path / "pki")
    pki.server_key.chmod(0o600)
    pki.client_key.chmod(0o600)
    text = (
        BASE + f"web: {{host: 0.0.0.0, tls: {{cert_file: {pki.server_cert}, key_file: {pki.server_key}}}}}\n"
    )
    web = parse_vessel_config(text).web
    assert web is not None
    assert web.cert_file == pki.server_cert
    assert web.key_file == pki.server_key
    mismatched = BASE + f"web: {{tls: {{cert_file: {pki.server_cert}, key_file: {pki.client_key}}}}}\n"
    with pytest.raises(VesselConfigError, match="cannot be used together"):
        parse_vessel_config(mismatched)
    pki.server_key.chmod(0o644)
    with pytest.raises(VesselConfigError, match="server key file not readable by others"):
        parse_vessel_config(text)


def test_a_console_off_loopback_without_tls_is_refused_at_start_up():
    cfg = parse_vessel_config(BASE + "web: {}\n")
    forced = dataclasses.replace(cfg, web=WebConfig(host="192.0.2.1"))  # past the config's check
    with pytest.raises(ConsoleRefused, match="needs TLS"):
        console_consumer(forced, Supervisor(forced))


def test_a_foxglove_port_gives_the_daemon_its_live_server_beside_the_console():
    cfg = parse_vessel_config(BASE + "web: {foxglove_port: 8765}\n")
    sup = Supervisor(cfg)
    assert console_consumer(cfg, sup) is not None
    live = foxglove_consumer(cfg, sup)
    assert live is not None and live.name == "foxglove"
    assert (live.web.host, live.web.foxglove_port) == ("127.0.0.1", 8765)
    assert live.options.frame is None and live.options.mount is None  # no site file, no mount
    assert live.options.devices == ("ins",)
    plain = parse_vessel_config(BASE + "web: {}\n")
    assert foxglove_consumer(plain, Supervisor(plain)) is None


def test_foxglove_live_over_tls_needs_a_pkcs8_key_and_says_how_to_convert_one(tmp_path):
    import subprocess

    pki = make_test_pki(tmp_path / "pki")
    pki.server_key.chmod(0o600)
    tls = f"tls: {{cert_file: {pki.server_cert}, key_file: KEY}}"
    text = BASE + "web: {host: 0.0.0.0, foxglove_port: 8765, " + tls + "}\n"
    with pytest.raises(VesselConfigError) as e:  # ecparam writes a traditional EC key
        parse_vessel_config(text.replace("KEY", str(pki.server_key)))
    assert any(
        "web.tls" in err and f"key_file {pki.server_key} is not PKCS#8" in err and "openssl pkcs8" in err
        for err in e.value.errors
    ), e.value.errors
    pkcs8 = tmp_path / "server-pkcs8.key"
    subprocess.run(
        ["openssl", "pkcs8", "-topk8", "-nocrypt", "-in", pki.server_key, "-out", pkcs8],
        check=True,
        timeout=60,
    )
    pkcs8.chmod(0o600)
    web = parse_vessel_config(text.replace("KEY", str(pkcs8))).web
    assert web is not None and web.key_file == pkcs8 and web.foxglove_port == 8765
