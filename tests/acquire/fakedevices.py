"""Small fake devices for the supervisor tests (not a test module): an INS writing PHINS NMEA on
a real pty behind a symlink, a PPS and a ZFP1 profiler on real UDP sockets, all on one clock
(GPS = ``gps0_ns`` + host time since the start, no drift), with a record of every byte sent."""

from __future__ import annotations

import os
import socket
import threading
import time
import tty
from pathlib import Path

import numpy as np

from drivers.hydrins.nav import NavRecord, status_words
from drivers.hydrins.nmea_encode import encode_epoch, encode_zda
from drivers.pps import encode_pps_datagram
from drivers.zf.zfp1 import encode_profile

NS = 1_000_000_000
INS_PERIOD_NS = 20_000_000  # 50 Hz
PROFILE_PERIOD_NS = 50_000_000  # 20 profiles/s
INS_LATENCY_NS = 3_000_000
ZDA_DELAY_NS = 50_000_000
STALE_NS = 300_000_000  # a pulse or ZDA this late is not sent
POINTS = 600  # per profile: three ZFP1 packets


def devices_yaml(tmp: Path, prof_port: int, pps_port: int) -> str:
    """The ``devices:`` entries of a vessel config reading these fakes (YAML, at column 0): the
    INS on the pty link ``tmp/ins``, the profiler and the PPS on their UDP ports."""
    return (
        f"  - name: ins\n"
        f"    kind: ins\n"
        f"    protocol: nmea\n"
        f"    transport: {{type: serial, port: {tmp}/ins, baud: 115200}}\n"
        f"    latency: {{band_ms: [0.0, 20.0], rate_hz: 50.0, gap_s: 0.5}}\n"
        f"  - name: profiler\n"
        f"    kind: profiler\n"
        f"    protocol: zfp1\n"
        f"    transport: {{type: udp, host: 127.0.0.1, port: {prof_port}}}\n"
        f"    latency: {{band_ms: [0.0, 60.0], rate_hz: 20.0, gap_s: 0.5}}\n"
        f"  - name: pps\n"
        f"    kind: pps\n"
        f"    source: {{type: udp, host: 127.0.0.1, port: {pps_port}}}\n"
        f"    time_device: ins\n"
        f"    time_messages: [ZDA]\n"
    )


def nav_at(gps_ns: int, k: int) -> NavRecord:
    algo, system = status_words(
        navigation=True,
        fine_alignment=True,
        gps_received=True,
        gps_valid=True,
        gps_detected=True,
        utc_detected=True,
        pps_detected=True,
    )
    return NavRecord(
        "nmea",
        gps_ns=gps_ns,
        lat_deg=45.5 + 1e-6 * k,
        lon_deg=-73.55,
        height_m=-24.0,
        height_ref="ellipsoid",
        roll_rad=0.01,
        pitch_rad=-0.02,
        heading_rad=1.0,
        v_north_m_s=1.0,
        v_east_m_s=0.5,
        v_down_m_s=0.0,
        surge_m=0.0,
        sway_m=0.0,
        heave_m=0.01,
        sigma_roll_rad=2e-4,
        sigma_pitch_rad=2e-4,
        sigma_heading_rad=3e-4,
        sigma_north_m=0.02,
        sigma_east_m=0.02,
        sigma_down_m=0.03,
        sigma_v_north_m_s=0.01,
        sigma_v_east_m_s=0.01,
        sigma_v_down_m_s=0.01,
        algorithm_status=algo,
        system_status=system,
        user_status=0,
    )


class FakeDevices(threading.Thread):
    def __init__(self, link: Path, profiler_port: int, pps_port: int, seconds: float, gps0_ns: int):
        super().__init__(daemon=True)
        self.link = Path(link)
        self.addr_prof = ("127.0.0.1", profiler_port)
        self.addr_pps = ("127.0.0.1", pps_port)
        self.seconds = seconds
        self.gps0_ns = gps0_ns
        self.master, slave = os.openpty()
        tty.setraw(slave)
        self._slave = slave
        os.symlink(os.ttyname(slave), self.link)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.ins_bytes = bytearray()
        self.datagrams: list[bytes] = []
        self.epochs: list[int] = []  # GPS ns of each INS epoch sent
        self.pulses: list[tuple[int, int]] = []  # (GPS second, host stamp)
        self.start_host_ns = 0
        self.hooks: list[tuple[float, object]] = []  # (seconds after start, callable) run in order

    def gps(self, host_ns: int) -> int:
        return self.gps0_ns + host_ns - self.start_host_ns

    def host(self, gps_ns: int) -> int:
        return self.start_host_ns + gps_ns - self.gps0_ns

    def schedule(self) -> list[tuple[int, str, int]]:
        ev: list[tuple[int, str, int]] = []
        end = self.gps0_ns + int(self.seconds * NS)
        first_s = -(-self.gps0_ns // NS)
        for s in range(first_s, end // NS + 1):
            ev.append((self.host(s * NS), "pps", s))
            ev.append((self.host(s * NS) + ZDA_DELAY_NS, "zda", s))
        g = -(-self.gps0_ns // INS_PERIOD_NS) * INS_PERIOD_NS
        while g < end:
            ev.append((self.host(g) + INS_LATENCY_NS, "nav", g))
            g += INS_PERIOD_NS
        g = -(-self.gps0_ns // PROFILE_PERIOD_NS) * PROFILE_PERIOD_NS
        while g < end:
            ev.append((self.host(g) + PROFILE_PERIOD_NS // 2, "profile", g))
            g += PROFILE_PERIOD_NS
        for at_s, fn in self.hooks:
            ev.append((self.start_host_ns + int(at_s * NS), "hook", id(fn)))
        return sorted(ev, key=lambda e: e[0])

    def run(self) -> None:
        self.start_host_ns = time.monotonic_ns() + 200_000_000
        hooks = {id(fn): fn for _, fn in self.hooks}
        rng = np.random.default_rng(1)
        for host_ns, kind, arg in self.schedule():
            time.sleep(max(host_ns - time.monotonic_ns(), 0) / NS)
            if kind in ("pps", "zda") and time.monotonic_ns() - host_ns > STALE_NS:
                continue  # stalled (a blocked pty write while the daemon was down): a receiver
                # does not send an old second's pulse and sentence together with the next ones
            if kind == "pps":
                self.sock.sendto(encode_pps_datagram(len(self.pulses) + 1, host_ns), self.addr_pps)
                self.pulses.append((arg, host_ns))
            elif kind == "zda":
                self._write(encode_zda(arg * NS))
            elif kind == "nav":
                self.epochs.append(arg)
                self._write(encode_epoch(nav_at(arg, len(self.epochs))))
            elif kind == "profile":
                counter = len(self.datagrams) // 3
                r = rng.integers(0, 200_000, POINTS).astype(np.uint32)
                r[::4] = 0  # no returns
                i = rng.integers(1, 65535, POINTS).astype(np.uint16)
                for d in encode_profile(
                    counter,
                    arg,
                    PROFILE_PERIOD_NS // 5080,
                    0,
                    70866,
                    r,
                    i,
                    max_payload=40 + 4 + 6 * (POINTS // 3),
                ):
                    self.sock.sendto(d, self.addr_prof)
                    self.datagrams.append(d)
            else:
                hooks[arg]()

    def _write(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            n = os.write(self.master, view)
            view = view[n:]
        self.ins_bytes += data

    def close(self) -> None:
        for fd in (self.master, self._slave):
            try:
                os.close(fd)
            except OSError:
                pass
        self.sock.close()
