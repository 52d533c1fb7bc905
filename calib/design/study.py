"""Site design study (DESIGN §7 "Design study"; thesis Chapters 3–4 as a tool): which targets,
inclinations, sizes and passes observe the boresight best, before anything is installed.

Two instruments, both driven by the simulator (:func:`calib.sim.simulate.simulate`):

* **Visibility criteria** (thesis §3.4.4, Appendix C; :mod:`calib.design.criteria`): one target per
  inclination, one systematic error injected at the thesis's magnitude, a level vessel and no
  noise; each pass's copy of the target, georeferenced with the error-free mount, is scored
  with Type I and Type II against the true plane.
* **Predicted σ of the boresight** (thesis §4.4.1.2, Fig. 4.12): a noise-free simulation of a
  configuration gives the geometry (true poses, ranges, scan angles); the adjustment's
  covariance is predicted at the truth (:func:`calib.boresight.adjust.predict_covariance`) with the
  scenario's observation sigmas under five models —

  - ``white``: every observation independent (the thesis's implicit model, the formal σ);
  - ``pass_bias``: POS errors constant within a pass and independent between passes (what
    time-correlated INS errors do over a pass of a few seconds), adjusted as the thesis does;
  - ``gauss_markov``: POS errors correlated in time with the trajectory's correlation time
    (first-order Gauss–Markov, across passes too), adjusted as the thesis does;
  - ``…_offsets``: the same errors, adjusted with per-pass trajectory translations
    (``estimate=("pass_offsets",)``, prior from the trajectory's σ).

  The *realistic* σ of a configuration is the better of the two Gauss–Markov predictions, and
  the recommendation minimizes it. The pass-bias model is the Gauss–Markov model's limit of
  an infinite correlation time within a pass; with the INS's real τ (tens of seconds) the POS
  error still drifts by half its σ in the 2–3 s between the moments one pass sees two targets
  a few metres apart, which a layout that relies on the per-pass offsets must survive (a Monte
  Carlo with Gauss–Markov errors confirms the Gauss–Markov prediction, not the pass-bias one).

Sweeps (groups): pass subsets on one vertical plane (``passes``) and on the scenario's own
targets (``site_passes``), single-plane inclination (``inclination``), plane size (``size``),
two- and three-plane combinations (``planes``), standoff (``standoff``), target height
(``height``), and the recommendation search over layouts (``layout``: inclinations, spread
along the wall, height stagger, setback) under a constraint (number of targets, maximum size,
passes allowed). One simulation serves every pass subset of a configuration; configurations
run in parallel processes (``jobs``), each with the same seed, so results do not depend on the
number of processes.

Design scenes hold only the targets (no quay wall or ground: they never enter the adjustment),
record every scan angle (the operator sets the profiler's windows to include the targets) and
carry no noise (the prediction assumes the sigmas). Inclination follows DESIGN: angle to the
horizontal, 90° vertical; a negative inclination tilts the plane the other way (the thesis's
terrestrial sweep, whose own angle is measured from the vertical:
:func:`calib.design.criteria.thesis_tilt_deg`).
"""

from __future__ import annotations

import csv
import itertools
import json
import math
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from calib.core import frames
from calib.boresight.adjust import (DEFAULT_POS_CORRELATION_S, AdjustOptions, ErrorModel, Observations,
                          adjust, build_observations, predict_covariance)  # fmt: skip
from calib.design.criteria import (CRITERIA_COLUMNS, SYSTEMATIC_ERRORS, THESIS_MAGNITUDES,
                            VISIBILITY_COLUMNS, best_inclinations, criteria_rows, injected,
                            is_angular, plot_criteria, summarize)  # fmt: skip
from calib.core.georef import Mount
from calib.boresight.ghmodel import State, linearize
from calib.sim.motion import Wave
from calib.sim.noise import PosNoise, ScannerNoise
from calib.survey.passplan import PassPlanError
from calib.sim.scenario import Scenario, Surface, load_scenario
from calib.sim.simulate import SimResult, SimulationError, simulate
from calib.io.site import Site

ANGLES = ("roll", "pitch", "yaw")
#: Error models of a prediction: white noise; POS errors constant within a pass (pass_bias)
#: or first-order Gauss–Markov with the trajectory's correlation time (gauss_markov), each
#: adjusted as the thesis does or with per-pass trajectory offsets (…_offsets).
MODELS = ("white", "pass_bias", "pass_bias_offsets", "gauss_markov", "gauss_markov_offsets")
#: The realistic σ of a configuration is the better of these (what the design optimizes).
REALISTIC = ("gauss_markov", "gauss_markov_offsets")
GROUPS = ("passes", "site_passes", "inclination", "size", "planes", "standoff", "height", "layout")
#: The estimate of a boresight direction whose formal σ exceeds this is reported unobservable.
UNOBSERVABLE_RAD = float(np.radians(1.0))
_RANGE_SIGMA_FLOOR_M = 1e-4
_CLEARANCE_M = 0.03  # targets stand this far in front of the wall line


class DesignError(ValueError):
    """The design study cannot run with this input (the message says why)."""


# ---------------------------------------------------------------------------------------------
# Observation sigmas and observations
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Sigmas:
    """The observation sigmas a prediction assumes: the scanner's noise model (range σ per
    point from range and incidence), constant POS sigmas and the POS errors' correlation time
    (first-order Gauss–Markov, for the realistic models)."""

    scanner: ScannerNoise
    position_m: np.ndarray  # (3,) north, east, down
    attitude_rad: np.ndarray  # (3,) roll, pitch, heading
    #: per POS channel (north, east, down, roll, pitch, heading)
    correlation_time_s: tuple[float, ...] = (DEFAULT_POS_CORRELATION_S,) * 6

    @classmethod
    def of_scenario(cls, sc: Scenario) -> "Sigmas":
        """The scenario's noise models; where one is off, the site-config defaults (and the
        adjustment's default correlation time unless the POS errors are Gauss–Markov)."""
        dflt = Site(mount=Mount(), targets=())
        s = sc.scanner_noise
        if s.is_zero:
            s = ScannerNoise(sigma_range_m=dflt.sigma_range_m,
                             sigma_scan_angle_rad=dflt.sigma_scan_angle_rad)  # fmt: skip
        p = sc.pos_noise
        on = p.model != "none"
        tau = (tuple(float(x) for x in p.tau) if p.model == "gauss_markov"
               else (DEFAULT_POS_CORRELATION_S,) * 6)  # fmt: skip
        return cls(s,
                   p.sigma_position_m if on and np.all(p.sigma_position_m > 0) else dflt.sigma_position_m,
                   p.sigma_attitude_rad if on and np.all(p.sigma_attitude_rad > 0) else dflt.sigma_attitude_rad,
                   tau)  # fmt: skip

    @classmethod
    def of_site(cls, site: Site) -> "Sigmas":
        return cls(ScannerNoise(sigma_range_m=site.sigma_range_m,
                                sigma_scan_angle_rad=site.sigma_scan_angle_rad),
                   np.asarray(site.sigma_position_m, float),
                   np.asarray(site.sigma_attitude_rad, float),
                   (DEFAULT_POS_CORRELATION_S,) * 6 if site.pos_correlation_time_s is None
                   else tuple(float(x) for x in np.broadcast_to(site.pos_correlation_time_s, 6)))  # fmt: skip


def target_planes(sim: SimResult) -> list[tuple[np.ndarray, float]]:
    """The true (normal, d) of the simulation's targets, in target order."""
    return [(sim.scene.rectangles[i].normal, sim.scene.rectangles[i].d)
            for i in sim.scene.indices("target")]  # fmt: skip


def observations(sim: SimResult, sigmas: Sigmas, noisy: bool = True) -> Observations:
    """The adjustment's observations of the simulation's target returns.

    ``noisy``: the observed trajectory (with the ``per_point`` POS errors where simulated), as
    a calibration sees it; otherwise the true poses (the geometry a prediction linearizes at).
    Sigmas come from ``sigmas`` either way (range σ per point from the range and the incidence),
    so a prediction and an adjustment of the same configuration weight alike.
    """
    sel = np.flatnonzero(sim.target_index >= 0)
    if sel.size == 0:
        raise DesignError(f"scenario {sim.scenario.name!r}: no return on any target")
    p = sim.points
    names = [t.name for t in sim.site.targets]
    obs = build_observations(
        sim.trajectory_observed if noisy else sim.trajectory_true, p.t_gps_s[sel], p.range_m[sel],
        p.scan_angle_rad[sel], sim.target_index[sel], p.pass_id[sel], names,
        sigmas.scanner.sigma_range_m, sigmas.scanner.sigma_scan_angle_rad, sigmas.position_m,
        sigmas.attitude_rad, point_ids=sel,
        pass_headings_rad={q.id: q.relative_heading_rad for q in sim.plan.passes},
    )  # fmt: skip
    if noisy and sim.pose_errors is not None:
        poses = sim.observed_poses()
        obs.l[:, 0:3] = poses.p_lgf_m[sel]
        obs.l[:, 3:6] = poses.rpy_rad[sel]
    obs.sigma_l[:, 0:3] = sigmas.position_m
    obs.sigma_l[:, 3:6] = sigmas.attitude_rad
    cos_incidence = p.intensity[sel] / sim.scene.reflectivity[sim.surface_index[sel]]
    obs.sigma_l[:, 6] = np.maximum(sigmas.scanner.range_sigma(p.range_m[sel], cos_incidence),
                                   _RANGE_SIGMA_FLOOR_M)  # fmt: skip
    return obs


def select_passes(obs: Observations, planes: list, pass_ids: Sequence[int]
                  ) -> tuple[Observations, list]:  # fmt: skip
    """The observations of the given passes, re-indexed; planes without points are dropped."""
    keep = np.isin(np.asarray(obs.pass_ids)[obs.pass_index], list(pass_ids))
    sub = obs.select(keep)
    used_passes = np.unique(sub.pass_index)
    sub.pass_index = np.searchsorted(used_passes, sub.pass_index)
    sub.pass_ids = [obs.pass_ids[i] for i in used_passes]
    used_planes = np.unique(sub.plane_index)
    sub.plane_index = np.searchsorted(used_planes, sub.plane_index)
    sub.plane_names = [obs.plane_names[i] for i in used_planes]
    return sub, [planes[i] for i in used_planes]


# ---------------------------------------------------------------------------------------------
# Prediction
# ---------------------------------------------------------------------------------------------


def reduced_information(obs: Observations, mount: Mount, planes, extras: Sequence[str] = ()
                        ) -> np.ndarray:  # fmt: skip
    """White-noise information of the boresight (and ``extras``, columns of
    :func:`calib.boresight.ghmodel.linearize`) with the planes' parameters eliminated (Schur complement),
    linearized at the truth: its inverse is the formal covariance, its eigenvalues say what is
    observable."""
    r_nom = frames.rotation_zyx(*mount.nominal_rad)
    m = len(planes)
    normals = np.array([np.asarray(n, float) / np.linalg.norm(n) for n, _ in planes])
    d_lgf = np.array([float(d) / np.linalg.norm(n) for n, d in planes])

    def state(centers):
        return State(np.asarray(mount.boresight_rad, float).copy(), normals,
                     d_lgf + np.einsum("ij,ij->i", normals, centers), centers,
                     np.zeros((len(obs.pass_ids), 3)), np.asarray(mount.lever_arm_m, float).copy(),
                     mount.range_offset_m, mount.scan_angle_offset_rad, mount.time_offset_s)  # fmt: skip

    x = linearize(state(np.zeros((m, 3))), r_nom, obs.plane_index, obs.pass_index, obs.l).x_lgf_m
    cnt = np.maximum(np.bincount(obs.plane_index, minlength=m), 1)[:, None]
    centers = np.stack([np.bincount(obs.plane_index, x[:, c], minlength=m) for c in range(3)], 1)
    lin = linearize(state(centers / cnt), r_nom, obs.plane_index, obs.pass_index, obs.l)
    w = 1.0 / np.sqrt(np.einsum("ij,ij->i", lin.B**2, obs.sigma_l**2))
    X = np.column_stack([lin.A_boresight] + [lin.A_extra[e] for e in extras]) * w[:, None]
    P = lin.A_plane * w[:, None]
    S = X.T @ X
    for j in range(m):
        rows = obs.plane_index == j
        Xj, Pj = X[rows], P[rows]
        S -= Xj.T @ Pj @ np.linalg.lstsq(Pj.T @ Pj, Pj.T @ Xj, rcond=None)[0]
    return 0.5 * (S + S.T)


def scan_angle_roll_correlation(obs: Observations, mount: Mount, planes) -> float:
    """|ρ| between the boresight roll and a scan-angle offset estimated together with the
    boresight pitch and yaw and the planes (1 when the two are the same rotation, as they are
    for a profiler: a scan-angle offset is a rotation about the scanner's x axis)."""
    S = reduced_information(obs, mount, planes, ("scan_angle_offset",))
    keep, other = [0, 3], [1, 2]
    S2 = S[np.ix_(keep, keep)] - S[np.ix_(keep, other)] @ np.linalg.lstsq(
        S[np.ix_(other, other)], S[np.ix_(other, keep)], rcond=None)[0]  # fmt: skip
    return float(min(abs(S2[0, 1]) / np.sqrt(S2[0, 0] * S2[1, 1]), 1.0))


@dataclass(frozen=True)
class Prediction:
    """Predicted boresight covariance (rad²) of one configuration under each model."""

    n_points: int
    n_planes: int
    n_passes: int
    observable: bool
    covariances: dict  # model → (3, 3)

    def sigma_deg(self, model: str) -> np.ndarray:
        """σ per angle; inf when unobservable, NaN for a model not predicted."""
        if not self.observable:
            return np.full(3, np.inf)
        if model not in self.covariances:
            return np.full(3, np.nan)
        return np.degrees(np.sqrt(np.diag(self.covariances[model])))

    def total_deg(self, model: str) -> float:
        """√(σ_roll² + σ_pitch² + σ_yaw²): the size of the rotation error."""
        return float(np.sqrt(np.sum(self.sigma_deg(model) ** 2)))

    def correlation(self, model: str) -> np.ndarray:
        if not self.observable or model not in self.covariances:
            return np.full((3, 3), np.nan)
        c = self.covariances[model]
        s = np.sqrt(np.diag(c))
        return c / np.outer(s, s)

    @property
    def realistic_model(self) -> str:
        """The better adjustment under Gauss–Markov POS errors: with or without per-pass
        offsets."""
        return min(REALISTIC, key=self.total_deg)


def predict(obs: Observations, mount: Mount, planes,
            correlation_time_s: float | Sequence[float] = DEFAULT_POS_CORRELATION_S,
            models: Sequence[str] = MODELS) -> Prediction:  # fmt: skip
    """Predicted covariance of the boresight from noise-free ``obs`` at the true ``mount`` and
    ``planes`` under ``models`` (of :data:`MODELS`; Gauss–Markov with ``correlation_time_s``,
    one value or six for north, east, down, roll, pitch, heading)."""
    n = len(obs)
    counts = dict(n_points=n, n_planes=len(planes), n_passes=len(obs.pass_ids))
    if n == 0 or not planes:
        return Prediction(**counts, observable=False, covariances={})
    info = reduced_information(obs, mount, planes)
    ev = np.linalg.eigvalsh(info)
    if not ev[0] > 0 or 1.0 / np.sqrt(ev[0]) > UNOBSERVABLE_RAD:
        return Prediction(**counts, observable=False, covariances={})
    covs = {}
    for model in models:
        if model == "white":  # = predict_covariance(...)["formal"], without a second pass
            covs[model] = np.linalg.inv(info)
            continue
        if model not in MODELS:
            raise DesignError(f"unknown error model {model!r}; expected one of {', '.join(MODELS)}")
        est = ("pass_offsets",) if model.endswith("_offsets") else ()
        em = (ErrorModel("pass_bias") if model.startswith("pass_bias")
              else ErrorModel("gauss_markov", tuple(np.atleast_1d(correlation_time_s))))  # fmt: skip
        covs[model] = predict_covariance(obs, mount, planes, est, em)["realistic"]
    return Prediction(**counts, observable=True, covariances=covs)


# ---------------------------------------------------------------------------------------------
# Design scenes
# ---------------------------------------------------------------------------------------------


def internal_inclination(inclination_rad: float) -> float:
    """A negative inclination (tilted the other way) as the same plane with its normal flipped
    toward the water: π − |i|, so that the passes stay on the water side."""
    return float(inclination_rad if inclination_rad >= 0 else np.pi + inclination_rad)


def _ground_top(base: Scenario) -> float | None:
    ups = [s.up_m for s in base.surfaces if s.kind == "ground"]
    return max(ups) if ups else None


def _targets(base: Scenario) -> list[Surface]:
    out = [s for s in base.surfaces if s.kind == "target"]
    if not out:
        raise DesignError(f"scenario {base.name!r} has no target")
    return out


def target(base: Scenario, name: str, inclination_rad: float, width_m: float, height_m: float,
           along_m: float = 0.0, raise_m: float = 0.0, setback_m: float = 0.0) -> Surface:
    """A target for a design scene of ``base``: on a ground-based site (one with a ground
    surface) it stands on the ground, else its centre is at the mean height of ``base``'s
    targets; ``raise_m`` lifts it, ``setback_m`` moves it back from the wall line (away from
    the passes)."""
    i = internal_inclination(inclination_rad)
    ground = _ground_top(base)
    if ground is not None:
        up = ground + 0.5 * height_m * abs(np.sin(i)) + 0.05
    else:
        up = float(np.mean([s.up_m for s in _targets(base)]))
    out = 0.5 * height_m * abs(np.cos(i)) + _CLEARANCE_M - setback_m
    return Surface(name, "target", float(along_m), float(out), float(up + raise_m), float(width_m),
                   float(height_m), float(i), 0.0, 0.9)  # fmt: skip


def design_scenario(base: Scenario, targets: Sequence[Surface], *, standoff_m: float | None = None,
                    level: bool = False, truth=None) -> Scenario:  # fmt: skip
    """``base`` with only ``targets`` in the scene, no noise, every scan angle recorded;
    ``level`` stills the waves (the thesis's criteria isolate the error); ``truth`` replaces
    the injected errors."""
    motion = base.motion
    if level:
        motion = replace(motion, roll=Wave(), pitch=Wave(), heave=Wave(), yaw=Wave())
    return replace(base, surfaces=tuple(targets), scanner_noise=ScannerNoise(),
                   pos_noise=PosNoise("none"), motion=motion,
                   scanner=replace(base.scanner, angular_windows_rad=()),
                   standoff_m=base.standoff_m if standoff_m is None else float(standoff_m),
                   truth=base.truth if truth is None else truth)  # fmt: skip


def site_scenario(base: Scenario, targets: Sequence[Surface]) -> Scenario:
    """``base`` (its noise, motion, passes) with only ``targets`` in the scene and every scan
    angle recorded: a planned site to simulate with noise."""
    return replace(base, surfaces=tuple(targets),
                   scanner=replace(base.scanner, angular_windows_rad=()))  # fmt: skip


def prepare(scenario: Scenario, sigmas: Sigmas, seed: int = 0):
    """Simulate a (noise-free) scenario: returns (simulation, noise-free observations of its
    targets, true planes)."""
    sim = simulate(scenario, seed)
    return sim, observations(sim, sigmas, noisy=False), target_planes(sim)


# ---------------------------------------------------------------------------------------------
# The study's specification
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Constraint:
    """What the recommended site may use."""

    n_targets: int
    max_size_m: float
    passes: tuple[int, ...]

    def __post_init__(self):
        if self.n_targets < 1:
            raise DesignError(f"constraint: n_targets is {self.n_targets}, expected ≥ 1")
        if not self.max_size_m > 0:
            raise DesignError(f"constraint: max_size_m is {self.max_size_m}, expected > 0")
        if not self.passes:
            raise DesignError("constraint: at least one pass must be allowed")


@dataclass(frozen=True)
class StudySpec:
    """What the study computes (degrees and metres, as in its tables). :func:`default_spec`
    fills it from the scenario."""

    constraint: Constraint
    seed: int = 0
    groups: tuple[str, ...] = GROUPS
    errors: tuple[str, ...] = SYSTEMATIC_ERRORS
    magnitudes: dict = field(default_factory=lambda: dict(THESIS_MAGNITUDES))  # rad or m
    criteria_inclinations_deg: tuple[float, ...] = tuple(range(0, 91, 10))
    criteria_size_m: float = 1.0
    type1_threshold: float = 0.3  # raw selection on the mean Type I of an inclination
    plane_size_m: float = 1.0
    inclinations_deg: tuple[float, ...] = tuple(range(0, 91, 15))
    sizes_m: tuple[float, ...] = (0.25, 0.5, 0.75, 1.0)
    combo_inclinations_deg: tuple[float, ...] = tuple(range(0, 91, 15))
    spacing_m: float = 3.5
    standoffs_m: tuple[float, ...] = (10.0, 15.0, 20.0, 25.0, 30.0)
    height_shifts_m: tuple[float, ...] = (-4.0, -2.0, 0.0, 2.0, 4.0)
    layout_inclinations_deg: tuple[float, ...] = (90.0, 60.0, 45.0, 30.0)
    layout_spreads_m: tuple[float, ...] = (0.0, 3.5)  # 0: one above the other
    layout_staggers_m: tuple[float, ...] = (0.0, 4.0)
    layout_setbacks_m: tuple[float, ...] = (0.0, 6.0)

    def __post_init__(self):
        bad = [g for g in self.groups if g not in GROUPS]
        if bad:
            raise DesignError(f"unknown study group(s) {', '.join(bad)}; expected "
                              f"{', '.join(GROUPS)}")  # fmt: skip
        bad = [e for e in self.errors if e not in SYSTEMATIC_ERRORS]
        if bad:
            raise DesignError(f"unknown systematic error(s) {', '.join(bad)}")


def ground_based(base: Scenario) -> bool:
    return _ground_top(base) is not None


def default_spec(base: Scenario, **changes) -> StudySpec:
    """The study of ``base``: the thesis's sweeps scaled to its geometry; the constraint is its
    own site (number of targets, largest target dimension, all passes). ``changes`` override
    fields (``n_targets``, ``max_size_m`` and ``passes`` go to the constraint)."""
    tg = _targets(base)
    cons = {"n_targets": len(tg), "max_size_m": max(max(s.width_m, s.height_m) for s in tg),
            "passes": tuple(p.id for p in base.passes)}  # fmt: skip
    for k in list(cons):
        v = changes.pop(k, None)
        if v is not None:
            cons[k] = tuple(int(x) for x in v) if k == "passes" else v
    unknown = sorted(set(cons["passes"]) - {p.id for p in base.passes})
    if unknown:
        raise DesignError(f"constraint: pass(es) {', '.join(map(str, unknown))} are not in "
                          f"scenario {base.name!r} (passes "
                          f"{', '.join(str(p.id) for p in base.passes)})")  # fmt: skip
    along = sorted(s.along_m for s in tg)
    spacing = (along[-1] - along[0]) / (len(along) - 1) if len(along) > 1 else 3.5
    S = base.standoff_m
    kw: dict = dict(spacing_m=max(spacing, 2.5),
                    layout_spreads_m=(0.0, max(spacing, 2.5)),
                    layout_setbacks_m=(0.0, round(0.4 * S, 1)),
                    standoffs_m=tuple(round(S * f, 1) for f in (2 / 3, 1.0, 4 / 3, 5 / 3, 2.0)))  # fmt: skip
    if ground_based(base):  # targets on the ground: the thesis's Chapter 3 sweep, raised stands
        kw.update(criteria_inclinations_deg=tuple(range(-90, 91, 10)),
                  inclinations_deg=tuple(range(-75, 91, 15)),  # vertical once
                  height_shifts_m=(0.0, 0.5, 1.0, 1.5, 2.0),
                  layout_staggers_m=(0.0, round(0.25 * S, 1)))  # fmt: skip
    else:
        kw.update(layout_staggers_m=(0.0, round(0.25 * S, 1)),
                  height_shifts_m=tuple(round(f * S, 1) for f in (-0.25, -0.125, 0.0, 0.125, 0.25)))
    kw.update(changes)
    return StudySpec(constraint=Constraint(**cons), **kw)


# ---------------------------------------------------------------------------------------------
# Configurations
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Layout:
    """One configuration of targets (site-frame surfaces) and the pass subsets to predict."""

    group: str
    label: str
    targets: tuple[Surface, ...]
    standoff_m: float
    pass_subsets: tuple[tuple[int, ...], ...]
    params: dict = field(default_factory=dict)  # spread_m, stagger_m, setback_m, height_m


def _square(base, name, incl_deg, size, along=0.0, raise_m=0.0, setback=0.0) -> Surface:
    return target(base, name, np.radians(incl_deg), size, size, along, raise_m, setback)


def _row_positions(n: int, spacing: float) -> list[float]:
    return [(j - (n - 1) / 2) * spacing for j in range(n)]


def layouts(base: Scenario, spec: StudySpec) -> list[Layout]:
    """All configurations of the study, group by group."""
    all_passes = tuple(p.id for p in base.passes)
    every = (all_passes,)
    subsets = tuple(c for k in range(1, len(all_passes) + 1)
                    for c in itertools.combinations(all_passes, k))  # fmt: skip
    S, size = base.standoff_m, spec.plane_size_m
    own = tuple(_targets(base))
    out: list[Layout] = []
    for g in spec.groups:
        if g == "passes":
            out.append(Layout(g, f"vertical {size:g} m", (_square(base, "P", 90.0, size),), S,
                              subsets))  # fmt: skip
        elif g == "site_passes":
            out.append(Layout(g, base.name, own, S, subsets))
        elif g == "inclination":
            out += [Layout(g, f"{i:g}°", (_square(base, "P", i, size),), S, every)
                    for i in spec.inclinations_deg]  # fmt: skip
        elif g == "size":
            out += [Layout(g, f"{s:g} m", (_square(base, "P", 90.0, s),), S, every)
                    for s in spec.sizes_m]  # fmt: skip
        elif g == "planes":
            incs = sorted(set(spec.combo_inclinations_deg), reverse=True)
            for k in (2, 3):
                for combo in itertools.combinations(incs, k):
                    tg = tuple(_square(base, f"P{j + 1}", inc, size, x)
                               for j, (inc, x) in enumerate(zip(combo, _row_positions(k, spec.spacing_m))))
                    out.append(Layout(g, "/".join(f"{c:g}" for c in combo), tg, S, every))
        elif g == "standoff":
            out += [Layout(g, f"{s:g} m", own, s, every) for s in spec.standoffs_m]
        elif g == "height":
            h0 = float(np.mean([t.up_m for t in own]))
            for dh in spec.height_shifts_m:
                tg = tuple(replace(t, up_m=t.up_m + dh) for t in own)
                out.append(Layout(g, f"{h0 + dh:.2f} m", tg, S, every, {"height_m": h0 + dh}))
        elif g == "layout":
            out += _layout_candidates(base, spec)
    return out


def _overlap(targets: Sequence[Surface], size_m: float) -> bool:
    """Whether two targets of a layout would intersect (their centres closer than the size,
    with a 0.2 m gap, along the wall and in height, at the same setback)."""
    for a, b in itertools.combinations(targets, 2):
        if (abs(a.along_m - b.along_m) < size_m + 0.2 and abs(a.up_m - b.up_m) < size_m + 0.2
                and abs(a.out_m - b.out_m) < size_m):  # fmt: skip
            return True
    return False


def _layout_candidates(base: Scenario, spec: StudySpec) -> list[Layout]:
    """The recommendation's search space: inclinations (every assignment for ≤ 2 targets,
    combinations for more), spread along the wall (0: stacked), height stagger (odd targets
    raised) and setback (odd targets moved back), at the constraint's size and passes; layouts
    whose targets would overlap are left out."""
    c = spec.constraint
    n, size = c.n_targets, c.max_size_m
    incs = spec.layout_inclinations_deg
    combos = (itertools.product(incs, repeat=n) if n <= 2
              else itertools.combinations_with_replacement(incs, n))  # fmt: skip
    ground = ground_based(base)
    out = []
    for combo in combos:
        for spread, stagger, setback in itertools.product(
                spec.layout_spreads_m if n > 1 else (0.0,),
                spec.layout_staggers_m if n > 1 else (0.0,),
                spec.layout_setbacks_m if n > 1 else (0.0,)):  # fmt: skip
            tg = []
            for j, (inc, x) in enumerate(zip(combo, _row_positions(n, spread / max(n - 1, 1)))):
                high = j % 2 == 1
                lift = (stagger if high else 0.0) if ground else (stagger / 2 if high else -stagger / 2)
                tg.append(_square(base, f"T{j + 1}", inc, size, x, lift, setback if high else 0.0))
            if _overlap(tg, size):
                continue
            label = ("/".join(f"{i:g}" for i in combo)
                     + f" spread {spread:g} stagger {stagger:g} setback {setback:g}")  # fmt: skip
            out.append(Layout("layout", label, tuple(tg), base.standoff_m, (c.passes,),
                              {"spread_m": spread, "stagger_m": stagger, "setback_m": setback}))
    return out


# ---------------------------------------------------------------------------------------------
# Tasks (run in worker processes)
# ---------------------------------------------------------------------------------------------

SIGMA_COLUMNS = (
    ["scenario", "group", "label", "n_targets", "inclinations_deg", "sizes_m", "standoff_m",
     "height_m", "spread_m", "stagger_m", "setback_m", "passes", "headings_deg", "n_points",
     "observable", "correlation_time_s"]
    + [f"sigma_{m}_{a}_deg" for m in MODELS for a in ANGLES + ("total",)]
    + ["realistic_total_deg", "estimator"]
    + [f"corr_{m}_{a}_{b}" for m in ("white", "realistic")
       for a, b in (("roll", "pitch"), ("roll", "yaw"), ("pitch", "yaw"))]
    + ["note"]
)  # fmt: skip


def _surface_inclination_deg(s: Surface) -> float:
    d = float(np.degrees(s.inclination_rad))
    return d - 180.0 if d > 90.0 + 1e-9 else d


def sigma_row(scenario: str, layout: Layout, pred: Prediction | None, subset: Sequence[int],
              headings: dict, correlation_time_s: float | Sequence[float],
              note: str = "") -> dict:  # fmt: skip
    """One line of ``sigma.csv``."""
    tg = layout.targets
    row = {
        "scenario": scenario, "group": layout.group, "label": layout.label,
        "n_targets": len(tg),
        "inclinations_deg": tuple(round(_surface_inclination_deg(s), 6) for s in tg),
        "sizes_m": tuple((s.width_m, s.height_m) for s in tg),
        "standoff_m": layout.standoff_m,
        "height_m": layout.params.get("height_m", float(np.mean([s.up_m for s in tg]))),
        "spread_m": layout.params.get("spread_m", float(np.ptp([s.along_m for s in tg]))),
        "stagger_m": layout.params.get("stagger_m", float(np.ptp([s.up_m for s in tg]))),
        "setback_m": layout.params.get("setback_m", 0.0),
        "passes": tuple(int(p) for p in subset),
        "headings_deg": tuple(round(headings.get(p, float("nan")), 3) for p in subset),
        "n_points": 0 if pred is None else pred.n_points,
        "observable": bool(pred is not None and pred.observable),
        "correlation_time_s": tuple(float(x) for x in np.atleast_1d(correlation_time_s)),
        "note": note,
    }  # fmt: skip
    for m in MODELS:
        s = np.full(3, np.inf) if pred is None or not pred.observable else pred.sigma_deg(m)
        for a, v in zip(ANGLES, s):
            row[f"sigma_{m}_{a}_deg"] = float(v)
        row[f"sigma_{m}_total_deg"] = float(np.sqrt(np.sum(s**2)))
    ok = pred is not None and pred.observable
    real = pred.realistic_model if ok else REALISTIC[0]
    row["realistic_total_deg"] = row[f"sigma_{real}_total_deg"]
    row["estimator"] = ("pass_offsets" if real.endswith("_offsets") else "none") if ok else ""
    for name, m in (("white", "white"), ("realistic", real)):
        c = pred.correlation(m) if ok else np.full((3, 3), np.nan)
        for (a, b), v in zip((("roll", "pitch"), ("roll", "yaw"), ("pitch", "yaw")),
                             (c[0, 1], c[0, 2], c[1, 2])):  # fmt: skip
            row[f"corr_{name}_{a}_{b}"] = float(v)
    return row


def _headings(base: Scenario) -> dict:
    return {p.id: float(np.degrees(p.relative_heading_rad)) % 360.0 for p in base.passes}


#: The recommendation's search predicts only these (the winner gets every model).
_SEARCH_MODELS = ("white",) + REALISTIC


def _sigma_task(base: Scenario, layout: Layout, sigmas: Sigmas, seed: int,
                models: Sequence[str] = MODELS) -> list[dict]:  # fmt: skip
    sc = design_scenario(base, layout.targets, standoff_m=layout.standoff_m)
    headings, tau = _headings(base), sigmas.correlation_time_s
    try:
        sim, obs, planes = prepare(sc, sigmas, seed)
    except (PassPlanError, SimulationError, DesignError) as e:
        return [sigma_row(base.name, layout, None, s, headings, tau, str(e))
                for s in layout.pass_subsets]  # fmt: skip
    rows = []
    for subset in layout.pass_subsets:
        o, p = select_passes(obs, planes, subset)
        rows.append(sigma_row(base.name, layout, predict(o, sim.mount_true, p, tau, models),
                              subset, headings, tau))  # fmt: skip
    return rows


def _criteria_task(base: Scenario, error: str, magnitude: float, inclination_deg: float,
                   size_m: float, seed: int) -> list[dict]:  # fmt: skip
    """One target at one inclination, one error injected, a level vessel, no noise."""
    tg = _square(base, "P", inclination_deg, size_m)
    sc = design_scenario(base, [tg], level=True,
                         truth=injected(error, magnitude, base.mount.boresight_rad))  # fmt: skip
    return criteria_rows(simulate(sc, seed), error, magnitude, inclination_deg)


def _run(tasks: list[tuple[Callable, tuple]], jobs: int,
         progress: Callable[[int, int], None] | None) -> list:  # fmt: skip
    """Run ``func(*args)`` for every task, in ``jobs`` processes; results in task order."""
    n = len(tasks)
    out: list = [None] * n
    if jobs <= 1 or n <= 1:
        for i, (f, args) in enumerate(tasks):
            out[i] = f(*args)
            if progress is not None:
                progress(i + 1, n)
        return out
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor, as_completed

    # fork: workers inherit the imported modules and need no ``__main__`` guard in the caller
    methods = multiprocessing.get_all_start_methods()
    ctx = multiprocessing.get_context("fork" if "fork" in methods else None)
    with ProcessPoolExecutor(max_workers=jobs, mp_context=ctx) as ex:
        futures = {ex.submit(f, *args): i for i, (f, args) in enumerate(tasks)}
        for done, fut in enumerate(as_completed(futures), start=1):
            out[futures[fut]] = fut.result()
            if progress is not None:
                progress(done, n)
    return out


# ---------------------------------------------------------------------------------------------
# The study
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Recommendation:
    """The best layout under the constraint, and the scenario's own site beside it."""

    constraint: Constraint
    layout: Layout
    row: dict  # its line of sigma.csv
    baseline_row: dict | None  # the scenario's own targets on the same passes

    @property
    def estimator(self) -> tuple[str, ...]:
        """The adjustment options to use (``estimate=``)."""
        return ("pass_offsets",) if self.row["estimator"] == "pass_offsets" else ()


def recommend(rows: Sequence[dict], layouts_: Sequence[Layout], constraint: Constraint,
              baseline_rows: Sequence[dict] = ()) -> Recommendation:  # fmt: skip
    """The ``layout`` row with the smallest realistic σ (ties: the smaller white σ)."""
    cands = [(r, lay) for r, lay in zip(rows, layouts_) if r["group"] == "layout" and r["observable"]]
    if not cands:
        raise DesignError("no observable layout satisfies the constraint "
                          f"({constraint.n_targets} targets ≤ {constraint.max_size_m:g} m, passes "
                          f"{', '.join(map(str, constraint.passes))})")  # fmt: skip
    row, lay = min(cands, key=lambda c: (c[0]["realistic_total_deg"], c[0]["sigma_white_total_deg"]))
    base = [r for r in baseline_rows if tuple(sorted(r["passes"])) == tuple(sorted(constraint.passes))]
    return Recommendation(constraint, lay, row, base[0] if base else None)


@dataclass
class StudyResult:
    scenario: Scenario
    spec: StudySpec
    sigmas: Sigmas
    criteria: list[dict]  # per error × inclination × pass
    visibility: list[dict]  # per error × inclination
    sigma: list[dict]  # per configuration × pass subset
    layouts: list[Layout]  # sigma[i] belongs to layouts[layout_of_row[i]]
    layout_of_row: list[int]
    roll_scan_correlation: float  # |ρ| at the scenario's own site
    recommendation: Recommendation | None
    runtime_s: float

    def rows(self, group: str) -> list[dict]:
        return [r for r in self.sigma if r["group"] == group]


def run_study(scenario: Scenario | str, spec: StudySpec | None = None, *, jobs: int = 1,
              progress: Callable[[int, int], None] | None = None) -> StudyResult:  # fmt: skip
    """The whole study of a scenario (a :class:`Scenario` or a shipped name / YAML path)."""
    t0 = time.perf_counter()
    base = scenario if isinstance(scenario, Scenario) else load_scenario(scenario)
    spec = spec or default_spec(base)
    sigmas = Sigmas.of_scenario(base)
    lays = layouts(base, spec)
    tasks: list[tuple[Callable, tuple]] = [
        (_criteria_task, (base, e, spec.magnitudes[e], inc, spec.criteria_size_m, spec.seed))
        for e in spec.errors for inc in spec.criteria_inclinations_deg
    ]  # fmt: skip
    n_crit = len(tasks)
    tasks += [(_sigma_task, (base, lay, sigmas, spec.seed,
                             _SEARCH_MODELS if lay.group == "layout" else MODELS)) for lay in lays]
    results = _run(tasks, jobs, progress)
    criteria = [r for part in results[:n_crit] for r in part]
    visibility = summarize(criteria)
    sigma, owner = [], []
    for k, part in enumerate(results[n_crit:]):
        sigma += part
        owner += [k] * len(part)
    # |ρ(roll, scan-angle offset)| on the scenario's own targets
    sim, obs, planes = prepare(design_scenario(base, _targets(base)), sigmas, spec.seed)
    rho = scan_angle_roll_correlation(obs, sim.mount_true, planes)
    rec = None
    if "layout" in spec.groups:
        rec = recommend(sigma, [lays[k] for k in owner], spec.constraint,
                        [r for r in sigma if r["group"] == "site_passes"])  # fmt: skip
        # the winner with every model
        full = _sigma_task(base, rec.layout, sigmas, spec.seed)[0]
        sigma[next(i for i, r in enumerate(sigma) if r is rec.row)] = full
        rec = replace(rec, row=full)
    return StudyResult(base, spec, sigmas, criteria, visibility, sigma, lays, owner, rho, rec,
                       time.perf_counter() - t0)


# ---------------------------------------------------------------------------------------------
# Site what-if (``mls design --site``)
# ---------------------------------------------------------------------------------------------


def site_as_scenario(site: Site, template: Scenario | str = "montreal",
                     scanner_height_m: float | None = None) -> Scenario:  # fmt: skip
    """A site config as a design scenario: its targets, wall azimuth, standoff, passes, mount
    and sigmas; the profiler, the motion and the noise models' kinds from ``template``. The
    vessel's scanner sails at ``scanner_height_m`` (ellipsoidal; default: the reference
    height)."""
    tpl = template if isinstance(template, Scenario) else load_scenario(template)
    if site.reference is None:
        raise DesignError("the site config has no 'reference': the what-if needs the LGF origin "
                          "(and, by default, the scanner's height) from it")  # fmt: skip
    if not site.targets:
        raise DesignError("the site config has no targets")
    ref = site.reference
    h = ref.height_m if scanner_height_m is None else float(scanner_height_m)
    frame = frames.LocalFrame(ref.lat_deg, ref.lon_deg, h)
    wall = site.wall_azimuth_rad
    water = wall - np.pi / 2
    surfaces = []
    for t in site.targets:
        c = t.rectangle(frame).center_m
        surfaces.append(Surface(
            t.name, "target", float(c[0] * np.cos(wall) + c[1] * np.sin(wall)),
            float(c[0] * np.cos(water) + c[1] * np.sin(water)), float(-c[2]), t.width_m,
            t.height_along_slope_m, t.inclination_rad,
            float(frames.wrap_pi(t.facing_azimuth_rad - water)), t.reflectivity))  # fmt: skip
    tau = Sigmas.of_site(site).correlation_time_s
    pos = PosNoise("gauss_markov", site.sigma_position_m, site.sigma_attitude_rad, tau[0:3], tau[3:6])
    return replace(
        tpl, name="site", description="site config what-if", reference=frame,
        wall_azimuth_rad=float(wall), standoff_m=float(site.standoff_m), passes=site.passes,
        surfaces=tuple(surfaces), mount=site.mount,
        truth=replace(tpl.truth, boresight_rad=np.asarray(site.mount.boresight_rad, float),
                      lever_arm_error_m=np.zeros(3), range_offset_m=0.0,
                      scan_angle_offset_rad=0.0, time_offset_s=0.0),
        scanner_noise=ScannerNoise(sigma_range_m=site.sigma_range_m,
                                   sigma_scan_angle_rad=site.sigma_scan_angle_rad),
        pos_noise=pos,
    )  # fmt: skip


@dataclass(frozen=True)
class WhatIf:
    """Predicted σ of a planned site: after each pass in the sailing order, and the pass that
    would help most next."""

    scenario: Scenario
    rows: list  # one per step: sigma_row(...) + "next_best_pass"
    roll_scan_correlation: float


def what_if(site: Site, template: Scenario | str = "montreal",
            scanner_height_m: float | None = None, seed: int = 0) -> WhatIf:  # fmt: skip
    sc = site_as_scenario(site, template, scanner_height_m)
    sigmas = Sigmas.of_site(site)
    sim, obs, planes = prepare(design_scenario(sc, sc.surfaces), sigmas, seed)
    order = [p.id for p in sorted(sim.plan.passes, key=lambda q: q.order)]
    lay = Layout("site", "site", sc.surfaces, sc.standoff_m, ())
    headings, tau = _headings(sc), sigmas.correlation_time_s

    def row(subset):
        o, p = select_passes(obs, planes, subset)
        return sigma_row(sc.name, lay, predict(o, sim.mount_true, p, tau), subset, headings, tau)

    rows = []
    for k in range(1, len(order) + 1):
        r = row(order[:k])
        rest = order[k:]
        nxt = {q: row(order[:k] + [q])["realistic_total_deg"] for q in rest}
        r["next_best_pass"] = min(nxt, key=nxt.get) if nxt else ""
        rows.append(r)
    rho = scan_angle_roll_correlation(obs, sim.mount_true, planes)
    return WhatIf(sc, rows, rho)


# ---------------------------------------------------------------------------------------------
# Monte Carlo check of a prediction
# ---------------------------------------------------------------------------------------------


def _mc_task(scenario: Scenario, seed: int, estimates: tuple[tuple[str, ...], ...]) -> np.ndarray:
    sim = simulate(scenario, seed)
    obs = observations(sim, Sigmas.of_scenario(scenario), noisy=True)
    out = []
    for est in estimates:
        res = adjust(obs, sim.site.mount, target_planes(sim),
                     AdjustOptions(estimate=est, outliers="none", jackknife=False,
                                   max_sigma_rad=UNOBSERVABLE_RAD))  # fmt: skip
        out.append(res.boresight_rad - sim.mount_true.boresight_rad)
    return np.array(out)


def empirical_errors(scenario: Scenario, seeds: Sequence[int],
                     estimates: Sequence[tuple[str, ...]] = ((),), jobs: int = 1,
                     progress=None) -> dict[tuple[str, ...], np.ndarray]:  # fmt: skip
    """Boresight errors (estimate − truth, rad; (len(seeds), 3) per adjustment option) of the
    scenario simulated with its noise, one simulation per seed adjusted with each of
    ``estimates`` (``AdjustOptions.estimate`` values)."""
    est = tuple(tuple(e) for e in estimates)
    res = np.array(_run([(_mc_task, (scenario, int(s), est)) for s in seeds], jobs, progress))
    return {e: res[:, k] for k, e in enumerate(est)}


def predicted_covariance(scenario: Scenario, model: str, seed: int = 0) -> np.ndarray:
    """Predicted boresight covariance (rad²) of a noisy scenario under ``model`` (see
    :func:`predict`), from its noise-free twin with the same seed (same waves)."""
    sigmas = Sigmas.of_scenario(scenario)
    sim, obs, planes = prepare(design_scenario(scenario, scenario.surfaces), sigmas, seed)
    pred = predict(obs, sim.mount_true, planes, sigmas.correlation_time_s, (model,))
    if not pred.observable:
        raise DesignError(f"scenario {scenario.name!r}: the boresight is not observable")
    return pred.covariances[model]


# ---------------------------------------------------------------------------------------------
# Outputs: CSV, figures, Markdown
# ---------------------------------------------------------------------------------------------

#: Colours of the six passes in the thesis's order (0°, 180°, 45°, 225°, 315°, 135°).
_MAX_LAYOUT_BARS = 25


def _fmt(v) -> str:
    if isinstance(v, tuple):  # a list; a list of pairs (sizes) as 1.23x0.76;…
        return ";".join("x".join(_fmt(y) for y in x) if isinstance(x, tuple) else _fmt(x)
                        for x in v)  # fmt: skip
    if isinstance(v, float):
        return f"{v:.6g}"
    return str(v)


def write_csv(path: Path, rows: Sequence[dict], columns: Sequence[str]) -> Path:
    with open(path, "w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(columns)
        for r in rows:
            w.writerow([_fmt(r.get(c, "")) for c in columns])
    return path


def plot_sigma_group(rows: Sequence[dict], group: str, path: Path, title: str = "") -> Path:
    """Thesis Fig. 4.12 style: σ of roll, pitch, yaw per configuration of one group's rows of
    ``sigma.csv``, white noise (top) and realistic (bottom: Gauss–Markov POS errors, the better
    adjustment)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [r for r in rows if r["group"] == group and r["observable"]]
    if group == "layout":  # the search: its best candidates only
        rows = sorted(rows, key=lambda r: r["realistic_total_deg"])[:_MAX_LAYOUT_BARS]
    if group in ("passes", "site_passes"):
        labels = ["/".join(f"{h:g}" for h in r["headings_deg"]) for r in rows]
    else:
        labels = [r["label"] for r in rows]
    x = np.arange(len(rows))
    width = 0.27
    label_in = 0.3 + 0.065 * max((len(t) for t in labels), default=1)  # rotated tick labels
    fig_w, fig_h = max(7.0, 0.22 * len(rows) + 3), 6.5 + label_in
    fig, axes = plt.subplots(2, 1, figsize=(fig_w, fig_h), sharex=True)

    def realistic(r, a):
        return r[f"sigma_{REALISTIC[1] if r['estimator'] == 'pass_offsets' else REALISTIC[0]}_{a}_deg"]

    tau = _tau_text(rows[0]) if rows else "?"
    for ax, what, key in ((axes[0], "white noise (formal)", lambda r, a: r[f"sigma_white_{a}_deg"]),
                          (axes[1], f"realistic (Gauss–Markov POS errors, τ = {tau} s, better "
                                    f"adjustment)", realistic)):  # fmt: skip
        for k, (a, colour) in enumerate(zip(ANGLES, ("tab:blue", "tab:orange", "tab:green"))):
            ax.bar(x + (k - 1) * width, [key(r, a) for r in rows], width, label=a, color=colour)
        ax.set_ylabel("σ (°)")
        ax.set_title(f"{title}{group}: {what}", fontsize=10)
        ax.grid(axis="y", alpha=0.3)
        ax.legend(fontsize=8)
    axes[1].set_xticks(x)
    axes[1].set_xticklabels(labels, rotation=90, fontsize=7)
    fig.subplots_adjust(left=0.8 / fig_w, right=1 - 0.15 / fig_w, top=1 - 0.35 / fig_h, hspace=0.2,
                        bottom=label_in / fig_h)  # fmt: skip
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def _deg3(row: dict, model: str) -> str:
    return ", ".join(f"{a} {row[f'sigma_{model}_{a}_deg']:.4f}°" for a in ANGLES)


def findings(result: StudyResult) -> list[dict]:
    """The thesis's qualitative findings, checked on this study (name, thesis, ours, holds)."""
    out = []

    def best(rows, key="sigma_white_total_deg"):
        rows = [r for r in rows if r["observable"]]
        return min(rows, key=lambda r: r[key]) if rows else None

    passes = result.rows("passes")
    if passes:
        b = best(passes)
        out.append({"name": "all six passes give the smallest σ (one vertical plane, white)",
                    "holds": len(b["passes"]) == max(len(r["passes"]) for r in passes),
                    "ours": f"best subset {b['passes']}: {b['sigma_white_total_deg']:.4f}°"})
    for g, what in (("passes", "one vertical plane"), ("site_passes", "the scenario's targets")):
        rows = result.rows(g)
        if rows:
            br = best(rows, "realistic_total_deg")
            out.append({"name": f"… realistic σ (time-correlated POS errors), {what}",
                        "holds": len(br["passes"]) == max(len(r["passes"]) for r in rows),
                        "ours": f"best subset {br['passes']}: {br['realistic_total_deg']:.4f}°"})
    inc = result.rows("inclination")
    if inc:
        b = best(inc)
        out.append({"name": "a vertical plane is best among single planes (white)",
                    "holds": abs(b["inclinations_deg"][0]) == 90.0,
                    "ours": f"best {b['label']}: {b['sigma_white_total_deg']:.4f}°"})
    size = sorted(result.rows("size"), key=lambda r: r["sizes_m"][0][0])
    if len(size) > 1:
        s = [r["sigma_white_total_deg"] for r in size]
        out.append({"name": "σ decreases with the plane size",
                    "holds": all(a > b for a, b in zip(s, s[1:])),
                    "ours": ", ".join(f"{r['label']}: {r['sigma_white_total_deg']:.4f}°" for r in size)})
    planes = {tuple(r["inclinations_deg"]): r for r in result.rows("planes") if r["observable"]}
    k3, k2 = (90.0, 60.0, 30.0), (90.0, 30.0)
    if k3 in planes and k2 in planes:
        for model, key in (("white", "sigma_white_total_deg"),
                           ("per-pass biases, thesis adjustment", "sigma_pass_bias_total_deg"),
                           ("Gauss–Markov, thesis adjustment", "sigma_gauss_markov_total_deg")):
            triples = [r for k, r in planes.items() if len(k) == 3]
            b = min(triples, key=lambda r: r[key])
            r3, r2 = planes[k3][key], planes[k2][key]
            out.append({"name": f"three planes 90/60/30 near the best, 90/30 within 20% ({model})",
                        "holds": r3 <= 1.10 * b[key] and r2 <= 1.20 * r3,
                        "ours": f"best triple {b['label']} {b[key]:.4f}°, 90/60/30 {r3:.4f}° "
                                f"(×{r3 / b[key]:.2f}), 90/30 {r2:.4f}° (×{r2 / r3:.2f} of 90/60/30)"})
    vis = [v for v in result.visibility if v["error"] == "lever_arm_z"]
    if vis:
        out.append({"name": "a Z lever-arm error is invisible in every configuration",
                    "holds": not any(v["visible"] for v in vis),
                    "ours": f"largest pass-to-pass spread {max(v['distance_spread_m'] for v in vis):.2e} m, "
                            f"{max(v['angle_spread_deg'] for v in vis):.2e}°"})
    out.append({"name": "roll boresight and scan-angle offset strongly correlated",
                "holds": result.roll_scan_correlation > 0.99,
                "ours": f"|ρ| = {result.roll_scan_correlation:.6f}"})
    return out


_MODEL_NAMES = {
    "white": "white noise (formal)",
    "pass_bias": "per-pass POS biases, thesis adjustment",
    "pass_bias_offsets": "per-pass POS biases, with pass offsets",
    "gauss_markov": "Gauss–Markov POS errors, thesis adjustment",
    "gauss_markov_offsets": "Gauss–Markov POS errors, with pass offsets",
}


def _tau_text(row: dict) -> str:
    return "/".join(f"{t:g}" for t in dict.fromkeys(row["correlation_time_s"]))


def _why(rec: Recommendation, sc: Scenario) -> str:
    """Where and why the recommended layout differs from the thesis's site (physics, with the
    layout's own parameters)."""
    tg, p = rec.layout.targets, rec.layout.params
    same_normal = len({round(_surface_inclination_deg(t), 6) for t in tg}) == 1
    txt = [
        "Under white noise (the thesis's model) a site's σ is set by how many points its "
        "targets return and how different their normals are, and the thesis's site (targets of "
        "different inclinations — vertical and 45° at Montreal — a few metres apart at one "
        "height and range) looks excellent. But INS "
        "errors are correlated in time: during the few seconds a pass sees the targets, the "
        "position error is nearly a constant translation of that pass's points, and seen from "
        f"{sc.standoff_m:g} m a translation of a centimetre looks like a boresight rotation of "
        "a few hundredths of a degree. Adjusting per-pass trajectory offsets removes a "
        "translation only where the targets can tell it from a rotation: with two targets of "
        "different normals a per-pass translation explains both targets' offsets at once, so "
        "the offsets take the boresight's signal with them."]
    if rec.estimator and same_normal:
        txt.append("The recommended targets share one normal: a translation moves both alike, "
                   "a rotation moves them by amounts that grow with their lever from the scanner, "
                   "so the per-pass offsets absorb the POS error and leave the rotation.")
    if p.get("spread_m", 1.0) == 0.0 and p.get("stagger_m", 0.0) > 0:
        txt.append(f"They stand one above the other ({p['stagger_m']:g} m apart): every profile "
                   "crosses both at the same instant, so the POS error's drift within a pass "
                   "cancels between them too (targets spread along the wall or in range are "
                   "crossed seconds apart, and the drift over those seconds — half the POS σ for "
                   f"correlation times of {_tau_text(rec.row)} s — corrupts exactly the difference "
                   "the design relies on). The height difference turns roll (a displacement across the "
                   "track proportional to the height) and pitch (along the track, proportional "
                   "to the height, seen at 45° by the oblique passes) into differences between "
                   "the targets that no translation produces.")
    if p.get("setback_m", 0.0) > 0:
        txt.append(f"One target is set back {p['setback_m']:g} m: a yaw moves points along the "
                   "track in proportion to their horizontal range, a translation does not.")
    r, b = rec.row, rec.baseline_row
    real = REALISTIC[1] if rec.estimator else REALISTIC[0]
    if p.get("setback_m", 0.0) == 0 and max(ANGLES, key=lambda a: r[f"sigma_{real}_{a}_deg"]) == "yaw":
        txt.append("Yaw stays the weakest angle: a profiler's yaw moves points along the track "
                   "by their horizontal range, the same for targets at one range, so only the "
                   "targets' own extent and the pass headings separate it from an along-track "
                   "translation.")
    if b:
        txt.append(f"Predicted realistic σ: {r['realistic_total_deg']:.4f}° against "
                   f"{b['realistic_total_deg']:.4f}° for the scenario's own site.")
    return " ".join(txt)


def _summary(result: StudyResult, empirical: dict | None) -> str:
    sc, spec, sg = result.scenario, result.spec, result.sigmas
    L = [f"# Site design study — {sc.name}", "",
         f"{sc.description.strip()}", "",
         f"Standoff {sc.standoff_m:g} m, passes "
         + ", ".join(f"{p.id} ({np.degrees(p.relative_heading_rad) % 360:g}°)" for p in sc.passes)
         + f"; profiler at {sc.scanner.effective_profile_rate_hz:.0f} profiles/s × "
         f"{sc.scanner.effective_points_per_360} points/360°. Sigmas assumed: range "
         f"{sg.scanner.sigma_range_m * 1e3:g} mm (+ beam divergence "
         f"{sg.scanner.beam_divergence_rad * 1e3:g} mrad), scan angle "
         f"{np.degrees(sg.scanner.sigma_scan_angle_rad):g}°, POS position "
         f"{', '.join(f'{x * 100:g}' for x in sg.position_m)} cm, attitude "
         f"{', '.join(f'{x:g}' for x in np.degrees(sg.attitude_rad))}°. "
         f"Study time {result.runtime_s:.1f} s.", ""]  # fmt: skip
    L += ["## Thesis findings on this model", "", "| finding | holds | ours |", "|---|---|---|"]
    L += [f"| {f['name']} | {'yes' if f['holds'] else '**no**'} | {f['ours']} |"
          for f in findings(result)]  # fmt: skip
    if result.visibility:
        L += ["", "## Visibility criteria (thesis Table 3.2)", "",
              "Each error alone at the thesis's magnitude, a level vessel, one "
              f"{spec.criteria_size_m:g} m target per inclination, georeferenced with the "
              "error-free mount. An error is visible where the passes' copies disagree (a "
              "plane-based adjustment sees nothing else); the best inclination is chosen among "
              f"those whose mean Type I reaches {spec.type1_threshold:g}.", "",
              "| error | magnitude | best inclination (distance) | spread | best inclination (angle) | spread |",
              "|---|---|---|---|---|---|"]  # fmt: skip
        def incl(v):  # the thesis's Chapter 3 angle beside ours on a ground-based site
            tilt = f" (thesis {v['thesis_tilt_deg']:g}°)" if ground_based(sc) else ""
            return f"{v['inclination_deg']:g}°{tilt}"

        for e in dict.fromkeys(v["error"] for v in result.visibility):
            vs = [v for v in result.visibility if v["error"] == e]
            bd, ba = best_inclinations(vs, e, spec.type1_threshold)
            mag = (f"{np.degrees(spec.magnitudes[e]):g}°" if is_angular(e)
                   else f"{spec.magnitudes[e] * 100:g} cm")  # fmt: skip
            if not any(v["visible"] for v in vs):
                L.append(f"| {e} | {mag} | invisible | {bd['distance_spread_m']:.1e} m | invisible | "
                         f"{ba['angle_spread_deg']:.1e}° |")
                continue
            L.append(f"| {e} | {mag} | {incl(bd)} | {bd['distance_spread_m'] * 1e3:.1f} mm | "
                     f"{incl(ba)} | {ba['angle_spread_deg']:.3f}° |")
        L += ["", "A Z lever-arm error moves every point of every pass by the same vertical "
              "vector (the vessel is level), which the plane's own offset absorbs: no plane, "
              "inclination or pass pattern sees it (thesis C.2.5); measure it by survey. A "
              "scan-angle offset is a rotation about the scanner's x axis, i.e. a boresight "
              f"rotation: |ρ(roll, scan-angle offset)| = {result.roll_scan_correlation:.6f}; the "
              "boresight absorbs it."]  # fmt: skip
    L += ["", "## Predicted σ (thesis Fig. 4.12)", "",
          "Per group the configuration with the smallest white-noise σ and the one with the "
          "smallest realistic σ (σ total = √(σ_roll² + σ_pitch² + σ_yaw²)).", "",
          "| group | best (white) | σ white | best (realistic) | σ realistic | adjustment |",
          "|---|---|---|---|---|---|"]  # fmt: skip
    for g in spec.groups:
        rows = [r for r in result.rows(g) if r["observable"]]
        if not rows:
            continue
        bw = min(rows, key=lambda r: r["sigma_white_total_deg"])
        br = min(rows, key=lambda r: r["realistic_total_deg"])
        lab = (lambda r: str(r["passes"])) if g.endswith("passes") else (lambda r: r["label"])
        L.append(f"| {g} | {lab(bw)} | {bw['sigma_white_total_deg']:.4f}° | {lab(br)} | "
                 f"{br['realistic_total_deg']:.4f}° | {br['estimator']} |")
    if result.sigma:
        L += ["", "Models: *white* treats every observation as independent (the thesis's "
              "implicit model, the adjustment's formal σ); *per-pass biases* hold the POS errors "
              "constant within a pass and independent between passes; *Gauss–Markov* correlates "
              "them in time with the trajectory's correlation times "
              f"({_tau_text(result.sigma[0])} s for north, east, down, roll, pitch, heading), "
              "across passes too. Each realistic model is predicted for the thesis's "
              "adjustment and for one with per-pass trajectory offsets. The realistic σ — what "
              "the recommendation minimizes — is the better Gauss–Markov one: per-pass biases "
              "are its limit of an infinite correlation time and miss the POS drift within a "
              "pass, which decides between layouts whose targets are crossed at different "
              "moments (a Gauss–Markov Monte Carlo follows the Gauss–Markov prediction)."]  # fmt: skip
    rec = result.recommendation
    if rec is not None:
        c, r, b = rec.constraint, rec.row, rec.baseline_row
        L += ["", "## Recommended site", "",
              f"Constraint: {c.n_targets} target(s) of at most {c.max_size_m:g} m, passes "
              f"{', '.join(map(str, c.passes))}. Adjust with "
              f"{'per-pass trajectory offsets (estimate pass_offsets)' if rec.estimator else 'the boresight and planes only'}.", "",
              "| target | inclination | size | along the wall | out from the wall line | above the scanner |",
              "|---|---|---|---|---|---|"]  # fmt: skip
        for s in rec.layout.targets:
            L.append(f"| {s.name} | {_surface_inclination_deg(s):g}° | {s.width_m:g} × {s.height_m:g} m "
                     f"| {s.along_m + 0.0:+.2f} m | {s.out_m + 0.0:+.2f} m | {s.up_m:.2f} m |")
        L += ["", "| model | recommended | scenario's own site |", "|---|---|---|"]
        for m in MODELS:
            L.append(f"| {_MODEL_NAMES[m]} | {_deg3(r, m)} (total {r[f'sigma_{m}_total_deg']:.4f}°) | "
                     + (f"{_deg3(b, m)} (total {b[f'sigma_{m}_total_deg']:.4f}°) |" if b else "— |"))
        corr = lambda x: ", ".join(f"{a}–{c} {x[f'corr_realistic_{a}_{c}']:+.2f}"  # noqa: E731
                                   for a, c in (("roll", "pitch"), ("roll", "yaw"), ("pitch", "yaw")))
        L.append(f"| correlation (realistic) | {corr(r)} | {corr(b) if b else '—'} |")
        L += ["", "### Why it differs from the thesis's site", "", _why(rec, sc)]
    if empirical:
        L += ["", "## Monte Carlo check", "", empirical.get("text", "")]
    L += ["", "## Files", "",
          "`criteria.csv` (per error, inclination and pass), `visibility.csv` (per error and "
          "inclination), `sigma.csv` (per configuration and pass subset; σ in degrees under "
          "each model — the search's layouts under white noise and Gauss–Markov only, the "
          "recommended one under all), `recommendation.json`, "
          "`criteria_<error>.png`, `sigma_<group>.png`."]  # fmt: skip
    return "\n".join(L) + "\n"


def recommendation_json(result: StudyResult) -> dict:
    rec = result.recommendation
    if rec is None:
        return {}
    def value(v):  # JSON has no tuple, inf or NaN
        if isinstance(v, tuple):
            return [value(x) for x in v]
        return None if isinstance(v, float) and not math.isfinite(v) else v

    def clean(r):
        return {k: value(v) for k, v in r.items()}

    return {
        "scenario": result.scenario.name,
        "constraint": asdict(rec.constraint),
        "estimate": list(rec.estimator),
        "targets": [{"name": s.name, "inclination_deg": _surface_inclination_deg(s),
                     "size_m": [s.width_m, s.height_m], "along_m": round(s.along_m, 6) + 0.0,
                     "out_m": round(s.out_m, 6) + 0.0, "up_m": round(s.up_m, 6)}
                    for s in rec.layout.targets],
        "predicted": clean(rec.row),
        "scenario_site": clean(rec.baseline_row) if rec.baseline_row else None,
        "roll_scan_angle_correlation": result.roll_scan_correlation,
    }  # fmt: skip


def write_study(result: StudyResult, out_dir: str | Path, empirical: dict | None = None,
                figures: bool = True, jobs: int = 1) -> list[Path]:  # fmt: skip
    """CSV tables, PNG figures (drawn in ``jobs`` processes) and ``summary.md`` into
    ``out_dir`` (created)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files = [write_csv(out / "criteria.csv", result.criteria, CRITERIA_COLUMNS),
             write_csv(out / "visibility.csv", result.visibility, VISIBILITY_COLUMNS),
             write_csv(out / "sigma.csv", result.sigma, SIGMA_COLUMNS)]  # fmt: skip
    if result.recommendation is not None:
        p = out / "recommendation.json"
        p.write_text(json.dumps(recommendation_json(result), indent=2, default=float) + "\n")
        files.append(p)
    if figures:
        title = f"{result.scenario.name}: "
        tasks: list[tuple[Callable, tuple]] = [
            (plot_criteria, ([r for r in result.criteria if r["error"] == e], e,
                             out / f"criteria_{e}.png", title))
            for e in dict.fromkeys(r["error"] for r in result.criteria)]  # fmt: skip
        tasks += [(plot_sigma_group, (result.rows(g), g, out / f"sigma_{g}.png", title))
                  for g in result.spec.groups if any(r["observable"] for r in result.rows(g))]
        files += _run(tasks, jobs, None)
    p = out / "summary.md"
    p.write_text(_summary(result, empirical), encoding="utf-8")
    files.append(p)
    return files


def write_what_if(w: WhatIf, out_dir: str | Path) -> list[Path]:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    return [write_csv(out / "whatif.csv", w.rows, list(SIGMA_COLUMNS) + ["next_best_pass"])]
