"""A broker outage is an alarm: no connection to the MQTT broker for ``mqtt.outage_alarm_s``
raises ``mqtt_unreachable`` (warning, device ``mqtt``), which the daemon shows where no broker is
needed — its status socket and its log — and clears when the broker is back. Against a real
mosquitto, killed and started again on the same port."""

from __future__ import annotations

import asyncio
import logging
import textwrap
import time
from pathlib import Path

import pytest

from acquire.alarms import WARNING, AlarmBook
from acquire.daemon.config import VesselConfigError, load_vessel_config
from acquire.daemon.supervisor import Supervisor
from acquire.status.bus import StatusListener, read_snapshot
from acquire.status.mqtt import UNREACHABLE_ALARM, MqttPublisher, MqttSettings
from tests.mosquitto import free_port
from tests.waiting import wait_until_async

pytestmark = pytest.mark.integration


async def until(condition, timeout_s: float, what: str) -> None:
    await wait_until_async(condition, timeout_s, what, interval_s=0.02)


def settings(host: str, port: int, outage_alarm_s: float) -> MqttSettings:
    return MqttSettings(
        host, port, topic_prefix="outage", backoff_min_s=0.1, backoff_max_s=0.5, outage_alarm_s=outage_alarm_s
    )


def unreachable(alarms: AlarmBook) -> list:
    return [e for e in alarms.drain() if e.alarm.key == UNREACHABLE_ALARM]


def test_a_broker_down_longer_than_the_bound_raises_mqtt_unreachable_until_it_is_back(broker_factory):
    broker = broker_factory()

    async def main() -> tuple[list, float, object]:
        alarms = AlarmBook()
        pub = MqttPublisher(settings(broker.host, broker.port, 1.0), "down", alarms=alarms)
        task = asyncio.create_task(pub.run())
        await until(lambda: pub.connected, 10, "the first connection")
        broker.kill()
        killed = time.monotonic()
        await until(lambda: alarms.is_active(*UNREACHABLE_ALARM), 10, "mqtt_unreachable")
        raised_after_s = time.monotonic() - killed
        down_s = pub.metrics()["down_s"]
        broker.start()
        await until(lambda: not alarms.is_active(*UNREACHABLE_ALARM), 10, "the alarm to clear")
        assert pub.connected and pub.metrics()["down_s"] is None
        await pub.stop()
        await task
        return unreachable(alarms), raised_after_s, down_s

    events, raised_after_s, down_s = asyncio.run(main())
    assert [e.action for e in events] == ["raise", "clear"]
    assert raised_after_s >= 1.0  # not before the bound (counted from the moment the publisher saw it)
    assert down_s >= 1.0
    raised, cleared = events[0].alarm, events[1].alarm
    assert raised.severity == WARNING
    assert f"MQTT broker {broker.host}:{broker.port} unreachable for" in raised.message
    assert "alarm after 1 s" in raised.message and "local socket" in raised.message
    assert "reachable again after" in cleared.message


def test_a_broker_never_reached_raises_it_from_start_up():
    port = free_port()  # nothing listens

    async def main() -> list:
        alarms = AlarmBook()
        pub = MqttPublisher(settings("127.0.0.1", port, 1.0), "never", alarms=alarms)
        task = asyncio.create_task(pub.run())
        await until(lambda: alarms.is_active(*UNREACHABLE_ALARM), 10, "mqtt_unreachable")
        await pub.stop()
        await task
        return unreachable(alarms)

    (event,) = asyncio.run(main())
    assert event.action == "raise" and "Connection refused" in event.alarm.message


@pytest.mark.realtime  # the broker must be back within the 5 s bound: it restarts in < 1 s and
def test_a_restart_within_the_bound_raises_nothing(broker_factory):  # the back-off retries ≤ 0.5 s
    broker = broker_factory()

    async def main() -> list:
        alarms = AlarmBook()
        pub = MqttPublisher(settings(broker.host, broker.port, 5.0), "blip", alarms=alarms)
        task = asyncio.create_task(pub.run())
        await until(lambda: pub.connected, 10, "the first connection")
        broker.kill()
        await until(lambda: not pub.connected, 10, "the publisher to see the crash")
        broker.start()
        await until(lambda: pub.connects == 2, 10, "the reconnection")
        await pub.stop()
        await task
        return unreachable(alarms)

    assert asyncio.run(main()) == []


def test_outage_alarm_s_is_read_from_the_vessel_config(tmp_path):
    def config(extra: str) -> Path:
        cfg = tmp_path / "vessel.yaml"
        cfg.write_text(
            textwrap.dedent(f"""\
            vessel: cfg-1
            devices:
              - {{name: ins, kind: ins, protocol: nmea, transport: {{type: udp, host: 127.0.0.1, port: 9}}}}
            session: {{directory: sessions}}
            status: {{socket: status.sock}}
            mqtt: {{host: 127.0.0.1{extra}}}
            """)
        )
        return cfg

    assert load_vessel_config(config("")).mqtt.outage_alarm_s == 30.0
    assert load_vessel_config(config(", outage_alarm_s: 120")).mqtt.outage_alarm_s == 120.0
    with pytest.raises(VesselConfigError, match=r"mqtt\.outage_alarm_s: got 0"):
        load_vessel_config(config(", outage_alarm_s: 0"))


class AlarmEvents(StatusListener):
    def __init__(self, path: Path):
        super().__init__(path)
        self.events: list[dict] = []

    def handle(self, received_ns: int, topic: str, data) -> None:
        if topic == "alarms" and isinstance(data, dict) and data.get("name") == UNREACHABLE_ALARM[0]:
            self.events.append(data)
        super().handle(received_ns, topic, data)


def _status_alarms(sock: Path) -> set[str]:
    try:
        snap = read_snapshot(sock, 3.0)
    except (OSError, ValueError):
        return set()
    return {a["name"] for a in snap.get("status", {}).get("alarms", [])}


def test_the_daemon_shows_the_outage_on_its_socket_and_in_its_log(tmp_path, broker_factory, caplog):
    broker = broker_factory()
    cfg = tmp_path / "vessel.yaml"
    cfg.write_text(
        textwrap.dedent(f"""\
        vessel: outage-1
        devices:
          - {{name: ins, kind: ins, protocol: nmea, transport: {{type: udp, host: 127.0.0.1, port: {free_port()}}}}}
        session: {{directory: sessions}}
        status: {{socket: {tmp_path}/status.sock, period_s: 0.25}}
        mqtt: {{host: 127.0.0.1, port: {broker.port}, topic_prefix: outage, outage_alarm_s: 1}}
        """)
    )
    sock = tmp_path / "status.sock"
    listener = AlarmEvents(sock)
    caplog.set_level(logging.WARNING, logger="mls.acquire")
    seen: dict[str, set[str]] = {}

    async def scenario() -> None:
        sup = Supervisor(load_vessel_config(cfg))
        task = asyncio.create_task(sup.run())
        await until(lambda: sup.mqtt is not None and sup.mqtt.connected, 20, "the daemon on MQTT")
        listener.start()
        await until(lambda: listener.connects > 0, 10, "the status socket")
        broker.kill()
        await until(lambda: listener.events, 10, "mqtt_unreachable on the status socket")
        seen["down"] = await asyncio.to_thread(_status_alarms, sock)
        broker.start()
        await until(lambda: len(listener.events) >= 2, 15, "its clear on the status socket")
        seen["up"] = await asyncio.to_thread(_status_alarms, sock)
        sup.request_stop("test")
        assert await task == 0

    try:
        asyncio.run(asyncio.wait_for(scenario(), 60))
    finally:
        listener.stop()
    assert [e["action"] for e in listener.events] == ["raise", "clear"]
    assert listener.events[0]["device"] == "mqtt" and listener.events[0]["severity"] == WARNING
    assert "mqtt_unreachable" in seen["down"] and "mqtt_unreachable" not in seen["up"]
    logged = [r.getMessage() for r in caplog.records if "mqtt_unreachable" in r.getMessage()]
    assert any(m.startswith("alarm raise mqtt_unreachable/mqtt: MQTT broker") for m in logged), logged
    assert any(m.startswith("alarm clear mqtt_unreachable/mqtt") for m in logged), logged
