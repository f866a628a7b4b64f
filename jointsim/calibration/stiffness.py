"""Stiffness: the target's Young's modulus from its press — the force–indentation curve read at
fixed depths together with the image metrics there (which carry the target's size).

Owns the per-press features (log |F|, image diameter and log |Σσ| at each of a few depths), the
test of whether the dataset can support an estimate at all (soft targets of several moduli;
rigid ones, E = +inf, cannot be fitted and are left out), and a ridge on degree-2 polynomial
features of them for log10 E, stored as plain arrays. A dataset of rigid targets alone gives
a model that says it is not estimable and why, and predicts NaN.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .curves import value_at

__all__ = ["StiffnessModel", "group_features", "fit_stiffness", "force_sensitivity", "decades", "stiffness_levels",
           "press_moduli", "MIN_SOFT_GROUPS"]

MIN_SOFT_GROUPS = 8
MIN_DECADES = 0.1  # soft moduli spanning less than this (log10) carry no modulus information
ALPHAS = tuple(10.0 ** np.arange(-4, 3))


def group_features(group: np.ndarray, depth: np.ndarray, force_mag: np.ndarray, sum_sigma: np.ndarray,
                   diameter: np.ndarray, levels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Press ids (G,) reaching every depth of ``levels`` (L,) and their features (G, 3L):
    log |F|, image diameter (mm) and log |Σσ| at each depth. Inputs are per sample (n,)."""
    cols, ids = [], None
    per_level = []
    for lv in levels:
        g, v = value_at(group, depth, np.column_stack([force_mag, diameter, sum_sigma]), float(lv))
        per_level.append(dict(zip(g.tolist(), v)))
        ids = set(g.tolist()) if ids is None else ids & set(g.tolist())
    ids = np.array(sorted(ids or ()), dtype=np.int64)
    for d in per_level:
        v = np.array([d[i] for i in ids.tolist()]).reshape(len(ids), 3)
        with np.errstate(divide="ignore", invalid="ignore"):
            cols += [np.log(np.abs(v[:, 0])), v[:, 1] * 1e3, np.log(np.abs(v[:, 2]))]
    X = np.column_stack(cols) if cols else np.empty((0, 0))
    ok = np.isfinite(X).all(axis=1) if len(X) else np.zeros(0, bool)
    return ids[ok], X[ok]


@dataclass(frozen=True)
class StiffnessModel:
    """log10 E from per-press features: ``estimable`` False (with ``reason``) when the data
    cannot support it. ``levels`` (L,) depths m; ``x_mean``, ``x_scale`` (3L,) standardise;
    ``powers`` (p, 3L) are the polynomial terms, ``coef`` (p,) and ``intercept`` the ridge."""

    estimable: bool
    reason: str
    levels: np.ndarray
    x_mean: np.ndarray
    x_scale: np.ndarray
    powers: np.ndarray
    coef: np.ndarray
    intercept: float

    def predict_features(self, X: np.ndarray) -> np.ndarray:
        """E (G,) Pa for per-press features (G, 3L); NaN when not estimable."""
        X = np.asarray(X, float)
        if not self.estimable or len(X) == 0:
            return np.full(len(X), np.nan)
        Z = (X - self.x_mean) / self.x_scale
        P = np.prod(Z[:, None, :] ** self.powers[None], axis=2)
        return 10.0 ** (P @ self.coef + self.intercept)

    def predict(self, group: np.ndarray, depth: np.ndarray, force_mag: np.ndarray, sum_sigma: np.ndarray,
                diameter: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Press ids (G,) that reach every level and their modulus (G,) Pa, from per-sample arrays."""
        ids, X = group_features(group, depth, force_mag, sum_sigma, diameter, self.levels)
        return ids, self.predict_features(X)

    @classmethod
    def not_estimable(cls, reason: str, levels: np.ndarray) -> "StiffnessModel":
        e = np.zeros(0)
        return cls(False, reason, np.asarray(levels, float), e, e, np.zeros((0, 0), int), e, float("nan"))


def decades(E: np.ndarray) -> list[tuple[float, np.ndarray]]:
    """The decades [lo, 10 lo) of moduli ``E`` (n,) Pa from the one holding the least, each
    with its mask (n,) bool."""
    return [(float(lo), (E >= lo) & (E < 10 * lo)) for lo in 10.0 ** np.arange(np.floor(np.log10(E.min())), np.log10(E.max()))]


def force_sensitivity(group: np.ndarray, depth: np.ndarray, force_mag: np.ndarray, radius: np.ndarray,
                      modulus: np.ndarray, level: float) -> list[dict[str, float]]:
    """How much the target's modulus changes the force, per decade of E (soft presses): |F| at
    depth ``level`` (m) relative to the fit of log |F| on log R over all of them, mean and
    spread (%). What the dataset offers a modulus estimate, whatever the estimator: a decade
    whose mean sits within the spread of the others cannot be told apart from them by force."""
    soft = np.isfinite(modulus)
    g, v = value_at(group[soft], depth[soft], np.column_stack([force_mag, radius, modulus])[soft], float(level))
    if len(g) < 3:
        return []
    lf, lr, E = np.log(v[:, 0]), np.log(v[:, 1]), v[:, 2]
    A = np.column_stack([np.ones(len(g)), lr])
    res = lf - A @ np.linalg.lstsq(A, lf, rcond=None)[0]
    return [{"from_pa": lo, "to_pa": 10 * lo, "n": int(m.sum()), "mean_percent": float(100 * np.expm1(res[m].mean())),
             "sd_percent": float(100 * res[m].std())} for lo, m in decades(E) if m.any()]


def fit_stiffness(group: np.ndarray, depth: np.ndarray, force_mag: np.ndarray, sum_sigma: np.ndarray,
                  diameter: np.ndarray, modulus: np.ndarray, levels: np.ndarray) -> StiffnessModel:
    """Fit on the training samples (per-sample arrays (n,); ``modulus`` Pa, +inf for rigid)."""
    from sklearn.linear_model import RidgeCV
    from sklearn.preprocessing import PolynomialFeatures

    ids, first = np.unique(group, return_index=True)
    E = modulus[first]
    soft = np.isfinite(E) & (E > 0)
    n_rigid = int((~soft).sum())
    if soft.sum() < MIN_SOFT_GROUPS:
        what = "all" if soft.sum() == 0 else f"{n_rigid} of"
        return StiffnessModel.not_estimable(
            f"{what} {len(ids)} training presses have rigid targets (target_modulus = +inf) and only "
            f"{int(soft.sum())} soft one(s) (at least {MIN_SOFT_GROUPS} needed): the modulus is not estimable from this "
            "dataset; generate one with soft targets", levels)
    logE = np.log10(E[soft])
    if np.ptp(logE) < MIN_DECADES:
        return StiffnessModel.not_estimable(
            f"the soft targets' moduli span {np.ptp(logE):.3f} decades (< {MIN_DECADES}): nothing to tell apart", levels)
    keep = np.isin(group, ids[soft])
    gids, X = group_features(group[keep], depth[keep], force_mag[keep], sum_sigma[keep], diameter[keep], levels)
    if len(gids) < MIN_SOFT_GROUPS:
        return StiffnessModel.not_estimable(
            f"only {len(gids)} soft press(es) reach every depth level {np.round(np.asarray(levels) * 1e3, 2).tolist()} mm "
            f"(at least {MIN_SOFT_GROUPS} needed)", levels)
    y = np.log10(E[np.searchsorted(ids, gids)])
    x_mean, x_scale = X.mean(axis=0), X.std(axis=0)
    x_scale = np.where(x_scale > 0, x_scale, 1.0)
    Z = (X - x_mean) / x_scale
    poly = PolynomialFeatures(degree=2, include_bias=False).fit(Z)
    r = RidgeCV(alphas=ALPHAS).fit(poly.transform(Z), y)
    reason = f"fitted on {len(gids)} soft presses ({n_rigid} rigid left out), ridge alpha {r.alpha_:g}"
    return StiffnessModel(True, reason, np.asarray(levels, float), x_mean, x_scale, poly.powers_.astype(int),
                          np.asarray(r.coef_, float), float(r.intercept_))


def stiffness_levels(depth_levels: np.ndarray) -> np.ndarray:
    """The three depth levels (m) the stiffness model reads, out of the size curves' (increasing):
    spread over their deeper two thirds, where every soft press has a sample."""
    d = np.asarray(depth_levels, float)
    return d[np.unique(np.linspace(len(d) // 3, len(d) - 1, 3).astype(int))]


def press_moduli(group: np.ndarray, modulus: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """The target modulus (G,) Pa of each press ``ids`` from per-sample ``group`` and ``modulus``."""
    _, first = np.unique(group, return_index=True)
    true = dict(zip(group[first].tolist(), modulus[first].tolist()))
    return np.array([true[i] for i in np.asarray(ids).tolist()])
