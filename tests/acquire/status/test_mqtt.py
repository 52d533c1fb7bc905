"""MQTT publishing against a real mosquitto: retained topics, reconnect, last will, commands."""

from __future__ import annotations

import asyncio
import json
import select
import signal
import subprocess
import sys
from pathlib import Path

import aiomqtt
import pytest

from acquire.status.bus import StatusBus
from acquire.status.mqtt import LOST, MqttPublisher, MqttSettings, check_command
from tests.waiting import wait_until_async

pytestmark = pytest.mark.integration
PROC = Path(__file__).parents[1] / "mqtt_proc.py"


class Subscriber:
    """Collects every message on a topic filter in the background."""

    def __init__(self, broker, topic: str):
        self.broker, self.topic = broker, topic
        self.messages: list[tuple[str, bytes, bool]] = []

    async def __aenter__(self):
        self.client = aiomqtt.Client(self.broker.host, self.broker.port)
        await self.client.__aenter__()
        await self.client.subscribe(self.topic, qos=1)
        self.task = asyncio.create_task(self._collect())
        return self

    async def _collect(self):
        async for m in self.client.messages:
            self.messages.append((str(m.topic), bytes(m.payload), bool(m.retain)))

    async def wait_for(self, pred, timeout_s=10.0, what="a message"):
        return await wait_until_async(
            lambda: [m for m in self.messages if pred(m)],
            timeout_s,
            what,
            interval_s=0.02,
            detail=lambda: f"got {self.messages}",
        )

    async def barrier(self, broker, topic: str) -> None:
        """Publish ``topic`` from a client of its own and wait for it: whatever the broker had
        for this subscriber before (its retained messages, a will) has been delivered."""
        async with aiomqtt.Client(broker.host, broker.port) as c:
            await c.publish(topic, b"barrier", qos=1)
        await self.wait_for(lambda m: m[0] == topic, what=f"the barrier on {topic}")

    async def __aexit__(self, *exc):
        self.task.cancel()
        await asyncio.gather(self.task, return_exceptions=True)
        await self.client.__aexit__(None, None, None)


async def until(cond, timeout_s=10.0, what="condition"):
    await wait_until_async(cond, timeout_s, what, interval_s=0.02)


def settings(broker, **kw) -> MqttSettings:
    return MqttSettings(
        broker.host, broker.port, topic_prefix="test", backoff_min_s=0.1, backoff_max_s=0.5, **kw
    )


def test_retained_topics_reach_a_late_subscriber(mosquitto):
    async def main():
        pub = MqttPublisher(settings(mosquitto), "late")
        bus = StatusBus([pub])
        task = asyncio.create_task(pub.run())
        bus.publish("status", {"state": "running", "session": "20240101T000000Z_late"})
        bus.publish("sensors/ins", {"connected": True, "rate_hz": 200.0})
        bus.publish("checklist", {"pps_locked": True})
        bus.publish("metrics", {"n": 1})  # not retained: gone for a late subscriber
        await until(lambda: pub.published == 4, what="4 publications")
        async with Subscriber(mosquitto, "test/late/#") as sub:
            await sub.wait_for(lambda m: m[0] == "test/late/checklist", what="retained checklist")
            await sub.barrier(mosquitto, "test/late/zz-barrier")  # every retained message is in
            got = {t: (json.loads(p), r) for t, p, r in sub.messages if t != "test/late/zz-barrier"}
        await pub.stop()
        await task
        return got

    got = asyncio.run(main())
    assert got == {
        "test/late/status": ({"state": "running", "session": "20240101T000000Z_late"}, True),
        "test/late/sensors/ins": ({"connected": True, "rate_hz": 200.0}, True),
        "test/late/checklist": ({"pps_locked": True}, True),
    }


def test_broker_killed_and_restarted_publisher_reconnects_without_blocking(broker_factory):
    broker = broker_factory()

    async def main():
        pub = MqttPublisher(settings(broker, queue_size=5), "crash")
        bus = StatusBus([pub])
        task = asyncio.create_task(pub.run())
        bus.publish("status", {"state": "running"})
        await until(lambda: pub.connected and pub.published == 1, what="first connection")
        broker.kill()
        await until(lambda: not pub.connected, what="the publisher to notice the crash")
        for i in range(20):  # the broker is down: offers return at once, the queue is bounded
            bus.publish("metrics", {"i": i})
        bus.publish("status", {"state": "running", "note": "while broker down"})
        assert pub.dropped == 15 and len(pub._queue) == 5
        await until(lambda: "refused" in (pub.last_error or ""), what="a refused reconnection")
        broker.start()
        await until(lambda: pub.connects == 2 and pub.connected, 15.0, "the reconnection")
        async with Subscriber(broker, "test/crash/#") as sub:
            status = await sub.wait_for(lambda m: m[0] == "test/crash/status", what="status")
            bus.publish("metrics", {"i": "after"})
            await sub.wait_for(
                lambda m: m[0] == "test/crash/metrics" and b"after" in m[1],
                what="a metrics message after the restart",
            )
        await pub.stop()
        await task
        return status, pub

    status, pub = asyncio.run(main())
    # the restarted broker (no persistence) lost the retained status; the publisher re-sent it
    assert json.loads(status[0][1]) == {"state": "running", "note": "while broker down"}
    assert status[0][2] is True
    assert pub.last_error is None  # cleared by the successful reconnection


def test_killed_publisher_leaves_its_last_will(mosquitto):
    async def main():
        async with Subscriber(mosquitto, "mls/will/status") as sub:
            proc = subprocess.Popen(  # noqa: ASYNC220 (started once; the test waits on the broker, not on it)
                [sys.executable, str(PROC), str(mosquitto.port), "will"],
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                text=True,
            )
            try:
                ready, _, _ = select.select([proc.stdout], [], [], 30.0)
                line = proc.stdout.readline() if ready else ""
                assert line.strip() == "READY", (line, proc.stderr.read() if not ready else "")
                await sub.wait_for(lambda m: b"running" in m[1], what="running status")
                proc.send_signal(signal.SIGKILL)
                proc.wait(10)
                lost = await sub.wait_for(lambda m: m[1] == LOST, what="the last will")
            finally:
                if proc.poll() is None:
                    proc.kill()
                    proc.wait(10)
                proc.stdout.close()
                proc.stderr.close()
        async with Subscriber(mosquitto, "mls/will/status") as late:  # and it is retained
            await late.wait_for(lambda m: m[1] == LOST and m[2], what="retained will")
        return lost

    lost = asyncio.run(main())
    assert json.loads(lost[0][1]) == {"state": "lost"}


def test_clean_stop_publishes_the_final_status_and_no_will(mosquitto):
    async def main():
        pub = MqttPublisher(settings(mosquitto), "clean")
        task = asyncio.create_task(pub.run())
        StatusBus([pub]).publish("status", {"state": "running"})
        await until(lambda: pub.published == 1, what="publication")
        async with Subscriber(mosquitto, "test/clean/#") as sub:
            await pub.stop({"state": "stopped"})
            await task
            await sub.wait_for(lambda m: b"stopped" in m[1], what="final status")
            # a client connecting after the disconnect: the broker has handled it (and sent a
            # will, had there been one) before this client's message
            await sub.barrier(mosquitto, "test/clean/barrier")
            return [json.loads(p)["state"] for t, p, _ in sub.messages if t == "test/clean/status"]

    assert asyncio.run(main()) == ["running", "stopped"]


def _results(sub: Subscriber) -> list[dict]:
    return [json.loads(p) for t, p, _ in list(sub.messages) if t.endswith("/cmd/result")]


@pytest.mark.parametrize(
    "enabled",
    [
        # realtime: a result that must not come has no event to wait for; 0.5 s after the echo is
        # ample for one (the enabled run's results come within milliseconds)
        pytest.param(False, id="disabled", marks=pytest.mark.realtime),
        pytest.param(True, id="enabled"),
    ],
)
def test_commands_only_when_enabled_and_only_the_explicit_set(mosquitto, enabled):
    calls = []

    def handler(name, args):
        calls.append((name, args))
        return True, f"{name} done"

    async def main(enabled: bool, vessel: str):
        pub = MqttPublisher(settings(mosquitto, commands_enabled=enabled), vessel, on_command=handler)
        task = asyncio.create_task(pub.run())
        await until(lambda: pub.connected, what="connection")
        async with (
            Subscriber(mosquitto, f"test/{vessel}/cmd/#") as sub,
            aiomqtt.Client(mosquitto.host, mosquitto.port) as op,
        ):
            for name, args in (
                ("mark", {"text": "T1 seen", "id": 7}),
                ("reboot", {}),
                ("pass_start", {"pass_id": "one"}),
            ):
                await op.publish(f"test/{vessel}/cmd/{name}", json.dumps(args), qos=1)
            await sub.wait_for(lambda m: m[0].endswith("pass_start"), what="the commands echoed")
            if enabled:  # one result per command, matched by its "command" field (the refusal
                # of "reboot" quotes the accepted set, "pass_start" included: not a substring test)
                await until(
                    lambda: {r["command"] for r in _results(sub)} >= {"mark", "reboot", "pass_start"},
                    what="the results of the 3 commands",
                )
            else:  # a result, were there one, would come from the publisher's own connection:
                # no message of the broker's orders it; give it the time one would take
                await asyncio.sleep(0.5)
            results = _results(sub)
        await pub.stop()
        await task
        return pub.subscribed, results

    if not enabled:
        subscribed, results = asyncio.run(main(False, "nocmd"))
        assert subscribed == [] and results == [] and calls == []
        return
    subscribed, results = asyncio.run(main(True, "cmd"))
    assert subscribed == ["test/cmd/cmd/+"]
    assert [r["command"] for r in results] == ["mark", "reboot", "pass_start"]
    assert calls == [("mark", {"text": "T1 seen"})]
    assert results[0] == {"command": "mark", "ok": True, "message": "mark done", "id": 7}
    assert results[1]["ok"] is False and "unknown command 'reboot'" in results[1]["message"]
    assert results[2]["ok"] is False and "'pass_id' must be int" in results[2]["message"]


def test_command_validation():
    assert check_command("rotate", {}) is None
    assert check_command("pass_end", {"pass_id": 3, "id": "x"}) is None
    assert "must be int" in check_command("pass_end", {"pass_id": True})
    assert "unknown argument(s) force" in check_command("rotate", {"force": 1})
    assert "JSON object" in check_command("mark", [1])
