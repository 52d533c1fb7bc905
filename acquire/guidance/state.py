"""The daemon's guidance state (docs/architecture.md §8): :class:`Guidance` follows the survey, built on the
pure functions of :mod:`acquire.guidance.lines` and :mod:`acquire.guidance.acceptance` and the pass-window tracking of
:class:`~acquire.guidance.tracking.PassTracker`; the daemon runs it through
:class:`~acquire.guidance.consumer.GuidanceConsumer`.

:class:`Guidance` is fed with :class:`~drivers.hydrins.nav.NavRecord` and
:class:`~drivers.zf.codec.Profile` objects and clock states; it notices when the vessel sails
into a line's capture window (the first INS epoch past the window's start, within
``match_xte_m`` and ``match_heading_rad`` of the line), gathers the window's samples and live
target hits, and when the vessel leaves the window (its end, or off the line, turned away, gone
back) accepts or rejects the pass with :func:`acquire.guidance.acceptance.evaluate_pass`. After each
accepted pass it predicts the boresight σ of the accepted passes and ranks the remaining ones
(:mod:`calib.design.passpredict`; the GLS estimator's σ by default, which never rises when a pass
is accepted), and it renders all of it as the ``checklist`` status message
(:meth:`Guidance.message`).
"""

from __future__ import annotations

import math
import threading
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from acquire.guidance.acceptance import AcceptanceTolerances, PassVerdict
from acquire.guidance.lines import (
    GuidanceSettings,
    heading_error,
    line_offsets,
    line_state,
    speed_over_ground,
)
from acquire.guidance.prechecks import Check
from acquire.guidance.tracking import PassTracker
from calib.core import frames
from calib.core.geometry import Rectangle, VerticalCylinder
from calib.core.georef import Mount
from calib.design.passpredict import (
    ANGLES,
    ObservationModel,
    PassGeometry,
    SigmaPrediction,
    predict_pass,
    predict_sigma,
    rank_candidates,
    scanned,
    weakest_angle,
)
from calib.io.site import Site
from calib.sim.scenario import ScannerModel
from calib.survey.passplan import PassPlan

SCHEMA = "mls.checklist/1"  # of the message (the checklist topic's ``guidance`` section)

# the defaults of :class:`Guidance` (immutable: one instance shared)
_DEFAULT_TOLERANCES = AcceptanceTolerances()
_DEFAULT_SETTINGS = GuidanceSettings()
_DEFAULT_SCANNER = ScannerModel()


@dataclass(frozen=True)
class SigmaReport:
    current: SigmaPrediction
    ranking: tuple[tuple[int, SigmaPrediction], ...]  # remaining passes, best first
    #: angles whose realistic σ the last accepted pass made larger (thesis estimator only:
    #: the GLS σ never rises)
    rose: tuple[str, ...] = ()

    def current_dict(self) -> dict:
        return {**self.current.as_dict(), "rose": list(self.rose)}


def sigma_rises(history: Sequence[dict], current: SigmaPrediction) -> tuple[str, ...]:
    """The angles whose realistic σ is larger than in the latest prediction of other passes.

    With the default GLS prediction this is always empty: its covariance is the inverse of an
    information matrix that each accepted pass can only add to. It names an angle with the
    thesis estimator (``Guidance(estimator="thesis")``): within a pass the POS error acts as
    one bias, and the white weights weigh each pass by its number of points, so a pass with
    many points whose geometry adds little to an angle passes its bias on to it. The formal σ
    never rises."""
    prev = next((h for h in reversed(history) if h["passes"] != list(current.pass_ids)), None)
    if prev is None:
        return ()
    now = current.as_dict()["realistic_deg"]
    return tuple(
        a
        for a in ANGLES
        if now[a] is not None
        and prev["realistic_deg"][a] is not None
        and now[a] > prev["realistic_deg"][a] * (1.0 + 1e-9)
    )


class Guidance(PassTracker):
    """The guidance state of one survey (the daemon's wiring: :mod:`acquire.guidance.consumer`).

    ``scanner`` describes the profiler for the candidate-pass predictions (rates, angular
    windows); ``thin_step`` how many points the σ prediction skips (None: about 100 k points/s
    of the scanner are kept); ``estimator`` the calibration's estimator the σ is predicted for
    (``"gls"``, the default, or ``"thesis"``: :class:`calib.design.passpredict.ObservationModel`).
    """

    def __init__(
        self,
        site: Site,
        plan: PassPlan,
        *,
        frame: frames.LocalFrame | None = None,
        mount: Mount | None = None,
        tolerances: AcceptanceTolerances = _DEFAULT_TOLERANCES,
        settings: GuidanceSettings = _DEFAULT_SETTINGS,
        scanner: ScannerModel = _DEFAULT_SCANNER,
        thin_step: int | None = None,
        estimator: str = "gls",
    ):
        self.site = site
        frame = site.frame(frame)
        rects = site.target_rectangles(frame)
        pts_s = scanner.effective_profile_rate_hz * scanner.effective_points_per_360
        super().__init__(
            plan,
            frame,
            site.mount if mount is None else mount,
            rects,
            tolerances,
            settings,
            thin_step or max(1, int(round(pts_s / 1e5))),
        )
        self.scanner = scanner
        self._centers = np.array([r.center_m for r in rects]).reshape(-1, 3)
        self.obs_model = ObservationModel.from_site(site, estimator)
        #: the site's piles (site.yaml ``piles``): features of the prediction beside the targets
        self.piles = tuple(p.cylinder(frame) for p in site.piles)
        self._pile_returns: dict[int, PassGeometry] = {}
        self._lock = threading.Lock()
        self._candidates: dict[int, tuple[float, PassGeometry]] = {}  # id → (down, geometry)
        self.sigma: SigmaReport | None = None
        self.sigma_history: list[dict] = []
        self._plan_msg = self._plan_dict()

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

    # -- prediction -------------------------------------------------------------------------

    def _track_down_m(self) -> float:
        downs = [
            float(np.median(g.trajectory.p_lgf_m[:, 2]))
            for g in self._accepted.values()
            if g.trajectory is not None
        ]
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
        scanner = replace(self.scanner, point_rate_scale=self.scanner.point_rate_scale / self.thin_step)
        g = predict_pass(
            self.plan.by_id(pid),
            self.scene.rectangles,
            self.mount,
            scanner,
            self.frame,
            track_down_m=track_down_m,
            piles=self.piles,
        )
        self._candidates[pid] = (track_down_m, g)
        return g

    def _with_piles(self, g: PassGeometry) -> PassGeometry:
        """An accepted pass with the returns its own trajectory puts on the site's piles (the
        live hits are the targets': the piles' are predicted, as a candidate's), cached."""
        if not self.piles or len(g) == 0:
            return g
        if g.pass_id not in self._pile_returns:
            scanner = replace(self.scanner, point_rate_scale=self.scanner.point_rate_scale / self.thin_step)
            window = (float(g.t_gps_s[0]), float(g.t_gps_s[-1]))
            on = scanned(
                g.pass_id, g.relative_heading_rad, g.trajectory, (), self.piles, self.mount, scanner, window
            )
            self._pile_returns[g.pass_id] = on
        return g.with_returns(self._pile_returns[g.pass_id], len(self.scene.rectangles))

    def refresh_prediction(self) -> SigmaReport:
        """Predicted σ of the accepted passes and of each remaining pass added to them
        (blocking; safe to run in a worker thread)."""
        with self._lock:
            order = [p.id for p in self.plan.passes]
            accepted = [self._with_piles(self._accepted[i]) for i in order if i in self._accepted]
            remaining = [i for i in order if i not in self._accepted]
            down = self._track_down_m()
            rects: list[Rectangle | VerticalCylinder] = [*self.scene.rectangles, *self.piles]
            current = predict_sigma(accepted, rects, self.mount, self.obs_model, thin_step=self.thin_step)
            cands = {i: self._candidate(i, down) for i in remaining}
            ranking = rank_candidates(
                accepted,
                cands,
                rects,
                self.mount,
                self.obs_model,
                thin_step=self.thin_step,
                gap_s=self.settings.prediction_gap_s,
            )
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
                if (
                    abs(xte[0]) <= self.settings.match_xte_m
                    and abs(herr) <= self.settings.match_heading_rad
                    and -self.settings.approach_m <= along[0] <= line.capture_end_m
                ):
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
            "passes": [
                {
                    "id": p.id,
                    "order": p.order,
                    "heading_deg": round(math.degrees(p.heading_rad), 3),
                    "relative_heading_deg": round(math.degrees(p.relative_heading_rad), 3),
                    "start_ne_m": ne(p.start_lgf_m),
                    "end_ne_m": ne(p.end_lgf_m),
                    "capture_m": [round(p.capture_start_m, 3), round(p.capture_end_m, 3)],
                    "length_m": round(p.length_m, 3),
                    "speed_mps": p.speed_mps,
                    "targets_side": p.targets_side,
                }
                for p in self.plan.passes
            ],
            "targets": [
                {"name": r.name, "center_ne_m": ne(r.center_m), "corners_ne_m": [ne(c) for c in r.corners()]}
                for r in self.scene.rectangles
            ],
        }

    def message(self, checks: Iterable[Check | Mapping[str, Any]] | None = None) -> dict:
        """The ``checklist`` status message (JSON-ready); ``checks``: the prechecks, as
        :class:`Check` or their dicts."""
        latest = self._latest()
        vessel = None
        active = None
        aid = self.active_pass_id()
        if latest is not None:
            sog = float(speed_over_ground(latest[7], latest[8]))
            vessel = self._vessel_dict(latest, sog)
            if aid is not None:
                active = self._active_dict(latest, sog, aid)
        elif aid is not None:
            active = {"pass_id": aid, "state": "approach"}
        passes = self._passes_list()
        sigma = self._sigma_dict()
        check_dicts = [c.as_dict() if isinstance(c, Check) else dict(c) for c in (checks or [])]
        n_acc = sum(r.status == "accepted" for r in self.passes.values())
        return {
            "schema": SCHEMA,
            "vessel_name": self.site.vessel,
            "prechecks": check_dicts,
            "prechecks_ok": bool(check_dicts) and all(c["ok"] for c in check_dicts),
            "plan": self._plan_msg,
            "vessel": vessel,
            "active": active,
            "passes": passes,
            "accepted": n_acc,
            "sigma": sigma,
            "calibration_ready": bool(self.sigma is not None and all(self.sigma.current.observable)),
            "tolerances": self.tol.as_dict(),
            "counters": dict(self.counters),
        }

    def _vessel_dict(self, latest: np.ndarray, sog_mps: float) -> dict:
        """The vessel at the latest navigation sample (a row of the nav columns): position in
        the local frame, heading, speed over ground, and latitude and longitude when known."""
        vessel = {
            "n_m": round(float(latest[1]), 3),
            "e_m": round(float(latest[2]), 3),
            "heading_deg": round(math.degrees(latest[6]), 3),
            "speed_mps": round(sog_mps, 3),
            "t_gps_s": float(latest[0]),
        }
        if self.last_nav is not None:
            vessel["lat_deg"] = self.last_nav.lat_deg
            vessel["lon_deg"] = self.last_nav.lon_deg
        return vessel

    def _active_dict(self, latest: np.ndarray, sog_mps: float, aid: int) -> dict:
        """The active line ``aid`` as the vessel at ``latest`` sees it (offsets, state of the
        capture, the live hits while capturing)."""
        line = self.plan.by_id(aid)
        st = line_state(latest[1:4], float(latest[6]), sog_mps, line, self._centers)
        active = st.as_dict()
        active["state"] = "capture" if self._capture is not None else "approach"
        active["planned_speed_mps"] = line.speed_mps
        active["heading_deg"] = round(math.degrees(line.heading_rad), 3)
        active["capture_m"] = [line.capture_start_m, line.capture_end_m]
        active["length_m"] = round(line.length_m, 3)
        if self._capture is not None:
            active["hits"] = self._hit_counts(self._capture)
        return active

    def _passes_list(self) -> list[dict]:
        """Every planned pass, in the plan's order, with its status and its last verdict."""
        passes = []
        for p in self.plan.passes:
            rec = self.passes[p.id]
            last = rec.verdicts[-1] if rec.verdicts else None
            passes.append(
                {
                    "id": p.id,
                    "order": p.order,
                    "heading_deg": round(math.degrees(p.heading_rad), 3),
                    "relative_heading_deg": round(math.degrees(p.relative_heading_rad), 3),
                    "status": rec.status,
                    "attempts": len(rec.verdicts),
                    "reasons": list(last.reasons) if last else [],
                    "hits": last.stats.get("hits", {}) if last else {},
                    "stats": {k: v for k, v in last.stats.items() if k != "hits"} if last else {},
                }
            )
        return passes

    def _sigma_dict(self) -> dict | None:
        """The σ prediction: the accepted passes', the ranking of the remaining ones and the
        history; None before the first prediction."""
        if self.sigma is None:
            return None
        rank = [
            {
                "pass_id": pid,
                "undetermined": pred.rank_key()[0],
                "worst_deg": pred.as_dict()["worst_deg"],
                "realistic_deg": pred.as_dict()["realistic_deg"],
            }
            for pid, pred in self.sigma.ranking
        ]
        return {
            "current": self.sigma.current_dict(),
            "next_best": rank[0] if rank else None,
            # the angle determined worst and the pass that helps it most
            "weakest": weakest_angle(self.sigma.current, self.sigma.ranking),
            "ranking": rank,
            "history": list(self.sigma_history),
        }
