"""A UDP sender that loses, reorders and duplicates datagrams on cue (the ``udp_*`` faults).

``send(payload, gps_ns)`` consults the device's fault :class:`~sim_devices.faults.Timeline` at
``gps_ns`` (the truth-clock instant of the emission): ``udp_loss`` drops the datagram,
``udp_reorder`` holds it back and sends it right after the next one, ``udp_duplicate`` sends it
twice in a row — each with the fault's probability, drawn from a seeded generator. Send errors
(nobody listening yet: ICMP port unreachable reported on a later send) are counted, not raised.
"""

from __future__ import annotations

import socket
from typing import Protocol

import numpy as np

from sim_devices.faults import Timeline


class DatagramSender(Protocol):
    """Where an emulator sends its datagrams: a :class:`UdpLink`, or what stands for one (an
    offline session collects them)."""

    stats: dict[str, int]

    def send(self, payload: bytes, gps_ns: int, /) -> None: ...

    def close(self) -> None: ...


class UdpLink:
    def __init__(self, address: tuple[str, int], timeline: Timeline | None = None, seed: int = 0) -> None:
        self.address = address
        self.timeline = timeline
        self.rng = np.random.default_rng(seed)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4 * 1024 * 1024)
        self._held: bytes | None = None
        self.stats: dict[str, int] = {
            "datagrams_sent": 0,
            "bytes_sent": 0,
            "lost": 0,
            "reordered": 0,
            "duplicated": 0,
            "send_errors": 0,
        }
        self._faulty = timeline is not None and any(
            timeline.events(k) for k in ("udp_loss", "udp_reorder", "udp_duplicate")
        )

    def _draw(self, kind: str, gps_ns: int) -> bool:
        assert self.timeline is not None  # only a link with udp_* faults draws
        f = self.timeline.active(kind, gps_ns)
        return f is not None and (
            f.params["probability"] >= 1.0 or self.rng.random() < f.params["probability"]
        )

    def _out(self, payload: bytes) -> None:
        try:
            self.sock.sendto(payload, self.address)
        except OSError:
            self.stats["send_errors"] += 1
            return
        self.stats["datagrams_sent"] += 1
        self.stats["bytes_sent"] += len(payload)

    def send(self, payload: bytes, gps_ns: int) -> None:
        if not self._faulty:
            self._out(payload)
            return
        if self._draw("udp_loss", gps_ns):
            self.stats["lost"] += 1
            return
        if self._held is None and self._draw("udp_reorder", gps_ns):
            self._held = payload
            self.stats["reordered"] += 1
            return
        self._out(payload)
        if self._draw("udp_duplicate", gps_ns):
            self._out(payload)
            self.stats["duplicated"] += 1
        if self._held is not None:
            held, self._held = self._held, None
            self._out(held)

    def close(self) -> None:
        if self._held is not None:
            held, self._held = self._held, None
            self._out(held)
        self.sock.close()
