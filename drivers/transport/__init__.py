"""Async byte transports yielding ``(bytes, host_ns)`` chunks (docs/architecture.md §5).

- ``base`` — the Transport base class (queue, events, reconnect back-off), Chunk, TransportEvent.
- ``registry`` — the table of transports by ``kind`` and ``create_transport`` (imports lazily).
- ``serial_port``, ``udp``, ``tcp``, ``udp_batch`` — one transport each; ``recvmmsg`` — many
  datagrams per system call for ``udp_batch``; ``pathwatch`` — waiting for a serial port's
  path to come back (inotify) for ``serial_port``.
"""
