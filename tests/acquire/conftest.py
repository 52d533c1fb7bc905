"""Fixtures of the acquisition tests: a real mosquitto broker per test worker.

Under pytest-xdist each worker process runs its own session, so each gets its own broker on its
own free port; tests that crash a broker use ``broker_factory`` for a private one.
"""

from __future__ import annotations

import pytest

from tests.mosquitto import Mosquitto


@pytest.fixture(scope="session")
def mosquitto(tmp_path_factory):
    broker = Mosquitto(tmp_path_factory.mktemp("mosquitto")).start()
    yield broker
    broker.stop()


@pytest.fixture
def broker_factory(tmp_path):
    brokers: list[Mosquitto] = []

    def make() -> Mosquitto:
        b = Mosquitto(tmp_path / f"broker{len(brokers)}").start()
        brokers.append(b)
        return b

    yield make
    for b in brokers:
        b.stop()
