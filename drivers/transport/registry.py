"""The transports by name: :data:`TRANSPORTS` (the config's ``kind`` → where the class lives) and
:func:`create_transport`, which imports only the transport asked for.

A plain table after python-can's ``BACKENDS``: a new transport is one module with a
:class:`~drivers.transport.base.Transport` subclass and one line here; nothing is filed by
importing a module.

- ``serial`` (:mod:`drivers.transport.serial_port`): a serial port or pty, read by a thread.
- ``udp`` (:mod:`drivers.transport.udp`): one datagram per chunk, optionally multicast.
- ``tcp`` (:mod:`drivers.transport.tcp`): a client that reconnects.
- ``udp-batch`` (:mod:`drivers.transport.udp_batch`): UDP for high datagram rates (the profiler
  at the full Z+F rate): kernel receive stamps, every waiting datagram drained per wake-up.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from typing import Any

from drivers.base import create_from_config
from drivers.transport.base import Transport, TransportEvent

#: kind → (module, class name)
TRANSPORTS: dict[str, tuple[str, str]] = {
    "serial": ("drivers.transport.serial_port", "SerialTransport"),
    "udp": ("drivers.transport.udp", "UdpTransport"),
    "tcp": ("drivers.transport.tcp", "TcpTransport"),
    "udp-batch": ("drivers.transport.udp_batch", "BatchUdpTransport"),
}


def transport_class(entry: tuple[str, str]) -> type[Transport]:
    """A :data:`TRANSPORTS` entry → the class, its module imported now."""
    module, name = entry
    return getattr(importlib.import_module(module), name)


def create_transport(
    config: dict[str, Any], on_event: Callable[[TransportEvent], None] | None = None
) -> Transport:
    """A config mapping with ``kind`` and that transport's keyword arguments → a transport."""
    return create_from_config("transport", TRANSPORTS, config, transport_class, on_event=on_event)
