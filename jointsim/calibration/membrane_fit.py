"""The membrane's modulus from a few known presses: what a calibration rig gives.

A rig presses a known rigid sphere (radius R) with its centre over a known point (x, y) of the
base plane to known depths d_k past first contact (where its load cell first reads a force)
and reads the contact force |F_k|. The membrane's moduli, all scaled by one factor s (the
datasets' ``membrane_scale``: batch, cure, temperature), are fitted to those forces through the
simulator:

    min over ln s of  Σ_k ((|F_k| − |F(d_k; s)|) / σ_k)²,   σ_k = rel · |F_k| + abs

by Gauss–Newton in ln s, the derivative a central difference in ln s at the start, then the
secant through the last two evaluations (the force is smooth and nearly proportional to s),
and a central difference again at the fit for its σ. Each evaluation builds the membrane at s,
inflated by the reservoir, and presses the sphere down to every depth in steps of at most the
scene's ``[dataset] step_mm``, as a dataset press does
(:func:`~jointsim.mechanics.touch.press_through`); the depths are past first contact on the
membrane at s, as the rig's are past its own.

Why the force and not the voltages: at a fixed depth the displaced saline, the EIT signal's
source, barely moves with the membrane's modulus (log-sensitivity −0.02 to −0.50 against the
force's +0.52 to +1.0, results/stiffness_sensitivity), so δV alone pins the scale poorly: a
press refitted through the simulator (jointsim.calibration.refine) reads it with a σ of
1.0–4.9 % in minutes, where a rig's forces give 0.4–0.6 % (results/membrane_fit.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from ..mechanics.build import membrane_from_scene
from ..mechanics.touch import press_through
from ..dataset.presses import PressList
from ..scene import Scene

__all__ = ["KnownPress", "MembraneScaleFit", "press_forces", "fit_membrane_scale", "known_presses", "FORCE_REL_SD",
           "FORCE_ABS_SD", "FORCE_SD_TEXT"]

FD_STEP = 0.02  # in ln s: the central difference of the force's derivative (F is nearly linear in s)
MAX_ITERATIONS = 8
STEP_TOL = 1e-4  # in ln s: a Gauss–Newton step below this ends the fit (0.01 % of the modulus)
# a load cell's σ of one reading, relative and in N: the fit's weights unless given
FORCE_REL_SD = 0.01
FORCE_ABS_SD = 1e-4
FORCE_SD_TEXT = f"{FORCE_REL_SD:.0%} + {FORCE_ABS_SD * 1e3:g} mN per reading"


@dataclass(frozen=True)
class KnownPress:
    """A press the rig knows: sphere ``radius`` m, its centre over ``xy`` (2,) m, ``depths``
    (K,) m past first contact, increasing, and the contact force |F| (K,) N read at each."""

    radius: float
    xy: np.ndarray
    depths: np.ndarray
    forces: np.ndarray

    def __post_init__(self) -> None:
        d, f = np.asarray(self.depths, float), np.asarray(self.forces, float)
        if not (self.radius > 0 and math.isfinite(self.radius)):
            raise ValueError(f"radius: must be a finite length > 0 m, got {self.radius!r}")
        if np.shape(self.xy) != (2,) or not np.all(np.isfinite(self.xy)):
            raise ValueError("xy: must be a finite (x, y) in m")
        if d.ndim != 1 or d.shape != f.shape or not len(d):
            raise ValueError("depths, forces: one force per depth, at least one")
        if not (np.all(d > 0) and np.all(np.diff(d) > 0)):
            raise ValueError("depths: must be > 0 m past first contact and increasing")
        if not (np.all(f > 0) and np.all(np.isfinite(f))):
            raise ValueError("forces: must be finite and > 0 N (a press past first contact pushes back)")


@dataclass(frozen=True)
class MembraneScaleFit:
    """The fitted scale ``scale`` of the membrane's moduli, its standard deviation ``sd_ln`` in
    ln s (from the Gauss–Newton curvature at the forces' σ), the forces at the fit (one array per
    press), the RMS of the weighted residuals ``misfit`` (≈ 1 where the σ is right and the model
    fits), and the Gauss–Newton ``iterations``."""

    scale: float
    sd_ln: float
    forces: tuple[np.ndarray, ...]
    misfit: float
    iterations: int


def press_forces(scene: Scene, press: KnownPress, scale: float, inflate_from: np.ndarray | None = None) -> np.ndarray:
    """|F| (K,) N of ``press`` on ``scene``'s membrane with its moduli × ``scale``, each depth past
    first contact on that membrane, reached in steps of at most ``[dataset] step_mm``."""
    scaled = replace(scene, membrane=scene.membrane.scaled(scale), target=replace(scene.target, kind="rigid"))
    model = membrane_from_scene(scaled, target_radius=press.radius, inflate_from=inflate_from)
    xy = np.asarray(press.xy, float)
    descent = press_through(model, xy, model.first_contact_height(xy), np.asarray(press.depths, float), scene.dataset.step)
    return np.array([np.linalg.norm(st.force) for _, st in descent])


def fit_membrane_scale(scene: Scene, presses: list[KnownPress], *, force_rel_sd: float = FORCE_REL_SD, force_abs_sd: float = FORCE_ABS_SD,
                       start: float = 1.0, inflate_from: np.ndarray | None = None) -> MembraneScaleFit:
    """The membrane's modulus scale s fitted to the forces of ``presses`` (module docstring).
    ``force_rel_sd``, ``force_abs_sd``: the load cell's σ of a reading, relative and in N;
    ``start``: the first s; ``inflate_from``: an inflated displacement to start each membrane's
    inflation from (the instrument's ``inflated_u``), which only saves time."""
    if not presses:
        raise ValueError("presses: at least one known press")
    if not (force_rel_sd >= 0 and force_abs_sd >= 0 and force_rel_sd + force_abs_sd > 0):
        raise ValueError("force_rel_sd, force_abs_sd: the force's σ must be >= 0 each and > 0 together")
    measured = np.concatenate([np.asarray(p.forces, float) for p in presses])
    sd = force_rel_sd * measured + force_abs_sd

    def forces(ln_s: float) -> np.ndarray:
        return np.concatenate([press_forces(scene, p, math.exp(ln_s), inflate_from) for p in presses])

    def slope(ln_s: float) -> np.ndarray:  # d(F/σ)/d ln s
        return (forces(ln_s + FD_STEP) - forces(ln_s - FD_STEP)) / (2 * FD_STEP) / sd

    ln_s = math.log(start)
    g = slope(ln_s)
    f = forces(ln_s)
    for it in range(1, MAX_ITERATIONS + 1):
        step = float(g @ ((measured - f) / sd) / (g @ g))
        ln_s += step
        f_new = forces(ln_s)
        if abs(step) < STEP_TOL:
            f = f_new
            break
        g, f = (f_new - f) / step / sd, f_new  # the secant through the last two: superlinear
    else:
        raise ValueError(f"the membrane's modulus scale did not settle in {MAX_ITERATIONS} steps (at x{math.exp(ln_s):.4g}): "
                         "do the forces grow with depth as a press's do?")
    g = slope(ln_s)
    r = (measured - f) / sd
    split = np.cumsum([len(p.depths) for p in presses])[:-1]
    return MembraneScaleFit(math.exp(ln_s), float(1 / math.sqrt(g @ g)), tuple(np.split(f, split)),
                            float(math.sqrt(np.mean(r**2))), it)


def known_presses(presses: PressList, what: str = "known presses") -> list[KnownPress]:
    """The presses of a press list (``jointsim dataset --presses``' CSV with a ``force_n``
    column) as :class:`KnownPress`; one-line errors for a list a rig's fit cannot use."""
    if presses.place != "centre":
        raise ValueError(f"{what}: give the target's centre (x_mm, y_mm), as the rig's stage sets it, not its contact point")
    if presses.depths is None or presses.forces is None:
        raise ValueError(f"{what}: give depth_mm and force_n: the force the rig read at each depth")
    if not np.isinf(presses.modulus).all():
        raise ValueError(f"{what}: rigid targets only (modulus_kpa empty or inf): a soft one's own modulus would enter the force")
    return [KnownPress(float(presses.radius[i]), presses.xy[i], presses.depths[i], presses.forces[i]) for i in range(len(presses))]
