"""Noise models: Gauss–Markov processes reproduce σ and correlation time, exactly
across gaps; white and per-point errors; range noise growing with range and incidence;
seeded reproducibility."""

from __future__ import annotations

import numpy as np
import pytest

from calib.sim.noise import PosNoise, ScannerNoise, gauss_markov, white_noise


def _autocorr(x: np.ndarray, lag: int) -> np.ndarray:
    x = x - x.mean(axis=0)
    return np.sum(x[:-lag] * x[lag:], axis=0) / np.sum(x * x, axis=0)


def test_gauss_markov_reproduces_sigma_and_correlation_time_on_a_long_run():
    dt = 0.25
    t = 1.2e9 + np.arange(1_000_000) * dt  # ~70 h at 4 Hz, on the GPS time scale
    sigma = np.array([0.02, 0.01, np.radians(0.012)])
    tau = np.array([2.0, 20.0, 10.0])
    x = gauss_markov(t, sigma, tau, np.random.default_rng(1))
    assert x.shape == (t.size, 3)
    np.testing.assert_allclose(x.std(axis=0), sigma, rtol=0.10)
    for j in range(3):
        lag = int(round(tau[j] / dt))  # the autocorrelation at lag τ is e⁻¹
        tau_hat = -lag * dt / np.log(_autocorr(x[:, j], lag))
        assert tau_hat == pytest.approx(tau[j], rel=0.10)
        # and the whole curve decays exponentially: at 3τ it is e⁻³
        r3 = _autocorr(x[:, j], 3 * lag)
        assert r3 == pytest.approx(np.exp(-3.0), abs=0.03)


def test_gauss_markov_is_exact_across_gaps_and_starts_stationary():
    # many independent channels sampled at 0, 0.1, then after a gap of 7 s
    k = 40000
    sigma = np.full(k, 0.5)
    x = gauss_markov(np.array([0.0, 0.1, 7.1]), sigma, 5.0, np.random.default_rng(2))
    np.testing.assert_allclose(x.std(axis=1), 0.5, rtol=0.03)
    corr_step = np.corrcoef(x[0], x[1])[0, 1]
    corr_gap = np.corrcoef(x[1], x[2])[0, 1]
    assert corr_step == pytest.approx(np.exp(-0.1 / 5.0), abs=0.01)
    assert corr_gap == pytest.approx(np.exp(-7.0 / 5.0), abs=0.015)


@pytest.mark.parametrize(("n", "k"), [(400, 2), (6, 50)])  # long runs filtered, short runs stepped
def test_gauss_markov_follows_the_exact_recursion(n, k):
    t = np.concatenate([np.arange(n // 2) * 0.1, 30.0 + np.arange(n - n // 2) * 0.1])
    sigma, tau = np.linspace(0.5, 2.0, k), np.linspace(1.0, 9.0, k)
    x = gauss_markov(t, sigma, tau, np.random.default_rng(9))
    w = np.random.default_rng(9).standard_normal((n, k))  # the same draws, by hand
    ref = np.empty((n, k))
    ref[0] = sigma * w[0]
    for i in range(1, n):
        phi = np.exp(-(t[i] - t[i - 1]) / tau)
        ref[i] = phi * ref[i - 1] + sigma * np.sqrt(1 - phi**2) * w[i]
    np.testing.assert_allclose(x, ref, rtol=1e-9, atol=1e-12)


def test_white_noise_is_independent_with_its_sigma():
    x = white_noise(200000, [0.02, 3.0], np.random.default_rng(3))
    np.testing.assert_allclose(x.std(axis=0), [0.02, 3.0], rtol=0.01)
    assert np.all(np.abs(_autocorr(x, 1)) < 0.01)


def test_pos_noise_models_and_seeds():
    t = np.arange(5000) * 0.02
    kw = dict(sigma_position_m=[0.02, 0.02, 0.03], sigma_attitude_rad=np.radians([0.01] * 3))
    for model in ("white", "gauss_markov"):
        m = PosNoise(model, **kw)
        a = m.epoch_errors(t, np.random.default_rng(5))
        b = m.epoch_errors(t, np.random.default_rng(5))
        c = m.epoch_errors(t, np.random.default_rng(6))
        assert a.shape == (5000, 6) and np.array_equal(a, b) and not np.array_equal(a, c)
        assert m.point_errors(10, np.random.default_rng(5)) is None
    pp = PosNoise("per_point", **kw)
    assert np.all(pp.epoch_errors(t, np.random.default_rng(5)) == 0)
    e = pp.point_errors(100000, np.random.default_rng(5))
    np.testing.assert_allclose(e.std(axis=0), pp.sigma, rtol=0.02)
    none = PosNoise("none", **kw)
    assert np.all(none.sigma == 0) and np.all(none.epoch_errors(t, np.random.default_rng(1)) == 0)
    with pytest.raises(ValueError, match="model is 'pink'"):
        PosNoise("pink")
    with pytest.raises(ValueError, match="sigma_position_m must be 3 finite numbers ≥ 0"):
        PosNoise("white", sigma_position_m=[-1, 0, 0])
    with pytest.raises(ValueError, match="correlation times > 0"):
        PosNoise("gauss_markov", tau_attitude_s=[0, 1, 1])


def test_range_noise_grows_with_range_and_incidence():
    n = ScannerNoise(
        sigma_range_m=0.002,
        sigma_range_per_m=1e-5,
        beam_divergence_rad=5e-4,
        sigma_scan_angle_rad=np.radians(0.005),
    )
    rho = np.array([10.0, 10.0, 100.0, 10.0])
    cos_inc = np.array([1.0, 0.5, 1.0, 0.0])
    s = n.range_sigma(rho, cos_inc)
    assert s[0] == pytest.approx(0.002 + 1e-4)
    assert s[1] == pytest.approx(0.002 + 1e-4 + 10.0 * 2.5e-4 * np.sqrt(3.0))
    assert s[2] == pytest.approx(0.002 + 1e-3)
    assert s[3] == pytest.approx(0.002 + 1e-4 + 10.0 * 2.5e-4 * np.tan(np.radians(89.0)))
    big = np.full(100000, 20.0)
    dr, da = n.draw(big, np.full(100000, 0.5), np.random.default_rng(0))
    assert dr.std() == pytest.approx(float(n.range_sigma(20.0, 0.5)), rel=0.02)
    assert da.std() == pytest.approx(np.radians(0.005), rel=0.02)
    assert ScannerNoise().is_zero and not n.is_zero
    with pytest.raises(ValueError, match="sigma_range_m must be a finite number ≥ 0"):
        ScannerNoise(sigma_range_m=-0.1)
