"""The GLS estimator (calib.boresight.gls) on synthetic observations with Gauss–Markov POS
errors: it equals the dense oracle on small problems, its σ is honest in a Monte Carlo (also
with τ misspecified), it beats the thesis estimator, τ is recovered from the data, and a rough
plane gets its roughness."""

from __future__ import annotations

import numpy as np
import pytest

from calib.boresight.adjust import adjust
from calib.boresight.errormodel import ErrorModel
from calib.boresight.gausshelmert import initial_state, plane_centers
from calib.boresight.gls import solve_gls
from calib.boresight.observations import AdjustOptions
from calib.boresight.oracle import dense_gls
from calib.boresight.tau import estimate_tau
from calib.core import frames
from calib.core.georef import Mount
from calib.core.trajectory import Trajectory
from calib.sim.noise import gauss_markov
from tests.calib import synth

TRUTH = np.radians([0.208, 1.245, 0.149])
LEVER = np.array([0.35, 0.85, -1.65])
MOUNT_TRUE = Mount(lever_arm_m=LEVER, boresight_rad=TRUTH)
MOUNT0 = Mount(lever_arm_m=LEVER, boresight_rad=np.zeros(3))


class Problem:
    """Noise-free synthetic observations with the union of the passes' epochs as trajectory;
    :meth:`draw` adds Gauss–Markov POS errors (drawn at the epochs, linearly interpolated to
    the points, as the oracle models them) plus white range and scan-angle noise."""

    def __init__(self, points_per_plane_per_pass: int, planes=None):
        rects = synth.montreal_planes() if planes is None else planes
        self.obs0, self.planes, trajs = synth.observations(
            MOUNT_TRUE, rects, points_per_plane_per_pass=points_per_plane_per_pass, noise=False, seed=1
        )
        ep = np.concatenate([tr.t_gps_s for tr in trajs])
        self.ep = ep
        self.traj = Trajectory(
            ep,
            np.concatenate([tr.p_lgf_m for tr in trajs]),
            np.concatenate([tr.rpy_rad for tr in trajs]),
            trajs[0].frame,
            max_gap_s=1e4,
        )
        t = self.obs0.t_gps_s
        self.k = np.clip(np.searchsorted(ep, t, side="right") - 1, 0, ep.size - 2)
        self.w = ((t - ep[self.k]) / (ep[self.k + 1] - ep[self.k]))[:, None]
        self.sig = self.obs0.sigma_l[0].copy()

    def draw(self, seed: int, tau_s: float):
        rng = np.random.default_rng(seed)
        gm = gauss_markov(self.ep, self.sig[:6], tau_s, rng)
        obs = self.obs0.select(np.ones(len(self.obs0), bool))
        obs.trajectory = self.traj
        err = np.empty((len(obs), 8))
        err[:, :6] = (1 - self.w) * gm[self.k] + self.w * gm[self.k + 1]
        err[:, 6:] = rng.standard_normal((len(obs), 2)) * self.sig[6:]
        obs.l = self.obs0.l + err
        return obs


@pytest.fixture(scope="module")
def small():
    return Problem(40)


def _gls(obs, planes, model, options=None):
    r_nom = frames.rotation_zyx(*MOUNT0.nominal_rad)
    state0 = initial_state(MOUNT0, planes, len(obs.pass_ids), plane_centers(obs, MOUNT0, r_nom))
    return solve_gls(obs, state0, r_nom, options or AdjustOptions(outliers="none"), model)


@pytest.mark.parametrize("tau_s", [5.0, (20.0, 20.0, 20.0, 10.0, 10.0, 10.0), 80.0])
def test_the_banded_gls_equals_the_dense_oracle(tau_s):
    """≤ 3,000 points: the O(n) knot-grid GLS and the dense-covariance GLS give the same
    boresight (within 0.05 σ) and the same σ (within 1 %)."""
    prob = Problem(60)
    obs = prob.draw(3, np.broadcast_to(tau_s, (6,)))
    assert len(obs) <= 3000
    model = ErrorModel("gauss_markov", tau_s if isinstance(tau_s, float) else tuple(tau_s))
    sol = _gls(obs, prob.planes, model)
    orc = dense_gls(obs, MOUNT0, prob.planes, model)
    assert sol.converged
    s_gls = np.sqrt(np.diag(sol.Ninv)[0:3])
    s_orc = orc.crlb_sigma_rad
    assert np.all(np.abs(sol.state.boresight_rad - orc.boresight_rad) <= 0.05 * s_orc)
    assert np.all(np.abs(s_gls / s_orc - 1.0) <= 0.01)
    # and the estimate is where the truth is (one draw: within 4 σ)
    assert np.all(np.abs(sol.state.boresight_rad - TRUTH) <= 4 * s_orc)


def _monte_carlo(prob: Problem, tau_true: float, tau_cfg: float, seeds, thesis: bool = False):
    err, sig, err_thesis = [], [], []
    model = ErrorModel("gauss_markov", tau_cfg)
    for seed in seeds:
        obs = prob.draw(seed, tau_true)
        r = adjust(
            obs, MOUNT0, prob.planes, AdjustOptions(outliers="none", error_model=model, jackknife=False)
        )
        err.append(r.boresight_rad - TRUTH)
        sig.append(r.sigma_realistic_rad)
        if thesis:
            t = adjust(
                obs,
                MOUNT0,
                prob.planes,
                AdjustOptions(estimator="thesis", outliers="none", error_model=model, jackknife=False),
            )
            err_thesis.append(t.boresight_rad - TRUTH)
    return np.array(err), np.array(sig), np.array(err_thesis)


def test_monte_carlo_gls_sigma_is_honest_and_beats_the_thesis_estimator(small):
    """48 draws of Gauss–Markov POS errors (τ = 20 s, known): per angle the RMS error is at
    most 1.3 × the mean σ, |error| ≤ 2σ in 85–100 % of draws, and the GLS RMS is below the
    thesis estimator's for every angle, and well below it overall."""
    err, sig, err_thesis = _monte_carlo(small, 20.0, 20.0, range(48), thesis=True)
    rms = np.sqrt(np.mean(err**2, axis=0))
    coverage = np.mean(np.abs(err) <= 2 * sig, axis=0)
    assert np.all(rms <= 1.3 * sig.mean(axis=0)), (rms, sig.mean(axis=0))
    assert np.all((coverage >= 0.85) & (coverage <= 1.0)), coverage
    rms_thesis = np.sqrt(np.mean(err_thesis**2, axis=0))
    assert np.all(rms <= rms_thesis), (rms, rms_thesis)
    assert np.linalg.norm(rms) < 0.6 * np.linalg.norm(rms_thesis), (rms, rms_thesis)


@pytest.mark.parametrize("factor", [3.0, 1.0 / 3.0])
def test_monte_carlo_coverage_with_tau_misspecified(small, factor):
    """τ configured ×3 or ×1/3 of the truth (20 s): the 2σ coverage stays ≥ 0.85 per angle."""
    err, sig, _ = _monte_carlo(small, 20.0, 20.0 * factor, range(100, 140))
    coverage = np.mean(np.abs(err) <= 2 * sig, axis=0)
    assert np.all(coverage >= 0.85), coverage


@pytest.mark.parametrize("tau_s", [5.0, 20.0, 80.0])
def test_estimate_tau_recovers_the_simulated_correlation_time(small, tau_s):
    """The restricted-likelihood τ is within a factor 2 of the simulator's, for 3 draws each."""
    for seed in range(3):
        obs = small.draw(200 + seed, tau_s)
        est = estimate_tau(obs, MOUNT0, small.planes, AdjustOptions())
        assert tau_s / 2 <= est.tau_s <= 2 * tau_s, (seed, est)


def test_a_rough_plane_gets_its_roughness_and_the_boresight_stays_put(small):
    """5 mm of extra white noise normal to one plane's points: its roughness_m is 5 mm ± 30 %,
    the smooth planes' stays well below it, and the boresight is within 3σ of the truth."""
    obs = small.draw(7, 20.0)
    j = 1
    mine = obs.plane_index == j
    # a range error δr moves a point by δr·∂F/∂range normal to its plane: scale the noise so
    # that the normal displacement has σ = 5 mm
    lin = _gls(obs, small.planes, ErrorModel("gauss_markov", 20.0)).lin
    dF_dr = np.abs(lin.B[mine, 6])
    assert dF_dr.min() > 0.1  # not grazing: the scaling stays modest
    rng = np.random.default_rng(11)
    obs.l[mine, 6] += rng.standard_normal(int(mine.sum())) * 0.005 / dF_dr
    res = adjust(obs, MOUNT0, small.planes, AdjustOptions(outliers="none", jackknife=False))
    stats = {p["name"]: p for p in res.plane_stats}
    assert stats[obs.plane_names[j]]["roughness_m"] == pytest.approx(0.005, rel=0.3)
    for name, p in stats.items():
        assert p["kind"] == "target"
        if name != obs.plane_names[j]:
            assert p["roughness_m"] < 0.002, (name, p["roughness_m"])
    assert np.all(np.abs(res.boresight_rad - TRUTH) <= 3 * res.sigma_realistic_rad)


def test_a_boresight_prior_combines_with_the_data_as_information(small):
    # (the mount watch's regularization) a Gaussian prior on the boresight: the solution is the
    # information-weighted mean of the data's solution and the prior's mean, to linearization
    obs = small.draw(3, 20.0)
    model = ErrorModel("gauss_markov", 20.0)
    free = _gls(obs, small.planes, model)
    b, C = free.state.boresight_rad, free.Ninv[:3, :3]
    mean = b + np.radians([0.05, -0.03, 0.02])
    sig = np.radians([0.01, 0.02, 0.5])
    prior = _gls(
        obs, small.planes, model, AdjustOptions(outliers="none", boresight_prior_rad=np.stack([mean, sig]))
    )
    P = np.diag(1.0 / sig**2)
    post = np.linalg.inv(np.linalg.inv(C) + P)
    expect = post @ (np.linalg.solve(C, b) + P @ mean)
    assert np.allclose(prior.Ninv[:3, :3], post, rtol=0.02)
    assert np.allclose(prior.state.boresight_rad, expect, atol=np.radians(2e-4))
    assert prior.df == free.df + 3
