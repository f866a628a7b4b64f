"""Where a sphere coming straight down touches the membrane, and the reverse: the sphere's
centre that touches it at a given point.

The membrane's outer surface is faceted (its nodes); the surface it discretises is smooth.
About a point s the smooth surface is the cubic z = f(x, y) fitted (least squares) to the outer
nodes around s. A sphere of radius R coming down the vertical touches a convex surface first
where the surface's outward normal n = (−∇f, 1)/√(1 + |∇f|²) points at its centre, so the
centre that touches at s is

    c = (s, f(s)) + R n(s),

off the axis *outside* s, by R sin θ with θ the surface's tilt. Drawing contact points (not
centres) uniformly over a disc is what makes a dataset cover that disc: a 30 mm sphere centred
15 mm off the axis of the paper's dome touches ~9 mm off it.

How far the sphere can then press is the mechanics' own limit
(:meth:`~jointsim.mechanics.dome.MembraneModel.press`): its lowest point stays at least the
membrane's thickness above the base.
"""

from __future__ import annotations

import math
from collections.abc import Iterator

import numpy as np

__all__ = ["FIT_RADIUS", "FIT_NODES", "surface_fit", "outer_points", "touch", "centre_touching", "point_touched", "depth_reach",
           "press_through"]

# the outer surface's nodes fitted by a cubic about a point: within this radius (m) of it, at
# least FIT_NODES of them (a 64-rim membrane's P2 surface has nodes ~1 mm apart: ~30 within
# 3 mm). A quadratic erred by 1 % of the slope 7 mm off the axis of a 25 mm sphere, the cubic by
# 0.03 % (tests/test_design.py)
FIT_RADIUS = 3e-3
FIT_NODES = 20


def surface_fit(points: np.ndarray, at: np.ndarray) -> tuple[float, np.ndarray]:
    """(f(at), ∇f (2,) at ``at``) of the cubic z = f(x, y) fitted (least squares) to ``points``
    (k ≥ 10, 3) around ``at`` (2,): the smooth surface's height and slope where the faceted
    one has a kink."""
    d = points[:, :2] - at
    x, y = d[:, 0], d[:, 1]
    A = np.column_stack([np.ones(len(d)), x, y, x * x, x * y, y * y, x**3, x * x * y, x * y * y, y**3])
    coef = np.linalg.lstsq(A, points[:, 2], rcond=None)[0]
    return float(coef[0]), coef[1:3]


def outer_points(model) -> np.ndarray:
    """The contact's (outer surface's) nodes of ``model``'s current membrane, (n, 3) m."""
    c = model.contact
    return c.X[c.nodes] + model.u[c.nodes]


def _fit_about(x: np.ndarray, at: np.ndarray) -> tuple[float, np.ndarray]:
    dist = np.linalg.norm(x[:, :2] - at, axis=1)
    radius = max(FIT_RADIUS, float(np.sort(dist)[min(FIT_NODES, len(dist) - 1)]))
    return surface_fit(x[dist <= radius], at)


def touch(model, xy: np.ndarray) -> tuple[int, np.ndarray]:
    """(index into the contact's nodes of the node the sphere coming down at ``xy`` touches
    first, ∇f (2,) of the outer surface there)."""
    n = model.first_contact(xy)[1]
    x = outer_points(model)
    return n, _fit_about(x, x[n, :2])[1]


def centre_touching(model, point: np.ndarray, radius: float | None = None) -> np.ndarray:
    """The centre (3,) m of the sphere of ``radius`` (default: the model's target's) that,
    coming down the vertical onto ``model``'s current membrane, touches its smooth outer surface
    first at the in-plane ``point`` (2,) m. A ValueError where ``point`` is off the membrane."""
    point = np.asarray(point, float)
    R = model.contact.radius if radius is None else float(radius)
    x = outer_points(model)
    r_out = float(np.hypot(x[:, 0], x[:, 1]).max())
    if math.hypot(*point) > r_out - FIT_RADIUS:
        raise ValueError(f"contact point {np.round(point * 1e3, 3).tolist()} mm is not on the membrane's top "
                         f"(its outer surface ends {r_out * 1e3:.3g} mm from the axis)")
    height, slope = _fit_about(x, point)
    normal = np.array([-slope[0], -slope[1], 1.0]) / math.sqrt(1.0 + slope @ slope)
    return np.array([point[0], point[1], height]) + R * normal


def depth_reach(model, touch_height: float) -> float:
    """How far (m) past the height ``touch_height`` at which it touches the sphere's centre may
    come down before its lowest point is the membrane's thickness above the base, where
    :meth:`~jointsim.mechanics.dome.MembraneModel.press` refuses it."""
    return touch_height - model.contact.radius - model.thickness


def press_through(model, xy: np.ndarray, touch_height: float, depths: np.ndarray, step: float) -> Iterator[tuple[float, object]]:
    """Press ``model``'s sphere, its centre over ``xy`` (2,) m, to each of ``depths`` (increasing,
    m past ``touch_height``, the height of its centre at first contact), each reached from the
    last in equal steps of at most ``step`` m; yields (depth, the model's state there). A press
    as a dataset takes it, and as a rig's known presses are simulated."""
    done = 0.0
    for d in depths:
        n = max(1, math.ceil((d - done) / step - 1e-9))
        for s in range(1, n + 1):
            state = model.press(np.array([xy[0], xy[1], touch_height - (done + (d - done) * s / n)]))
        done = d
        yield d, state


def point_touched(model, xy: np.ndarray, radius: float | None = None, tol: float = 1e-9) -> np.ndarray:
    """The in-plane point (2,) m where the sphere of ``radius`` (default: the model's target's)
    coming down at ``xy`` (2,) m first touches ``model``'s smooth outer surface: the inverse of
    :func:`centre_touching`, by the fixed point s = xy − R n_xy(s) (a contraction where R is
    less than the surface's radius of curvature, R/ρ ≈ 0.6 for the largest paper target)."""
    xy = np.asarray(xy, float)
    R = model.contact.radius if radius is None else float(radius)
    x = outer_points(model)
    s = xy.copy()
    for _ in range(100):
        slope = _fit_about(x, s)[1]
        s_new = xy + R * slope / math.sqrt(1.0 + slope @ slope)
        if np.abs(s_new - s).max() < tol:
            return s_new
        s = s_new
    raise ValueError(f"the touch point of a sphere of radius {R * 1e3:.4g} mm at {np.round(xy * 1e3, 3).tolist()} mm "
                     "did not converge (a surface more curved than the sphere)")
