"""The console inside the daemon: when the vessel config has a ``web`` section, ``mls acquire``
runs a :class:`ConsoleConsumer` next to the devices (as the guidance and the mount watch).

Its task serves the page (:class:`~acquire.console.server.ConsoleServer`), adds its sink
(:class:`~acquire.console.fanout.ConsoleSink`) to the supervisor's status bus, seeded with what
the bus retained before, and follows the vessel's last calibration in the history
(:mod:`acquire.console.history`); at shutdown the task is cancelled and all is undone. A console that
cannot bind its port fails as any consumer does (``consumer_failed``, retried with a back-off):
the acquisition goes on without it.
"""

from __future__ import annotations

import asyncio
import logging
from dataclasses import dataclass
from pathlib import Path

from acquire.console.actions import ActionDesk
from acquire.console.fanout import ConsoleSink
from acquire.console.history import follow_history
from acquire.console.server import ConsoleServer, tls_context
from acquire.daemon.configschema import VesselConfig, WebConfig
from acquire.daemon.consumers import ChecklistPublisher, Tap
from acquire.daemon.supervisor import Supervisor

log = logging.getLogger("mls.acquire")


@dataclass
class ConsoleConsumer:
    """Serves the console while the daemon runs (a consumer that takes no records)."""

    server: ConsoleServer
    supervisor: Supervisor
    name: str = "console"
    kinds: tuple[str, ...] = ()  # the bus is its input, not the record stream
    history_db: Path | None = None  # the calibration history (None: calib.assess.history's default)

    async def run(self, tap: Tap, checklist: ChecklistPublisher) -> None:
        bus, sink = self.supervisor.bus, self.server.sink
        sink.seed(bus.retained)
        await self.server.start()
        bus.add_sink(sink)
        log.info("console: %s", self.server.url)
        history = asyncio.create_task(
            follow_history(self.supervisor.config.vessel, sink.push, self.history_db)
        )
        try:
            await asyncio.Event().wait()  # until the supervisor cancels the consumers
        finally:
            history.cancel()
            if sink in bus.sinks:
                bus.sinks.remove(sink)
            await asyncio.shield(self.server.close())


def make_server(web_cfg: WebConfig, sup: Supervisor) -> ConsoleServer:
    """The console's server for the supervisor ``sup`` (actions recorded in its session)."""
    desk = ActionDesk(log_event=sup.log_event, alarms=sup.alarms, gps_ns=sup.clock.gps_ns)
    return ConsoleServer(web_cfg, ConsoleSink(), desk, vessel=sup.config.vessel)


def console_consumer(
    cfg: VesselConfig, sup: Supervisor, history_db: Path | None = None
) -> ConsoleConsumer | None:
    """The daemon's console (None without a ``web`` section); :class:`ConsoleRefused` when it
    could not be served (TLS missing off loopback).
    ``history_db``: the calibration history it shows the last result of (None: the default)."""
    if cfg.web is None:
        return None
    tls_context(cfg.web)  # refused now, at start-up, rather than in the consumer's task
    return ConsoleConsumer(make_server(cfg.web, sup), sup, history_db=history_db)
