"""Foxglove live as the supervisor's consumer, over TLS: ``wss://`` with the certificate of
``web.tls`` (a PKCS#8 key), the bus's ``clock`` reaching a subscribed client, the records of its tap
on their channels, and at cancellation (the daemon's shutdown) the server stopped and the feed off
the bus."""

from __future__ import annotations

import asyncio
import socket
import ssl
import subprocess
import textwrap

from acquire.daemon.config import parse_vessel_config
from acquire.daemon.consumers import ChecklistPublisher, Tap
from acquire.daemon.supervisor import Supervisor
from acquire.foxglove.daemon import foxglove_consumer
from tests.acquire.daemon_util import free_port
from tests.foxglove_client import FoxgloveClient
from tests.mosquitto import make_test_pki
from tests.waiting import wait_until_async

T_NS = 1_400_000_000 * 10**9


def _config(tmp_path, port: int):
    pki = make_test_pki(tmp_path / "pki")
    key = tmp_path / "server-pkcs8.key"
    subprocess.run(
        ["openssl", "pkcs8", "-topk8", "-nocrypt", "-in", pki.server_key, "-out", key], check=True, timeout=60
    )
    key.chmod(0o600)
    text = textwrap.dedent(f"""\
        vessel: v1
        devices:
          - {{name: ins, kind: ins, protocol: nmea, transport: {{type: udp, host: 127.0.0.1, port: 7001}}}}
        session: {{directory: sessions}}
        web: {{port: {free_port(socket.SOCK_STREAM)}, foxglove_port: {port}, tls: {{cert_file: {pki.server_cert}, key_file: {key}}}}}
        """)
    return parse_vessel_config(text), ssl.create_default_context(cafile=str(pki.ca))


def _refused(port: int) -> bool:
    with socket.socket() as s:
        return s.connect_ex(("127.0.0.1", port)) != 0


def test_the_server_speaks_tls_feeds_from_bus_and_tap_and_stops_when_cancelled(tmp_path):
    port = free_port(socket.SOCK_STREAM)
    cfg, client_tls = _config(tmp_path, port)
    sup = Supervisor(cfg)
    live = foxglove_consumer(cfg, sup)
    assert live is not None
    tap = Tap("foxglove", live.kinds)

    async def main():
        task = asyncio.ensure_future(live.run(tap, ChecklistPublisher(sup.bus.publish)))
        await wait_until_async(lambda: live.port == port, 10, "the Foxglove server")
        feed = live.feeds[0]
        assert feed in sup.bus.sinks
        client = await FoxgloveClient.connect(f"wss://localhost:{port}", ssl=client_tls)
        try:

            def received() -> bool:  # publish until the subscription is in place
                sup.bus.publish("clock", {"state": "HOLDOVER", "gps_ns": T_NS, "error_bound_us": 9.0})
                tap.offer("event", {"event": "pass_start", "pass": 2}, T_NS)
                return {"/clock", "/log"} <= client.topics()

            async def poll_and_look() -> bool:
                await client.poll(0.05)
                return received()

            await wait_until_async(poll_and_look, 30, "/clock and /log at the client")
            clock = client.messages["/clock"][0][1]
            assert (clock["state"], clock["state_code"], clock["error_bound_us"]) == ("HOLDOVER", 1, 9.0)
            assert any("pass_start" in m["message"] for _, m in client.messages["/log"])
            assert client.server_info["name"] == "mls v1"
        finally:
            await client.close()
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
        assert feed not in sup.bus.sinks and live.port is None
        await wait_until_async(
            lambda: _refused(port), 10, "the port closed (the SDK stops its server in its own threads)"
        )

    asyncio.run(main())
