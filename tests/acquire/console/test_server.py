"""The console's server on a real port (aiohttp's client): the page and its assets served by the
daemon itself, the WebSocket (snapshot first, then live; a slow client drops and is resynced),
the operator token (401 without, 403 wrong or read-only), the actions through the MQTT commands'
checks and rate limits and recorded as session events, TLS off loopback."""

from __future__ import annotations

import asyncio
import json
import re
import ssl

import aiohttp
import pytest

from acquire.alarms import CRITICAL, AlarmBook
from acquire.console.actions import LIMITS, ActionDesk
from acquire.console.fanout import ConsoleSink
from acquire.console.server import STATIC, ConsoleRefused, ConsoleServer, tls_context
from acquire.daemon.configschema import WebConfig
from acquire.status.bus import StatusBus
from acquire.status.commands import CommandLimiter
from tests.mosquitto import make_test_pki

TOKEN = "s3cret-operator-token"


class Desk:
    """A console with a fake session: what it logged."""

    def __init__(self, token: str | None = TOKEN, host: str = "127.0.0.1", **web) -> None:
        self.events: list[dict] = []
        self.alarms = AlarmBook()
        self.desk = ActionDesk(
            log_event=lambda d, ns: self.events.append(d),
            alarms=self.alarms,
            gps_ns=lambda ns: ns,
            limiter=CommandLimiter(LIMITS, clock=lambda: 0.0),  # no refill: the burst alone
        )
        self.bus = StatusBus()
        self.sink = ConsoleSink(client_queue=8)
        self.server = ConsoleServer(
            WebConfig(host=host, port=0, token=token, **web), self.sink, self.desk, "v1"
        )

    async def __aenter__(self) -> Desk:
        await self.server.start()
        self.bus.add_sink(self.sink)
        return self

    async def __aexit__(self, *exc) -> None:
        await self.server.close()


async def _post(session, url, name, body, token=None, raw=None):
    headers = {"Authorization": f"Bearer {token}"} if token else {}
    data = raw if raw is not None else json.dumps(body).encode()
    async with session.post(f"{url}api/action/{name}", data=data, headers=headers) as r:
        return r.status, await r.json()


def test_the_page_and_its_assets_come_from_the_daemon_with_no_outside_reference():
    async def main():
        async with Desk() as d, aiohttp.ClientSession() as s:
            url = d.server.url
            async with s.get(url) as r:
                page = await r.text()
                assert r.status == 200
                assert "default-src 'self'" in r.headers["Content-Security-Policy"]
            for asset in re.findall(r'(?:src|href)="(/static/[^"]+)"', page):
                async with s.get(url.rstrip("/") + asset) as r:
                    assert r.status == 200, asset
            async with s.get(f"{url}static/../server.py") as r:
                assert r.status in (403, 404)
            async with s.get(f"{url}api/session") as r:
                assert await r.json() == {"vessel": "v1", "actions": True}

    asyncio.run(main())
    for f in STATIC.iterdir():  # nothing fetched from the internet, no third-party code
        text = f.read_text()
        assert not re.search(r"https?://", text), f"{f.name} refers to another site"


def test_the_websocket_sends_the_snapshot_first_then_every_publication():
    async def main():
        async with Desk() as d, aiohttp.ClientSession() as s:
            d.bus.publish("status", {"state": "running"})
            d.bus.publish("alarms", {"action": "raise"})  # not retained: not in a later snapshot
            d.bus.publish("clock", {"state": "LOCKED"})
            async with s.ws_connect(f"{d.server.url}ws") as ws:
                first = [json.loads((await ws.receive()).data) for _ in range(3)]
                assert [m["topic"] for m in first] == ["status", "clock", "_snapshot_end"]
                assert first[0]["data"] == {"state": "running"}
                d.bus.publish("sensors/ins", {"state": "connected"})
                d.bus.publish("alarms", {"action": "clear"})
                live = [json.loads((await ws.receive()).data) for _ in range(2)]
                assert live == [
                    {"topic": "sensors/ins", "data": {"state": "connected"}},
                    {"topic": "alarms", "data": {"action": "clear"}},
                ]
                assert d.sink.stats()["clients"] == 1
            with pytest.raises(aiohttp.WSServerHandshakeError) as e:  # another site's page
                await s.ws_connect(f"{d.server.url}ws", origin="http://example.org")
            assert e.value.status == 403

    asyncio.run(main())


def test_a_console_added_late_is_seeded_with_what_the_bus_retained():
    bus = StatusBus()
    bus.publish("checklist", {"guidance": {"accepted": 2}})
    sink = ConsoleSink()
    sink.seed(bus.retained)
    assert json.loads(sink.snapshot()[0]) == {"topic": "checklist", "data": {"guidance": {"accepted": 2}}}


def test_a_slow_client_loses_what_does_not_fit_counted_and_gets_a_fresh_snapshot():
    async def main():
        sink = ConsoleSink(client_queue=4)
        c = sink.connect()  # the snapshot: only the end marker
        for i in range(10):
            sink.offer("status", json.dumps({"i": i}).encode(), True, 1)
        assert sink.dropped == c.dropped == 7
        assert c.resync
        got = [await sink.next_frame(c) or "" for _ in range(4)]
        assert json.loads(got[-1])["data"] == {"i": 2}
        again = [json.loads(await sink.next_frame(c) or "") for _ in range(2)]  # caught up: a new snapshot
        assert again == [
            {"topic": "status", "data": {"i": 9}},
            {"topic": "_snapshot_end", "data": {"retained": 1}},
        ]

    asyncio.run(main())


def test_actions_need_the_operator_token():
    async def main():
        async with Desk() as d, aiohttp.ClientSession() as s:
            url = d.server.url
            status, body = await _post(s, url, "mark", {"text": "quay"})
            assert status == 401
            assert not body["ok"]
            assert "token" in body["message"]
            assert (await _post(s, url, "mark", {"text": "quay"}, token="wrong-token-000000"))[0] == 403
            assert d.events == []
            status, body = await _post(s, url, "mark", {"text": "quay", "id": 7}, token=TOKEN)
            assert status == 200
            assert body["ok"]
            assert body["id"] == 7
            assert d.events == [{"event": "mark", "source": "web", "text": "quay"}]
        async with Desk(token=None) as d, aiohttp.ClientSession() as s:
            status, body = await _post(s, d.server.url, "mark", {"text": "x"}, token=TOKEN)
            assert status == 403
            assert "read-only" in body["message"]
            assert d.events == []

    asyncio.run(main())


def test_actions_go_through_the_mqtt_commands_checks_and_rate_limits():
    async def main():
        async with Desk() as d, aiohttp.ClientSession() as s:
            url = d.server.url
            bad = [
                ("pass_start", None, b'{"pass_id": 0}'),
                ("pass_start", None, b'{"pass_id": 1, "pass_id": 2}'),
                ("mark", None, b'{"text": "a", "colour": 1}'),
                ("rotate", None, b"{}"),
                ("alarm_ack", None, b'{"alarm": "x y", "device": "ins"}'),
            ]
            for name, body, raw in bad:
                status, answer = await _post(s, url, name, body, token=TOKEN, raw=raw)
                assert status == 400, (name, raw, answer)
                assert not answer["ok"]
            refused = [e for e in d.events if e["event"] == "command_refused"]
            assert len(refused) == len(bad)
            assert {e["source"] for e in refused} == {"web"}
            codes = [(await _post(s, url, "pass_start", {"pass_id": 3}, token=TOKEN))[0] for _ in range(7)]
            assert codes == [200] * 5 + [429] * 2  # the MQTT bucket: 5 at once, then 2/s
            assert [e["pass_id"] for e in d.events if e["event"] == "pass_start"] == [3] * 5

    asyncio.run(main())


def test_an_active_alarm_is_acknowledged_and_the_pages_hear_of_it():
    async def main():
        async with Desk() as d, aiohttp.ClientSession() as s:
            url = d.server.url
            ack = {"alarm": "device_unavailable", "device": "ins"}
            assert (await _post(s, url, "alarm_ack", ack, token=TOKEN))[0] == 409  # not active
            d.alarms.raise_now("device_unavailable", "ins", 1, severity=CRITICAL, message="gone")
            status, body = await _post(s, url, "alarm_ack", ack, token=TOKEN)
            assert status == 200
            assert body["ok"]
            assert {"event": "alarm_ack", "source": "web", **ack} in d.events
            async with s.ws_connect(f"{url}ws") as ws:
                msg = json.loads((await ws.receive()).data)
                assert msg["topic"] == "_console"
                assert msg["data"]["acked"][0]["alarm"] == "device_unavailable"
                assert msg["data"]["acked"][0]["first_host_ns"] == 1  # the raise it acknowledged

    asyncio.run(main())


def test_off_loopback_the_console_refuses_to_start_without_tls():
    with pytest.raises(ConsoleRefused, match="not loopback"):
        tls_context(WebConfig(host="0.0.0.0"))

    async def main():
        d = Desk(host="0.0.0.0")
        with pytest.raises(ConsoleRefused):
            await d.server.start()
        assert d.server.runner is None

    asyncio.run(main())


def test_with_tls_the_console_is_served_over_https(tmp_path):
    pki = make_test_pki(tmp_path / "pki")
    pki.server_key.chmod(0o600)

    async def main():
        async with Desk(cert_file=pki.server_cert, key_file=pki.server_key) as d:
            assert d.server.url.startswith("https://127.0.0.1:")
            ctx = ssl.create_default_context(cafile=str(pki.ca))
            async with aiohttp.ClientSession() as s:
                async with s.get(d.server.url, ssl=ctx) as r:
                    assert r.status == 200
                with pytest.raises(aiohttp.ClientError):
                    async with s.get(d.server.url.replace("https", "http")) as r:
                        await r.read()

    asyncio.run(main())
