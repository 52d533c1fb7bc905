"""The pass-window tracking of the daemon's guidance (docs/architecture.md §8): :class:`PassTracker` keeps the
recent navigation, notices when the vessel sails into a line's capture window, gathers the
window's samples, profiles and live target hits, and when the vessel leaves it accepts or
rejects the pass with :func:`acquire.guidance.acceptance.evaluate_pass`."""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from acquire.guidance.acceptance import AcceptanceTolerances, PassVerdict, PassWindow, evaluate_pass
from acquire.guidance.lines import GuidanceSettings, heading_error, line_offsets, speed_over_ground
from acquire.guidance.targethits import target_hits
from calib.core import frames
from calib.core.geometry import Rectangle
from calib.core.georef import Mount
from calib.core.trajectory import Trajectory, TrajectoryError
from calib.design.passpredict import PassGeometry
from calib.sim.scene import Scene
from calib.survey.passplan import PassPlan, PlannedPass
from drivers.hydrins.nav import NavRecord
from drivers.zf.codec import Profile

#: Columns of the navigation kept in memory (LGF metres, radians, flags 1/0/NaN).
_NAV_COLUMNS = (
    "t",
    "n",
    "e",
    "d",
    "roll",
    "pitch",
    "heading",
    "vn",
    "ve",
    "sn",
    "se",
    "sd",
    "sr",
    "sp",
    "sh",
    "nav",
    "dr",
    "pps",
    "utc",
)
_C = {name: i for i, name in enumerate(_NAV_COLUMNS)}


def _flag(v: bool | None) -> float:
    return math.nan if v is None else float(v)


class _Columns:
    """Growable float64 rows with amortized appends and trimming from the front."""

    def __init__(self, width: int, capacity: int = 4096):
        self._a = np.empty((capacity, width))
        self._lo = 0
        self._hi = 0
        self.offset = 0  # absolute index of the first row kept

    def __len__(self) -> int:
        return self._hi - self._lo

    @property
    def end(self) -> int:
        """Absolute index after the last row."""
        return self.offset + len(self)

    def extend(self, rows: np.ndarray) -> None:
        m = rows.shape[0]
        if self._hi + m > self._a.shape[0]:
            keep = self._a[self._lo : self._hi]
            cap = max(2 * (keep.shape[0] + m), 4096)
            a = np.empty((cap, self._a.shape[1]))
            a[: keep.shape[0]] = keep
            self._a, self._lo, self._hi = a, 0, keep.shape[0]
        self._a[self._hi : self._hi + m] = rows
        self._hi += m

    def rows(self, start_abs: int | None = None, end_abs: int | None = None) -> np.ndarray:
        lo = self._lo if start_abs is None else self._lo + max(start_abs - self.offset, 0)
        hi = self._hi if end_abs is None else self._lo + min(end_abs - self.offset, len(self))
        return self._a[lo : max(hi, lo)]

    def trim_before(self, abs_index: int) -> None:
        k = min(max(abs_index - self.offset, 0), len(self))
        self._lo += k
        self.offset += k


@dataclass(frozen=True)
class _WindowExit:
    """Where and how the vessel left a capture window."""

    k: int  # index, in the rows examined, of the first sample past the window
    completed: bool  # sailed through to the window's end
    reason: str  # why it ended early ("" when completed)


def _window_exit(line: PlannedPass, rows: np.ndarray, first: int, s: GuidanceSettings) -> _WindowExit | None:
    """The first sample, at or after ``rows[first]``, that ends ``line``'s capture window: past
    its end, off the line, turned away, or back before its start; None while still inside."""
    along, xte = line_offsets(rows[:, 1:4], line)
    herr = heading_error(rows[:, 6], line.heading_rad)
    done = along >= line.capture_end_m
    off = np.abs(xte) > s.abort_xte_m
    turned = np.abs(herr) > s.abort_heading_rad
    back = along < line.capture_start_m - 1.0
    stop = done | off | turned | back
    stop[:first] = False
    hits = np.flatnonzero(stop)
    if hits.size == 0:
        return None
    k = int(hits[0])
    reason = (
        ""
        if done[k]
        else f"left the line (XTE {xte[k]:+.1f} m)"
        if off[k]
        else f"turned away (heading error {math.degrees(herr[k]):+.0f}°)"
        if turned[k]
        else "went back before the window"
    )
    return _WindowExit(k=k, completed=bool(done[k]), reason=reason)


@dataclass
class _PassRecord:
    status: str = "pending"  # pending | capturing | accepted | rejected
    verdicts: list[PassVerdict] = field(default_factory=list)


@dataclass
class _Capture:
    line: PlannedPass
    i_enter: int  # absolute nav index of the first sample in the window
    t_enter: float
    t_exit: float = math.inf
    i_exit: int | None = None
    completed: bool = False
    exit_reason: str = ""
    clock_states: set = field(default_factory=set)
    profile_t: list = field(default_factory=list)
    incomplete: int = 0
    unlocked: int = 0
    hits: list = field(default_factory=list)  # TargetHits per batch


class PassTracker:
    """The capture windows of one survey's lines, followed from the navigation and the
    profiles fed to it (see the module docstring); :class:`~acquire.guidance.state.Guidance`
    adds the σ prediction and the checklist message.

    ``rects`` are the targets in ``frame``; ``thin_step`` how many points of an accepted pass
    the σ prediction skips.
    """

    def __init__(
        self,
        plan: PassPlan,
        frame: frames.LocalFrame,
        mount: Mount,
        rects: Sequence[Rectangle],
        tolerances: AcceptanceTolerances,
        settings: GuidanceSettings,
        thin_step: int,
    ):
        self.plan = plan
        self.frame = frame
        self.mount = mount
        self.tol = tolerances
        self.settings = settings
        self.scene = Scene(tuple(rects), ("target",) * len(rects))
        self.target_names = [r.name for r in rects]
        self.thin_step = thin_step
        self._nav = _Columns(len(_NAV_COLUMNS))
        self._pending_nav: list[tuple[int, NavRecord]] = []  # (GPS ns, record): timed ones only
        self.last_nav: NavRecord | None = None
        self._profiles: deque[Profile] = deque()
        self._last_profile_t = -math.inf
        self._cursor = 0  # absolute nav index the state machine advances next
        self._clock_state: str | None = None
        self._capture: _Capture | None = None
        self._selected: int | None = None
        self.passes = {p.id: _PassRecord() for p in plan.passes}
        self._accepted: dict[int, PassGeometry] = {}
        self.counters = {
            "nav_without_time": 0,
            "nav_rejected": 0,
            "profiles_dropped": 0,
            "points_seen": 0,
            "points_gated": 0,
            "points_uncovered": 0,
        }

    # -- inputs -----------------------------------------------------------------------------

    def on_nav(self, rec: NavRecord) -> None:
        """One INS epoch (canonical record)."""
        self.last_nav = rec
        if rec.gps_ns is None:
            self.counters["nav_without_time"] += 1
            return
        self._pending_nav.append((rec.gps_ns, rec))

    def on_profile(self, profile: Profile) -> None:
        """One profile from the profiler (kept until the navigation covers it)."""
        if profile.n_points == 0:
            return
        self._profiles.append(profile)
        self._last_profile_t = max(self._last_profile_t, float(profile.gps_ns[-1]) * 1e-9)
        while len(self._profiles) > self.settings.max_pending_profiles:
            self._profiles.popleft()
            self.counters["profiles_dropped"] += 1

    def on_clock(self, state: str) -> None:
        """The clock model's state (``LOCKED``, ``HOLDOVER``, ``UNLOCKED``), at least when it
        changes."""
        self._clock_state = str(state)
        if self._capture is not None and self._capture.i_exit is None:
            self._capture.clock_states.add(self._clock_state)

    @property
    def accepted_ids(self) -> list[int]:
        """Accepted passes, in the order they were accepted."""
        return list(self._accepted)

    def select_pass(self, pass_id: int) -> None:
        """The operator's choice of the next line (shown until the vessel is on a line)."""
        self.plan.by_id(pass_id)
        self._selected = pass_id

    # -- processing -------------------------------------------------------------------------

    def _ingest_nav(self) -> None:
        recs, self._pending_nav = self._pending_nav, []
        if not recs:
            return
        rows = np.array(
            [
                (
                    gps_ns * 1e-9,
                    r.lat_deg,
                    r.lon_deg,
                    r.height_m,
                    r.roll_rad,
                    r.pitch_rad,
                    r.heading_rad,
                    r.v_north_m_s,
                    r.v_east_m_s,
                    r.sigma_north_m,
                    r.sigma_east_m,
                    r.sigma_down_m,
                    r.sigma_roll_rad,
                    r.sigma_pitch_rad,
                    r.sigma_heading_rad,
                    _flag(r.navigation),
                    _flag(r.dead_reckoning),
                    _flag(r.pps_detected),
                    _flag(r.utc_detected),
                )
                for gps_ns, r in recs
            ],
            np.float64,
        )
        ok = np.all(np.isfinite(rows[:, :7]), axis=1)
        rows = rows[ok]
        rows = rows[np.argsort(rows[:, 0], kind="stable")]
        last = self._nav.rows()[-1, 0] if len(self._nav) else -math.inf
        if rows.size:
            keep = np.concatenate([[rows[0, 0] > last], np.diff(rows[:, 0]) > 0])
        else:
            keep = np.zeros(0, bool)
        self.counters["nav_rejected"] += int(len(recs) - np.count_nonzero(keep))
        rows = rows[np.asarray(keep, bool)]
        if rows.size == 0:
            return
        rows[:, 1:4] = self.frame.to_lgf(rows[:, 1], rows[:, 2], rows[:, 3])
        self._nav.extend(rows)

    def _latest(self) -> np.ndarray | None:
        return self._nav.rows()[-1] if len(self._nav) else None

    def _pending_ids(self) -> list[int]:
        return [p.id for p in self.plan.passes if self.passes[p.id].status != "accepted"]

    def _advance(self) -> None:
        """Run the capture state machine over the samples not yet advanced through."""
        cap = self._capture
        if cap is not None and cap.i_exit is not None:
            return  # closing: wait for the window's profiles
        start = max(self._cursor, self._nav.offset)
        if start >= self._nav.end:
            return
        # one sample of context for crossings
        ctx = start - 1 if start - 1 >= self._nav.offset else start
        rows = self._nav.rows(ctx, None)
        first = start - ctx  # index in rows of the first new sample
        if cap is None:
            entry = self._entry(rows, first)
            if entry is None:
                self._cursor = self._nav.end
                return
            k_enter, line = entry
            cap = self._start_capture(line, ctx + k_enter, float(rows[k_enter, 0]))
            first = k_enter + 1
        end = _window_exit(cap.line, rows, first, self.settings)
        if end is None:
            self._cursor = self._nav.end
            return
        cap.i_exit = ctx + end.k
        cap.t_exit = float(rows[end.k, 0])
        cap.completed = end.completed
        cap.exit_reason = end.reason
        self._cursor = ctx + end.k + 1

    def _entry(self, rows: np.ndarray, first: int) -> tuple[int, PlannedPass] | None:
        """The earliest entry, at or after ``rows[first]``, into the capture window of a line
        not yet accepted: crossing its start within the match tolerances of cross-track and
        heading error (index in ``rows``, the line); None when the vessel entered none."""
        p, hdg = rows[:, 1:4], rows[:, 6]
        best = None
        for pid in self._pending_ids():
            line = self.plan.by_id(pid)
            along, xte = line_offsets(p, line)
            herr = heading_error(hdg, line.heading_rad)
            cross = np.zeros(rows.shape[0], bool)
            cross[1:] = (along[:-1] < line.capture_start_m) & (along[1:] >= line.capture_start_m)
            cross &= np.abs(xte) <= self.settings.match_xte_m
            cross &= np.abs(herr) <= self.settings.match_heading_rad
            cross[:first] = False
            k = np.flatnonzero(cross)
            if k.size and (best is None or k[0] < best[0]):
                best = (int(k[0]), line)
        return best

    def _start_capture(self, line: PlannedPass, i_enter: int, t_enter: float) -> _Capture:
        """Open the capture of ``line``'s window at nav index ``i_enter`` (time ``t_enter``)."""
        cap = _Capture(line, i_enter, t_enter)
        if self._clock_state is not None:
            cap.clock_states.add(self._clock_state)
        self._capture = cap
        self.passes[line.id].status = "capturing"
        return cap

    def _consume_profiles(self) -> None:
        """Profiles the navigation covers: into the capture window, or dropped."""
        if not self._profiles or not len(self._nav):
            return
        t_nav = self._nav.rows()[-1, 0]
        cap = self._capture
        t_limit = t_nav
        if cap is None or cap.i_exit is None:
            # only as far as the state machine has looked
            t_limit = min(
                t_nav,
                self._nav.rows(self._cursor - 1, self._cursor)[0, 0]
                if self._cursor - 1 >= self._nav.offset
                else t_nav,
            )
        batch = []
        while self._profiles and float(self._profiles[0].gps_ns[-1]) * 1e-9 <= t_limit:
            prof = self._profiles.popleft()
            t_mid = 0.5e-9 * float(prof.gps_ns[0] + prof.gps_ns[-1])
            if cap is not None and cap.t_enter <= t_mid <= cap.t_exit:
                batch.append((t_mid, prof))
        if batch and cap is not None:
            self._window_profiles(cap, batch)

    def _window_profiles(self, cap: _Capture, batch: list[tuple[float, Profile]]) -> None:
        for t_mid, prof in batch:
            cap.profile_t.append(t_mid)
            cap.incomplete += not prof.complete
            cap.unlocked += not prof.pps_locked
        t_prof = np.array([b[0] for b in batch])
        sizes = [b[1].n_points for b in batch]
        t = np.concatenate([b[1].gps_ns for b in batch]) * 1e-9
        rho = np.concatenate([b[1].range_m for b in batch])
        alpha = np.concatenate([b[1].scan_angle_rad for b in batch])
        inten = np.concatenate([b[1].intensity for b in batch])
        which = np.repeat(np.arange(len(batch)), sizes)
        self.counters["points_seen"] += int(t.size)
        traj = self._trajectory(float(t.min()) - 0.5, float(t.max()) + 0.5)
        if traj is None:
            return
        try:
            hits = target_hits(
                t,
                rho,
                alpha,
                which,
                t_prof,
                traj,
                self.mount,
                self.scene,
                settings=self.settings,
                intensity=inten,
            )
        except TrajectoryError:
            # some profile mid-times outside the navigation: place them one by one
            keep = ~traj.uncovered(t_prof + self.mount.time_offset_s)
            if not keep.any():
                return
            sel = keep[which]
            remap = np.cumsum(keep) - 1
            hits = target_hits(
                t[sel],
                rho[sel],
                alpha[sel],
                remap[which[sel]],
                t_prof[keep],
                traj,
                self.mount,
                self.scene,
                settings=self.settings,
                intensity=inten[sel],
            )
        self.counters["points_gated"] += hits.n_gated
        self.counters["points_uncovered"] += hits.n_uncovered
        cap.hits.append(hits)

    def _trajectory(self, t0: float, t1: float, with_sigmas: bool = False) -> Trajectory | None:
        rows = self._nav.rows()
        i0 = max(int(np.searchsorted(rows[:, 0], t0, "right")) - 1, 0)
        i1 = min(int(np.searchsorted(rows[:, 0], t1, "left")) + 1, rows.shape[0])
        r = rows[i0:i1]
        if r.shape[0] < 2:
            return None
        sigma_p_m = sigma_rpy_rad = None  # (the INS's sigmas only when all are valid)
        if with_sigmas:
            sp, sa = r[:, [_C["sn"], _C["se"], _C["sd"]]], r[:, [_C["sr"], _C["sp"], _C["sh"]]]
            if np.all(np.isfinite(sp)) and np.all(sp > 0) and np.all(np.isfinite(sa)) and np.all(sa > 0):
                sigma_p_m, sigma_rpy_rad = sp, sa
        return Trajectory(
            r[:, 0],
            r[:, 1:4],
            r[:, 4:7],
            self.frame,
            sigma_p_m=sigma_p_m,
            sigma_rpy_rad=sigma_rpy_rad,
            name="INS",
        )

    def _maybe_close(self) -> PassVerdict | None:
        cap = self._capture
        if cap is None or cap.i_exit is None:
            return None
        t_nav = self._nav.rows()[-1, 0]
        if self._last_profile_t < cap.t_exit and t_nav < cap.t_exit + self.settings.settle_s:
            return None  # late profiles may still come
        self._consume_profiles()
        window = self._window(cap)
        rec = self.passes[cap.line.id]
        verdict = evaluate_pass(window, self.tol, attempt=len(rec.verdicts) + 1)
        rec.verdicts.append(verdict)
        rec.status = "accepted" if verdict.accepted else "rejected"
        if verdict.accepted:
            self._accepted[cap.line.id] = self._geometry(cap)
            if self._selected == cap.line.id:
                self._selected = None
        self._capture = None
        return verdict

    def _window(self, cap: _Capture) -> PassWindow:
        rows = self._nav.rows(cap.i_enter, cap.i_exit)  # samples inside the window
        line = cap.line
        along, xte = line_offsets(rows[:, 1:4], line)
        hits = self._hit_counts(cap)
        return PassWindow(
            pass_id=line.id,
            planned_speed_mps=line.speed_mps,
            capture_m=(line.capture_start_m, line.capture_end_m),
            completed=cap.completed,
            exit_reason=cap.exit_reason,
            t_enter_gps_s=cap.t_enter,
            t_exit_gps_s=cap.t_exit,
            t_gps_s=rows[:, 0],
            along_m=along,
            xte_m=xte,
            heading_error_rad=heading_error(rows[:, 6], line.heading_rad),
            speed_mps=speed_over_ground(rows[:, 7], rows[:, 8]),
            navigation=rows[:, _C["nav"]],
            dead_reckoning=rows[:, _C["dr"]],
            ins_pps=rows[:, _C["pps"]],
            utc=rows[:, _C["utc"]],
            profile_t_gps_s=np.asarray(cap.profile_t, float),
            profiles_incomplete=cap.incomplete,
            profiles_pps_unlocked=cap.unlocked,
            hits=hits,
            clock_states=tuple(sorted(cap.clock_states)),
        )

    def _hit_counts(self, cap: _Capture) -> dict[str, int]:
        n = len(self.target_names)
        c = sum((h.counts(n) for h in cap.hits), np.zeros(n, np.int64))
        return {name: int(k) for name, k in zip(self.target_names, c, strict=True)}

    def _geometry(self, cap: _Capture) -> PassGeometry:
        """The accepted pass as the σ prediction sees it (thinned)."""
        cat = lambda f: np.concatenate([getattr(h, f) for h in cap.hits]) if cap.hits else np.empty(0)  # noqa: E731
        t = cat("t_gps_s")
        order = np.argsort(t, kind="stable")
        traj = self._trajectory(cap.t_enter - 1.0, cap.t_exit + 1.0, with_sigmas=True)
        # accepted: INS records in the window (evaluate_pass), and the one before its entry
        assert traj is not None, "an accepted pass has navigation across its window"
        g = PassGeometry(
            pass_id=cap.line.id,
            relative_heading_rad=cap.line.relative_heading_rad,
            trajectory=traj,
            t_gps_s=t[order],
            range_m=cat("range_m")[order],
            scan_angle_rad=cat("scan_angle_rad")[order],
            target_index=cat("target_index").astype(np.int64)[order],
        )
        return g.thinned(self.thin_step)

    def _trim(self) -> None:
        if not len(self._nav):
            return
        t_last = self._nav.rows()[-1, 0]
        rows = self._nav.rows()
        k = int(np.searchsorted(rows[:, 0], t_last - self.settings.nav_history_s))
        limit = self._nav.offset + k
        if self._capture is not None:
            limit = min(limit, self._capture.i_enter - 1)
        self._nav.trim_before(min(limit, self._cursor - 1))
