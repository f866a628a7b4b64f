"""Direct regression: the 256 voltage changes → contact x, y, depth, target diameter and |force|,
without an image.

Owns the features (δV relative to the measured reference, projected on its leading principal
components and whitened), fresh noise draws of the training samples (:func:`noisy_features`)
moved about the ring by the sensor's symmetries (:func:`moved_by_symmetry`), and two learned
maps from them: a ridge (linear, the baseline) and a small multilayer perceptron
(scikit-learn ``MLPRegressor``, ReLU). Both are stored as plain arrays (PCA mean and
components, layer weights and biases, output scale) and evaluated by a NumPy forward pass: no
pickle, identical predictions in a new process, and the same numbers scikit-learn's
``predict`` gives (tested).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..eit.protocol import RingSymmetry
from .data import voltage_features

__all__ = ["OUTPUTS", "KINDS", "DirectRegressor", "fit_regressor", "pca_whitening", "regression_targets", "noisy_features",
           "moved_by_symmetry"]

OUTPUTS = ("x", "y", "depth", "diameter", "force")
KINDS = ("mlp", "ridge")
RIDGE_ALPHAS = tuple(10.0 ** np.arange(-4, 4))
HIDDEN = (128, 64)


def regression_targets(position: np.ndarray, size: np.ndarray, force_mag: np.ndarray) -> np.ndarray:
    """The regression's outputs (n, 5): x, y, depth m, diameter m, |force| N."""
    return np.column_stack([position, size, force_mag])


@dataclass(frozen=True)
class DirectRegressor:
    """Features (n, m) → outputs (n, 5) (:data:`OUTPUTS`, SI). ``x_mean`` (m,), ``components``
    (k, m) and ``x_scale`` (k,) whiten the features; ``weights[i]`` (a, b) and ``biases[i]``
    (b,) are the layers (ReLU between them, none after the last); ``y_mean``, ``y_scale`` (5,)
    undo the outputs' standardisation."""

    kind: str
    x_mean: np.ndarray
    components: np.ndarray
    x_scale: np.ndarray
    weights: tuple[np.ndarray, ...]
    biases: tuple[np.ndarray, ...]
    y_mean: np.ndarray
    y_scale: np.ndarray

    def whiten(self, features: np.ndarray) -> np.ndarray:
        return ((np.asarray(features, float) - self.x_mean) @ self.components.T) / self.x_scale

    def __call__(self, features: np.ndarray) -> np.ndarray:
        """Outputs (n, 5) for features (n, m); NaN rows where a feature is not finite."""
        F = np.asarray(features, float)
        ok = np.isfinite(F).all(axis=1)
        h = self.whiten(np.where(ok[:, None], F, 0.0))
        for i, (W, b) in enumerate(zip(self.weights, self.biases)):
            h = h @ W + b
            if i < len(self.weights) - 1:
                h = np.maximum(h, 0.0)
        out = h * self.y_scale + self.y_mean
        out[~ok] = np.nan
        return out


def noisy_features(voltages_clean: np.ndarray, reference_clean: np.ndarray, snr_db: tuple[float, float] | np.ndarray,
                   reference_frames: int, copies: int, rng: np.random.Generator) -> np.ndarray:
    """``copies`` fresh noisy versions of each sample, as features (copies·n, m), copy-major.
    Each draws an SNR uniform in ``snr_db`` (a tuple (lo, hi) dB; an array (n,) is each
    sample's SNR) and the instrument's white noise as
    ``jointsim dataset`` does: standard deviation re the mean standing |V| of the sample's
    ``reference_clean`` (n, m), on ``voltages_clean`` (n, m) once and on the reference averaged
    over ``reference_frames`` (drawn per sample here; a dataset draws one reference per press,
    shared by its samples). The simulator's clean voltages are the expensive part of a
    sample; noise draws are free, and a regressor that sees many of them learns to average the
    noise instead of fitting the few draws the store holds."""
    from ..eit.noise import noise_std

    v, ref = np.asarray(voltages_clean, float), np.asarray(reference_clean, float)
    out = []
    for _ in range(copies):
        snr = rng.uniform(snr_db[0], snr_db[1], len(v)) if isinstance(snr_db, tuple) else np.asarray(snr_db, float)
        std = np.array([noise_std(r, q) for r, q in zip(ref, snr)])[:, None]
        measured = v + std * rng.standard_normal(v.shape)
        measured_ref = ref + std / np.sqrt(reference_frames) * rng.standard_normal(v.shape)
        out.append(voltage_features(measured, measured - measured_ref))
    return np.vstack(out) if out else np.empty((0, v.shape[1]))


def copy_groups(group: np.ndarray, copies: int) -> np.ndarray:
    """Press ids (copies·n,) for :func:`noisy_features`' copy-major rows of samples of presses
    ``group`` (n,): each copy of a press a press of its own (its frames share one noise draw of
    the reference, as a press's do)."""
    group = np.asarray(group)
    return np.tile(group, copies) + np.repeat(np.arange(copies), len(group)) * (group.max() + 1)


def moved_by_symmetry(features: np.ndarray, targets: np.ndarray, symmetries: Sequence[RingSymmetry],
                      rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Each sample (features (n, m), targets (n, 5)) moved by one of ``symmetries`` drawn
    uniformly: its features read through the symmetry's measurement map, its contact (x, y)
    moved with it; depth, size and force stay. A press turned by an electrode pitch, or
    mirrored, is a press the sensor could have seen; the dataset holds each at one place only.
    The features are ratios δV/V of the same measurement, so a reversed pair's sign cancels."""
    X, T = np.array(features, float), np.array(targets, float)
    pick = rng.integers(0, len(symmetries), len(X))
    for i, g in enumerate(symmetries):
        rows = np.flatnonzero(pick == i)
        X[rows] = X[rows][:, g.source]
        T[rows, :2] = g.positions(T[rows, :2])
    return X, T


def _ridge_alpha(Z: np.ndarray, T: np.ndarray, groups: np.ndarray) -> float:
    """The ridge penalty of least grouped-CV squared error (3 folds by press)."""
    from sklearn.linear_model import Ridge
    from sklearn.model_selection import GroupKFold

    folds = int(min(3, len(np.unique(groups))))
    err = {}
    for a in RIDGE_ALPHAS:
        e = 0.0
        for tr, te in GroupKFold(n_splits=folds).split(Z, T, groups):
            e += float(((Ridge(alpha=a).fit(Z[tr], T[tr]).predict(Z[te]) - T[te]) ** 2).sum())
        err[a] = e
    return min(err, key=err.get)


def pca_whitening(X: np.ndarray, n_components: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The leading principal components of ``X`` (n, m), whitened: (mean (m,), components (k, m),
    scale (k,), the whitened X (n, k)), k at most ``n_components``."""
    from sklearn.decomposition import PCA

    k = int(min(n_components, X.shape[1], len(X) - 1))
    pca = PCA(n_components=k, svd_solver="full").fit(X)
    x_scale = np.sqrt(pca.explained_variance_)
    x_scale = np.where(x_scale > 0, x_scale, 1.0)
    return pca.mean_.copy(), pca.components_.copy(), x_scale, ((X - pca.mean_) @ pca.components_.T) / x_scale


def fit_regressor(
    features: np.ndarray, targets: np.ndarray, groups: np.ndarray, *, kind: str = "mlp", seed: int = 0,
    n_components: int = 48,
) -> DirectRegressor:
    """Fit on training samples: ``features`` (n, m), ``targets`` (n, 5), ``groups`` (n,) press
    ids (the ridge's penalty is chosen by grouped CV). Rows with non-finite values are dropped."""
    from sklearn.linear_model import Ridge
    from sklearn.neural_network import MLPRegressor

    if kind not in KINDS:
        raise ValueError(f"regressor kind = {kind!r}: one of {KINDS}")
    ok = np.isfinite(features).all(axis=1) & np.isfinite(targets).all(axis=1)
    X, T, g = np.asarray(features, float)[ok], np.asarray(targets, float)[ok], groups[ok]
    if len(X) < 10:
        raise ValueError(f"the direct regression needs at least 10 samples with finite voltages and labels, got {len(X)}")
    x_mean, components, x_scale, Z = pca_whitening(X, n_components)
    y_mean, y_scale = T.mean(axis=0), T.std(axis=0)
    y_scale = np.where(y_scale > 0, y_scale, 1.0)
    S = (T - y_mean) / y_scale
    if kind == "ridge":
        r = Ridge(alpha=_ridge_alpha(Z, S, g)).fit(Z, S)
        weights, biases = (r.coef_.T.copy(),), (np.atleast_1d(r.intercept_).copy(),)
    else:
        m = MLPRegressor(hidden_layer_sizes=HIDDEN, alpha=1e-3, learning_rate_init=1e-3, max_iter=2000,
                         early_stopping=len(X) >= 200, n_iter_no_change=30, tol=1e-6, random_state=seed).fit(Z, S)
        weights, biases = tuple(w.copy() for w in m.coefs_), tuple(b.copy() for b in m.intercepts_)
    return DirectRegressor(kind, x_mean, components, x_scale, weights, biases, y_mean, y_scale)
