"""A Foxglove WebSocket client for the tests (aiohttp, protocol ``foxglove.sdk.v1``): it
subscribes to every channel the server advertises and decodes what arrives — protobuf with the
descriptors of the advertisement (:mod:`tests.foxglove_wire`), JSON as JSON."""

from __future__ import annotations

import asyncio
import base64
import json
import struct
from dataclasses import dataclass, field
from typing import Any

import aiohttp

from tests.foxglove_wire import Descriptors

SUBPROTOCOL = "foxglove.sdk.v1"
MESSAGE_DATA = 1  # the binary opcode of a message


@dataclass
class FoxgloveClient:
    ws: aiohttp.ClientWebSocketResponse
    session: aiohttp.ClientSession
    channels: dict[int, dict] = field(default_factory=dict)  # id → its advertisement
    subscriptions: dict[int, int] = field(default_factory=dict)  # subscription id → channel id
    messages: dict[str, list[tuple[int, Any]]] = field(default_factory=dict)  # topic → (log ns, msg)
    server_info: dict = field(default_factory=dict)
    descriptors: dict[int, Descriptors] = field(default_factory=dict)  # protobuf channel id → types

    @classmethod
    async def connect(cls, url: str, ssl: Any = True) -> FoxgloveClient:
        session = aiohttp.ClientSession()
        try:
            ws = await session.ws_connect(url, protocols=[SUBPROTOCOL], ssl=ssl)
        except BaseException:
            await session.close()
            raise
        return cls(ws, session)

    async def close(self) -> None:
        await self.ws.close()
        await self.session.close()

    def topics(self) -> set[str]:
        return {t for t, msgs in self.messages.items() if msgs}

    async def poll(self, quiet_s: float) -> None:
        """Handle what arrives until nothing has for ``quiet_s`` seconds."""
        while True:
            try:
                msg = await asyncio.wait_for(self.ws.receive(), quiet_s)
            except TimeoutError:
                return
            if msg.type == aiohttp.WSMsgType.TEXT:
                await self._control(json.loads(msg.data))
            elif msg.type == aiohttp.WSMsgType.BINARY:
                self._data(msg.data)
            else:
                raise AssertionError(f"the server closed the connection: {msg.type} {msg.data!r}")

    async def _control(self, doc: dict) -> None:
        if doc["op"] == "serverInfo":
            self.server_info = doc
        elif doc["op"] == "advertise":
            new = [c for c in doc["channels"] if c["id"] not in self.channels]
            for c in new:
                self.channels[c["id"]] = c
                self.subscriptions[c["id"]] = c["id"]  # one subscription per channel, same id
                if c["encoding"] == "protobuf":
                    self.descriptors[c["id"]] = Descriptors.parse(base64.b64decode(c["schema"]))
            if new:
                subs = [{"id": c["id"], "channelId": c["id"]} for c in new]
                await self.ws.send_json({"op": "subscribe", "subscriptions": subs})

    def _data(self, data: bytes) -> None:
        assert data[0] == MESSAGE_DATA, data[:1]
        sub, log_ns = struct.unpack_from("<IQ", data, 1)
        c = self.channels[self.subscriptions[sub]]
        payload = data[13:]
        if c["encoding"] == "json":
            msg = json.loads(payload)
        else:
            assert c["encoding"] == "protobuf", c
            msg = self.descriptors[c["id"]].decode(f".{c['schemaName']}", payload)
        self.messages.setdefault(c["topic"], []).append((log_ns, msg))
