"""The CoM map: the image's reconstructed centre of mass → the true contact position (x, y)
and indentation depth.

Owns the thin-plate-spline fit (scipy's ``RBFInterpolator``, smoothing chosen by grouped
cross-validation on the training presses) and its evaluation. The map is stored as its
training points and hyper-parameters: the interpolant is a deterministic linear solve of
them, rebuilt when the map is loaded (no pickle), so a loaded map predicts exactly what the
fitted one did.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["ComMap", "fit_com_map", "SMOOTHINGS"]

SCALE = 1e3  # fitted in mm: the kernel's and the smoothing's natural scale
SMOOTHINGS = (1e-3, 1e-2, 1e-1, 1.0, 10.0)  # candidate TPS smoothings (mm² units), chosen by CV
KERNEL = "thin_plate_spline"
DEGREE = 1


@dataclass(frozen=True)
class ComMap:
    """Thin-plate spline from reconstructed CoM (n, 3) m to (x, y, depth) (n, 3) m, through
    ``points`` (p, 3) and ``values`` (p, 3) in mm with ``smoothing``."""

    points: np.ndarray
    values: np.ndarray
    smoothing: float
    kernel: str = KERNEL
    degree: int = DEGREE
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
        return out


def _subsample(n: int, cap: int, rng: np.random.Generator) -> np.ndarray:
    return np.sort(rng.choice(n, cap, replace=False)) if n > cap else np.arange(n)


def _cv_error(X: np.ndarray, Y: np.ndarray, groups: np.ndarray, smoothing: float, folds: int) -> float:
    """Mean squared 3-D error of held-out groups over ``folds`` grouped folds."""
    from scipy.interpolate import RBFInterpolator
    from sklearn.model_selection import GroupKFold

    err = []
    for tr, te in GroupKFold(n_splits=folds).split(X, Y, groups):
        f = RBFInterpolator(X[tr], Y[tr], kernel=KERNEL, smoothing=smoothing, degree=DEGREE)
        err.append(((f(X[te]) - Y[te]) ** 2).sum(axis=1))
    return float(np.mean(np.concatenate(err)))


def fit_com_map(
    com: np.ndarray, target: np.ndarray, group: np.ndarray, *, seed: int = 0, max_points: int = 3000,
    smoothings: tuple[float, ...] = SMOOTHINGS,
) -> tuple[ComMap, dict[str, float]]:
    """Fit the map from training samples: ``com`` (n, 3) m reconstructed, ``target`` (n, 3) m
    true (x, y, depth), ``group`` (n,) press ids (the CV folds keep a press together). Rows
    with a non-finite CoM are dropped; above ``max_points`` a seeded subsample is fitted (the
    spline's solve is cubic in the points). Returns the map and {smoothing: CV mean squared
    error mm²}."""
    ok = np.isfinite(com).all(axis=1) & np.isfinite(target).all(axis=1)
    X, Y, g = com[ok] * SCALE, target[ok] * SCALE, group[ok]
    if len(np.unique(g)) < 3 or len(X) < 10:
        raise ValueError(f"the CoM map needs samples of at least 3 presses with a reconstructed CoM, got {len(X)} "
                         f"sample(s) of {len(np.unique(g))} press(es)")
    rng = np.random.default_rng(seed)
    keep = _subsample(len(X), max_points, rng)
    X, Y, g = X[keep], Y[keep], g[keep]
    folds = int(min(3, len(np.unique(g))))
    cv_keep = _subsample(len(X), min(max_points, 1500), rng)  # the CV on fewer points: 3 × |grid| solves
    scores = {s: _cv_error(X[cv_keep], Y[cv_keep], g[cv_keep], s, folds) for s in smoothings}
    best = min(scores, key=scores.get)
    return ComMap(X, Y, float(best)), scores
