"""The console as the supervisor's consumer: it serves while it runs, its sink on the
supervisor's status bus (seeded with what the bus retained before), and at cancellation (the
daemon's shutdown) the sink leaves the bus and the port is closed."""

from __future__ import annotations

import asyncio
import json
import socket
import textwrap

import aiohttp

from acquire.console.daemon import console_consumer
from acquire.daemon.config import parse_vessel_config
from acquire.daemon.consumers import ChecklistPublisher, Tap
from acquire.daemon.supervisor import Supervisor
from tests.acquire.daemon_util import free_port
from tests.waiting import wait_until_async


def _config(port: int):
    return parse_vessel_config(
        textwrap.dedent(f"""\
            vessel: v1
            devices:
              - {{name: ins, kind: ins, protocol: nmea, transport: {{type: udp, host: 127.0.0.1, port: 7001}}}}
            session: {{directory: sessions}}
            web: {{port: {port}}}
            """)
    )


def _refused(port: int) -> bool:
    with socket.socket() as s:
        return s.connect_ex(("127.0.0.1", port)) != 0


def test_the_console_serves_while_its_task_runs_and_leaves_the_bus_when_cancelled():
    port = free_port(socket.SOCK_STREAM)
    cfg = _config(port)
    sup = Supervisor(cfg)
    console = console_consumer(cfg, sup)
    assert console is not None

    async def main():
        sup.bus.publish("status", {"state": "running"})  # before the console: in its snapshot
        task = asyncio.ensure_future(console.run(Tap("console", ()), ChecklistPublisher(sup.bus.publish)))
        await wait_until_async(lambda: console.server.sink in sup.bus.sinks, 10, "the console's sink")
        async with aiohttp.ClientSession() as s, s.ws_connect(f"http://127.0.0.1:{port}/ws") as ws:
            assert json.loads((await ws.receive()).data) == {"topic": "status", "data": {"state": "running"}}
            assert json.loads((await ws.receive()).data)["topic"] == "_snapshot_end"
            sup.bus.publish("alarms", {"action": "raise"})
            assert json.loads((await ws.receive()).data)["topic"] == "alarms"
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)
            assert (await ws.receive()).type in (aiohttp.WSMsgType.CLOSE, aiohttp.WSMsgType.CLOSED)
        assert console.server.sink not in sup.bus.sinks
        assert _refused(port)

    asyncio.run(main())
