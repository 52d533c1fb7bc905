"""The ``mqtt`` section of the vessel config: ``tls``, and when commands may be enabled."""

from __future__ import annotations

import os
import re

import pytest

from acquire.daemon.config import VesselConfigError, parse_vessel_config

HEAD = (
    "vessel: v\ndevices:\n  - {name: ins, kind: ins, protocol: stdbin, "
    "transport: {type: tcp, host: 10.0.0.2, port: 8110}}\nsession: {directory: logs}\n"
)  # 4 lines: the mqtt section starts on line 5


def parse(mqtt: str, base):
    return parse_vessel_config(HEAD + "mqtt:\n" + mqtt, source="vessel.yaml", base_dir=base)


def errors(mqtt: str, base) -> list[str]:
    with pytest.raises(VesselConfigError) as exc:
        parse(mqtt, base)
    return exc.value.errors


@pytest.fixture
def certs(tmp_path, pki):
    """The test PKI's files next to the config (relative paths), and credentials."""
    for name, src in (("ca.crt", pki.ca), ("client.crt", pki.client_cert), ("client.key", pki.client_key)):
        (tmp_path / name).write_bytes(src.read_bytes())
    os.chmod(tmp_path / "client.key", 0o600)
    (tmp_path / "server.key").write_bytes(pki.server_key.read_bytes())
    os.chmod(tmp_path / "server.key", 0o600)
    cred = tmp_path / "cred.yaml"
    cred.write_text("username: boat\npassword: s3cret\n")
    os.chmod(cred, 0o600)
    return tmp_path


def test_tls_section_is_parsed_with_paths_relative_to_the_config(certs):
    cfg = parse(
        "  host: shore.example.org\n  credentials_file: cred.yaml\n  commands_enabled: true\n"
        "  tls: {ca_file: ca.crt, cert_file: client.crt, key_file: client.key}\n",
        certs,
    )
    tls = cfg.mqtt.tls
    assert (tls.ca_file, tls.cert_file, tls.key_file) == (
        certs / "ca.crt",
        certs / "client.crt",
        certs / "client.key",
    )
    assert tls.verify_hostname is True and cfg.mqtt.port == 8883  # the MQTT-over-TLS port by default
    assert (
        parse("  host: b\n  port: 8884\n  tls: {ca_file: ca.crt, verify_hostname: false}\n", certs).mqtt.port
        == 8884
    )


def test_bad_tls_files_are_errors_naming_file_line_and_key(certs):
    (certs / "junk.crt").write_text("not a certificate\n")
    (certs / "open.key").write_bytes((certs / "client.key").read_bytes())
    os.chmod(certs / "open.key", 0o644)
    errs = errors(
        "  host: b\n"
        "  tls:\n"
        "    ca_file: nope.crt\n"  # line 8
        "    cert_file: junk.crt\n"
        "    key_file: open.key\n"
        "    verify: true\n",
        certs,
    )
    assert len(errs) == 4, errs
    assert re.match(
        r"vessel\.yaml:8:\d+: mqtt\.tls\.ca_file: got 'nope\.crt', expected a readable PEM file", errs[0]
    )
    assert errs[1].startswith("vessel.yaml:9:") and "no '-----BEGIN' block" in errs[1]
    assert (
        errs[2].startswith("vessel.yaml:10:")
        and "not readable by others" in errs[2]
        and "chmod 600" in errs[2]
    )
    assert errs[3].startswith("vessel.yaml:11:") and "unknown key 'verify'" in errs[3]


def test_a_key_without_its_certificate_or_of_another_certificate_is_an_error(certs):
    errs = errors("  host: b\n  tls: {ca_file: ca.crt, key_file: client.key}\n", certs)
    assert len(errs) == 1 and "a client key needs its certificate: add cert_file" in errs[0]
    errs = errors("  host: b\n  tls: {ca_file: ca.crt, cert_file: client.crt, key_file: server.key}\n", certs)
    assert len(errs) == 1 and "mqtt.tls.cert_file" in errs[0] and "cannot be used together" in errs[0]


def test_commands_to_a_remote_broker_need_tls_and_credentials_or_an_explicit_opt_in(certs):
    errs = errors("  host: shore.example.org\n  commands_enabled: true\n", certs)
    assert len(errs) == 1
    assert errs[0].startswith("vessel.yaml:7:") and "mqtt.commands_enabled" in errs[0]
    assert "need TLS with credentials; TLS (mqtt.tls) missing" in errs[0]
    assert "commands_insecure_ok: true" in errs[0]
    errs = errors("  host: 10.1.2.3\n  commands_enabled: true\n  tls: {ca_file: ca.crt}\n", certs)
    assert len(errs) == 1 and "credentials (credentials_file) missing" in errs[0]
    # allowed: loopback; TLS with credentials; the explicit opt-in; commands disabled
    for ok in (
        "  host: 127.0.0.1\n  commands_enabled: true\n",
        "  host: localhost\n  commands_enabled: true\n",
        "  host: '::1'\n  commands_enabled: true\n",
        "  host: 10.1.2.3\n  commands_enabled: true\n  credentials_file: cred.yaml\n  tls: {ca_file: ca.crt}\n",
        "  host: 10.1.2.3\n  commands_enabled: true\n  commands_insecure_ok: true\n",
        "  host: 10.1.2.3\n  commands_enabled: false\n",
    ):
        assert parse(ok, certs).mqtt is not None, ok
