"""Size curves: image and voltage metrics against true target size at fixed depth or fixed
force, and their monotone inverse (measurement → size).

Owns reading a press group's metric at a fixed value of its depth or force (linear
interpolation along the group's samples, which press deeper one after the other; force is
monotone in depth within a press), the monotone inverse of one curve (isotonic regression,
stored as its breakpoints and evaluated by linear interpolation, as scikit-learn's
``IsotonicRegression.predict`` does), and :class:`LevelCurves`: one inverse per level of depth
or force, interpolated between levels for a sample at any depth or force inside them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["ALONG", "value_at", "Monotone", "LevelCurves", "fit_level_curves", "default_levels"]

ALONG = ("depth", "force")
MIN_CURVE_GROUPS = 3  # a level with fewer press groups reaching it has no curve


def value_at(group: np.ndarray, along: np.ndarray, value: np.ndarray, level: float) -> tuple[np.ndarray, np.ndarray]:
    """Each group's ``value`` where its ``along`` (depth or |force|) crosses ``level``.

    Parameters: ``group`` (n,) ids, ``along`` (n,), ``value`` (n,) or (n, k), ``level`` scalar.
    Returns the ids of the groups whose samples bracket ``level`` (G,) and the value
    interpolated linearly between the bracketing pair (G,) or (G, k); groups that never reach
    the level (or start past it) are left out."""
    order = np.lexsort((along, group))
    g, a, v = group[order], along[order], np.asarray(value)[order]
    lo, hi = np.arange(len(g) - 1), np.arange(1, len(g))
    ok = (g[lo] == g[hi]) & (a[lo] <= level) & (a[hi] >= level) & (a[hi] > a[lo])
    lo, hi = lo[ok], hi[ok]
    ids, first = np.unique(g[lo], return_index=True)  # the first bracketing pair of each group
    lo, hi = lo[first], hi[first]
    t = (level - a[lo]) / (a[hi] - a[lo])
    t = t.reshape(-1, *([1] * (v.ndim - 1)))
    return ids, v[lo] + t * (v[hi] - v[lo])


@dataclass(frozen=True)
class Monotone:
    """A monotone curve through breakpoints ``x`` (K,) ascending, ``y`` (K,), evaluated by
    linear interpolation and clipped outside [x₀, x_K] (an isotonic fit's prediction)."""

    x: np.ndarray
    y: np.ndarray

    @classmethod
    def fit(cls, x: np.ndarray, y: np.ndarray, increasing: bool | str = "auto") -> "Monotone":
        """The least-squares monotone y(x) of the finite pairs of ``x``, ``y`` (n,), increasing,
        decreasing, or whichever fits better ("auto")."""
        from sklearn.isotonic import IsotonicRegression

        ok = np.isfinite(x) & np.isfinite(y)
        if ok.sum() < 2:
            raise ValueError(f"a monotone curve needs at least 2 finite points, got {int(ok.sum())}")
        iso = IsotonicRegression(increasing=increasing, out_of_bounds="clip").fit(x[ok], y[ok])
        return cls(np.asarray(iso.X_thresholds_, float), np.asarray(iso.y_thresholds_, float))

    def __call__(self, x: np.ndarray) -> np.ndarray:
        x = np.asarray(x, float)
        return np.where(np.isfinite(x), np.interp(x, self.x, self.y), np.nan)


def default_levels(along: str, group: np.ndarray, coord: np.ndarray, n: int = 6) -> np.ndarray:
    """Levels most press groups reach: ``n`` of them up to the 20th percentile of the groups'
    largest depth (evenly spaced from a sixth of it) or force (geometrically, from 1/16 of it)."""
    top = _group_max(group, coord)
    hi = float(np.quantile(top, 0.2))
    if not hi > 0:
        raise ValueError(f"the press groups barely reach any {along}: cannot choose calibration levels")
    return np.linspace(hi / 6, hi, n) if along == "depth" else np.geomspace(hi / 16, hi, n)


def _group_max(group: np.ndarray, coord: np.ndarray) -> np.ndarray:
    order = np.lexsort((coord, group))
    g = group[order]
    last = np.r_[g[1:] != g[:-1], True]
    return coord[order][last]


def _invert_rows(size: np.ndarray, rows: np.ndarray, metric: np.ndarray) -> np.ndarray:
    """For each row i of non-decreasing ``rows`` (n, K) over ``size`` (K,), the size where it
    reaches ``metric[i]`` (linear between grid points, clipped to the grid's ends)."""
    K = len(size)
    idx = np.clip((rows < metric[:, None]).sum(axis=1), 1, K - 1)
    i = np.arange(len(rows))
    lo, hi = rows[i, idx - 1], rows[i, idx]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.clip(np.where(hi > lo, (metric - lo) / (hi - lo), 0.5), 0.0, 1.0)
    return size[idx - 1] + t * (size[idx] - size[idx - 1])


@dataclass(frozen=True)
class LevelCurves:
    """Size curves of one ``metric`` at each of ``levels`` (L,) of ``along`` (depth m or
    |force| N): ``curves[l]`` is the monotone metric(diameter m) at that level (None where too
    few groups reached it), all ``increasing`` or all decreasing. A sample measured between two
    levels is read on the two curves blended linearly in the level (in log force for force),
    and the blended curve is inverted: measurement → diameter. Outside [levels[0],
    levels[-1]] the prediction is NaN."""

    along: str
    metric: str
    levels: np.ndarray
    curves: tuple[Monotone | None, ...]
    increasing: bool = True
    grid_points: int = 256

    def _coord(self, v: np.ndarray) -> np.ndarray:
        v = np.asarray(v, float)
        if self.along == "force":
            with np.errstate(divide="ignore", invalid="ignore"):
                return np.log(v)
        return v

    def _grid(self) -> tuple[np.ndarray, np.ndarray]:
        """Diameter grid (K,) over every curve's range and each level's curve on it (L, K) (NaN
        for a level without a curve), signed so that it never decreases."""
        xs = [c.x for c in self.curves if c is not None]
        if not xs:
            return np.zeros(2), np.full((len(self.levels), 2), np.nan)
        size = np.linspace(min(x[0] for x in xs), max(x[-1] for x in xs), self.grid_points)
        sign = 1.0 if self.increasing else -1.0
        F = np.stack([sign * c(size) if c is not None else np.full(len(size), np.nan) for c in self.curves])
        return size, F

    def inverse_at_level(self, k: int, metric: np.ndarray) -> np.ndarray:
        """Diameter (n,) of measurements ``metric`` (n,) taken exactly at ``levels[k]``."""
        return self.predict(metric, np.full(len(np.atleast_1d(metric)), self.levels[k]))

    def predict(self, metric: np.ndarray, at: np.ndarray) -> np.ndarray:
        """Diameter (n,) m of samples with ``metric`` (n,) measured at depth or force ``at`` (n,)."""
        m = np.atleast_1d(np.asarray(metric, float)) * (1.0 if self.increasing else -1.0)
        size, F = self._grid()
        lv, c = self._coord(self.levels), self._coord(at)
        if len(lv) == 1:
            k, t = np.zeros(len(c), int), np.zeros(len(c))
            inside = np.isclose(c, lv[0])
            F = np.vstack([F, F])
        else:
            k = np.clip(np.searchsorted(lv, c, side="right") - 1, 0, len(lv) - 2)
            t = (c - lv[k]) / (lv[k + 1] - lv[k])
            inside = (c >= lv[0]) & (c <= lv[-1])
        ok = inside & np.isfinite(c) & np.isfinite(m)
        out = np.full(len(m), np.nan)
        if ok.any():
            kk, tt = k[ok], t[ok][:, None]
            rows = np.where(tt == 0, F[kk], (1 - tt) * F[kk] + tt * F[kk + 1])
            good = np.isfinite(rows).all(axis=1)
            sub = np.full(ok.sum(), np.nan)
            sub[good] = _invert_rows(size, rows[good], m[ok][good])
            out[ok] = sub
        return out


def fit_level_curves(
    along: str, metric: str, levels: np.ndarray, group: np.ndarray, coord: np.ndarray, value: np.ndarray,
    size: np.ndarray,
) -> LevelCurves:
    """Fit the monotone metric(diameter) at each level from the training samples: ``group``,
    ``coord`` (the depth or |force| of each sample), ``value`` (the metric), ``size`` (the true
    diameter), all (n,). The direction (increasing or decreasing) is the sign of the metric's
    correlation with size over all levels together, the same at every level."""
    if along not in ALONG:
        raise ValueError(f"along = {along!r}: one of {ALONG}")
    ids, first = np.unique(group, return_index=True)
    size_of = dict(zip(ids.tolist(), size[first].tolist()))
    read = []
    for lv in np.asarray(levels, float):
        gids, v = value_at(group, coord, value, lv)
        s = np.array([size_of[i] for i in gids.tolist()])
        ok = np.isfinite(v)
        read.append((s[ok], v[ok]))
    pooled = [(s - s.mean(), v - v.mean()) for s, v in read if len(s) >= 2]
    cov = sum(float((a * b).sum()) for a, b in pooled)
    increasing = cov >= 0
    curves = tuple(Monotone.fit(s, v, increasing) if len(s) >= MIN_CURVE_GROUPS else None for s, v in read)
    return LevelCurves(along, metric, np.asarray(levels, float), curves, bool(increasing))
