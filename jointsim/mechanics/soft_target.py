"""Soft (hyperelastic) spherical targets: a neo-Hookean sphere of radius R and Young's modulus
E pressed onto the dome membrane, both bodies solved together in one Newton system.

Only the sphere's lower hemisphere is meshed, as a shell about a rigid core, in P2 tetrahedra.
Two meshes: layers (:func:`hemisphere_mesh`: an isotropic cap graded from ``mesh_size`` at the
lowest point, where it touches, copied onto concentric spheres whose spacing grows by
``growth``; the default, what every dataset presses with), or graded by gmsh
(:func:`graded_hemisphere_mesh`: ``mesh_size`` uniform over a given patch about the lowest point,
coarser along the surface and into the body: a 15 mm sphere's 6 mm contact zone at 0.25 mm in
29 k nodes, where layers fine enough at the zone's edge would need ~600 k). The cut face (the
equatorial disc) is bonded to the stage: it moves rigidly with the prescribed centre. The
target's unknowns are its displacements in a frame that moves with the centre, so the bonded
face's are zero and a new pose only moves the frame.

Material (small-strain Lamé parameters of the compressible neo-Hookean law in materials.py):
μ = E / (2(1 + ν)), κ = E / (3(1 − 2ν)). Contact between the membrane's outer surface (slave
nodes) and the sphere's surface (master triangles): :mod:`.surface_contact`, with the rigid
case's penalty stiffness. The coupled Hessian lies on the union of both meshes' P2 patterns
and the contact candidates' couplings; the solver's symbolic analysis is redone only when the
candidates leave that pattern (:class:`CoupledTerms`)."""

from __future__ import annotations

import math

import numpy as np
import scipy.sparse as sp

from ..geometry import DomeSurface
from ..mesh.tetmesh import TetMesh
from .contact import nodal_areas
from .dome import ECOFLEX_00_50, MembraneModel, MembraneState
from .fem import ElasticTerm, P2Mesh
from .materials import Material
from .newton import NewtonError, NewtonSystem, csr_rows, find_keys, minimize_energy
from .pressure import linear_subtriangles
from .prisms import split_prisms
from .surface_contact import SurfaceContact

__all__ = ["GENERIC_TURN", "soft_material", "hemisphere_mesh", "graded_hemisphere_mesh", "SoftSphere", "CoupledTerms", "SoftTargetModel", "SYLGARD_184", "press_on_rigid_flat"]


def soft_material(youngs_modulus: float, poisson_ratio: float = 0.49) -> Material:
    """Neo-Hookean material with small-strain Young's modulus ``youngs_modulus`` (Pa) and
    Poisson ratio ``poisson_ratio`` (in [0, 0.5))."""
    if not (np.isfinite(youngs_modulus) and youngs_modulus > 0):
        raise ValueError(f"target youngs_modulus = {youngs_modulus}: must be > 0 Pa")
    if not (np.isfinite(poisson_ratio) and 0 <= poisson_ratio < 0.5):
        raise ValueError(f"target poisson_ratio = {poisson_ratio}: must be in [0, 0.5) (0.5 is incompressible: use 0.49-0.499)")
    mu = youngs_modulus / (2 * (1 + poisson_ratio))
    return Material.neo_hookean(mu, bulk_ratio=2 * (1 + poisson_ratio) / (3 * (1 - 2 * poisson_ratio)))


SYLGARD_184 = soft_material(1.5e6)  # DESIGN.md: E ~ 0.6-3 MPa


# rad: a turn of the target's mesh about its axis that puts its rings off every ring of an
# isotropic cap (whose vertices sit at rational fractions of a turn): pressed on the axis, the two
# structured meshes otherwise meet with slaves on facet edges by symmetry, where the contact's
# tangent is not the response of a finite move (tests/test_soft_target.py)
GENERIC_TURN = 2 * math.pi * (math.sqrt(2) - 1) / 16


def _check_shell(radius: float, mesh_size: float, core: float) -> None:
    """The arguments both hemisphere meshes share, each refused in one line."""
    if radius <= 0:
        raise ValueError(f"radius = {radius}: must be > 0 m")
    if not 0 < mesh_size <= radius / 4:
        raise ValueError(f"mesh_size = {mesh_size}: must be in (0, radius / 4 = {radius / 4:.3g}] m")
    if not 0 < core < 1:
        raise ValueError(f"core = {core}: must be in (0, 1)")


def _turned(v: np.ndarray, turn: float) -> np.ndarray:
    """Points ``v`` (n, 3) turned by ``turn`` rad about the vertical axis."""
    c, s = math.cos(turn), math.sin(turn)
    return v @ np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])


def hemisphere_mesh(radius: float, mesh_size: float, growth: float = 1.35, core: float = 0.1,
                    turn: float = 0.0) -> tuple[TetMesh, int]:
    """Linear tetrahedra of the half shell core·R ≤ ‖x‖ ≤ R, z ≤ 0, centred at the origin:
    the lower hemisphere triangulated as an isotropic cap graded from ``mesh_size`` (m) at the
    lowest point (0, 0, −R) to ≈ 8× that (at most R/2) at the equator, copied onto concentric spheres whose
    spacing starts at ``mesh_size`` below the surface and grows by ``growth`` per layer (at
    most a third of the radius), and
    the prisms between consecutive copies split into tetrahedra (as the membrane's).
    Returns the mesh and n, the vertices per sphere (layer l's copy of vertex i is l·n + i;
    layer 0 is the outer surface). ``turn`` (rad): the mesh turned about the vertical axis
    (:data:`GENERIC_TURN`: off every ring of an isotropic cap's)."""
    from ..geometry import isotropic_cap

    _check_shell(radius, mesh_size, core)
    if not 1 <= growth <= 3:
        raise ValueError(f"growth = {growth}: must be in [1, 3]")
    rim_edge = min(8 * mesh_size, radius / 2)
    n_rim = max(16, 16 * int(round(2 * np.pi * radius / (16 * rim_edge))))
    cap = isotropic_cap(radius, radius, n_rim, apex_edge=mesh_size)
    v = np.asarray(cap.vertices, float) * np.array([1.0, 1.0, -1.0])  # apex down, centre at 0
    if turn:
        v = _turned(v, turn)
    v *= radius / np.linalg.norm(v, axis=1, keepdims=True)  # exactly on the sphere
    f = np.asarray(cap.faces)
    r, t = [radius], mesh_size
    while r[-1] - min(t, r[-1] / 3) > core * radius + 0.5 * min(t, r[-1] / 3):
        r.append(r[-1] - min(t, r[-1] / 3))  # each sphere ≥ 2/3 of the last: no tapered slivers
        t *= growth
    r.append(core * radius)
    n = len(v)
    nodes = np.vstack([v * (rl / radius) for rl in r])
    # split_prisms wants the lower-index triangle first: layer l (outer) before l + 1
    tets = np.vstack([split_prisms(l * n + f, (l + 1) * n + f) for l in range(len(r) - 1)])
    return TetMesh(nodes, tets).oriented(), n


# the graded hemisphere's cells grow by these per unit distance beyond its fine patch, along the
# surface and into the body: a contact patch of radius a strains the body to a depth of about a,
# which cells of a/5-a/3 there still resolve in P2 (h + 0.35 a/2 for a of 3-5 mm)
GRADED_ALONG, GRADED_INTO = 0.25, 0.35


def graded_hemisphere_mesh(radius: float, mesh_size: float, fine_radius: float, core: float = 0.1,
                           turn: float = 0.0) -> tuple[TetMesh, np.ndarray]:
    """Linear tetrahedra of the half shell core·R ≤ ‖x‖ ≤ R, z ≤ 0, centred at the origin,
    meshed by gmsh (:mod:`jointsim.mesh.gmsh_session`: the same mesh on every machine) with
    cells of ``mesh_size`` (m) on the sphere within ``fine_radius`` (m, along the surface) of
    the lowest point (0, 0, −R), growing by :data:`GRADED_ALONG` per unit distance along the
    surface beyond it and :data:`GRADED_INTO` into the body, to at most R/3. Unlike
    :func:`hemisphere_mesh`, whose cells grow from the lowest point on and whose every layer
    repeats the surface's triangles, the patch is uniform and the cells coarsen with depth, so a
    patch resolved uniformly costs ~ (patch / mesh_size)² cells, not that times the layers.
    Returns the mesh and which of its nodes lie on the outer sphere. ``turn`` (rad): the mesh
    turned about the vertical axis."""
    from ..mesh.gmsh_session import compact, gmsh_session, size_field

    _check_shell(radius, mesh_size, core)
    if not 0 <= fine_radius <= np.pi * radius / 2:
        raise ValueError(f"fine_radius = {fine_radius}: must be in [0, πR/2 = {np.pi * radius / 2:.3g}] m")
    R, h, fine = float(radius), float(mesh_size), float(fine_radius)
    r = "Sqrt(x^2+y^2+z^2)"
    along = f"{R:.17g}*Acos(Min(1,Max(-1,-z/{r})))"  # geodesic distance from the lowest point, scaled to the surface
    size = (f"Min({R / 3:.17g},{h:.17g}+{GRADED_ALONG:.17g}*Max(0,{along}-{fine:.17g})"
            f"+{GRADED_INTO:.17g}*Max(0,{R:.17g}-{r}))")
    with gmsh_session("hemisphere") as gmsh:
        occ = gmsh.model.occ
        outer, inner = occ.addSphere(0, 0, 0, R), occ.addSphere(0, 0, 0, core * R)
        # the spheres' parametric poles onto the cut plane, far from where the target touches
        occ.rotate([(3, outer), (3, inner)], 0, 0, 0, 1, 0, 0, np.pi / 2)
        shell, _ = occ.cut([(3, outer)], [(3, inner)])
        occ.cut(shell, [(3, occ.addBox(-2 * R, -2 * R, 0, 4 * R, 4 * R, 2 * R))])
        occ.synchronize()
        size_field(gmsh, size)
        gmsh.model.mesh.generate(3)
        tags, xyz, _ = gmsh.model.mesh.getNodes()
        _, tets = gmsh.model.mesh.getElementsByType(4)
    nodes, tets, _ = compact(tags, xyz, tets, 4)
    if turn:
        nodes = _turned(nodes, turn)
    # gmsh puts the surface's nodes on the sphere to round-off; no other node comes near it
    return TetMesh(nodes, tets).oriented(), np.linalg.norm(nodes, axis=1) > R * (1 - 1e-9)


class SoftSphere:
    """The meshed lower half of a soft sphere, centred at the origin of its own frame, with
    cells of ``mesh_size`` m where it touches (:func:`hemisphere_mesh`; with ``fine_radius`` m
    given, :func:`graded_hemisphere_mesh`, that fine out to it): ``mesh`` (P2),
    ``elastic`` (its energy term), ``fixed`` (n, 3)
    (bonded to the stage: the equatorial cut face and the rigid core of radius core·R, which
    the deformation at small depth hardly reaches) and its spherical surface: ``tris`` (k, 3)
    linear triangles (outward), ``nodes`` with area ``weights``."""

    def __init__(self, radius: float, material: Material, mesh_size: float, growth: float = 1.35, core: float = 0.1,
                 device: str = "cpu", turn: float = 0.0, fine_radius: float | None = None):
        self.radius = float(radius)
        self.material = material
        self.mesh_size = float(mesh_size)
        if fine_radius is None:
            lin, n = hemisphere_mesh(radius, mesh_size, growth, core, turn)
            outer = np.arange(lin.n_nodes) < n  # layer 0, the sphere
        else:
            lin, outer = graded_hemisphere_mesh(radius, mesh_size, fine_radius, core, turn)
        self.mesh = P2Mesh.from_linear(lin)
        self.elastic = ElasticTerm(self.mesh, material, device=device)
        X = self.mesh.nodes
        rr = np.linalg.norm(X, axis=1)
        self.fixed = np.zeros_like(X, bool)
        self.fixed[(np.abs(X[:, 2]) < 1e-9 * radius) | (rr < core * radius * (1 + 1e-9))] = True
        bf = self.mesh.boundary_faces
        # every corner on the sphere (a face of the cut plane may have its three on the rim)
        on_surface = np.all(outer[bf[:, :3]], axis=1) & ~np.all(np.abs(X[bf[:, :3], 2]) < 1e-9 * radius, axis=1)
        self.tris = linear_subtriangles(bf[on_surface])
        self.nodes, self.weights = nodal_areas(X, self.tris)


def press_on_rigid_flat(sphere: SoftSphere, depth: float, penalty: float) -> tuple[np.ndarray, float]:
    """The Hertz case: ``sphere`` pressed by ``depth`` (m) onto a rigid, frictionless flat (a
    square plate of side 4R, contact penalty ``penalty`` Pa/m). (force (3,) N of the flat on
    the sphere, largest penetration m)."""
    R, ns = sphere.radius, sphere.mesh.n_nodes
    L = 2 * R
    plate = np.array([[-L, -L, 0], [L, -L, 0], [L, L, 0], [-L, L, 0]], float) + [0, 0, -R + depth]
    X = np.vstack([sphere.mesh.nodes, plate])
    contact = SurfaceContact(X, sphere.nodes, sphere.weights, np.array([[0, 1, 2], [0, 2, 3]]) + ns, stiffness=penalty, margin=0.2 * R)
    terms = CoupledTerms(ns + 4, [(0, sphere.elastic, sphere.mesh.sparsity[:2])], [contact])
    u = np.zeros_like(X)
    terms.refresh(u)
    fixed = np.vstack([sphere.fixed, np.ones((4, 3), bool)])
    res = minimize_energy([terms], u, fixed, rtol=1e-9, system=NewtonSystem(terms.indptr, terms.indices, ~fixed.ravel()))
    return contact.force_on(res.u, np.arange(ns)), contact.penetration(res.u)


def _entries(P: sp.csr_matrix) -> tuple[np.ndarray, np.ndarray]:
    """(rows, cols) of a CSR matrix's stored entries."""
    return csr_rows(P.indptr), P.indices.astype(np.int64)


def default_contact_slave(target: Material, membrane: Material) -> str:
    """Whose surface nodes are the soft contact's slaves by default: the target's unless it is
    10× stiffer (shear modulus) than the membrane (see :class:`SoftTargetModel`)."""
    return "target" if target.mu < 10 * membrane.mu else "membrane"


class CoupledTerms:
    """One energy term over the unknowns of several bodies: ``blocks`` [(first node, term,
    (indptr, indices) of the term's own Hessian pattern)], each term evaluated on its rows of
    u, plus ``contacts`` (:class:`SurfaceContact`) over all of them. The Hessian comes back on
    one fixed pattern, the union of the blocks' and the contact candidates' couplings
    (``indptr``, ``indices``), which changes only in :meth:`refresh`."""

    def __init__(self, n_nodes: int, blocks: list[tuple[int, object, tuple[np.ndarray, np.ndarray]]], contacts: list[SurfaceContact]):
        self.n = 3 * n_nodes
        self.blocks = [(int(o), t, int(len(p[0]) - 1) // 3) for o, t, p in blocks]
        rows, cols = [], []
        for o, _, (indptr, indices) in blocks:
            rows.append(csr_rows(indptr) + 3 * o)
            cols.append(np.asarray(indices, np.int64) + 3 * o)
        self._base = self._pattern(np.concatenate(rows), np.concatenate(cols))
        self.contacts = contacts
        self._set_pattern(self._base)
        self.rebuilds = 0

    @property
    def RELINEARISES(self) -> bool:
        """Whether a Hessian evaluation re-lags a contact (then Newton must take the energy and
        gradient from that same evaluation, not from the line search's before it)."""
        return any(getattr(c, "RELINEARISES", False) for c in self.contacts)

    def _pattern(self, rows, cols) -> sp.csr_matrix:
        """The pattern of (rows, cols), every entry 1. Duplicates are summed and then reset:
        a small integer type would wrap (256 contact couplings of one diagonal entry summed
        to 0 in int8 and dropped it from the pattern)."""
        P = sp.csr_matrix((np.ones(len(rows), np.int64), (rows, cols)), shape=(self.n, self.n))
        P.sum_duplicates()
        P.sort_indices()
        P.data[:] = 1
        return P

    def _set_pattern(self, P: sp.csr_matrix) -> None:
        P.sort_indices()
        self.indptr = P.indptr.astype(np.int64)
        self.indices = P.indices.astype(np.int32)
        self.keys = csr_rows(self.indptr) * self.n + self.indices
        self._slots: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}

    def _coupling_dofs(self):
        r, c = [], []
        for ct in self.contacts:
            a, b = ct.couplings()
            r.append(a)
            c.append(b)
        a, b = np.concatenate(r), np.concatenate(c)
        rows = (3 * a[:, None, None] + np.arange(3)[:, None] + 0 * np.arange(3)).ravel()
        cols = (3 * b[:, None, None] + 0 * np.arange(3)[:, None] + np.arange(3)).ravel()
        return rows, cols

    def refresh(self, u: np.ndarray) -> bool:
        """Update the contacts' candidates at ``u`` (n, 3); True when the pattern had to change
        (then rebuild the solver's analysis on ``indptr``, ``indices``)."""
        for ct in self.contacts:
            ct.update_candidates(u)
        rows, cols = self._coupling_dofs()
        if find_keys(self.keys, rows * self.n + cols) is not None:
            return False
        C = self._pattern(rows, cols)
        self._set_pattern(self._pattern(*_entries(self._base + C)))
        self.rebuilds += 1
        return True

    def _place(self, H: sp.spmatrix, offset: int, cache_key: int | None) -> tuple[np.ndarray, np.ndarray]:
        """(slots, values) of the block matrix ``H`` placed at node ``offset`` in the pattern."""
        H = sp.csr_matrix(H)
        hit = self._slots.get(cache_key) if cache_key is not None else None
        if hit is not None and np.array_equal(hit[0], H.indptr) and np.array_equal(hit[1], H.indices):
            return hit[2], H.data
        rows = csr_rows(H.indptr) + 3 * offset
        slot = find_keys(self.keys, rows * self.n + H.indices.astype(np.int64) + 3 * offset)
        if slot is None:
            raise RuntimeError("a Hessian term has entries outside the coupled pattern (refresh the contacts)")
        if cache_key is not None:
            self._slots[cache_key] = (H.indptr.copy(), H.indices.copy(), slot)
        return slot, H.data

    def _matrix(self, parts) -> sp.csr_matrix:
        data = np.zeros(len(self.indices))
        for slot, vals in parts:  # canonical CSR blocks: each slot once per part
            data[slot] += vals
        return sp.csr_matrix((data, self.indices, self.indptr), shape=(self.n, self.n))

    def evaluate(self, u: np.ndarray, hessian: bool):
        """(energy, gradient (3n,), Hessian on the pattern or None, admissible)."""
        E, g, parts = 0.0, np.zeros(self.n), []
        for i, (o, term, m) in enumerate(self.blocks):
            e, gb, Hb, ok = term.evaluate(u[o : o + m], hessian)
            if not ok:
                return np.inf, np.zeros(self.n), None, False
            E += e
            g[3 * o : 3 * (o + m)] += gb
            if hessian and Hb is not None and Hb.nnz:
                parts.append(self._place(Hb, o, i))
        for ct in self.contacts:
            e, gc, Hc, _ = ct.evaluate(u, hessian)
            E += e
            g += gc
            if hessian and Hc is not None and Hc.nnz:
                parts.append(self._place(Hc, 0, None))
        return E, g, (self._matrix(parts) if hessian else None), True

    def projected_hessian(self, u: np.ndarray) -> sp.csr_matrix:
        """Each term's SPD-projected Hessian (after :meth:`evaluate` at the same ``u``)."""
        parts = []
        for i, (o, term, m) in enumerate(self.blocks):
            ub = u[o : o + m]
            Hb = term.projected_hessian(ub) if hasattr(term, "projected_hessian") else term.evaluate(ub, True)[2]
            if Hb is not None and Hb.nnz:
                parts.append(self._place(Hb, o, i))
        for ct in self.contacts:
            Hc = ct.projected_hessian(u)
            if Hc is not None and Hc.nnz:
                parts.append(self._place(Hc, 0, None))
        return self._matrix(parts)


class _MembranePressure:
    """The saline pressure term seen through the coupled unknowns (the membrane's rows)."""

    def __init__(self, term, n_membrane: int):
        self.term, self.n = term, n_membrane

    @property
    def pressure(self) -> float:
        return self.term.pressure

    @pressure.setter
    def pressure(self, p: float) -> None:
        self.term.pressure = float(p)

    def volume(self, u: np.ndarray) -> float:
        return self.term.volume(u[: self.n])

    def volume_gradient(self, u: np.ndarray) -> np.ndarray:
        """∂V/∂u, flat, over both bodies' unknowns (zero on the target's)."""
        g = np.zeros(u.size)
        g[: 3 * self.n] = self.term.volume_gradient(u[: self.n])
        return g


class _TargetContact:
    """The membrane–target contact with the interface of the rigid :class:`SphereContact`
    (``nodes``, ``radius``, ``centre``, ``force``, ``contact_area``, ``penetration``), so the
    membrane model's pose logic serves both. ``slave`` "target": the target's surface nodes
    against the membrane's outer triangles; "membrane": the reverse."""

    def __init__(self, X_membrane, nodes, weights, outer_tris, stiffness, target: SoftSphere, margin: float, slave: str = "target"):
        if slave not in ("target", "membrane"):
            raise ValueError(f"slave = {slave!r}: allowed values are 'target', 'membrane'")
        self.n_membrane = nm = len(X_membrane)
        self.slave = slave
        self.target = target
        self.radius = target.radius
        self.nodes = np.asarray(nodes)  # the membrane's outer-surface nodes (first contact)
        self.stiffness = float(stiffness)
        self._Xm = np.asarray(X_membrane, float)
        self._t_nodes = nm + np.arange(target.mesh.n_nodes)
        self._scale = 1.0
        X0 = self._world(np.array([0.0, 0.0, 1e3]))
        # the membrane's outer nodes against the target, for the contact area whichever side
        # is the slave (as the rigid case measures it)
        self._probe = SurfaceContact(X0, self.nodes, weights, nm + target.tris, stiffness, margin)
        if slave == "target":
            self.surface = SurfaceContact(X0, nm + target.nodes, target.weights, outer_tris, stiffness, margin)
        else:
            self.surface = self._probe
        self._centre = np.array([0.0, 0.0, 1e3])

    def _world(self, centre):
        return np.vstack([self._Xm, self._scale * self.target.mesh.nodes + centre])

    def place(self, centre: np.ndarray, scale: float = 1.0) -> None:
        """The target at ``centre`` (3,) m with its body scaled by ``scale`` about it (a sphere of
        radius ``scale`` × R, its mesh homothetic, the target's slave areas with it): how the
        derivatives with respect to the radius move it (:meth:`SoftTargetModel.target_gradients`)."""
        self._scale = float(scale)
        if self.slave == "target":
            self.surface.weights = self.target.weights * self._scale**2
        self.centre = centre

    @property
    def X(self) -> np.ndarray:
        return self.surface.X

    @property
    def centre(self) -> np.ndarray:
        return self._centre

    @centre.setter
    def centre(self, c) -> None:
        self._centre = np.array(c, float)
        self.surface.X = self._probe.X = self._world(self._centre)

    def force(self, u: np.ndarray) -> np.ndarray:
        """Total force (3,) N that the membrane exerts on the target."""
        return self.surface.force_on(u, self._t_nodes)

    def contact_area(self, u: np.ndarray) -> float:
        """Area (m²) of the membrane's outer surface in contact: its nodes whose gap to the
        target is below the largest penetration (the interpenetration's scale)."""
        if self._probe is self.surface:
            return self.surface.contact_area(u)
        self._probe.update_candidates(u)
        tri, _, _, gap = self._probe._choose(u, self._probe.cand_s, self._probe.cand_t)
        return float(self._probe.weights[(tri >= 0) & (gap <= self.penetration(u))].sum())

    def penetration(self, u: np.ndarray) -> float:
        return self.surface.penetration(u)

    def centre_of_pressure(self, u: np.ndarray) -> np.ndarray:
        return self.surface.centre_of_pressure(u)


class SoftTargetModel(MembraneModel):
    """:class:`MembraneModel` pressed by a soft sphere (``target_material``, radius
    ``target_radius``) instead of a rigid one; same poses, same state. The unknowns ``u`` are
    the membrane's P2 nodes followed by the target's (in the target's moving frame);
    :attr:`target` is the :class:`SoftSphere`. ``target_mesh_size`` (m): the target's cell
    size at its lowest point (default: half the membrane's edge, at most R/8);
    ``contact_margin`` (m): slave nodes within it of the other surface are contact candidates;
    ``contact_slave``: whose surface nodes are the contact's slaves, "target" or "membrane"
    (default: the target's unless it is 10× stiffer than the membrane); ``target_turn`` (rad):
    the target's mesh turned about its axis (:func:`hemisphere_mesh`); ``target_fine_radius``
    (m): the target meshed by :func:`graded_hemisphere_mesh`, its cells ``target_mesh_size``
    out to this far from its lowest point (None: :func:`hemisphere_mesh`'s layers)."""

    TANGENT_PREDICTOR = False  # the target's own unknowns are not in the rigid-contact tangent
    TARGET_PARAMETERS = MembraneModel.TARGET_PARAMETERS + ("ln_target_modulus",)

    def __init__(
        self,
        dome: DomeSurface,
        thickness: float = 2e-3,
        material: Material = ECOFLEX_00_50,
        layers: int | None = None,
        pressure: float = 0.0,
        target_radius: float = 7.5e-3,
        target_material: Material | None = None,
        target_mesh_size: float | None = None,
        target_growth: float = 1.35,
        target_core: float = 0.1,
        target_turn: float = 0.0,
        target_fine_radius: float | None = None,
        penalty: float | None = None,
        force_tol: float | None = None,
        friction: float = 0.0,
        closed: bool = False,
        contact_margin: float = 1e-3,
        contact_slave: str | None = None,
        volumetric: str = "pointwise",
        device: str = "cpu",
        inflate_to: float | None = None,
        inflate_from: np.ndarray | None = None,
        element: str = "wedge15",
    ):
        if friction != 0.0:
            raise ValueError(f"friction = {friction}: friction against a soft target is not modelled (use 0)")
        super().__init__(dome, thickness, material, layers, pressure, target_radius, penalty, force_tol, 0.0, closed, volumetric,
                         device=device, inflate_to=inflate_to, inflate_from=inflate_from, element=element)
        edge = float(np.median(np.linalg.norm(dome.vertices[dome.faces[:, 1]] - dome.vertices[dome.faces[:, 0]], axis=1)))
        h = target_mesh_size if target_mesh_size is not None else min(0.5 * edge, target_radius / 8)
        self.target = SoftSphere(target_radius, target_material if target_material is not None else SYLGARD_184, h, target_growth, target_core,
                                 device, target_turn, target_fine_radius)
        nm = self.mesh.n_nodes
        self.n_membrane = nm
        rigid = self.contact
        if contact_slave is None:
            # the softer body's nodes are the slaves: a stiff master's facets stay flat, while a
            # soft master dents around each slave node and its closest facet flips between the
            # dent's sides from one Newton iteration to the next (measured: no convergence with
            # membrane slaves on a target as soft as the membrane, nor with target slaves on a
            # target 100× stiffer; both converge with the rule below)
            contact_slave = default_contact_slave(self.target.material, material)
        self.contact = _TargetContact(
            self.mesh.nodes, rigid.nodes, rigid.weights, linear_subtriangles(self.outer_faces), rigid.stiffness, self.target, contact_margin, contact_slave
        )
        self.contact.centre = rigid.centre
        self._membrane_pressure = self.pressure
        self.pressure = _MembranePressure(self._membrane_pressure, nm)
        self.coupled = CoupledTerms(
            nm + self.target.mesh.n_nodes,
            [(0, self.elastic, self.mesh.sparsity[:2]), (0, self._membrane_pressure, self.mesh.sparsity[:2]),
             (nm, self.target.elastic, self.target.mesh.sparsity[:2])],
            [self.contact.surface],
        )
        self.fixed = np.vstack([self.fixed, self.target.fixed])
        self.u = np.vstack([self.u, np.zeros((self.target.mesh.n_nodes, 3))])
        self.system.free_factors()
        self.system = None
        self.pattern_rebuilds = 0

    @property
    def terms(self) -> list:
        return [self.coupled]

    def _system(self, guess: np.ndarray) -> None:
        """Contact candidates at ``guess``; a new solver analysis when they leave the pattern."""
        if self.coupled.refresh(guess) or self.system is None:
            if self.system is not None:
                self.system.free_factors()
            self.system = NewtonSystem(self.coupled.indptr, self.coupled.indices, ~self.fixed.ravel())
            self.pattern_rebuilds += 1

    def _newton(self, guess: np.ndarray, predicted: bool = False):
        # predicted is always False here: no tangent predictor (TANGENT_PREDICTOR). So a target
        # move too small for the tolerance (a servo's ~1e-12 m jitter in a palpation hold) gets one
        # Newton step all the same, the linear response: at none the bodies stayed put and the
        # force answered with the contact penalty's stiffness (a hold rang at ±0.3 %)
        kw = dict(rtol=0.0, atol=self._step_tol)
        its = 0
        for attempt in range(4):
            self._system(guess)
            try:
                res = minimize_energy(self.terms, guess, self.fixed, system=self.system, min_iter=int(self._moved and attempt == 0), **kw)
            except NewtonError:
                # the extrapolation may have overshot: start from the last equilibrium
                self._system(self.u)
                res = minimize_energy(self.terms, self.u, self.fixed, system=self.system, **kw)
            its += res.iterations
            if self.contact.surface.covers(res.u):
                res.iterations = its  # over the re-solves
                return self._tally(res)
            guess = res.u  # a slave's closest triangle left its candidates: solve again
        raise NewtonError("soft target: the contact pairs did not settle in 4 solves")

    def _extrapolate(self, centre: np.ndarray) -> np.ndarray:
        """The secant predictor of both bodies (see :meth:`MembraneModel._extrapolate`)."""
        if len(self.history) < 2:
            return self.u
        (c0, u0), (c1, u1) = self.history
        step = np.linalg.norm(c1 - c0)
        if step == 0:
            return self.u
        guess = u1 + float(np.dot(centre - c1, c1 - c0) / step**2) * (u1 - u0)
        return guess if self.coupled.evaluate(guess, False)[3] else self.u

    def target_gradients(self, u: np.ndarray, rel_step: float = 1e-6) -> np.ndarray:
        """∂g/∂(c_x, c_y, c_z, R, ln E) (3n, 5) at ``u``: how the energy's gradient over both
        bodies (the unknowns held) changes with the target's centre, its radius and its
        Young's modulus.

        - the centre moves the target's frame, so only the contact sees it;
        - the radius scales the target's body by s about its centre (its mesh homothetic). Its
          unknowns stay its displacements in that frame, so its elastic energy is
          s³ W(u/s) (F = I + ∇u/s over s³ the volume), its gradient s² ∇W(u/s);
        - the modulus scales the target's energy: ∂g/∂ln E is its elastic gradient.

        The first two by central differences over ``rel_step`` × R of the contact's gradient
        with each slave on its triangle at ``u``, its closest point and normal taken afresh on
        either side (:meth:`~.surface_contact.SurfaceContact.held_gradient`)."""
        u = np.asarray(u, float)
        ct, nm = self.contact, self.n_membrane
        centre, R = ct.centre.copy(), ct.radius
        tri = ct.surface.assignment(u)
        out = np.zeros((u.size, 5))
        h = rel_step * R

        def gradient(c: np.ndarray, s: float) -> np.ndarray:
            ct.place(c, s)
            g = ct.surface.held_gradient(u, tri)
            if s != 1.0:
                g[3 * nm:] += s * s * self.target.elastic.evaluate(u[nm:] / s, False)[1]
            return g

        try:
            for a in range(3):
                e = np.eye(3)[a] * h
                out[:, a] = (gradient(centre + e, 1.0) - gradient(centre - e, 1.0)) / (2 * h)
            out[:, 3] = (gradient(centre, 1.0 + rel_step) - gradient(centre, 1.0 - rel_step)) / (2 * h)
        finally:
            ct.place(centre, 1.0)
        out[3 * nm:, 4] = self.target.elastic.evaluate(u[nm:], False)[1]
        return out

    def equilibrium_derivative(self, dg: np.ndarray, rtol: float = 1e-6) -> np.ndarray:
        """du/dθ = −H⁻¹ ∂g/∂θ (n, 3, k) at the equilibrium the model stands at, as
        :meth:`MembraneModel.equilibrium_derivative`, with H the true tangent: Newton's lagged
        contact Hessian keeps each slave's closest triangle and normal, so it misses how they
        slide and turn as the bodies move (measured: 16 % of the membrane's response to a
        sideways move, 1.2 % of its response to the target's modulus; tests/test_soft_target.py,
        results/design_study/soft_derivatives.md).
        H·v is Newton's Hessian with its contact part replaced by a central difference along v
        of the contact's gradient with each slave on its triangle at the equilibrium
        (:meth:`~.surface_contact.SurfaceContact.held_gradient`); the system is solved by
        GMRES preconditioned with Newton's factorised Hessian, to
        ``rtol`` (the differenced contact is linear to ~1e-7). Off the axis it is the limit of
        re-solved differences (0.004–0.1 %). On the axis two structured meshes meet
        symmetrically: with their rings aligned, slaves sit on facet edges and this tangent is
        not the response to any finite move (61 % off in c_z; a target turned by
        :data:`GENERIC_TURN` removes that: 0.01 %), and whole rings of slaves reach the
        contact's edge together, so the response itself has kinks at the micrometre scale (at
        2 mm deep, moves of ± 2 µm up and down differ by 83 %): there no derivative describes
        it. Raises NewtonError where that Hessian is not positive definite or GMRES does not
        converge."""
        from scipy.sparse.linalg import LinearOperator, gmres

        u = self.u
        dg = np.asarray(dg, float).reshape(u.size, -1)
        self._system(u)  # none yet on a model that has not pressed
        self.system.context = self.factor_context()
        # one assembly: Newton's Hessian, factorised as factor_tangent would, and less its
        # contact part the tangent's base
        H = self.coupled.evaluate(u, True)[2]
        if not self.system.factor_hessian(self.system.data([H]), u):
            raise NewtonError("equilibrium_derivative: the Hessian is not positive definite at this equilibrium")
        free = np.flatnonzero(~self.fixed.ravel())
        surface = self.contact.surface
        Hc = surface.evaluate(u, True)[2]
        base = (H - Hc)[free][:, free].tocsr()
        step = 1e-4 * max(self.contact.penetration(u), 1e-9)  # m: far below the contact's scale
        tri = surface.assignment(u)

        def tangent(v: np.ndarray) -> np.ndarray:
            w = np.zeros(u.size)
            w[free] = v
            eps = step / max(float(np.abs(w).max()), 1e-300)
            w = w.reshape(u.shape)
            dc = (surface.held_gradient(u + eps * w, tri) - surface.held_gradient(u - eps * w, tri)) / (2 * eps)
            return base @ v + dc[free]

        n = len(free)
        A = LinearOperator((n, n), matvec=tangent, dtype=float)
        M = LinearOperator((n, n), matvec=lambda r: self.system.solve_tangent(r[:, None])[:, 0], dtype=float)
        du = np.zeros_like(dg)
        for j in range(dg.shape[1]):
            b = -dg[free, j]
            if not b.any():
                continue
            x0 = self.system.solve_tangent(b[:, None])[:, 0]
            x, info = gmres(A, b, x0=x0, M=M, rtol=rtol, atol=0.0, restart=40, maxiter=5)
            # the differenced contact is linear only to ~1e-7 of b (a slave at the edge of
            # contact within the step): GMRES's own estimate then stalls below its true residual
            miss = np.linalg.norm(A.matvec(x) - b) / np.linalg.norm(b)
            if info != 0 and miss > 10 * rtol:
                raise NewtonError(f"equilibrium_derivative: GMRES left a residual of {miss:.2g} for column {j}")
            du[free, j] = x
        return du.reshape(u.shape + (dg.shape[1],))

    def state(self, iterations: int = 0, residual: float = 0.0) -> MembraneState:
        """The membrane's state as for a rigid target (``u``: the membrane's rows); ``force``
        is the membrane's push on the target and ``min_jacobian`` covers both bodies."""
        u = self.u
        nm = self.n_membrane
        um = u[:nm]
        n = self.n_surface
        dome = DomeSurface(self.dome.vertices + um[:n], self.dome.faces, self.dome.rim)
        jm = self.elastic.kernel(um, hessian=False).min_det.min()
        jt = self.target.elastic.kernel(u[nm:], hessian=False).min_det.min()
        return MembraneState(
            dome=dome,
            u=um.copy(),
            force=self.contact.force(u),
            contact_area=self.contact.contact_area(u),
            displaced_volume=self.V0 - self.pressure.volume(u),
            peak_strain=self.mesh.peak_green_strain(um),
            iterations=iterations,
            residual=residual,
            penetration=self.contact.penetration(u),
            pressure=self.pressure.pressure,
            min_jacobian=float(min(jm, jt)),
            contact_centre=self.contact.centre_of_pressure(u),
        )
