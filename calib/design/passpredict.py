"""Predicted boresight σ during the survey: which passes so far give what σ, and which next pass
helps most (docs/architecture.md §7 "Design study", §8).

A pass enters the prediction as a :class:`PassGeometry`: a trajectory and the raw observations
(time, range, scan angle) of its returns on the targets. For a pass already sailed these are the
live target hits and the INS trajectory; for a pass still to sail, :func:`predict_pass` sails the
planned line (straight, level, at the planned speed) and scans the targets with the simulator's
exact ray casting (:func:`calib.sim.simulate.scan`). :func:`predict_sigma` then builds the
adjustment's observations with the site's sigmas (and the passes' trajectory epochs: the GLS
knots) and asks :func:`calib.boresight.covariance.predict_covariance` for the boresight
covariance of the calibration's estimator (:attr:`ObservationModel.estimator`):

- ``"gls"`` (default): the GLS estimator, the POS errors as Gauss–Markov processes estimated
  with the boresight. Its covariance is its realistic one (the Cramér–Rao bound of the model),
  and it is the inverse of an information matrix that only grows with each pass: the predicted
  σ of the accepted passes never rises when a pass is added. ``formal`` is still the white
  formal σ (the geometry: the adjustment's observability gate judges that one).
- ``"thesis"``: white weights, realistic σ by propagating the Gauss–Markov POS errors through
  them. That σ can rise after a pass: the white weights give a pass with many points whose
  geometry adds little to an angle the weight to pass its POS bias on to it.

Density. A full-rate profiler puts ~10⁴ points on a target per pass; the prediction keeps every
``k``-th (``thin_step``) and scans candidates at 1/k of the point rate, then corrects to the
full density. The white formal covariance scales as ``1/k`` exactly (``N`` grows with the number
of points). For GLS, ``k`` neighbouring points share their POS errors (the same knots) and
differ in range and scan-angle noise only, so they carry what one point with that white
variance over ``k`` carries: the thinned points' range σ (beam footprint included) and
scan-angle σ are divided by ``√k``.
For the thesis estimator only the white part of the realistic covariance scales,
``C_real(full) ≈ C_real(thin) − (1 − 1/k)·C_formal(thin)`` (the diagonal of the propagated
double sum is ``N`` itself; the correlated pairs keep their weight when the spacing stays well
below the correlation time).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from calib.boresight.covariance import PREDICTION_ESTIMATORS, predict_covariance
from calib.boresight.errormodel import DEFAULT_POS_CORRELATION_S, ErrorModel
from calib.boresight.observations import AdjustmentError, Observations, build_observations
from calib.core import frames
from calib.core.geometry import Rectangle, VerticalCylinder
from calib.core.georef import Mount
from calib.core.trajectory import Trajectory
from calib.io.site import Site
from calib.sim.scenario import ScannerModel
from calib.sim.scene import Scene
from calib.sim.simulate import scan
from calib.survey.passplan import PlannedPass

ANGLES = ("roll", "pitch", "yaw")
#: A boresight angle whose predicted σ exceeds this is "not determined" (the adjustment's own
#: observability limit, :class:`calib.boresight.observations.AdjustOptions`).
DEFAULT_LIMIT_RAD = float(np.radians(0.05))


@dataclass(frozen=True)
class PassGeometry:
    """One pass as the adjustment sees it: trajectory + raw observations of target returns."""

    pass_id: int
    relative_heading_rad: float
    trajectory: Trajectory
    t_gps_s: np.ndarray  # (n,) sorted
    range_m: np.ndarray
    scan_angle_rad: np.ndarray
    target_index: np.ndarray  # (n,) into the target list

    def __len__(self) -> int:
        return int(self.t_gps_s.size)

    @property
    def t_end_gps_s(self) -> float:
        return float(self.trajectory.t_gps_s[-1])

    def shifted(self, dt_s: float) -> PassGeometry:
        """The same pass ``dt_s`` later (for placing a candidate after the passes sailed)."""
        tr = self.trajectory
        moved = Trajectory(
            tr.t_gps_s + dt_s,
            tr.p_lgf_m,
            tr.rpy_rad,
            tr.frame,
            tr.sigma_p_m,
            tr.sigma_rpy_rad,
            tr.max_gap_s,
            tr.name,
        )
        return replace(self, trajectory=moved, t_gps_s=self.t_gps_s + dt_s)

    def thinned(self, step: int) -> PassGeometry:
        """Every ``step``-th point (in time order)."""
        if step <= 1:
            return self
        s = slice(0, None, int(step))
        return replace(
            self,
            t_gps_s=self.t_gps_s[s],
            range_m=self.range_m[s],
            scan_angle_rad=self.scan_angle_rad[s],
            target_index=self.target_index[s],
        )

    def counts(self, n_targets: int) -> np.ndarray:
        return np.bincount(self.target_index, minlength=n_targets)

    def with_returns(self, other: PassGeometry, index_offset: int = 0) -> PassGeometry:
        """This pass with ``other``'s returns added (their feature indices + ``index_offset``),
        in time order."""
        t = np.concatenate([self.t_gps_s, other.t_gps_s])
        order = np.argsort(t, kind="stable")
        cat = lambda a, b: np.concatenate([a, b])[order]  # noqa: E731
        return replace(
            self,
            t_gps_s=t[order],
            range_m=cat(self.range_m, other.range_m),
            scan_angle_rad=cat(self.scan_angle_rad, other.scan_angle_rad),
            target_index=cat(self.target_index, other.target_index + index_offset),
        )


@dataclass(frozen=True)
class ObservationModel:
    """The sigmas, the POS error model and the estimator the prediction assumes (the
    calibration's own: GLS over Gauss–Markov POS errors by default; ``"thesis"`` for the thesis
    estimator's realistic σ)."""

    sigma_range_m: float
    sigma_scan_angle_rad: float
    sigma_position_m: np.ndarray
    sigma_attitude_rad: np.ndarray
    error_model: ErrorModel
    estimator: str = "gls"
    #: range σ growing with range, and the beam divergence (full angle): the GLS adds the beam
    #: footprint at each point's incidence to its range σ, as the calibration does
    sigma_range_per_m: float = 0.0
    beam_divergence_rad: float = 0.0

    def __post_init__(self):
        if self.estimator not in PREDICTION_ESTIMATORS:
            raise AdjustmentError(
                f"estimator {self.estimator!r}: expected one of {', '.join(PREDICTION_ESTIMATORS)}"
            )
        if self.estimator == "gls" and self.error_model.kind != "gauss_markov":
            raise AdjustmentError(
                f"the GLS estimator needs Gauss–Markov POS errors, not {self.error_model.kind!r}"
            )

    @classmethod
    def from_site(cls, site: Site, estimator: str = "gls") -> ObservationModel:
        tau = site.pos_correlation_time_s
        model = ErrorModel(
            "gauss_markov", DEFAULT_POS_CORRELATION_S if tau is None else tuple(float(x) for x in tau)
        )
        return cls(
            site.sigma_range_m,
            site.sigma_scan_angle_rad,
            np.asarray(site.sigma_position_m, float),
            np.asarray(site.sigma_attitude_rad, float),
            model,
            estimator,
            float(site.sigma_range_per_m),
            float(site.beam_divergence_rad),
        )


@dataclass(frozen=True)
class SigmaPrediction:
    """Predicted boresight uncertainty of a set of passes (radians)."""

    pass_ids: tuple[int, ...]
    formal_rad: np.ndarray  # (3,) white formal σ (the geometry); NaN where nothing can be said
    realistic_rad: np.ndarray  # (3,) the estimator's σ (GLS: its covariance, the CRLB)
    correlation: np.ndarray  # (3, 3) GLS: of its covariance; thesis: of the formal one
    n_points: int
    limit_rad: float = DEFAULT_LIMIT_RAD
    note: str = ""

    @property
    def observable(self) -> np.ndarray:
        """(3,) bool: the angle is determined, its formal σ positive and within the limit (the
        adjustment's observability test; the realistic σ is the number to quote)."""
        f = self.formal_rad
        with np.errstate(invalid="ignore"):
            return np.isfinite(f) & (f > 0.0) & (f <= self.limit_rad)

    @property
    def worst_rad(self) -> float:
        """The largest realistic σ; inf while any angle is not determined."""
        if not self.observable.all():
            return np.inf
        return float(np.max(self.realistic_rad))

    def rank_key(self) -> tuple[int, float]:
        """Smaller is better: first the number of undetermined angles, then the largest
        realistic σ among the determined ones (a pass that makes an angle observable beats one
        that only sharpens the others)."""
        ok = self.observable
        return int(np.sum(~ok)), float(np.max(self.realistic_rad[ok])) if ok.any() else np.inf

    def as_dict(self) -> dict:
        """JSON-ready, degrees; an angle beyond the display cap is ``null``."""

        ok = self.observable

        def deg(v):
            return {a: (float(np.degrees(x)) if o else None) for a, x, o in zip(ANGLES, v, ok, strict=False)}

        worst = self.worst_rad
        return {
            "passes": [int(p) for p in self.pass_ids],
            "realistic_deg": deg(self.realistic_rad),  # null: not determined
            "formal_deg": deg(self.formal_rad),
            "observable": {a: bool(o) for a, o in zip(ANGLES, ok, strict=False)},
            "worst_deg": None if not np.isfinite(worst) else float(np.degrees(worst)),
            "limit_deg": float(np.degrees(self.limit_rad)),
            "n_points": int(self.n_points),
            "note": self.note,
        }


def _unknown(pass_ids, n_points, limit_rad, note) -> SigmaPrediction:
    nan = np.full(3, np.nan)
    return SigmaPrediction(
        tuple(pass_ids), nan, nan.copy(), np.full((3, 3), np.nan), n_points, limit_rad, note
    )


# -- candidate passes -------------------------------------------------------------------------


def line_trajectory(
    pp: PlannedPass,
    frame: frames.LocalFrame,
    t_start_gps_s: float,
    track_down_m: float,
    rate_hz: float = 10.0,
) -> Trajectory:
    """A level vessel sailing the whole line at its heading and speed from ``t_start_gps_s``."""
    n = max(int(np.ceil(pp.duration_s * rate_hz)), 1)
    t_rel = np.linspace(0.0, pp.duration_s, n + 1)
    p = pp.position_at(t_rel * pp.speed_mps)
    p[:, 2] = track_down_m
    rpy = np.column_stack([np.zeros(n + 1), np.zeros(n + 1), np.full(n + 1, pp.heading_rad)])
    return Trajectory(t_start_gps_s + t_rel, p, rpy, frame, name=f"planned line {pp.id}")


def predict_pass(
    pp: PlannedPass,
    targets: Sequence[Rectangle],
    mount: Mount,
    scanner: ScannerModel,
    frame: frames.LocalFrame,
    *,
    t_start_gps_s: float = 0.0,
    track_down_m: float | None = None,
    piles: Sequence[VerticalCylinder] = (),
) -> PassGeometry:
    """The noise-free target (and pile) returns of the planned line ``pp`` (capture window
    only), with the scanner mounted as ``mount`` (the a-priori mount: what the survey will see);
    a pile's returns are indexed after the targets' (``len(targets) + k``)."""
    down = float(pp.start_lgf_m[2]) if track_down_m is None else float(track_down_m)
    traj = line_trajectory(pp, frame, t_start_gps_s, down)
    cw0, cw1 = pp.capture_window_s
    guard = abs(mount.time_offset_s) + 1e-3
    t0 = t_start_gps_s + max(cw0, guard)
    t1 = t_start_gps_s + min(cw1, pp.duration_s - guard)
    return scanned(pp.id, pp.relative_heading_rad, traj, targets, piles, mount, scanner, (t0, t1))


def scanned(
    pass_id: int,
    relative_heading_rad: float,
    traj: Trajectory,
    targets: Sequence[Rectangle],
    piles: Sequence[VerticalCylinder],
    mount: Mount,
    scanner: ScannerModel,
    window_gps_s: tuple[float, float],
) -> PassGeometry:
    """The noise-free returns on the targets and piles of a pass sailed along ``traj`` within
    ``window_gps_s``; a pile's as the calibration keeps them (within
    :data:`~calib.boresight.scene_ties.MIN_COS_INCIDENCE_CYLINDER` of head-on)."""
    from calib.boresight.scene_ties import MIN_COS_INCIDENCE_CYLINDER

    kinds = ("target",) * len(targets) + ("other",) * len(piles)
    ret = scan(scanner, Scene(tuple(targets), kinds, (), tuple(piles)), traj, mount, *window_gps_s)
    keep = (ret.surface < len(targets)) | (ret.cos_incidence >= MIN_COS_INCIDENCE_CYLINDER)
    return PassGeometry(
        pass_id,
        relative_heading_rad,
        traj,
        ret.t_gps_s[keep],
        ret.range_true_m[keep] - mount.range_offset_m,
        frames.wrap_2pi(ret.alpha_rad[keep]),
        ret.surface[keep].astype(np.int64),
    )


# -- the prediction ---------------------------------------------------------------------------


def build_pass_observations(
    passes: Sequence[PassGeometry], target_names: Sequence[str], model: ObservationModel
) -> tuple[Observations, list[int]]:
    """The adjustment's observations of ``passes`` and the target indices that have points
    (the planes of the observations, in that order)."""
    n_t = len(target_names)
    counts = sum((p.counts(n_t) for p in passes), np.zeros(n_t, np.int64))
    used = [int(j) for j in np.flatnonzero(counts > 0)]
    remap = np.full(n_t, -1, np.int64)
    remap[used] = np.arange(len(used))
    parts = []
    for p in passes:
        if len(p) == 0:
            continue
        parts.append(
            build_observations(
                p.trajectory,
                p.t_gps_s,
                p.range_m,
                p.scan_angle_rad,
                remap[p.target_index],
                np.full(len(p), p.pass_id),
                [target_names[j] for j in used],
                model.sigma_range_m,
                model.sigma_scan_angle_rad,
                model.sigma_position_m,
                model.sigma_attitude_rad,
                sigma_range_per_m=model.sigma_range_per_m,
                beam_divergence_rad=model.beam_divergence_rad,
            )
        )
    pass_ids = sorted({p.pass_id for p in passes if len(p)})
    traj = joint_trajectory([p.trajectory for p in passes if len(p)])
    cat = lambda name: np.concatenate([getattr(o, name) for o in parts])  # noqa: E731
    pid = np.concatenate([np.full(len(o), o.pass_ids[0]) for o in parts])
    obs = Observations(
        cat("t_gps_s"),
        cat("l"),
        cat("sigma_l"),
        cat("plane_index"),
        np.searchsorted(pass_ids, pid),
        [target_names[j] for j in used],
        pass_ids,
        np.arange(pid.size),
        traj,
        pass_headings_rad={p.pass_id: p.relative_heading_rad for p in passes},
        beam_half_divergence_rad=0.5 * model.beam_divergence_rad,
    )
    return obs, used


def joint_trajectory(trajectories: Sequence[Trajectory]) -> Trajectory | None:
    """The passes' trajectories as one (their epochs are the GLS knots, as in the calibration),
    or None when two of them overlap in time (one vessel cannot sail both; the GLS then puts
    its knots on a uniform grid)."""
    if not trajectories:
        return None
    trs = sorted(trajectories, key=lambda tr: float(tr.t_gps_s[0]))
    if len(trs) == 1:
        return trs[0]
    if any(float(a.t_gps_s[-1]) >= float(b.t_gps_s[0]) for a, b in zip(trs, trs[1:], strict=False)):
        return None
    cat = lambda name: np.concatenate([getattr(tr, name) for tr in trs])  # noqa: E731
    sig = {
        name: cat(name)
        for name in ("sigma_p_m", "sigma_rpy_rad")
        if all(getattr(tr, name) is not None for tr in trs)
    }
    return Trajectory(
        cat("t_gps_s"),
        cat("p_lgf_m"),
        cat("rpy_rad"),
        trs[0].frame,
        max_gap_s=max(tr.max_gap_s for tr in trs),
        name="passes",
        **sig,
    )


def predict_sigma(
    passes: Sequence[PassGeometry],
    targets: Sequence[Rectangle | VerticalCylinder],
    mount: Mount,
    model: ObservationModel,
    *,
    thin_step: int = 1,
    limit_rad: float = DEFAULT_LIMIT_RAD,
) -> SigmaPrediction:
    """Boresight σ that ``passes`` would give (points thinned by ``thin_step``, corrected to the
    full density as the module docstring says); ``targets``: the features their returns index,
    planar targets and piles."""
    ids = tuple(sorted({p.pass_id for p in passes}))
    n = sum(len(p) for p in passes)
    names = [t.name for t in targets]
    with_points = [p for p in passes if len(p)]
    if not with_points:
        return _unknown(ids, 0, limit_rad, "no target points yet")
    obs, used = build_pass_observations(with_points, names, model)
    if len(used) < 2:
        return _unknown(ids, n, limit_rad, "points on fewer than two targets")
    planes = [_feature(targets[j]) for j in used]
    k = max(int(thin_step), 1)
    try:
        with np.errstate(all="ignore"):
            # the thesis estimator's formal covariance is the white one whatever the model
            thesis_model = model.error_model if model.estimator == "thesis" else ErrorModel("white")
            cov = predict_covariance(obs, mount, planes, model=thesis_model, estimator="thesis")
            white = cov["formal"]
            if model.estimator == "gls":
                # k points per kept one: their white noise (range, with the beam footprint,
                # and scan angle) averages down
                full = replace(
                    obs,
                    sigma_l=obs.sigma_l.copy(),
                    beam_half_divergence_rad=obs.beam_half_divergence_rad / np.sqrt(k),
                )
                full.sigma_l[:, 6:8] /= np.sqrt(k)
                cov = predict_covariance(full, mount, planes, model=model.error_model, estimator="gls")
    except (AdjustmentError, np.linalg.LinAlgError, ValueError) as e:
        return _unknown(ids, n, limit_rad, f"no prediction: {e}")
    formal = white / k
    sf = np.sqrt(np.clip(np.diag(formal), 0.0, None))
    if model.estimator == "gls":
        sr = np.sqrt(np.clip(np.diag(cov["realistic"]), 0.0, None))
    else:
        realistic = cov["realistic"] - (1.0 - 1.0 / k) * cov["formal"]
        sr = np.sqrt(np.maximum(np.diag(realistic), np.diag(formal)))
    bad = ~np.isfinite(sf) | ~np.isfinite(sr)
    sf[bad], sr[bad] = np.nan, np.nan
    return SigmaPrediction(ids, sf, sr, cov["correlation"], n, limit_rad)


def _feature(f: Rectangle | VerticalCylinder):
    """A feature as the adjustment takes it: a plane's (normal, d), a cylinder itself."""
    return f if isinstance(f, VerticalCylinder) else (f.normal, f.d)


def rank_candidates(
    accepted: Sequence[PassGeometry],
    candidates: Mapping[int, PassGeometry],
    targets: Sequence[Rectangle | VerticalCylinder],
    mount: Mount,
    model: ObservationModel,
    *,
    thin_step: int = 1,
    gap_s: float = 60.0,
    limit_rad: float = DEFAULT_LIMIT_RAD,
) -> list[tuple[int, SigmaPrediction]]:
    """For each candidate (pass id → its predicted geometry, any start time), the prediction
    with the accepted passes plus that one, sailed ``gap_s`` after the last accepted pass;
    best first (see :meth:`SigmaPrediction.rank_key`)."""
    t_next = max((p.t_end_gps_s for p in accepted), default=0.0) + gap_s
    out = []
    for pid, cand in candidates.items():
        moved = cand.shifted(t_next - float(cand.trajectory.t_gps_s[0]))
        out.append(
            (
                pid,
                predict_sigma(
                    [*accepted, moved], targets, mount, model, thin_step=thin_step, limit_rad=limit_rad
                ),
            )
        )
    out.sort(key=lambda item: (item[1].rank_key(), item[0]))
    return out


def weakest_angle(
    current: SigmaPrediction, ranking: Sequence[tuple[int, SigmaPrediction]]
) -> dict[str, Any] | None:
    """The angle the accepted passes determine worst — one not determined yet, else the largest
    realistic σ (in practice the yaw: a wall seen from one standoff barely observes it) — and the
    remaining pass that sharpens it most (making it determined first, then the smallest σ of
    it); None before any pass. JSON-ready, degrees (``null``: not determined)."""
    if not current.pass_ids:
        return None
    ok = current.observable
    k = int(np.argmin(ok)) if not ok.all() else int(np.argmax(current.realistic_rad))

    def deg(pred: SigmaPrediction) -> float | None:
        return float(np.degrees(pred.realistic_rad[k])) if pred.observable[k] else None

    best = min(
        ranking,
        key=lambda item: (not item[1].observable[k], _nan_inf(item[1].realistic_rad[k]), item[0]),
        default=None,
    )
    return {
        "angle": ANGLES[k],
        "realistic_deg": deg(current),
        "best_pass": None if best is None else int(best[0]),
        "best_deg": None if best is None else deg(best[1]),
    }


def _nan_inf(x: float) -> float:
    return float(x) if np.isfinite(x) else np.inf
