"""MQTT over TLS, and the command policy: retained commands ignored, rate limits, acknowledged
refusals, unique client ids, a session takeover alarmed — against a real mosquitto (TLS listener
with certificates made by ``openssl``) and, for the MQTT 5 takeover, a scripted broker."""

from __future__ import annotations

import asyncio
import contextlib
import json
import ssl

import aiomqtt
import pytest

from acquire.alarms import AlarmBook
from acquire.status.bus import StatusBus
from acquire.status.commands import CommandLimiter
from acquire.status.mqtt import MqttPublisher, MqttSettings, MqttTls
from tests.acquire.status.test_mqtt import Subscriber, until

pytestmark = pytest.mark.integration


def settings(broker, **kw) -> MqttSettings:
    return MqttSettings(
        kw.pop("host", broker.host),
        broker.port,
        topic_prefix="sec",
        backoff_min_s=0.1,
        backoff_max_s=0.3,
        **kw,
    )


class Frozen:
    """A clock that does not move: rate limits independent of the machine's speed."""

    def __call__(self) -> float:
        return 0.0


async def stopped(pub: MqttPublisher, task: asyncio.Task) -> None:
    await pub.stop()
    await asyncio.wait_for(task, 10)


# -- TLS ----------------------------------------------------------------------------------------


def client_tls(pki, ca=None) -> ssl.SSLContext:
    ctx = ssl.create_default_context(cafile=str(ca or pki.ca))
    ctx.load_cert_chain(str(pki.client_cert), str(pki.client_key))
    return ctx


def test_publishes_over_tls_with_a_client_certificate(tls_broker, pki):
    tls = MqttTls(pki.ca, pki.client_cert, pki.client_key)

    async def main():
        pub = MqttPublisher(settings(tls_broker, host="localhost", tls=tls), "tls")
        task = asyncio.create_task(pub.run())
        StatusBus([pub]).publish("status", {"state": "running"})
        await until(lambda: pub.published == 1, what="the status published over TLS")
        async with aiomqtt.Client("localhost", tls_broker.port, tls_context=client_tls(pki)) as sub:
            await sub.subscribe("sec/tls/status", qos=1)
            message = await asyncio.wait_for(anext(aiter(sub.messages)), 10)
        await stopped(pub, task)
        return message

    message = asyncio.run(main())
    assert json.loads(message.payload) == {"state": "running"} and message.retain


def test_a_broker_not_signed_by_the_ca_is_refused_with_an_alarm_and_retried(tls_broker, pki):
    alarms = AlarmBook()
    tls = MqttTls(pki.other_ca, pki.client_cert, pki.client_key)

    async def main():
        pub = MqttPublisher(settings(tls_broker, host="localhost", tls=tls), "badca", alarms=alarms)
        task = asyncio.create_task(pub.run())
        await until(lambda: alarms.is_active("mqtt_refused", "mqtt"), what="the mqtt_refused alarm")
        first = alarms.get("mqtt_refused", "mqtt").last_host_ns
        await until(lambda: alarms.get("mqtt_refused", "mqtt").last_host_ns > first, what="a second attempt")
        alive = not task.done()
        await stopped(pub, task)
        return pub, alive

    pub, alive = asyncio.run(main())
    alarm = alarms.get("mqtt_refused", "mqtt")
    assert alive and pub.connects == 0 and alarm.active and alarm.severity == "critical"
    assert "certificate verify failed" in alarm.message and "retrying" in alarm.message
    assert [e.action for e in alarms.drain()] == ["raise"]  # refreshed, not raised again


# -- commands -----------------------------------------------------------------------------------


def _results(sub: Subscriber) -> list[dict]:
    return [json.loads(p) for t, p, _ in list(sub.messages) if t.endswith("/cmd/result")]


def test_retained_commands_are_ignored_and_counted(mosquitto):
    calls: list[tuple[str, dict]] = []

    def handler(name, args):
        calls.append((name, args))
        return True, f"{name} done"

    async def main():
        async with aiomqtt.Client(mosquitto.host, mosquitto.port) as op:
            # left on the broker before the daemon starts: replayed at every subscription
            await op.publish("sec/ret/cmd/mark", json.dumps({"text": "stale"}), qos=1, retain=True)
            pub = MqttPublisher(settings(mosquitto, commands_enabled=True), "ret", on_command=handler)
            task = asyncio.create_task(pub.run())
            await until(lambda: pub.commands["retained"] == 1, what="the replayed command counted")
            await op.publish("sec/ret/cmd/mark", json.dumps({"text": "live retained"}), qos=1, retain=True)
            await until(lambda: pub.commands["retained"] == 2, what="a live retained command counted")
            async with Subscriber(mosquitto, "sec/ret/cmd/result") as sub:
                await op.publish("sec/ret/cmd/mark", json.dumps({"text": "fresh", "id": 1}), qos=1)
                await sub.wait_for(lambda m: True, what="the result of the fresh command")
                results = _results(sub)
            await op.publish("sec/ret/cmd/mark", b"", qos=1, retain=True)  # clear the broker's copy
        await stopped(pub, task)
        return pub, results

    pub, results = asyncio.run(main())
    assert calls == [("mark", {"text": "fresh"})]
    assert results == [{"command": "mark", "ok": True, "message": "mark done", "id": 1}]
    assert pub.metrics()["commands"] == {
        "accepted": 1,
        "refused": 0,
        "rate_limited": 0,
        "retained": 2,
        "dropped": 0,
    }


def test_a_rotate_flood_is_rate_limited_and_refusals_are_acknowledged(mosquitto):
    calls: list[str] = []

    def handler(name, args):
        calls.append(name)
        return True, f"{name}: a new segment is being opened"

    async def main():
        limiter = CommandLimiter(reply_limit=(5.0, 10.0), clock=Frozen())
        pub = MqttPublisher(
            settings(mosquitto, commands_enabled=True), "flood", on_command=handler, limiter=limiter
        )
        task = asyncio.create_task(pub.run())
        await until(lambda: pub.subscribed, what="the command subscription")
        async with (
            Subscriber(mosquitto, "sec/flood/cmd/result") as sub,
            aiomqtt.Client(mosquitto.host, mosquitto.port) as op,
        ):
            for i in range(100):
                await op.publish("sec/flood/cmd/rotate", json.dumps({"id": i}), qos=1)
            await until(
                lambda: pub.commands["accepted"] + pub.commands["rate_limited"] == 100,
                what="the 100 rotate commands handled",
            )
            await until(lambda: len(_results(sub)) == 12, what="12 results")
            results = _results(sub)
        await stopped(pub, task)
        return pub, results

    pub, results = asyncio.run(main())
    assert calls == ["rotate", "rotate"]  # the burst; then one per 30 s
    assert [r["ok"] for r in results] == [True, True] + [False] * 10
    assert [r["id"] for r in results] == list(range(12))
    assert all("rate limited" in r["message"] for r in results[2:])
    assert pub.commands == {"accepted": 2, "refused": 0, "rate_limited": 98, "retained": 0, "dropped": 88}


def test_invalid_commands_are_refused_with_the_reason_and_a_session_event(mosquitto):
    calls: list = []
    events: list[dict] = []

    async def main():
        pub = MqttPublisher(
            settings(mosquitto, commands_enabled=True),
            "bad",
            on_command=lambda n, a: calls.append((n, a)) or (True, "done"),
            on_event=events.append,
        )
        task = asyncio.create_task(pub.run())
        await until(lambda: pub.subscribed, what="the command subscription")
        async with (
            Subscriber(mosquitto, "sec/bad/cmd/result") as sub,
            aiomqtt.Client(mosquitto.host, mosquitto.port) as op,
        ):
            for name, payload in (
                ("pass_start", b'{"pass_id": 9223372036854775808, "id": 1}'),
                ("pass_start", b'{"pass_id": -5, "id": 2}'),
                ("pass_end", b'{"pass_id": 3, "operator": "x", "id": 3}'),
                ("mark", b"not json"),
            ):
                await op.publish(f"sec/bad/cmd/{name}", payload, qos=1)
            await until(lambda: len(_results(sub)) == 4, what="4 refusals")
            results = _results(sub)
        await stopped(pub, task)
        return results

    results = asyncio.run(main())
    assert calls == []
    assert [(r["command"], r["ok"], r.get("id")) for r in results] == [
        ("pass_start", False, 1),
        ("pass_start", False, 2),
        ("pass_end", False, 3),
        ("mark", False, None),
    ]
    assert "must be in 1 … 9007199254740991" in results[0]["message"]
    assert "unknown argument(s) operator" in results[2]["message"]
    assert "payload is not JSON" in results[3]["message"]
    assert [(e["event"], e["source"], e["command"]) for e in events] == [
        ("command_refused", "mqtt", r["command"]) for r in results
    ]
    assert [e["reason"] for e in events] == [r["message"] for r in results]


def test_commands_over_plaintext_to_a_remote_broker_are_not_subscribed():
    remote = MqttSettings("192.0.2.7", commands_enabled=True)
    pub = MqttPublisher(remote, "v")
    assert not pub.commands_active and "need TLS with credentials" in pub.command_refusal
    assert MqttPublisher(
        MqttSettings("192.0.2.7", commands_enabled=True, commands_insecure_ok=True), "v"
    ).commands_active
    assert MqttPublisher(MqttSettings("127.0.0.1", commands_enabled=True), "v").commands_active


# -- client id ----------------------------------------------------------------------------------


def test_two_daemons_of_one_vessel_have_their_own_client_ids_and_both_stay_connected(mosquitto):
    async def main():
        pubs = [MqttPublisher(settings(mosquitto), "twin") for _ in range(2)]
        tasks = [asyncio.create_task(p.run()) for p in pubs]
        await until(lambda: all(p.connected for p in pubs), what="both connected")
        for i in range(3):  # both keep publishing on their own connection
            for p in pubs:
                p.offer("metrics", json.dumps({"i": i}).encode(), False, 1)
        await until(lambda: all(p.published == 3 for p in pubs), what="3 messages each")
        for p, t in zip(pubs, tasks, strict=True):
            await stopped(p, t)
        return pubs

    a, b = asyncio.run(main())
    assert a.client_id != b.client_id and a.client_id.startswith("mls-acquire-twin-")
    assert a.connects == b.connects == 1 and a.takeovers == b.takeovers == 0


# -- session takeover (MQTT 5 reason code 0x8E, from a scripted broker) --------------------------


class ScriptedBroker:
    """Just enough of an MQTT 5 broker: CONNACK, SUBACK, PUBACK, PINGRESP; :meth:`take_over`
    sends the current client ``DISCONNECT`` with reason 0x8E "session taken over"."""

    def __init__(self) -> None:
        self.writers: list[asyncio.StreamWriter] = []
        self.closed: dict[int, asyncio.Event] = {}  # per writer: the client closed its side
        self.connects = 0

    async def __aenter__(self):
        self.server = await asyncio.start_server(self._client, "127.0.0.1", 0)
        self.host, self.port = self.server.sockets[0].getsockname()[:2]
        return self

    async def __aexit__(self, *exc):
        for w in self.writers:
            w.close()
        self.server.close()
        await self.server.wait_closed()

    async def take_over(self) -> None:
        writer = self.writers[-1]
        writer.write(bytes([0xE0, 2, 0x8E, 0]))
        await writer.drain()
        # the client reads the DISCONNECT and closes its side before ours closes
        await asyncio.wait_for(self.closed[id(writer)].wait(), 10.0)
        writer.close()

    async def _client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.writers.append(writer)
        self.closed[id(writer)] = asyncio.Event()
        try:
            while True:
                kind, body = await _read_packet(reader)
                reply = self._reply(kind, body)
                if reply is None:
                    break
                writer.write(reply)
                await writer.drain()
        except (asyncio.IncompleteReadError, ConnectionError):
            pass
        self.closed[id(writer)].set()
        writer.close()

    def _reply(self, kind: int, body: bytes) -> bytes | None:
        packet_type, flags = kind >> 4, kind & 0x0F
        if packet_type == 1:  # CONNECT
            self.connects += 1
            return bytes([0x20, 3, 0, 0, 0])
        if packet_type == 8:  # SUBSCRIBE: one filter granted QoS 1
            return bytes([0x90, 4, body[0], body[1], 0, 1])
        if packet_type == 3:  # PUBLISH
            if (flags >> 1) & 3 == 0:
                return b""
            n = int.from_bytes(body[:2], "big")
            return bytes([0x40, 2, body[2 + n], body[3 + n]])
        if packet_type == 12:  # PINGREQ
            return bytes([0xD0, 0])
        return None  # DISCONNECT, or anything else: close


async def _read_packet(reader: asyncio.StreamReader) -> tuple[int, bytes]:
    kind = (await reader.readexactly(1))[0]
    length, shift = 0, 0
    while True:
        byte = (await reader.readexactly(1))[0]
        length += (byte & 0x7F) << shift
        shift += 7
        if not byte & 0x80:
            break
    return kind, await reader.readexactly(length)


def test_a_session_taken_over_raises_an_alarm_and_the_publisher_reconnects():
    alarms = AlarmBook()

    async def main():
        async with ScriptedBroker() as broker:
            pub = MqttPublisher(settings(broker), "taken", alarms=alarms)
            pub.stable_s = 0.3  # a connection that held 0.3 s clears the alarm
            task = asyncio.create_task(pub.run())
            StatusBus([pub]).publish("status", {"state": "running"})
            await until(lambda: pub.connected and pub.published == 1, what="the first connection")
            await broker.take_over()
            await until(lambda: pub.takeovers == 1, what="the takeover noticed")
            raised = alarms.get("mqtt_taken_over", "mqtt")
            await until(lambda: pub.connects == 2 and pub.connected, what="the reconnection")
            await until(lambda: not alarms.is_active("mqtt_taken_over", "mqtt"), what="the alarm cleared")
            await stopped(pub, task)
            return pub, raised

    pub, raised = asyncio.run(main())
    assert raised.active and raised.severity == "warning"
    assert "session taken over" in raised.message and pub.client_id in raised.message
    events = [(e.action, e.alarm.name) for e in alarms.drain()]
    assert events == [("raise", "mqtt_taken_over"), ("clear", "mqtt_taken_over")]


def test_a_fight_over_the_client_id_with_a_silent_broker_raises_the_takeover_alarm(mosquitto):
    """mosquitto < 2.0.15 closes the old connection without a reason: the daemon sees its
    sessions end one after the other right after connecting."""
    alarms = AlarmBook()

    async def thief(client_id: str, done: asyncio.Event) -> int:
        connects = 0
        while not done.is_set():
            try:
                async with aiomqtt.Client(mosquitto.host, mosquitto.port, identifier=client_id) as c:
                    connects += 1
                    async for _ in c.messages:  # until the daemon takes the id back
                        pass
            except aiomqtt.MqttError:  # refused while the daemon holds the id: try again, or stop
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(done.wait(), 0.05)
        return connects

    async def main():
        pub = MqttPublisher(settings(mosquitto), "fight", alarms=alarms)
        task = asyncio.create_task(pub.run())
        await until(lambda: pub.connected, what="the first connection")
        done = asyncio.Event()
        stealing = asyncio.create_task(thief(pub.client_id, done))
        await until(lambda: alarms.is_active("mqtt_taken_over", "mqtt"), 20.0, "the takeover alarm")
        done.set()
        await until(lambda: stealing.done() or pub.connected, what="the thief to give up")
        await stopped(pub, task)
        stealing.cancel()
        await asyncio.gather(stealing, return_exceptions=True)
        return pub

    pub = asyncio.run(main())
    alarm = alarms.get("mqtt_taken_over", "mqtt")
    assert pub.takeovers >= 1 and pub.client_id in alarm.message
    assert "session taken over" in alarm.message
