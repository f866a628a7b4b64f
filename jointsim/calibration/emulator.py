"""Model-based estimation: an emulator of the coupled model, and the fit of a frame's (or a
press's frames') parameters through it, with an uncertainty per estimate.

The emulator maps a press θ = (x, y, depth, diameter) — the contact's centre of pressure, the
depth past first contact, the target's diameter, m — to the expected features of its frame,
z(θ) = E[W(f(v))], where f is the calibration's feature (δV over the standing voltage) and W the
whitening of its leading principal components: a multilayer perceptron trained on a dataset's
noise-free samples, evaluated (and differentiated) in NumPy from plain arrays. What it does not
explain — the nuisances the dataset randomises (membrane modulus, conductivity, contact
impedances, electrode placement), its own error, and the instrument's noise — is a Gaussian
with covariance C, estimated from held-out presses' residuals and the noise's own draws.

A frame's estimate is the maximum of the likelihood, θ̂ = argmin (z − z(θ))ᵀ C⁻¹ (z − z(θ)),
by Levenberg–Marquardt from a start (the direct regression's estimate), and its covariance
the inverse Fisher information there, (Jᵀ C⁻¹ J)⁻¹ with J = ∂z/∂θ. A press's frames share x, y
and the diameter and each has its depth: fitted jointly, their 3 + m parameters at once.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["PARAMETERS", "Emulator", "fit_emulator", "fit_frames", "fit_press", "fit_presses"]

PARAMETERS = ("x", "y", "depth", "diameter")
HIDDEN = (128, 128)


@dataclass(frozen=True)
class Emulator:
    """θ (n, 4) m → whitened features (n, k). ``t_mean``, ``t_scale`` (4,) standardise θ;
    ``weights[i]`` (a, b), ``biases[i]`` (b,) the layers (ReLU between, none after the last);
    ``x_mean`` (m,), ``components`` (k, m), ``x_scale`` (k,) whiten the features (what
    :meth:`whiten` applies to a frame's); ``covariance`` (k, k) the residual's C."""

    t_mean: np.ndarray
    t_scale: np.ndarray
    weights: tuple[np.ndarray, ...]
    biases: tuple[np.ndarray, ...]
    x_mean: np.ndarray
    components: np.ndarray
    x_scale: np.ndarray
    covariance: np.ndarray

    def whiten(self, features: np.ndarray) -> np.ndarray:
        return ((np.asarray(features, float) - self.x_mean) @ self.components.T) / self.x_scale

    def __call__(self, theta: np.ndarray) -> np.ndarray:
        return self.evaluate(theta)[0]

    def evaluate(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(z (n, k), J (n, 4, k) = ∂z/∂θ per m) at θ (n, 4)."""
        h = (np.atleast_2d(np.asarray(theta, float)) - self.t_mean) / self.t_scale
        J = np.broadcast_to(np.diag(1.0 / self.t_scale), (len(h), 4, 4))
        for i, (W, b) in enumerate(zip(self.weights, self.biases)):
            h = h @ W + b
            J = J @ W
            if i < len(self.weights) - 1:
                on = h > 0
                h = np.where(on, h, 0.0)
                J = J * on[:, None, :]
        return h, J


def fit_emulator(features: np.ndarray, theta: np.ndarray, groups: np.ndarray, noise: np.ndarray | None = None, *,
                 seed: int = 0, n_components: int = 32, held_out: float = 0.2) -> Emulator:
    """Train on noise-free ``features`` (n, m) of presses ``theta`` (n, 4) m, press ids
    ``groups`` (n,): the whitening from all, the perceptron on the presses not held out, C from
    the held-out presses' residuals (the emulator's error and the nuisances, as a new press
    meets them) plus the covariance of ``noise`` (features' noisy minus clean, (r, m), the
    instrument's), when given."""
    from sklearn.neural_network import MLPRegressor

    from .regression import pca_whitening

    X, T = np.asarray(features, float), np.asarray(theta, float)
    ok = np.isfinite(X).all(axis=1) & np.isfinite(T).all(axis=1)
    X, T, g = X[ok], T[ok], np.asarray(groups)[ok]
    if len(X) < 50:
        raise ValueError(f"an emulator needs at least 50 samples with finite features and labels, got {len(X)}")
    x_mean, components, x_scale, Z = pca_whitening(X, n_components)
    k = len(x_scale)
    ids = np.unique(g)
    out = np.isin(g, np.random.default_rng(seed).permutation(ids)[: max(2, int(round(held_out * len(ids))))])
    t_mean, t_scale = T[~out].mean(axis=0), T[~out].std(axis=0)
    t_scale = np.where(t_scale > 0, t_scale, 1.0)
    m = MLPRegressor(hidden_layer_sizes=HIDDEN, alpha=1e-4, learning_rate_init=1e-3, max_iter=3000, early_stopping=True,
                     n_iter_no_change=50, tol=1e-7, random_state=seed).fit((T[~out] - t_mean) / t_scale, Z[~out])
    emu = Emulator(t_mean, t_scale, tuple(w.copy() for w in m.coefs_), tuple(b.copy() for b in m.intercepts_),
                   x_mean, components, x_scale, np.eye(k))
    R = Z[out] - emu(T[out])
    C = np.cov(R.T)
    if noise is not None and len(noise):
        C = C + np.cov((np.asarray(noise, float) @ components.T / x_scale).T)
    return Emulator(emu.t_mean, emu.t_scale, emu.weights, emu.biases, emu.x_mean, emu.components, emu.x_scale, C)


def _levenberg_marquardt(residual_and_jacobian, p0: np.ndarray, Ci: np.ndarray, iters: int = 60):
    """argmin rᵀ C⁻¹ r from ``p0``, where ``residual_and_jacobian(p)`` gives r (k,) and its
    derivative J = ∂r/∂p (len(p), k); (p, J C⁻¹ Jᵀ at p, the cost)."""
    p = np.array(p0, float)
    r, J = residual_and_jacobian(p)
    cost, lam = float(r @ Ci @ r), 1e-3
    for _ in range(iters):
        H, grad = J @ Ci @ J.T, J @ Ci @ r
        step = -np.linalg.solve(H + lam * np.diag(np.diag(H)) + 1e-12 * np.trace(H) * np.eye(len(p)), grad)
        rn, Jn = residual_and_jacobian(p + step)
        cn = float(rn @ Ci @ rn)
        if cn < cost:
            p, r, J, cost, lam = p + step, rn, Jn, cn, max(lam / 3, 1e-7)
            if np.all(np.abs(step) < 1e-9):
                break
        else:
            lam *= 5
            if lam > 1e8:
                break
    return p, J @ Ci @ J.T, cost


def fit_frames(emulator: Emulator, features: np.ndarray, start: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each frame's θ̂ (n, 4) m from its features (n, m), started at ``start`` (n, 4), and its
    covariance (n, 4, 4) m²; NaN where a frame's features are not finite."""
    Z = emulator.whiten(np.where(np.isfinite(features), features, 0.0))
    Ci = np.linalg.inv(emulator.covariance)
    est, cov = np.full((len(Z), 4), np.nan), np.full((len(Z), 4, 4), np.nan)
    for i in np.flatnonzero(np.isfinite(features).all(axis=1) & np.isfinite(start).all(axis=1)):
        def rj(p, z=Z[i]):
            f, J = emulator.evaluate(p)
            return z - f[0], -J[0]
        p, H, _ = _levenberg_marquardt(rj, start[i], Ci)
        est[i], cov[i] = p, np.linalg.pinv(H)
    return est, cov


def fit_press(emulator: Emulator, features: np.ndarray, start: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One press's frames (m, features) fitted jointly: x, y and the diameter shared, a depth per
    frame, started at ``start`` (m, 4) (their mean for the shared ones). The frames' θ̂ (m, 4)
    and the covariance of each frame's four (m, 4, 4) m², from the joint Fisher information."""
    ok = np.isfinite(features).all(axis=1) & np.isfinite(start).all(axis=1)
    Z = emulator.whiten(features[ok])
    m = len(Z)
    Ci = np.linalg.inv(emulator.covariance)
    Cim = np.kron(np.eye(m), Ci)

    def unpack(p):
        th = np.empty((m, 4))
        th[:, [0, 1, 3]] = p[:3]
        th[:, 2] = p[3:]
        return th

    def rj(p):
        f, J = emulator.evaluate(unpack(p))  # (m, k), (m, 4, k)
        k = f.shape[1]
        Jp = np.zeros((3 + m, m * k))
        for j in range(m):
            Jp[:3, j * k:(j + 1) * k] = J[j][[0, 1, 3]]
            Jp[3 + j, j * k:(j + 1) * k] = J[j][2]
        return (Z - f).ravel(), -Jp

    s = start[ok]
    p0 = np.concatenate([[s[:, 0].mean(), s[:, 1].mean(), s[:, 3].mean()], s[:, 2]])
    p, H, _ = _levenberg_marquardt(rj, p0, Cim)
    P = np.linalg.pinv(H)
    est, cov = np.full((len(features), 4), np.nan), np.full((len(features), 4, 4), np.nan)
    est[ok] = unpack(p)
    for j, i in enumerate(np.flatnonzero(ok)):
        sel = [0, 1, 3 + j, 2]  # x, y, depth_j, diameter in θ's order
        cov[i] = P[np.ix_(sel, sel)]
    return est, cov


def fit_presses(emulator: Emulator, features: np.ndarray, start: np.ndarray, group: np.ndarray,
                min_depth: float = -np.inf) -> tuple[np.ndarray, np.ndarray]:
    """:func:`fit_press` for each press of ``group`` (n,): its frames that ``start`` puts at least
    ``min_depth`` deep, fitted jointly; θ̂ (n, 4) m and covariances (n, 4, 4) m², NaN for the
    frames left out."""
    est, cov = np.full((len(features), 4), np.nan), np.full((len(features), 4, 4), np.nan)
    for k in np.unique(group):
        i = np.flatnonzero((group == k) & (start[:, 2] >= min_depth))
        if len(i):
            est[i], cov[i] = fit_press(emulator, features[i], start[i])
    return est, cov
