"""The daemon's devices: one class per config ``kind`` (``ins``, ``profiler``, ``pps``, ``can``),
filed in :data:`DEVICES` (the drivers' :class:`~drivers.base.Registry`), each run as one asyncio
task by :mod:`acquire.daemon.supervisor`.

A device opens its transport through the drivers' registries (:func:`drivers.transport.registry.
create_transport`, :func:`drivers.pps.create_pps_source`, :func:`drivers.can.open_can_bus`),
then loops: bytes in → the exact bytes to the session's raw channel → the sans-I/O codec →
canonical records. What it does with a record (docs/architecture.md §4, §6):

- **ins** (``nmea`` | ``stdbin``): every read to ``/ins/raw``; every epoch (a
  :class:`~drivers.hydrins.nav.NavRecord`) to ``/ins/nav`` with its GPS time — the INS time tag
  when the INS reports UTC and PPS (``time_source: device``), else the clock model's estimate
  of the receive stamp (``time_source: clock``) — fed to the latency monitor (one sample per
  epoch, with the INS PPS flag) and to the consumer taps; the time messages named by the PPS
  device (``ZDA``, ``RMC``, ``GGA``, ``TIME__``, ``validity_time``) go to the
  :class:`~acquire.timing.timekeeper.TimeKeeper` as whole GPS seconds — the INS's UTC undone
  with the GPS − UTC it announces (``$PMLS,GPSUTC``, also handed to the TimeKeeper: alarm
  ``leap_second_mismatch``) or else the leap-second table's, its dates unrolled from a GPS week
  rollover against the host's date.
- **profiler** (``zfp1``): every datagram to ``/lidar/raw`` (device time tag = the packet's
  ``t0_ns`` when it says PPS-locked and time-valid); every assembled profile to the latency
  monitor (one sample per profile: host stamp of its first packet, ``t0`` of its first point,
  the PPS flag) and to the taps.
- **pps**: every pulse to the TimeKeeper.
- **can**: every frame to ``/can/<name>`` as the 16-byte SocketCAN ``can_frame`` (72-byte
  ``canfd_frame`` for CAN FD), little-endian; event markers (id 0x6E0) to ``/events`` as
  ``pass_start`` / ``pass_end`` / ``mark`` with ``source: can:<name>``.

Connection changes of a transport (``connected`` / ``disconnected`` / ``reconnect_failed``)
are ``/events``; while a transport is not connected, :meth:`Device.connection_error` gives the OS
error of its last attempt (the supervisor's critical alarm ``device_unavailable``, from
start-up on: a port that does not exist or is already bound is never silent). Gaps (records resuming after more than the device's ``latency.gap_s``) are ``/events``.
A device never blocks on its consumers: the session writer, the status bus and the taps all
take records without waiting (bounded queues that count what they drop).
"""

from __future__ import annotations

import asyncio
import operator
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from acquire.daemon.configschema import CanTransport, DeviceConfig, NetTransport, SerialTransport
from acquire.daemon.consumers import ConsumerHub
from acquire.timing.clock import ClockModel
from acquire.timing.latency import LatencyMonitor
from acquire.timing.timekeeper import TimeKeeper
from drivers.base import Registry
from drivers.can import can_frame_bytes

if TYPE_CHECKING:  # the drivers are imported when a device of theirs is made
    from drivers.can import CanReader
    from drivers.hydrins.nmea_decode import NmeaNavAssembler
    from drivers.hydrins.nmea_sentences import Zda
    from drivers.hydrins.stdbin_decode import StdbinNavDecoder
    from drivers.pps import PpsSource
    from drivers.transport.base import Transport

NS_PER_S = 1_000_000_000
STATUS_HOLD_NS = NS_PER_S  # how long an INS status stands for epochs that lost theirs
DEVICES = Registry("devices")


@dataclass
class DaemonContext:
    """What a device needs from the daemon (all non-blocking)."""

    submit: Callable[..., Any]  # SessionWriter.submit-like (topic, payload, host_ns=, device_ns=)
    clock: ClockModel
    gps_ns: Callable[[int], int]  # the clock model's GPS ns of a host stamp (fast, cached)
    timekeeper: TimeKeeper
    monitor: LatencyMonitor
    hub: ConsumerHub
    log_event: Callable[[dict, int], None]  # (event data, host_ns) → /events, taps, status
    # (topic, payloads, host stamps, device stamps): a burst of records of one channel at once
    submit_many: Callable[[str, list, list[int], list[int | None]], Any]


def transport_config(t: SerialTransport | NetTransport, name: str, high_rate: bool = False) -> dict:
    """A vessel-config transport → the mapping :func:`drivers.transport.registry.create_transport` takes
    (``high_rate``: UDP through :mod:`drivers.transport.udp_batch`, the profiler's thousands of datagrams
    per second)."""
    if isinstance(t, SerialTransport):
        return {"kind": "serial", "port": t.port, "baudrate": t.baud, "name": name}
    if t.type == "udp":
        return {
            "kind": "udp-batch" if high_rate else "udp",
            "host": t.host,
            "port": t.port,
            "name": name,
            "max_chunks": 16384,
        }
    return {"kind": "tcp", "host": t.host, "port": t.port, "name": name}


class Device:
    """Base class: life cycle, counters, transport events and gap detection."""

    kind = ""
    channel = ""  # the raw session channel

    def __init__(self, cfg: DeviceConfig, ctx: DaemonContext) -> None:
        self.cfg = cfg
        self.name = cfg.name
        self.ctx = ctx
        self.connected = False
        self.opened = False
        self.reconnects = 0
        self.chunks = 0
        self.records = 0
        self.gaps = 0
        self.last_host_ns: int | None = None
        self.gap_ns: int | None = cfg.latency.gap_ns  # None: no gap events (sparse records)
        self._ever_connected = False

    def channel_metadata(self) -> dict[str, dict[str, str]]:
        return {}

    async def open(self) -> None:
        raise NotImplementedError

    async def run(self) -> None:
        raise NotImplementedError

    async def close(self) -> None:
        pass

    def status(self) -> dict:
        return {
            "kind": self.kind,
            "connected": self.connected,
            "chunks": self.chunks,
            "records": self.records,
            "reconnects": self.reconnects,
            "gaps": self.gaps,
        }

    def losses(self) -> int:
        """Packets/records lost so far (for the ``packet_loss`` alarm); 0 when not counted."""
        return 0

    def connection_error(self) -> str | None:
        """Why the opened device is not connected (the OS error text of the last attempt, or why
        it went away), None while it is connected or not yet tried. The supervisor's own record
        covers a device whose :meth:`open` raised."""
        return None

    # -- helpers ----------------------------------------------------------------------------

    def on_transport_event(self, ev) -> None:
        """A connection change of the transport → state, reconnect count, ``/events``."""
        if ev.kind == "connected":
            if self._ever_connected and not self.connected:
                self.reconnects += 1
            self.connected = self._ever_connected = True
        elif ev.kind == "disconnected":
            self.connected = False
        self.ctx.log_event({"event": ev.kind, "device": self.name, "detail": ev.detail}, ev.host_ns)

    def seen_many(self, host_ns: list[int]) -> None:
        """:meth:`seen` of a burst's stamps (in order)."""
        last, gap = self.last_host_ns, self.gap_ns
        if gap is not None and (
            (last is not None and host_ns[0] - last > gap)
            or max(map(operator.sub, host_ns[1:], host_ns[:-1]), default=0) > gap
        ):
            for h in host_ns:
                self.seen(h)
        else:
            self.last_host_ns = host_ns[-1]

    def seen(self, host_ns: int) -> None:
        """A record at ``host_ns``: a gap event when it ends a pause longer than ``gap_s``."""
        last = self.last_host_ns
        self.last_host_ns = host_ns
        if last is not None and self.gap_ns is not None and host_ns - last > self.gap_ns:
            self.gaps += 1
            gps = self.ctx.clock.to_gps
            a, b = gps(last), gps(host_ns)
            self.ctx.log_event(
                {
                    "event": "data_gap",
                    "device": self.name,
                    "gap_s": round((host_ns - last) / NS_PER_S, 6),
                    "last_host_ns": last,
                    "resumed_host_ns": host_ns,
                    "last_gps_ns": a.gps_ns,
                    "resumed_gps_ns": b.gps_ns,
                    "clock": b.state.value,
                },
                host_ns,
            )


class _StreamDevice(Device):
    """A device read through a byte transport (serial, UDP, TCP)."""

    high_rate = False

    def __init__(self, cfg: DeviceConfig, ctx: DaemonContext) -> None:
        super().__init__(cfg, ctx)
        self.transport: Transport | None = None

    async def open(self) -> None:
        from drivers.transport.registry import create_transport

        t = self.cfg.transport
        assert isinstance(t, (SerialTransport, NetTransport)), "the config gives it a byte transport"
        config = transport_config(t, self.name, self.high_rate)
        if config["kind"] == "udp-batch":  # kernel realtime stamps, through the daemon's host clock
            config["host_clock"] = self.ctx.timekeeper.host_clock
        transport = create_transport(config, on_event=self.on_transport_event)
        self.transport = transport
        await transport.open()
        self.opened = True

    def _opened_transport(self) -> Transport:
        """The transport :meth:`open` made (the supervisor runs a device only once it is open)."""
        assert self.transport is not None, f"{self.name}: run before open"
        return self.transport

    async def close(self) -> None:
        if self.transport is not None:
            await self.transport.close()
        self.connected = False

    def connection_error(self) -> str | None:
        t = self.transport
        return None if t is None or t.connected else t.last_error

    def status(self) -> dict:
        out = super().status()
        if self.transport is not None:
            out["transport"] = self.transport.describe()
            if (error := self.connection_error()) is not None:
                out["error"] = error
            dropped = self.transport.stats.events.get("dropped_datagrams", 0)
            if dropped:
                out["dropped_datagrams"] = dropped
        return out


@DEVICES.register("ins")
class InsDevice(_StreamDevice):
    channel = "/ins/raw"

    def __init__(self, cfg: DeviceConfig, ctx: DaemonContext, time_messages: tuple[str, ...] = ()) -> None:
        super().__init__(cfg, ctx)
        from drivers.hydrins.nmea_decode import NmeaNavAssembler
        from drivers.hydrins.nmea_sentences import Gga, Rmc, Zda
        from drivers.hydrins.stdbin_decode import StdbinNavDecoder

        self.time_messages = frozenset(time_messages)
        self._nmea: NmeaNavAssembler | None = None  # the decoder when the INS speaks NMEA
        self.decoder: StdbinNavDecoder | NmeaNavAssembler
        if cfg.protocol == "stdbin":
            self.decoder = StdbinNavDecoder()
        else:
            self.decoder = self._nmea = NmeaNavAssembler()
        # sentence types that label PPS pulses (full date: ZDA, RMC; time of day: GGA)
        self._time_types = tuple(
            t for k, t in (("ZDA", Zda), ("RMC", Rmc), ("GGA", Gga)) if k in self.time_messages
        )
        self._nav_labels = bool(self.time_messages & {"TIME__", "validity_time"})
        self.synced_records = 0
        self.last_nav: dict | None = None
        self._zda_utc_ns: int | None = None  # date of the last ZDA (dates GGA time messages)
        self._announced: int | None = None  # the GPS − UTC the INS announces
        self._status_nav = None  # the last epoch that carried the system status words

    def channel_metadata(self) -> dict[str, dict[str, str]]:
        return {"/ins/raw": {"protocol": self.cfg.protocol or "nmea", "device": self.name}}

    def status(self) -> dict:
        out = super().status()
        out.update(
            protocol=self.cfg.protocol,
            synced_records=self.synced_records,
            decoder=self.decoder.stats.as_dict(),
        )
        if self.last_nav is not None:
            out["nav"] = self.last_nav
        return out

    async def run(self) -> None:
        t, submit = self._opened_transport(), self.ctx.submit
        while True:
            chunks = await t.read_batch(256)
            self.chunks += len(chunks)
            for data, host_ns in chunks:
                submit("/ins/raw", data, host_ns=host_ns)
                for nav in self._decode(data, host_ns):
                    self._nav(nav)
            announced = getattr(self.decoder, "gps_minus_utc_s", None)  # $PMLS,GPSUTC (NMEA)
            if announced != self._announced:
                self._announced = announced
                self.ctx.timekeeper.on_gps_minus_utc(announced)

    def _decode(self, data: bytes, host_ns: int) -> list:
        nmea = self._nmea
        if not self._time_types or nmea is None:
            return self.decoder.feed(data, host_ns)
        from drivers.hydrins.nmea_sentences import Zda

        out = []
        for rec in nmea.decoder.feed(data, host_ns):
            if isinstance(rec, Zda):
                self._note_zda_date(rec)
            if isinstance(rec, self._time_types):
                gps_s = self._sentence_gps_s(rec, nmea.gps_minus_utc_s)
                if gps_s is not None and rec.host_ns is not None:
                    self.ctx.timekeeper.on_time(gps_s, rec.host_ns)
            out.extend(nmea.push(rec))
        return out

    def _note_zda_date(self, rec: Zda) -> None:
        """Keep the UTC instant of a complete ZDA (it dates the GGA time messages that follow)."""
        from drivers.hydrins.timeofday import device_date_ns

        year, month, day, tod = rec.year, rec.month, rec.day, rec.time_of_day_ns
        if year is None or month is None or day is None or tod is None:
            return
        try:
            midnight, _ = device_date_ns(year, month, day, time.time_ns())
            self._zda_utc_ns = midnight + tod
        except ValueError:
            pass

    def _sentence_gps_s(self, rec, leap: int | None) -> int | None:
        """The GPS second of a ZDA/RMC/GGA: the INS's UTC undone with the GPS − UTC it announces
        (``leap``; None: the leap-second table's), its date unrolled from a GPS week rollover."""
        from drivers.hydrins.nmea_sentences import Gga, Rmc
        from drivers.hydrins.timeofday import device_fields_to_gps_ns, resolve_gps_ns

        tod = rec.time_of_day_ns
        if tod is None:
            return None
        if isinstance(rec, Rmc) and rec.valid is False:
            return None
        try:
            if isinstance(rec, Gga):
                hint = self._zda_utc_ns if self._zda_utc_ns is not None else time.time_ns()
                return resolve_gps_ns(tod, hint, leap) // NS_PER_S
            if None in (rec.year, rec.month, rec.day):
                return None
            gps_ns, _ = device_fields_to_gps_ns(rec.year, rec.month, rec.day, tod, time.time_ns(), leap)
            return gps_ns // NS_PER_S
        except ValueError:
            return None

    def _sync_flags(self, nav, host_ns: int | None) -> tuple[bool | None, bool | None]:
        """(UTC detected, PPS detected) as the INS says. An epoch that lost its STATUS sentence
        (bytes dropped on the line) keeps the status of the last epoch that had one, up to
        :data:`STATUS_HOLD_NS` old: the INS does not leave UTC for one epoch, and timing that
        epoch by an unlocked clock model instead would misplace it in the trajectory."""
        if nav.system_status is not None:
            self._status_nav = nav
        else:
            held = self._status_nav
            if (
                held is not None
                and host_ns is not None
                and held.host_ns is not None
                and host_ns - held.host_ns <= STATUS_HOLD_NS
            ):
                nav = held
        return nav.utc_detected, nav.pps_detected

    def _nav(self, nav) -> None:
        ctx = self.ctx
        host_ns = nav.host_ns
        self.records += 1
        self.seen(host_ns)
        utc, pps = self._sync_flags(nav, host_ns)
        synced = nav.gps_ns is not None and bool(utc) and bool(pps)
        if synced:
            gps_ns, source = nav.gps_ns, "device"
            self.synced_records += 1
        else:
            gps_ns, source = ctx.gps_ns(host_ns), "clock"
        if self._nav_labels and nav.gps_ns is not None and utc:
            ctx.timekeeper.on_time(nav.gps_ns // NS_PER_S, host_ns)
        # the INS says it is on UTC: its time tags are checked against the clock even without PPS
        tag = nav.gps_ns if utc else None
        ctx.monitor.observe(self.name, host_ns, tag, pps_flag=pps)
        data = nav.to_dict()
        data["time_gps_ns"], data["time_source"] = gps_ns, source
        self.last_nav = {
            k: data[k]
            for k in (
                "lat_deg",
                "lon_deg",
                "heading_deg",
                "navigation",
                "fine_alignment",
                "gps_valid",
                "utc_detected",
                "pps_detected",
                "time_source",
            )
        }
        ctx.submit("/ins/nav", data, host_ns=host_ns, device_ns=nav.gps_ns if synced else None)
        hub = ctx.hub
        if hub.taps:
            hub.publish("nav", nav, gps_ns)


@DEVICES.register("profiler")
class ProfilerDevice(_StreamDevice):
    channel = "/lidar/raw"
    high_rate = True

    def __init__(self, cfg: DeviceConfig, ctx: DaemonContext) -> None:
        super().__init__(cfg, ctx)
        from drivers.zf.assembler import ProfileAssembler
        from drivers.zf.zfp1 import ZFP1

        codecs = {"zfp1": ZFP1}
        self.assembler = ProfileAssembler(codecs[cfg.protocol or "zfp1"])
        self.profiles_synced = 0

    def channel_metadata(self) -> dict[str, dict[str, str]]:
        return {"/lidar/raw": {"protocol": self.cfg.protocol or "zfp1", "device": self.name}}

    def losses(self) -> int:
        ev = self.assembler.stats.events
        dropped = self.transport.stats.events.get("dropped_datagrams", 0) if self.transport else 0
        return ev.get("packets_lost", 0) + ev.get("profiles_lost", 0) + dropped

    def status(self) -> dict:
        out = super().status()
        ev = self.assembler.stats.events
        out.update(
            protocol=self.cfg.protocol,
            profiles=self.records,
            profiles_synced=self.profiles_synced,
            packets_lost=ev.get("packets_lost", 0),
            profiles_lost=ev.get("profiles_lost", 0),
            rejected=dict(self.assembler.stats.rejected),
        )
        return out

    async def run(self) -> None:
        t, asm, ctx = self._opened_transport(), self.assembler, self.ctx
        monitor, hub, name = ctx.monitor, ctx.hub, self.name
        submit_many = ctx.submit_many
        while True:
            chunks = await t.read_batch(1024)  # a burst at once, with a breath between bursts
            self.chunks += len(chunks)
            datagrams = [c[0] for c in chunks]
            host_ns = [c[1] for c in chunks]
            # device time tags: each packet's t0 when PPS-locked and time-valid; the points only when wanted
            profiles, tags = asm.feed_batch(datagrams, host_ns)
            submit_many("/lidar/raw", datagrams, host_ns, tags)
            self.seen_many(host_ns)
            for prof in profiles:
                self.records += 1
                time_valid, pps, t0, prof_host_ns = prof.time_valid, prof.pps_locked, prof.t0_ns, prof.host_ns
                assert prof_host_ns is not None, "feed_batch stamps every profile with its first packet's"
                synced = pps and time_valid and t0 is not None
                t0 = t0 if time_valid else None
                if synced:
                    self.profiles_synced += 1
                monitor.observe(name, prof_host_ns, t0, pps_flag=pps)
                if hub.taps and hub.wants("profile"):
                    hub.publish("profile", prof.build(), t0 if synced else ctx.gps_ns(prof_host_ns))
            await asyncio.sleep(0)


@DEVICES.register("pps")
class PpsDevice(Device):
    def __init__(self, cfg: DeviceConfig, ctx: DaemonContext) -> None:
        super().__init__(cfg, ctx)
        self.source: PpsSource | None = None
        self.gap_ns = ctx.clock.params.loss_timeout_ns + NS_PER_S  # pulses are 1 s apart

    def _source_config(self) -> dict:
        s = self.cfg.source
        assert s is not None, "the config gives every pps device its source"
        if s.type == "kernel":
            return {
                "kind": "kernel",
                "device": s.device,
                "name": self.name,
                "host_clock": self.ctx.timekeeper.host_clock,
            }
        if s.type == "serial-line":
            return {"kind": "serial-line", "port": s.port, "line": s.line, "name": self.name}
        return {"kind": "udp", "host": s.host, "port": s.udp_port, "name": self.name}

    async def open(self) -> None:
        from drivers.pps import create_pps_source

        source = create_pps_source(self._source_config())
        self.source = source
        await source.open()
        self.opened = self.connected = True

    async def close(self) -> None:
        if self.source is not None:
            await self.source.close()
        self.connected = False

    async def run(self) -> None:
        tk, source = self.ctx.timekeeper, self.source
        assert source is not None, f"{self.name}: run before open"
        async for edge in source:
            self.records += 1
            self.seen(edge.host_ns)
            tk.on_edge(edge)

    def status(self) -> dict:
        return {**super().status(), **self.ctx.timekeeper.status()}


@DEVICES.register("can")
class CanDevice(Device):
    def __init__(self, cfg: DeviceConfig, ctx: DaemonContext) -> None:
        super().__init__(cfg, ctx)
        self.channel = f"/can/{self.name}"
        self.reader: CanReader | None = None
        self.markers = 0
        self.gap_ns = None  # event markers come when they come

    def _can_transport(self) -> CanTransport:
        t = self.cfg.transport
        assert isinstance(t, CanTransport), "the config gives every can device a CAN transport"
        return t

    def bus_config(self) -> dict:
        t = self._can_transport()
        cfg: dict[str, Any] = {"interface": t.interface, "channel": t.channel}
        if t.bitrate is not None and t.interface != "socketcan":  # SocketCAN: set by `ip link`
            cfg["bitrate"] = t.bitrate
        return cfg

    def channel_metadata(self) -> dict[str, dict[str, str]]:
        t = self._can_transport()
        return {
            self.channel: {
                "format": "socketcan_can_frame_le",
                "interface": t.interface,
                "channel": t.channel,
                "device": self.name,
                "event_marker_id": "0x6e0",
            }
        }

    async def open(self) -> None:
        from drivers.can import EVENT_MARKER_ID, CanReader, decode_event_marker, open_can_bus

        bus = open_can_bus(self.bus_config())
        reader = CanReader(bus, {EVENT_MARKER_ID: decode_event_marker}, close_bus=True)
        self.reader = reader
        await reader.__aenter__()
        self.opened = self.connected = True

    async def close(self) -> None:
        if self.reader is not None:
            await self.reader.__aexit__(None, None, None)
            self.reader = None
        self.connected = False

    async def run(self) -> None:
        from drivers.can import EventMarker

        submit, reader = self.ctx.submit, self.reader
        assert reader is not None, f"{self.name}: run before open"
        async for frame in reader:
            self.records += 1
            self.seen(frame.host_ns)
            submit(
                self.channel,
                can_frame_bytes(frame.arbitration_id, frame.data, frame.is_extended_id),
                host_ns=frame.host_ns,
            )
            m = frame.decoded
            if isinstance(m, EventMarker):
                self.markers += 1
                self.ctx.log_event(
                    {
                        "event": m.kind,
                        "pass_id": m.pass_id,
                        "sequence": m.sequence,
                        "source": f"can:{self.name}",
                    },
                    frame.host_ns,
                )

    def status(self) -> dict:
        out = {**super().status(), "markers": self.markers}
        if self.reader is not None:
            out["rejected"] = dict(self.reader.stats.rejected)
            out["dropped_frames"] = self.reader.stats.events.get("dropped_frames", 0)
        return out
