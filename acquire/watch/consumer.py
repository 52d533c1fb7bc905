"""The mount watch as a consumer of the daemon's record stream (the
:mod:`acquire.daemon.consumers` protocol): the live counterpart of
:func:`calib.watch.runner.run_watch`.

- ``nav`` records go to the :class:`~acquire.watch.lines.LineCutter` (lines by heading, or by
  the pass marks once the session has one) and to the :class:`~acquire.watch.buffers.NavBuffer`;
  ``profile`` records to the :class:`~acquire.watch.buffers.PointBuffer` (decimated) while a
  line is open; ``event`` records' ``pass_start`` / ``pass_end`` to the line cutter. Records
  that are not what they should be are counted and ignored.
- A closed line's heading (relative to the wall) goes to a
  :class:`~calib.watch.runner.BlockCutter`, which closes a block with the lines before it (each
  line is in up to two blocks; a line that leaves the cutter's window without a partner of
  another heading is dropped and counted). When a block closes, its data (snapshots of the
  buffers) and its family are queued and :func:`~acquire.watch.blockjob.run_block` runs in the
  worker process (:class:`~acquire.watch.solver.BlockSolver`: never the event loop's), one block
  at a time; at most :data:`MAX_WAITING_BLOCKS` wait behind it (more: the oldest is
  skipped, counted, and the state says the watch is behind). The buffers keep nothing older than
  the oldest line the cutter may still take.
- Each block's estimate goes to the :class:`~calib.watch.sequential.MountTest`; the state is
  published on the retained status topic ``mount`` and as the ``mount`` section of the
  ``checklist`` topic (a one-line verdict), and the block is logged on ``/events``
  (``mount_watch_block``). When the test crosses its threshold the critical alarm
  ``mount_shift`` (device ``mount``) is raised with :meth:`~calib.watch.sequential.MountAlarm.message`
  and stays raised for the rest of the session: the mount needs a new calibration.
"""

from __future__ import annotations

import asyncio
import math
import time
from collections import deque
from collections.abc import Callable

from acquire.alarms import CRITICAL, MOUNT_SHIFT, AlarmBook
from acquire.watch.blockjob import BlockJob, WatchModel
from acquire.watch.buffers import NavBuffer, PointBuffer
from acquire.watch.lines import Line, LineCutter
from acquire.watch.report import block_summary, checklist_section
from acquire.watch.solver import BlockSolver
from calib.core import frames
from calib.watch.block import BlockEstimate
from calib.watch.report import verdict
from calib.watch.runner import BlockCutter
from calib.watch.sequential import MountTest, WatchDesign

SCHEMA = "mls.mount/1"
MAX_WAITING_BLOCKS = 2  # closed blocks waiting for the worker
NAV_KEEP_S = 2.0  # navigation kept before the oldest line still needed
TRIM_EVERY = 200  # INS epochs between trims of the buffers


class MountWatchConsumer:
    """The live mount watch (module docstring). ``publish(topic, data)``: the status bus;
    ``alarms``: the daemon's alarm book; ``log_event(data)``: ``/events``; ``info``: what the
    ``mount`` topic says of the calibration (path, boresight)."""

    name = "mount_watch"
    kinds = ("nav", "profile", "event")

    def __init__(
        self,
        model: WatchModel,
        design: WatchDesign | None = None,
        *,
        max_points_per_s: float = 20_000,
        min_line_s: float = 20.0,
        max_line_s: float = 900.0,
        max_points: int = 4_000_000,
        publish: Callable[[str, dict], None] | None = None,
        alarms: AlarmBook | None = None,
        log_event: Callable[[dict], None] | None = None,
        info: dict | None = None,
    ) -> None:
        self.model = model
        self.design = design = design if design is not None else WatchDesign()
        self.test = MountTest(design)
        self.cutter = LineCutter(min_line_s, max_line_s)
        self.blocks = BlockCutter(model.options)
        self.nav = NavBuffer()
        o = model.options
        self.points = PointBuffer(max_points_per_s, o.min_range_m, o.max_range_m, max_points)
        f = model.frame  # its first conversion sets pyproj up (~0.1 s): now, not in the loop later
        f.to_lgf([f.lat_deg], [f.lon_deg], [f.height_m])
        self._publish = publish
        self.alarms = alarms
        self.log_event = log_event
        self.info = dict(info or {})
        self.lines: dict[int, Line] = {}  # closed lines a later block may still take
        self.last_lines: deque[Line] = deque(maxlen=4)
        self.waiting: deque[BlockJob] = deque()
        self.running: BlockJob | None = None
        self.last_block: BlockEstimate | None = None
        self.checklist = None
        self._task: asyncio.Task | None = None
        self.solver = BlockSolver()
        self._epochs = 0
        self.counters = {
            "records": 0,
            "nav_ignored": 0,
            "profiles_ignored": 0,
            "events_ignored": 0,
            "lines_dropped": 0,  # left the block cutter's window without a partner of another heading
            "blocks_skipped": 0,  # the worker was behind
        }

    # -- records --------------------------------------------------------------------------

    def feed(self, kind: str, record, gps_ns: int | None = None) -> None:
        """One record of the tap (never raises on a bad record: it is counted)."""
        self.counters["records"] += 1
        if kind == "nav":
            self.on_nav(record)
        elif kind == "profile":
            self.on_profile(record)
        elif kind == "event":
            self.on_event(record)

    def on_nav(self, rec) -> None:
        try:
            t = int(rec.gps_ns) / 1e9
            row = (
                t,
                float(rec.lat_deg),
                float(rec.lon_deg),
                float(rec.height_m),
                float(rec.roll_rad),
                float(rec.pitch_rad),
                float(rec.heading_rad),
                float(rec.sigma_north_m),
                float(rec.sigma_east_m),
                float(rec.sigma_down_m),
                float(rec.sigma_roll_rad),
                float(rec.sigma_pitch_rad),
                float(rec.sigma_heading_rad),
            )
            speed = math.hypot(float(rec.v_north_m_s), float(rec.v_east_m_s))
        except (AttributeError, TypeError, ValueError, OverflowError):
            self.counters["nav_ignored"] += 1
            return
        if not all(math.isfinite(x) for x in row[:7]) or not self.nav.add(row):
            self.counters["nav_ignored"] += 1
            return
        self._closed(self.cutter.on_nav(t, row[6], speed, row[1], row[2]))
        self._epochs += 1
        if self._epochs % TRIM_EVERY == 0:
            self._trim()

    def on_profile(self, prof) -> None:
        if self.cutter.run is None:  # no line open: nothing to keep
            return
        try:
            if not prof.time_valid:
                raise ValueError("profile without a valid time")
            t, r, a = prof.gps_ns, prof.range_m, prof.scan_angle_rad
            if not (t.dtype.kind == "i" and r.dtype.kind == "f" and a.dtype.kind == "f"):
                raise TypeError("profile arrays of the wrong type")
        except (AttributeError, TypeError, ValueError):
            self.counters["profiles_ignored"] += 1
            return
        self.points.add(t, r, a)

    def on_event(self, data) -> None:
        if not isinstance(data, dict):
            self.counters["events_ignored"] += 1
            return
        ev = data.get("event")
        if ev in ("pass_start", "pass_end"):
            before = self.cutter.marks
            self._closed(self.cutter.on_mark(ev, data.get("pass_id")))
            if not before and self.cutter.marks:
                self.publish()  # the mode changed

    # -- lines and blocks -----------------------------------------------------------------

    def _closed(self, lines: list[Line]) -> None:
        for line in lines:
            self.last_lines.append(line)
            self.lines[line.id] = line
            rel = float(frames.wrap_2pi(line.heading_rad - self.model.wall_azimuth_rad))
            block = self.blocks.add(line.id, rel)
            if block is not None:
                self._queue(tuple(self.lines[i] for i in block.line_ids), block.family)
            kept = set(self.blocks.kept)
            self.lines = {i: ln for i, ln in self.lines.items() if i in kept}
            self.counters["lines_dropped"] = self.blocks.dropped
            self._trim()
            self.publish()

    def _queue(self, lines: tuple[Line, ...], family: int) -> None:
        job = BlockJob(lines, self.nav.snapshot(), self.points.snapshot(), time.monotonic_ns(), family)
        self.waiting.append(job)
        while len(self.waiting) > MAX_WAITING_BLOCKS:
            self.waiting.popleft()
            self.counters["blocks_skipped"] += 1

    def _trim(self) -> None:
        starts = [ln.t_start_s for ln in self.lines.values()]
        if self.cutter.open_since_s is not None:
            starts.append(self.cutter.open_since_s)
        if starts:
            keep = min(starts)
        elif self.cutter.t_last is not None:
            keep = self.cutter.t_last
        else:
            return
        self.nav.trim_before(keep - NAV_KEEP_S)
        self.points.trim_before(keep)

    def take(self, block: BlockEstimate, family: int = 0) -> None:
        """A block's estimate (in the loop): the test, the alarm, the publications."""
        self.last_block = block
        self.test.update(block, family)
        if self.log_event is not None:
            self.log_event(
                {
                    "event": "mount_watch_block",
                    **block_summary(block),
                    "family": family,
                    "statistic": self.test.state()["statistic"],
                }
            )
        if self.test.alarm is not None and self.alarms is not None:
            # raised once (this block crossed); later blocks refine its size: the active alarm's
            # message follows, without a new raise (it is never cleared in the session)
            self.alarms.raise_now(
                *MOUNT_SHIFT, time.monotonic_ns(), message=self.test.alarm.message(), severity=CRITICAL
            )
        self.publish()

    async def _work(self) -> None:
        while self.waiting:
            job = self.waiting.popleft()
            self.running = job
            self.publish()
            try:
                block = await self.solver.solve(job, self.model)
            finally:
                self.running = None
            self.take(block, job.family)

    # -- publication ----------------------------------------------------------------------

    def state(self) -> dict:
        """The ``mount`` status topic."""
        st = self.test.state()
        pending = [self.lines[i].as_dict() for i in self.blocks.pending if i in self.lines]
        last_ok = st.get("last_block")
        doc = {
            "schema": SCHEMA,
            "verdict": verdict(st, self.test.alarm, len(pending), self.last_block),
            "state": "shift" if self.test.alarm else ("steady" if st["blocks_ok"] else "waiting"),
            **st,
            "calibration": self.info,
            "design": self.design.as_dict(),
            "last_block_status": None if self.last_block is None else block_summary(self.last_block),
            "patches": 0 if not last_ok else last_ok.get("patches", 0),
            "lines": {
                "mode": self.cutter.mode,
                "closed": self.cutter.lines,
                "ignored_short": self.cutter.ignored,
                "open_since_gps_s": self.cutter.open_since_s,
                "pending": pending,
                "last": [ln.as_dict() for ln in self.last_lines],
            },
            "worker": {
                "busy": self.running is not None,
                "running_lines": None if self.running is None else list(self.running.line_ids),
                "waiting": len(self.waiting),
                "behind": len(self.waiting) >= MAX_WAITING_BLOCKS or self.counters["blocks_skipped"] > 0,
            },
            "kept": {
                "nav_epochs": len(self.nav),
                "points": len(self.points),
                "points_budget_share": self.points.scale,
            },
            "counters": dict(self.counters),
        }
        return doc

    def publish(self) -> None:
        doc = self.state()
        if self._publish is not None:
            self._publish("mount", doc)
        if self.checklist is not None:
            self.checklist.publish("mount", checklist_section(doc, doc["verdict"]))

    # -- the consumer protocol -----------------------------------------------------------

    async def run(self, tap, checklist) -> None:
        self.checklist = checklist
        self.publish()
        self.solver.start()  # its imports now, not at the first block
        try:
            async for kind, record, gps_ns in tap:
                self.feed(kind, record, gps_ns)
                task = self._task
                if task is not None and task.done():
                    self._task = None
                    task.result()  # a bug in the worker's bookkeeping ends the consumer (restarted)
                if self.waiting and self._task is None:
                    self._task = asyncio.ensure_future(self._work())
        finally:
            if self._task is not None:
                self._task.cancel()
                await asyncio.gather(self._task, return_exceptions=True)
                self._task = None
            self.solver.close()
