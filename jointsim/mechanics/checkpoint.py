"""Checkpoints of a membrane: everything its next press depends on, as plain arrays.

Owns the layout of a membrane's state (displacement, the secant predictor's last two
equilibria, target centre, saline pressure, the closed chamber's compliance, the tangent the
next step predicts with, friction's stick anchors, the Newton shift carried between
regularised steps), so that a load step can be undone
(:meth:`~jointsim.mechanics.dome.MembraneModel._advance`) and a palpation resumed bit for bit.
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["membrane_state", "restore_membrane"]

# ``model`` below is a MembraneModel (or SoftTargetModel), typed Any: the model's module imports
# this one, and an import back would be a cycle


def membrane_state(model: Any) -> dict[str, np.ndarray]:
    """Everything ``model``'s next ``press`` depends on, as plain arrays (for checkpoints):
    displacement, the last two equilibria (the secant predictor), target centre, pressure
    and the closed chamber's compliance estimate."""
    hist = model.history
    return {
        "u": model.u.copy(),
        "hist_centre": np.array([c for c, _ in hist]).reshape(len(hist), 3),
        "hist_u": np.array([u for _, u in hist]).reshape((len(hist),) + model.u.shape),
        "centre": model.contact.centre.copy(),
        "pressure": np.float64(model.pressure.pressure),
        "compliance": np.float64(np.nan if model.compliance is None else model.compliance),
        # where the solver's factor (the next step's tangent predictor) was taken; (0, n, 3): none
        "tangent_u": _tangent_u(model),
        # friction's stick anchors (SphereFriction.commit): node indices and anchor − centre
        "friction_nodes": model.friction.anchor_nodes.copy() if model.friction is not None else np.zeros(0, np.int64),
        "friction_anchors": model.friction.anchors.copy() if model.friction is not None else np.zeros((0, 3)),
        # the Levenberg-Marquardt shift a regularised Newton step starts from, carried from one
        # to the next: without it a resumed run's next regularised step takes another path
        "newton_shift": np.float64(np.nan if model.system is None else model.system.shift),
        # the target centre and pressure the tangent was factored with (they may have moved since:
        # a step that converged without a factorisation keeps the factor of the step before)
        "tangent_context": _tangent_context(model),
    }

def _tangent_context(model: Any) -> np.ndarray:
    s = model.system
    if len(_tangent_u(model)) and s.tangent_context is not None:
        return s.tangent_context.copy()
    return np.zeros(0)


def _tangent_u(model: Any) -> np.ndarray:
    s = model.system
    ready = model.TANGENT_PREDICTOR and s is not None and s.tangent_ready and s.tangent_u is not None
    return np.array(s.tangent_u, float)[None] if ready else np.zeros((0,) + model.u.shape)

def restore_membrane(model: Any, state: dict[str, np.ndarray]) -> None:
    """Put ``model`` back in a :func:`membrane_state` of a model built from the same scene and mesh."""
    u = np.asarray(state["u"], float)
    if u.shape != model.u.shape:
        raise ValueError(f"state['u']: shape {u.shape}, this membrane has {model.u.shape} (another mesh?)")
    model.u = u.copy()
    model.history = [(np.array(c, float), np.array(v, float)) for c, v in zip(state["hist_centre"], state["hist_u"])]
    model.contact.centre = np.array(state["centre"], float)
    model.pressure.pressure = float(state["pressure"])
    c = float(state.get("compliance", np.nan))
    model.compliance = None if np.isnan(c) else c
    if model.friction is not None:  # a state saved before the anchors: none held
        model.friction.anchor_nodes = np.asarray(state.get("friction_nodes", np.zeros(0)), np.int64).copy()
        model.friction.anchors = np.asarray(state.get("friction_anchors", np.zeros((0, 3))), float).reshape(-1, 3).copy()
    shift = float(state.get("newton_shift", np.nan))  # a checkpoint of an older version has none
    if model.system is not None and not np.isnan(shift):
        model.system.shift = shift
    tangent = np.asarray(state.get("tangent_u", np.zeros((0,) + u.shape)), float)
    if model.TANGENT_PREDICTOR and len(tangent):
        context = np.asarray(state.get("tangent_context", np.zeros(0)), float)
        if len(context):  # factor the matrix the tangent was: its centre and pressure, then back
            centre, pressure = model.contact.centre.copy(), model.pressure.pressure
            model.contact.centre, model.pressure.pressure = context[:3].copy(), float(context[3])
            model.system.context = context.copy()
        model.system.factor_tangent(model.terms, tangent[0])
        if len(context):
            model.contact.centre, model.pressure.pressure = centre, pressure
    elif model.system is not None:
        model.system.tangent_ready = False
