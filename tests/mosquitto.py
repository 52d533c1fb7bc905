"""A real mosquitto broker on a free loopback port, for the MQTT tests.

``Mosquitto(workdir).start()`` runs ``mosquitto -c <conf>`` (anonymous, no persistence) and waits
until the port accepts connections. ``kill()`` / ``start()`` again on the same port simulate a
broker crash and restart. A missing binary is an error (never a skip): the CI installs
``mosquitto`` with apt.

``Mosquitto(workdir, tls=make_test_pki(dir))`` listens with TLS only (TLS ≥ 1.2, the server
certificate of ``localhost``/``127.0.0.1``, client certificates required and verified against the
test CA). :func:`make_test_pki` makes the certificates with the ``openssl`` command line.
"""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
from dataclasses import dataclass
from pathlib import Path

from tests.waiting import wait_until

CANDIDATES = ("mosquitto", "/usr/sbin/mosquitto", "/usr/local/sbin/mosquitto")


def mosquitto_binary() -> str:
    for c in CANDIDATES:
        found = shutil.which(c) or (c if os.path.isabs(c) and os.access(c, os.X_OK) else None)
        if found:
            return found
    raise RuntimeError(
        "mosquitto not found (looked for: " + ", ".join(CANDIDATES) + "). The MQTT tests need a "
        "real broker: install it with `apt-get install mosquitto`."
    )


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@dataclass(frozen=True)
class BrokerPki:
    ca: Path  # the test CA's certificate
    server_cert: Path
    server_key: Path
    client_cert: Path
    client_key: Path
    other_ca: Path  # a CA that signed nothing here: verifying the broker with it fails


def _openssl(*args: str | Path, cwd: Path) -> None:
    subprocess.run(["openssl", *map(str, args)], cwd=cwd, check=True, capture_output=True, timeout=60)


def _key_and_csr(d: Path, name: str, cn: str) -> None:
    _openssl("ecparam", "-name", "prime256v1", "-genkey", "-noout", "-out", f"{name}.key", cwd=d)
    _openssl("req", "-new", "-key", f"{name}.key", "-subj", f"/CN={cn}", "-out", f"{name}.csr", cwd=d)
    os.chmod(d / f"{name}.key", 0o600)


def _self_signed_ca(d: Path, name: str) -> None:
    _openssl("ecparam", "-name", "prime256v1", "-genkey", "-noout", "-out", f"{name}.key", cwd=d)
    _openssl(
        "req", "-x509", "-new", "-key", f"{name}.key", "-subj", f"/CN={name}", "-days", "2",
        "-addext", "basicConstraints=critical,CA:TRUE", "-addext", "keyUsage=critical,keyCertSign,cRLSign",
        "-out", f"{name}.crt", cwd=d,
    )  # fmt: skip


def _sign(d: Path, name: str, ext: str) -> None:
    (d / f"{name}.ext").write_text(ext)
    _openssl(
        "x509", "-req", "-in", f"{name}.csr", "-CA", "ca.crt", "-CAkey", "ca.key", "-CAcreateserial",
        "-days", "2", "-extfile", f"{name}.ext", "-out", f"{name}.crt", cwd=d,
    )  # fmt: skip


def make_test_pki(directory: Path) -> BrokerPki:
    """A CA, a server certificate for localhost/127.0.0.1 and a client certificate, signed by
    it, and an unrelated CA (EC P-256 keys, valid 2 days), made with ``openssl``."""
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    _self_signed_ca(d, "ca")
    _self_signed_ca(d, "other-ca")
    _key_and_csr(d, "server", "localhost")
    _sign(d, "server", "subjectAltName=DNS:localhost,IP:127.0.0.1\nextendedKeyUsage=serverAuth\n")
    _key_and_csr(d, "client", "mls-test-client")
    _sign(d, "client", "extendedKeyUsage=clientAuth\n")
    return BrokerPki(
        d / "ca.crt",
        d / "server.crt",
        d / "server.key",
        d / "client.crt",
        d / "client.key",
        d / "other-ca.crt",
    )


class Mosquitto:
    def __init__(self, workdir: Path, port: int | None = None, tls: BrokerPki | None = None):
        self.tls = tls
        self.workdir = Path(workdir)
        self.workdir.mkdir(parents=True, exist_ok=True)
        self.port = port or free_port()
        self.host = "127.0.0.1"
        self.proc: subprocess.Popen | None = None
        self.log = self.workdir / "mosquitto.log"

    def start(self, timeout_s: float = 10.0) -> Mosquitto:
        conf = self.workdir / "mosquitto.conf"
        tls = ""
        if self.tls is not None:
            tls = (
                f"cafile {self.tls.ca}\ncertfile {self.tls.server_cert}\nkeyfile {self.tls.server_key}\n"
                "tls_version tlsv1.2\nrequire_certificate true\n"
            )
            if os.geteuid() == 0:  # as root, mosquitto drops to user mosquitto before reading
                tls += "user root\n"  # the files, which live in a private tmp_path
        conf.write_text(
            f"listener {self.port} {self.host}\n" + tls + "allow_anonymous true\n"
            "persistence false\n"
            "log_dest stderr\n"
            "log_type error\nlog_type warning\nlog_type notice\n"
        )
        with open(self.log, "ab") as log:
            self.proc = subprocess.Popen([mosquitto_binary(), "-c", str(conf)], stdout=log, stderr=log)

        def listening() -> bool:
            if self.proc.poll() is not None:
                raise RuntimeError(
                    f"mosquitto exited with {self.proc.returncode}: {self.log.read_text()[-2000:]}"
                )
            try:
                socket.create_connection((self.host, self.port), timeout=0.2).close()
                return True
            except OSError:
                return False

        if not wait_until(listening, timeout_s, "mosquitto", interval_s=0.05, fail=False):
            self.stop()
            raise RuntimeError(
                f"mosquitto did not open port {self.port} in {timeout_s} s: {self.log.read_text()[-2000:]}"
            )
        return self

    def kill(self) -> None:
        """Crash the broker (SIGKILL): clients see the connection drop."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGKILL)
            self.proc.wait(10)
        self.proc = None

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10)
        self.proc = None
