"""A press refined through the simulator itself: its target fitted to the measured frames by
Levenberg–Marquardt on the coupled model, from the emulator's (or the regression's) estimate.

The emulator (:mod:`.emulator`) is fast and approximate: its own error, not the noise, sets
its accuracy (held-out R² 0.64–0.69 in the whitened features; results/calibration/model_based.md).
Where an estimate must be as good as the frames allow, the press is refitted through the
simulator that made the emulator's training data: the membrane pressed, the chamber morphed,
the forward solved, with the derivatives of :func:`~jointsim.design.sensitivity.press_sensitivity`
(the implicit function theorem through the mechanics, differences along the morph) — the
estimator whose error the Cramér–Rao bounds of :mod:`jointsim.design` describe.

The data of one press: the measured reference frame y₀ (the mean of r untouched frames) and
the press's K frames y_k. The unknowns

    p = (x_c, y_c, R, d̃_1 … d̃_K, [ln E,] ln s, ln σ, ln z_1 … ln z_n),

the target's centre in the base plane, its radius, each frame's depth, a soft target's Young's
modulus E (a neo-Hookean sphere solved with the membrane,
:class:`~jointsim.mechanics.soft_target.SoftTargetModel`; absent for a rigid one), the
membrane's modulus scale s, the saline's conductivity and every electrode's contact impedance;
a prior over the scene's [dataset] randomisation about the scene's values holds the nuisances
(the radius and E weakly, over their ranges; the head at the scene's, since a cap's press sees
only its ratio to the modulus). A soft target's press costs ~6× a rigid one's (two bodies
in one Newton system, ~40 s at the P1 dataset fidelity for six frames), and its fit does not
yet read the modulus (:func:`refine_press`). The depths d̃_k are past the height where the
sphere touches one membrane node, the same node at every trial (the one touched first at the start): the height of first contact
itself, what a dataset's depths are measured from and what the estimates report, has a kink
wherever the node touched first changes. The misfit

    Φ(p) = Σ_k ‖y_k − V_k(p)‖²/σ_n² + r ‖y₀ − V₀(p)‖²/σ_n² + (p − m)ᵀ P (p − m),

σ_n the noise of one frame, P the prior's precision, is minimised by Levenberg–Marquardt, each
trial point one press through the simulator (a few seconds at the dataset fidelity).

The electrodes' centres are fitted too. A tenth of a millimetre of electrode placement moves
the frames by tens of noise σ, so they cannot be left out. The fit starts from
:func:`fit_electrical` (the reference frame alone, at the scene's modulus scale), descends with
the centres held there, then descends again with them free (:func:`_joint_descent`). Held to the
end, as an earlier version did (refitted to the reference between descents), they left the fit
off its optimum along a curved valley in which the modulus scale trades against the electrode
ring's radius: on the test chamber a fit 16 % high in the scale had every electrode ~13 µm
inside its true place, its Φ within 3 of the truth's while the linearised model put the two
45σ apart. The scale came out biased by 7.5–10 % median on held-out dataset presses, and the
target's centre with it by 3–5 of its σ. The joint descent follows the valley at about 1σ a
step (:data:`MAX_TRIALS`).

The estimate's covariance is the p-block of (JᵀJ/σ_n² + P)⁻¹ at the fit, the electrodes'
centres included (:func:`marginal_covariance`); the contact's (its centre of pressure, what the
calibration labels as position) and the depths' through their own derivatives. A press the
emulator already fits within the goals gains nothing; one it fits poorly gains most
(:func:`worth_refining`).
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass, replace

import numpy as np

from ..design.bounds import nuisance_prior
from ..design.sensitivity import ELECTRODE_STEP, TARGET_MODULUS, electrode_moves, head_moves, parameter_names, press_electrical, press_mechanics
from ..eit.fit import ElectricalFit, fit_reference
from ..instrument import Instrument, Readout
from ..mechanics.build import membrane_from_scene
from ..mechanics.dome import MembraneModel, UnreachablePose
from ..mechanics.newton import NewtonError
from ..mechanics.touch import centre_touching, depth_reach
from ..mesh.morph import MeshInversionError

__all__ = ["PressRefit", "fit_electrical", "marginal_covariance", "refine_press", "worth_refining"]

try:  # a factorisation that breaks down at a trial point far off (a zero pivot) rejects the trial
    from pypardiso.pardiso_wrapper import PyPardisoError as _FactorisationError
except ImportError:  # pragma: no cover - PARDISO absent: SuperLU raises RuntimeError
    _FactorisationError = RuntimeError
# what a trial point can cause: it is rejected and the damping raised
_TRIAL_FAILURES = (UnreachablePose, NewtonError, MeshInversionError, ValueError, _FactorisationError)

def _step_limits(K: int, n_p: int, n_centres: int = 0) -> np.ndarray:
    """The largest step of each of the ``n_p`` parameters of a ``K``-frame press: 0.5 mm of
    centre, 1 mm of radius, 0.2 mm of depth, 0.5 in a log (×1.65); then 20 µm for each of
    ``n_centres`` electrode coordinates (twice the spread a reference fit leaves them)."""
    return np.concatenate([[0.5e-3, 0.5e-3, 1e-3], np.full(K, 0.2e-3), np.full(n_p - 3 - K, 0.5), np.full(n_centres, 20e-6)])


MIN_DEPTH = 20e-6  # m: a frame's depth is kept past first contact by at least this
# presses through the simulator per fit, at most: the joint descent follows a curved valley
# (the modulus scale against the electrode ring's radius and the contact impedances) at about
# 1σ a step. On 24 held-out dataset presses (P1 `dataset` preset, 64-rim membrane) it took
# 22–60, half of them 35 or fewer (results/calibration/simulator_refine_split*.md); stopped
# at 30, one was left with its scale 16 % off and its contact 96 µm (15σ)
MAX_TRIALS = 60


@dataclass(frozen=True, eq=False)
class PressRefit:
    """One press fitted through the simulator: per frame the contact's centre of pressure
    ``contact`` (K, 2) m and ``depth`` (K,) m; the target's ``diameter`` m and centre ``centre``
    (2,) m; the membrane's modulus ``scale``; their standard deviations ``contact_sd`` (K, 2),
    ``depth_sd`` (K,), ``diameter_sd``, ``scale_sd``; the misfit per channel in noise σ
    ``misfit`` (before, after: √(Φ_data / n)); ``trials`` presses through the simulator,
    ``iterations`` accepted steps, ``seconds``; a soft target's Young's ``modulus`` Pa and the
    σ of its logarithm ``ln_modulus_sd`` (its relative error; NaN for a rigid target)."""

    contact: np.ndarray
    depth: np.ndarray
    diameter: float
    centre: np.ndarray
    scale: float
    contact_sd: np.ndarray
    depth_sd: np.ndarray
    diameter_sd: float
    scale_sd: float
    misfit: tuple[float, float]
    trials: int
    iterations: int
    seconds: float
    modulus: float = math.nan
    ln_modulus_sd: float = math.nan


def fit_electrical(inst: Instrument, v_ref: np.ndarray, reference_frames: int, noise_std: float) -> ElectricalFit:
    """The saline, contact impedances and electrode centres of ``inst``'s sensor fitted to the
    measured reference ``v_ref`` (n_meas,) V, the mean of ``reference_frames`` frames of noise
    ``noise_std`` V each (:func:`~jointsim.eit.fit.fit_reference`), on the instrument's
    reference chamber from the scene's conductivity and contact impedances. The start of
    :func:`refine_press` (a start 10 % off in the contact impedances left the first descents to
    chase them, and the modulus scale with them, by tens of thousands of σ), and ``jointsim
    frames --fit-reference``."""
    scene, layout, ch = inst.scene, inst.reference.layout, inst.reference
    return fit_reference(ch.mesh, layout.centres, layout.radii, ch.ground, inst.protocol, v_ref,
                         scene.saline.conductivity, scene.electrodes.contact_impedances,
                         noise_std / math.sqrt(reference_frames), order=scene.mesh.element_order,
                         membrane=layout.membrane, membrane_patch=layout.membrane_patch)


class _Press:
    """The simulator of one press for the fit: p ↦ (the reference's and the frames' voltages,
    their derivatives, the contacts) on a membrane rebuilt when the modulus scale moves (with a
    soft target, whenever the scale, its radius or its modulus moves) and a
    readout rebuilt for the saline and contact impedances of p (a few tenths of a second beside
    the press's seconds)."""

    def __init__(self, inst: Instrument, K: int, offsets: np.ndarray | None = None, soft: bool = False):
        self.inst = inst
        self.K = K
        self.soft = bool(soft)
        self.i_scale = 3 + K + self.soft  # p's membrane modulus scale (after a soft target's ln E)
        self.scene = inst.scene
        self.names = parameter_names(len(inst.reference.layout.radii), self.soft)
        self.n_el = len(inst.reference.layout.radii)
        # the electrodes' centres (module docstring), and their discs moved either way for
        # press_electrical's position columns
        self.offsets = np.zeros((self.n_el, 2)) if offsets is None else np.asarray(offsets, float).reshape(-1, 2)
        self.moves = self.moves_at(self.offsets)
        self.model: MembraneModel | None = None
        self.built = (math.nan, math.nan, math.nan)  # (scale, radius, E) of a soft target's model
        self.scale = math.nan
        self.trials = 0
        self.node: int | None = None  # the node whose touch the depths are past (module docstring)

    def membrane(self, scale: float, radius: float, modulus: float | None = None) -> MembraneModel:
        """The untouched membrane at the modulus ``scale`` with a rigid sphere of ``radius`` m, or
        a soft one of Young's modulus ``modulus`` Pa (its mesh rebuilt whenever R or E moves,
        as the dataset builds each press's: the same target mesh, turn and slaves)."""
        if modulus is not None:
            key = (scale, float(radius), float(modulus))
            if self.model is None or self.built != key:
                sc = self.scene
                scaled = replace(sc, membrane=sc.membrane.scaled(scale), target=replace(sc.target, kind="rigid"))
                self.model = membrane_from_scene(scaled, target_radius=float(radius), target_modulus=float(modulus),
                                                 inflate_from=self.inst.inflated_u)
                self.built = key
            return self.model
        if self.model is None or abs(math.log(scale / self.scale)) > 1e-9:
            sc = self.scene
            scaled = replace(sc, membrane=sc.membrane.scaled(scale), target=replace(sc.target, kind="rigid"))
            self.model = membrane_from_scene(scaled, target_radius=radius, inflate_from=self.inst.inflated_u)
            self.scale = scale
        self.model.contact.radius = float(radius)
        return self.model

    def moves_at(self, offsets: np.ndarray) -> list:
        """The electrode discs at ``offsets`` (2 n_el,) m from the layout's centres, each moved
        either way for the position derivatives."""
        return electrode_moves(self.inst, ELECTRODE_STEP, offsets)

    def readout(self, eta: np.ndarray) -> Readout:
        """The readout of the electrical nuisances ``eta`` = (ln σ, ln z_l…) with the electrodes
        at :attr:`offsets` from the layout's centres."""
        n = self.n_el
        inst = self.inst
        return Readout.on(inst.reference, self.scene, inst.protocol, rng=None, reference_frames=inst.readout.reference_frames,
                          conductivity=math.exp(eta[0]), contact_impedance=np.exp(eta[1:1 + n]),
                          offsets=self.offsets, snr_db=inst.readout.snr_db)

    def __call__(self, p: np.ndarray) -> tuple[np.ndarray, ...]:
        """At ``p`` (module docstring): V₀ (M,), V (K, M), ∂[V₀; V]/∂p ((K+1)·M, n_p), the
        contacts (K, 2) and ∂contact_k/∂p (K, 2, n_p), the depths (K,) past first contact and
        ∂depth_k/∂p (K, n_p), and ∂[V₀; V]/∂(x0, y0, x1, …) ((K+1)·M, 2 n_el) along the electrodes'
        centres (the joint descent's and the covariance's, :func:`refine_press`).
        A ValueError where a frame's sphere would be above the membrane."""
        K, i_s = self.K, self.i_scale
        centre, radius, depths_node, ln_s = p[:2], float(p[2]), p[3:3 + K], float(p[i_s])
        self.trials += 1
        model = self.membrane(math.exp(ln_s), radius, math.exp(p[3 + K]) if self.soft else None)
        if self.node is None:
            self.node = model.first_contact(centre)[1]
        z_node, _ = _node_touch(model, centre, model.u, None, self.node)
        z_first = model.first_contact_height(centre)
        depths = z_first - (z_node - depths_node)  # past the first contact, as the dataset measures
        if depths.min() <= 0.0:
            raise ValueError("refine_press: a frame's sphere above the membrane")
        order = np.argsort(depths, kind="stable")
        d = np.maximum.accumulate(depths[order])  # the press goes down: ties kept in order
        mech = press_mechanics(model, centre, d, head=head_moves(self.scene))
        # the depths are the fit's past one node's touch, the same node at every trial: the
        # height of first contact has a kink wherever the node touched first changes
        _, along = _node_touch(model, centre, mech.u_ref, mech.du_ref, self.node)
        _, first = _node_touch(model, centre, mech.u_ref, mech.du_ref)
        mech = replace(mech, dzc=along)
        readout = self.readout(p[i_s + 1:])
        try:
            inst = replace(self.inst, readout=readout)
            ps = press_electrical(inst, mech, moves=self.moves)
            chamber, _ = inst.morpher.morph(inst.dome(mech.u_ref))
            v0 = readout.voltages(chamber, True)
        finally:
            readout.free()
        n = self.names
        ix, iy, idep, irad, imod = (n.index(k) for k in ("x", "y", "depth", "radius", "ln_modulus"))
        electrical = slice(n.index("ln_conductivity"), n.index("ln_conductivity") + 1 + self.n_el)
        centres = slice(n.index("x0"), n.index("x0") + 2 * self.n_el)
        M, n_p = len(v0), len(p)
        J = np.zeros(((K + 1) * M, n_p))
        J[:M, i_s] = ps.jacobian_ref[:, imod]
        J[:M, i_s + 1:] = ps.jacobian_ref[:, electrical]
        Jc = np.zeros(((K + 1) * M, 2 * self.n_el))
        Jc[:M] = ps.jacobian_ref[:, centres]
        V = np.zeros((K, M))
        contact = np.zeros((K, 2))
        cj = np.zeros((K, 2, n_p))
        dd = np.zeros((K, n_p))
        for j, k in enumerate(order):  # frame k is the j-th deepest of the press
            V[k] = ps.voltages[j]
            rows = slice((k + 1) * M, (k + 2) * M)
            Jk = ps.jacobian[j]  # at a fixed depth past the node's touch
            J[rows, 0], J[rows, 1], J[rows, 2] = Jk[:, ix], Jk[:, iy], Jk[:, irad]
            J[rows, 3 + k] = Jk[:, idep]
            J[rows, i_s] = Jk[:, imod]  # the membrane's alone: a soft target's E held
            J[rows, i_s + 1:] = Jk[:, electrical]
            Jc[rows] = Jk[:, centres]
            contact[k] = ps.contact[j, :2]
            c = ps.contact_jacobian[j]  # (2, 4; a soft target 5) the same way
            cj[k, :, 0], cj[k, :, 1], cj[k, :, 2], cj[k, :, 3 + k] = c[:, 0], c[:, 1], c[:, 3], c[:, 2]
            if self.soft:  # a soft target's modulus (it does not move the first contact: dd's 0)
                J[rows, 3 + K] = Jk[:, n.index(TARGET_MODULUS)]
                cj[k, :, 3 + K] = c[:, 4]
            # depth = z_first − z_node + the fit's depth; the modulus scale acts as the head's inverse
            dd[k, :3] = (first["x"] - along["x"], first["y"] - along["y"], first["radius"] - along["radius"])
            dd[k, 3 + k], dd[k, i_s] = 1.0, -(first["ln_pressure"] - along["ln_pressure"])
        return v0, V, J, contact, cj, depths, dd, Jc


def _node_touch(model: MembraneModel, xy: np.ndarray, u: np.ndarray, du: np.ndarray | None,
                node: int | None = None) -> tuple[float, dict[str, float]]:
    """The height at which the sphere coming down at ``xy`` touches the membrane's outer node
    ``node`` (an index into the contact's nodes; default the one it touches first: its
    :meth:`~jointsim.mechanics.dome.MembraneModel.first_contact_height`, what a dataset's
    depths are measured from), z = z_n + √(R² − ρ²) at in-plane distance ρ, on the untouched
    membrane ``u``; and ∂z/∂(x, y, radius, ln p) with ``du`` the membrane's head derivative.
    Not the smooth surface's slope (:func:`~jointsim.design.sensitivity.press_mechanics`): off
    a node the two differ by tens of per cent, and a fit must follow the depths the dataset
    pressed to."""
    R = model.contact.radius
    n = model.contact.nodes[model.first_contact(xy)[1] if node is None else node]
    xn = model.contact.X[n] + u[n]
    off = np.asarray(xy, float) - xn[:2]
    s = math.sqrt(max(R * R - off @ off, (0.01 * R) ** 2))
    head = 0.0 if du is None else float(du[n, 2] + off @ du[n, :2] / s)
    return float(xn[2] + s), {"x": float(-off[0] / s), "y": float(-off[1] / s), "radius": R / s, "ln_pressure": head}


def _levenberg_marquardt(evaluate, objective, p: np.ndarray, state: tuple, precision: np.ndarray, mean: np.ndarray,
                         budget: int, sim: "_Press", tol: float, limits: np.ndarray, r_lo: float) -> tuple[np.ndarray, tuple, int]:
    """Levenberg–Marquardt on Φ from ``p`` (its ``evaluate`` ``state``) until the steps fall
    below ``tol`` σ or the simulator has been called ``budget`` times: (p, its state, accepted
    steps). The damping follows the gain ratio ρ, Φ's actual fall over the quadratic model's
    (Nielsen's rule: divided by at most 3 where the model held). Undamped, a step along the weak
    directions (depths, radius, scale and contact impedances are strongly correlated) reaches
    where the node the sphere touches first changes, and Φ rises tenfold; dividing the damping
    by 10 on every good step made the iteration alternate between the two."""
    r, J = state[0], state[1]
    phi = objective(p, r)
    mu, nu, accepted = 1e-3, 2.0, 0
    while sim.trials < budget:
        A = J.T @ J + np.diag(precision)
        g = J.T @ r + precision * (p - mean)
        D = np.diag(A) + 1e-12 * np.diag(A).max()
        step = -np.linalg.solve(A + mu * np.diag(D), g)
        # a trust region: no step past what one linearisation can hold (far from the fit, the
        # first steps asked contact impedances to change ×e^10 and the scale ×100)
        step *= min(1.0, float(np.min(limits / np.maximum(np.abs(step), 1e-300))))
        trial = p + step
        trial[2] = max(trial[2], 0.5 * r_lo)
        step = trial - p
        predicted = -(2 * g @ step + step @ A @ step)
        try:
            out = evaluate(trial)
        except _TRIAL_FAILURES:
            mu, nu = mu * nu, 2 * nu
            continue
        phi_t = objective(trial, out[0])
        rho = (phi - phi_t) / max(predicted, 1e-300)
        if os.environ.get("JOINTSIM_REFINE_TRACE"):
            z = step / np.sqrt(np.diag(np.linalg.inv(A)))
            top = np.argsort(-np.abs(z))[:4]
            print(f"  trial {sim.trials}: Φ {phi_t:.5g} (from {phi:.5g}, gain ratio {rho:.2f}), damping {mu:.2g}; "
                  f"largest steps in σ: {', '.join(f'{i}: {z[i]:+.2f}' for i in top)}", flush=True)
        if phi_t < phi:
            p, state, phi = trial, out, phi_t
            r, J = state[0], state[1]
            mu, nu = mu * max(1 / 3, 1 - (2 * rho - 1) ** 3), 2.0
            accepted += 1
            sd = np.sqrt(np.diag(np.linalg.inv(J.T @ J + np.diag(precision))))
            if np.all(np.abs(step) < tol * sd):
                break
        else:
            mu, nu = mu * nu, 2 * nu
            if mu > 1e6:
                break
    return p, state, accepted


def refine_press(inst: Instrument, frames: np.ndarray, v_ref: np.ndarray, reference_frames: int,
                 contact: np.ndarray, depths: np.ndarray, diameter: float, *, electrical: ElectricalFit | None = None,
                 noise_std: float | None = None, modulus: float | None = None, max_trials: int = MAX_TRIALS,
                 tol: float = 0.1) -> PressRefit:
    """The press of measured ``frames`` (K, n_meas) V against the measured reference ``v_ref``
    (n_meas,) V (the mean of ``reference_frames`` frames), fitted through the simulator of
    ``inst``'s scene, from a start: the contact (2,) m (the first frame's centre of pressure, or
    where the target first touched), the frames' ``depths`` (K,) m, the target's ``diameter`` m
    and the sensor's ``electrical`` nuisances (:func:`fit_electrical`; default the scene's), the
    modulus scale at 1 (module docstring). ``noise_std`` V of one frame (default the
    instrument's, at its SNR). Stops when every step is below ``tol`` of its parameter's σ, or
    after ``max_trials`` presses through the simulator.

    ``modulus``: the target is soft, its Young's modulus fitted too, ``modulus`` Pa among the
    values it starts from (None: a rigid target). The press is first fitted as a rigid
    target's (~6× cheaper a trial), then as the soft one's from there, its modulus started at
    whichever of ``modulus`` and :data:`SOFT_STARTS` values over the scene's [dataset] range
    fits best: a soft sphere's size and modulus trade along a valley the descent does not
    follow from an estimate as far off as the emulator's. Not yet a reliable reading of the
    modulus: along that valley the frames may not separate two spheres at all, and the σ at
    the fit is then one point's curvature (docs/calibration.md, "Soft targets")."""
    t0 = time.perf_counter()
    frames = np.atleast_2d(np.asarray(frames, float))
    K = len(frames)
    sigma = inst.readout.noise_std if noise_std is None else float(noise_std)
    layout = inst.reference.layout
    soft = modulus is not None
    if soft and not (math.isfinite(modulus) and modulus > 0):
        raise ValueError(f"refine_press: modulus = {modulus}: a soft target's Young's modulus must be > 0 Pa")
    scene = inst.scene
    sim = _Press(inst, K, None if electrical is None else electrical.centres[:, :2] - layout.centres[:, :2])
    eta = _scene_electrical(scene)
    if electrical is not None:
        eta = np.concatenate([[math.log(electrical.conductivity)], np.log(electrical.contact_impedance)])
    radius = 0.5 * float(diameter)
    start_model = sim.membrane(1.0, radius)  # the first trial's, too
    centre = centre_touching(start_model, np.asarray(contact, float))[:2]
    # a start past what the dome allows there (a large sphere near the ring, deep) held short of it
    reach = depth_reach(start_model, start_model.first_contact_height(centre))
    if reach <= MIN_DEPTH:
        raise ValueError(f"refine_press: a {2e3 * radius:.3g} mm sphere touching at {np.round(np.asarray(contact) * 1e3, 2).tolist()} "
                         "mm cannot press the dome there; start from another diameter")
    start_depths = np.clip(np.asarray(depths, float), MIN_DEPTH, 0.95 * reach)
    p = np.concatenate([centre, [radius], start_depths, [0.0], eta])
    fit, p = _fit(sim, frames, v_ref, reference_frames, sigma, p, (), max_trials, tol)
    if not soft:
        return replace(fit, seconds=time.perf_counter() - t0)
    # the soft target from the rigid fit: its depths past first contact (the soft fit's node is
    # the one touched first there), its modulus where the candidates fit best
    e_lo, e_hi = scene.dataset.target_modulus
    starts = (float(modulus),) + tuple(np.exp(np.linspace(math.log(e_lo), math.log(e_hi), SOFT_STARTS)))
    q = np.concatenate([p[:3], fit.depth, [math.nan], p[3 + K:]])
    soft_sim = _Press(inst, K, sim.offsets, soft=True)
    soft_fit, _ = _fit(soft_sim, frames, v_ref, reference_frames, sigma, q, starts, max_trials, tol)
    return replace(soft_fit, misfit=(fit.misfit[0], soft_fit.misfit[1]), trials=sim.trials + soft_sim.trials,
                   iterations=fit.iterations + soft_fit.iterations, seconds=time.perf_counter() - t0)


# a soft target's fit starts its modulus at the best of these many values, log-spaced over the
# scene's [dataset] range, and the one asked for (refine_press)
SOFT_STARTS = 4


def _scene_electrical(scene) -> np.ndarray:
    """The scene's electrical nuisances as p holds them: (ln σ, ln z_l…)."""
    return np.concatenate([[math.log(scene.saline.conductivity)], np.log(scene.electrodes.contact_impedances)])


def _fit(sim: _Press, frames: np.ndarray, v_ref: np.ndarray, reference_frames: int, sigma: float, p: np.ndarray,
         moduli: tuple[float, ...], max_trials: int, tol: float) -> tuple[PressRefit, np.ndarray]:
    """:func:`refine_press`'s descents from ``p`` through ``sim`` (its electrodes where it holds
    them): a rigid target, or a soft one (``sim.soft``) with p's ln E (NaN) set to the best of
    ``moduli`` (one trial each): (the fit, its p)."""
    K, M = frames.shape
    soft = sim.soft
    scene, n, i_s = sim.scene, sim.n_el, sim.i_scale
    # the prior: the modulus scale and the electrical nuisances over the scene's randomisation
    # about its values, the radius (and a soft target's ln E) weakly over its range
    names = sim.names[sim.names.index("ln_modulus"):sim.names.index("ln_conductivity") + 1 + n]
    nuisance_sd = nuisance_prior(scene, ("x", "y", "depth", "radius") + names)
    eta_scene = _scene_electrical(scene)
    r_lo, r_hi = scene.dataset.radius
    n_p = i_s + len(nuisance_sd)
    mean = np.zeros(n_p)
    mean[2] = 0.5 * (r_lo + r_hi)
    mean[i_s + 1:] = eta_scene
    precision = np.zeros(n_p)
    precision[2] = 1.0 / (r_hi - r_lo) ** 2
    precision[i_s:] = 1.0 / np.maximum(nuisance_sd, 1e-12) ** 2
    if soft:
        e_lo, e_hi = np.log(scene.dataset.target_modulus)
        mean[3 + K], precision[3 + K] = 0.5 * (e_lo + e_hi), 1.0 / max(e_hi - e_lo, 1.0) ** 2
    w = np.concatenate([np.full(M, math.sqrt(reference_frames)), np.ones(K * M)]) / sigma
    y = np.concatenate([v_ref, frames.ravel()])

    def evaluate(p):
        v0, V, J, c, cj, d, dd, Jc = sim(p)
        r = w * (np.concatenate([v0, V.ravel()]) - y)
        return r, w[:, None] * J, c, cj, d, dd, w[:, None] * Jc

    def objective(p, r):
        dp = p - mean
        return float(r @ r + dp @ (precision * dp))

    start = state = None
    for E in moduli or (None,):
        trial = p.copy()
        if E is not None:
            trial[3 + K] = math.log(E)
        try:
            out = evaluate(trial)
        except _TRIAL_FAILURES:
            if E is None:
                raise
            continue  # a modulus the press cannot take there: the others are tried
        if state is None or objective(trial, out[0]) < objective(start, state[0]):
            start, state = trial, out
    if state is None:
        raise ValueError(f"refine_press: the soft target cannot be pressed there at any of {np.round(moduli).tolist()} Pa")
    p = start
    before = math.sqrt(float(state[0] @ state[0]) / len(state[0]))
    # first with the electrodes' centres held where the reference frame alone puts them (a
    # quick descent: the target and the nuisances' large moves), then with them free too
    p, state, iterations = _levenberg_marquardt(evaluate, objective, p, state, precision, mean, max_trials // 2, sim, tol,
                                                _step_limits(K, len(p)), r_lo)
    centre_sd = nuisance_prior(scene, ("x", "y", "depth", "radius") + sim.names[sim.names.index("x0"):])
    free = centre_sd > 0
    p, state, done = _joint_descent(sim, evaluate, objective, p, state, precision, mean, max_trials, tol, K, r_lo,
                                    free, centre_sd[free])
    iterations += done
    r, J, c, cj, d, dd, Jc = state
    C = marginal_covariance(J, precision, Jc, centre_sd)
    sd = np.sqrt(np.diag(C))
    contact_sd = np.sqrt(np.einsum("kip,pq,kiq->ki", cj, C, cj))
    depth_sd = np.sqrt(np.einsum("kp,pq,kq->k", dd, C, dd))
    ln_s = float(p[i_s])
    fit = PressRefit(c, d, 2 * float(p[2]), p[:2].copy(), math.exp(ln_s), contact_sd, depth_sd,
                     2 * float(sd[2]), math.exp(ln_s) * float(sd[i_s]), (before, math.sqrt(float(r @ r) / len(r))),
                     sim.trials, iterations, math.nan,
                     math.exp(p[3 + K]) if soft else math.nan, float(sd[3 + K]) if soft else math.nan)
    return fit, p


def _joint_descent(sim: _Press, evaluate, objective, p: np.ndarray, state: tuple, precision: np.ndarray, mean: np.ndarray,
                   budget: int, tol: float, K: int, r_lo: float, free: np.ndarray, centre_sd: np.ndarray) -> tuple[np.ndarray, tuple, int]:
    """Levenberg–Marquardt on (p, the ``free`` electrode coordinates' offsets) from ``p`` and the
    electrodes where :attr:`_Press.offsets` holds them, their prior N(0, ``centre_sd``²) about the
    layout (the scene's jitter): (p, its state in :func:`refine_press`'s form, accepted steps),
    the electrodes left at the accepted offsets."""
    n_p = len(p)
    start = sim.offsets.ravel().copy()

    def at(q: np.ndarray) -> np.ndarray:
        o = start.copy()
        o[free] = q[n_p:]
        return o.reshape(-1, 2)

    def joint(q: np.ndarray) -> tuple:
        sim.offsets = at(q)
        sim.moves = sim.moves_at(sim.offsets)
        return widen(evaluate(q[:n_p]))

    def widen(st: tuple) -> tuple:
        r, J, c, cj, d, dd, Jc = st
        q = int(free.sum())
        return (r, np.hstack([J, Jc[:, free]]), c, np.concatenate([cj, np.zeros(cj.shape[:2] + (q,))], axis=2), d,
                np.hstack([dd, np.zeros((len(dd), q))]), Jc)

    q0 = np.concatenate([p, start[free]])
    P = np.concatenate([precision, 1.0 / centre_sd**2])
    m = np.concatenate([mean, np.zeros(len(centre_sd))])
    q, st, done = _levenberg_marquardt(joint, lambda q, r: objective(q[:n_p], r) + float(q[n_p:] @ (q[n_p:] / centre_sd**2)),
                                       q0, widen(state), P, m, budget, sim, tol,
                                       _step_limits(K, n_p, len(centre_sd)), r_lo)
    sim.offsets = at(q)
    sim.moves = sim.moves_at(sim.offsets)
    r, J, c, cj, d, dd, Jc = st
    return q[:n_p], (r, J[:, :n_p], c, cj[..., :n_p], d, dd[:, :n_p], Jc), done


def marginal_covariance(J: np.ndarray, precision: np.ndarray, J_held: np.ndarray, held_sd: np.ndarray) -> np.ndarray:
    """The covariance (n_p, n_p) of the fitted p, from the weighted Jacobian ``J`` (m, n_p) and
    the prior's ``precision`` (n_p,), with other parameters fitted beside it (``J_held`` (m, q),
    their prior std ``held_sd`` (q,), 0 for one known exactly) marginalised: the p-block of the
    joint (JᵀJ + P)⁻¹. The electrodes' centres are fitted to the same frames as the target and the
    nuisances, so what the data leave of them in doubt is the estimate's doubt too (on the
    test chamber it widens the modulus scale's σ 2.7× and the contact impedances' 4–6×, the
    target's by 0–2 %)."""
    free = np.asarray(held_sd) > 0
    Jh = np.asarray(J_held)[:, free]
    A = np.block([[J.T @ J + np.diag(precision), J.T @ Jh],
                  [Jh.T @ J, Jh.T @ Jh + np.diag(1.0 / np.asarray(held_sd)[free] ** 2)]])
    s = 1.0 / np.sqrt(np.diag(A))  # the columns' units differ by 1e4 (m against ln): scaled
    n_p = J.shape[1]
    return (s[:, None] * np.linalg.inv(s[:, None] * A * s[None, :]) * s[None, :])[:n_p, :n_p]


def worth_refining(sd: np.ndarray, goals: np.ndarray) -> np.ndarray:
    """Which estimates (n,) are worth a fit through the simulator: those whose reported σ
    ``sd`` (n, q) exceeds half its goal ``goals`` (q,) (a median error ≈ 0.67 σ) in any
    parameter. Where the emulator already meets the goals the simulator's seconds buy nothing."""
    return np.any(np.asarray(sd) > 0.5 * np.asarray(goals), axis=1)
