"""Status bus: topic policy, the local socket server (snapshot, fan-out, slow clients), mls status."""

from __future__ import annotations

import asyncio
import json
import threading

import pytest
from typer.testing import CliRunner

from acquire.status.bus import (
    SNAPSHOT_END,
    StatusBus,
    StatusListener,
    StatusServer,
    read_snapshot,
    topic_policy,
)
from cli.app import app
from tests.waiting import wait_until, wait_until_async

pytestmark = pytest.mark.integration  # real Unix sockets


def test_topic_policy_follows_design_section_8():
    assert topic_policy("status") == (True, 1)
    assert topic_policy("sensors/ins") == (True, 1)
    assert topic_policy("checklist") == (True, 1)
    assert topic_policy("mount") == (True, 1)
    assert topic_policy("clock") == (False, 0) and topic_policy("metrics") == (False, 0)
    assert topic_policy("alarms") == (False, 1)
    for bad in ("sensors", "sensors/a/b", "status/x", "gossip"):
        with pytest.raises(ValueError, match="status topic"):
            topic_policy(bad)


async def _read_lines(reader, n):
    return [json.loads(await asyncio.wait_for(reader.readline(), 5)) for _ in range(n)]


def test_clients_get_the_snapshot_then_live_lines(tmp_path):
    async def main():
        server = StatusServer(tmp_path / "status.sock")
        bus = StatusBus([server])
        async with server:
            bus.publish("status", {"state": "starting"})
            bus.publish("status", {"state": "running"})  # latest wins
            bus.publish("sensors/ins", {"rate_hz": 200.0, "roll_rad": float("nan")})
            bus.publish("clock", {"state": "LOCKED"})  # latest clock is in the snapshot too
            bus.publish("alarms", {"action": "raise", "name": "data_gap"})  # an event: not
            r1, w1 = await asyncio.open_unix_connection(str(server.path))
            r2, w2 = await asyncio.open_unix_connection(str(server.path))
            snap = await _read_lines(r1, 4)
            assert await _read_lines(r2, 4) == snap
            await until(lambda: server.clients == 2)
            bus.publish("metrics", {"n": 1})
            live = await _read_lines(r1, 1), await _read_lines(r2, 1)
            w1.close(), w2.close()
            return snap, live, bus.retained

    snap, live, retained = asyncio.run(main())
    assert snap == [
        {"topic": "status", "data": {"state": "running"}},
        {"topic": "sensors/ins", "data": {"rate_hz": 200.0, "roll_rad": None}},
        {"topic": "clock", "data": {"state": "LOCKED"}},
        {"topic": SNAPSHOT_END, "data": {"retained": 3}},
    ]
    assert live == ([{"topic": "metrics", "data": {"n": 1}}],) * 2
    assert set(retained) == {"status", "sensors/ins"}


async def until(cond, timeout_s=5.0):
    await wait_until_async(cond, timeout_s, "the server's clients")


def test_a_client_that_does_not_read_is_dropped_and_never_blocks_the_others(tmp_path):
    async def main():
        server = StatusServer(tmp_path / "s.sock", client_queue=8)
        bus = StatusBus([server])
        async with server:
            slow_r, slow_w = await asyncio.open_unix_connection(str(server.path))  # never reads
            fast_r, fast_w = await asyncio.open_unix_connection(str(server.path), limit=2**20)
            await _read_lines(fast_r, 1)  # its snapshot end
            await until(lambda: server.clients == 2)
            blob = "x" * 65536
            received = 0
            for i in range(100):  # 6.5 MB: far more than the socket buffers of the slow client
                bus.publish("metrics", {"i": i, "blob": blob})  # returns at once, always
                received += len(await _read_lines(fast_r, 1))
            await until(lambda: server.clients == 1)
            slow_w.close(), fast_w.close()
            return received, server.clients_dropped

    received, dropped = asyncio.run(main())
    assert received == 100 and dropped == 1


def test_a_stale_socket_file_is_replaced_and_a_live_one_refused(tmp_path):
    path = tmp_path / "s.sock"
    path.write_text("stale")

    async def main():
        async with StatusServer(path):
            with pytest.raises(RuntimeError, match="another daemon"):
                await StatusServer(path).start()
        return path.exists()

    assert asyncio.run(main()) is False  # removed at close


class _ServerThread:
    """A status server in a background event loop (for the synchronous CLI)."""

    def __init__(self, path, publications):
        self.path, self.publications = path, publications
        self.ready = threading.Event()
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, daemon=True)

    def __enter__(self):
        self.thread.start()

        async def start():
            self.server = StatusServer(self.path)
            await self.server.start()
            bus = StatusBus([self.server])
            for topic, data in self.publications:
                bus.publish(topic, data)

        asyncio.run_coroutine_threadsafe(start(), self.loop).result(5)
        return self

    def __exit__(self, *exc):
        asyncio.run_coroutine_threadsafe(self.server.close(), self.loop).result(5)
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(5)
        self.loop.close()


def test_mls_status_prints_the_snapshot_and_sets_the_exit_code(tmp_path):
    path = tmp_path / "status.sock"
    runner = CliRunner()
    ok = [
        (
            "status",
            {
                "state": "running",
                "session": "20250101T000000Z_survey-1",
                "alarms": [
                    {
                        "severity": "warning",
                        "name": "latency_jump",
                        "device": "ins",
                        "message": "latency +28.0 ms, baseline +8.0 ms",
                    }
                ],
            },
        ),
        ("clock", {"state": "LOCKED", "drift_ppm": 35.0}),
        ("sensors/ins", {"connected": True, "rate_hz": 200.0}),
        ("sensors/profiler", {"connected": False}),
        ("mount", {"verdict": "mount steady: roll +0.003 ± 0.004° (2 blocks)", "alarm": None}),
    ]
    with _ServerThread(path, ok):
        assert read_snapshot(path)["clock"] == {"state": "LOCKED", "drift_ppm": 35.0}
        r = runner.invoke(app, ["status", "--socket", str(path)], env={"COLUMNS": "200"})
        assert r.exit_code == 0, r.output
        for text in (
            "20250101T000000Z_survey-1",
            "clock.state",
            "LOCKED",
            "latency_jump",
            "profiler",
            "False",
            "active alarms: 1",
            "mount watch: mount steady: roll +0.003 ± 0.004° (2 blocks)",
        ):
            assert text in r.output, text
        r = runner.invoke(app, ["status", "--socket", str(path), "--json"])
        assert json.loads(r.output)["sensors/ins"]["rate_hz"] == 200.0
    critical = [("status", {"state": "running", "alarms": [{"severity": "critical", "name": "time_step"}]})]
    with _ServerThread(path, critical):
        assert runner.invoke(app, ["status", "--socket", str(path)]).exit_code == 2
    r = runner.invoke(app, ["status", "--socket", str(tmp_path / "none.sock")])
    assert r.exit_code == 1 and "is mls-acquire running?" in r.output


def test_a_client_receives_what_was_published_just_before_the_server_closes(tmp_path):
    """The daemon's final status ("stopped") reaches the clients before the socket goes."""

    async def main():
        server = StatusServer(tmp_path / "status.sock")
        bus = StatusBus([server])
        await server.start()
        bus.publish("status", {"state": "running"})
        reader, writer = await asyncio.open_unix_connection(str(server.path))
        await _read_lines(reader, 2)  # the snapshot
        await until(lambda: server.clients == 1)
        for i in range(50):
            bus.publish("metrics", {"n": i, "pad": "x" * 4000})  # ~200 kB still queued at close
        bus.publish("status", {"state": "stopped"})
        await server.close()
        rest = [json.loads(ln) for ln in (await asyncio.wait_for(reader.read(), 5)).splitlines()]
        writer.close()
        return rest, server.path.exists()

    rest, still_there = asyncio.run(main())
    assert [m["data"]["n"] for m in rest[:-1]] == list(range(50))
    assert rest[-1] == {"topic": "status", "data": {"state": "stopped"}} and not still_there


def test_the_listener_waits_for_the_daemon_skips_garbage_and_reconnects(tmp_path):
    """What mls demo follows the survey with: the latest message per topic, across a daemon
    restart; a line that is not a status message is skipped."""
    import socket

    path = tmp_path / "status.sock"
    listener = StatusListener(path, retry_s=0.02)
    listener.start()
    try:
        for state in ("running", "restarted"):
            srv = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            path.unlink(missing_ok=True)
            srv.bind(str(path))
            srv.listen(1)
            conn, _ = srv.accept()
            conn.sendall(
                b'not json\n{"topic": "status"}\n{"topic": "status", "data": {"state": "'
                + state.encode()
                + b'"}}\n{"topic": "clock", "data": {"state": "LO'
            )
            conn.sendall(b'CKED"}}\n')
            wait_until(
                lambda state=state: (
                    (listener.latest("clock") or {}).get("state") == "LOCKED"
                    and listener.latest("status") == {"state": state}
                ),
                5,
                f"the listener to have the {state} status",
            )
            srv.close()  # no longer listening: the listener's next connection reaches the next one
            conn.close()
        assert listener.connects == 2 and listener.latest("gossip") is None
    finally:
        listener.stop()
    assert not listener.is_alive()
