"""The Hydrins INS emulator: the scenario's navigation on a pseudo-terminal, in real time.

Output (:class:`InsSettings`): the PHINS-standard NMEA block (:func:`drivers.hydrins.nmea_encode.
encode_epoch`) at ``rate_hz`` (default 100, up to 200) plus ``$GPZDA`` once per second,
``zda_delay_s`` after each PPS edge (the whole GPS second S, in UTC); or STDBIN frames
(:func:`drivers.hydrins.stdbin_encode.encode_nav`, version ``stdbin_version``; no ZDA — the frame's
validity time and system-date block date it). Epoch k carries the time tag of its GPS instant
t_k (UTC on the wire) and leaves at ``host(t_k) + latency_s + U(0, jitter_s)`` on the truth
clock (host seconds: latency and jitter are the device's, not scaled by ``--speed``), never
before the previous epoch.

Status words follow the scenario: during the first ``alignment_s`` of the run the INS aligns
(alignment bit, not navigating); then it navigates, fine-aligned, GNSS received and valid, UTC
and PPS detected. A ``gnss_outage`` fault sets dead reckoning and clears GPS received/valid
for the epochs in its window, and lets the reported position drift north at
``position_drift_m_s`` with the north/east σ growing alike.

Counts (:meth:`InsEmulator.stats`): ``epochs`` written, of which ``epochs_unplugged`` while
unplugged and ``epochs_in_flight`` cut off by an unplug (not yet read when the pty closed): what
a reader can be held to is ``epochs`` less those two.

Faults (:mod:`sim_devices.faults`): ``serial_unplug``, ``garbage``, ``bad_checksum``,
``ins_latency_jump`` (on the epochs whose time tag is in the window), ``gnss_outage``,
``zda_late`` (NMEA: the ZDAs of the seconds in the window leave ``delay_s`` later),
``leap_second`` (the UTC tags of the epochs and ZDAs in the window are made with the fault's
GPS − UTC; an NMEA INS then announces its count, ``$PMLS,GPSUTC``, before every ZDA of the run
and before the first epoch tagged with a new count).
"""

from __future__ import annotations

import math
import time
from collections import deque
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from calib.core.frames import leap_seconds_at_gps_ns
from drivers.hydrins.nav import status_words
from drivers.hydrins.nmea_encode import encode_epoch, encode_gps_utc, encode_zda
from drivers.hydrins.stdbin_encode import encode_nav
from sim_devices.faults import Fault, Timeline
from sim_devices.feed import InsTrack
from sim_devices.serialpty import PtyPort

NS_PER_S = 1_000_000_000
_WGS84_A, _WGS84_E2 = 6378137.0, 6.69437999014e-3
# bytes a decoder would take for the start of something: never in injected garbage
_NMEA_FORBIDDEN = set(b"$!*\r\n\t\x0b\x0c ")
_STDBIN_FORBIDDEN = set(b"IA")
_EV_LINK, _EV_ZDA, _EV_NAV, _EV_GARBAGE = 0, 1, 2, 3


@dataclass(frozen=True)
class InsSettings:
    protocol: str = "nmea"  # nmea | stdbin
    rate_hz: float = 100.0
    stdbin_version: int = 3
    latency_s: float = 0.003
    jitter_s: float = 0.0005
    zda_delay_s: float = 0.05
    alignment_s: float = 0.0
    talker: str = "HE"
    backlog_s: float = 0.05
    linger_s: float = 0.5  # the pty stays open this long after the last epoch

    def __post_init__(self) -> None:
        if self.protocol not in ("nmea", "stdbin"):
            raise ValueError(f"INS protocol {self.protocol!r}: expected nmea or stdbin")
        if not 0 < self.rate_hz <= 200:
            raise ValueError(f"INS rate {self.rate_hz:g} Hz: expected 0 < rate ≤ 200")
        if self.stdbin_version not in (2, 3, 4, 5):
            raise ValueError(f"STDBIN version {self.stdbin_version}: expected 2, 3, 4 or 5")
        for name in ("latency_s", "jitter_s", "zda_delay_s", "alignment_s"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"INS {name} {getattr(self, name)!r}: expected ≥ 0")
        if self.zda_delay_s >= 0.9:
            raise ValueError(
                f"INS zda_delay_s {self.zda_delay_s:g}: expected < 0.9 s (a ZDA must follow its PPS edge)"
            )


def _garbage(rng: np.random.Generator, n: int, forbidden: set[int]) -> bytes:
    alphabet = np.array([b for b in range(256) if b not in forbidden], dtype=np.uint8)
    return rng.choice(alphabet, size=n).tobytes()


def _corrupt_nmea(block: bytes, rng: np.random.Generator, probability: float) -> tuple[bytes, int]:
    """Wrong checksum on each sentence (with ``probability``); returns the bytes and the count."""
    out, n = [], 0
    for sentence in block.split(b"\r\n"):
        if len(sentence) > 3 and sentence[-3:-2] == b"*" and (probability >= 1 or rng.random() < probability):
            sentence = sentence[:-2] + b"%02X" % (int(sentence[-2:], 16) ^ 0x5A)
            n += 1
        out.append(sentence)
    return b"\r\n".join(out), n


class InsEmulator:
    name = "ins"
    spin_ns = 0  # sleep only: the output jitter (0.5 ms by default) dwarfs the sleep overshoot (10–30 µs)

    def __init__(
        self,
        track: InsTrack,
        settings: InsSettings,
        faults: list[Fault],
        start_gps_ns: int,
        end_gps_ns: int,
        link: str | Path,
        seed: int = 0,
    ) -> None:
        self.track = track
        self.s = settings
        self.faults = faults
        self.timeline = Timeline(faults, start_gps_ns)
        self.start_gps_ns, self.end_gps_ns = start_gps_ns, end_gps_ns
        self.port = PtyPort(link, settings.backlog_s)
        self.rng = np.random.default_rng([seed, 1])
        self.counts = {
            "epochs": 0,
            "epochs_unplugged": 0,  # written while unplugged: lost to the fault
            "epochs_in_flight": 0,  # written before an unplug, not yet read at it: lost to the fault too
            "zda": 0,
            "corrupted": 0,
            "garbage_bytes": 0,
        }
        self._epoch_ends: deque[int] = deque(maxlen=4096)  # port.accepted after each epoch since the plug
        self.applied: list[dict] = []
        # an NMEA INS with a leap_second fault announces its GPS − UTC all along ($PMLS,GPSUTC)
        self.announce = settings.protocol == "nmea" and any(f.kind == "leap_second" for f in faults)
        self._announced: int | None = None  # the count announced last

    # -- schedule ---------------------------------------------------------------------------------

    def schedule(self, clock) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(host_ns, event kind, argument) of every emission, in emission order."""
        s, tr = self.s, self.track
        lat = np.full(len(tr), round(s.latency_s * NS_PER_S), dtype=np.int64)
        for j0, j1, jump in self.timeline.events("ins_latency_jump"):
            lat[(tr.gps_ns >= j0) & (tr.gps_ns < j1)] += round(jump.params["latency_s"] * NS_PER_S)
        jitter = np.rint(self.rng.uniform(0.0, s.jitter_s, len(tr)) * NS_PER_S).astype(np.int64)
        nav_host = np.maximum.accumulate(clock.host_ns_array(tr.gps_ns) + lat + jitter)
        hosts, kinds, args = [nav_host], [np.full(len(tr), _EV_NAV)], [np.arange(len(tr))]
        if s.protocol == "nmea":
            sec = np.arange(
                -(-self.start_gps_ns // NS_PER_S), -(-self.end_gps_ns // NS_PER_S), dtype=np.int64
            )
            zda_host = clock.host_ns_array(sec * NS_PER_S) + round(s.zda_delay_s * NS_PER_S)
            for z0, z1, late in self.timeline.events("zda_late"):
                zda_host[(sec * NS_PER_S >= z0) & (sec * NS_PER_S < z1)] += round(
                    late.params["delay_s"] * NS_PER_S
                )
            hosts.append(zda_host)
            kinds.append(np.full(sec.size, _EV_ZDA))
            args.append(sec)
        for i, f in enumerate(self.faults):
            g0, g1 = f.window_ns(self.start_gps_ns)
            if f.kind == "serial_unplug":
                marks = [(g0, 0)] + ([] if g1 is None or g1 >= self.end_gps_ns else [(g1, 1)])
                for g, what in marks:
                    hosts.append(np.array([clock.host_ns(g)]))
                    kinds.append(np.array([_EV_LINK]))
                    args.append(np.array([what]))
            elif f.kind == "garbage":
                hosts.append(np.array([clock.host_ns(g0)]))
                kinds.append(np.array([_EV_GARBAGE]))
                args.append(np.array([i]))
        h, k, a = np.concatenate(hosts), np.concatenate(kinds), np.concatenate(args)
        order = np.lexsort((k, h))
        return h[order], k[order], a[order]

    # -- content ----------------------------------------------------------------------------------

    def nav_bytes(self, k: int) -> bytes:
        s, tr, tl = self.s, self.track, self.timeline
        gps = int(tr.gps_ns[k])
        nav = tr.nav(k, s.protocol)
        aligning = gps < self.start_gps_ns + round(s.alignment_s * NS_PER_S)
        outage = tl.active("gnss_outage", gps)
        if outage is not None:
            started = tl.started_at("gnss_outage", gps)
            assert started is not None  # an active outage has started
            dt_s = (gps - started) / NS_PER_S
            err_m = outage.params["position_drift_m_s"] * dt_s
            phi = math.radians(nav.lat_deg)
            meridian_m = _WGS84_A * (1 - _WGS84_E2) / (1 - _WGS84_E2 * math.sin(phi) ** 2) ** 1.5
            nav = replace(
                nav,
                lat_deg=nav.lat_deg + math.degrees(err_m / meridian_m),
                sigma_north_m=math.hypot(nav.sigma_north_m, err_m),
                sigma_east_m=math.hypot(nav.sigma_east_m, err_m),
            )
        algo, system = status_words(
            navigation=not aligning,
            alignment=aligning,
            fine_alignment=not aligning,
            dead_reckoning=outage is not None,
            gps_received=outage is None,
            gps_valid=outage is None,
            gps_detected=True,
            utc_detected=True,
            pps_detected=True,
        )
        nav = replace(nav, algorithm_status=algo, system_status=system, user_status=0)
        leap = self.gps_minus_utc_s(gps)
        if s.protocol == "nmea":
            return self._announcement(gps, leap, every=False) + encode_epoch(nav, s.talker, leap)
        return encode_nav(nav, s.stdbin_version, counter=k, gps_minus_utc_s=leap)

    def gps_minus_utc_s(self, gps_ns: int) -> int | None:
        """The GPS − UTC a ``leap_second`` fault makes the INS believe at ``gps_ns`` (None: the table's)."""
        f = self.timeline.active("leap_second", gps_ns)
        return None if f is None else f.params["gps_minus_utc_s"]

    def zda_bytes(self, second: int) -> bytes:
        """The ZDA of a GPS second (after the announcement of GPS − UTC, when the INS makes one)."""
        gps = second * NS_PER_S
        leap = self.gps_minus_utc_s(gps)
        return self._announcement(gps, leap, every=True) + encode_zda(gps, gps_minus_utc_s=leap)

    def _announcement(self, gps_ns: int, leap: int | None, every: bool) -> bytes:
        """``$PMLS,GPSUTC`` before every ZDA and before the first epoch tagged with a new count."""
        if not self.announce:
            return b""
        value = leap_seconds_at_gps_ns(gps_ns) if leap is None else leap
        if not every and value == self._announced:
            return b""
        self._announced = value
        return encode_gps_utc(value)

    def _checksums(self, data: bytes, gps_ns: int) -> bytes:
        f = self.timeline.active("bad_checksum", gps_ns)
        if f is None:
            return data
        p = f.params["probability"]
        if self.s.protocol == "nmea":
            data, n = _corrupt_nmea(data, self.rng, p)
        elif p >= 1 or self.rng.random() < p:
            data, n = data[:-1] + bytes([data[-1] ^ 0xFF]), 1
        else:
            n = 0
        self.counts["corrupted"] += n
        return data

    # -- run --------------------------------------------------------------------------------------

    def prepare(self) -> dict:
        pty = self.port.plug()
        return {
            "link": str(self.port.link),
            "pty": pty,
            "protocol": self.s.protocol,
            "rate_hz": self.s.rate_hz,
            "stdbin_version": self.s.stdbin_version if self.s.protocol == "stdbin" else None,
        }

    def run(self, clock, pacer, timing) -> bool:
        hosts, kinds, args = self.schedule(clock)
        port, mono = self.port, time.monotonic_ns
        for host, kind, arg in zip(hosts.tolist(), kinds.tolist(), args.tolist(), strict=True):
            if kind == _EV_NAV:  # build the bytes before the instant, write at it
                data = self.nav_bytes(arg)
            elif kind == _EV_ZDA:
                data = self.zda_bytes(arg)
            if not pacer.wait_until(host):
                return False
            gps_now = clock.gps_ns(host)
            if kind == _EV_LINK:
                if arg == 0:
                    self._count_in_flight(port.unplug())
                    self.applied.append({"kind": "unplugged", "host_ns": mono()})
                else:
                    path = port.plug()
                    self.applied.append({"kind": "replugged", "host_ns": mono(), "pty": path})
                continue
            if kind == _EV_GARBAGE:
                f = self.faults[arg]
                n = f.params["bytes"]
                port.write(
                    _garbage(self.rng, n, _NMEA_FORBIDDEN if self.s.protocol == "nmea" else _STDBIN_FORBIDDEN)
                )
                self.counts["garbage_bytes"] += n
                self.applied.append({"kind": "garbage", "host_ns": mono(), "bytes": n})
                continue
            port.write(self._checksums(data, gps_now))
            timing.record(host, mono())
            if kind == _EV_NAV:
                self._count_epoch()
            else:
                self.counts["zda"] += 1
        # closing a pty discards what its reader has not read yet: stay plugged a moment
        pacer.wait_until(mono() + round(self.s.linger_s * NS_PER_S))
        return True

    def _count_epoch(self) -> None:
        self.counts["epochs"] += 1
        if self.port.plugged:
            self._epoch_ends.append(self.port.accepted)
        else:
            self.counts["epochs_unplugged"] += 1

    def _count_in_flight(self, lost_bytes: int) -> None:
        """The epochs an unplug cut off: those whose last byte was among the ``lost_bytes`` it
        dropped (the last written)."""
        delivered = self.port.accepted - lost_bytes
        self.counts["epochs_in_flight"] += sum(1 for end in self._epoch_ends if end > delivered)
        self._epoch_ends.clear()

    def close(self) -> None:
        self.port.close()

    def stats(self) -> dict:
        return {**self.counts, **self.port.stats, "applied": self.applied, "overruns": self.port.overruns}
