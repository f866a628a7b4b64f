"""The sensor's electrical nuisance parameters fitted to a measured reference frame: the
saline's conductivity, every electrode's contact impedance and (optionally) every electrode's
centre in the base plane.

A real sensor is not the scene: its saline is warmer, its electrodes' contact differs one from
another, its electrodes sit where the flex circuit put them. The untouched sensor's reference
frame (hundreds of channels) holds most of that. With θ = (ln σ, ln z_l, x_l, y_l) the
Levenberg–Marquardt iteration

    (JᵀJ + μ D + P) δ = −Jᵀ r − P (θ − θ₀),   r = V(θ) − V_meas,

uses the adjoint sensitivities of :mod:`.parameters` on the fields of each iterate (one
factorisation per iterate; positions by re-clipping the discs at the moved centres), D the
diagonal of JᵀJ, μ adapted (halved on a step that lowers ‖r‖, raised ×4 and retried on one that
does not), and a weak Gaussian prior P about the scene's values (``prior_log`` on the logs,
``prior_position`` m on the centres) that keeps a parameter the frame cannot see where the
scene put it (the ground's contact impedance, for instance, where every measurement is
differential).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..mesh.electrodes import place_discs
from ..mesh.tetmesh import TetMesh
from .forward import ForwardModel
from .parameters import conductivity_sensitivity, contact_impedance_sensitivity, electrode_position_sensitivity, moved_discs
from .protocol import Protocol

__all__ = ["ElectricalFit", "fit_reference"]

POSITION_STEP = 1e-5  # m: the discs' moves for the position derivatives (tests/test_parameters.py)


@dataclass(frozen=True)
class ElectricalFit:
    """The fitted ``conductivity`` S/m, ``contact_impedance`` (n_el,) Ω·m² (the ground's
    included, in the layout's order) and electrode ``centres`` (n_el, 3) m; the relative residual
    ‖V(θ) − V_meas‖/‖V_meas‖ ``before`` and ``after``; ``iterations``."""

    conductivity: float
    contact_impedance: np.ndarray
    centres: np.ndarray
    before: float
    after: float
    iterations: int


def fit_reference(mesh: TetMesh, centres: np.ndarray, radii: np.ndarray, ground: int, protocol: Protocol,
                  v_meas: np.ndarray, conductivity: float, contact_impedance: np.ndarray, noise_std: float, *,
                  positions: bool = True, order: int = 1, prior_log: float = 1.0, prior_position: float = 0.5e-3,
                  max_iterations: int = 30, rtol: float = 1e-10, membrane: np.ndarray | None = None,
                  membrane_patch: str = "stretch") -> ElectricalFit:
    """Fit the reference frame ``v_meas`` (n_meas,) V of the chamber ``mesh`` with disc
    electrodes (``centres`` (n_el, 3), ``radii`` (n_el,) m, the ``ground``'s index) under
    ``protocol``, from the scene's ``conductivity`` and ``contact_impedance`` (n_el,); with
    ``positions`` the electrodes' centres too (the ground's stays: the ring is placed against
    it). The misfit is weighed by the channels' ``noise_std`` V against the prior (the MAP
    estimate). Stops when a step changes no parameter by more than ``rtol`` (relative, or
    m/radius for a position) or after ``max_iterations``."""
    v_meas = np.asarray(v_meas, float)
    n_el = len(radii)
    z0 = np.asarray(contact_impedance, float)
    moving = [l for l in range(n_el) if l != ground] if positions else []
    theta0 = np.concatenate([[np.log(conductivity)], np.log(z0), np.zeros(2 * len(moving))])
    prior = np.concatenate([np.full(1 + n_el, 1 / prior_log**2), np.full(2 * len(moving), 1 / prior_position**2)])

    def unpack(theta: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
        c = np.array(centres, float)
        c[moving, :2] += theta[1 + n_el:].reshape(-1, 2)
        return float(np.exp(theta[0])), np.exp(theta[1:1 + n_el]), c

    def solve(theta: np.ndarray):
        """(residual, the fields it came from, the centres) at ``theta``: one factorisation."""
        sigma, z, c = unpack(theta)
        patches = [p.follow(mesh.nodes) for p in place_discs(mesh, c, radii, membrane, membrane_patch, order == 2)]
        model = ForwardModel(mesh, patches, ground, z, "auto", order)
        fields = model.solve(sigma)
        return fields.voltages(protocol) - v_meas, fields, c

    def jacobian(fields, c: np.ndarray) -> np.ndarray:
        """∂V/∂θ on solved ``fields`` (no further solve)."""
        dz = contact_impedance_sensitivity(fields, protocol)
        cols = [conductivity_sensitivity(fields, protocol, dz)[:, None], dz.T]
        if moving:  # every disc moved (in the model's patch order), the moving ones kept
            moved = moved_discs(mesh, c, radii, POSITION_STEP, order == 2, membrane, membrane_patch)
            dc = electrode_position_sensitivity(fields, protocol, moved, POSITION_STEP)[moving]  # (k, 2, n_meas)
            cols.append(dc.reshape(-1, protocol.n_meas).T)
        return np.hstack(cols)

    scale = float(noise_std) ** 2  # the prior's weight against the squared residual (V²)

    def cost(r: np.ndarray, theta: np.ndarray) -> float:
        d = theta - theta0
        return float(r @ r + scale * d @ (prior * d))

    theta = theta0.copy()
    r, fields, c = solve(theta)
    J = jacobian(fields, c)
    before = float(np.linalg.norm(r) / np.linalg.norm(v_meas))
    mu, it = 1e-3, 0
    for it in range(1, max_iterations + 1):
        JtJ = J.T @ J
        g = J.T @ r + scale * prior * (theta - theta0)
        # the damping's floor keeps a direction the frame does not see (zero in JᵀJ) from
        # making H singular when the prior is weak
        D = np.diag(JtJ) + 1e-12 * np.diag(JtJ).max()
        while True:
            H = JtJ + mu * np.diag(D) + scale * np.diag(prior)
            step = -np.linalg.solve(H, g)
            # a trust region: a log at most ×e, a centre at most half its disc's radius per step
            step *= min(1.0, 1.0 / max(np.abs(step[:1 + n_el]).max(), 1e-300),
                        *([0.5 * np.min(np.asarray(radii)[moving]) / max(np.abs(step[1 + n_el:]).max(), 1e-300)]
                          if moving else []))
            trial = theta + step
            r_new, fields, c = solve(trial)
            if cost(r_new, trial) < cost(r, theta):
                mu = max(mu / 2, 1e-9)
                break
            mu *= 4
            if mu > 1e8:
                step = np.zeros_like(theta)
                break
        if not step.any():
            break
        # the accepted trial's fields serve its Jacobian: no second solve
        theta, r = trial, r_new
        J = jacobian(fields, c)
        size = np.abs(step) / np.concatenate([np.ones(1 + n_el), np.repeat(np.asarray(radii)[moving], 2)])
        if size.max() < rtol:
            break
    sigma, z, c = unpack(theta)
    return ElectricalFit(sigma, z, c, before, float(np.linalg.norm(r) / np.linalg.norm(v_meas)), it)
