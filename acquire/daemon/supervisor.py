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

from acquire.alarms import CRITICAL, WARNING, AlarmBook
from acquire.daemon import sdnotify
from acquire.daemon.configschema import VesselConfig
from acquire.daemon.consumers import ChecklistPublisher, Consumer, ConsumerHub
from acquire.daemon.devices import DEVICES, DaemonContext, Device
from acquire.daemon.pidlock import LockHeld, PidLock, lock_path_for
from acquire.daemon.reports import StatusReports
from acquire.daemon.sessionfiles import salvage_report, write_session_files
from acquire.errors import AcquireError
from acquire.log.batch import LogBatcher
from acquire.log.session import LogError
from acquire.log.sessionlog import SessionWriter
from acquire.status.bus import StatusBus, StatusServer
from acquire.status.runfiles import check_session_root
from acquire.timing.clock import ClockModel, ClockState
from acquire.timing.latency import LatencyMonitor
from acquire.timing.timekeeper import SYSTEM_LEAP_SECONDS_LIST, ClockCache, TimeKeeper, coarse_gps_offset_ns
from drivers.base import DriverError

log = logging.getLogger("mls.acquire")
NS_PER_S = 1_000_000_000
MONITOR_PERIOD_S = 0.25
LOSS_CLEAR_S = 5.0  # packet_loss clears after this long without a new loss
STEP_CLEAR_S = 10.0
DRIVER_BACKOFF_S = (0.5, 30.0)


class StartupError(AcquireError, RuntimeError):
    """The daemon cannot start (the message says what and why)."""


class Supervisor(StatusReports):
    """Runs one vessel config until stopped (see the module docstring)."""

    def __init__(
        self, config: VesselConfig, consumers: Sequence[Consumer] = (), env: dict[str, str] | None = None
    ) -> None:
        self.config = config
        self.consumers = list(consumers)
        self.env = env
        self.state = "starting"
        self.stop_reason: str | None = None
        self._stop: asyncio.Event | None = None
        self._tasks: set[asyncio.Task] = set()
        self._device_tasks: dict[str, asyncio.Task] = {}
        self.crashed: dict[str, str] = {}  # device → the error while it is down after a driver bug
        self.unavailable: dict[str, str] = {}  # device → the error while it cannot be opened/read
        self.salvaged: dict = {}
        self.lock = PidLock(lock_path_for(config.status.socket), str(config.source))
        self.stale_lock: dict | None = None  # the holder of a stale daemon lock taken over
        self.started_mono_ns = time.monotonic_ns()
        self.started_utc = _dt.datetime.now(_dt.UTC)
        self.loop_lag_ns = 0
        self._check_devices()
        self.clock = ClockModel(config.clock, coarse_offset_ns=coarse_gps_offset_ns())
        self.alarms = AlarmBook(to_gps=self.clock.gps_ns)
        self.monitor = LatencyMonitor(self.clock, self.alarms)
        self.hub = ConsumerHub()
        self.clock_cache = ClockCache(self.clock)
        self.timekeeper = TimeKeeper(
            self.clock,
            self._submit,
            self._clock_state,
            self.clock_cache.invalidate,
            alarms=self.alarms,
            leap_list=SYSTEM_LEAP_SECONDS_LIST,
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
        self.devices: dict[str, Device] = {}
        for d in config.devices:
            extra = {}
            if d.kind == "ins":
                pps = next((p for p in config.devices_of("pps") if p.time_device == d.name), None)
                extra["time_messages"] = pps.time_messages if pps is not None else ()
            self.devices[d.name] = DEVICES[d.kind](d, self.ctx, **extra)
            if d.kind in ("ins", "profiler"):
                self.monitor.add_device(d.name, d.latency)
        # opened by start(): the session, the status socket, MQTT, the watchdog
        self.writer: SessionWriter | None = None
        self.batcher: LogBatcher | None = None
        self.server: StatusServer | None = None
        self.watchdog: sdnotify.HealthWatchdog | None = None
        self.bus = StatusBus()
        self.mqtt = None
        self.checklist = ChecklistPublisher(self.bus.publish)
        self._losses: dict[str, tuple[int, int]] = {}  # device → (count, host_ns of last increase)
        self._tap_drops: dict[str, int] = {}
        self._steps = 0
        self._step_ns: int | None = None
        self._was_locked = False
        self._errors_seen: set[str] = set()

    def _check_devices(self) -> None:
        for kind, channel in (("ins", "/ins/raw"), ("profiler", "/lidar/raw")):
            devs = self.config.devices_of(kind)
            if len(devs) > 1:
                raise StartupError(
                    f"{self.config.source}: {len(devs)} {kind} devices "
                    f"({', '.join(d.name for d in devs)}); the session has one "
                    f"{channel} channel: configure one {kind}"
                )

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
        cfg = self.config
        try:  # before the salvage opens what it finds there (made if missing: nothing else)
            check_session_root(cfg.session_dir)
        except OSError as e:
            raise StartupError(f"session directory: {e}") from None
        try:  # before anything is touched: a refused daemon leaves no trace
            self.stale_lock = self.lock.take(log)
        except (OSError, LockHeld) as e:
            raise StartupError(f"daemon lock: {e}") from None
        try:
            self.salvaged = await asyncio.to_thread(salvage_report, cfg.session_dir)
        except (OSError, LogError) as e:  # a damaged old session must not stop acquisition
            self.salvaged = {"error": str(e)}
        server = StatusServer(cfg.status.socket)
        try:
            await server.start()
        except (OSError, RuntimeError) as e:
            raise StartupError(f"status socket {cfg.status.socket}: {e}") from None
        self.server = server
        self.bus.add_sink(server)
        metadata: dict[str, dict[str, str]] = {}
        for d in self.devices.values():
            metadata.update(d.channel_metadata())
        self.writer = SessionWriter(
            cfg.session_dir,
            cfg.vessel,
            cfg.session,
            alarms=self.alarms,
            clock=self.clock,
            channel_metadata=metadata,
        )
        self.batcher = LogBatcher(self.writer.submit_batch, self.clock_cache)
        self.ctx.submit = self.batcher.submit  # the devices' hot path
        self.ctx.submit_many = self.batcher.submit_many
        try:
            session_dir = await asyncio.to_thread(self.writer.start)
        except (OSError, LogError) as e:
            raise StartupError(f"session directory {cfg.session_dir}: {e}") from None
        write_session_files(cfg, session_dir, self.started_utc)
        if cfg.mqtt is not None:
            from acquire.status.mqtt import MqttPublisher

            self.mqtt = MqttPublisher(
                cfg.mqtt, cfg.vessel, on_command=self.command, alarms=self.alarms, on_event=self.log_event
            )
            self.bus.add_sink(self.mqtt)
            self._spawn(self.mqtt.run(), "mqtt")
        self.log_event(
            {
                "event": "session_start",
                "session": session_dir.name,
                "pid": os.getpid(),
                "config": str(cfg.source),
                "devices": list(self.devices),
                "salvaged": self.salvaged,
                "stale_lock": self.stale_lock,
            }
        )
        self._publish_status()
        for dev in self.devices.values():
            try:
                await dev.open()
            except asyncio.CancelledError:
                raise
            except Exception as e:  # retried by the device task
                self._device_failed(dev, e, "open")
                with contextlib.suppress(Exception):
                    await dev.close()
        self._guarded("monitor", self.monitor_step, time.monotonic_ns())  # unopened devices: alarms now
        for name, dev in self.devices.items():
            self._device_tasks[name] = self._spawn(self._device_loop(dev), f"device:{name}")
        for c in self.consumers:
            self._spawn(self._consumer_loop(c), f"consumer:{c.name}")
        self._spawn(self._monitor_loop(), "monitor")
        self._spawn(self._status_loop(), "status")
        self.watchdog = sdnotify.HealthWatchdog(
            {"drivers": self.drivers_health, "log": self.writer.health},
            env=self.env,
            advisories={"devices": self.devices_availability},
        )
        self._spawn(self.watchdog.run(), "watchdog")
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

    async def shutdown(self) -> None:
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
        if self.writer is not None:
            now = time.monotonic_ns()
            self.timekeeper.flush()  # log the pulses still waiting for a label
            self._drain_alarms()
            self.log_event(
                {
                    "event": "session_end",
                    "reason": self.stop_reason or "error",
                    "records": {n: d.records for n, d in self.devices.items()},
                },
                now,
            )
            self._log_status(now)
            self.batcher.flush()
            await asyncio.to_thread(self.writer.close)
        final = self.status_doc(state="stopped")
        if self.server is not None:
            self.bus.publish("status", final)
        if self.mqtt is not None:
            with contextlib.suppress(Exception):
                await self.mqtt.stop(final)
        if self.server is not None:
            await self.server.close()
        rest = [t for t in self._tasks if not t.done()]
        for t in rest:
            t.cancel()
        await asyncio.gather(*rest, return_exceptions=True)
        self.lock.release()  # last: the socket is gone before another daemon may start
        self.state = "stopped"
        log.info("stopped (%s)", self.stop_reason)

    # -- tasks ------------------------------------------------------------------------------

    async def _device_loop(self, dev: Device) -> None:
        """Open and run a device for ever; after a failure close it, wait (doubling back-off)
        and open it again. A device error (:class:`~drivers.base.DriverError`, ``OSError``: the
        device is absent or went away) makes it *unavailable* (alarm ``device_unavailable``);
        anything else is a bug in a driver (alarm ``driver_failed``), which also withholds the
        systemd watchdog until the device runs again."""
        backoff = DRIVER_BACKOFF_S[0]
        while True:
            try:
                if not dev.opened:
                    await dev.open()
                self.crashed.pop(dev.name, None)
                self.unavailable.pop(dev.name, None)
                now = time.monotonic_ns()
                if self.alarms.is_active("driver_failed", dev.name):
                    self.alarms.clear_now("driver_failed", dev.name, now, message=f"{dev.name} running again")
                self.update_device_alarms(now)  # cleared once its transport is connected
                await dev.run()
                raise EOFError(f"{dev.name}: the device stream ended")
            except asyncio.CancelledError:
                raise
            except Exception as e:
                self._device_failed(dev, e, "open" if not dev.opened else "run")
                with contextlib.suppress(Exception):
                    await dev.close()
                dev.opened = False
                await asyncio.sleep(backoff)
                backoff = min(backoff * 2, DRIVER_BACKOFF_S[1])

    def _device_failed(self, dev: Device, e: BaseException, when: str) -> None:
        text = f"{type(e).__name__}: {e}"
        now = time.monotonic_ns()
        if isinstance(e, (DriverError, OSError, EOFError)):
            self.unavailable[dev.name] = text
            name, what = "device_unavailable", "not connected"
        else:
            self.crashed[dev.name] = text
            name, what = "driver_failed", "driver failed"
        message = f"{dev.name} ({dev.kind}) {what}: {text}; retrying"
        self.alarms.raise_now(name, dev.name, now, severity=CRITICAL, message=message)
        self.log_event(
            {
                "event": name,
                "device": dev.name,
                "when": when,
                "error": text,
                "traceback": traceback.format_exception(e)[-3:],
            },
            now,
        )
        log.error("device %s: %s (%s): %s", dev.name, what, when, text)

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
        period_ns = int(MONITOR_PERIOD_S * NS_PER_S)
        due = time.monotonic_ns()
        while True:
            due += period_ns
            await asyncio.sleep(max(due - time.monotonic_ns(), 0) / NS_PER_S)
            now = time.monotonic_ns()
            self.loop_lag_ns = max(self.loop_lag_ns, now - due)
            if now - due > 5 * period_ns:
                due = now  # fell far behind (suspend): do not run a burst
            self._guarded("monitor", self.monitor_step, now)

    def monitor_step(self, now: int) -> None:
        """One round of the monitors (what the 4 Hz loop runs)."""
        self.monitor.tick(now)
        self.timekeeper.tick(now)
        self.update_device_alarms(now)
        al = self.alarms
        if self.clock.steps > self._steps:
            self._steps, self._step_ns = self.clock.steps, now
            al.raise_now(
                "time_step",
                "clock",
                now,
                severity=CRITICAL,
                message=f"PPS labels stepped: the clock model restarted ({self.clock.steps} steps so far)",
            )
        elif self._step_ns is not None and now - self._step_ns > STEP_CLEAR_S * NS_PER_S:
            self._step_ns = None
            al.clear_now("time_step", "clock", now, message="clock model steady since the step")
        for name, dev in self.devices.items():
            lost = dev.losses()
            count, since = self._losses.get(name, (0, 0))
            if lost > count:
                self._losses[name] = (lost, now)
                al.raise_now(
                    "packet_loss",
                    name,
                    now,
                    severity=WARNING,
                    message=f"{lost - count} packets lost (total {lost})",
                )
            elif al.is_active("packet_loss", name) and now - since > LOSS_CLEAR_S * NS_PER_S:
                al.clear_now(
                    "packet_loss", name, now, message=f"no loss for {LOSS_CLEAR_S:g} s (total {lost})"
                )
        for tap in self.hub.taps:
            before = self._tap_drops.get(tap.name, 0)
            self._tap_drops[tap.name] = tap.dropped
            al.update(
                "consumer_overflow",
                tap.name,
                tap.dropped > before,
                now,
                severity=WARNING,
                message=f"{tap.name} does not keep up: {tap.dropped} records dropped",
                clear_after_ns=int(LOSS_CLEAR_S * NS_PER_S),
            )
        if self._drain_alarms():
            self._publish_status()

    def _clock_state(self, old: ClockState, new: ClockState, now: int) -> None:
        st = self.clock.status(now)
        bound = st.as_dict()["error_bound_us"]
        self.log_event(
            {
                "event": "clock_state",
                "from": old.value,
                "to": new.value,
                "error_bound_us": bound,
                "edges_in_window": st.edges_in_window,
            },
            now,
        )
        al = self.alarms
        if new == ClockState.LOCKED:
            self._was_locked = True
            al.clear_now("clock_holdover", "clock", now, message="PPS back: LOCKED")
            al.clear_now("clock_unlocked", "clock", now, message="PPS back: LOCKED")
        elif new == ClockState.HOLDOVER:
            al.raise_now(
                "clock_holdover",
                "clock",
                now,
                severity=WARNING,
                message=f"no PPS for {st.as_dict()['last_edge_age_s']} s: holding over, "
                f"error bound {bound} µs",
            )
        elif self._was_locked:
            al.clear_now("clock_holdover", "clock", now)
            al.raise_now(
                "clock_unlocked",
                "clock",
                now,
                severity=CRITICAL,
                message="clock UNLOCKED: holdover bound exceeded or PPS labels lost; "
                "GPS times come from the devices' tags or the system clock",
            )

    def _drain_alarms(self) -> bool:
        events = self.alarms.drain()
        for ev in events:
            d = ev.as_dict()
            self.bus.publish("alarms", d)
            self.log_event({"event": "alarm", **d}, ev.alarm.last_host_ns)
            log.warning("alarm %s %s/%s: %s", ev.action, ev.alarm.name, ev.alarm.device, ev.alarm.message)
        return bool(events)

    async def _status_loop(self) -> None:
        period = self.config.status.period_s
        while True:
            now = time.monotonic_ns()
            self._guarded("status", self._publish_status)
            self._guarded("status details", self._publish_details, now)
            self._guarded("status log", self._log_status, now)
            self.loop_lag_ns = 0
            await asyncio.sleep(period)

    # -- operator commands (MQTT) -----------------------------------------------------------

    def command(self, name: str, args: dict) -> tuple[bool, str]:
        now = time.monotonic_ns()
        if name == "rotate":
            if self.writer is None:
                return False, "rotate: no session open"
            self.writer.rotate()
            self.log_event({"event": "rotate", "source": "mqtt"}, now)
            return True, "rotate: a new segment is being opened"
        data = {"event": name, "source": "mqtt", **args}
        self.log_event(data, now)
        what = f"pass {args['pass_id']}" if "pass_id" in args else repr(args.get("text", ""))
        return True, f"{name} {what} logged at GPS {self.clock.gps_ns(now)}"


def _no_writer(*args, **kwargs) -> bool:
    return False  # records before the session is open (none: the devices start after it)
