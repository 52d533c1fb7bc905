"""Foxglove live inside the daemon: with ``web.foxglove_port`` in the vessel config, ``mls
acquire`` runs a :class:`FoxgloveConsumer` next to the devices (as the console and the mount
watch): the SDK's WebSocket server on ``web.host`` (TLS with ``web.tls``), fed by
:class:`~acquire.foxglove.live.LiveFeed` from the record stream and the status bus.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any

from acquire.daemon.configschema import VesselConfig, WebConfig
from acquire.daemon.consumers import ChecklistPublisher, Tap
from acquire.daemon.supervisor import Supervisor
from acquire.errors import AcquireError
from acquire.foxglove.channels import Channels
from acquire.foxglove.live import LiveFeed, LiveOptions

log = logging.getLogger("mls.acquire")


class FoxgloveSetupError(AcquireError, ValueError):
    """The live Foxglove server cannot be set up from the vessel config (the message says why)."""


@dataclass
class FoxgloveConsumer:
    """Serves the vessel's Foxglove channels while the daemon runs (module docstring)."""

    web: WebConfig
    options: LiveOptions
    supervisor: Supervisor
    name: str = "foxglove"
    kinds: tuple[str, ...] = ("nav", "profile", "event")
    port: int | None = None  # the bound port, once serving
    feeds: list[LiveFeed] = field(default_factory=list)  # the current run's (tests read it)

    async def run(self, tap: Tap, checklist: ChecklistPublisher) -> None:
        import foxglove

        context = foxglove.Context()
        feed = LiveFeed(Channels(context, list(self.options.devices)), self.options)
        cert, key = _tls(self.web)
        server = foxglove.start_server(
            name=f"mls {self.supervisor.config.vessel}",
            host=self.web.host,
            port=self.web.foxglove_port,
            context=context,
            tls_cert=cert,
            tls_key=key,
        )
        bus = self.supervisor.bus
        self.port, self.feeds = server.port, [feed]
        bus.add_sink(feed)
        log.info(
            "foxglove live: %s://%s:%d", "wss" if self.web.cert_file else "ws", self.web.host, server.port
        )
        try:
            async for kind, record, gps_ns in tap:
                feed.feed(kind, record, gps_ns)
        finally:
            if feed in bus.sinks:
                bus.sinks.remove(feed)
            server.stop()
            self.port = None


def _tls(web: WebConfig) -> tuple[bytes | None, bytes | None]:
    """The server's certificate and PKCS#8 key (PEM) from ``web.tls``, None without it."""
    if web.cert_file is None or web.key_file is None:
        return None, None
    return web.cert_file.read_bytes(), web.key_file.read_bytes()


def _site_frame(cfg: VesselConfig) -> Any:
    """The site's LGF (None without a site file: the feed takes the first epoch's position)."""
    from acquire.daemon.config import site_of

    return None if cfg.site_file is None else site_of(cfg, FoxgloveSetupError)[1]


def foxglove_consumer(cfg: VesselConfig, sup: Supervisor) -> FoxgloveConsumer | None:
    """The daemon's live Foxglove server (None without ``web.foxglove_port``);
    :class:`FoxgloveSetupError` for a site file that cannot be read."""
    if cfg.web is None or cfg.web.foxglove_port is None:
        return None
    from acquire.daemon.config import mount_of

    devices = tuple(sorted(d.name for d in cfg.devices))
    options = LiveOptions(frame=_site_frame(cfg), mount=mount_of(cfg), devices=devices)
    return FoxgloveConsumer(cfg.web, options, sup)
