"""The console's web server (aiohttp, in the daemon's own event loop).

Routes: ``GET /`` the page and ``/static/…`` its assets (all served from this package: no CDN,
nothing fetched at sea); ``GET /ws`` a WebSocket pushing every status-bus message
(:mod:`acquire.console.fanout`: the snapshot first, then live; refused to a page of another
origin); ``GET /api/session`` whether the console takes actions; ``POST /api/action/<name>``
an operator action (:mod:`acquire.console.actions`: the bearer token, then the MQTT commands'
checks).

Over anything but loopback the server refuses to start without TLS (:class:`ConsoleRefused`).
"""

from __future__ import annotations

import asyncio
import contextlib
import ssl
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import urlsplit

from aiohttp import WSMsgType, web

from acquire.console.actions import ActionDesk, ActionResult, token_refusal
from acquire.console.fanout import ConsoleSink
from acquire.daemon.configschema import WebConfig
from acquire.errors import AcquireError
from acquire.status.mqtt import is_loopback

STATIC = Path(__file__).resolve().parent / "static"
MAX_ACTION_BYTES = 4096  # a command payload is ≤ 1 KiB: anything far larger is cut off here
SECURITY_HEADERS = {
    "Content-Security-Policy": "default-src 'self'; connect-src 'self'; img-src 'self' data:; "
    "style-src 'self'; script-src 'self'; frame-ancestors 'none'",
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",
    "Cache-Control": "no-store",
}


class ConsoleRefused(AcquireError, RuntimeError):
    """The console cannot be served as configured (the message says why)."""


def tls_context(web_cfg: WebConfig) -> ssl.SSLContext | None:
    """The server's TLS context (TLS ≥ 1.2), None without ``web.tls``; :class:`ConsoleRefused`
    for a host off loopback without it."""
    if web_cfg.cert_file is None or web_cfg.key_file is None:
        if not is_loopback(web_cfg.host):
            raise ConsoleRefused(
                f"web.host {web_cfg.host} is not loopback: the console needs TLS there "
                "(web.tls: cert_file, key_file)"
            )
        return None
    ctx = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
    ctx.minimum_version = ssl.TLSVersion.TLSv1_2
    ctx.load_cert_chain(str(web_cfg.cert_file), str(web_cfg.key_file))
    return ctx


@dataclass
class ConsoleServer:
    """The console's aiohttp application on ``web.host:web.port``."""

    config: WebConfig
    sink: ConsoleSink
    desk: ActionDesk | None  # None: read-only (no actions at all)
    vessel: str = ""
    runner: web.AppRunner | None = None
    port: int | None = None  # the bound port (``web.port`` 0: a free one)

    @property
    def url(self) -> str:
        scheme = "https" if self.config.cert_file is not None else "http"
        host = f"[{self.config.host}]" if ":" in self.config.host else self.config.host
        return f"{scheme}://{host}:{self.port if self.port is not None else self.config.port}/"

    def app(self) -> web.Application:
        app = web.Application(client_max_size=MAX_ACTION_BYTES, middlewares=[_headers])
        app.router.add_get("/", self._index)
        app.router.add_get("/ws", self._ws)
        app.router.add_get("/api/session", self._session)
        app.router.add_post("/api/action/{name}", self._action)
        app.router.add_static("/static/", STATIC, follow_symlinks=False)
        return app

    async def start(self) -> None:
        """Bind and serve; :class:`ConsoleRefused` (no TLS off loopback) or ``OSError``."""
        ctx = tls_context(self.config)
        runner = web.AppRunner(self.app(), access_log=None, handle_signals=False, shutdown_timeout=1.0)
        await runner.setup()
        site = web.TCPSite(runner, self.config.host, self.config.port, ssl_context=ctx)
        try:
            await site.start()
        except BaseException:
            await runner.cleanup()
            raise
        self.runner = runner
        server = site._server  # the bound socket's port (web.port 0 in tests)
        if isinstance(server, asyncio.Server) and server.sockets:
            self.port = int(server.sockets[0].getsockname()[1])

    async def close(self) -> None:
        """Tell the pages the console closes, then stop serving."""
        self.sink.close_all()
        if self.runner is not None:
            with contextlib.suppress(Exception):
                await asyncio.wait_for(self.runner.cleanup(), 3.0)
            self.runner = None

    async def _index(self, request: web.Request) -> web.StreamResponse:
        return web.FileResponse(STATIC / "index.html")

    async def _session(self, request: web.Request) -> web.Response:
        return web.json_response(
            {"vessel": self.vessel, "actions": self.desk is not None and self.config.token is not None}
        )

    async def _ws(self, request: web.Request) -> web.StreamResponse:
        origin = request.headers.get("Origin")
        if origin is not None and urlsplit(origin).netloc != request.host:
            # another site's page in the bridge's browser must not read the survey
            return web.json_response({"ok": False, "message": "WebSocket from another origin"}, status=403)
        ws = web.WebSocketResponse(heartbeat=20.0, max_msg_size=4096)
        await ws.prepare(request)
        client = self.sink.connect()
        sender = asyncio.ensure_future(self._send(ws, client))
        try:
            async for msg in ws:  # the page sends nothing; this notices it going away
                if msg.type in (WSMsgType.ERROR, WSMsgType.CLOSE):
                    break
        finally:
            self.sink.disconnect(client)
            sender.cancel()
            with contextlib.suppress(asyncio.CancelledError, ConnectionError):
                await sender
        return ws

    async def _send(self, ws: web.WebSocketResponse, client) -> None:
        while True:
            text = await self.sink.next_frame(client)
            if text is None:
                await ws.close()
                return
            await ws.send_str(text)

    async def _action(self, request: web.Request) -> web.Response:
        name = request.match_info["name"]
        refusal = token_refusal(request.headers.get("Authorization"), self.config.token)
        if refusal is None and self.desk is None:
            refusal = ActionResult(403, name, False, "read-only console")
        if refusal is not None:
            return _answer(refusal, name, {"WWW-Authenticate": "Bearer"} if refusal.status == 401 else None)
        assert self.desk is not None, "checked above"
        result = self.desk.handle(name, await request.read())
        if result.ok and name == "alarm_ack":
            self.sink.push("_console", {"acked": list(self.desk.acked.values())})
        return _answer(result, name, None)


def _answer(result: ActionResult, name: str, headers: dict[str, str] | None) -> web.Response:
    body = result.as_dict()
    body["command"] = body["command"] or name[:40]
    return web.json_response(body, status=result.status, headers=headers)


@web.middleware
async def _headers(request: web.Request, handler) -> web.StreamResponse:
    response = await handler(request)
    if not response.prepared:
        response.headers.update(SECURITY_HEADERS)
    return response
