"""Quadratic prisms (15-node serendipity wedges) through the membrane's thickness, with the
element energy, gradient and Hessian in a Warp kernel — the alternative to fem.py's P2
tetrahedra for the dome (``MembraneModel(element="wedge15")``).

A prism layer of the membrane is one wedge per surface triangle instead of three P2 tetrahedra:
no midside nodes on the quad faces' diagonals, so about 30 % fewer nodes at the same surface
mesh, a sparser Hessian, and a factorisation ~2× cheaper (results/element_pattern.md).

Locking: the volumetric energy U = κ/2 (θ − 1)² is taken of the dilatation θ projected, element
by element, onto the linear polynomials {1, ξ, η, ζ} of the reference prism (L² with the element's
volume weights) — a discontinuous linear pressure condensed out, as in the 15-node hybrid
elements of commercial codes. Its four constraints per element against ~14 unknowns leave the
nearly incompressible shell free to bend; with the pressure at every quadrature point (P2
tetrahedra's "pointwise") the apex load on the dome is 2–3.5 % stiff at κ = 1000 μ, with this
projection within 0.8 % of the axisymmetric reference on one to three layers (results/dome_apex_load.md).

Hessian of the projected term: with B = Σ_q w_q φ(ξ_q) ∂J_q/∂u (4 × 45) and the Gram matrix
G = Σ_q w_q φ φᵀ, θ_q = φ(ξ_q)ᵀ G⁻¹ Σ w φ J, and

    ∂²E_vol = Σ_q w_q κ(θ_q − 1) ∂²J_q + κ Bᵀ G⁻¹ B,

the first term in the material tangent's pressure slot (materials.tangent_with_pressure with
k_local = 0), the second added per element.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import scipy.sparse as sp

from .._warp import wp
from ..linalg import element_pattern
from ..mesh.tetmesh import TetMesh
from . import fem
from .fem import (
    ElasticTerm,
    ElementState,
    HessianTarget,
    peak_green_strain,
    warp_device,
)
from .materials import (
    Material,
    first_piola,
    stiffness_block,
    strain_energy,
    tangent_with_pressure,
)
from .prisms import membrane_mesh, split_prisms

__all__ = ["WedgeMesh", "WedgeKernel", "WedgeElasticTerm", "wedge_shape", "WEDGE_POINTS", "WEDGE_WEIGHTS"]

wp.set_module_options({"max_unroll": 1, "enable_backward": False})

# node order: bottom corners 0 1 2, top corners 3 4 5, bottom midsides 01 12 20, top midsides
# 34 45 53, vertical midsides 03 14 25. Reference prism: (ξ, η) in the unit triangle, ζ ∈ [−1, 1]
_PAIRS = ((0, 1), (1, 2), (2, 0))
_NODES, _DOFS = 15, 45


def wedge_shape(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Shape functions N (q, 15) and their reference gradients ∂N/∂(ξ, η, ζ) (q, 15, 3) at
    points (q, 3)."""
    xi, eta, zeta = np.asarray(points, float).T
    L = np.stack([1 - xi - eta, xi, eta])  # (3, q)
    dL = np.array([[-1.0, -1.0], [1.0, 0.0], [0.0, 1.0]])  # ∂L_i/∂(ξ, η)
    q = len(xi)
    N = np.zeros((q, _NODES))
    dNdL = np.zeros((q, _NODES, 3))
    dNdz = np.zeros((q, _NODES))
    bubble = 1 - zeta**2
    for i in range(3):
        for s, off in ((-1.0, 0), (1.0, 3)):  # corners: ½ L (2L − 1)(1 ± ζ) − ½ L (1 − ζ²)
            z = 1 + s * zeta
            N[:, off + i] = 0.5 * L[i] * ((2 * L[i] - 1) * z - bubble)
            dNdL[:, off + i, i] = 0.5 * ((4 * L[i] - 1) * z - bubble)
            dNdz[:, off + i] = 0.5 * L[i] * (s * (2 * L[i] - 1) + 2 * zeta)
        N[:, 12 + i] = L[i] * bubble  # vertical midsides
        dNdL[:, 12 + i, i] = bubble
        dNdz[:, 12 + i] = -2 * zeta * L[i]
    for k, (i, j) in enumerate(_PAIRS):
        for s, off in ((-1.0, 6), (1.0, 9)):  # in-plane midsides: 2 L_i L_j (1 ± ζ)
            z = 1 + s * zeta
            N[:, off + k] = 2 * L[i] * L[j] * z
            dNdL[:, off + k, i] = 2 * L[j] * z
            dNdL[:, off + k, j] = 2 * L[i] * z
            dNdz[:, off + k] = s * 2 * L[i] * L[j]
    dN = np.concatenate([dNdL @ dL, dNdz[:, :, None]], axis=2)
    return N, dN


def _quadrature() -> tuple[np.ndarray, np.ndarray]:
    """3-point triangle (degree 2) × 3-point Gauss in ζ (degree 5): the stiffness of an affine
    wedge exactly; weights sum to the reference prism's volume, 1."""
    tri = np.array([[1 / 6, 1 / 6], [2 / 3, 1 / 6], [1 / 6, 2 / 3]])
    z, wz = np.array([-np.sqrt(0.6), 0.0, np.sqrt(0.6)]), np.array([5.0, 8.0, 5.0]) / 9
    pts = np.array([[a, b, c] for a, b in tri for c in z])
    return pts, np.repeat(np.full(3, 1 / 6), 3) * np.tile(wz, 3)


WEDGE_POINTS, WEDGE_WEIGHTS = _quadrature()


def _reference_geometry(nodes: np.ndarray, elements: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """∇_X N (m, q, 15, 3) and det ∂X/∂ξ (m, q) of the elements' reference maps at ``points`` (q, 3)."""
    dN = wedge_shape(points)[1]
    Jx = np.einsum("mni,qnk->mqik", nodes[elements], dN)
    return np.einsum("qnk,mqkj->mqnj", dN, np.linalg.inv(Jx)), np.linalg.det(Jx)
_FLIP = np.array([0, 2, 1, 3, 5, 4, 8, 7, 6, 11, 10, 9, 12, 14, 13])  # the same prism, mirrored
_FACE_BOTTOM, _FACE_TOP = [0, 1, 2, 6, 7, 8], [3, 4, 5, 9, 10, 11]
_CENTROID = np.array([[1 / 3, 1 / 3, 0.0]])


@dataclass(frozen=True, eq=False)
class WedgeMesh:
    """``nodes`` (n, 3) reference positions in m; ``elements`` (m, 15) in the module's node
    order; ``boundary_faces`` (k, 6): the triangular faces on the inner and outer surfaces
    (corners a, b, c then midsides ab, bc, ca, outward) — the prisms' quad faces on the boundary
    are the rim's, which is bonded. Isoparametric: midside nodes off their edge's midpoint curve
    the element."""

    nodes: np.ndarray
    elements: np.ndarray
    boundary_faces: np.ndarray

    @classmethod
    def on_membrane(cls, dome, thickness: float, layers: int, centre: np.ndarray | None, place) -> "WedgeMesh":
        """The prism layers of :func:`~jointsim.mechanics.prisms.membrane_mesh` (layer l's copy of
        dome vertex i is node l·n + i) as wedges; the midside nodes (in-plane edges of every
        level, then the vertical edges of every layer) placed by ``place`` (edge ends (k, 2, 3)
        → nodes (k, 3); as for ``P2Mesh.from_linear``)."""
        lin, n = membrane_mesh(dome, thickness, layers, centre)
        return cls.extrude(lin.nodes, np.asarray(dome.faces), layers, place)

    @classmethod
    def extrude(cls, corners: np.ndarray, faces: np.ndarray, layers: int, place=None) -> "WedgeMesh":
        """Wedges between the ``layers + 1`` copies of a triangulated surface: ``corners``
        ((layers + 1)·n, 3), level l's copy of vertex i at row l·n + i; ``faces`` (k, 3) the
        surface's triangles. Midside nodes by ``place`` (edge ends (k, 2, 3) → nodes (k, 3);
        None: the midpoints)."""
        corners = np.asarray(corners, float)
        f = np.asarray(faces)
        n = len(corners) // (layers + 1)
        place = place if place is not None else (lambda ends: ends.mean(axis=1))
        edges, inv = np.unique(np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1), axis=0, return_inverse=True)
        face_edge = inv.ravel().reshape(3, -1).T  # (faces, 3): edges 01 12 20 of each face
        levels = np.arange(layers + 1)
        mids = place(corners[(levels[:, None, None] * n + edges[None]).reshape(-1, 2)])
        column = np.arange(n)
        vertical = place(np.stack([corners[(levels[:-1, None] * n + column).ravel()], corners[(levels[1:, None] * n + column).ravel()]], axis=1))
        nodes = np.vstack([corners, mids, vertical])
        mid0, vert0, ne = len(corners), len(corners) + len(mids), len(edges)
        elements = np.vstack([
            np.hstack([l * n + f, (l + 1) * n + f, mid0 + l * ne + face_edge, mid0 + (l + 1) * ne + face_edge, vert0 + l * n + f])
            for l in range(layers)
        ]).astype(np.int32)
        # orient: ζ must run along the right-handed normal of the bottom triangle
        flip = _reference_geometry(nodes, elements, _CENTROID)[1][:, 0] < 0
        elements[flip] = elements[flip][:, _FLIP]
        nf = len(f)
        surfaces = []
        for rows, local in ((elements[:nf], _FACE_BOTTOM), (elements[-nf:], _FACE_TOP)):
            face = rows[:, local]
            p = nodes[face[:, :3]]
            normal = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
            inward = np.einsum("ki,ki->k", normal, nodes[rows].mean(axis=1) - p.mean(axis=1)) > 0
            face[inward] = face[inward][:, [0, 2, 1, 5, 4, 3]]  # a c b, midsides ac cb ba
            surfaces.append(face)
        return cls(nodes, elements, np.vstack(surfaces))

    @property
    def n_nodes(self) -> int:
        return len(self.nodes)

    @property
    def n_elements(self) -> int:
        return len(self.elements)

    @cached_property
    def quadrature_geometry(self) -> tuple[np.ndarray, np.ndarray]:
        """∇_X N (m, q, 15, 3) and det ∂X/∂ξ (m, q) at the quadrature points: the reference
        geometry, fixed for the mesh, which the kernel reads instead of recomputing each call."""
        return _reference_geometry(self.nodes, self.elements, WEDGE_POINTS)

    @property
    def jacobians(self) -> np.ndarray:
        """det ∂X/∂ξ (m, q) at the quadrature points (> 0 in a valid element)."""
        return self.quadrature_geometry[1]

    @cached_property
    def centroid_gradients(self) -> np.ndarray:
        """∇_X N (m, 15, 3) at each element's centroid (ξ = η = ⅓, ζ = 0): F there is I + Σ u_a ⊗ ∇N_a."""
        return _reference_geometry(self.nodes, self.elements, _CENTROID)[0][:, 0]

    def peak_green_strain(self, u: np.ndarray) -> float:
        """Largest principal Green–Lagrange strain over the elements at displacement ``u``
        (n, 3), each element's F taken at its centroid."""
        return peak_green_strain(np.eye(3) + np.einsum("mni,mnj->mij", u[self.elements], self.centroid_gradients))

    @cached_property
    def corner_tets(self) -> np.ndarray:
        """Each prism's corners split into three tetrahedra (m·3, 4), conforming between
        neighbours, positively oriented: a linear tetrahedral mesh of the membrane for output."""
        return TetMesh(self.nodes, split_prisms(self.elements[:, :3], self.elements[:, 3:6])).oriented().tets

    @cached_property
    def sparsity(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(indptr, indices, slot) of the 3n × 3n Hessian: element entry (e, r, c) adds into
        data[slot[e·2025 + 45 r + c]]."""
        dof = (3 * self.elements[:, :, None] + np.arange(3)).reshape(-1, _DOFS).astype(np.int64)
        return element_pattern(dof, 3 * self.n_nodes)


_Mat15x3 = wp.types.matrix(shape=(15, 3), dtype=wp.float64)


@wp.func
def _deformation(u: wp.array(dtype=wp.vec3d), els: wp.array2d(dtype=wp.int32), e: int, grads: wp.array3d(dtype=wp.vec3d), q: int) -> wp.mat33d:
    F = wp.identity(n=3, dtype=wp.float64)
    for a in range(15):
        F += wp.outer(u[els[e, a]], grads[e, q, a])
    return F


@wp.kernel
def _wedge_element(
    u: wp.array(dtype=wp.vec3d),
    els: wp.array2d(dtype=wp.int32),
    params: wp.array2d(dtype=wp.float64),
    grads: wp.array3d(dtype=wp.vec3d),
    weights: wp.array2d(dtype=wp.float64),
    gram_inv: wp.array(dtype=wp.mat44d),
    phi: wp.array2d(dtype=wp.float64),
    nq: int,
    mode: int,
    slot: wp.array2d(dtype=wp.int32),
    offset: int,
    energy: wp.array(dtype=wp.float64),
    grad: wp.array2d(dtype=wp.float64),
    hess_data: wp.array(dtype=wp.float64),
    min_det: wp.array(dtype=wp.float64),
    K: wp.array3d(dtype=wp.float64),
    B: wp.array3d(dtype=wp.float64),
):
    # K (45 × 45) and B (4 × 45) live in per-element rows of global arrays: as local matrices
    # they make the generated code (and its compile) explode
    e = wp.tid() + offset
    one = wp.float64(1.0)
    zero = wp.float64(0.0)
    c1 = params[e, 0]
    c2 = params[e, 1]
    c3 = params[e, 2]
    kappa = params[e, 3]
    # pass 1: the dilatation's projection onto φ = (1, ξ, η, ζ): θ(ξ) = φ(ξ)ᵀ G⁻¹ Σ_q w φ J, with
    # the Gram matrix G = Σ_q w φ φᵀ of the reference geometry (gram_inv: its inverse)
    Gi = gram_inv[e]
    moments = wp.vec4d()
    jmin = wp.float64(1.0e30)
    for q in range(nq):
        J = wp.determinant(_deformation(u, els, e, grads, q))
        jmin = wp.min(jmin, J)
        moments += weights[e, q] * J * wp.vec4d(phi[q, 0], phi[q, 1], phi[q, 2], phi[q, 3])
    coef = Gi @ moments
    if mode != 0:
        for r in range(45):
            for c in range(45):
                K[e, r, c] = zero
            for m in range(4):
                B[e, m, r] = zero
    E = zero
    for q in range(nq):
        w = weights[e, q]
        F = _deformation(u, els, e, grads, q)
        J = wp.determinant(F)
        phq = wp.vec4d(phi[q, 0], phi[q, 1], phi[q, 2], phi[q, 3])
        theta = wp.dot(phq, coef)
        p = kappa * (theta - one)
        E += w * (strain_energy(F, c1, c2, c3, zero) + wp.float64(0.5) * kappa * (theta - one) * (theta - one))
        t = tangent_with_pressure(F, c1, c2, c3, p, zero)
        P = first_piola(t)
        for a in range(15):
            ra = w * (P @ grads[e, q, a])
            for i in range(3):
                grad[e, 3 * a + i] += ra[i]
        if mode != 0:
            # B += w φ_q ⊗ ∂J/∂u (∂J/∂u_a = J F^{-T} ∇N_a), then the isochoric and p·∂²J part of
            # the tangent, block (a, b ≥ a), as in fem._p2_element
            Dg = _Mat15x3()
            Tg = _Mat15x3()
            Pg = _Mat15x3()
            Rg = _Mat15x3()
            for a in range(15):
                ga = grads[e, q, a]
                da = t.D @ ga
                ta = t.T @ ga
                pa = t.c_dd * da - t.c_dt * ta
                ra = t.c_tt * ta - t.c_dt * (t.F @ ga)
                dj = w * J * ta
                for i in range(3):
                    Dg[a, i] = da[i]
                    Tg[a, i] = ta[i]
                    Pg[a, i] = pa[i]
                    Rg[a, i] = ra[i]
                    for m in range(4):
                        B[e, m, 3 * a + i] = B[e, m, 3 * a + i] + phq[m] * dj[i]
            for a in range(15):
                da = wp.vec3d(Dg[a, 0], Dg[a, 1], Dg[a, 2])
                ta = wp.vec3d(Tg[a, 0], Tg[a, 1], Tg[a, 2])
                ga = grads[e, q, a]
                for b in range(a, 15):
                    tb = wp.vec3d(Tg[b, 0], Tg[b, 1], Tg[b, 2])
                    pb = wp.vec3d(Pg[b, 0], Pg[b, 1], Pg[b, 2])
                    rb = wp.vec3d(Rg[b, 0], Rg[b, 1], Rg[b, 2])
                    block = stiffness_block(t, w, da, ta, ga, tb, pb, rb, grads[e, q, b])
                    for i in range(3):
                        for j in range(3):
                            K[e, 3 * a + i, 3 * b + j] = K[e, 3 * a + i, 3 * b + j] + block[i, j]
    energy[e] = E
    min_det[e] = jmin
    if mode != 0:
        # κ Bᵀ G⁻¹ B into the upper blocks, then each entry (its mirror below the block diagonal)
        for r in range(45):
            gb = wp.vec4d(B[e, 0, r], B[e, 1, r], B[e, 2, r], B[e, 3, r])
            gb = Gi @ gb
            for c in range((r // 3) * 3, 45):
                bc = wp.vec4d(B[e, 0, c], B[e, 1, c], B[e, 2, c], B[e, 3, c])
                K[e, r, c] = K[e, r, c] + kappa * wp.dot(gb, bc)
        for r in range(45):
            for c in range(45):
                v = K[e, r, c]
                if c // 3 < r // 3:
                    v = K[e, c, r]
                at = int(slot[e, 45 * r + c])
                if at >= 0:
                    wp.atomic_add(hess_data, at, v)


class WedgeKernel(fem.ElementKernel):
    """Warp arrays for one wedge mesh and its material, reused across calls; called as
    fem.ElementKernel is (whose ``retarget`` it shares)."""

    volumetric = "projected"

    def __init__(self, mesh: WedgeMesh, material: Material, device: str = "cpu"):
        self.mesh = mesh
        self.device = warp_device(device)
        if np.any(mesh.jacobians <= 0):
            raise ValueError("mesh: wedges must be positively oriented and curved midside nodes must not fold them")
        m = mesh.n_elements
        grads, det = mesh.quadrature_geometry
        w = WEDGE_WEIGHTS * det
        phi = np.column_stack([np.ones(len(WEDGE_POINTS)), WEDGE_POINTS])
        self.nq = len(WEDGE_POINTS)
        self._grads = wp.array(np.ascontiguousarray(grads), dtype=wp.vec3d, device=device)
        self._weights = wp.array(w, dtype=wp.float64, device=device)
        self._gram_inv = wp.array(np.linalg.inv(np.einsum("mq,qi,qj->mij", w, phi, phi)), dtype=wp.mat44d, device=device)
        self._els = wp.array(mesh.elements, dtype=wp.int32, device=device)
        self._params = wp.array(np.tile([material.c1, material.c2, material.c3, material.bulk], (m, 1)), dtype=wp.float64, device=device)
        self._phi = wp.array(phi, dtype=wp.float64, device=device)
        indptr, indices, slot = mesh.sparsity
        self._indptr, self._indices = indptr, indices
        self._slot = wp.array(slot.reshape(m, _DOFS * _DOFS).astype(np.int32), dtype=wp.int32, device=device)
        self.pattern_target = HessianTarget(self._slot, len(indices))
        self._energy = wp.zeros(m, dtype=wp.float64, device=device)
        self._grad = wp.zeros((m, _DOFS), dtype=wp.float64, device=device)
        self._mindet = wp.zeros(m, dtype=wp.float64, device=device)
        self._K = wp.zeros((m, _DOFS, _DOFS), dtype=wp.float64, device=device)
        self._B = wp.zeros((m, 4, _DOFS), dtype=wp.float64, device=device)
        self._empty1 = wp.zeros(1, dtype=wp.float64, device=device)

    def __call__(self, u: np.ndarray, hessian: bool = True, elements: bool = False, target: HessianTarget | None = None) -> ElementState:
        uw = wp.array(np.ascontiguousarray(u, dtype=np.float64), dtype=wp.vec3d, device=self.device)
        hessian = hessian or elements or target is not None
        to = target if target is not None else self.pattern_target
        self._grad.zero_()
        m = self.mesh.n_elements
        fixed = [uw, self._els, self._params, self._grads, self._weights, self._gram_inv, self._phi, self.nq, int(hessian), to.slot]
        # a wedge is ~6 P2 tetrahedra's work: chunks of a sixth of fem's MIN_CHUNK elements
        values = fem.launch_elements(_wedge_element, self.device, m, fem.MIN_CHUNK // 6, fixed,
                                     lambda data: [self._energy, self._grad, data, self._mindet, self._K, self._B],
                                     to.size if hessian else None, self._empty1)
        H = per_element = None
        if hessian and target is None:
            n = 3 * self.mesh.n_nodes
            H, values = sp.csr_matrix((values, self._indices, self._indptr), shape=(n, n)), None
        if elements:  # the kernel's upper blocks, mirrored
            Ku = self._K.numpy()
            below = (np.arange(_DOFS)[None, :] // 3) < (np.arange(_DOFS)[:, None] // 3)
            per_element = np.where(below, np.swapaxes(Ku, 1, 2), Ku)
        return ElementState(self._energy.numpy().copy(), self._grad.numpy().copy(), H, self._mindet.numpy().copy(), per_element, values)


class WedgeElasticTerm(ElasticTerm):
    """The hyperelastic energy of a wedge mesh, as an energy term for the Newton solver (the
    methods of fem.ElasticTerm, on :class:`WedgeKernel`)."""

    def __init__(self, mesh: WedgeMesh, material: Material, device: str = "cpu"):
        self.mesh = mesh
        self.kernel = WedgeKernel(mesh, material, device)
        self._targets: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
