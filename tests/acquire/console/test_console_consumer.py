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
from acquire.console.history import last_calibration, read_safely
from acquire.daemon.config import parse_vessel_config
from acquire.daemon.consumers import ChecklistPublisher, Tap
from acquire.daemon.supervisor import Supervisor
from calib.assess.history import record_result
from tests.acquire.daemon_util import free_port
from tests.calib.assess.test_history import make_bundle, make_result
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


def test_the_console_serves_while_its_task_runs_and_leaves_the_bus_when_cancelled(tmp_path):
    port = free_port(socket.SOCK_STREAM)
    cfg = _config(port)
    sup = Supervisor(cfg)
    console = console_consumer(cfg, sup, history_db=tmp_path / "history.sqlite")
    assert console is not None

    async def main():
        sup.bus.publish("status", {"state": "running"})  # before the console: in its snapshot
        task = asyncio.ensure_future(console.run(Tap("console", ()), ChecklistPublisher(sup.bus.publish)))
        sink = console.server.sink
        await wait_until_async(lambda: "calibration" in sink.latest, 10, "the console's sink and history")
        assert sink in sup.bus.sinks
        async with aiohttp.ClientSession() as s, s.ws_connect(f"http://127.0.0.1:{port}/ws") as ws:
            assert json.loads((await ws.receive()).data) == {"topic": "status", "data": {"state": "running"}}
            assert json.loads((await ws.receive()).data) == {
                "topic": "calibration",
                "data": {"recorded": False, "vessel": "v1"},  # (an empty history: none recorded)
            }
            assert json.loads((await ws.receive()).data)["topic"] == "_snapshot_end"
            sup.bus.publish("alarms", {"action": "raise"})
            assert json.loads((await ws.receive()).data)["topic"] == "alarms"
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)
            assert (await ws.receive()).type in (aiohttp.WSMsgType.CLOSE, aiohttp.WSMsgType.CLOSED)
        assert console.server.sink not in sup.bus.sinks
        assert _refused(port)

    asyncio.run(main())


def test_the_last_calibration_of_the_vessel_is_pushed_from_the_history(tmp_path):
    db = tmp_path / "history.sqlite"
    old = make_result([0.2, 1.2, 0.1], [0.001, 0.012, 0.001])
    new = {
        **make_result([0.21, 1.25, 0.15], [0.0011, 0.0118, 0.0008], [0.002, 0.02, 0.03]),
        "verdict": "trusted",
    }
    record_result(old, make_bundle(tmp_path / "jul", gps_s=1_246_665_618.0), "v1", "bracket-A", db=db)
    record_result(new, make_bundle(tmp_path / "oct", gps_s=1_254_000_000.0), "v1", "bracket-A", db=db)
    record_result(old, make_bundle(tmp_path / "other", gps_s=1_260_000_000.0), "v2", "pole", db=db)
    doc = last_calibration("v1", db)
    assert doc["recorded"] and doc["id"] == 2 and doc["mount_id"] == "bracket-A"
    assert doc["verdict"] == "trusted" and doc["sigma_kind"] == "realistic"
    assert doc["boresight_deg"] == {"roll": 0.21, "pitch": 1.25, "yaw": 0.15}
    assert doc["sigma_deg"] == {"roll": 0.002, "pitch": 0.02, "yaw": 0.03}
    assert last_calibration("v2", db)["sigma_kind"] == "scaled"  # an older result: no realistic σ
    assert last_calibration("v3", db) == {"recorded": False, "vessel": "v3"}


def test_an_unreadable_history_is_shown_not_raised(tmp_path):
    db = tmp_path / "history.sqlite"
    db.write_text("not a database")
    doc = read_safely("v1", db)
    assert doc["recorded"] is False and "not a usable history database" in doc["error"]
