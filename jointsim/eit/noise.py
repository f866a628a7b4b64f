"""Measurement noise in the paper's convention: SNR = 20·log10(mean |V_standing| / std), plus an
optional slow multiplicative drift of each channel's gain."""

from __future__ import annotations

import numpy as np

__all__ = ["noise_std", "add_noise", "gain_drift"]


def noise_std(standing: np.ndarray, snr_db: float) -> float:
    """Noise standard deviation for ``snr_db`` relative to the mean absolute standing voltage."""
    if not np.isfinite(snr_db):
        raise ValueError(f"snr_db = {snr_db}: must be finite")
    ref = float(np.mean(np.abs(standing)))
    if ref == 0:
        raise ValueError("standing voltages are all zero: the SNR reference is undefined")
    return ref / 10 ** (snr_db / 20)


def add_noise(
    v: np.ndarray,
    snr_db: float,
    rng: np.random.Generator | int | None = None,
    standing: np.ndarray | None = None,
) -> np.ndarray:
    """``v`` (…, n_meas) plus white Gaussian noise at ``snr_db`` re the mean |standing| voltage
    (``v`` itself when not given). Seeded by ``rng`` (a Generator or an int seed)."""
    rng = np.random.default_rng(rng)
    std = noise_std(v if standing is None else standing, snr_db)
    return v + rng.normal(0.0, std, size=np.shape(v))


def gain_drift(
    n_frames: int,
    n_meas: int,
    drift_per_s: float,
    frame_rate_hz: float = 50.0,
    rng: np.random.Generator | int | None = None,
) -> np.ndarray:
    """Multiplicative gains (n_frames, n_meas), 1 at frame 0, each channel an independent random
    walk with std(g(t) − 1) = drift_per_s·√(t / 1 s). Multiply clean voltages by it before
    adding noise."""
    if drift_per_s < 0:
        raise ValueError(f"drift_per_s = {drift_per_s}: must be >= 0")
    rng = np.random.default_rng(rng)
    dt = 1.0 / frame_rate_hz
    steps = rng.normal(0.0, drift_per_s * np.sqrt(dt), size=(n_frames, n_meas))
    steps[0] = 0.0
    return 1.0 + np.cumsum(steps, axis=0)
