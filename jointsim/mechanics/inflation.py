"""Deployment by inflation: a membrane moulded flat raised by the saline until its apex stands
at the dome's height (the reservoir then holds that pressure).

Owns the search for that pressure (secant steps on log apex rise against log pressure, each
equilibrium warm-started from the last) and its start from an earlier model's inflated state.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .newton import NewtonError, minimize_energy

__all__ = ["inflate"]

# ``model`` below is a MembraneModel, typed Any: the model's module imports this one, and an
# import back would be a cycle


def inflate(model: Any, height: float, mu: float, a: float, start: np.ndarray | None = None, rtol: float = 1e-4,
            max_iter: int = 30) -> None:
    """Raise ``model``'s saline pressure until the inner surface's apex (its node nearest the axis)
    stands ``height`` above the base (rim radius ``a``), to ``rtol``; the model is left there,
    at that pressure. ``start``: a displacement (n_nodes, 3) of this mesh already inflated to
    about that height (an earlier model's, its moduli scaled or its target another); the
    search then starts from it at the pressure that best balances it, instead of from the
    flat sheet (one equilibrium, no Newton iteration, instead of ~4: 0.6 s against 11.6 s at
    64/2)."""
    X = model.mesh.nodes[: model.n_surface]
    if not 0 < height < a:
        raise ValueError(f"inflate_to = {height}: must be in (0, {a:.4g}) m, a dome no higher than the rim's radius")
    apex = int(np.argmin(np.hypot(X[:, 0], X[:, 1])))
    moulded = float(X[apex, 2])
    if height <= moulded:
        raise ValueError(f"inflate_to = {height}: must exceed the apex's moulded height {moulded:.4g} m")
    # start from a thin membrane's estimate: the target cap stretched equibiaxially by its
    # arc over its chord, tension μt(1 − λ⁻⁶), p = 2T/R; then secant steps on log z(log p)
    # (z ∝ p^⅓ for a membrane), each equilibrium warm-started from the last
    R = (a * a + height * height) / (2 * height)
    lam = R * np.arcsin(a / R) / a
    p_est = 2 * mu * model.thickness * (1 - lam**-6) / R

    def apex_at(p: float) -> float:
        model.pressure.pressure = p
        res = minimize_energy([model.elastic, model.pressure], model.u, model.fixed, rtol=0.0, atol=model.force_tol, system=model.system)
        model.u = res.u
        return float(X[apex, 2] + model.u[apex, 2])

    def point(p: float) -> tuple[float, float]:  # (log pressure, log rise of the apex)
        return np.log(p), np.log(apex_at(p) - moulded)

    if start is None:
        # straight to the estimate: Newton's line search takes the flat sheet there (measured
        # 25-28 iterations on the paper's dome, against ~50 through a ramp); where it cannot, a
        # ramp from a plate-like deflection in steps of 4x in pressure (~1.6x in height)
        try:
            pts = [point(p_est)]
        except NewtonError:
            model.u = np.zeros_like(model.u)
            pts = [point(p) for p in p_est * 4.0 ** np.arange(-3, 1)]
    else:
        start = np.asarray(start, float)
        if start.shape != model.u.shape or not np.isfinite(start).all():
            raise ValueError(f"inflate_from: must be a finite displacement of shape {model.u.shape}, got {start.shape}")
        model.u = np.where(model.fixed, 0.0, start)
        # W'(u) = p V'(u) at equilibrium: the p that leaves the least out-of-balance force
        free = ~model.fixed.ravel()
        g = model.elastic.evaluate(model.u, False)[1][free]
        dV = model.pressure.volume_gradient(model.u)[free]
        p0 = float(g @ dV / (dV @ dV))
        pts = [point(p0 if p0 > 0 else p_est)]
    target = np.log(height - moulded)
    for _ in range(max_iter):
        lp1, lz1 = pts[-1]
        if abs(np.exp(lz1) - (height - moulded)) <= rtol * height:
            return
        lp0, lz0 = pts[-2] if len(pts) > 1 else (lp1, lz1)
        slope = (lz1 - lz0) / (lp1 - lp0) if lp1 != lp0 else 1 / 3
        step = (target - lz1) / max(slope, 0.05)
        lp = lp1 + float(np.clip(step, -np.log(4.0), np.log(4.0)))
        pts.append(point(float(np.exp(lp))))
    last = (moulded + np.exp(pts[-1][1])) * 1e3
    raise NewtonError(f"inflation to an apex height of {height * 1e3:.4g} mm: not reached in {max_iter} pressure steps "
                      f"(last {last:.4g} mm at {np.exp(pts[-1][0]):.4g} Pa)")
