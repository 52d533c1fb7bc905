"""Random errors of the simulated observations: scanner range and scan angle, and POS errors.

POS errors are six channels (north, east, down in metres; roll, pitch, heading in radians)
drawn by one of four models:

* ``none``: no error;
* ``white``: independent per trajectory epoch (σ per channel);
* ``gauss_markov``: a first-order Gauss–Markov process per channel, σ and correlation time τ,
  ``x_k = φ_k·x_{k−1} + w_k`` with ``φ_k = exp(−Δt_k/τ)``, ``w_k ~ N(0, σ²(1 − φ_k²))`` and a
  stationary start ``x_0 ~ N(0, σ²)`` (exact for any sampling, gaps included);
* ``per_point``: independent per scanner point (the adjustment's own stochastic model); a
  trajectory cannot carry it, so it exists only in memory (see ``calib.sim.simulate``).

Every draw takes a ``numpy.random.Generator``: the same seed gives the same errors.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.signal import lfilter

POS_NOISE_MODELS = ("none", "white", "gauss_markov", "per_point")


def white_noise(n: int, sigma, rng: np.random.Generator) -> np.ndarray:
    """(n, k) independent normal errors with standard deviations ``sigma`` (k,)."""
    sigma = np.atleast_1d(np.asarray(sigma, float))
    return rng.standard_normal((n, sigma.size)) * sigma


def gauss_markov(t_s, sigma, tau_s, rng: np.random.Generator) -> np.ndarray:
    """(n, k) first-order Gauss–Markov processes sampled at the increasing times ``t_s``.

    Runs of equal steps are filtered at C speed; a change of step (a gap) is one exact
    transition.
    """
    t = np.asarray(t_s, float)
    sigma = np.atleast_1d(np.asarray(sigma, float))
    tau = np.broadcast_to(np.asarray(tau_s, float), sigma.shape)
    if np.any(tau <= 0):
        raise ValueError(f"gauss_markov: correlation times must be > 0, got {tau!r}")
    n, k = t.size, sigma.size
    w = rng.standard_normal((n, k))
    out = np.empty((n, k))
    if n == 0:
        return out
    out[0] = sigma * w[0]
    dt = np.diff(t)
    if np.any(dt <= 0):
        raise ValueError("gauss_markov: times must increase strictly")
    # runs of (nearly) equal steps: [a, b) in step indices, step i leads to epoch i + 1
    change = np.flatnonzero(np.abs(np.diff(dt)) > 1e-3 * dt[1:]) + 1
    bounds = np.concatenate([[0], change, [dt.size]])
    for a, b in zip(bounds[:-1], bounds[1:], strict=False):
        phi = np.exp(-np.mean(dt[a:b]) / tau)
        drive = w[a + 1 : b + 1] * (sigma * np.sqrt(1.0 - phi**2))
        if b - a <= k:  # short run, many channels: step through it across the channels
            for i in range(a + 1, b + 1):
                out[i] = phi * out[i - 1] + drive[i - a - 1]
            continue
        for j in range(k):
            out[a + 1 : b + 1, j], _ = lfilter([1.0], [1.0, -phi[j]], drive[:, j], zi=[phi[j] * out[a, j]])
    return out


@dataclass(frozen=True)
class PosNoise:
    """POS error model (see the module docstring); σ and τ per channel."""

    model: str = "none"
    sigma_position_m: np.ndarray = field(default_factory=lambda: np.zeros(3))
    sigma_attitude_rad: np.ndarray = field(default_factory=lambda: np.zeros(3))
    tau_position_s: np.ndarray = field(default_factory=lambda: np.full(3, 20.0))
    tau_attitude_s: np.ndarray = field(default_factory=lambda: np.full(3, 10.0))
    #: site.yaml states the correlation times (False: the calibration must estimate them)
    tau_in_site: bool = True

    def __post_init__(self):
        if self.model not in POS_NOISE_MODELS:
            raise ValueError(
                f"PosNoise.model is {self.model!r}, expected one of {', '.join(POS_NOISE_MODELS)}"
            )
        for attr in ("sigma_position_m", "sigma_attitude_rad", "tau_position_s", "tau_attitude_s"):
            v = np.broadcast_to(np.asarray(getattr(self, attr), float), (3,)).copy()
            if np.any(v < 0) or not np.all(np.isfinite(v)):
                raise ValueError(f"PosNoise.{attr} must be 3 finite numbers ≥ 0, got {v!r}")
            object.__setattr__(self, attr, v)
        if self.model == "gauss_markov" and np.any(self.tau <= 0):
            raise ValueError("PosNoise: gauss_markov needs correlation times > 0")

    @property
    def sigma(self) -> np.ndarray:
        """(6,) σ of north, east, down (m), roll, pitch, heading (rad)."""
        if self.model == "none":
            return np.zeros(6)
        return np.concatenate([self.sigma_position_m, self.sigma_attitude_rad])

    @property
    def tau(self) -> np.ndarray:
        return np.concatenate([self.tau_position_s, self.tau_attitude_s])

    def epoch_errors(self, t_s, rng: np.random.Generator) -> np.ndarray:
        """(n, 6) errors of the trajectory epochs at times ``t_s`` (zero for ``none`` and
        ``per_point``, whose errors belong to the points)."""
        t = np.asarray(t_s, float)
        if self.model == "white":
            return white_noise(t.size, self.sigma, rng)
        if self.model == "gauss_markov":
            return gauss_markov(t, self.sigma, self.tau, rng)
        return np.zeros((t.size, 6))

    def point_errors(self, n: int, rng: np.random.Generator) -> np.ndarray | None:
        """(n, 6) independent per-point errors for ``per_point``; None for the other models."""
        return white_noise(n, self.sigma, rng) if self.model == "per_point" else None

    def to_dict(self) -> dict:
        d = {
            "model": self.model,
            "sigma_position_m": [float(x) for x in self.sigma_position_m],
            "sigma_attitude_deg": [float(x) for x in np.degrees(self.sigma_attitude_rad)],
        }
        if self.model == "gauss_markov":
            d["tau_position_s"] = [float(x) for x in self.tau_position_s]
            d["tau_attitude_s"] = [float(x) for x in self.tau_attitude_s]
        return d


@dataclass(frozen=True)
class ScannerNoise:
    """Range and scan-angle noise of the profiler.

    ``σ_ρ = sigma_range_m + sigma_range_per_m·ρ + ρ·(beam_divergence_rad/2)·tan(incidence)``:
    constant, growing with range, and growing with the footprint's elongation at oblique
    incidence (tan clamped at 89°).
    """

    sigma_range_m: float = 0.0
    sigma_range_per_m: float = 0.0
    beam_divergence_rad: float = 0.0
    sigma_scan_angle_rad: float = 0.0
    #: the returned intensity is reflectivity × cos(incidence) (Lambertian); False: reflectivity
    #: alone (a scanner that normalizes its intensity, as an independent simulator's did)
    intensity_follows_incidence: bool = True

    def __post_init__(self):
        for attr in ("sigma_range_m", "sigma_range_per_m", "beam_divergence_rad", "sigma_scan_angle_rad"):
            v = float(getattr(self, attr))
            if not np.isfinite(v) or v < 0:
                raise ValueError(f"ScannerNoise.{attr} must be a finite number ≥ 0, got {v!r}")
            object.__setattr__(self, attr, v)

    @property
    def is_zero(self) -> bool:
        return not (
            self.sigma_range_m
            or self.sigma_range_per_m
            or self.beam_divergence_rad
            or self.sigma_scan_angle_rad
        )

    def range_sigma(self, range_m, cos_incidence) -> np.ndarray:
        rho = np.asarray(range_m, float)
        sigma = self.sigma_range_m + self.sigma_range_per_m * rho
        if self.beam_divergence_rad:
            c = np.maximum(np.abs(np.asarray(cos_incidence, float)), np.cos(np.radians(89.0)))
            tan = np.sqrt(1.0 - c * c)
            tan /= c
            tan *= rho
            tan *= 0.5 * self.beam_divergence_rad
            sigma = sigma + tan
        return np.broadcast_to(sigma, rho.shape)

    def draw(self, range_m, cos_incidence, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """Range and scan-angle errors for returns at the given ranges and incidences."""
        rho = np.asarray(range_m, float)
        d_range = rng.standard_normal(rho.size) * self.range_sigma(rho, cos_incidence)
        d_angle = rng.standard_normal(rho.size) * self.sigma_scan_angle_rad
        return d_range, d_angle

    def to_dict(self) -> dict:
        return {
            "sigma_range_m": self.sigma_range_m,
            "sigma_range_per_m": self.sigma_range_per_m,
            "beam_divergence_mrad": self.beam_divergence_rad * 1e3,
            "sigma_scan_angle_deg": float(np.degrees(self.sigma_scan_angle_rad)),
        }
