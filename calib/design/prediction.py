"""Predicted σ of the boresight for a configuration (thesis §4.4.1.2, Fig. 4.12): the observations
of a simulated design scene and the adjustment's covariance predicted from them.

A noise-free simulation of a configuration gives the geometry (true poses, ranges, scan angles,
the trajectory's epochs); the adjustment's covariance is predicted at the truth
(:func:`calib.boresight.covariance.predict_covariance`) with the scenario's observation sigmas
under six models —

- ``white``: every observation independent (the thesis's implicit model, the formal σ);
- ``gls``: POS errors correlated in time (first-order Gauss–Markov with the trajectory's
  correlation times, across passes too), adjusted by the GLS estimator
  (:mod:`calib.boresight.gls`, the calibration's default): the POS error processes are
  estimated with the boresight, and the predicted σ is the estimator's covariance — its
  realistic σ and the Cramér–Rao bound of the model (no unbiased estimator does better);
- ``pass_bias``: POS errors constant within a pass and independent between passes (what
  time-correlated INS errors do over a pass of a few seconds), adjusted as the thesis does;
- ``gauss_markov``: the Gauss–Markov POS errors adjusted as the thesis does (white weights,
  ``--estimator thesis``), realistic σ by propagation;
- ``…_offsets``: the same errors, adjusted with per-pass trajectory translations
  (``estimate=("pass_offsets",)``, prior from the trajectory's σ; ``--estimator
  pass_offsets``).

The *realistic* σ of a configuration is the σ of the calibration's estimator: GLS (the default,
what the recommendation minimizes); the thesis and pass-offset models stay beside it for
comparison. A prediction without the ``gls`` model falls back to the better of the two
Gauss–Markov thesis predictions (the pass-bias model is their limit of an infinite correlation
time within a pass; with the INS's real τ the POS error still drifts by half its σ in the 2–3 s
between the moments one pass sees two targets a few metres apart, which a layout that relies on
the per-pass offsets must survive).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from calib.boresight.covariance import predict_covariance
from calib.boresight.errormodel import DEFAULT_POS_CORRELATION_S, ErrorModel
from calib.boresight.ghmodel import State, linearize
from calib.boresight.observations import Observations, build_observations
from calib.core import frames
from calib.core.errors import CalibError
from calib.core.georef import Mount
from calib.io.site import Site
from calib.sim.noise import ScannerNoise
from calib.sim.scenario import Scenario
from calib.sim.simulate import SimResult, simulate

ANGLES = ("roll", "pitch", "yaw")
#: Error models of a prediction: white noise; POS errors first-order Gauss–Markov with the
#: trajectory's correlation times adjusted by GLS (gls); POS errors constant within a pass
#: (pass_bias) or Gauss–Markov (gauss_markov), each adjusted as the thesis does or with per-pass
#: trajectory offsets (…_offsets).
MODELS = ("white", "gls", "pass_bias", "pass_bias_offsets", "gauss_markov", "gauss_markov_offsets")
#: The model whose σ is each calibration estimator's realistic σ (``mls calib run --estimator``).
ESTIMATOR_MODEL = {"gls": "gls", "thesis": "gauss_markov", "pass_offsets": "gauss_markov_offsets"}
#: The calibration's default estimator: its σ is the realistic σ the design optimizes.
DEFAULT_ESTIMATOR = "gls"
#: The realistic models, one per estimator (the default first).
REALISTIC = tuple(ESTIMATOR_MODEL.values())
#: Without a GLS prediction the realistic σ is the better of these (the thesis's adjustment, with
#: or without pass offsets).
THESIS_REALISTIC = ("gauss_markov", "gauss_markov_offsets")
#: The estimate of a boresight direction whose formal σ exceeds this is reported unobservable.
UNOBSERVABLE_RAD = float(np.radians(1.0))
_RANGE_SIGMA_FLOOR_M = 1e-4


class DesignError(CalibError, ValueError):
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
    def of_scenario(cls, sc: Scenario) -> Sigmas:
        """The scenario's noise models; where one is off, the site-config defaults (and the
        adjustment's default correlation time unless the POS errors are Gauss–Markov)."""
        dflt = Site(mount=Mount(), targets=())
        s = sc.scanner_noise
        if s.is_zero:
            s = ScannerNoise(sigma_range_m=dflt.sigma_range_m, sigma_scan_angle_rad=dflt.sigma_scan_angle_rad)
        p = sc.pos_noise
        on = p.model != "none"
        tau = (
            tuple(float(x) for x in p.tau) if p.model == "gauss_markov" else (DEFAULT_POS_CORRELATION_S,) * 6
        )
        return cls(
            s,
            p.sigma_position_m if on and np.all(p.sigma_position_m > 0) else dflt.sigma_position_m,
            p.sigma_attitude_rad if on and np.all(p.sigma_attitude_rad > 0) else dflt.sigma_attitude_rad,
            tau,
        )

    @classmethod
    def of_site(cls, site: Site) -> Sigmas:
        return cls(
            ScannerNoise(
                sigma_range_m=site.sigma_range_m,
                sigma_range_per_m=site.sigma_range_per_m,
                beam_divergence_rad=site.beam_divergence_rad,
                sigma_scan_angle_rad=site.sigma_scan_angle_rad,
            ),
            np.asarray(site.sigma_position_m, float),
            np.asarray(site.sigma_attitude_rad, float),
            (DEFAULT_POS_CORRELATION_S,) * 6
            if site.pos_correlation_time_s is None
            else tuple(float(x) for x in np.broadcast_to(site.pos_correlation_time_s, 6)),
        )


def target_planes(sim: SimResult) -> list[tuple[np.ndarray, float]]:
    """The true (normal, d) of the simulation's targets, in target order."""
    return [(sim.scene.rectangles[i].normal, sim.scene.rectangles[i].d) for i in sim.scene.indices("target")]


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
    names = [t.name for t in sim.site.targets]
    return _observations_of(sim, sigmas, sel, sim.target_index[sel], names, noisy)


def feature_observations(sim: SimResult, sigmas: Sigmas, shape_sigma_m: float) -> tuple[Observations, list]:
    """Noise-free observations of the targets and of the scene's vertical cylinders (piles),
    and the true features (target planes, then :class:`~calib.core.geometry.VerticalCylinder` each):
    what the calibration's adjustment uses of a scene with piles. A cylinder's points are those
    the calibration keeps (within :data:`~calib.boresight.scene_ties.MIN_COS_INCIDENCE_CYLINDER`
    of head-on), their range σ grown by ``shape_sigma_m`` (a real pile is no perfect cylinder:
    the adjustment estimates that variance; the prediction assumes it)."""
    from calib.boresight.scene_ties import MIN_COS_INCIDENCE_CYLINDER

    scene, p = sim.scene, sim.points
    n_targets = len(sim.site.targets)
    feature_of_surface = np.full(len(scene.names), -1)
    feature_of_surface[scene.cylinder_indices] = n_targets + np.arange(len(scene.cylinders))
    cos_incidence = p.intensity / scene.reflectivity[sim.surface_index]
    on_cylinder = (feature_of_surface[sim.surface_index] >= 0) & (cos_incidence >= MIN_COS_INCIDENCE_CYLINDER)
    feature = np.where(
        sim.target_index >= 0,
        sim.target_index,
        np.where(on_cylinder, feature_of_surface[sim.surface_index], -1),
    )
    sel = np.flatnonzero(feature >= 0)
    if sel.size == 0:
        raise DesignError(f"scenario {sim.scenario.name!r}: no return on any target or pile")
    names = [t.name for t in sim.site.targets] + [scene.names[j] for j in scene.cylinder_indices]
    obs = _observations_of(sim, sigmas, sel, feature[sel], names, noisy=False)
    piles = feature[sel] >= n_targets
    obs.sigma_l[piles, 6] = np.hypot(obs.sigma_l[piles, 6], shape_sigma_m)
    return obs, target_planes(sim) + list(scene.cylinders)


def _observations_of(
    sim: SimResult, sigmas: Sigmas, sel: np.ndarray, feature_index: np.ndarray, names: list[str], noisy: bool
) -> Observations:
    """The observations of the returns ``sel`` on the features ``feature_index`` (named ``names``)."""
    p = sim.points
    obs = build_observations(
        sim.trajectory_observed if noisy else sim.trajectory_true,
        p.t_gps_s[sel],
        p.range_m[sel],
        p.scan_angle_rad[sel],
        feature_index,
        p.pass_id[sel],
        names,
        sigmas.scanner.sigma_range_m,
        sigmas.scanner.sigma_scan_angle_rad,
        sigmas.position_m,
        sigmas.attitude_rad,
        point_ids=sel,
        pass_headings_rad={q.id: q.relative_heading_rad for q in sim.plan.passes},
    )
    if noisy and sim.pose_errors is not None:
        poses = sim.observed_poses()
        obs.l[:, 0:3] = poses.p_lgf_m[sel]
        obs.l[:, 3:6] = poses.rpy_rad[sel]
    obs.sigma_l[:, 0:3] = sigmas.position_m
    obs.sigma_l[:, 3:6] = sigmas.attitude_rad
    cos_incidence = p.intensity[sel] / sim.scene.reflectivity[sim.surface_index[sel]]
    obs.sigma_l[:, 6] = np.maximum(
        sigmas.scanner.range_sigma(p.range_m[sel], cos_incidence), _RANGE_SIGMA_FLOOR_M
    )
    return obs


def select_passes(obs: Observations, planes: list, pass_ids: Sequence[int]) -> tuple[Observations, list]:
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


def prepare(scenario: Scenario, sigmas: Sigmas, seed: int = 0):
    """Simulate a (noise-free) scenario: returns (simulation, noise-free observations of its
    targets, true planes)."""
    sim = simulate(scenario, seed)
    return sim, observations(sim, sigmas, noisy=False), target_planes(sim)


# ---------------------------------------------------------------------------------------------
# Prediction
# ---------------------------------------------------------------------------------------------


def reduced_information(obs: Observations, mount: Mount, planes, extras: Sequence[str] = ()) -> np.ndarray:
    """White-noise information of the boresight (and ``extras``, columns of
    :func:`calib.boresight.ghmodel.linearize`) with the planes' parameters eliminated (Schur complement),
    linearized at the truth: its inverse is the formal covariance, its eigenvalues say what is
    observable."""
    r_nom = frames.rotation_zyx(*mount.nominal_rad)
    m = len(planes)
    normals = np.array([np.asarray(n, float) / np.linalg.norm(n) for n, _ in planes])
    d_lgf = np.array([float(d) / np.linalg.norm(n) for n, d in planes])

    def state(centers):
        return State(
            np.asarray(mount.boresight_rad, float).copy(),
            normals,
            d_lgf + np.einsum("ij,ij->i", normals, centers),
            centers,
            np.zeros((len(obs.pass_ids), 3)),
            np.asarray(mount.lever_arm_m, float).copy(),
            mount.range_offset_m,
            mount.scan_angle_offset_rad,
            mount.time_offset_s,
        )

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
    S2 = (
        S[np.ix_(keep, keep)]
        - S[np.ix_(keep, other)]
        @ np.linalg.lstsq(S[np.ix_(other, other)], S[np.ix_(other, keep)], rcond=None)[0]
    )
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
        """The model of the realistic σ: the GLS estimator's when predicted, else the better
        thesis adjustment under Gauss–Markov POS errors (with or without per-pass offsets)."""
        if ESTIMATOR_MODEL[DEFAULT_ESTIMATOR] in self.covariances:
            return ESTIMATOR_MODEL[DEFAULT_ESTIMATOR]
        return min(THESIS_REALISTIC, key=self.total_deg)

    @property
    def estimator(self) -> str:
        """The calibration estimator (``--estimator``) of :attr:`realistic_model`."""
        return next(e for e, m in ESTIMATOR_MODEL.items() if m == self.realistic_model)


def predict(
    obs: Observations,
    mount: Mount,
    planes,
    correlation_time_s: float | Sequence[float] = DEFAULT_POS_CORRELATION_S,
    models: Sequence[str] = MODELS,
) -> Prediction:
    """Predicted covariance of the boresight from noise-free ``obs`` at the true ``mount`` and
    ``planes`` under ``models`` (of :data:`MODELS`; Gauss–Markov with ``correlation_time_s``,
    one value or six for north, east, down, roll, pitch, heading). ``obs`` should carry its
    trajectory: the GLS knots are its epochs, as in the calibration."""
    n = len(obs)
    counts = dict(n_points=n, n_planes=len(planes), n_passes=len(obs.pass_ids))
    if n == 0 or not planes:
        return Prediction(**counts, observable=False, covariances={})
    info = reduced_information(obs, mount, planes)
    ev = np.linalg.eigvalsh(info)
    if not ev[0] > 0 or 1.0 / np.sqrt(ev[0]) > UNOBSERVABLE_RAD:
        return Prediction(**counts, observable=False, covariances={})
    gm = ErrorModel("gauss_markov", tuple(np.atleast_1d(correlation_time_s)))
    covs = {}
    for model in models:
        if model == "white":  # = predict_covariance(...)["formal"], without a second pass
            covs[model] = np.linalg.inv(info)
            continue
        if model not in MODELS:
            raise DesignError(f"unknown error model {model!r}; expected one of {', '.join(MODELS)}")
        if model == "gls":
            covs[model] = predict_covariance(obs, mount, planes, (), gm, estimator="gls")["realistic"]
            continue
        est = ("pass_offsets",) if model.endswith("_offsets") else ()
        em = ErrorModel("pass_bias") if model.startswith("pass_bias") else gm
        covs[model] = predict_covariance(obs, mount, planes, est, em, estimator="thesis")["realistic"]
    return Prediction(**counts, observable=True, covariances=covs)
