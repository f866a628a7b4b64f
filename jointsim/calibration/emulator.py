"""Model-based estimation: an emulator of the coupled model, and the fit of a frame's (or a
press's frames') parameters through it, with an uncertainty per estimate.

The emulator maps a press θ = (x, y, depth, diameter) — the contact's centre of pressure, the
depth past first contact, the target's diameter, m — to the expected features of its frame,
z(θ) = E[W(f(v))], where f is the calibration's feature (δV over the standing voltage) and W the
whitening of its leading principal components: a multilayer perceptron trained on a dataset's
noise-free samples, evaluated (and differentiated) in NumPy from plain arrays. What it does not
explain — the nuisances the dataset randomises (membrane modulus, conductivity, contact
impedances, electrode placement), its own error, and the instrument's noise — is a Gaussian
with covariance C = R + N: R from held-out presses' residuals, N the noise's, from its own
draws scaled to the frame's SNR (N(snr) = N₀ 10^(−snr/10)). Of C, the part S a press carries to
each of its frames is shared: R's part (its nuisances are drawn once per press), the held-out
residuals' covariance between two frames of one press; and N's, the reference frame's noise,
a share 1/(r + 1) of N when the reference averages r frames. The rest, C − S, is new in every
frame.

The training presses' labels are the prior, θ ~ N(μ, diag(s²)) (their mean and spread): a
frame's estimate is the posterior's mode,

    θ̂ = argmin (z − z(θ))ᵀ C⁻¹ (z − z(θ)) + Σᵢ ((θᵢ − μᵢ)/sᵢ)²,

by Levenberg–Marquardt from a start (the direct regression's estimate), and its covariance the
inverse of the Fisher information plus the prior's, (Jᵀ C⁻¹ J + diag(s⁻²))⁻¹ with J = ∂z/∂θ.
Where the frames hold a parameter (position, depth) the prior barely moves it (its s is tens
of the data's σ); where they do not (the diameter, mostly), the estimate stays near the
training mean and says so with a σ near the training spread, instead of an extrapolation with
a σ the linearisation makes up. A press's frames share x, y and the diameter and each has its
depth: fitted jointly, their 3 + m parameters at once, with the covariance of the m frames'
residuals I ⊗ (C − S) + 11ᵀ ⊗ S, so that what the frames share is not counted m times. Each
fit starts from the given start and from it with the diameter at the prior's mean and ± its
spread, and keeps the lowest objective: the objective has local minima along the diameter.

The σ that covariance gives is recalibrated (:func:`recalibrated`): C is an average over
presses, while the emulator's error near one press, and the nuisances' effect there, are
coherent in θ and not in C, so the σ of a frame's fit came out too small (the diameter's
most, tenfold and more). Each parameter's σ is multiplied by the factor that makes it cover
the truth as often as a Gaussian's does, on presses the emulator was fitted on in no way.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

__all__ = ["PARAMETERS", "Emulator", "coverage", "fit_emulator", "fit_frames", "fit_press", "fit_presses", "held_out_presses",
           "recalibrated", "shared_part", "sigmas"]

PARAMETERS = ("x", "y", "depth", "diameter")
HIDDEN = (128, 128)


@dataclass(frozen=True)
class Emulator:
    """θ (n, 4) m → whitened features (n, k). ``t_mean``, ``t_scale`` (4,) standardise θ;
    ``weights[i]`` (a, b), ``biases[i]`` (b,) the layers (ReLU between, none after the last);
    ``x_mean`` (m,), ``components`` (k, m), ``x_scale`` (k,) whiten the features (what
    :meth:`whiten` applies to a frame's); ``covariance`` (k, k) the residual's C at the training
    SNRs. Absent (None) in maps written before them, and then C is all there is, frames
    independent, no prior: ``residual`` (k, k) R, the emulator's error and the nuisances;
    ``shared`` (k, k) R's part common to a press's frames; ``noise_0db`` (k, k) N₀;
    ``reference_share`` N's part common to a press's frames; ``prior_mean`` and ``prior_sd``
    (4,) m the prior on θ; ``sd_scale`` (2, 4) the factors on each parameter's σ that make the
    per-frame fits' (row 0) and the press fits' (row 1) cover the truth of presses the
    emulator was not fitted on (:func:`recalibrated`), at one SNR (``jointsim calibrate``: the
    instrument's): the factor grows with the SNR, where the emulator's own error dominates."""

    t_mean: np.ndarray
    t_scale: np.ndarray
    weights: tuple[np.ndarray, ...]
    biases: tuple[np.ndarray, ...]
    x_mean: np.ndarray
    components: np.ndarray
    x_scale: np.ndarray
    covariance: np.ndarray
    residual: np.ndarray | None = None
    shared: np.ndarray | None = None
    noise_0db: np.ndarray | None = None
    reference_share: float = 0.0
    prior_mean: np.ndarray | None = None
    prior_sd: np.ndarray | None = None
    sd_scale: np.ndarray | None = None

    def covariances(self, snr_db: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(C, S) (k, k): a frame's residual covariance at ``snr_db`` (None: the training
        SNRs'), and the part of it a press's frames share."""
        if self.residual is None:
            return self.covariance, np.zeros_like(self.covariance)
        N = (self.covariance - self.residual if snr_db is None or self.noise_0db is None
             else self.noise_0db * 10.0 ** (-float(snr_db) / 10.0))
        return self.residual + N, self.shared + self.reference_share * N

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


def fit_emulator(features: np.ndarray, theta: np.ndarray, groups: np.ndarray, noise: np.ndarray | None = None,
                 noise_snr_db: np.ndarray | None = None, reference_frames: int = 1, *,
                 seed: int = 0, n_components: int = 32, held_out: float = 0.2) -> Emulator:
    """Train on noise-free ``features`` (n, m) of presses ``theta`` (n, 4) m, press ids
    ``groups`` (n,): the whitening from all, the perceptron on the presses not held out, R and
    its shared part from half the held-out presses' residuals (the emulator's error and the
    nuisances, as a new press meets them; :func:`held_out_presses`), the prior from the
    training presses' labels. With
    ``noise`` (features' noisy minus clean, (r, m), the instrument's) C adds its covariance,
    and with their SNRs ``noise_snr_db`` (r,) N₀; ``reference_frames``: the frames the
    reference averages."""
    from sklearn.neural_network import MLPRegressor

    from .regression import pca_whitening

    X, T = np.asarray(features, float), np.asarray(theta, float)
    ok = np.isfinite(X).all(axis=1) & np.isfinite(T).all(axis=1)
    X, T, g = X[ok], T[ok], np.asarray(groups)[ok]
    if len(X) < 50:
        raise ValueError(f"an emulator needs at least 50 samples with finite features and labels, got {len(X)}")
    x_mean, components, x_scale, Z = pca_whitening(X, n_components)
    k = len(x_scale)
    residual, recalibration = held_out_presses(g, held_out, seed)
    out = residual | recalibration
    t_mean, t_scale = T[~out].mean(axis=0), T[~out].std(axis=0)
    t_scale = np.where(t_scale > 0, t_scale, 1.0)
    m = MLPRegressor(hidden_layer_sizes=HIDDEN, alpha=1e-4, learning_rate_init=1e-3, max_iter=3000, early_stopping=True,
                     n_iter_no_change=50, tol=1e-7, random_state=seed).fit((T[~out] - t_mean) / t_scale, Z[~out])
    emu = Emulator(t_mean, t_scale, tuple(w.copy() for w in m.coefs_), tuple(b.copy() for b in m.intercepts_),
                   x_mean, components, x_scale, np.eye(k))
    Rs = Z[residual] - emu(T[residual])
    R = np.cov(Rs.T)
    S = shared_part(Rs - Rs.mean(axis=0), g[residual], R)
    C, N0 = R, None
    if noise is not None and len(noise):
        W = np.asarray(noise, float) @ components.T / x_scale
        C = R + np.cov(W.T)
        if noise_snr_db is not None:
            N0 = np.cov((W * 10.0 ** (np.asarray(noise_snr_db, float)[:, None] / 20.0)).T)
    return replace(emu, covariance=C, residual=R, shared=S, noise_0db=N0, reference_share=1.0 / (reference_frames + 1),
                   prior_mean=t_mean, prior_sd=t_scale)


def held_out_presses(groups: np.ndarray, fraction: float = 0.2, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """The samples (n,) bool of the presses :func:`fit_emulator` holds out (the ``fraction`` of
    ``groups``' press ids, at least two, drawn by ``seed``), in two halves: those its residual
    covariance is measured on, and those its σ is recalibrated on (:func:`recalibrated`),
    which nothing of the emulator has seen."""
    ids = np.random.default_rng(seed).permutation(np.unique(groups))[: max(2, int(round(fraction * len(np.unique(groups)))))]
    half = (len(ids) + 1) // 2
    return np.isin(groups, ids[:half]), np.isin(groups, ids[half:])


def shared_part(R: np.ndarray, groups: np.ndarray, C: np.ndarray) -> np.ndarray:
    """S (k, k): the covariance between two frames of one press of the centred residuals ``R``
    (n, k), averaged over every ordered pair of a press's frames, made positive semi-definite
    and no larger than their covariance ``C`` (S ≤ 0.99 C: a frame always adds something of
    its own); zeros when no press has two frames."""
    k = R.shape[1]
    total, pairs = np.zeros((k, k)), 0
    for i in np.unique(groups):
        r = R[groups == i]
        s = r.sum(axis=0)
        total += np.outer(s, s) - r.T @ r  # Σ_{j≠l} r_j r_lᵀ
        pairs += len(r) * (len(r) - 1)
    if pairs == 0:
        return np.zeros((k, k))
    # in C's whitened coordinates S's eigenvalues are the shared fractions: clip them to [0, 0.99]
    L = np.linalg.cholesky(C + 1e-12 * np.trace(C) / k * np.eye(k))
    Li = np.linalg.inv(L)
    M = Li @ (total / pairs) @ Li.T
    w, V = np.linalg.eigh((M + M.T) / 2)
    return L @ (V * np.clip(w, 0.0, 0.99)) @ V.T @ L.T


def _levenberg_marquardt(residual_and_jacobian, p0: np.ndarray, Ci: np.ndarray, mean: np.ndarray, precision: np.ndarray,
                         iters: int = 60):
    """argmin rᵀ C⁻¹ r + Σ precisionᵢ (pᵢ − meanᵢ)² from ``p0``, where ``residual_and_jacobian(p)``
    gives r (k,) and its derivative J = ∂r/∂p (len(p), k); (p, J C⁻¹ Jᵀ + diag(precision) at p,
    the cost)."""
    p = np.array(p0, float)

    def objective(p, r):
        return float(r @ Ci @ r + precision @ (p - mean) ** 2)

    r, J = residual_and_jacobian(p)
    cost, lam = objective(p, r), 1e-3
    for _ in range(iters):
        H, grad = J @ Ci @ J.T + np.diag(precision), J @ Ci @ r + precision * (p - mean)
        step = -np.linalg.solve(H + lam * np.diag(np.diag(H)) + 1e-12 * np.trace(H) * np.eye(len(p)), grad)
        rn, Jn = residual_and_jacobian(p + step)
        cn = objective(p + step, rn)
        if cn < cost:
            p, r, J, cost, lam = p + step, rn, Jn, cn, max(lam / 3, 1e-7)
            if np.all(np.abs(step) < 1e-9):
                break
        else:
            lam *= 5
            if lam > 1e8:
                break
    return p, J @ Ci @ J.T + np.diag(precision), cost


def _prior(emulator: Emulator) -> tuple[np.ndarray, np.ndarray]:
    """(mean, precision) (4,) of θ's prior; zero precision for an emulator without one."""
    if emulator.prior_mean is None:
        return np.zeros(4), np.zeros(4)
    return np.asarray(emulator.prior_mean, float), 1.0 / np.asarray(emulator.prior_sd, float) ** 2


def fit_frames(emulator: Emulator, features: np.ndarray, start: np.ndarray,
               snr_db: float | np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Each frame's θ̂ (n, 4) m from its features (n, m), started at ``start`` (n, 4), and its
    covariance (n, 4, 4) m²; NaN where a frame's features are not finite. ``snr_db``: the
    frames' SNR (one, or (n,)); None: the training SNRs'."""
    Z = emulator.whiten(np.where(np.isfinite(features), features, 0.0))
    snr = np.broadcast_to(np.array(np.nan if snr_db is None else snr_db, float), (len(Z),))
    mean, precision = _prior(emulator)
    est, cov = np.full((len(Z), 4), np.nan), np.full((len(Z), 4, 4), np.nan)
    for i in np.flatnonzero(np.isfinite(features).all(axis=1) & np.isfinite(start).all(axis=1)):
        def rj(p, z=Z[i]):
            f, J = emulator.evaluate(p)
            return z - f[0], -J[0]
        Ci = np.linalg.inv(emulator.covariances(None if np.isnan(snr[i]) else snr[i])[0])
        p, H = _best_of(lambda p0: _levenberg_marquardt(rj, p0, Ci, mean, precision), start[i], _diameters(emulator), 3)
        est[i], cov[i] = p, np.linalg.pinv(H)
    return est, _scaled(emulator, cov, 0)


def _diameters(emulator: Emulator) -> np.ndarray:
    """The diameters a fit starts from besides its start's: the prior's mean and ± one spread
    (none without a prior). The objective has local minima along the diameter, which the
    frames hold least: a fit from one start answers as well as that start."""
    if emulator.prior_mean is None:
        return np.zeros(0)
    return emulator.prior_mean[3] + emulator.prior_sd[3] * np.array([-1.0, 0.0, 1.0])


def _best_of(fit, start: np.ndarray, diameters: np.ndarray, at: int) -> tuple[np.ndarray, np.ndarray]:
    """The lowest-cost of ``fit(p0)`` ((p, H, cost)) from ``start`` and from ``start`` with its
    entry ``at`` set to each of ``diameters``: (p, H)."""
    starts = [start] + [np.where(np.arange(len(start)) == at, d, start) for d in diameters]
    p, H, _ = min((fit(np.asarray(p0, float)) for p0 in starts), key=lambda r: r[2])
    return p, H


def _scaled(emulator: Emulator, cov: np.ndarray, row: int) -> np.ndarray:
    """``cov`` (n, 4, 4) with each parameter's σ times ``sd_scale[row]`` (unchanged without)."""
    if emulator.sd_scale is None:
        return cov
    s = np.asarray(emulator.sd_scale, float)[row]
    return cov * np.outer(s, s)


def fit_press(emulator: Emulator, features: np.ndarray, start: np.ndarray,
              snr_db: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """One press's frames (m, features) fitted jointly: x, y and the diameter shared, a depth per
    frame, started at ``start`` (m, 4) (their mean for the shared ones). The frames' θ̂ (m, 4)
    and the covariance of each frame's four (m, 4, 4) m², from the joint Fisher information
    and the prior's. ``snr_db``: the press's SNR (None: the training SNRs')."""
    ok = np.isfinite(features).all(axis=1) & np.isfinite(start).all(axis=1)
    Z = emulator.whiten(features[ok])
    m = len(Z)
    # (I ⊗ A + 11ᵀ ⊗ S)⁻¹ with A = C − S, through the projector P = 11ᵀ/m onto the frames' mean:
    # I ⊗ A⁻¹ + P ⊗ ((A + mS)⁻¹ − A⁻¹)
    C, S = emulator.covariances(snr_db)
    Ai = np.linalg.inv(C - S)
    Cim = np.kron(np.eye(m), Ai) + np.kron(np.full((m, m), 1.0 / m), np.linalg.inv(C - S + m * S) - Ai)
    mu, prec = _prior(emulator)
    mean = np.concatenate([mu[[0, 1, 3]], np.full(m, mu[2])])
    precision = np.concatenate([prec[[0, 1, 3]], np.full(m, prec[2])])

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
    p, H = _best_of(lambda q: _levenberg_marquardt(rj, q, Cim, mean, precision), p0, _diameters(emulator), 2)
    P = np.linalg.pinv(H)
    est, cov = np.full((len(features), 4), np.nan), np.full((len(features), 4, 4), np.nan)
    est[ok] = unpack(p)
    for j, i in enumerate(np.flatnonzero(ok)):
        sel = [0, 1, 3 + j, 2]  # x, y, depth_j, diameter in θ's order
        cov[i] = P[np.ix_(sel, sel)]
    return est, _scaled(emulator, cov, 1)


def fit_presses(emulator: Emulator, features: np.ndarray, start: np.ndarray, group: np.ndarray,
                min_depth: float = -np.inf, snr_db: float | np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """:func:`fit_press` for each press of ``group`` (n,): its frames that ``start`` puts at least
    ``min_depth`` deep, fitted jointly at their mean ``snr_db`` (one, or (n,); None: the
    training SNRs'); θ̂ (n, 4) m and covariances (n, 4, 4) m², NaN for the frames left out."""
    est, cov = np.full((len(features), 4), np.nan), np.full((len(features), 4, 4), np.nan)
    snr = None if snr_db is None else np.broadcast_to(np.asarray(snr_db, float), (len(features),))
    for k in np.unique(group):
        i = np.flatnonzero((group == k) & (start[:, 2] >= min_depth))
        if len(i):
            est[i], cov[i] = fit_press(emulator, features[i], start[i], None if snr is None else float(snr[i].mean()))
    return est, cov


def sigmas(covariances: np.ndarray) -> np.ndarray:
    """Each parameter's σ (n, 4) from the estimates' covariances (n, 4, 4)."""
    return np.sqrt(np.einsum("nii->ni", covariances))


def recalibrated(emulator: Emulator, features: np.ndarray, start: np.ndarray, theta: np.ndarray, group: np.ndarray,
                 snr_db: float | np.ndarray | None = None, min_depth: float = -np.inf) -> Emulator:
    """The emulator with ``sd_scale``: fitted to the noisy ``features`` (n, m) of presses it was
    not trained on (frames from ``start`` (n, 4), presses by ``group``, their frames at least
    ``min_depth`` deep, at ``snr_db``), each parameter's factor is the 68.3rd percentile of
    |θ̂ − θ|/σ against the truth ``theta`` (n, 4): what makes σ cover it as often as a
    Gaussian's does (module docstring)."""
    plain = replace(emulator, sd_scale=None)
    fits = (fit_frames(plain, features, start, snr_db), fit_presses(plain, features, start, group, min_depth, snr_db))
    scale = []
    for est, cov in fits:
        z = np.abs(est - theta) / sigmas(cov)
        scale.append([float(np.nanquantile(z[:, j], 0.6827)) if np.isfinite(z[:, j]).any() else 1.0 for j in range(4)])
    return replace(emulator, sd_scale=np.array(scale))


def coverage(estimates: np.ndarray, covariances: np.ndarray, truth: np.ndarray) -> dict[str, dict[str, float]]:
    """How well the reported uncertainties hold: per parameter, the share of finite estimates
    (n, 4) within 1σ and 2σ of ``truth`` (n, 4), σ from ``covariances`` (n, 4, 4) (68.3 % and
    95.4 % when they are right), and the errors' RMS in σ (1 when right)."""
    z = np.abs(np.asarray(estimates) - truth) / sigmas(covariances)
    ok = np.isfinite(z)
    out = {}
    for j, name in enumerate(PARAMETERS):
        zj = z[ok[:, j], j]
        out[name] = {"n": int(len(zj)), "within_1sd": float(np.mean(zj < 1)) if len(zj) else float("nan"),
                     "within_2sd": float(np.mean(zj < 2)) if len(zj) else float("nan"),
                     "rms_z": float(np.sqrt(np.mean(zj ** 2))) if len(zj) else float("nan")}
    return out
