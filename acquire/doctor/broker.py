"""The MQTT broker of the config reachable: one MQTT 5 connection as the daemon makes it (TLS
context of :func:`acquire.status.mqtt.tls_context`, the credentials file's user), with a client
id of its own so that the running daemon's session is not taken over. Unreachable is a warning
(the status goes on on the local socket; the broker may be ashore, the link down); refused — a
certificate not verified, credentials refused — is not ready: it will not heal by itself."""

from __future__ import annotations

import asyncio
import os
import ssl
import time

import aiomqtt
from aiomqtt.exceptions import MqttConnectError

from acquire.doctor.result import CheckResult, fail, ok, skip, warn
from acquire.status.mqtt import MqttSettings, tls_context


async def _connect(s: MqttSettings, ctx: ssl.SSLContext | None, timeout_s: float) -> None:
    client = aiomqtt.Client(
        s.host,
        s.port,
        username=s.username,
        password=s.password,
        identifier=f"mls-doctor-{os.getpid()}",
        protocol=aiomqtt.ProtocolVersion.V5,
        tls_context=ctx,
        timeout=timeout_s,
    )
    async with asyncio.timeout(timeout_s + 1.0):
        async with client:
            pass


def _refused(e: BaseException) -> bool:
    cause = e.__cause__ or e.__context__
    return isinstance(e, MqttConnectError) or isinstance(cause, ssl.SSLError)


def broker_check(settings: MqttSettings | None, timeout_s: float = 3.0) -> CheckResult:
    if settings is None:
        return skip("broker", "no mqtt section: status on the local socket only")
    s = settings
    where = f"{s.host}:{s.port}" + (" (TLS)" if s.tls is not None else "")
    data = {"host": s.host, "port": s.port, "tls": s.tls is not None, "username": s.username}
    try:
        ctx = tls_context(s.tls) if s.tls is not None else None
    except (OSError, ssl.SSLError) as e:
        return fail(
            "broker",
            f"{where}: the TLS files cannot be used: {e}",
            "check mqtt.tls ca_file, cert_file, key_file",
            data=data,
        )
    t0 = time.monotonic()
    try:
        asyncio.run(_connect(s, ctx, timeout_s))
    except (aiomqtt.MqttError, OSError, TimeoutError) as e:
        text = str(e) or type(e).__name__
        data["error"] = text
        if _refused(e):
            return fail(
                "broker",
                f"{where} refused the connection: {text}",
                "check the CA (mqtt.tls.ca_file), the client certificate and the credentials file",
                data=data,
            )
        return warn(
            "broker",
            f"{where} unreachable: {text}",
            "is the broker running and the link up? (the daemon keeps retrying)",
            data=data,
        )
    data["connect_ms"] = round((time.monotonic() - t0) * 1e3, 1)
    return ok("broker", f"{where}: connected in {data['connect_ms']:.0f} ms", data=data)
