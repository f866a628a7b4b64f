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
    def fit(cls, x: np.ndarray, y: np.ndarray) -> "Monotone":
        """The least-squares monotone (increasing or decreasing, whichever fits) y(x) of the
        finite pairs of ``x``, ``y`` (n,)."""
        from sklearn.isotonic import IsotonicRegression

        ok = np.isfinite(x) & np.isfinite(y)
        if ok.sum() < 2:
            raise ValueError(f"a monotone curve needs at least 2 finite points, got {int(ok.sum())}")
        iso = IsotonicRegression(increasing="auto", out_of_bounds="clip").fit(x[ok], y[ok])
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


@dataclass(frozen=True)
class LevelCurves:
    """Inverse size curves of one ``metric`` at each of ``levels`` (L,) of ``along`` (depth m
    or |force| N): ``curves[l]`` maps the metric to the target diameter (m), None at a level
    too few groups reached. Between two levels the two inverses are blended linearly in the
    level (in log force for force); outside [levels[0], levels[-1]] the prediction is NaN."""

    along: str
    metric: str
    levels: np.ndarray
    curves: tuple[Monotone | None, ...]

    def _coord(self, v: np.ndarray) -> np.ndarray:
        v = np.asarray(v, float)
        if self.along == "force":
            with np.errstate(divide="ignore", invalid="ignore"):
                return np.log(v)
        return v

    def at_levels(self, metric: np.ndarray) -> np.ndarray:
        """Every level's inverse at ``metric`` (n,): (L, n), NaN where a level has no curve."""
        m = np.asarray(metric, float)
        return np.stack([c(m) if c is not None else np.full(m.shape, np.nan) for c in self.curves])

    def predict(self, metric: np.ndarray, at: np.ndarray) -> np.ndarray:
        """Diameter (n,) m of samples with ``metric`` (n,) measured at depth or force ``at`` (n,)."""
        p = self.at_levels(metric)
        lv, c = self._coord(self.levels), self._coord(at)
        k = np.clip(np.searchsorted(lv, c, side="right") - 1, 0, len(lv) - 2) if len(lv) > 1 else np.zeros(len(c), int)
        cols = np.arange(p.shape[1])
        if len(lv) == 1:
            out = p[0]
            inside = np.isclose(c, lv[0])
        else:
            t = (c - lv[k]) / (lv[k + 1] - lv[k])
            out = (1 - t) * p[k, cols] + t * p[k + 1, cols]
            inside = (c >= lv[0]) & (c <= lv[-1])
        return np.where(inside & np.isfinite(c), out, np.nan)


def fit_level_curves(
    along: str, metric: str, levels: np.ndarray, group: np.ndarray, coord: np.ndarray, value: np.ndarray,
    size: np.ndarray,
) -> LevelCurves:
    """Fit the inverse (metric → diameter) at each level from the training samples: ``group``,
    ``coord`` (the depth or |force| of each sample), ``value`` (the metric), ``size`` (the true
    diameter), all (n,)."""
    if along not in ALONG:
        raise ValueError(f"along = {along!r}: one of {ALONG}")
    ids, sizes = np.unique(group, return_index=True)
    size_of = dict(zip(ids.tolist(), size[sizes].tolist()))
    curves: list[Monotone | None] = []
    for lv in np.asarray(levels, float):
        gids, v = value_at(group, coord, value, lv)
        s = np.array([size_of[i] for i in gids.tolist()])
        ok = np.isfinite(v)
        curves.append(Monotone.fit(v[ok], s[ok]) if ok.sum() >= MIN_CURVE_GROUPS else None)
    return LevelCurves(along, metric, np.asarray(levels, float), tuple(curves))
