"""The office jobs' tests share the acquisition tests' broker fixtures (the demo and the
daemon export run the real daemon)."""

from tests.acquire.conftest import broker_factory, mosquitto  # noqa: F401
