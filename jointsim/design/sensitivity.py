"""What a press's measurements depend on: their derivatives with respect to the target's and the
sensor's parameters, through the coupled model (membrane → chamber → CEM forward).

A rigid sphere of radius R comes down at ``xy`` onto the inflated membrane and is pressed to
depths d_k past first contact. The measured data are the reference frame (the untouched sensor)
and the frames of the press; their parameters θ = (x, y, d, R) of the target and the nuisances
η of the sensor:

- mechanical, by the implicit function theorem: at an equilibrium g(u; θ) = 0, so
  du/dθ = −H⁻¹ ∂g/∂θ with H the exact Hessian (one factorisation per frame, one back-solve per
  parameter: :meth:`~jointsim.mechanics.dome.MembraneModel.equilibrium_derivative`), for the
  sphere's centre (c_x, c_y, c_z), its radius and the reservoir head (ln p). The voltages depend
  on u alone (membrane → inner surface → chamber **morph** → forward), so ∂V/∂θ is the central
  difference of V along du/dθ, the membrane moved by ``probe`` at most: the morph keeps the
  tetrahedra, so the difference carries no mesh noise.
- depth past first contact: the centre's height is z = z_c(x, y, R, p) − d, with z_c the height
  at which the sphere touches the untouched membrane. On the smooth outer surface z = f(x, y)
  touched at s, ∂z_c/∂x = f_x(s), ∂z_c/∂y = f_y(s), ∂z_c/∂R = √(1 + |∇f|²) and
  ∂z_c/∂ln p = (∂u(s)/∂ln p · n)/n_z (the envelope theorem); f is a cubic fitted to the outer
  surface's nodes about s, not the faceted surface, whose touching node jumps as the sphere
  moves sideways. Hence ∂V/∂x|_d = ∂V/∂c_x + ∂V/∂c_z f_x, and so on.
- the membrane's modulus (ln μ): with every modulus scaled by s and the contact penalty with
  it (its default, 100·3μ/h), the energy is s × that of the unscaled membrane under p/s, so
  ∂V/∂ln μ = −∂V/∂ln p exactly for a membrane moulded as a cap (tests/test_design.py checks it
  against a membrane built with scaled moduli). A membrane moulded flat is inflated to the dome's
  height whatever its modulus, so there neither the modulus nor the head (the inflation sets
  it) changes a depth-controlled press: both columns are zero.
- a soft target (:class:`~jointsim.mechanics.soft_target.SoftTargetModel`): the same, with its
  Young's modulus a fifth target parameter (ln E, :data:`TARGET_MODULUS`); its energy is E × that
  of the unit modulus, so ∂g/∂ln E is its elastic gradient, and its radius scales its body about
  the centre (:meth:`~jointsim.mechanics.soft_target.SoftTargetModel.target_gradients`). H is
  then the two bodies' true tangent, the contact's sliding and turning facets included. Every
  modulus (the membrane's, the penalty with it, the target's) × s is the head ÷ s, so
  ∂V/∂ln μ = −∂V/∂ln p − ∂V/∂ln E: the target's modulus is read only against the membrane's
  and the head, as far as their priors fix them.
- electrical, by the adjoint on the solved lead fields (:mod:`jointsim.eit.parameters`):
  the saline's conductivity (ln σ), each electrode's contact impedance (ln z_l, the ground's
  included) and its centre in the base plane (x_l, y_l).

The membrane's mesh must resolve the contact. Node-to-sphere contact on a membrane whose
P2 nodes lie ~1 mm apart (64 rim vertices) makes the derivatives ripple as nodes enter the
contact, and a contact a few nodes wide gains or loses whole nodes as the sphere grows: a size
signal the mesh makes, not the sensor (results/design_study/convergence.md). A press is
therefore read through a membrane refined about its contact (:func:`contact_membrane`,
:func:`~jointsim.geometry.refine_near`): the same chamber and readout, its morpher remapped
onto the refined surface (:meth:`~jointsim.instrument.Instrument.on_membrane`).

A frame's noise is the instrument's: white, ``noise_std`` per channel per frame
(:attr:`~jointsim.instrument.Readout.noise_std`, the scene's SNR re the mean standing |V|).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from ..eit.parameters import (
    conductivity_sensitivity,
    contact_impedance_sensitivity,
    electrode_position_sensitivity,
    moved_discs,
)
from ..geometry import axis_turn, chamber_cap, refine_near
from ..instrument import Instrument
from ..mechanics.build import membrane_from_scene
from ..mechanics.dome import MembraneModel
from ..mechanics.soft_target import GENERIC_TURN
from ..mechanics.touch import touch
from ..scene import Scene

__all__ = ["TARGET", "TARGET_MODULUS", "target_names", "ELECTRODE_STEP", "CONTACT_MARGIN", "PressSensitivity", "PressMechanics", "parameter_names", "press_sensitivity", "press_mechanics", "press_electrical", "electrode_moves",
           "unrefinable", "contact_zone", "contact_membrane", "head_moves"]

TARGET = ("x", "y", "depth", "radius")  # the target's parameters, m
# a soft target's Young's modulus (ln E), after TARGET: parameter_names(soft=True)
TARGET_MODULUS = "ln_target_modulus"
# m: an electrode's move either way for its position derivative (a difference of clipped moments,
# no solve; tests/test_parameters.py); the moves made once (electrode_moves) must use the step
# press_sensitivity divides by
ELECTRODE_STEP = 1e-5


# m: how far the refined zone reaches past the sphere's geometric contact at the deepest depth:
# a node pitch of the coarse membrane, so the contact's sideways moves stay inside it
CONTACT_MARGIN = 1e-3


def unrefinable(scene: Scene) -> str:
    """Why ``scene``'s membrane cannot be refined about a contact (:func:`contact_membrane`
    refines the round cap it is moulded as), or "" where it can."""
    c = scene.chamber
    if scene.membrane.moulding != "cap" or c.base_radius_y is not None or c.surface_file is not None:
        return ("contact_levels: a membrane refined about the contact is for a round dome moulded as a cap "
                "(not membrane.moulding = \"flat\", chamber.base_radius_y_mm or chamber.surface_file)")
    return ""


def contact_zone(scene: Scene, radius: float, xy: np.ndarray, depth: float) -> tuple[np.ndarray, float]:
    """(the in-plane point (2,) m where a sphere of ``radius`` m coming down at ``xy`` first
    touches ``scene``'s moulded cap (on the line between the two spheres' centres), the radius
    m of the zone to refine about it: the sphere's geometric contact √(2Rd − d²) at ``depth``
    plus :data:`CONTACT_MARGIN`). Only for a round cap moulding: a ValueError naming the scene's
    keys otherwise."""
    why = unrefinable(scene)
    if why:
        raise ValueError(why)
    c = scene.chamber
    outer = (c.base_radius**2 + c.dome_height**2) / (2 * c.dome_height) + c.membrane_thickness
    touch_xy = np.asarray(xy, float) * outer / (outer + radius)
    d = min(float(depth), radius)
    return touch_xy, math.sqrt(2 * radius * d - d * d) + CONTACT_MARGIN


def contact_membrane(scene: Scene, radius: float, xy: np.ndarray, depth: float, levels: int,
                     modulus: float | None = None, turn: np.ndarray | None = None,
                     target_mesh_size: float | None = None, graded_target: bool = False) -> MembraneModel:
    """The membrane of ``scene`` (inflated, untouched, pressed by a sphere of ``radius`` m:
    rigid, or soft of Young's modulus ``modulus`` Pa, its mesh turned off the membrane's rings:
    :data:`~jointsim.mechanics.soft_target.GENERIC_TURN`) meshed ``levels`` times finer about where
    that sphere coming down at ``xy`` touches, out to its contact at ``depth`` m
    (:func:`contact_zone`; :func:`~jointsim.geometry.refine_near` on the scene's cap at
    [membrane] rim_vertices); ``turn`` (2, 2): that mesh turned about the axis by this rotation,
    the membrane a press at ``turn @ xy`` is read through when it is :meth:`PressMechanics.turned`;
    ``target_mesh_size`` (m): a soft sphere's cells where it touches (None: half the refined
    membrane's median edge, :class:`~jointsim.mechanics.soft_target.SoftTargetModel`'s rule);
    ``graded_target``: that sphere meshed uniformly at that size over the same zone about its
    lowest point and coarser into its body
    (:func:`~jointsim.mechanics.soft_target.graded_hemisphere_mesh`), not in layers."""
    about, zone = contact_zone(scene, radius, xy, depth)
    dome = refine_near(chamber_cap(scene.chamber, scene.membrane.rim_vertices), about, zone, levels)
    if turn is not None:
        dome = dome.turned(turn)
    rigid = replace(scene, target=replace(scene.target, kind="rigid"))
    return membrane_from_scene(rigid, target_radius=radius, dome=dome, target_modulus=modulus,
                               target_turn=GENERIC_TURN, target_mesh_size=target_mesh_size,
                               target_fine_radius=zone if graded_target and modulus is not None else None)


def parameter_names(n_electrodes: int, soft: bool = False) -> tuple[str, ...]:
    """The parameters' names, in the Jacobians' column order: the target's (:data:`TARGET`, and
    for a ``soft`` target :data:`TARGET_MODULUS`), then ln_pressure, ln_modulus (the membrane's),
    ln_conductivity, ln_z0…, then x0, y0, x1, … of the electrodes (in the layout's order, the
    ground included)."""
    n = n_electrodes
    return (target_names(soft) + ("ln_pressure", "ln_modulus", "ln_conductivity") + tuple(f"ln_z{l}" for l in range(n))
            + tuple(f"{a}{l}" for l in range(n) for a in "xy"))


def target_names(soft: bool | tuple[str, ...]) -> tuple[str, ...]:
    """The target's parameters: :data:`TARGET`, with :data:`TARGET_MODULUS` for a soft target
    (``soft`` True, or a :func:`parameter_names` tuple that holds it)."""
    soft = TARGET_MODULUS in soft if isinstance(soft, tuple) else bool(soft)
    return TARGET + ((TARGET_MODULUS,) if soft else ())


@dataclass(frozen=True, eq=False)
class PressSensitivity:
    """The derivatives of one press (target ``radius`` m at centre ``xy`` (2,) m, pressed to
    ``depths`` (K,) m): the frames' clean ``voltages`` (K, n_meas) V and the reference's
    ``v_ref`` (n_meas,); ``jacobian`` (K, n_meas, P) ∂V_k/∂p and ``jacobian_ref`` (n_meas, P)
    in :func:`parameter_names` order (per m for lengths, per unit of ln for the others); the
    contact's centre of pressure ``contact`` (K, 3) m and its in-plane derivative
    ``contact_jacobian`` (K, 2, t) with respect to the target's parameters (:func:`target_names`); ``force`` (K,) N (the
    normal force); ``noise_std`` V of one frame; ``names`` the parameters."""

    xy: np.ndarray
    radius: float
    depths: np.ndarray
    voltages: np.ndarray
    v_ref: np.ndarray
    jacobian: np.ndarray
    jacobian_ref: np.ndarray
    contact: np.ndarray
    contact_jacobian: np.ndarray
    force: np.ndarray
    noise_std: float
    names: tuple[str, ...]


def electrode_moves(inst: Instrument, step: float, offsets: np.ndarray | None = None) -> list:
    """The instrument's electrode discs, at ``offsets`` (n_el, 2) m in the base plane from the
    layout's centres where given, moved by ±``step`` (:func:`~jointsim.eit.parameters.moved_discs`),
    clipped once on the reference chamber's base (which no morph moves)."""
    layout = inst.reference.layout
    centres = layout.centres
    if offsets is not None:
        centres = centres.copy()
        centres[:, :2] += np.asarray(offsets, float).reshape(-1, 2)
    return moved_discs(inst.reference.mesh, centres, layout.radii, step, inst.readout.forward.order == 2,
                       layout.membrane, layout.membrane_patch)


def _electrical(inst: Instrument, chamber, moves: list, step: float) -> np.ndarray:
    """∂V/∂(ln σ, ln z…, x0, y0, …) (n_meas, 1 + n_el + 2 n_el) of ``chamber`` (a morph)."""
    ro = inst.readout
    fields = ro.fields(chamber, True)
    dz = contact_impedance_sensitivity(fields, ro.protocol)
    dsigma = conductivity_sensitivity(fields, ro.protocol, dz)
    dc = electrode_position_sensitivity(fields, ro.protocol, moves, step)
    return np.column_stack([dsigma, dz.T, dc.reshape(-1, ro.n_meas).T])


@dataclass(frozen=True, eq=False)
class PressMechanics:
    """The mechanical half of a press's derivatives (:func:`press_mechanics`), all the
    electrical half (:func:`press_electrical`) reads: the target's centre ``xy`` (2,) m and
    ``radius`` m, pressed to ``depths`` (K,) m; the untouched membrane's displacement
    ``u_ref`` (n, 3) and its derivative along the head ``du_ref`` (n, 3) (None for a membrane
    moulded flat, whose inflation sets the head); per depth the displacement ``u`` (K, n, 3)
    and its derivatives ``du`` (K, n, 3, q) along (c_x, c_y, c_z, R[, ln E], ln p); the
    derivatives of the first contact's height ``dzc`` (x, y, radius, ln_pressure: ∂z_c/∂·);
    the contact's centre of pressure ``contact`` (K, 3) m and its in-plane derivatives
    ``dcop`` (K, 2, t) along (c_x, c_y, c_z, R[, ln E]); the normal ``force`` (K,) N."""

    xy: np.ndarray
    radius: float
    depths: np.ndarray
    soft: bool
    u_ref: np.ndarray
    du_ref: np.ndarray | None
    u: np.ndarray
    du: np.ndarray
    dzc: dict[str, float]
    contact: np.ndarray
    dcop: np.ndarray
    force: np.ndarray

    def turned(self, m: np.ndarray) -> "PressMechanics":
        """The same press turned about the chamber's axis by the rotation ``m`` (2, 2): what a
        membrane whose mesh is this one's turned by ``m`` gives for the target at ``m @ xy``
        (its equilibria are this one's turned; a round cap's mechanics know no direction).
        Displacements turn node by node; a derivative along the centre's x and y becomes one
        along the turned axes (∂/∂c'_i = Σ_j m_ij ∂/∂c_j), as do the touching surface's slopes
        and the contact's in-plane derivatives."""
        m = np.asarray(m, float)
        if m.shape != (2, 2) or abs(np.linalg.det(m) - 1.0) > 1e-9 or not np.allclose(m @ m.T, np.eye(2), atol=1e-12):
            raise ValueError("turned: a rotation about the axis, (2, 2) orthogonal with determinant +1")
        r = axis_turn(m)

        def along_c(a: np.ndarray) -> np.ndarray:  # the columns along c_x, c_y (last axis) turned
            a = a.copy()
            a[..., :2] = a[..., :2] @ m.T
            return a

        slope = m @ np.array([self.dzc["x"], self.dzc["y"]])
        return replace(self, xy=m @ self.xy, u_ref=self.u_ref @ r.T,
                       du_ref=None if self.du_ref is None else self.du_ref @ r.T, u=self.u @ r.T,
                       du=along_c(np.einsum("ij,knjq->kniq", r, self.du)),
                       dzc={**self.dzc, "x": float(slope[0]), "y": float(slope[1])},
                       contact=self.contact @ r.T, dcop=along_c(np.einsum("ij,kjt->kit", m, self.dcop)))


def head_moves(scene: Scene) -> bool:
    """Whether the reservoir's head moves the scene's untouched membrane: one moulded as a cap
    (a membrane moulded flat takes its shape from the inflation, which the head sets)."""
    return scene.membrane.moulding == "cap"


def press_mechanics(model: MembraneModel, xy: np.ndarray, depths: np.ndarray, *, head: bool = True,
                    step_max: float = 0.5e-3) -> PressMechanics:
    """The mechanical half of :func:`press_sensitivity`: ``model``'s target (its radius; a soft
    one's modulus) pressed at ``xy`` (2,) m through ``depths`` (K,) m, increasing, past first
    contact, in load steps of ``step_max`` m at most, and the equilibria's derivatives by the
    implicit function theorem (module docstring). ``head``: the reservoir's head moves the
    untouched membrane (:func:`head_moves`). ``model`` must be untouched; it is left so."""
    xy = np.asarray(xy, float)
    depths = np.asarray(depths, float)
    soft = TARGET_MODULUS in model.TARGET_PARAMETERS
    t = len(target_names(soft))
    untouched = model.get_state()
    contact = model.contact

    def head_load(u: np.ndarray) -> np.ndarray:
        # E_p = −p V(u): ∂g/∂ln p = p ∂g/∂p = −p ∇V
        return -model.pressure.pressure * model.pressure.volume_gradient(u).ravel()

    rtol = model.force_rtol
    model.force_rtol = 0.0
    try:
        # the untouched sensor: its head derivative, where the sphere touches, and the surface there
        node, slope = touch(model, xy)
        nz = 1.0 / math.sqrt(1.0 + slope @ slope)
        normal = np.array([-slope[0], -slope[1], 1.0]) * nz
        dzc = {"x": float(slope[0]), "y": float(slope[1]), "radius": 1.0 / nz, "ln_pressure": 0.0}
        u_ref = model.u.copy()
        du_ref = None
        if head:
            du_ref = model.equilibrium_derivative(head_load(model.u)[:, None])[..., 0]
            dzc["ln_pressure"] = float(du_ref[contact.nodes[node]] @ normal) / nz
            model.set_state(untouched)
        z0 = model.first_contact_height(xy)
        K = len(depths)
        u = np.zeros((K,) + u_ref.shape)
        du = np.zeros((K,) + u_ref.shape + (t + 1,))
        cop = np.zeros((K, 3))
        dcop = np.zeros((K, 2, t))
        force = np.zeros(K)
        done = 0.0
        for k, d in enumerate(depths):
            n = max(1, math.ceil((d - done) / step_max - 1e-9))
            for s in range(1, n + 1):
                st = model.press(np.array([xy[0], xy[1], z0 - (done + (d - done) * s / n)]))
            done = d
            u[k] = model.u
            cop[k], force[k] = st.contact_centre, -st.force[2]
            # the equilibrium's derivatives: the sphere's centre and radius (at fixed z), a soft
            # one's modulus, the head
            dg = np.column_stack([model.target_gradients(u[k]), head_load(u[k])])
            du[k] = model.equilibrium_derivative(dg)
            # the contact's centre of pressure moves with u and with the sphere (centre, radius)
            dcop[k] = np.column_stack([_cop_along(contact, u[k], du[k][..., j], j) for j in range(t)])
    finally:
        model.force_rtol = rtol
        model.set_state(untouched)
    return PressMechanics(xy, contact.radius, depths, soft, u_ref, du_ref, u, du, dzc, cop, dcop, force)


def press_electrical(inst: Instrument, mech: PressMechanics, *, moves: list | None = None,
                     electrode_step: float = ELECTRODE_STEP, probe: float = 10e-6) -> PressSensitivity:
    """The electrical half of :func:`press_sensitivity`: the press ``mech`` measured by ``inst``
    (the instrument of the same scene on the membrane ``mech`` was solved on, nominal readout):
    the frames' voltages, ∂V/∂θ for each mechanical parameter as the central difference of V
    along du/dθ (the membrane moved by ``probe`` m at most), the electrical nuisances by the
    adjoint, and the target's columns taken to a fixed depth past first contact."""
    if moves is None:
        moves = electrode_moves(inst, electrode_step)
    ro = inst.readout
    names = parameter_names(len(inst.reference.layout.radii), mech.soft)
    t = len(target_names(mech.soft))
    head, modulus = names.index("ln_pressure"), names.index("ln_modulus")
    K, M, P = len(mech.depths), ro.n_meas, len(names)
    cap = mech.du_ref is not None

    def voltages(u: np.ndarray) -> np.ndarray:
        chamber, _ = inst.morpher.morph(inst.dome(u))
        return ro.voltages(chamber, True)

    def along(u: np.ndarray, du: np.ndarray) -> np.ndarray:
        """∂V/∂θ for du/dθ: the central difference of V along du."""
        eps = probe / max(float(np.abs(du).max()), 1e-300)
        return (voltages(u + eps * du) - voltages(u - eps * du)) / (2 * eps)

    J = np.zeros((K, M, P))
    J_ref = np.zeros((M, P))
    if cap:
        J_ref[:, head] = along(mech.u_ref, mech.du_ref)
    J_ref[:, head + 2:] = _electrical(inst, inst.reference, moves, electrode_step)
    V = np.zeros((K, M))
    cj = np.zeros((K, 2, t))
    for k in range(K):
        chamber, _ = inst.morpher.morph(inst.dome(mech.u[k]))
        V[k] = ro.voltages(chamber, True)
        J[k, :, head + 2:] = _electrical(inst, chamber, moves, electrode_step)
        dv = [along(mech.u[k], mech.du[k][..., j]) for j in range(mech.du.shape[-1])]  # c_x, c_y, c_z, R, [ln E,] ln p
        dcop = list(mech.dcop[k].T)
        J[k, :, :4] = np.column_stack(_at_fixed_depth(dv, mech.dzc))
        cj[k, :, :4] = np.column_stack(_at_fixed_depth(dcop, mech.dzc))
        if mech.soft:  # the modulus does not move the first contact: the sphere is not yet strained
            J[k, :, 4], cj[k, :, 4] = dv[4], dcop[4]
        if cap:
            J[k, :, head] = dv[-1] + mech.dzc["ln_pressure"] * dv[2]
    if cap:  # every modulus scaled by s acts as the head divided by s (module docstring)
        J[:, :, modulus] = -J[:, :, head] - (J[:, :, 4] if mech.soft else 0.0)
        J_ref[:, modulus] = -J_ref[:, head]
    return PressSensitivity(mech.xy, mech.radius, mech.depths, V, ro.v_ref, J, J_ref, mech.contact, cj, mech.force,
                            ro.noise_std, names)


def press_sensitivity(inst: Instrument, model: MembraneModel, xy: np.ndarray, depths: np.ndarray, *,
                      moves: list | None = None, electrode_step: float = ELECTRODE_STEP, probe: float = 10e-6,
                      step_max: float = 0.5e-3) -> PressSensitivity:
    """The derivatives of the press of ``model``'s target (its radius; a soft one's modulus) at ``xy`` (2,) m through
    ``depths`` (K,) m, increasing, past first contact, measured by ``inst`` (the instrument of
    the same scene, nominal readout): :func:`press_mechanics`, then :func:`press_electrical`.
    ``model`` must be untouched (as built, or reset to its untouched state); it is left so.
    ``moves``: :func:`electrode_moves` at ``electrode_step`` (computed here when not given);
    ``probe``: the largest membrane displacement m of a central difference along du/dθ;
    ``step_max``: the press's load steps, m. Raises what the mechanics raise for a press they
    cannot take (:class:`~jointsim.mechanics.dome.UnreachablePose`, NewtonError)."""
    mech = press_mechanics(model, xy, depths, head=head_moves(inst.scene), step_max=step_max)
    return press_electrical(inst, mech, moves=moves, electrode_step=electrode_step, probe=probe)


def _at_fixed_depth(d: list, dzc: dict[str, float]) -> list:
    """Derivatives with respect to (c_x, c_y, c_z, R) at a fixed centre height → with respect
    to :data:`TARGET` (x, y, depth, radius) at a fixed depth: z = z_c − d, so the centre follows
    the first contact (∂z_c/∂x, ∂z_c/∂y, ∂z_c/∂R in ``dzc``) and ∂/∂depth = −∂/∂c_z."""
    return [d[0] + dzc["x"] * d[2], d[1] + dzc["y"] * d[2], -d[2], d[3] + dzc["radius"] * d[2]]


def _cop_along(contact, u: np.ndarray, du: np.ndarray, j: int, probe: float = 1e-6) -> np.ndarray:
    """∂(centre of pressure xy)/∂θ_j for θ = (c_x, c_y, c_z, R[, ln E]): u moved along ``du``
    and the sphere with it (a soft one's body scaled about its centre for R), by central
    differences."""
    centre, radius = contact.centre.copy(), contact.radius
    soft = hasattr(contact, "place")
    eps = probe / max(float(np.abs(du).max()), 1.0)
    out = []
    try:
        for sgn in (1, -1):
            dc = np.zeros(5)
            dc[j] = sgn * eps
            if soft:
                contact.place(centre + dc[:3], 1.0 + dc[3] / radius)
            else:
                contact.centre, contact.radius = centre + dc[:3], radius + dc[3]
            out.append(contact.centre_of_pressure(u + sgn * eps * du)[:2])
    finally:
        if soft:
            contact.place(centre, 1.0)
        else:
            contact.centre, contact.radius = centre, radius
    return (out[0] - out[1]) / (2 * eps)
