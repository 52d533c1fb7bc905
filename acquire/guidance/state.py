"""The daemon's guidance state (DESIGN §8): :class:`Guidance` follows the survey, built on the
pure functions of :mod:`acquire.guidance.lines`, and :class:`GuidanceConsumer` runs it inside the
daemon.

:class:`Guidance` is fed with :class:`~drivers.hydrins.nav.NavRecord` and
:class:`~drivers.zf.codec.Profile` objects and clock states; it notices when the vessel sails
into a line's capture window (the first INS epoch past the window's start, within
``match_xte_m`` and ``match_heading_rad`` of the line), gathers the window's samples and live
target hits, and when the vessel leaves the window (its end, or off the line, turned away, gone
back) accepts or rejects the pass with :func:`acquire.guidance.lines.evaluate_pass`. After each
accepted pass it predicts the boresight σ of the accepted passes and ranks the remaining ones
(:mod:`calib.design.passpredict`), and it renders all of it as the ``checklist`` status message
(:meth:`Guidance.message`).

The daemon's wiring is :class:`GuidanceConsumer` (the :mod:`acquire.daemon.consumers` protocol)::

    site = load_site(cfg.site_file)
    g = Guidance(site, plan_site(site))
    Supervisor(cfg, consumers=[GuidanceConsumer(g, clock_state=lambda: ..., checks=lambda: ...)])

It feeds ``g.on_nav(rec)`` / ``g.on_profile(p)`` from the tap, ``g.on_clock(state)`` and
``g.update()`` every ``period_s``, runs ``g.refresh_prediction()`` in a thread after each
accepted pass, and publishes ``g.message(checks)`` as the ``guidance`` section of the
``checklist`` topic.
"""

from __future__ import annotations

import math
import threading
from collections import deque
from dataclasses import dataclass, field, replace
from typing import Iterable, Sequence

import numpy as np

from acquire.guidance.lines import (AcceptanceTolerances, Check, GuidanceSettings,
                              PassVerdict, PassWindow, evaluate_pass, heading_error,
                              line_offsets, line_state, speed_over_ground, target_hits)  # fmt: skip
from calib.core import frames
from calib.core.georef import Mount
from calib.survey.passplan import PassPlan, PlannedPass
from calib.design.passpredict import (ANGLES, ObservationModel, PassGeometry, SigmaPrediction,
                               predict_pass, predict_sigma, rank_candidates)  # fmt: skip
from calib.sim.scenario import ScannerModel
from calib.sim.scene import Scene
from calib.io.site import Site
from calib.core.trajectory import Trajectory, TrajectoryError
from drivers.hydrins.nav import NavRecord
from drivers.zf.codec import Profile

SCHEMA = "mls.checklist/1"  # of the message (the checklist topic's ``guidance`` section)
#: Columns of the navigation kept in memory (LGF metres, radians, flags 1/0/NaN).
_NAV_COLUMNS = ("t", "n", "e", "d", "roll", "pitch", "heading", "vn", "ve", "sn", "se", "sd",
                "sr", "sp", "sh", "nav", "dr", "pps", "utc")  # fmt: skip
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
            keep = self._a[self._lo:self._hi]
            cap = max(2 * (keep.shape[0] + m), 4096)
            a = np.empty((cap, self._a.shape[1]))
            a[: keep.shape[0]] = keep
            self._a, self._lo, self._hi = a, 0, keep.shape[0]
        self._a[self._hi:self._hi + m] = rows
        self._hi += m

    def rows(self, start_abs: int | None = None, end_abs: int | None = None) -> np.ndarray:
        lo = self._lo if start_abs is None else self._lo + max(start_abs - self.offset, 0)
        hi = self._hi if end_abs is None else self._lo + min(end_abs - self.offset, len(self))
        return self._a[lo:max(hi, lo)]

    def trim_before(self, abs_index: int) -> None:
        k = min(max(abs_index - self.offset, 0), len(self))
        self._lo += k
        self.offset += k


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


@dataclass(frozen=True)
class SigmaReport:
    current: SigmaPrediction
    ranking: tuple[tuple[int, SigmaPrediction], ...]  # remaining passes, best first
    rose: tuple[str, ...] = ()  # angles whose realistic σ the last accepted pass made larger

    def current_dict(self) -> dict:
        return {**self.current.as_dict(), "rose": list(self.rose)}


def sigma_rises(history: Sequence[dict], current: SigmaPrediction) -> tuple[str, ...]:
    """The angles whose realistic σ is larger than in the latest prediction of other passes.

    That happens: within a pass the POS error acts as one bias, and the adjustment weighs each
    pass by its number of points (the white model), so a pass with many points whose geometry
    adds little to an angle passes its bias on to it. The formal σ never rises."""
    prev = next((h for h in reversed(history) if h["passes"] != list(current.pass_ids)), None)
    if prev is None:
        return ()
    now = current.as_dict()["realistic_deg"]
    return tuple(a for a in ANGLES if now[a] is not None and prev["realistic_deg"][a] is not None
                 and now[a] > prev["realistic_deg"][a] * (1.0 + 1e-9))  # fmt: skip


class Guidance:
    """The guidance state of one survey (see the module docstring for the wiring).

    ``scanner`` describes the profiler for the candidate-pass predictions (rates, angular
    windows); ``thin_step`` how many points the σ prediction skips (None: about 100 k points/s
    of the scanner are kept).
    """

    def __init__(self, site: Site, plan: PassPlan, *, frame: frames.LocalFrame | None = None,
                 mount: Mount | None = None,
                 tolerances: AcceptanceTolerances = AcceptanceTolerances(),
                 settings: GuidanceSettings = GuidanceSettings(),
                 scanner: ScannerModel = ScannerModel(), thin_step: int | None = None):  # fmt: skip
        self.site = site
        self.plan = plan
        self.frame = site.frame(frame)
        self.mount = site.mount if mount is None else mount
        self.tol = tolerances
        self.settings = settings
        self.scanner = scanner
        rects = site.target_rectangles(self.frame)
        self.scene = Scene(tuple(rects), ("target",) * len(rects))
        self.target_names = [r.name for r in rects]
        self._centers = np.array([r.center_m for r in rects]).reshape(-1, 3)
        self.obs_model = ObservationModel.from_site(site)
        pts_s = scanner.effective_profile_rate_hz * scanner.effective_points_per_360
        self.thin_step = thin_step or max(1, int(round(pts_s / 1e5)))
        self._lock = threading.Lock()
        self._nav = _Columns(len(_NAV_COLUMNS))
        self._pending_nav: list[NavRecord] = []
        self.last_nav: NavRecord | None = None
        self._profiles: deque[Profile] = deque()
        self._last_profile_t = -math.inf
        self._cursor = 0  # absolute nav index the state machine advances next
        self._clock_state: str | None = None
        self._capture: _Capture | None = None
        self._selected: int | None = None
        self.passes = {p.id: _PassRecord() for p in plan.passes}
        self._accepted: dict[int, PassGeometry] = {}
        self._candidates: dict[int, tuple[float, PassGeometry]] = {}  # id → (down, geometry)
        self.sigma: SigmaReport | None = None
        self.sigma_history: list[dict] = []
        self.counters = {"nav_without_time": 0, "nav_rejected": 0, "profiles_dropped": 0,
                         "points_seen": 0, "points_gated": 0, "points_uncovered": 0}  # fmt: skip
        self._plan_msg = self._plan_dict()

    # -- inputs -----------------------------------------------------------------------------

    def on_nav(self, rec: NavRecord) -> None:
        """One INS epoch (canonical record)."""
        self.last_nav = rec
        if rec.gps_ns is None:
            self.counters["nav_without_time"] += 1
            return
        self._pending_nav.append(rec)

    def on_profile(self, profile: Profile) -> None:
        """One profile from the profiler (kept until the navigation covers it)."""
        if profile.n_points == 0:
            return
        self._profiles.append(profile)
        self._last_profile_t = max(self._last_profile_t,
                                   float(profile.gps_ns[-1]) * 1e-9)  # fmt: skip
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

    def update(self, predict: bool = True) -> list[PassVerdict]:
        """Process what arrived; returns the passes that finished (accepted or rejected). With
        ``predict``, an accepted pass refreshes the σ prediction here (else call
        :meth:`refresh_prediction`)."""
        self._ingest_nav()
        finished = []
        while True:
            self._advance()
            self._consume_profiles()
            verdict = self._maybe_close()
            if verdict is None:
                break
            finished.append(verdict)
            if verdict.accepted and predict:
                self.refresh_prediction()
        self._trim()
        return finished

    def _ingest_nav(self) -> None:
        recs, self._pending_nav = self._pending_nav, []
        if not recs:
            return
        rows = np.array([(r.gps_ns * 1e-9, r.lat_deg, r.lon_deg, r.height_m, r.roll_rad,
                          r.pitch_rad, r.heading_rad, r.v_north_m_s, r.v_east_m_s,
                          r.sigma_north_m, r.sigma_east_m, r.sigma_down_m, r.sigma_roll_rad,
                          r.sigma_pitch_rad, r.sigma_heading_rad, _flag(r.navigation),
                          _flag(r.dead_reckoning), _flag(r.pps_detected),
                          _flag(r.utc_detected)) for r in recs], float)  # fmt: skip
        ok = np.all(np.isfinite(rows[:, :7]), axis=1)
        rows = rows[ok]
        rows = rows[np.argsort(rows[:, 0], kind="stable")]
        last = self._nav.rows()[-1, 0] if len(self._nav) else -math.inf
        keep = np.concatenate([[rows[0, 0] > last], np.diff(rows[:, 0]) > 0]) if rows.size else []
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
        p, hdg, t = rows[:, 1:4], rows[:, 6], rows[:, 0]
        if cap is None:
            best = None
            for pid in self._pending_ids():
                line = self.plan.by_id(pid)
                along, xte = line_offsets(p, line)
                herr = heading_error(hdg, line.heading_rad)
                cross = np.zeros(rows.shape[0], bool)
                cross[1:] = (along[:-1] < line.capture_start_m) & (along[1:] >= line.capture_start_m)
                cross &= (np.abs(xte) <= self.settings.match_xte_m)
                cross &= (np.abs(herr) <= self.settings.match_heading_rad)
                cross[:first] = False
                k = np.flatnonzero(cross)
                if k.size and (best is None or k[0] < best[0]):
                    best = (int(k[0]), line)
            if best is None:
                self._cursor = self._nav.end
                return
            k, line = best
            cap = _Capture(line, ctx + k, float(t[k]))
            if self._clock_state is not None:
                cap.clock_states.add(self._clock_state)
            self._capture = cap
            self.passes[line.id].status = "capturing"
            first = k + 1
        line = cap.line
        along, xte = line_offsets(p, line)
        herr = heading_error(hdg, line.heading_rad)
        s = self.settings
        done = along >= line.capture_end_m
        off = np.abs(xte) > s.abort_xte_m
        turned = np.abs(herr) > s.abort_heading_rad
        back = along < line.capture_start_m - 1.0
        stop = done | off | turned | back
        stop[:first] = False
        k = np.flatnonzero(stop)
        if k.size == 0:
            self._cursor = self._nav.end
            return
        k = int(k[0])
        cap.i_exit = ctx + k
        cap.t_exit = float(t[k])
        cap.completed = bool(done[k])
        cap.exit_reason = ("" if done[k] else
                           f"left the line (XTE {xte[k]:+.1f} m)" if off[k] else
                           f"turned away (heading error {math.degrees(herr[k]):+.0f}°)" if turned[k]
                           else "went back before the window")  # fmt: skip
        self._cursor = ctx + k + 1

    def _consume_profiles(self) -> None:
        """Profiles the navigation covers: into the capture window, or dropped."""
        if not self._profiles or not len(self._nav):
            return
        t_nav = self._nav.rows()[-1, 0]
        cap = self._capture
        t_limit = t_nav
        if cap is None or cap.i_exit is None:
            # only as far as the state machine has looked
            t_limit = min(t_nav, self._nav.rows(self._cursor - 1, self._cursor)[0, 0]
                          if self._cursor - 1 >= self._nav.offset else t_nav)
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
            hits = target_hits(t, rho, alpha, which, t_prof, traj, self.mount, self.scene,
                               settings=self.settings, intensity=inten)  # fmt: skip
        except TrajectoryError:
            # some profile mid-times outside the navigation: place them one by one
            keep = ~traj.uncovered(t_prof + self.mount.time_offset_s)
            if not keep.any():
                return
            sel = keep[which]
            remap = np.cumsum(keep) - 1
            hits = target_hits(t[sel], rho[sel], alpha[sel], remap[which[sel]], t_prof[keep],
                               traj, self.mount, self.scene, settings=self.settings,
                               intensity=inten[sel])  # fmt: skip
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
        kw = {}
        if with_sigmas:
            sp, sa = r[:, [_C["sn"], _C["se"], _C["sd"]]], r[:, [_C["sr"], _C["sp"], _C["sh"]]]
            if np.all(np.isfinite(sp)) and np.all(sp > 0) and np.all(np.isfinite(sa)) \
                    and np.all(sa > 0):
                kw = {"sigma_p_m": sp, "sigma_rpy_rad": sa}
        return Trajectory(r[:, 0], r[:, 1:4], r[:, 4:7], self.frame, name="INS", **kw)

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
            pass_id=line.id, planned_speed_mps=line.speed_mps,
            capture_m=(line.capture_start_m, line.capture_end_m), completed=cap.completed,
            exit_reason=cap.exit_reason, t_enter_gps_s=cap.t_enter, t_exit_gps_s=cap.t_exit,
            t_gps_s=rows[:, 0], along_m=along, xte_m=xte,
            heading_error_rad=heading_error(rows[:, 6], line.heading_rad),
            speed_mps=speed_over_ground(rows[:, 7], rows[:, 8]),
            navigation=rows[:, _C["nav"]], dead_reckoning=rows[:, _C["dr"]],
            ins_pps=rows[:, _C["pps"]], utc=rows[:, _C["utc"]],
            profile_t_gps_s=np.asarray(cap.profile_t, float),
            profiles_incomplete=cap.incomplete, profiles_pps_unlocked=cap.unlocked,
            hits=hits, clock_states=tuple(sorted(cap.clock_states)),
        )  # fmt: skip

    def _hit_counts(self, cap: _Capture) -> dict[str, int]:
        n = len(self.target_names)
        c = sum((h.counts(n) for h in cap.hits), np.zeros(n, np.int64))
        return {name: int(k) for name, k in zip(self.target_names, c)}

    def _geometry(self, cap: _Capture) -> PassGeometry:
        """The accepted pass as the σ prediction sees it (thinned)."""
        cat = lambda f: np.concatenate([getattr(h, f) for h in cap.hits]) if cap.hits \
            else np.empty(0)  # noqa: E731
        t = cat("t_gps_s")
        order = np.argsort(t, kind="stable")
        traj = self._trajectory(cap.t_enter - 1.0, cap.t_exit + 1.0, with_sigmas=True)
        g = PassGeometry(cap.line.id, cap.line.relative_heading_rad, traj, t[order],
                         cat("range_m")[order], cat("scan_angle_rad")[order],
                         cat("target_index").astype(np.int64)[order])  # fmt: skip
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

    # -- prediction -------------------------------------------------------------------------

    def _track_down_m(self) -> float:
        downs = [float(np.median(g.trajectory.p_lgf_m[:, 2])) for g in self._accepted.values()
                 if g.trajectory is not None]  # fmt: skip
        if downs:
            return float(np.median(downs))
        if len(self._nav):
            return float(np.median(self._nav.rows()[:, 3]))
        return float(self.plan.passes[0].start_lgf_m[2])

    def _candidate(self, pid: int, track_down_m: float) -> PassGeometry:
        """The predicted geometry of a line (cached; made again when the vessel's height
        estimate moved by more than 0.5 m since)."""
        cached = self._candidates.get(pid)
        if cached is not None and abs(cached[0] - track_down_m) <= 0.5:
            return cached[1]
        scanner = replace(self.scanner,
                          point_rate_scale=self.scanner.point_rate_scale / self.thin_step)
        g = predict_pass(self.plan.by_id(pid), self.scene.rectangles, self.mount, scanner,
                         self.frame, track_down_m=track_down_m)  # fmt: skip
        self._candidates[pid] = (track_down_m, g)
        return g

    def refresh_prediction(self) -> SigmaReport:
        """Predicted σ of the accepted passes and of each remaining pass added to them
        (blocking; safe to run in a worker thread)."""
        with self._lock:
            order = [p.id for p in self.plan.passes]
            accepted = [self._accepted[i] for i in order if i in self._accepted]
            remaining = [i for i in order if i not in self._accepted]
            down = self._track_down_m()
            rects = self.scene.rectangles
            current = predict_sigma(accepted, rects, self.mount, self.obs_model,
                                    thin_step=self.thin_step)  # fmt: skip
            cands = {i: self._candidate(i, down) for i in remaining}
            ranking = rank_candidates(accepted, cands, rects, self.mount, self.obs_model,
                                      thin_step=self.thin_step,
                                      gap_s=self.settings.prediction_gap_s)  # fmt: skip
            report = SigmaReport(current, tuple(ranking), sigma_rises(self.sigma_history, current))
            self.sigma = report
            self.sigma_history.append(report.current_dict())
            return report

    # -- output -----------------------------------------------------------------------------

    def active_pass_id(self) -> int | None:
        """The line being sailed (capturing), else the pending line the vessel is on, else the
        operator's choice, else the next pending line in the plan's order."""
        if self._capture is not None:
            return self._capture.line.id
        pending = self._pending_ids()
        latest = self._latest()
        if latest is not None and pending:
            best = None
            for pid in pending:
                line = self.plan.by_id(pid)
                along, xte = line_offsets(latest[1:4], line)
                herr = float(heading_error(latest[6], line.heading_rad))
                if (abs(xte[0]) <= self.settings.match_xte_m
                        and abs(herr) <= self.settings.match_heading_rad
                        and -self.settings.approach_m <= along[0] <= line.capture_end_m):
                    if best is None or abs(xte[0]) < best[0]:
                        best = (abs(xte[0]), pid)
            if best is not None:
                return best[1]
        if self._selected is not None and self._selected in pending:
            return self._selected
        return pending[0] if pending else None

    def _plan_dict(self) -> dict:
        ne = lambda v: [round(float(v[0]), 3), round(float(v[1]), 3)]  # noqa: E731
        return {
            "reference": self.frame.as_dict(),
            "wall_azimuth_deg": math.degrees(self.plan.wall_azimuth_rad),
            "standoff_m": self.plan.standoff_m,
            "passes": [{
                "id": p.id, "order": p.order,
                "heading_deg": round(math.degrees(p.heading_rad), 3),
                "relative_heading_deg": round(math.degrees(p.relative_heading_rad), 3),
                "start_ne_m": ne(p.start_lgf_m), "end_ne_m": ne(p.end_lgf_m),
                "capture_m": [round(p.capture_start_m, 3), round(p.capture_end_m, 3)],
                "length_m": round(p.length_m, 3), "speed_mps": p.speed_mps,
                "targets_side": p.targets_side,
            } for p in self.plan.passes],
            "targets": [{"name": r.name, "center_ne_m": ne(r.center_m),
                         "corners_ne_m": [ne(c) for c in r.corners()]}
                        for r in self.scene.rectangles],
        }  # fmt: skip

    def message(self, checks: Iterable[Check] | None = None) -> dict:
        """The ``checklist`` status message (JSON-ready)."""
        latest = self._latest()
        vessel = None
        active = None
        aid = self.active_pass_id()
        if latest is not None:
            sog = float(speed_over_ground(latest[7], latest[8]))
            vessel = {"n_m": round(float(latest[1]), 3), "e_m": round(float(latest[2]), 3),
                      "heading_deg": round(math.degrees(latest[6]), 3),
                      "speed_mps": round(sog, 3), "t_gps_s": float(latest[0])}  # fmt: skip
            if self.last_nav is not None:
                vessel["lat_deg"] = self.last_nav.lat_deg
                vessel["lon_deg"] = self.last_nav.lon_deg
            if aid is not None:
                line = self.plan.by_id(aid)
                st = line_state(latest[1:4], float(latest[6]), sog, line, self._centers)
                active = st.as_dict()
                active["state"] = "capture" if self._capture is not None else "approach"
                active["planned_speed_mps"] = line.speed_mps
                active["heading_deg"] = round(math.degrees(line.heading_rad), 3)
                active["capture_m"] = [line.capture_start_m, line.capture_end_m]
                active["length_m"] = round(line.length_m, 3)
                if self._capture is not None:
                    active["hits"] = self._hit_counts(self._capture)
        elif aid is not None:
            active = {"pass_id": aid, "state": "approach"}
        passes = []
        for p in self.plan.passes:
            rec = self.passes[p.id]
            last = rec.verdicts[-1] if rec.verdicts else None
            passes.append({
                "id": p.id, "order": p.order,
                "heading_deg": round(math.degrees(p.heading_rad), 3),
                "relative_heading_deg": round(math.degrees(p.relative_heading_rad), 3),
                "status": rec.status, "attempts": len(rec.verdicts),
                "reasons": list(last.reasons) if last else [],
                "hits": last.stats.get("hits", {}) if last else {},
                "stats": {k: v for k, v in last.stats.items() if k != "hits"} if last else {},
            })  # fmt: skip
        sigma = None
        if self.sigma is not None:
            rank = [{"pass_id": pid, "undetermined": pred.rank_key()[0],
                     "worst_deg": pred.as_dict()["worst_deg"],
                     "realistic_deg": pred.as_dict()["realistic_deg"]}
                    for pid, pred in self.sigma.ranking]  # fmt: skip
            sigma = {"current": self.sigma.current_dict(),
                     "next_best": rank[0] if rank else None, "ranking": rank,
                     "history": list(self.sigma_history)}  # fmt: skip
        checks = [c.as_dict() if isinstance(c, Check) else dict(c) for c in (checks or [])]
        n_acc = sum(r.status == "accepted" for r in self.passes.values())
        return {
            "schema": SCHEMA,
            "vessel_name": self.site.vessel,
            "prechecks": checks,
            "prechecks_ok": bool(checks) and all(c["ok"] for c in checks),
            "plan": self._plan_msg,
            "vessel": vessel,
            "active": active,
            "passes": passes,
            "accepted": n_acc,
            "sigma": sigma,
            "calibration_ready": bool(self.sigma is not None
                                      and all(self.sigma.current.observable)),
            "tolerances": self.tol.as_dict(),
            "counters": dict(self.counters),
        }  # fmt: skip


# =============================================================================================
# The daemon's consumer (acquire.daemon.consumers protocol)
# =============================================================================================


class GuidanceConsumer:
    """Runs a :class:`Guidance` as a consumer of the daemon's record stream
    (:mod:`acquire.daemon.consumers`): ``nav`` and ``profile`` records feed it, ``pass_start`` events
    select a line; every ``period_s`` it updates and publishes its message as the ``guidance``
    section of the ``checklist`` topic. The σ prediction runs in a worker thread.

    ``clock_state()`` returns the clock model's state now (``"LOCKED"``…); ``checks()`` the
    pre-survey checks to publish with the guidance (e.g. :func:`prechecks` over the daemon's
    latest status), or None.
    """

    name = "guidance"
    kinds = ("nav", "profile", "event")

    def __init__(self, guidance: Guidance, *, clock_state=None, checks=None,
                 period_s: float = 0.5):  # fmt: skip
        self.guidance = guidance
        self.clock_state = clock_state
        self.checks = checks
        self.period_s = period_s
        self.records = 0

    def feed(self, kind: str, record, gps_ns: int | None = None) -> None:
        g = self.guidance
        self.records += 1
        if kind == "nav":
            g.on_nav(record)
        elif kind == "profile":
            g.on_profile(record)
        elif kind == "event" and isinstance(record, dict) and record.get("event") == "pass_start":
            try:
                g.select_pass(int(record["pass_id"]))
            except (KeyError, TypeError, ValueError):
                pass  # an event naming no pass of the plan changes nothing

    async def run(self, tap, checklist) -> None:
        import asyncio

        async def read() -> None:
            async for kind, record, gps_ns in tap:
                self.feed(kind, record, gps_ns)

        reader = asyncio.create_task(read())
        predict: asyncio.Future | None = None
        predicted_for = -1  # accepted passes the last prediction was started for
        try:
            while True:
                g = self.guidance
                if self.clock_state is not None:
                    g.on_clock(self.clock_state())
                g.update(predict=False)
                if predict is not None and predict.done():
                    predict.result()  # a failed prediction ends the consumer (restarted)
                    predict = None
                n_acc = len(g.accepted_ids)
                if predict is None and n_acc != predicted_for:
                    predict = asyncio.ensure_future(asyncio.to_thread(g.refresh_prediction))
                    predicted_for = n_acc
                checklist.publish("guidance", g.message(self.checks() if self.checks else None))
                if reader.done():
                    reader.result()  # re-raise what ended the reader
                    return
                await asyncio.sleep(self.period_s)
        finally:
            reader.cancel()
            if predict is not None:
                await asyncio.gather(predict, return_exceptions=True)
