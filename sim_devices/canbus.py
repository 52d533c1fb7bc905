"""The CAN emulator: pass start/end event markers on a python-can bus, at the scenario's times.

Each :class:`~sim_devices.feed.PassMark` in the run window becomes an event-marker frame
(:func:`drivers.can.event_marker_message`, id 0x6E0) sent at the mark's instant on the truth
clock; the marker sequence counts from 1. The bus is python-can's ``udp_multicast`` on loopback
(across processes), as :func:`drivers.can.open_can_bus` opens it. Note that python-can binds the
port on every address, so two runs on one port see each other's frames whatever the group.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

from drivers.can import event_marker_message, open_can_bus
from sim_devices.feed import PassMark

if TYPE_CHECKING:
    import can

#: python-can's defaults for udp_multicast over IPv4 (the vessel config has no port key)
DEFAULT_GROUP = "239.74.163.2"
DEFAULT_PORT = 43113


@dataclass(frozen=True)
class CanSettings:
    interface: str = "udp_multicast"
    channel: str = DEFAULT_GROUP
    port: int = DEFAULT_PORT

    def bus_config(self) -> dict[str, str | int | bool]:
        cfg: dict[str, str | int | bool] = {"interface": self.interface, "channel": self.channel}
        if self.interface == "udp_multicast":
            cfg.update(port=self.port, loopback_only=True)
        return cfg


class MessageBus(Protocol):
    """Where the emulator sends its frames: a python-can bus, or what stands for one (an
    offline session collects them)."""

    def send(self, msg: can.Message, /) -> None: ...

    def shutdown(self) -> None: ...


class CanEmulator:
    name = "can"
    spin_ns = 200_000

    def __init__(self, marks: tuple[PassMark, ...], settings: CanSettings) -> None:
        self.marks = marks
        self.s = settings
        self.bus: MessageBus | None = None
        self.sent: list[dict] = []

    def prepare(self) -> dict:
        self.bus = open_can_bus(self.s.bus_config())
        return {**self.s.bus_config(), "markers": len(self.marks)}

    def run(self, clock, pacer, timing) -> bool:
        for seq, m in enumerate(self.marks, start=1):
            host = clock.host_ns(m.gps_ns)
            if not pacer.wait_until(host):
                return False
            assert self.bus is not None  # opened by prepare() (or set by the caller)
            self.bus.send(event_marker_message(m.kind, m.pass_id, seq))
            timing.record(host, time.monotonic_ns())
            self.sent.append({"sequence": seq, "kind": m.kind, "pass_id": m.pass_id, "gps_ns": m.gps_ns})
        return True

    def close(self) -> None:
        if self.bus is not None:
            self.bus.shutdown()
            self.bus = None

    def stats(self) -> dict:
        return {"markers": len(self.sent), "sent": self.sent}
