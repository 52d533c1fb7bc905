"""Sending the autopilot sentences of :mod:`acquire.guidance.autopilot` (``mls plan --nmea``).

- :class:`NmeaOutput`: where the sentences go — stdout (``-``), a file or serial device path,
  or ``udp://HOST:PORT`` (port 10110 when omitted);
- :func:`sentences_at`: the XTE and APB sentences for a vessel at a latitude and longitude,
  taken at the height of the line;
- :func:`follow_daemon`: the vessel's position and active pass from the running daemon's
  ``checklist`` messages on its status socket, and the sentences at every update.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, BinaryIO

if TYPE_CHECKING:
    import socket

from acquire.errors import AcquireError

NMEA_UDP_PORT = 10110


class NmeaOutputError(AcquireError, ValueError):
    """The destination of the sentences is malformed (the message says why)."""


class NmeaOutput:
    """Where the sentences go: stdout, a file/serial device, or UDP."""

    def __init__(self, dest: str):
        import socket
        import sys

        self.sock: socket.socket | None = None  # UDP
        self.fh: BinaryIO | None = None  # stdout, a file or a serial device otherwise
        self._own = dest != "-"
        if dest == "-":
            self.fh = sys.stdout.buffer
        elif dest.startswith("udp://"):
            from acquire.status.feed import parse_host_port

            try:
                self.addr = parse_host_port(dest[len("udp://") :], default_port=NMEA_UDP_PORT)
            except ValueError as e:
                raise NmeaOutputError(str(e)) from None
            self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        else:
            self.fh = open(dest, "ab", buffering=0)  # noqa: SIM115 (closed in close())

    def write(self, data: bytes) -> None:
        if self.sock is not None:
            self.sock.sendto(data, self.addr)
        else:
            assert self.fh is not None  # without a socket, __init__ opened the file (or stdout)
            self.fh.write(data)
            self.fh.flush()

    def close(self) -> None:
        if self.sock is not None:
            self.sock.close()
        elif self.fh is not None and self._own:
            self.fh.close()


def sentences_at(
    frame, line, lat_deg: float, lon_deg: float, *, talker: str, lookahead_m: float
) -> list[bytes]:
    """The XTE and APB sentences for following ``line`` (a planned pass in the LGF of ``frame``)
    from the vessel at ``lat_deg``, ``lon_deg``, its height taken as the line's."""
    import numpy as np

    from acquire.guidance.autopilot import autopilot_sentences

    p = frame.to_lgf([lat_deg], [lon_deg], [frame.height_m])[0]
    p[2] = line.start_lgf_m[2]
    return autopilot_sentences(np.asarray(p), line, talker=talker, lookahead_m=lookahead_m)


async def follow_daemon(
    socket_path: Path,
    plan,
    frame,
    active: int | None,
    out: NmeaOutput,
    talker: str,
    lookahead_m: float,
    on_link: Callable[[dict], None] | None = None,
) -> None:
    """Write the sentences to ``out`` at every vessel position the daemon publishes, for the
    pass ``active`` (else the daemon's active pass); ``on_link`` gets the feed's link events
    (``{"up": bool, "detail": str}``). Runs until cancelled."""
    from acquire.status.feed import LINK, SocketFeed, guidance_of

    async for topic, data in SocketFeed(socket_path):
        if topic == LINK:
            if on_link is not None:
                on_link(data)
            continue
        if topic != "checklist":
            continue
        g = guidance_of(data)
        vessel = g.get("vessel") or {}
        pid = active or (g.get("active") or {}).get("pass_id")
        if pid is None or "lat_deg" not in vessel:
            continue
        for s in sentences_at(
            frame,
            plan.by_id(int(pid)),
            vessel["lat_deg"],
            vessel["lon_deg"],
            talker=talker,
            lookahead_m=lookahead_m,
        ):
            out.write(s)
