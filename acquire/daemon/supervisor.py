"""The acquisition daemon (``mls acquire``): devices, clock, monitors, session log, status bus.

:class:`Supervisor` runs one vessel config (docs/architecture.md §4, §6, §8) in one asyncio loop:

- **start-up**: check the session root (made if missing; refused when another user's or
  writable by others: :func:`acquire.status.runfiles.check_session_root`); take the daemon lock
  (:mod:`acquire.daemon.pidlock`: a second daemon on the same config is refused before it
  touches anything); salvage every unfinished session under the log directory
  (:func:`acquire.log.recover.salvage_root`); serve the status socket; seed
  the :class:`~acquire.timing.clock.ClockModel` from the system clock (UTC + leap seconds,
  flagged UNLOCKED until PPS); open the session
  (:class:`~acquire.log.sessionlog.SessionWriter`) and copy the vessel config (``vessel.yaml``),
  the site file (``site.yaml``) and a summary (``session.json``: vessel, mount, devices) into
  it (:mod:`acquire.daemon.sessionfiles`); start MQTT when configured; open every device
  (:mod:`acquire.daemon.devices`); then tell systemd ``READY=1``.
- **running**: one task per device, reopened with a back-off when it fails (alarm
  ``device_unavailable`` for a device error, ``driver_failed`` for a bug); one task per
  consumer tap (:mod:`acquire.daemon.consumers`); a 4 Hz monitor loop (latency monitor tick, PPS
  bookkeeping, clock-state alarms ``clock_holdover`` / ``clock_unlocked`` / ``time_step`` on
  ``clock`` and the time keeper's ``time_ambiguous`` / ``leap_table_stale`` /
  ``leap_second_mismatch`` / ``host_clock_step``, ``packet_loss``, ``consumer_overflow``,
  then every alarm transition to the ``alarms`` topic and ``/events`` — so an alarm reaches the
  socket, MQTT and the log within ~0.25 s of being raised); a status loop every
  ``status.period_s`` (retained ``status``, ``sensors/<name>`` and ``checklist``; ``clock`` and
  ``metrics``; the same to ``/status``, ``/clock``, ``/latency``; the ``presurvey`` section of
  the checklist; built by :mod:`acquire.daemon.reports`); the systemd watchdog, pinged only
  while no driver is down after a bug and the log writer progresses (a device that is not
  connected is a critical ``device_unavailable`` from start-up, named in ``STATUS=``, but does
  not stop the pings: a restart brings no device back). MQTT commands (when
  enabled): ``pass_start`` / ``pass_end`` / ``mark`` to ``/events`` (``source: mqtt``),
  ``rotate`` to a new segment.
- **shutdown** (SIGTERM, SIGINT or :meth:`Supervisor.request_stop`): ``STOPPING=1``, devices and
  consumers cancelled and closed, ``session_end`` logged, the segment closed (fsync), the final
  retained ``status`` (``{"state": "stopped", ...}``) published to the socket and MQTT (a clean
  MQTT disconnect: no last will), the socket removed, the lock released; every task the
  supervisor started has ended when :meth:`Supervisor.run` returns.

Nothing on the record path waits: records are stamped and batched in the loop
(:mod:`acquire.log.batch`), and the writer's queue, the MQTT queue, the socket clients' queues
and the taps are bounded and count what they drop (``log_queue_overflow``,
``consumer_overflow``).
"""

from __future__ import annotations

import asyncio
import contextlib
import datetime as _dt
import gc
import logging
import os
import signal
import time
import traceback
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from acquire.alarms import WARNING, AlarmBook
from acquire.daemon import sdnotify
from acquire.daemon.configschema import VesselConfig
from acquire.daemon.consumers import ChecklistPublisher, Consumer, ConsumerHub
from acquire.daemon.devices import DEVICES, DaemonContext, Device
from acquire.daemon.devicetasks import DRIVER_BACKOFF_S, DeviceRunner
from acquire.daemon.monitoring import LOSS_CLEAR_S as LOSS_CLEAR_S  # re-exported: the fault campaign reads it
from acquire.daemon.monitoring import MonitorAlarms
from acquire.daemon.pidlock import LockHeld, PidLock, lock_path_for
from acquire.daemon.reports import DeviceHealth, Outlets, StatusReporter
from acquire.daemon.sessionfiles import salvage_report, write_session_files
from acquire.errors import AcquireError
from acquire.log.batch import LogBatcher
from acquire.log.session import LogError
from acquire.log.sessionlog import SessionWriter
from acquire.status.bus import StatusBus, StatusServer
from acquire.status.runfiles import check_session_root
from acquire.timing.clock import ClockModel
from acquire.timing.latency import LatencyMonitor
from acquire.timing.timekeeper import SYSTEM_LEAP_SECONDS_LIST, ClockCache, TimeKeeper, coarse_gps_offset_ns
from drivers.timing import HostClock

if TYPE_CHECKING:
    from acquire.status.mqtt import MqttPublisher

log = logging.getLogger("mls.acquire")
NS_PER_S = 1_000_000_000
MONITOR_PERIOD_S = 0.25


class StartupError(AcquireError, RuntimeError):
    """The daemon cannot start (the message says what and why)."""


class Supervisor:
    """Runs one vessel config until stopped (see the module docstring)."""

    def __init__(
        self,
        config: VesselConfig,
        consumers: Sequence[Consumer] = (),
        env: dict[str, str] | None = None,
        host_clock: HostClock | None = None,
    ) -> None:
        """``host_clock``: the host's clock (default: the real one; ``mls acquire
        --sim-host-clock`` gives the simulated devices' fake), read by the time keeper, the
        clock model's seed and the transports' kernel stamps."""
        self.config = config
        self.host_clock = host_clock if host_clock is not None else HostClock()
        self.consumers = list(consumers)
        self.env = env
        self.state = "starting"
        self.stop_reason: str | None = None
        self._stop: asyncio.Event | None = None
        self._tasks: set[asyncio.Task] = set()
        self.salvaged: dict = {}
        self.lock = PidLock(lock_path_for(config.status.socket), str(config.source))
        self.stale_lock: dict | None = None  # the holder of a stale daemon lock taken over
        self._errors_seen: set[str] = set()
        self.started_mono_ns = time.monotonic_ns()
        self.started_utc = _dt.datetime.now(_dt.UTC)
        self._check_devices()
        self.clock = ClockModel(config.clock, coarse_offset_ns=coarse_gps_offset_ns(self.host_clock))
        self.alarms = AlarmBook(to_gps=self.clock.gps_ns)
        self.monitor = LatencyMonitor(self.clock, self.alarms)
        self.hub = ConsumerHub()
        self.bus = StatusBus()
        self.checklist = ChecklistPublisher(self.bus.publish)
        self.clock_cache = ClockCache(self.clock)
        self.devices: dict[str, Device] = {}  # filled below, once the devices' context exists
        self.monitor_alarms = MonitorAlarms(
            clock=self.clock,
            alarms=self.alarms,
            devices=self.devices,
            hub=self.hub,
            bus=self.bus,
            log_event=self.log_event,
        )
        self.timekeeper = TimeKeeper(
            self.clock,
            self._submit,
            self.monitor_alarms.clock_state,
            self.clock_cache.invalidate,
            alarms=self.alarms,
            leap_list=SYSTEM_LEAP_SECONDS_LIST,
            host_clock=self.host_clock,
        )
        self.ctx = DaemonContext(
            _no_writer,
            self.clock,
            self.clock_cache.gps_ns,
            self.timekeeper,
            self.monitor,
            self.hub,
            self.log_event,
            _no_writer,
        )
        self._make_devices()
        self.health = DeviceHealth(self.devices)
        self.device_runner = DeviceRunner(health=self.health, alarms=self.alarms, log_event=self.log_event)
        self.outlets = Outlets()  # opened by start(): the session, the status socket, MQTT
        self.batcher: LogBatcher | None = None  # made with the session writer
        self.watchdog: sdnotify.HealthWatchdog | None = None
        self.reports = self._make_reporter()

    def _check_devices(self) -> None:
        for kind, channel in (("ins", "/ins/raw"), ("profiler", "/lidar/raw")):
            devs = self.config.devices_of(kind)
            if len(devs) > 1:
                raise StartupError(
                    f"{self.config.source}: {len(devs)} {kind} devices "
                    f"({', '.join(d.name for d in devs)}); the session has one "
                    f"{channel} channel: configure one {kind}"
                )

    def _make_devices(self) -> None:
        """One device per configured device (an INS gets the time messages its PPS device names);
        the INS and the profiler watched by the latency monitor."""
        config = self.config
        for d in config.devices:
            extra = {}
            if d.kind == "ins":
                pps = next((p for p in config.devices_of("pps") if p.time_device == d.name), None)
                extra["time_messages"] = pps.time_messages if pps is not None else ()
            self.devices[d.name] = DEVICES[d.kind](d, self.ctx, **extra)
            if d.kind in ("ins", "profiler"):
                self.monitor.add_device(d.name, d.latency)

    def _make_reporter(self) -> StatusReporter:
        """The status documents' builder, reading this daemon's parts."""
        return StatusReporter(
            config=self.config,
            health=self.health,
            outlets=self.outlets,
            clock=self.clock,
            timekeeper=self.timekeeper,
            monitor=self.monitor,
            alarms=self.alarms,
            hub=self.hub,
            bus=self.bus,
            checklist=self.checklist,
            ctx=self.ctx,
            started_utc=self.started_utc,
            started_mono_ns=self.started_mono_ns,
        )

    @property
    def writer(self) -> SessionWriter | None:
        """The session writer (None until :meth:`start` opened the session)."""
        return self.outlets.writer

    @property
    def mqtt(self) -> MqttPublisher | None:
        """The MQTT publisher (None until :meth:`start`, and when the config has no ``mqtt``)."""
        return self.outlets.mqtt

    def drivers_health(self) -> tuple[bool, str]:
        """The watchdog's check of the device tasks (:meth:`DeviceHealth.drivers_health`)."""
        return self.health.drivers_health()

    def device_error(self, dev: Device) -> str | None:
        """Why ``dev`` is not connected, None when it is (:meth:`DeviceHealth.device_error`)."""
        return self.health.device_error(dev)

    def status_doc(self, state: str | None = None) -> dict:
        """The retained ``status`` document (``state``: the daemon's own when None)."""
        return self.reports.status_doc(state or self.state)

    def _publish_status(self) -> None:
        self.reports.publish_status(self.state)

    # -- record plumbing --------------------------------------------------------------------

    def _submit(self, topic, payload, **kw) -> bool:
        return self.ctx.submit(topic, payload, **kw)

    def log_event(self, data: dict, host_ns: int | None = None) -> None:
        """An ``/events`` entry (also to the consumer taps)."""
        host_ns = time.monotonic_ns() if host_ns is None else int(host_ns)
        self.ctx.submit("/events", data, host_ns=host_ns)
        if self.hub.taps:
            self.hub.publish("event", data, self.clock.gps_ns(host_ns))

    # -- life cycle -------------------------------------------------------------------------

    def request_stop(self, reason: str = "requested") -> None:
        if self.stop_reason is None:
            self.stop_reason = reason
        if self._stop is not None:
            self._stop.set()

    def _spawn(self, coro, name: str) -> asyncio.Task:
        task = asyncio.get_running_loop().create_task(coro, name=name)
        self._tasks.add(task)
        task.add_done_callback(self._task_done)
        return task

    def _task_done(self, task: asyncio.Task) -> None:
        self._tasks.discard(task)
        if not task.cancelled() and task.exception() is not None:
            e = task.exception()
            log.error("task %s ended: %s: %s", task.get_name(), type(e).__name__, e)

    def _guarded(self, what: str, fn, *args) -> None:
        """Run one round of a periodic job; a bug in it is logged (once per message) and the
        job goes on at its next round."""
        try:
            fn(*args)
        except Exception as e:  # noqa: BLE001 — the daemon must keep acquiring
            text = f"{what}: {type(e).__name__}: {e}"
            if text not in self._errors_seen and len(self._errors_seen) < 100:
                self._errors_seen.add(text)
                log.error("%s\n%s", text, traceback.format_exc())
                with contextlib.suppress(Exception):
                    self.log_event({"event": "internal_error", "where": what, "error": text})

    async def run(self) -> int:
        """Start, run until stopped, shut down. Returns the exit status (0: orderly stop)."""
        loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        if self.stop_reason is not None:
            self._stop.set()
        for sig in (signal.SIGTERM, signal.SIGINT):
            with contextlib.suppress(NotImplementedError, RuntimeError, ValueError):
                loop.add_signal_handler(sig, self.request_stop, signal.Signals(sig).name)
        try:
            await self.start()
            await self._stop.wait()
        finally:
            await self.shutdown()
            for sig in (signal.SIGTERM, signal.SIGINT):
                with contextlib.suppress(NotImplementedError, RuntimeError, ValueError):
                    loop.remove_signal_handler(sig)
        return 0

    async def start(self) -> None:
        """Check the session root, take the lock, salvage, serve the status socket, open the
        session, MQTT and the devices, start the tasks; then ``READY=1`` (the module docstring)."""
        self._claim_session_root()
        self.salvaged = await self._salvage()
        await self._serve_status()
        session_dir = await self._open_session()
        self._start_mqtt()
        self._log_session_start(session_dir)
        self._publish_status()
        await self._open_devices()
        self._guarded("monitor", self.monitor_step, time.monotonic_ns())  # unopened devices: alarms now
        self._spawn_tasks()
        # what start-up built (modules, config, numpy/scipy) lives as long as the daemon: out of the
        # collector's sight, a full collection takes ~1 ms instead of ~100 ms holding the GIL
        gc.collect()
        gc.freeze()
        self.state = "running"
        self._publish_status()
        sdnotify.notify(
            f"READY=1\nSTATUS=acquiring: {len(self.devices)} devices, session {session_dir.name}", self.env
        )
        log.info("acquiring: session %s", session_dir)

    def _claim_session_root(self) -> None:
        """Check the session root, then take the daemon lock (a refused daemon leaves no trace)."""
        cfg = self.config
        try:  # before the salvage opens what it finds there (made if missing: nothing else)
            check_session_root(cfg.session_dir)
        except OSError as e:
            raise StartupError(f"session directory: {e}") from None
        try:  # before anything is touched: a refused daemon leaves no trace
            self.stale_lock = self.lock.take(log)
        except (OSError, LockHeld) as e:
            raise StartupError(f"daemon lock: {e}") from None

    async def _salvage(self) -> dict:
        """The salvage report of the unfinished sessions under the session root."""
        try:
            return await asyncio.to_thread(salvage_report, self.config.session_dir)
        except (OSError, LogError) as e:  # a damaged old session must not stop acquisition
            return {"error": str(e)}

    async def _serve_status(self) -> None:
        """Serve the status socket, a sink of the status bus."""
        socket = self.config.status.socket
        server = StatusServer(socket)
        try:
            await server.start()
        except (OSError, RuntimeError) as e:
            raise StartupError(f"status socket {socket}: {e}") from None
        self.outlets.server = server
        self.bus.add_sink(server)

    async def _open_session(self) -> Path:
        """Open the session (the devices' records batched into its writer) and write the vessel
        config, site file and summary into it: its directory."""
        cfg = self.config
        metadata: dict[str, dict[str, str]] = {}
        for d in self.devices.values():
            metadata.update(d.channel_metadata())
        writer = self.outlets.writer = SessionWriter(
            cfg.session_dir,
            cfg.vessel,
            cfg.session,
            alarms=self.alarms,
            clock=self.clock,
            channel_metadata=metadata,
        )
        self.batcher = LogBatcher(writer.submit_batch, self.clock_cache)
        self.ctx.submit = self.batcher.submit  # the devices' hot path
        self.ctx.submit_many = self.batcher.submit_many
        try:
            session_dir = await asyncio.to_thread(writer.start)
        except (OSError, LogError) as e:
            raise StartupError(f"session directory {cfg.session_dir}: {e}") from None
        write_session_files(cfg, session_dir, self.started_utc)
        return session_dir

    def _start_mqtt(self) -> None:
        """The MQTT publisher, when configured: a sink of the status bus, run in its own task."""
        cfg = self.config
        if cfg.mqtt is None:
            return
        from acquire.status.mqtt import MqttPublisher

        mqtt = self.outlets.mqtt = MqttPublisher(
            cfg.mqtt, cfg.vessel, on_command=self.command, alarms=self.alarms, on_event=self.log_event
        )
        self.bus.add_sink(mqtt)
        self._spawn(mqtt.run(), "mqtt")

    def _log_session_start(self, session_dir: Path) -> None:
        self.log_event(
            {
                "event": "session_start",
                "session": session_dir.name,
                "pid": os.getpid(),
                "config": str(self.config.source),
                "devices": list(self.devices),
                "salvaged": self.salvaged,
                "stale_lock": self.stale_lock,
            }
        )

    async def _open_devices(self) -> None:
        """A first open of every device (one that fails is retried by its task)."""
        for dev in self.devices.values():
            try:
                await dev.open()
            except asyncio.CancelledError:
                raise
            except Exception as e:  # retried by the device task
                self.device_runner.failed(dev, e, "open")
                with contextlib.suppress(Exception):
                    await dev.close()

    def _spawn_tasks(self) -> None:
        """The device, consumer, monitor, status and watchdog tasks."""
        writer = self.outlets.writer
        assert writer is not None, "the session is open before the tasks start"
        for name, dev in self.devices.items():
            self.health.tasks[name] = self._spawn(self.device_runner.run(dev), f"device:{name}")
        for c in self.consumers:
            self._spawn(self._consumer_loop(c), f"consumer:{c.name}")
        self._spawn(self._monitor_loop(), "monitor")
        self._spawn(self._status_loop(), "status")
        self.watchdog = sdnotify.HealthWatchdog(
            {"drivers": self.health.drivers_health, "log": writer.health},
            env=self.env,
            advisories={"devices": self.health.devices_availability},
        )
        self._spawn(self.watchdog.run(), "watchdog")

    async def shutdown(self) -> None:
        """Stop the tasks, close the devices, the session, MQTT and the socket, release the lock."""
        if self.state in ("stopped", "stopping") or not self.lock.held:  # (refused: nothing to undo)
            self.state = "stopped"
            return
        self.state = "stopping"
        sdnotify.notify(f"STOPPING=1\nSTATUS=stopping ({self.stop_reason or 'error'})", self.env)
        with contextlib.suppress(Exception):
            self._publish_status()
        ending = [t for t in self._tasks if t.get_name().startswith(("device:", "consumer:"))]
        for t in ending:
            t.cancel()
        await asyncio.gather(*ending, return_exceptions=True)
        for dev in self.devices.values():
            with contextlib.suppress(Exception):
                await asyncio.wait_for(dev.close(), 5.0)
        helpers = [t for t in self._tasks if t.get_name() in ("monitor", "status", "watchdog")]
        for t in helpers:
            t.cancel()
        await asyncio.gather(*helpers, return_exceptions=True)
        await self._close_session()
        await self._publish_final_status()
        rest = [t for t in self._tasks if not t.done()]
        for t in rest:
            t.cancel()
        await asyncio.gather(*rest, return_exceptions=True)
        self.lock.release()  # last: the socket is gone before another daemon may start
        self.state = "stopped"
        log.info("stopped (%s)", self.stop_reason)

    async def _close_session(self) -> None:
        """``session_end`` and the last status, clock and alarms logged; the segment closed."""
        writer, batcher = self.outlets.writer, self.batcher
        if writer is None:
            return
        assert batcher is not None, "made with the writer"
        now = time.monotonic_ns()
        self.timekeeper.flush()  # log the pulses still waiting for a label
        self.monitor_alarms.drain()
        self.log_event(
            {
                "event": "session_end",
                "reason": self.stop_reason or "error",
                "records": {n: d.records for n, d in self.devices.items()},
            },
            now,
        )
        self.reports.log_status(now, self.state)
        batcher.flush()
        await asyncio.to_thread(writer.close)

    async def _publish_final_status(self) -> None:
        """The final retained ``status`` to the socket and MQTT; both closed."""
        server, mqtt = self.outlets.server, self.outlets.mqtt
        final = self.status_doc(state="stopped")
        if server is not None:
            self.bus.publish("status", final)
        if mqtt is not None:
            with contextlib.suppress(Exception):
                await mqtt.stop(final)
        if server is not None:
            await server.close()

    # -- tasks ------------------------------------------------------------------------------

    async def _consumer_loop(self, consumer: Consumer) -> None:
        kinds = getattr(consumer, "kinds", ("nav", "profile", "event"))
        backoff = DRIVER_BACKOFF_S[0]
        while True:
            tap = self.hub.subscribe(consumer.name, tuple(kinds))
            try:
                await consumer.run(tap, self.checklist)
                return
            except asyncio.CancelledError:
                raise
            except Exception as e:
                now = time.monotonic_ns()
                self.log_event(
                    {
                        "event": "consumer_failed",
                        "consumer": consumer.name,
                        "error": f"{type(e).__name__}: {e}",
                    },
                    now,
                )
                self.alarms.raise_now(
                    "consumer_failed",
                    consumer.name,
                    now,
                    severity=WARNING,
                    message=f"{consumer.name}: {type(e).__name__}: {e}; restarting",
                )
            finally:
                self.hub.unsubscribe(tap)
            await asyncio.sleep(backoff)
            backoff = min(backoff * 2, DRIVER_BACKOFF_S[1])

    async def _monitor_loop(self) -> None:
        period_ns, reports = int(MONITOR_PERIOD_S * NS_PER_S), self.reports
        due = time.monotonic_ns()
        while True:
            due += period_ns
            await asyncio.sleep(max(due - time.monotonic_ns(), 0) / NS_PER_S)
            now = time.monotonic_ns()
            reports.loop_lag_ns = max(reports.loop_lag_ns, now - due)
            if now - due > 5 * period_ns:
                due = now  # fell far behind (suspend): do not run a burst
            self._guarded("monitor", self.monitor_step, now)

    def monitor_step(self, now: int) -> None:
        """One round of the monitors (what the 4 Hz loop runs)."""
        self.monitor.tick(now)
        self.timekeeper.tick(now)
        self.health.update_alarms(self.alarms, now)
        if self.monitor_alarms.step(now):
            self._publish_status()

    async def _status_loop(self) -> None:
        period, reports = self.config.status.period_s, self.reports
        while True:
            now = time.monotonic_ns()
            self._guarded("status", self._publish_status)
            self._guarded("status details", reports.publish_details, now)
            self._guarded("status log", reports.log_status, now, self.state)
            reports.loop_lag_ns = 0
            await asyncio.sleep(period)

    # -- operator commands (MQTT) -----------------------------------------------------------

    def command(self, name: str, args: dict) -> tuple[bool, str]:
        now = time.monotonic_ns()
        if name == "rotate":
            writer = self.outlets.writer
            if writer is None:
                return False, "rotate: no session open"
            writer.rotate()
            self.log_event({"event": "rotate", "source": "mqtt"}, now)
            return True, "rotate: a new segment is being opened"
        data = {"event": name, "source": "mqtt", **args}
        self.log_event(data, now)
        what = f"pass {args['pass_id']}" if "pass_id" in args else repr(args.get("text", ""))
        return True, f"{name} {what} logged at GPS {self.clock.gps_ns(now)}"


def _no_writer(*args, **kwargs) -> bool:
    return False  # records before the session is open (none: the devices start after it)
