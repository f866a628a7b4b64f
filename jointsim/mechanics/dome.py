"""The membrane model: a moulded body under its loads, solved pose after pose.

:class:`MembraneModel` puts together the body (:func:`~.body.membrane_body`: the moulding
meshed, its bonded boundary), the energy terms on it (:func:`~.loads.membrane_terms`: strain
energy, saline pressure, the target's contact and friction) and owns the load-stepping solver:
a target move split into steps, each solved by Newton from a predictor (the tangent of the last
equilibrium, or the secant of the last two), cut back when it fails, the first contact solved
on its own, a closed chamber's pressure found as the multiplier of its volume, force control by
secant steps on the depth. Deployment by inflation is :mod:`.inflation`'s, checkpoints
:mod:`.checkpoint`'s. Each press returns a :class:`MembraneState`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..geometry import DomeSurface
from .body import membrane_body
from .checkpoint import membrane_state, restore_membrane
from .inflation import inflate
from .loads import membrane_terms
from .materials import Material
from .newton import NewtonError, NewtonSystem, minimize_energy

__all__ = ["MembraneModel", "MembraneState", "UnreachablePose", "ECOFLEX_00_50", "membrane_material"]

ECOFLEX_00_50 = Material.neo_hookean(22e3)  # DESIGN.md: μ ≈ 22 kPa, κ = 1000 μ
# re-lagging passes of the friction's normal forces per load step (tests/test_mechanics.py
# checks the sliding force against μ·N with this many)
FRICTION_PASSES = 2
# longest target move solved as one load step (m): longer moves are split evenly. A frame at
# 25 mm/s and 50 Hz moves 0.5 mm; a 2 mm press from first contact in one step does not converge
MAX_STEP = 0.75e-3
# times a step that fails is halved and retried before the failure is reported
MAX_CUTBACKS = 3
# a move that brings the target into contact is solved first to this × thickness past the
# touch, then on from there with the tangent predictor: over 15 first 0.5 mm frames on 64/2
# (3 target radii × 5 positions), 0.42× the factorisations and 0.54× the time of one step from
# the untouched state, the forces the same to 1e-5 (results/mechanics_first_contact.md)
FIRST_CONTACT = 0.01
# Newton stops when the out-of-balance force is below this fraction of the contact force at the
# last equilibrium (or below force_tol). Against a stop at force_tol alone (~1e-7 N), measured
# on the 48-rim test dome in 1 and 2 layers, 0.5 mm steps to 3 mm: force within 1e-4,
# displacement within 0.07 µm, displaced volume within 1e-4 — far below the 2 % mesh error and
# the EIT noise — for ~15 % fewer Newton iterations
FORCE_RTOL = 1e-3
# a load step's first Newton iteration is regularised (newton.minimize_energy's
# regularise_first) only where the target moves more than this × thickness: the Hessian at the
# tangent predictor of a 0.5 mm frame is indefinite, but after a smaller move it was positive
# definite (up to 0.1 × thickness, 200 µm, down or up, at 0.5 and 2 mm depth on 64/2 in a
# scratch probe; at this move on the test dome in tests/test_membrane.py), so the full Newton
# step is the better first one and its factor is the tangent the next frame predicts with: a
# hold's servo-sized moves no longer end on a shifted factor that the next frame has to replace
# by factoring the tangent (results/palpation_benchmark.md: the hold frames' mechanics 0.06 and
# 0.15 s at the dataset and paper resolutions, 0.28 and 0.56 s in the run before)
REGULARISE_MOVE = 0.05
TOUCH_CLEARANCE = 1e-12  # × target radius: ~1000 ulps of the gap, physically nothing
# a target move no longer than this × target radius is a hold: the membrane stays bit for bit
# where it was (no load step). The rig's servo, held still, keeps moving the target by
# round-off: on an on-axis press its lateral coordinates sit at 0, where a float resolves
# 1e-20 m, and the loop target → membrane's lateral force (~1e-15 N of round-off) → servo
# either decays to an exact fixed point or cycles for ever (±8.7e-20 m, every frame, with
# OpenBLAS's Haswell kernels; 0 on AVX-512), so a hold's membrane depended on the CPU. 1e-12 ×
# 7.5 mm = 7.5 fm, ~1e-8 of what Newton resolves (FORCE_RTOL × the force over the contact
# stiffness: ~1 µm for 19 mN at ~20 N/m, a 1 mm press)
HOLD_MOVE = 1e-12


class UnreachablePose(ValueError):
    """The target pose asked for cannot be simulated on this dome: the target misses it, or
    would press it beyond what it can take. A property of the pose, not a fault: a dataset
    redraws such a target, while any other error stops the run."""


@dataclass
class MembraneState:
    """One equilibrium: the deformed inner ``dome``, the contact ``force`` (3,) N the membrane
    exerts on the target, ``contact_area`` m², ``displaced_volume`` m³ (saline pushed out to
    the reservoir), ``peak_strain`` (largest principal Green–Lagrange strain), Newton
    ``iterations`` (summed over the move's steps) and the last step's ``residual``,
    ``penetration`` m (largest, at the surface nodes), the saline ``pressure`` Pa (the
    reservoir's, or the closed chamber's multiplier), the element quality ``min_jacobian``
    (smallest det F over the quadrature points; ≤ 0 would be inverted) and the
    ``contact_centre`` (3,) m, the contact's centre of pressure on the deformed outer
    surface (NaN without contact): where on the sensor the target presses, which is not
    below the target's centre off the axis (the dome slopes: the contact lies between the
    target's centre and the dome's)."""

    dome: DomeSurface
    u: np.ndarray
    force: np.ndarray
    contact_area: float
    displaced_volume: float
    peak_strain: float
    iterations: int
    residual: float
    penetration: float
    pressure: float = 0.0
    min_jacobian: float = 1.0
    contact_centre: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))


def membrane_material(membrane) -> Material:
    """The material law of a scene's [membrane] section."""
    if membrane.law == "yeoh":
        return Material.yeoh(*membrane.yeoh_c, bulk_ratio=membrane.bulk_ratio)
    return Material.neo_hookean(membrane.shear_modulus, bulk_ratio=membrane.bulk_ratio)


class _ExactContact:
    """A contact term whose Hessian is exact (its curvature uncapped): the tangent a derivative
    of the equilibrium needs, where Newton's capped one is an approximation."""

    def __init__(self, contact):
        self.contact = contact

    def evaluate(self, u: np.ndarray, hessian: bool):
        return self.contact.evaluate(u, hessian, exact=True)


class MembraneModel:
    """The membrane of a dome with its loads; call :meth:`press` for target poses in order
    (each solve warm-starts from the previous one). ``element`` "wedge15" (the default) or
    "p2_tet"; ``layers`` through the thickness, by default the element's (scene.MEMBRANE_LAYERS)."""

    TANGENT_PREDICTOR = True  # see _tangent_guess; a subclass with other unknowns turns it off
    # the target's parameters that :meth:`target_gradients` differentiates the energy's gradient by
    TARGET_PARAMETERS: tuple[str, ...] = ("c_x", "c_y", "c_z", "radius")

    def __init__(
        self,
        dome: DomeSurface,
        thickness: float = 2e-3,
        material: Material = ECOFLEX_00_50,
        layers: int | None = None,
        pressure: float = 0.0,
        target_radius: float = 7.5e-3,
        penalty: float | None = None,
        force_tol: float | None = None,
        friction: float = 0.0,
        closed: bool = False,
        volumetric: str = "pointwise",
        isoparametric: bool = True,
        device: str = "cpu",
        inflate_to: float | None = None,
        inflate_from: np.ndarray | None = None,
        element: str = "wedge15",
    ):
        # converged when the out-of-balance nodal force is below force_tol (N): by default
        # 1e-6·μ·t², a millionth of the force that strains a membrane-thick cube by one
        self.force_tol = force_tol if force_tol is not None else 1e-6 * material.mu * thickness**2
        self._step_tol = self.force_tol  # the current step's (see FORCE_RTOL)
        # the step's tolerance relative to the contact force (FORCE_RTOL); 0 solves every step to
        # force_tol, as derivatives by differences of equilibria need (jointsim.design)
        self.force_rtol = FORCE_RTOL
        self.body = body = membrane_body(dome, thickness, layers, element, isoparametric)
        self.loads = loads = membrane_terms(body, material, pressure=pressure, target_radius=target_radius, penalty=penalty,
                                            friction=friction, volumetric=volumetric, device=device)
        self.element = element
        self.dome = dome
        self.thickness = thickness
        self.mesh, self.n_surface = body.mesh, body.n_surface
        self.outer_faces, self.inner_tris = body.outer_faces, body.inner_tris
        self.elastic, self.pressure, self.contact, self.friction = loads.elastic, loads.pressure, loads.contact, loads.friction
        X = self.mesh.nodes
        self.closed = bool(closed)
        self.fixed = body.fixed.copy()
        self.u = np.zeros_like(X)
        indptr, indices, _ = self.mesh.sparsity
        self.system = NewtonSystem(indptr, indices, ~self.fixed.ravel())
        if inflate_to is not None:
            # deployed by inflation (a membrane moulded flat): the pressure is what it takes
            inflate(self, float(inflate_to), material.mu, body.rim_radius, inflate_from)
        elif pressure != 0.0:
            # the reservoir head inflates the stress-free dome before any contact, to force_tol
            # as every equilibrium (a relative 1e-9 of the head's load, as before, lies at the
            # round-off of the gradient: 1–3 iterations spent there), from an earlier model's
            # rest state where given
            start = self.u if inflate_from is None else self._rest_start(inflate_from)
            self.u = minimize_energy([self.elastic, self.pressure], start, self.fixed, rtol=0.0, atol=self.force_tol, system=self.system).u
        # displaced volume is counted from the pressurised, untouched dome; a closed chamber is
        # sealed in that state and keeps this volume
        self.V0 = self.pressure.volume(self.u)
        self.history: list[tuple[np.ndarray, np.ndarray]] = []
        self._iterations = 0  # Newton iterations of the last press
        self._step_its = 0  # of the step being solved (_tally)
        self._moved = False  # whether the target moves in the step being solved
        self.compliance: float | None = None  # dV/dp of the chamber, for the closed-chamber secant

    def _rest_start(self, earlier: np.ndarray) -> np.ndarray:
        """Where the head's solve starts from ``earlier``, the rest displacement of a model of
        this mesh under another head or moduli (n_nodes, 3): scaled by the α that best balances
        this model's loads, α = argmin ‖α·g_elastic(u) − f‖ (f the head's load), which is the
        ratio of the loads over the moduli where the response is linear (a head lifts the cap
        by ~0.1 mm of its 2 mm thickness: an earlier model at ×1/s the moduli gives α ≈ 1/s). A
        dataset draws the membrane's moduli per group: started there, the rest state takes 2–3
        Newton iterations instead of 3–4 from the moulded shape (5–8 to the old 1e-9 tolerance)."""
        earlier = np.asarray(earlier, float)
        if earlier.shape != self.u.shape or not np.isfinite(earlier).all():
            raise ValueError(f"inflate_from: must be a finite displacement of shape {self.u.shape}, got {earlier.shape}")
        u = np.where(self.fixed, 0.0, earlier)
        free = ~self.fixed.ravel()
        k = self.elastic.evaluate(u, False)[1][free]
        f = -self.pressure.evaluate(u, False)[1][free]
        if np.linalg.norm(k - f) <= self.force_tol:
            return u  # already at rest here (the same scene's): kept bit for bit, as frames at no indentation need
        kk = float(k @ k)
        alpha = float(k @ f) / kk if kk > 0 else 0.0
        return u * alpha if alpha > 0 else np.zeros_like(u)

    @property
    def terms(self) -> list:
        return self.loads.all

    def get_state(self) -> dict[str, np.ndarray]:
        """Everything the next :meth:`press` depends on (:func:`~.checkpoint.membrane_state`)."""
        return membrane_state(self)

    def set_state(self, state: dict[str, np.ndarray]) -> None:
        """Restore a :meth:`get_state` (:func:`~.checkpoint.restore_membrane`)."""
        restore_membrane(self, state)

    def first_contact(self, xy: np.ndarray) -> tuple[float, int]:
        """(centre height, node) of the target coming down at ``xy`` when it touches the outer
        surface of the current (deformed) membrane: the height at which it touches, and the
        index into the contact's nodes of the node it touches first. Raises UnreachablePose
        where it misses the dome."""
        x = self.contact.X[self.contact.nodes] + self.u[self.contact.nodes]
        R = self.contact.radius
        d2 = ((x[:, :2] - np.asarray(xy)) ** 2).sum(axis=1)
        near = d2 < R * R
        if not near.any():
            reach = np.hypot(x[:, 0], x[:, 1]).max() + R  # from the axis, in any direction: the rim is a circle
            raise UnreachablePose(f"target at xy = {np.asarray(xy) * 1e3} mm misses the dome: a target of radius "
                                  f"{R * 1e3:.4g} mm must be within {reach * 1e3:.4g} mm of the axis")
        height = x[near, 2] + np.sqrt(R * R - d2[near])
        i = int(np.argmax(height))
        return float(height[i]), int(np.flatnonzero(near)[i])

    def first_contact_height(self, xy: np.ndarray) -> float:
        """:meth:`first_contact`'s height raised by ``TOUCH_CLEARANCE``·R: the touching node's
        gap is R − |x − c| up to round-off, and a touch must give exactly zero force, not a
        force of either sign from the last bits."""
        return self.first_contact(xy)[0] + TOUCH_CLEARANCE * self.contact.radius

    def press(self, centre: np.ndarray, substeps: int = 1) -> MembraneState:
        """Move the target centre to ``centre`` (3,) m in ``substeps`` straight-line steps (more
        when a step would exceed ``MAX_STEP``) and solve for equilibrium. A step whose Newton
        iteration fails is halved and retried, up to ``MAX_CUTBACKS`` times; then NewtonError
        (with the step) is raised and the model is left at the last equilibrium reached. A move
        of at most ``HOLD_MOVE`` × radius leaves the model as it is (a hold)."""
        centre = np.asarray(centre, float)
        lowest = centre[2] - self.contact.radius
        if lowest < self.thickness:
            raise UnreachablePose(
                f"target centre z = {centre[2] * 1e3:.3g} mm: the sphere's lowest point would be "
                f"{lowest * 1e3:.3g} mm above the base, less than the membrane thickness "
                f"{self.thickness * 1e3:.3g} mm; indentation beyond what the dome can take"
            )
        start = self.contact.centre.copy()
        if np.linalg.norm(centre - start) <= HOLD_MOVE * self.contact.radius:
            return self.state()
        if np.linalg.norm(start) > 1e2:  # first call: start from first contact above
            start = np.array([centre[0], centre[1], self.first_contact_height(centre[:2])])
        n = max(int(substeps), int(np.ceil(np.linalg.norm(centre - start) / MAX_STEP)))
        res = None
        self._iterations = 0  # over every step and sub-step of this move (_advance)
        for s in range(1, n + 1):
            frm = start + (centre - start) * (s - 1) / n
            new = start + (centre - start) * s / n
            try:
                touch = self._touch_step(frm, new)
                if touch is not None:
                    self._advance(frm, touch, MAX_CUTBACKS)
                    frm = touch
                res = self._advance(frm, new, MAX_CUTBACKS)
            except NewtonError as e:
                raise NewtonError(f"target step {s}/{n} to centre {new * 1e3} mm: {e}") from e
        return self.state(self._iterations, res.residual)

    def _touch_step(self, frm: np.ndarray, to: np.ndarray) -> np.ndarray | None:
        """Where the move ``frm`` → ``to`` of a target that touches nothing first reaches
        ``FIRST_CONTACT`` × thickness into the membrane (at most), when the move goes on beyond
        that by more than as much again: the first contact is solved there, and the rest of the
        move from it with the tangent predictor, which a move from no contact has not. None
        otherwise, and where no step has that predictor (friction, or a model with other unknowns)."""
        if not self.TANGENT_PREDICTOR or self.friction is not None:
            return None
        x = self.contact.X[self.contact.nodes] + self.u[self.contact.nodes]
        gap = float(np.min(np.linalg.norm(x - frm, axis=1))) - self.contact.radius
        length = float(np.linalg.norm(to - frm))
        if gap < 0:
            return None
        # the target must travel at least the gap before any node is inside it
        depth = FIRST_CONTACT * self.thickness
        s = gap + depth
        return frm + (to - frm) * (s / length) if s + depth < length else None

    def _advance(self, frm: np.ndarray, to: np.ndarray, cutbacks: int):
        """Equilibrium with the target moved from ``frm`` to ``to``, committed to the model;
        on failure the model is restored and the move taken in two halves."""
        saved = self.get_state()
        try:
            res = self._solve_step(to)
        except NewtonError as e:
            self.set_state(saved)
            if not cutbacks:
                raise
            mid = 0.5 * (frm + to)
            try:
                self._advance(frm, mid, cutbacks - 1)
                return self._advance(mid, to, cutbacks - 1)
            except NewtonError:
                if cutbacks < MAX_CUTBACKS:
                    raise
                raise NewtonError(f"{e} (nor with the step halved up to {MAX_CUTBACKS} times)") from e
        self._iterations += res.iterations
        if self.friction is not None:
            self.friction.commit(res.u)
        self.history.append((to.copy(), res.u.copy()))
        self.history = self.history[-2:]
        self.u = res.u
        return res

    def _solve_step(self, centre: np.ndarray):
        """Equilibrium with the target at ``centre``: friction re-lagged ``FRICTION_PASSES``
        times, and in a closed chamber the pressure adjusted until the volume is the sealed one."""
        # before the first press the target is parked far away: the step then starts at centre
        old_centre = self.contact.centre.copy() if np.linalg.norm(self.contact.centre) < 1e2 else centre
        u_start = self.u
        if self.friction is not None:
            self.friction.lag(u_start, old_centre)
        guess = self._tangent_guess(old_centre, centre) if self.TANGENT_PREDICTOR else None
        self._step_tol = max(self.force_tol, self.force_rtol * float(np.linalg.norm(self.contact.force(self.u))))
        self.contact.centre = centre
        self._step_its = 0  # over the step's Newton solves: friction passes, pressure updates (_tally)
        self._moved = bool(np.any(centre != old_centre))
        large = float(np.linalg.norm(centre - old_centre)) > REGULARISE_MOVE * self.thickness
        res = self._newton(self._extrapolate(centre) if guess is None else guess, predicted=guess is not None and large)
        for _ in range(FRICTION_PASSES if self.friction is not None else 0):
            self.friction.lag(u_start, old_centre, u_normal=res.u)
            res = self._newton(res.u)
        if self.closed:
            res = self._hold_volume(res)
        res.iterations = self._step_its
        return res

    def _tally(self, res):
        """``res``, its iterations counted into the step's (see :meth:`_solve_step`)."""
        self._step_its += res.iterations
        return res

    def factor_context(self) -> np.ndarray:
        """What the Hessian depends on besides the displacement: target centre and saline pressure."""
        return np.append(self.contact.centre, self.pressure.pressure)

    def _newton(self, guess: np.ndarray, predicted: bool = False, atol: float | None = None):
        atol = self._step_tol if atol is None else atol
        self.system.context = self.factor_context()
        try:
            return self._tally(minimize_energy(self.terms, guess, self.fixed, rtol=0.0, atol=atol, system=self.system, regularise_first=predicted))
        except NewtonError:
            # the extrapolation may have overshot: start from the last equilibrium
            return self._tally(minimize_energy(self.terms, self.u, self.fixed, rtol=0.0, atol=atol, system=self.system))

    def _hold_volume(self, res, rtol: float = 1e-6, max_iter: int = 20):
        """Closed chamber: the saline pressure p is the multiplier of the constraint V = V0, found
        by secant steps on p (V decreases monotonically with −p; dV/dp starts from a probe)."""
        p0, V = self.pressure.pressure, self.pressure.volume(res.u)
        if self.compliance is None:
            self.pressure.pressure = p0 + 1.0  # 1 Pa probe of the chamber compliance
            probe = self._newton(res.u)
            self.compliance = max((self.pressure.volume(probe.u) - V) / 1.0, 1e-300)
            self.pressure.pressure = p0
        # a pressure change Δp adds Δp·∂V/∂u to the residual; below the step's force tolerance
        # Newton would not move, so the volume could not be resolved to rtol·V0: solve to a tenth
        # of the residual of the pressure change that moves the volume by that much
        free = ~self.fixed.ravel()
        dV = np.linalg.norm(self.pressure.volume_gradient(res.u)[free])
        atol = min(self._step_tol, 0.1 * rtol * self.V0 / self.compliance * dV)
        for _ in range(max_iter):
            if abs(V - self.V0) <= rtol * self.V0:
                return res
            p_prev, V_prev = self.pressure.pressure, V
            self.pressure.pressure = p_prev + (self.V0 - V) / self.compliance
            res = self._newton(res.u, atol=atol)
            V = self.pressure.volume(res.u)
            if V != V_prev:
                self.compliance = max((V - V_prev) / (self.pressure.pressure - p_prev), 1e-300)
        raise NewtonError(f"closed chamber: volume {V * 1e9:.6g} mm³ after {max_iter} pressure updates, sealed {self.V0 * 1e9:.6g} mm³")

    def equilibrate(self, pressure: float | None = None) -> MembraneState:
        """Equilibrium where the target stands with the saline at ``pressure`` Pa (default: as
        it is), to ``force_tol``: a load changed in place (a reservoir head raised) without a
        target move. Committed to the model."""
        if pressure is not None:
            self.pressure.pressure = float(pressure)
        self._step_tol = self.force_tol
        self._step_its = 0
        res = self._newton(self.u)
        self.u = res.u
        self.history = []  # the predictors' equilibria were under the old load
        return self.state(res.iterations, res.residual)

    def target_gradients(self, u: np.ndarray) -> np.ndarray:
        """∂g/∂θ (3n, len(TARGET_PARAMETERS)) at ``u`` for the target's parameters θ: the rigid
        sphere's centre and radius (:meth:`~.contact.SphereContact.parameter_gradients`)."""
        return self.contact.parameter_gradients(u)

    def equilibrium_derivative(self, dg: np.ndarray) -> np.ndarray:
        """du/dθ (n, 3, k) of the equilibrium the model stands at, for loads that change with
        parameters θ by ``dg`` = ∂g/∂θ (3n, k) (the energy gradient's derivative, the nodes
        held): by the implicit function theorem g(u(θ), θ) = 0 gives du/dθ = −H⁻¹ ∂g/∂θ on the
        free components, H the exact Hessian (the contact's curvature uncapped); 0 on the fixed
        ones. One factorisation. Raises NewtonError where H is not positive definite (no
        stable equilibrium to differentiate). Frictionless, open chamber only: friction's
        stick and a closed chamber's volume constraint are not differentiated."""
        if self.friction is not None or self.closed:
            raise ValueError("equilibrium_derivative: only a frictionless membrane in an open chamber")
        dg = np.asarray(dg, float).reshape(self.u.size, -1)
        exact = _ExactContact(self.contact)
        terms = [exact if t is self.contact else t for t in self.terms]
        self.system.context = self.factor_context()
        self.system.factor_tangent(terms, self.u)
        if not self.system.tangent_ready:
            raise NewtonError("equilibrium_derivative: the Hessian is not positive definite at this equilibrium")
        free = ~self.fixed.ravel()
        du = np.zeros_like(dg)
        du[free] = self.system.solve_tangent(-dg[free])
        return du.reshape(self.u.shape + (dg.shape[1],))

    def press_to_force(self, xy: np.ndarray, force: float, rtol: float = 1e-3, max_iter: int = 30) -> MembraneState:
        """Force control: lower the target at ``xy`` until the contact force along z equals
        ``force`` (N) within ``rtol``, by secant steps on the depth (the force grows
        monotonically with depth). The depth reached is ``first contact − centre z``."""
        if force <= 0:
            raise ValueError(f"force = {force}: must be > 0 N")
        xy = np.asarray(xy, float)
        top = self.first_contact_height(xy) if np.linalg.norm(self.contact.centre) > 1e2 else None
        z0 = self.contact.centre[2] if top is None else top
        f0 = 0.0 if top is not None else float(self.contact.force(self.u)[2])
        z1 = z0 - 0.25 * self.thickness  # a first guess: a fraction of the membrane thickness
        st = self.press(np.array([xy[0], xy[1], z1]))
        f1 = float(st.force[2])
        for _ in range(max_iter):
            if abs(f1 - force) <= rtol * force:
                return st
            slope = (f1 - f0) / (z1 - z0) if z1 != z0 else -1.0
            # the force rises as z falls: slope < 0; guard against flat or wrong-signed secants
            dz = (force - f1) / slope if slope < 0 else -0.25 * self.thickness
            dz = float(np.clip(dz, -0.5 * self.thickness, 0.5 * self.thickness))
            z0, f0 = z1, f1
            z1 = z1 + dz
            st = self.press(np.array([xy[0], xy[1], z1]))
            f1 = float(st.force[2])
        raise NewtonError(f"force control: {f1:.4g} N after {max_iter} depth updates, commanded {force:.4g} N")

    def _tangent_guess(self, old_centre: np.ndarray, centre: np.ndarray) -> np.ndarray | None:
        """The first-order response of the last equilibrium to the target moving from
        ``old_centre`` to ``centre``: K du = −∂g/∂c · dc with the factor of the equilibrium's
        tangent K still held by the solver (one solve, no factorisation). None when that factor
        is not at hand or the guess inverts an element. Better than the secant once the contact
        zone grows (measured on the 64-rim membrane, 0.5 mm steps to 3 mm: 4–9 Newton
        iterations per step against 5–8, 41 factorisations per press against 47)."""
        dc = np.asarray(centre, float) - old_centre
        if not dc.any():
            return None
        # with friction the tangent is the stuck nodes' (stiff) one: right for a move below the
        # slip ε (a servo's jitter), wrong for a press step, whose nodes mostly slip (0.5 mm
        # steps on the palpation's 64/2 press: 24–29 Newton iterations against 8–10 without it)
        if self.friction is not None and np.linalg.norm(dc) > self.friction.eps:
            return None
        rhs = self.contact.centre_sensitivity(self.u, dc)
        if self.friction is not None:  # lagged at this step's start (_solve_step)
            rhs += self.friction.centre_sensitivity(self.u, dc)
        if not rhs.any():
            return None
        if not self.system.tangent_ready:
            # the last step ended on a regularised factor (a one-iteration step, as at the start
            # of a hold). Without the tangent, a move too small to need an iteration (a servo's
            # jitter, ~1e-12 m) would leave the membrane where it was, and the force would answer
            # with the penalty's stiffness (~5e4 N/m on the paper's press): the palpation rig's
            # explicit loop then rings by ×2.4 per frame until Newton steps in (a ±0.3 % force
            # oscillation in a hold). Factored once, it serves every later frame of the hold
            self.system.context = self.factor_context()  # the last equilibrium's: the centre has not moved yet
            self.system.factor_tangent(self.terms, self.u)
            if not self.system.tangent_ready:
                return None
        free = self.system.free
        du = np.zeros(self.u.size)
        du[free] = self.system.solve_tangent(rhs[free])
        guess = self.u + du.reshape(self.u.shape)
        return guess if self.elastic.evaluate(guess, False)[3] else None

    def _extrapolate(self, centre: np.ndarray) -> np.ndarray:
        """Initial guess for the target at ``centre``: the last equilibrium moved along the
        secant of the last two (the response to a small target motion is nearly linear)."""
        if len(self.history) < 2:
            return self.u
        (c0, u0), (c1, u1) = self.history
        step = np.linalg.norm(c1 - c0)
        if step == 0:
            return self.u
        t = float(np.dot(centre - c1, c1 - c0) / step**2)
        guess = u1 + t * (u1 - u0)
        return guess if self.elastic.evaluate(guess, False)[3] else self.u

    def state(self, iterations: int = 0, residual: float = 0.0) -> MembraneState:
        u = self.u
        n = self.n_surface
        dome = DomeSurface(self.dome.vertices + u[:n], self.dome.faces, self.dome.rim)
        s = self.elastic.kernel(u, hessian=False)
        return MembraneState(
            dome=dome,
            u=u.copy(),
            force=self.contact.force(u) + (self.friction.force(u) if self.friction is not None else 0.0),
            contact_area=self.contact.contact_area(u),
            displaced_volume=self.V0 - self.pressure.volume(u),
            peak_strain=self.mesh.peak_green_strain(u),
            iterations=iterations,
            residual=residual,
            penetration=self.contact.penetration(u),
            pressure=self.pressure.pressure,
            min_jacobian=float(s.min_det.min()),
            contact_centre=self.contact.centre_of_pressure(u),
        )
