"""The vessel config's ``web`` section (:mod:`acquire.daemon.config`): the bridge console
(:mod:`acquire.console`, docs/console.md)::

    web:
      host: 127.0.0.1              # default; any other address needs tls
      port: 8480
      tls: {cert_file: console.crt, key_file: console.key}   # PEM, the key chmod 600
      credentials_file: web-token.yaml                       # token: <≥ 16 characters>, chmod 600
      foxglove_port: 8765          # optional

Every error names the file, line, column and key, as in the other sections.
"""

from __future__ import annotations

import ssl
import stat
from functools import partial
from pathlib import Path

from acquire.daemon.confignodes import Errors, host_name, int_between, mapping_keys, opt, resolved_path
from acquire.daemon.configschema import WebConfig
from acquire.status.mqtt import is_loopback
from calib.io.configfile import Node, load_yaml

MIN_TOKEN_CHARS = 16


def _private(node: Node, path: Path, what: str) -> Path:
    """``path`` readable, and neither readable nor writable by others."""
    try:
        st = path.stat()
        path.read_bytes()  # readable by the daemon
    except OSError as e:
        raise node.fail(f"a readable {what} ({e.strerror})") from None
    if st.st_mode & (stat.S_IROTH | stat.S_IWOTH):
        raise node.fail(
            f"a {what} not readable by others ({path} has mode {stat.filemode(st.st_mode)}; chmod 600 it)"
        )
    return path


def web_token(node: Node, base: Path) -> str:
    """The operator token of ``web.credentials_file``: YAML ``token: …`` of at least
    :data:`MIN_TOKEN_CHARS` characters without spaces, in a file not readable by others."""
    path = _private(node, resolved_path(node, base), "credentials file")
    token_node = load_yaml(path).mapping(required={"token"})["token"]
    token = token_node.string()
    if len(token) < MIN_TOKEN_CHARS or any(c.isspace() for c in token):
        raise token_node.fail(f"a token of at least {MIN_TOKEN_CHARS} characters without spaces")
    return token


def _pem(node: Node, base: Path, what: str, private: bool) -> Path:
    path = resolved_path(node, base)
    if private:
        _private(node, path, f"{what} file")
    try:
        data = path.read_bytes()
    except OSError as e:
        raise node.fail(f"a readable PEM file of the {what} ({e.strerror})") from None
    if b"-----BEGIN " not in data:
        raise node.fail(f"a PEM file of the {what} (no '-----BEGIN' block in {path})")
    return path


def _web_tls(node: Node, errs: Errors, base: Path) -> tuple[Path | None, Path | None]:
    """``web.tls``: the server's certificate and key (PEM), usable together."""
    m = mapping_keys(node, errs, required={"cert_file", "key_file"})
    cert = opt(m, "cert_file", errs, lambda n: _pem(n, base, "server certificate", False), None)
    key = opt(m, "key_file", errs, lambda n: _pem(n, base, "server key", True), None)
    if cert is None or key is None:
        return None, None
    try:
        ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER).load_cert_chain(str(cert), str(key))
    except (OSError, ssl.SSLError) as e:
        errs.add(f"{m['cert_file'].where()}: these TLS files cannot be used together ({e})")
        return None, None
    return cert, key


def _pkcs8(key: Path) -> bool:
    """Whether the PEM key is PKCS#8 (what the Foxglove SDK's TLS takes)."""
    return b"-----BEGIN PRIVATE KEY-----" in key.read_bytes()


def parse_web(node: Node, errs: Errors, base: Path) -> WebConfig:
    """The ``web`` section (module docstring): HTTPS required off loopback."""
    m = mapping_keys(node, errs, optional={"host", "port", "tls", "credentials_file", "foxglove_port"})
    d = WebConfig()
    port = partial(int_between, lo=1, hi=65535)
    cert, key = _web_tls(m["tls"], errs, base) if "tls" in m else (None, None)
    host = opt(m, "host", errs, host_name, d.host)
    if not is_loopback(host) and "tls" not in m:
        errs.add(
            f"{m['host'].where()}: got {host!r}, not loopback: the console is served "
            f"over HTTPS there; add web.tls with cert_file and key_file (docs/console.md)"
        )
    web_port = opt(m, "port", errs, port, d.port)
    foxglove_port = opt(m, "foxglove_port", errs, port, None)
    if foxglove_port is not None and foxglove_port == web_port:
        errs.add(f"{m['foxglove_port'].where()}: got {foxglove_port}, the console's own port")
    if foxglove_port is not None and key is not None and not _pkcs8(key):
        errs.add(
            f"{m['tls'].where()}: key_file {key} is not PKCS#8 ('-----BEGIN PRIVATE KEY-----'), "
            f"which the live Foxglove server needs: convert it with "
            f"'openssl pkcs8 -topk8 -nocrypt -in OLD -out NEW' (docs/console.md)"
        )
    return WebConfig(
        host=host,
        port=web_port,
        cert_file=cert,
        key_file=key,
        credentials_file=opt(m, "credentials_file", errs, lambda n: resolved_path(n, base), None),
        token=opt(m, "credentials_file", errs, lambda n: web_token(n, base), None),
        foxglove_port=foxglove_port,
    )
