"""The survey lines of the mount watch, cut live from the navigation (pure: no I/O, no clock).

A **line** is a stretch sailed on one heading; the watch groups lines of different headings into
blocks (:class:`calib.watch.runner.BlockCutter`). :class:`LineCutter` cuts them two ways:

- **by the pass marks** (``pass_start`` / ``pass_end`` events, from the CAN markers or MQTT
  commands) once the session has one: a line runs from its ``pass_start`` to its ``pass_end``
  (or to the next ``pass_start``). A mark is timed by the navigation around it — the INS time of
  the last epoch before it in the record stream — so a line is cut in the INS's own time, whatever
  state the clock model is in;
- **by the heading** otherwise (production surveys may have no marks; ``mls watch`` cuts a
  session without marks with this same class): a line is a run of epochs whose heading
  stays within :data:`HEADING_TOLERANCE_RAD` of its reference course — the
  circular mean of its first ``min_line_s`` (the running mean until then) — while the vessel
  makes way (≥ :data:`MIN_SPEED_MPS`); it ends at its last steady epoch once the heading has
  been off the course for :data:`TURN_S` (a turn; a shorter excursion, a yaw swing or one bad
  epoch, is skipped), at a stop, or at a gap in the navigation longer than
  :data:`MAX_NAV_GAP_S`.

Either way a line shorter than ``min_line_s`` is ignored, and one longer than ``max_line_s`` is
closed there and the next one starts at once (the watch keeps a block's data in memory).
Closed lines come back from :meth:`LineCutter.on_nav` / :meth:`LineCutter.on_mark` as
:class:`Line` s with their circular-mean heading.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

HEADING_TOLERANCE_RAD = math.radians(10.0)
MIN_LINE_S = 20.0
TURN_S = 2.0  # the heading off the line's mean this long: a turn (a yaw swing is shorter)
MIN_SPEED_MPS = 0.5  # slower is not surveying (at the quay, drifting)
MAX_NAV_GAP_S = 2.0  # a gap in the navigation this long ends the line (the data would too)


@dataclass(frozen=True)
class Line:
    """A closed line: its span in GPS seconds (the INS's time), its mean heading (true,
    radians, [0, 2π)), the pass it was marked as (None when cut by heading) and why it ended."""

    id: int
    t_start_s: float
    t_end_s: float
    heading_rad: float
    pass_id: int | None
    source: str  # "marks" | "heading"
    ended_by: str  # pass_end | pass_start | turn | stop | gap | max_line | end
    lat_deg: float = math.nan  # the mean position of its epochs (NaN: not given)
    lon_deg: float = math.nan

    @property
    def duration_s(self) -> float:
        return self.t_end_s - self.t_start_s

    def as_dict(self) -> dict:
        return {
            "id": self.id,
            "t_start_gps_s": self.t_start_s,
            "t_end_gps_s": self.t_end_s,
            "duration_s": round(self.duration_s, 3),
            "heading_deg": round(math.degrees(self.heading_rad), 2),
            "pass_id": self.pass_id,
            "source": self.source,
            "ended_by": self.ended_by,
        }


class _Run:
    """An open line: its start, its last steady epoch, its heading sums and its reference
    course (frozen ``settle_s`` after its start)."""

    __slots__ = ("t_start", "t_last", "s", "c", "pass_id", "off_since", "course", "settle_s", "pos", "n_pos")

    def __init__(self, t: float, heading: float, pass_id: int | None = None, settle_s: float = 0.0) -> None:
        self.t_start = self.t_last = t
        self.s, self.c = math.sin(heading), math.cos(heading)
        self.pass_id = pass_id
        self.off_since: float | None = None
        self.course: float | None = None
        self.settle_s = settle_s
        self.pos = [0.0, 0.0]  # sums of the epochs' latitude and longitude
        self.n_pos = 0

    def add(self, t: float, heading: float, lat: float = math.nan, lon: float = math.nan) -> None:
        self.t_last = t
        self.s += math.sin(heading)
        self.c += math.cos(heading)
        if lat == lat and lon == lon:
            self.pos[0] += lat
            self.pos[1] += lon
            self.n_pos += 1
        if self.course is None and t - self.t_start >= self.settle_s:
            self.course = self.mean

    @property
    def mean(self) -> float:
        return math.atan2(self.s, self.c) % (2.0 * math.pi)

    @property
    def reference(self) -> float:
        return self.mean if self.course is None else self.course


def _off(heading: float, mean: float) -> float:
    """|heading − mean| wrapped to [0, π]."""
    return abs((heading - mean + math.pi) % (2.0 * math.pi) - math.pi)


class LineCutter:
    """Cuts lines from the navigation and the pass marks (module docstring)."""

    def __init__(self, min_line_s: float = MIN_LINE_S, max_line_s: float = 900.0) -> None:
        self.min_line_s = float(min_line_s)
        self.max_line_s = float(max_line_s)
        self.marks = False  # a pass mark was seen: lines come from the marks from now on
        self.run: _Run | None = None
        self.t_last: float | None = None  # the INS time of the latest epoch
        self.next_id = 1
        self.lines = 0  # lines closed (kept)
        self.ignored = 0  # closed shorter than min_line_s

    @property
    def mode(self) -> str:
        return "marks" if self.marks else "heading"

    @property
    def open_since_s(self) -> float | None:
        """The start of the open line (None: none open)."""
        return None if self.run is None else self.run.t_start

    def finish(self) -> list[Line]:
        """The end of the navigation (a recorded survey read to its end): the open line, closed
        at its last steady epoch."""
        return [] if self.run is None else self._close(self.run.t_last, "end")

    def _close(self, t_end: float, why: str) -> list[Line]:
        run, self.run = self.run, None
        if run is None:
            return []
        if t_end - run.t_start < self.min_line_s:
            self.ignored += 1
            return []
        n = run.n_pos
        lat, lon = (run.pos[0] / n, run.pos[1] / n) if n else (math.nan, math.nan)
        line = Line(self.next_id, run.t_start, t_end, run.mean, run.pass_id, self.mode, why, lat, lon)
        self.next_id += 1
        self.lines += 1
        return [line]

    def on_nav(
        self,
        t_s: float,
        heading_rad: float,
        speed_mps: float = math.nan,
        lat_deg: float = math.nan,
        lon_deg: float = math.nan,
    ) -> list[Line]:
        """One INS epoch (GPS seconds, true heading, speed over ground or NaN, position); the
        lines it closes. Epochs not after the previous one are ignored."""
        if not (math.isfinite(t_s) and math.isfinite(heading_rad)):
            return []
        if self.t_last is not None and t_s <= self.t_last:
            return []
        gap = self.t_last is not None and t_s - self.t_last > MAX_NAV_GAP_S
        t_prev, self.t_last = self.t_last, t_s
        run = self.run
        if gap and run is not None:
            return self._after_gap(run, t_s, heading_rad)
        if self.marks:
            return [] if run is None else self._marked_epoch(run, t_s, heading_rad, lat_deg, lon_deg)
        moving = not (speed_mps < MIN_SPEED_MPS)  # NaN: unknown, taken as moving
        if run is None:
            if moving:
                self.run = _Run(t_s, heading_rad, settle_s=self.min_line_s)
            return []
        return self._heading_epoch(run, t_s, t_prev, heading_rad, moving, (lat_deg, lon_deg))

    def _after_gap(self, run: _Run, t_s: float, heading_rad: float) -> list[Line]:
        """The first epoch after a gap in the navigation: the open line closed at its last epoch
        (a marked line goes on from this epoch)."""
        pid = run.pass_id
        out = self._close(run.t_last, "gap")
        if self.marks and pid is not None:  # the marked line goes on after the gap
            self.run = _Run(t_s, heading_rad, pid)
        return out

    def _marked_epoch(
        self, run: _Run, t_s: float, heading_rad: float, lat_deg: float, lon_deg: float
    ) -> list[Line]:
        """An epoch of a line between pass marks: added; the line cut at ``max_line_s``."""
        run.add(t_s, heading_rad, lat_deg, lon_deg)
        if t_s - run.t_start >= self.max_line_s:
            out = self._close(t_s, "max_line")
            self.run = _Run(t_s, heading_rad, run.pass_id)
            return out
        return []

    def _heading_epoch(
        self,
        run: _Run,
        t_s: float,
        t_prev: float | None,
        heading_rad: float,
        moving: bool,
        lat_lon_deg: tuple[float, float],
    ) -> list[Line]:
        """An epoch of a line cut by heading: added while on the line's heading and moving; the
        line closed after ``TURN_S`` off it or at a stop (a new one starts when moving), and cut
        at ``max_line_s``."""
        if moving and _off(heading_rad, run.reference) <= HEADING_TOLERANCE_RAD:
            run.off_since = None
            run.add(t_s, heading_rad, *lat_lon_deg)
        else:
            if run.off_since is None:
                run.off_since = t_prev if t_prev is not None else t_s
            if t_s - run.off_since >= TURN_S or not moving:
                out = self._close(run.t_last, "turn" if moving else "stop")
                if moving:
                    self.run = _Run(t_s, heading_rad, settle_s=self.min_line_s)
                return out
        if run.t_last - run.t_start >= self.max_line_s:
            out = self._close(run.t_last, "max_line")
            self.run = _Run(t_s, heading_rad, settle_s=self.min_line_s)
            return out
        return []

    def on_mark(self, event: str, pass_id) -> list[Line]:
        """A ``pass_start`` / ``pass_end`` event (timed by the latest epoch); the lines it
        closes. The first mark switches the cutter to marks (a line cut by heading that is
        open then is dropped: it would overlap the marked one)."""
        if event not in ("pass_start", "pass_end"):
            return []
        try:
            pid = int(pass_id)
        except (TypeError, ValueError):
            return []
        if not self.marks:
            self.marks = True
            self.run = None
        t = self.t_last
        out: list[Line] = []
        if event == "pass_start":
            if self.run is not None:
                out += self._close(self.run.t_last, "pass_start")
            if t is not None:
                self.run = _Run(t, math.nan, pid)
                self.run.s = self.run.c = 0.0  # no epoch yet: the heading sums start empty
            return out
        if self.run is not None and self.run.pass_id == pid:
            out += self._close(self.run.t_last if t is None else t, "pass_end")
        return out
