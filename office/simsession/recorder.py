"""The daemon's side of ``mls sim session`` (:mod:`office.simsession.record`): the emulators' output put
through the daemon's own devices, time keeper, monitors and session writer, in host-time order,
on the caller's thread and the simulated host clock.

:class:`Recorder` builds the daemon's pieces as :class:`acquire.daemon.supervisor.Supervisor`
does (one :class:`~acquire.daemon.devices.DaemonContext`, the devices of the vessel config from
:data:`~acquire.daemon.devices.DEVICES`, a :class:`~acquire.timing.clock.ClockModel` fed by a
:class:`~acquire.timing.timekeeper.TimeKeeper`, a :class:`~acquire.timing.latency.LatencyMonitor`,
one :class:`~acquire.alarms.AlarmBook`) and plays the session's timeline into them: INS writes
(``InsDevice``'s read loop: ``/ins/raw``, its decoder, ``/ins/nav``), PPS pulses, CAN marks
(``CanDevice``'s loop: ``/can/<name>``, ``/events``), the profiler's datagrams (``/lidar/raw``, one
latency sample per profile), the 4 Hz monitor step (alarms to ``/events``) and the status period
(``/clock``, ``/latency``). Records are stamped with the truth clock (``log_time`` = GPS time of the
host stamp, LOCKED) and handed to :class:`OfflineSessionWriter` a few thousand at a time.
"""

from __future__ import annotations

import json
import os
import queue
from itertools import repeat
from pathlib import Path
from typing import Any

import numpy as np

from acquire.daemon.reports import clock_doc
from acquire.log.sessionlog import SessionWriter

NS_PER_S = 1_000_000_000
LOCKED = "LOCKED"
CHANNEL_FLUSH = 4096  # records handed to the writer at once
PRIMING_PULSES = 8  # PPS pulses the clock model has before the session (it is LOCKED from the start)
MONITOR_PERIOD_NS = 250_000_000  # the supervisor's monitor step
_INS, _PPS, _CAN, _TICK, _STATUS = range(5)


class OfflineSessionWriter(SessionWriter):
    """The daemon's session writer with its writer loop on the caller's thread: :meth:`pump` does
    what the writer thread does with what is queued (``_write_all``, then ``_maintain``: chunk
    flush, fsync, disk check, rotation), at once; time is the ``monotonic_ns`` given (the
    simulated host clock), so flushes, fsyncs and rotations follow session time."""

    def _run(self) -> None:  # start() starts a thread that ends at once: pump() does its work
        return

    def pump(self, maintain: bool = True) -> None:
        """Write what is queued, then (``maintain``) flush, fsync, check the disk, rotate."""
        while True:
            try:
                item = self._queue.get_nowait()
            except queue.Empty:
                break
            if isinstance(item, list):
                with self._seq_lock:
                    self._queued -= len(item)
                self._write_all(item)
        if maintain:
            self._maintain(self._now())

    def finish(self) -> None:
        """Write what is queued, close the segment (``shutdown``: summary, footer, fsync) and
        release the session lock, as the writer thread does at ``close()``."""
        self.pump(maintain=False)
        self._close_segment(self._now(), "shutdown")
        self._stats.state = "closed"
        self.close()


class _Collect:
    """Stands for an emulator's link, bus and pacer: keeps what is sent, never waits."""

    def __init__(self) -> None:
        self.sent: list = []
        self.stats: dict[str, int] = {}

    def send(self, item: Any, *_: Any) -> None:
        self.sent.append(item)

    def close(self) -> None:
        pass

    def shutdown(self) -> None:
        pass

    def wait_until(self, _host_ns: int) -> bool:
        return True

    def record(self, *_) -> None:
        pass


class Recorder:
    """One session: the daemon's pieces, the emulators' timelines, the writer (module docstring)."""

    def __init__(self, cfg, clock, spec, sim, lidar, marks, t0_ns: int, t_end_ns: int) -> None:
        from acquire.alarms import AlarmBook
        from acquire.daemon.consumers import ConsumerHub
        from acquire.daemon.devices import DEVICES, DaemonContext
        from acquire.timing.clock import ClockModel
        from acquire.timing.latency import LatencyMonitor
        from acquire.timing.timekeeper import TimeKeeper

        self.cfg, self.clock, self.spec, self.sim, self.lidar = cfg, clock, spec, sim, lidar
        self.t0_ns, self.t_end_ns = t0_ns, t_end_ns
        self.now = clock.host_ns(t0_ns)  # the simulated host clock: the latest record's stamp
        self.h_end = clock.host_ns(t_end_ns)
        self.pending: list[tuple] = []
        self.done = False
        self.writer: OfflineSessionWriter | None = None
        self.session_dir: Path | None = None
        cm = self.clock_model = ClockModel(cfg.clock, coarse_offset_ns=t0_ns - self.now)
        second = t0_ns // NS_PER_S
        for s in range(second - PRIMING_PULSES, second):
            cm.add_edge(clock.host_ns(s * NS_PER_S), s)
        self.alarms = AlarmBook(to_gps=cm.gps_ns)
        self.monitor = LatencyMonitor(cm, self.alarms)
        # the simulated host's system clock is disciplined: its view of GPS time is the truth clock's
        self.timekeeper = TimeKeeper(
            cm, self._submit, alarms=self.alarms, host_gps_offset_ns=lambda: clock.gps_ns(self.now) - self.now
        )
        self.ctx = DaemonContext(
            self._submit,
            cm,
            self._gps_ns,
            self.timekeeper,
            self.monitor,
            ConsumerHub(),
            self._log_event,
            self._submit_many,
        )
        self.devices = {}
        for d in cfg.devices:  # as the supervisor builds them
            extra = {}
            if d.kind == "ins":
                pps = next((p for p in cfg.devices_of("pps") if p.time_device == d.name), None)
                extra["time_messages"] = pps.time_messages if pps is not None else ()
            self.devices[d.name] = DEVICES[d.kind](d, self.ctx, **extra)
            if d.kind in ("ins", "profiler"):
                self.monitor.add_device(d.name, d.latency)
        self.ins = next(d for d in self.devices.values() if d.kind == "ins")
        self.ins.decoder.utc_clock = self._utc_now_ns  # the simulated host's UTC dates the tags
        self.profiler = next(d for d in self.devices.values() if d.kind == "profiler")
        self.pps = next(d for d in self.devices.values() if d.kind == "pps")
        self.can = next(d for d in self.devices.values() if d.kind == "can")
        self._timeline(marks)

    # -- the emulators' timelines -----------------------------------------------------------

    def _timeline(self, marks) -> None:
        from drivers.pps import decode_pps_datagram
        from sim_devices.canbus import CanEmulator, CanSettings
        from sim_devices.feed import ins_track
        from sim_devices.ins import InsEmulator, InsSettings
        from sim_devices.pps import PpsEmulator, PpsSettings

        spec, clock, t0, t1 = self.spec, self.clock, self.t0_ns, self.t_end_ns
        track = ins_track(self.sim, t0, t1, spec.ins_rate_hz)
        settings = InsSettings(protocol=spec.ins_protocol, rate_hz=spec.ins_rate_hz)
        self.ins_emu = InsEmulator(track, settings, [], t0, t1, Path(os.devnull), seed=spec.seed)
        self.ins_host, self.ins_kind, self.ins_arg = self.ins_emu.schedule(clock)
        pps = PpsEmulator(PpsSettings(), [], t0, t1, seed=spec.seed)
        pps.link = link = _Collect()
        pps.run(clock, link, link)  # the emulator's own pulses and stamp jitter
        self.pps_edges = [decode_pps_datagram(d, self.pps.name) for d in link.sent]
        can = CanEmulator(marks, CanSettings())
        can.bus = bus = _Collect()
        can.run(clock, bus, bus)
        self.can_msgs = bus.sent
        self.can_host = [clock.host_ns(m.gps_ns) for m in marks]
        h0, h1 = clock.host_ns(t0), clock.host_ns(t1)
        ticks = np.arange(h0, h1, MONITOR_PERIOD_NS, dtype=np.int64)
        status = np.arange(h0, h1, round(self.cfg.status.period_s * NS_PER_S), dtype=np.int64)
        parts = [
            (self.ins_host, _INS),
            (np.array([e.host_ns for e in self.pps_edges], np.int64), _PPS),
            (np.array(self.can_host, np.int64), _CAN),
            (ticks, _TICK),
            (status, _STATUS),
        ]
        hosts = np.concatenate([h for h, _ in parts])
        codes = np.concatenate([np.full(h.size, c) for h, c in parts])
        args = np.concatenate([np.arange(h.size) for h, _ in parts])
        order = np.lexsort((codes, hosts))
        self.ev_host, self.ev_code, self.ev_arg = hosts[order], codes[order].tolist(), args[order].tolist()
        self.ev = 0

    # -- record plumbing --------------------------------------------------------------------

    def _gps_ns(self, host_ns: int) -> int:
        return self.clock.gps_ns(host_ns)

    def _utc_now_ns(self) -> int:
        """The simulated host's ``time.time_ns()``: UTC ns since the Unix epoch."""
        from calib.core.frames import leap_seconds_at_gps_ns
        from calib.core.gpstime import GPS_EPOCH_UNIX_S

        gps = self.clock.gps_ns(self.now)
        return gps + (GPS_EPOCH_UNIX_S - leap_seconds_at_gps_ns(gps)) * NS_PER_S

    def _submit(self, topic, payload, *, host_ns, device_ns=None, **_) -> bool:
        self.pending.append((topic, payload, host_ns, device_ns, self.clock.gps_ns(host_ns), LOCKED))
        return True

    def _submit_many(self, topic, payloads, host_ns, device_ns) -> None:
        for p, h, d in zip(payloads, host_ns, device_ns, strict=True):
            self._submit(topic, p, host_ns=h, device_ns=d)

    def _log_event(self, data: dict, host_ns: int | None = None) -> None:
        self._submit("/events", data, host_ns=self.now if host_ns is None else int(host_ns))

    def _flush(self) -> None:
        if not self.pending:
            return
        writer = self.writer
        assert writer is not None  # records flow once the session is open
        batch, self.pending = self.pending, []
        self.now = max(self.now, int(batch[-1][2]))
        if writer.submit_batch(batch) != len(batch):  # pumped after each batch: never full
            raise RuntimeError("the session writer's queue overflowed")
        # what comes at or after the session's end is the shutdown's: no rotation into an
        # empty last segment when the session lasts a whole number of rotation periods
        writer.pump(maintain=self.now < self.h_end)

    # -- the session ------------------------------------------------------------------------

    def open(self, simulation: dict) -> Path:
        """Create the session (the daemon's start-up: writer, session files, ``session_start``)."""
        from acquire.daemon.sessionfiles import write_session_files
        from calib.core.frames import gps_ns_to_utc

        cfg = self.cfg
        metadata: dict[str, dict[str, str]] = {}
        for d in self.devices.values():
            metadata.update(d.channel_metadata())
        started = gps_ns_to_utc(self.t0_ns)
        self.writer = OfflineSessionWriter(
            cfg.session_dir,
            cfg.vessel,
            cfg.session,
            alarms=self.alarms,
            channel_metadata=metadata,
            start_utc=started,
            monotonic_ns=lambda: self.now,
        )
        d = self.session_dir = self.writer.start()
        write_session_files(cfg, d, started)
        self.update_summary(
            {
                "config_file": str(d / "vessel.yaml"),
                "site_file": str(d / "site.yaml"),
                "simulation": simulation,
            }
        )
        self._log_event(
            {
                "event": "session_start",
                "session": d.name,
                "pid": os.getpid(),
                "config": str(d / "vessel.yaml"),
                "devices": list(self.devices),
                "salvaged": {},
                "stale_lock": None,
            }
        )
        self._log_event({"event": "simulated_session", **simulation})
        return d

    def update_summary(self, extra: dict) -> None:
        """``session.json`` with ``extra`` keys (written atomically, as the daemon writes it)."""
        assert self.session_dir is not None  # the session was opened
        path = self.session_dir / "session.json"
        doc = {**json.loads(path.read_text(encoding="utf-8")), **extra}
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")
        tmp.replace(path)

    def record(self, progress=None) -> None:
        """Every chunk of the profiler with the events of its time, then the events left."""
        lidar = self.lidar
        total_s = (self.t_end_ns - self.t0_ns) / NS_PER_S
        for dg in lidar.chunks():
            hosts, i = dg.host_ns, 0
            last = int(hosts[-1])
            while self.ev < len(self.ev_code) and int(self.ev_host[self.ev]) <= last:
                j = int(np.searchsorted(hosts, self.ev_host[self.ev], side="right"))
                self._lidar(dg, i, j)
                i = j
                self._event()
            self._lidar(dg, i, len(dg))
            self._flush()
            if progress is not None:
                done_s = (self.clock.gps_ns(last) - self.t0_ns) / NS_PER_S
                progress(min(done_s, total_s), total_s, lidar.counts.returns)
        while self.ev < len(self.ev_code):
            self._event()
        self._flush()
        self.done = True

    def _lidar(self, dg, i: int, j: int) -> None:
        """Datagrams ``i:j`` of a chunk: ``/lidar/raw``, and the latency sample of each profile
        whose first packet is among them (the profiler device's loop)."""
        if j <= i:
            return
        hosts = dg.host_ns[i:j]
        self.now = max(self.now, int(hosts[-1]))
        logs = self.clock.gps_ns_array(hosts)
        h = hosts.tolist()
        self.pending.extend(
            zip(
                repeat("/lidar/raw"),
                dg.payloads[i:j],
                h,
                dg.t0_ns[i:j].tolist(),
                logs.tolist(),
                repeat(LOCKED),
            )
        )
        dev = self.profiler
        dev.chunks += 1
        dev.seen_many(h)
        a, b = np.searchsorted(dg.first_packet, [i, j])
        observe, name = self.monitor.observe, dev.name
        for ph, pt in zip(dg.profile_host_ns[a:b].tolist(), dg.profile_t0_ns[a:b].tolist(), strict=True):
            observe(name, ph, pt, pps_flag=True)
        dev.records += int(b - a)
        if len(self.pending) >= CHANNEL_FLUSH:
            self._flush()

    def _event(self) -> None:
        k = self.ev
        self.ev += 1
        code, arg = self.ev_code[k], self.ev_arg[k]
        host = int(self.ev_host[k])
        self.now = max(self.now, host)
        if code == _INS:
            self._ins(host, int(self.ins_kind[arg]), int(self.ins_arg[arg]))
        elif code == _PPS:
            edge = self.pps_edges[arg]
            self.pps.records += 1
            self.pps.seen(edge.host_ns)
            self.timekeeper.on_edge(edge)
        elif code == _CAN:
            self._can(host, self.can_msgs[arg])
        elif code == _TICK:  # the supervisor's monitor step (the daemon's own alarms only)
            self.monitor.tick(host)
            self.timekeeper.tick(host)
            self._drain_alarms()
        else:
            self._status(host)

    def _ins(self, host: int, kind: int, arg: int) -> None:
        """One write of the INS emulator through the INS device's read loop."""
        from sim_devices.ins import _EV_NAV

        emu, dev = self.ins_emu, self.ins
        data = emu.nav_bytes(arg) if kind == _EV_NAV else emu.zda_bytes(arg)
        dev.chunks += 1
        self._submit("/ins/raw", data, host_ns=host)
        for nav in dev._decode(data, host):
            dev._nav(nav)
        announced = getattr(dev.decoder, "gps_minus_utc_s", None)  # $PMLS,GPSUTC (NMEA)
        if announced != dev._announced:
            dev._announced = announced
            self.timekeeper.on_gps_minus_utc(announced)

    def _can(self, host: int, msg) -> None:
        """One frame through the CAN device's loop: ``/can/<name>``, the marker to ``/events``."""
        from drivers.can import CanFrame, can_frame_bytes, decode_event_marker

        dev = self.can
        dev.records += 1
        dev.seen(host)
        data = bytes(msg.data)
        self._submit(dev.channel, can_frame_bytes(msg.arbitration_id, data, msg.is_extended_id), host_ns=host)
        m = decode_event_marker(CanFrame(msg.arbitration_id, data, host, host / NS_PER_S, msg.is_extended_id))
        dev.markers += 1
        self._log_event(
            {"event": m.kind, "pass_id": m.pass_id, "sequence": m.sequence, "source": f"can:{dev.name}"}, host
        )

    def _drain_alarms(self) -> None:
        for ev in self.alarms.drain():
            self._log_event({"event": "alarm", **ev.as_dict()}, ev.alarm.last_host_ns)

    def _status(self, host: int) -> None:
        self._submit("/clock", clock_doc(self.clock_model, self.timekeeper, host), host_ns=host)
        self._submit("/latency", self.monitor.snapshot(), host_ns=host)

    def close(self, reason: str) -> None:
        """The daemon's shutdown: pending pulses, alarms, ``session_end``, status, segment closed."""
        if self.writer is None:
            return
        if self.done:  # stopped at the session's end (else where it was interrupted)
            self.now = max(self.now, self.h_end)
        now = self.now
        self.timekeeper.flush()
        self._drain_alarms()
        self._log_event(
            {
                "event": "session_end",
                "reason": reason,
                "records": {n: d.records for n, d in self.devices.items()},
            },
            now,
        )
        self._status(now)
        self._flush()
        self.writer.finish()
