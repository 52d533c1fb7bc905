"""Fixtures of the status bus tests: a test PKI (``openssl``) and a mosquitto listening with TLS."""

from __future__ import annotations

import pytest

from tests.mosquitto import Mosquitto, make_test_pki


@pytest.fixture(scope="session")
def pki(tmp_path_factory):
    return make_test_pki(tmp_path_factory.mktemp("pki"))


@pytest.fixture(scope="session")
def tls_broker(tmp_path_factory, pki):
    broker = Mosquitto(tmp_path_factory.mktemp("mosquitto-tls"), tls=pki).start()
    yield broker
    broker.stop()
