"""The CoM map: the image's reconstructed centre of mass → the true contact position (x, y)
and indentation depth.

Owns the thin-plate-spline fit (scipy's ``RBFInterpolator``, smoothing chosen by grouped
cross-validation on the training presses) and its evaluation. In x and y the spline fits the
correction to the reconstructed CoM (position − CoM), so that as the smoothing grows the map
tends to an affine correction of the CoM, not to a flat surface; the depth, which the image's
CoM does not measure directly, is fitted as itself. Each training point is weighted by its
noise: its smoothing is scaled by its noise power, so the noisy frames of a dataset that
spans 40–80 dB bend the map less than the clean ones; the smoothing chosen by the CV is that
of a point at the training set's median SNR.

The map is stored as its training points, their smoothings and the hyper-parameters: the
interpolant is a deterministic linear solve of them, rebuilt when the map is loaded (no
pickle), so a loaded map predicts exactly what the fitted one did.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["ComMap", "fit_com_map", "noise_factors", "SMOOTHINGS"]

SCALE = 1e3  # fitted in mm: the kernel's and the smoothing's natural scale
SMOOTHINGS = (1e-3, 1e-2, 1e-1, 1.0, 10.0, 1e2, 1e3)  # candidate TPS smoothings (mm² units), chosen by CV
KERNEL = "thin_plate_spline"
DEGREE = 1


@dataclass(frozen=True)
class ComMap:
    """Thin-plate spline from reconstructed CoM (n, 3) m to (x, y, depth) (n, 3) m, through
    ``points`` (p, 3) and ``values`` (p, 3) in mm with per-point ``smoothing`` (p,) (or one
    for all). ``residual``: the values' x and y are corrections added to the CoM's (maps of
    format version 1 fitted the position itself)."""

    points: np.ndarray
    values: np.ndarray
    smoothing: np.ndarray | float
    kernel: str = KERNEL
    degree: int = DEGREE
    residual: bool = True
    _rbf: object = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        from scipy.interpolate import RBFInterpolator

        rbf = RBFInterpolator(self.points, self.values, kernel=self.kernel, smoothing=self.smoothing, degree=self.degree)
        object.__setattr__(self, "_rbf", rbf)

    def __call__(self, com: np.ndarray) -> np.ndarray:
        """(x, y, depth) (n, 3) m for reconstructed CoMs ``com`` (n, 3) m; NaN rows for NaN input."""
        com = np.asarray(com, float).reshape(-1, 3)
        out = np.full(com.shape, np.nan)
        ok = np.isfinite(com).all(axis=1)
        if ok.any():
            out[ok] = self._rbf(com[ok] * SCALE) / SCALE
            if self.residual:
                out[ok, :2] += com[ok, :2]
        return out


def noise_factors(snr_db: np.ndarray) -> np.ndarray:
    """Each point's smoothing factor (n,): its noise power relative to the median point's."""
    snr_db = np.asarray(snr_db, float)
    return 10.0 ** ((np.median(snr_db) - snr_db) / 10.0)


def _subsample(n: int, cap: int, rng: np.random.Generator) -> np.ndarray:
    return np.sort(rng.choice(n, cap, replace=False)) if n > cap else np.arange(n)


def _cv_error(X: np.ndarray, Y: np.ndarray, factor: np.ndarray, groups: np.ndarray, smoothing: float, folds: int) -> float:
    """Mean 3-D error (mm) of held-out groups over ``folds`` grouped folds, each point weighted
    by its inverse noise amplitude: the mean distance, not its square, and weighted, so that
    the wild CoMs of noisy frames do not choose the smoothing."""
    from scipy.interpolate import RBFInterpolator
    from sklearn.model_selection import GroupKFold

    err, weight = [], []
    for tr, te in GroupKFold(n_splits=folds).split(X, Y, groups):
        f = RBFInterpolator(X[tr], Y[tr], kernel=KERNEL, smoothing=smoothing * factor[tr], degree=DEGREE)
        err.append(np.linalg.norm(f(X[te]) - Y[te], axis=1))
        weight.append(factor[te] ** -0.5)
    return float(np.average(np.concatenate(err), weights=np.concatenate(weight)))


def fit_com_map(
    com: np.ndarray, target: np.ndarray, group: np.ndarray, snr_db: np.ndarray | None = None, *, seed: int = 0,
    max_points: int = 3000, smoothings: tuple[float, ...] = SMOOTHINGS,
) -> tuple[ComMap, dict[str, float]]:
    """Fit the map from training samples: ``com`` (n, 3) m reconstructed, ``target`` (n, 3) m
    true (x, y, depth), ``group`` (n,) press ids (the CV folds keep a press together),
    ``snr_db`` (n,) each sample's noise level (None: all weighted alike). Rows with a
    non-finite CoM are dropped; above ``max_points`` a seeded subsample is fitted (the spline's
    solve is cubic in the points). Returns the map and {smoothing: CV weighted mean error mm}."""
    ok = np.isfinite(com).all(axis=1) & np.isfinite(target).all(axis=1)
    if snr_db is not None:
        ok &= np.isfinite(snr_db)
    X, g = com[ok] * SCALE, group[ok]
    factor = np.ones(len(X)) if snr_db is None else noise_factors(np.asarray(snr_db)[ok])
    Y = target[ok] * SCALE
    Y[:, :2] -= X[:, :2]  # x, y: the correction to the CoM
    if len(np.unique(g)) < 3 or len(X) < 10:
        raise ValueError(f"the CoM map needs samples of at least 3 presses with a reconstructed CoM, got {len(X)} "
                         f"sample(s) of {len(np.unique(g))} press(es)")
    rng = np.random.default_rng(seed)
    keep = _subsample(len(X), max_points, rng)
    X, Y, g, factor = X[keep], Y[keep], g[keep], factor[keep]
    folds = int(min(3, len(np.unique(g))))
    cv = _subsample(len(X), min(max_points, 1500), rng)  # the CV on fewer points: 3 × |grid| solves
    scores = {s: _cv_error(X[cv], Y[cv], factor[cv], g[cv], s, folds) for s in smoothings}
    best = min(scores, key=scores.get)
    return ComMap(X, Y, float(best) * factor), scores
