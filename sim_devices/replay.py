"""Replay of a recorded session: its raw channels re-emitted on the same transports, in time.

The session is read by the caller (``mls sim replay`` reads the MCAP segments with
``acquire``'s log reader; ``sim_devices`` does not import ``acquire``) and handed over as a
:class:`RecordedSession`: the channels with their metadata, and ``messages(topics)``, a fresh
iterator of :class:`RecordedMessage` in recording order (each replay process reads its own
channels). What goes where:

- ``/ins/raw`` → the master side of a pty behind ``<run dir>/ins`` (the exact chunks as read);
- ``/lidar/raw`` → UDP datagrams to the profiler address (one message = one datagram);
- ``/pps`` (a JSON channel: one message per pulse) → PPS1 datagrams stamped with the pulse's
  replay instant (the pulse's host stamp is ``data["host_ns"]`` when the record has it, else
  the message's host stamp);
- ``/can/<name>`` → CAN frames on the emulators' bus; each record is a SocketCAN frame
  (:func:`drivers.can.parse_can_frame`) as the daemon logs it.

Timing: a message received at host time h in the recording is emitted at
``start + (h − h₀)/speed`` (h₀ = the first message of the session). When the session's clock
model gave GPS times (``RecordedSession.gps_fit``), the replay's truth clock continues it.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

from drivers.base import DriverError
from drivers.can import open_can_bus, parse_can_frame
from drivers.pps import encode_pps_datagram
from drivers.zf.zfp1 import parse_header
from sim_devices.canbus import CanSettings, MessageBus
from sim_devices.clock import TruthClock
from sim_devices.ins import InsSettings
from sim_devices.runner import EmulatorRun, free_udp_port
from sim_devices.serialpty import PtyPort
from sim_devices.udp import UdpLink
from sim_devices.vesselconfig import write_vessel_config


@dataclass(frozen=True)
class RecordedMessage:
    topic: str
    host_ns: int  # the recording host's receive stamp (the timing to reproduce)
    payload: bytes | dict  # raw bytes, or the JSON data of /pps


@dataclass(frozen=True)
class RecordedSession:
    name: str
    channels: dict[str, dict]  # topic → channel metadata (e.g. {"protocol": "nmea"})
    counts: dict[str, int]  # messages per topic
    first_host_ns: int
    last_host_ns: int
    messages: Callable[[set[str]], Iterator[RecordedMessage]]
    gps_fit: tuple[int, float] | None = None  # (GPS ns at first_host_ns, GPS ns per host ns)

    @property
    def duration_s(self) -> float:
        return (self.last_host_ns - self.first_host_ns) / 1e9


class _Replayer:
    """One process's share of the replay: the messages of ``topics`` at their instants."""

    spin_ns = 200_000

    def __init__(self, name: str, session: RecordedSession, topics: set[str], speed: float) -> None:
        self.name = name
        self.session = session
        self.topics = topics
        self.speed = speed
        self.counts = {"messages": 0}

    def emit(self, msg: RecordedMessage, host_ns: int) -> None:
        raise NotImplementedError

    def run(self, clock, pacer, timing) -> bool:
        h0, anchor, speed = self.session.first_host_ns, clock.host_anchor_ns, self.speed
        for msg in self.session.messages(self.topics):
            host = anchor + round((msg.host_ns - h0) / speed)
            if not pacer.wait_until(host):
                return False
            self.emit(msg, host)
            timing.record(host, time.monotonic_ns())
            self.counts["messages"] += 1
        return True

    def stats(self) -> dict:
        return dict(self.counts)


class SerialReplayer(_Replayer):
    def __init__(self, session, speed, link: Path, linger_s: float = 0.5) -> None:
        super().__init__("ins", session, {"/ins/raw"}, speed)
        self.port = PtyPort(link)
        self.linger_ns = round(linger_s * 1e9)

    def run(self, clock, pacer, timing) -> bool:
        done = super().run(clock, pacer, timing)
        # closing a pty discards what its reader has not read yet: stay plugged a moment
        pacer.wait_until(time.monotonic_ns() + self.linger_ns)
        return done

    def prepare(self) -> dict:
        meta = self.session.channels.get("/ins/raw", {})
        return {"link": str(self.port.link), "pty": self.port.plug(), "protocol": meta.get("protocol")}

    def emit(self, msg, host_ns) -> None:
        self.port.write(msg.payload)

    def close(self) -> None:
        self.port.close()

    def stats(self) -> dict:
        return {**self.counts, **self.port.stats}


class UdpReplayer(_Replayer):
    def __init__(self, name: str, session, speed, topic: str, address: tuple[str, int]) -> None:
        super().__init__(name, session, {topic}, speed)
        self.address = address
        if topic == "/lidar/raw":
            self.spin_ns = 0  # thousands of datagrams per second: sleep only
        self.link: UdpLink | None = None
        self.sequence = 0

    def prepare(self) -> dict:
        self.link = UdpLink(self.address)
        return {"address": list(self.address), "protocol": "PPS1" if self.name == "pps" else "zfp1"}

    def emit(self, msg, host_ns) -> None:
        link = self.link
        assert link is not None  # opened by prepare()
        if self.name == "pps":  # re-stamp the pulse with its replay instant
            self.sequence += 1
            stamp = host_ns
            if isinstance(msg.payload, dict) and isinstance(msg.payload.get("host_ns"), int):
                stamp = host_ns + round((msg.payload["host_ns"] - msg.host_ns) / self.speed)
            link.send(encode_pps_datagram(self.sequence, stamp), 0)
        else:
            link.send(msg.payload, 0)

    def close(self) -> None:
        if self.link is not None:
            self.link.close()

    def stats(self) -> dict:
        return {**self.counts, **(self.link.stats if self.link else {})}


class CanReplayer(_Replayer):
    def __init__(self, session, speed, settings: CanSettings) -> None:
        topics = {t for t in session.channels if t.startswith("/can/")}
        super().__init__("can", session, topics, speed)
        self.settings = settings
        self.bus: MessageBus | None = None

    def prepare(self) -> dict:
        self.bus = open_can_bus(self.settings.bus_config())
        return {**self.settings.bus_config(), "channels": sorted(self.topics)}

    def emit(self, msg, host_ns) -> None:
        import can

        try:
            arbitration_id, data, extended = parse_can_frame(bytes(msg.payload))
        except DriverError:  # a damaged record in the log: counted, the replay goes on
            self.counts["bad_records"] = self.counts.get("bad_records", 0) + 1
            return
        assert self.bus is not None  # opened by prepare()
        self.bus.send(
            can.Message(
                arbitration_id=arbitration_id, data=data, is_extended_id=extended, is_fd=len(data) > 8
            )
        )

    def close(self) -> None:
        if self.bus is not None:
            self.bus.shutdown()
            self.bus = None


@dataclass
class ReplaySpec:
    run_dir: Path
    speed: float = 1.0
    profiler: tuple[str, int] = ("127.0.0.1", 0)
    pps: tuple[str, int] = ("127.0.0.1", 0)
    can: CanSettings = field(default_factory=CanSettings)
    lead_s: float = 0.25
    realtime: bool = False


class ReplayRun(EmulatorRun):
    """Re-emits a :class:`RecordedSession` (channels absent from the session are not started)."""

    def __init__(self, session: RecordedSession, spec: ReplaySpec) -> None:
        super().__init__(spec.run_dir, spec.lead_s, realtime=spec.realtime)
        if not 0 < spec.speed <= 100:
            raise ValueError(f"speed {spec.speed!r}: expected 0 < speed ≤ 100")
        self.session = session
        self.spec = spec
        host, port = spec.profiler
        self.profiler_address = (host, port or free_udp_port(host))
        host, port = spec.pps
        self.pps_address = (host, port or free_udp_port(host))

    def emulators(self) -> list:
        s, sp, ch = self.session, self.spec, self.session.channels
        out: list[_Replayer] = []
        if "/ins/raw" in ch:
            out.append(SerialReplayer(s, sp.speed, self.run_dir / "ins"))
        if "/lidar/raw" in ch:
            out.append(UdpReplayer("profiler", s, sp.speed, "/lidar/raw", self.profiler_address))
        if "/pps" in ch:
            out.append(UdpReplayer("pps", s, sp.speed, "/pps", self.pps_address))
        if any(t.startswith("/can/") for t in ch):
            out.append(CanReplayer(s, sp.speed, sp.can))
        if not out:
            raise ValueError(
                f"session {s.name}: no channel to replay (it has {', '.join(sorted(ch)) or 'none'}; "
                f"replayed: /ins/raw, /lidar/raw, /pps, /can/<name>)"
            )
        return out

    def make_clock(self) -> TruthClock:
        gps0, rate = self.session.gps_fit or (0, 1.0)
        return TruthClock.starting_in(self.lead_s, gps0, drift_ppm=(rate - 1.0) * 1e6, speed=self.spec.speed)

    def write_run_files(self) -> None:
        c, s = self.clock, self.session
        assert c is not None  # the run has started: its clock is set
        window = {
            "session": s.name,
            "duration_s": s.duration_s / self.spec.speed,
            "start_host_ns": c.host_anchor_ns,
            "end_host_ns": c.host_anchor_ns + round((s.last_host_ns - s.first_host_ns) / self.spec.speed),
        }
        if s.gps_fit is not None:
            c.write(
                self.run_dir / "truth_clock.json",
                window=window,
                source="the recorded session's clock model (log_time against host stamps)",
            )
        self._devices_json(speed=self.spec.speed, window=window, replay_of=s.name)

    def write_vessel_config(self, path: str | Path) -> Path:
        """The vessel config of this replay (after :meth:`start`); rates from the recording."""
        s, span = self.session, max(self.session.duration_s, 1e-9)
        protocol = s.channels.get("/ins/raw", {}).get("protocol") or "nmea"
        ins_rate = s.counts.get("/ins/nav", 0) / span or 100.0
        per_profile = 1
        first = next(iter(s.messages({"/lidar/raw"})), None)
        if first is not None:
            assert isinstance(first.payload, bytes)  # /lidar/raw is a raw channel
            try:
                per_profile = parse_header(first.payload)[5]
            except DriverError:
                pass
        return write_vessel_config(
            path,
            what=f"the replay of session {s.name}",
            vessel=s.name.split("_", 1)[-1] or "replay",
            run_dir=self.run_dir,
            locations=self.locations,
            speed=self.spec.speed,
            ins=InsSettings(protocol=protocol, rate_hz=min(ins_rate, 200.0)),
            profiler_rate_hz=s.counts.get("/lidar/raw", 0) / per_profile / span or 200.0,
        )

    def elapsed_s(self) -> float:
        if self.clock is None:
            return 0.0
        t = (time.monotonic_ns() - self.clock.host_anchor_ns) / 1e9
        return min(max(t, 0.0), self.session.duration_s / self.spec.speed)
