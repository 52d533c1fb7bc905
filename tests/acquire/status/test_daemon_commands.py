"""The daemon with MQTT commands (issue 26): a retained command left on the broker is not run at
start-up, an out-of-range pass id is refused and logged as an event, a valid one is logged."""

from __future__ import annotations

import asyncio
import json
import textwrap

import aiomqtt
import pytest

from acquire.daemon.config import load_vessel_config
from acquire.daemon.supervisor import Supervisor
from acquire.log.read import iter_messages
from tests.acquire.daemon_util import free_port
from tests.acquire.status.test_mqtt import until

pytestmark = pytest.mark.integration


def test_daemon_ignores_retained_commands_and_logs_refusals(tmp_path, mosquitto):
    cfg = tmp_path / "vessel.yaml"
    cfg.write_text(
        textwrap.dedent(f"""\
        vessel: sec-1
        devices:
          - {{name: ins, kind: ins, protocol: nmea, transport: {{type: udp, host: 127.0.0.1, port: {free_port()}}}}}
        session: {{directory: sessions}}
        status: {{socket: status.sock}}
        mqtt: {{host: 127.0.0.1, port: {mosquitto.port}, topic_prefix: sectest, commands_enabled: true}}
        """)
    )
    base = "sectest/sec-1/cmd"

    async def scenario():
        async with aiomqtt.Client(mosquitto.host, mosquitto.port) as op:
            await op.publish(f"{base}/mark", json.dumps({"text": "stale"}), qos=1, retain=True)
            await op.subscribe(f"{base}/result", qos=1)
            sup = Supervisor(load_vessel_config(cfg))
            task = asyncio.create_task(sup.run())
            await until(lambda: sup.mqtt and sup.mqtt.commands["retained"] == 1, 20.0, "the retained command")
            await op.publish(f"{base}/pass_start", b'{"pass_id": 9223372036854775808, "id": 1}', qos=1)
            await op.publish(f"{base}/pass_start", b'{"pass_id": 4, "id": 2}', qos=1)
            results = []
            async for m in op.messages:
                results.append(json.loads(m.payload))
                if len(results) == 2:
                    break
            await op.publish(f"{base}/mark", b"", qos=1, retain=True)  # clear the broker's copy
        sup.request_stop("test")
        await task
        return sup.writer.session_dir, results

    session, results = asyncio.run(asyncio.wait_for(scenario(), 40))
    assert [(r["id"], r["ok"]) for r in results] == [(1, False), (2, True)]
    assert "must be in 1 … 9007199254740991" in results[0]["message"]
    events = [m.payload for m in iter_messages(session, {"/events"})]
    mine = [e for e in events if e.get("source") == "mqtt"]
    assert [(e["event"], e.get("pass_id"), e.get("command")) for e in mine] == [
        ("command_refused", None, "pass_start"),
        ("pass_start", 4, None),
    ]
    assert "9223372036854775808" in mine[0]["reason"]
    assert not any(e.get("text") == "stale" for e in events)  # the retained mark never ran
