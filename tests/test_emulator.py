"""Model-based estimation (jointsim.calibration.emulator): the emulator's derivative is its
function's, the per-frame fit is the maximum-likelihood estimate with the inverse Fisher
information as its covariance (checked where the model is the emulator itself: the estimates'
scatter matches the covariance they report), and a press's frames fitted jointly share x, y
and the diameter, which they then know better than one frame does."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from jointsim.calibration.emulator import Emulator, fit_emulator, fit_frames, fit_press, recalibrated, shared_part

K = 8


def _emulator(seed: int = 0, noise: float = 0.05) -> Emulator:
    """A small smooth-enough perceptron θ → 8 features (θ in mm-ish units), identity whitening."""
    rng = np.random.default_rng(seed)
    W = (rng.normal(0, 1, (4, 24)), rng.normal(0, 0.4, (24, K)))
    b = (rng.normal(0, 0.5, 24), rng.normal(0, 0.1, K))
    t_mean, t_scale = np.array([0.0, 0.0, 1.5e-3, 15e-3]), np.array([6e-3, 6e-3, 0.8e-3, 6e-3])
    return Emulator(t_mean, t_scale, W, b, np.zeros(K), np.eye(K), np.ones(K), noise**2 * np.eye(K))


def test_the_jacobian_is_the_derivative():
    emu = _emulator()
    theta = np.array([[2e-3, -1e-3, 1.2e-3, 12e-3], [-4e-3, 3e-3, 2.0e-3, 20e-3]])
    _, J = emu.evaluate(theta)
    h = 1e-9
    for j in range(4):
        d = np.zeros(4)
        d[j] = h
        fd = (emu(theta + d) - emu(theta - d)) / (2 * h)
        np.testing.assert_allclose(J[:, j, :], fd, rtol=1e-5, atol=1e-6 * np.abs(fd).max())


def test_frames_fitted_through_the_model_scatter_as_their_reported_covariance():
    """Frames drawn from the emulator with its Gaussian noise, small enough that the model is
    linear over the noise's reach (the regime where the inverse Fisher information is the
    estimator's covariance; at 10× the noise this perceptron's kinks already make 1σ cover 44 %):
    each fit from a start 0.5 mm off finds the truth within its reported σ as often as a
    Gaussian does (68 % within 1σ, 95 % within 2σ, ±5 % and ±4 % over 600 draws), and
    noise-free frames give the truth itself."""
    emu = _emulator(noise=0.001)
    rng = np.random.default_rng(1)
    truth = np.array([1e-3, -2e-3, 1.5e-3, 14e-3])
    clean = emu(truth[None])[0]
    start = truth + np.array([0.5e-3, -0.5e-3, 0.3e-3, 0.5e-3])
    est, cov = fit_frames(emu, clean[None], start[None])
    np.testing.assert_allclose(est[0], truth, atol=1e-8)
    n = 600
    frames = clean + rng.multivariate_normal(np.zeros(K), emu.covariance, n)
    est, cov = fit_frames(emu, frames, np.tile(start, (n, 1)))
    z = np.abs(est - truth) / np.sqrt(np.einsum("nii->ni", cov))
    assert np.all(np.abs((z < 1).mean(axis=0) - 0.683) < 0.05), (z < 1).mean(axis=0)
    assert np.all(np.abs((z < 2).mean(axis=0) - 0.954) < 0.04), (z < 2).mean(axis=0)


def test_a_press_fitted_jointly_shares_position_and_size_and_knows_them_better():
    """Five frames of one press at five depths: the joint fit returns one x, y and diameter for
    all, a depth for each, and a σ of x at most the single frames' smallest (it pools them)."""
    emu = _emulator()
    rng = np.random.default_rng(2)
    depths = np.array([0.6e-3, 1.0e-3, 1.5e-3, 2.0e-3, 2.5e-3])
    truth = np.column_stack([np.full(5, 2e-3), np.full(5, 1e-3), depths, np.full(5, 16e-3)])
    frames = emu(truth) + rng.multivariate_normal(np.zeros(K), emu.covariance, 5)
    start = truth + 0.3e-3
    est, cov = fit_press(emu, frames, start)
    assert np.ptp(est[:, 0]) == 0 and np.ptp(est[:, 1]) == 0 and np.ptp(est[:, 3]) == 0
    _, cov1 = fit_frames(emu, frames, start)
    assert np.sqrt(cov[0, 0, 0]) <= np.sqrt(cov1[:, 0, 0]).min() * (1 + 1e-9)
    assert np.all(np.abs(est - truth) < 5 * np.sqrt(np.einsum("nii->ni", cov)))


def test_an_emulator_learns_a_smooth_model_and_refuses_too_few_samples():
    """Trained on 600 noise-free samples of a smooth θ → 16 features map, it predicts held-out
    presses with R² > 0.99 in the whitened space; fewer than 50 samples are refused."""
    rng = np.random.default_rng(3)
    A = rng.normal(size=(4, 16))

    def model(t):
        u = (t - [0, 0, 1.5e-3, 15e-3]) / [6e-3, 6e-3, 0.8e-3, 6e-3]
        return np.tanh(u @ A) + 0.1 * (u @ A) ** 2

    T = np.column_stack([rng.uniform(-10e-3, 10e-3, (700, 2)), rng.uniform(0.3e-3, 3e-3, 700), rng.uniform(8e-3, 30e-3, 700)])
    groups = np.arange(700) // 3
    emu = fit_emulator(model(T[:600]), T[:600], groups[:600], n_components=8)
    Z = emu.whiten(model(T[600:]))
    r2 = 1 - ((Z - emu(T[600:])) ** 2).sum() / ((Z - Z.mean(axis=0)) ** 2).sum()
    assert r2 > 0.99
    assert np.all(np.linalg.eigvalsh(emu.covariance) > 0)
    with pytest.raises(ValueError, match="at least 50 samples"):
        fit_emulator(model(T[:40]), T[:40], groups[:40])


def test_what_a_press_shares_is_not_counted_once_per_frame():
    """Presses of five frames whose residuals share 80 % of their covariance (a press's
    nuisances, drawn once): fitted with that shared part S, the joint fit's σ of x covers the
    truth as a Gaussian does (68 % within 1σ, ± 10 % over 200 presses; the errors' RMS in σ 1 ±
    15 %, three times its sampling error); fitted as if the frames were independent, its σ is
    too small (RMS over 1.4: were x held by the frames' mean alone, √(1 + 4 × 0.8) = 2.05)."""
    base = _emulator(noise=0.001)
    C = base.covariance
    with_shared = replace(base, residual=C, shared=0.8 * C)
    rng = np.random.default_rng(4)
    depths = np.array([0.6e-3, 1.0e-3, 1.5e-3, 2.0e-3, 2.5e-3])
    truth = np.column_stack([np.full(5, 2e-3), np.full(5, 1e-3), depths, np.full(5, 16e-3)])
    clean = base(truth)
    z = {True: [], False: []}
    for _ in range(200):
        frames = clean + rng.multivariate_normal(np.zeros(K), 0.8 * C) + rng.multivariate_normal(np.zeros(K), 0.2 * C, 5)
        for shared, emu in ((True, with_shared), (False, base)):
            est, cov = fit_press(emu, frames, truth)
            z[shared].append(abs(est[0, 0] - truth[0, 0]) / np.sqrt(cov[0, 0, 0]))
    rms = {k: float(np.sqrt(np.mean(np.square(v)))) for k, v in z.items()}
    assert abs(np.mean(np.array(z[True]) < 1) - 0.683) < 0.1, np.mean(np.array(z[True]) < 1)
    assert abs(rms[True] - 1) < 0.15 and rms[False] > 1.4, rms


def test_the_shared_part_is_the_covariance_between_a_press_frames():
    """Residuals r = a + e per frame, a ~ N(0, S) drawn once per press of six frames, e ~ N(0,
    D): ``shared_part`` recovers S within 15 % (Frobenius; 600 presses give ~5 %), and zero for
    independent frames (within 0.1 of C)."""
    rng = np.random.default_rng(5)
    k, n, m = 4, 600, 6
    B = rng.normal(size=(k, k))
    S, D = B @ B.T / k, np.diag(rng.uniform(0.5, 1.5, k))
    groups = np.repeat(np.arange(n), m)
    R = np.repeat(rng.multivariate_normal(np.zeros(k), S, n), m, axis=0) + rng.multivariate_normal(np.zeros(k), D, n * m)
    R -= R.mean(axis=0)
    C = np.cov(R.T)
    assert np.linalg.norm(shared_part(R, groups, C) - S) < 0.15 * np.linalg.norm(S)
    E = rng.multivariate_normal(np.zeros(k), D, n * m)
    assert np.linalg.norm(shared_part(E - E.mean(axis=0), groups, np.cov(E.T))) < 0.1 * np.linalg.norm(D)


def test_a_parameter_the_frames_do_not_hold_is_the_prior():
    """An emulator blind to the diameter (its first layer's diameter row zero): a fit returns
    the prior's mean and σ for it, while the frames' position barely feels the prior (its σ
    is thousands of the data's: moved by under 1 % of the data's σ)."""
    base = _emulator(noise=0.001)
    W0 = base.weights[0].copy()
    W0[3] = 0.0
    blind = replace(base, weights=(W0, *base.weights[1:]))
    prior = replace(blind, prior_mean=np.array([0.0, 0.0, 1.5e-3, 15e-3]), prior_sd=np.array([6e-3, 6e-3, 0.8e-3, 6e-3]))
    truth = np.array([1e-3, -2e-3, 1.5e-3, 22e-3])
    frame = blind(truth[None]) + np.random.default_rng(6).multivariate_normal(np.zeros(K), blind.covariance)
    est, cov = fit_frames(prior, frame, (truth + 0.3e-3)[None])
    assert est[0, 3] == pytest.approx(15e-3, abs=1e-9) and np.sqrt(cov[0, 3, 3]) == pytest.approx(6e-3, rel=1e-6)
    alone, alone_cov = fit_frames(blind, frame, (truth + 0.3e-3)[None])  # the same frame, no prior
    sd = np.sqrt(np.diag(alone_cov[0])[:3])
    assert np.all(np.abs(est[0, :3] - alone[0, :3]) < 1e-2 * sd), (est[0, :3] - alone[0, :3]) / sd


def test_the_instrument_snr_is_read_from_the_reference_frames_scatter():
    """20 frames of the untouched sensor at 74.2 dB (add_noise's convention): the SNR read back
    from their scatter within 0.3 dB (5120 samples of the variance: ~0.1 dB sampling error); one
    frame, or frames that do not scatter, give none."""
    from jointsim.eit.noise import add_noise
    from jointsim.studies.measured import reference_snr_db

    v = 1e-2 * (1.0 + np.sin(np.arange(256)))
    frames = np.array([add_noise(v, 74.2, rng=i) for i in range(20)])
    assert reference_snr_db(frames) == pytest.approx(74.2, abs=0.3)
    assert reference_snr_db(frames[:1]) is None and reference_snr_db(np.tile(v, (3, 1))) is None


def test_sigma_recalibrated_on_presses_the_emulator_did_not_see():
    """Frames whose residual is 3× what the emulator's covariance says (its σ 3× too small):
    recalibrated on 150 presses of 4 frames, each parameter's per-frame factor is at least 3
    (and under 4.5: this perceptron's curvature over 3× the noise adds its own error), and on
    150 other presses the recalibrated σ covers the truth 68 % of the time (± 8 %: 600 draws)."""
    emu = _emulator(noise=0.001)
    rng = np.random.default_rng(7)

    def presses(n):
        centre = np.column_stack([rng.uniform(-3e-3, 3e-3, (n, 2)), np.full(n, 16e-3)])
        depths = np.array([0.8e-3, 1.2e-3, 1.6e-3, 2.0e-3])
        truth = np.column_stack([np.repeat(centre[:, :2], 4, axis=0), np.tile(depths, n), np.repeat(centre[:, 2], 4)])
        frames = emu(truth) + 3 * rng.multivariate_normal(np.zeros(K), emu.covariance, len(truth))
        return frames, truth, np.repeat(np.arange(n), 4)

    frames, truth, group = presses(150)
    cal = recalibrated(emu, frames, truth + 0.2e-3, truth, group)
    assert np.all((cal.sd_scale[0] > 3 * 0.95) & (cal.sd_scale[0] < 4.5)), cal.sd_scale
    frames, truth, _ = presses(150)
    est, cov = fit_frames(cal, frames, truth + 0.2e-3)
    z = np.abs(est - truth) / np.sqrt(np.einsum("nii->ni", cov))
    assert np.all(np.abs((z < 1).mean(axis=0) - 0.683) < 0.08), (z < 1).mean(axis=0)
