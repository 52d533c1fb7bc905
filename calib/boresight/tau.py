"""The correlation time of the POS errors: what the data say about it, and what it changes.

τ is rarely known exactly. :func:`estimate_tau` picks, on a log grid, the τ (one value for the
six channels) that maximizes the restricted likelihood of the GLS model
(:attr:`calib.boresight.gls.GlsSolution.neg2_log_lik`): the residuals' correlation along each
pass tells a drift of 5 s from one of 100 s. :func:`tau_sensitivity` solves again at τ/3, τ and
3τ, for the report: a boresight that moves by more than its σ between them says that τ matters
and should be configured. :func:`choose_tau` is the calibration's choice: τ from the command
line, else site.yaml, else (GLS) estimated from the data, else the default, and where it came from
(a :class:`TauSource`, stated in words only where it is written: :attr:`TauSource.text`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from enum import Enum

import numpy as np

from calib.boresight.errormodel import DEFAULT_POS_CORRELATION_S, ErrorModel
from calib.boresight.gausshelmert import initial_state, plane_centers
from calib.boresight.gls import solve_gls
from calib.boresight.observations import AdjustOptions, Observations
from calib.core import frames
from calib.io.site import Site

#: the τ grid of the likelihood search (s)
TAU_GRID_S = (2.0, 5.0, 10.0, 20.0, 40.0, 80.0, 160.0, 320.0)


@dataclass(frozen=True)
class TauEstimate:
    tau_s: float
    grid_s: tuple[float, ...]
    neg2_log_lik: tuple[float, ...]

    @property
    def at_edge(self) -> bool:
        return self.tau_s in (self.grid_s[0], self.grid_s[-1])

    def as_dict(self) -> dict:
        """result.json's ``tau_estimate``."""
        return {"tau_s": self.tau_s, "grid_s": list(self.grid_s), "neg2_log_lik": list(self.neg2_log_lik)}


def _solve_at(obs: Observations, mount, planes, options: AdjustOptions, tau_s: float, plane_var_m2=None):
    """GLS at ``tau_s``; without given roughness variances they are estimated with it (white
    noise the model lacks would otherwise be explained as a short-τ POS error)."""
    r_nom = frames.rotation_zyx(*mount.nominal_rad)
    state = initial_state(mount, planes, len(obs.pass_ids), plane_centers(obs, mount, r_nom))
    rough = None
    if plane_var_m2 is None and options.roughness != "none":
        rough = (
            np.arange(len(obs.plane_names))
            if options.roughness == "all"
            else np.asarray(obs.patch_planes, int)
        )
    return solve_gls(
        obs, state, r_nom, options, ErrorModel("gauss_markov", tau_s), plane_var_m2, rough_planes=rough
    )


def estimate_tau(
    obs: Observations, mount, planes, options: AdjustOptions, plane_var_m2=None, grid_s=TAU_GRID_S
) -> TauEstimate:
    """The grid τ of the highest restricted likelihood (refined by a parabola in log τ)."""
    opts = replace(options, outliers="none", jackknife=False)
    ll = [_solve_at(obs, mount, planes, opts, t, plane_var_m2).neg2_log_lik for t in grid_s]
    i = int(np.argmin(ll))
    tau = grid_s[i]
    if 0 < i < len(grid_s) - 1:
        x = np.log(grid_s[i - 1 : i + 2])
        a, b, _ = np.polyfit(x, ll[i - 1 : i + 2], 2)
        if a > 0:
            tau = float(np.exp(np.clip(-b / (2 * a), x[0], x[2])))
    return TauEstimate(float(tau), tuple(grid_s), tuple(float(v) for v in ll))


def tau_sensitivity(
    obs: Observations, mount, planes, options: AdjustOptions, tau_s: float, plane_var_m2=None
) -> list[dict]:
    """Boresight and σ at τ/3, τ and 3τ (rows for the report and result.json)."""
    opts = replace(options, outliers="none", jackknife=False)
    rows = []
    for factor in (1 / 3, 1.0, 3.0):
        sol = _solve_at(obs, mount, planes, opts, tau_s * factor, plane_var_m2)
        rows.append(
            {
                "tau_s": tau_s * factor,
                "boresight_deg": [float(x) for x in np.degrees(sol.state.boresight_rad)],
                "sigma_deg": [float(x) for x in np.degrees(np.sqrt(np.diag(sol.Ninv)[0:3]))],
            }
        )
    return rows


# -- the POS error model a calibration uses ------------------------------------------------


class TauSource(Enum):
    """Where the POS correlation time of the realistic σ came from."""

    NOT_USED = "not_used"  # the error model has no correlation time (pass_bias, white)
    COMMAND_LINE = "command_line"
    SITE_YAML = "site_yaml"
    DEFAULT = "default"  # none configured: DEFAULT_POS_CORRELATION_S assumed
    ESTIMATED = "estimated"  # none configured: estimated from the data (GLS)

    @property
    def text(self) -> str:
        """How result.json (``realistic_correlation_time_source``) and the report state it."""
        return _TAU_SOURCE_TEXT[self]


_TAU_SOURCE_TEXT = {
    TauSource.NOT_USED: "not used",
    TauSource.COMMAND_LINE: "command line",
    TauSource.SITE_YAML: "site.yaml pos_sigmas.correlation_time_s",
    TauSource.DEFAULT: "default (not configured)",
    TauSource.ESTIMATED: "estimated from the data",
}


def error_model(options, site: Site) -> tuple[ErrorModel, TauSource]:
    """The POS error model for ``sigma_realistic`` and where its correlation time came from."""
    if options.error_model != "gauss_markov":
        return ErrorModel(options.error_model), TauSource.NOT_USED
    if options.correlation_time_s is not None:
        tau = np.atleast_1d(np.asarray(options.correlation_time_s, float))
        source = TauSource.COMMAND_LINE
    elif site.pos_correlation_time_s is not None:
        tau = np.asarray(site.pos_correlation_time_s, float)
        source = TauSource.SITE_YAML
    else:
        tau = np.array([DEFAULT_POS_CORRELATION_S])
        source = TauSource.DEFAULT
    value = float(tau[0]) if np.all(tau == tau[0]) else tuple(float(x) for x in tau)
    return ErrorModel("gauss_markov", value), source


@dataclass(frozen=True, kw_only=True)
class TauChoice:
    """The POS error model a calibration uses and where its correlation time came from."""

    model: ErrorModel
    source: TauSource
    estimate: TauEstimate | None = None  # the likelihood search, when estimated from the data

    @property
    def estimated(self) -> bool:
        """Whether τ was estimated from the data (none configured, GLS)."""
        return self.source is TauSource.ESTIMATED


_NOT_CONFIGURED = "no POS correlation time configured (site.yaml pos_sigmas.correlation_time_s)"


def choose_tau(options, site, obs, mount, planes, notes: list[str], progress) -> TauChoice:
    """The POS error model; with none configured the GLS estimates τ from the data."""
    model, source = error_model(options, site)
    if source is not TauSource.DEFAULT:  # configured, or a model without a correlation time
        return TauChoice(model=model, source=source)
    if options.estimator != "gls":
        notes.append(f"{_NOT_CONFIGURED}: sigma_realistic assumes {DEFAULT_POS_CORRELATION_S:g} s")
        return TauChoice(model=model, source=source)
    if progress is not None:
        progress("estimating the POS correlation time", 0, None)
    est = estimate_tau(obs, mount, planes, options.adjust_options(model))
    notes.append(
        f"{_NOT_CONFIGURED}: estimated {est.tau_s:.1f} s from the data (restricted likelihood"
        f"{', at the edge of the searched range' if est.at_edge else ''}); the report shows "
        f"the boresight at τ/3, τ and 3τ"
    )
    return TauChoice(model=ErrorModel("gauss_markov", est.tau_s), source=TauSource.ESTIMATED, estimate=est)
