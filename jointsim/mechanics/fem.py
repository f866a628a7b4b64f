"""Quadratic (P2, 10-node) tetrahedra for finite-strain hyperelasticity, with the element
energy, gradient and Hessian computed in a Warp kernel (CPU by default, CUDA when asked).

Locking: the silicone is nearly incompressible (κ/μ = 1000, ν = 0.4995). Linear tetrahedra lock
outright; quadratic ones with the penalty U(J) = κ/2 (J − 1)² at every quadrature point
("pointwise", the default) still lock in bending: a 2 mm cantilever with two elements through
its thickness deflects 13 % too little (six elements: 3 %; results/locking_cantilever.md). ``volumetric="mean_dilatation"`` is the
mixed u–p form with an element-wise constant pressure (P2–P0), the pressure condensed out: the
volumetric energy V·U(θ) of each element's volume ratio θ = v/V = Σ_q w_q J_q (Nagtegaal–Parks–
Rice / Simo–Taylor–Pister), which adds U''(θ)/V · B Bᵀ (B = ∂v/∂u) to the element matrix; the
isochoric part stays pointwise. The same cantilever is then within 1.5 % of beam theory at two
elements (tests/test_mechanics.py), but a constant pressure per element converges only to first
order and is too soft with one element through a thickness (the cantilever: +46 %).
On the dome (a thick shell under an apex load; results/dome_apex_load.md) against an
independent axisymmetric Taylor–Hood reference, the pointwise form with two or three layers is
within 0.5 % at κ = 10 μ and 2–3.5 % stiff at 1000 μ, mean dilatation 4–6.5 % soft (20 % on one
layer): there the pointwise form is the right one. results/mechanics_benchmark.md: its contact
force under mesh refinement (2 % at 92 rim vertices, two layers).

The element Hessian uses the material tangent A = ∂P/∂F in closed form, contracted with each pair
of nodes' shape-function gradients (materials.py). Each element's 30 × 30 matrix is accumulated in the kernel
(its upper block triangle, mirrored) and added straight into the values of the global sparse
pattern, or of a Newton system's free upper triangle (:class:`HessianTarget`), so no
(m, 30, 30) array is written and re-read for assembly. The per-element matrices
are still available for the positive semi-definite projection (eigenvalues clamped at 0), the
Newton solver's fallback when the shifted Hessian fails. On the CPU the elements are split into
KERNEL_THREADS chunks launched from as many threads (Warp releases the GIL while a CPU kernel
runs): with 2 cores the kernel's share of a 92/2 press step is 1.18× faster than on one thread
(results/mechanics_solvers.md).
"""

from __future__ import annotations

import os
import weakref
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import scipy.sparse as sp
from threadpoolctl import threadpool_limits

from .._cores import available_cores
from .._warp import wp
from ..linalg import element_pattern
from ..mesh.tetmesh import KEAST_POINTS, TET_EDGES, TetMesh, unique_edges
from .materials import (
    Material,
    first_piola,
    stiffness_block,
    strain_energy,
    tangent_with_pressure,
)
from .newton import NewtonSystem, SystemValues

__all__ = ["P2Mesh", "tet_fields", "principal_green_strain", "ElementState", "HessianTarget", "ElementKernel", "ElasticTerm", "project_psd", "assemble_hessian", "assemble_gradient", "warp_device"]

# the element loops are short but deeply nested: unrolling them makes compile times explode,
# and no adjoint kernels are needed (derivatives are formed explicitly)
wp.set_module_options({"max_unroll": 1, "enable_backward": False})

_MatN = wp.types.matrix(shape=(10, 3), dtype=wp.float64)

# Warp runs a CPU kernel on one thread but releases the GIL while it runs, so on the CPU the
# elements are split into this many contiguous chunks launched from as many threads, each with
# its own Hessian buffer (neighbouring elements add into the same entries), summed after. One
# on a single core; more than 4 chunks would spend more on the buffers than they save
KERNEL_THREADS = max(1, min(4, available_cores()))
MIN_CHUNK = 1024  # elements: below this a launch is too short to share
_POOL: tuple[int, ThreadPoolExecutor] | None = None  # (the process it was made in, the pool)


def _pool() -> ThreadPoolExecutor:
    """The kernel threads of this process. A forked child gets a pool of its own: the parent's
    copied pool has no threads there, and a chunk submitted to it would never run."""
    global _POOL
    if _POOL is None or _POOL[0] != os.getpid():
        _POOL = (os.getpid(), ThreadPoolExecutor(max_workers=KERNEL_THREADS, thread_name_prefix="jointsim-kernel"))
    return _POOL[1]


def warp_device(device: str, name: str = "device") -> str:
    """``device`` when Warp can run the element kernel there ("cpu", "cuda", "cuda:0", …), else a
    ValueError naming the parameter (``name``) and the devices this machine has (Warp's own
    error for a missing CUDA driver says neither)."""
    if not isinstance(device, str):
        raise ValueError(f"{name} = {device!r}: a Warp device name such as 'cpu' or 'cuda:0'")
    try:
        wp.get_device(device)
    except (RuntimeError, ValueError):
        have = ", ".join(repr(d.alias) for d in wp.get_devices())
        raise ValueError(f"{name} = {device!r}: not a Warp device on this machine (available: {have})") from None
    return device


# the element quadrature: Keast's 4-point degree-2 rule (barycentric points, weights summing to 1)
QUAD_BARY = KEAST_POINTS
QUAD_W = np.full(4, 0.25)


def principal_green_strain(F: np.ndarray) -> np.ndarray:
    """Largest principal Green–Lagrange strain of E = (FᵀF − I)/2 at each of the deformation
    gradients F (m, 3, 3): (m,)."""
    return np.linalg.eigvalsh(0.5 * (np.swapaxes(F, 1, 2) @ F - np.eye(3)))[:, -1]


def tet_fields(nodes: np.ndarray, tets: np.ndarray, u: np.ndarray, material) -> dict[str, np.ndarray]:
    """Strain and stress per linear tetrahedron (m,) of ``tets`` over ``nodes`` (n, 3) displaced by
    ``u`` (n, 3), each from its corners' constant F, in ``material``
    (:meth:`~jointsim.mechanics.materials.Material.cauchy_stress`): the largest principal
    Green–Lagrange strain, the von Mises stress √(3/2 s:s) Pa and the mean stress tr σ/3 Pa.
    For output (the membrane's VTU, split into corner tetrahedra): the element's own field varies
    inside it."""
    X = nodes[tets]
    x = X + u[tets]
    dX = np.swapaxes(X[:, 1:] - X[:, :1], 1, 2)
    dx = np.swapaxes(x[:, 1:] - x[:, :1], 1, 2)
    F = dx @ np.linalg.inv(dX)
    sigma = material.cauchy_stress(F)
    mean = np.trace(sigma, axis1=1, axis2=2) / 3
    dev = sigma - mean[:, None, None] * np.eye(3)
    return {"green_strain_max": principal_green_strain(F), "von_mises_stress": np.sqrt(1.5 * np.einsum("mij,mij->m", dev, dev)),
            "mean_stress": mean}


def peak_green_strain(F: np.ndarray) -> float:
    """Largest principal Green–Lagrange strain E = (FᵀF − I)/2 over deformation gradients F (m, 3, 3)."""
    return float(principal_green_strain(F).max())


@dataclass(frozen=True, eq=False)
class P2Mesh:
    """``nodes`` (n, 3) reference positions in m; ``tets`` (m, 10): corners 0–3 then the midside
    nodes of edges 01, 02, 03, 12, 13, 23. Isoparametric: a midside node off its edge's midpoint
    curves the element (the kernel takes the geometry's Jacobian at each quadrature point)."""

    nodes: np.ndarray
    tets: np.ndarray

    @classmethod
    def from_linear(cls, mesh: TetMesh, place: Callable[[np.ndarray], np.ndarray] | None = None) -> "P2Mesh":
        """The P2 mesh on ``mesh``'s corners; ``place`` maps the ends (k, 2, 3) of its k edges to
        their midside nodes (k, 3) (None: the midpoints, straight-sided elements)."""
        edges, index = unique_edges(mesh)
        ends = mesh.nodes[edges]
        points = ends.mean(axis=1) if place is None else np.asarray(place(ends), float)
        nodes = np.vstack([mesh.nodes, points])
        tets = np.hstack([mesh.tets, mesh.n_nodes + index])
        return cls(nodes, tets.astype(np.int32))

    @cached_property
    def jacobians(self) -> np.ndarray:
        """det ∂X/∂ξ (m, 4) at the quadrature points: six times the local volume scale, > 0 in a
        valid (curved) element."""
        l = QUAD_BARY
        # ∂N/∂ξ (4 points, 10 nodes, 3) with ξ = (λ1, λ2, λ3), λ0 = 1 − Σξ; the kernel's
        # _shape_gradients at the same points
        dl = np.array([[-1.0, -1, -1], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
        corner = (4 * l[:, :, None] - 1) * dl[None]
        a, b = TET_EDGES.T
        edge = 4 * (l[:, a, None] * dl[b] + l[:, b, None] * dl[a])
        Gr = np.concatenate([corner, edge], axis=1)
        J = np.einsum("mni,qnk->mqik", self.nodes[self.tets], Gr)
        return np.linalg.det(J)

    @cached_property
    def corner_gradient_map(self) -> np.ndarray:
        """(m, 3, 3) inverse of each element's corner edge matrix [X1 − X0, X2 − X0, X3 − X0]: the
        map from the deformed corner edges to the element's straight-sided F, kept because every
        equilibrium's strain report needs it (its inversion cost a third of that report)."""
        p = self.nodes[self.tets[:, :4]]
        return np.linalg.inv(np.swapaxes(p[:, 1:] - p[:, :1], 1, 2))

    def peak_green_strain(self, u: np.ndarray) -> float:
        """Largest principal Green–Lagrange strain over the elements at displacement ``u``
        (n, 3), from each element's straight-sided F (its corner nodes' gradient)."""
        x = (self.nodes + u)[self.tets[:, :4]]
        return peak_green_strain(np.swapaxes(x[:, 1:] - x[:, :1], 1, 2) @ self.corner_gradient_map)

    @property
    def n_nodes(self) -> int:
        return len(self.nodes)

    @property
    def n_tets(self) -> int:
        return len(self.tets)

    @property
    def elements(self) -> np.ndarray:
        """The element connectivity, by the name every membrane mesh has (wedge.WedgeMesh's)."""
        return self.tets

    @property
    def n_elements(self) -> int:
        return len(self.tets)

    @property
    def corner_tets(self) -> np.ndarray:
        """The linear tetrahedra of the corners (m, 4)."""
        return self.tets[:, :4]

    @cached_property
    def boundary_faces(self) -> np.ndarray:
        """Boundary faces as 6-node triangles (k, 6): corners a, b, c then midpoints ab, bc, ca,
        oriented outward."""
        faces = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])
        edge_of = {(0, 1): 4, (0, 2): 5, (0, 3): 6, (1, 2): 7, (1, 3): 8, (2, 3): 9}
        mids = np.array([[edge_of[tuple(sorted((f[i], f[(i + 1) % 3])))] for i in range(3)] for f in faces])
        corner = self.tets[:, faces].reshape(-1, 3)
        mid = self.tets[:, mids].reshape(-1, 3)
        key = np.sort(corner, axis=1)
        _, inv, cnt = np.unique(key, axis=0, return_inverse=True, return_counts=True)
        b = cnt[inv.ravel()] == 1
        return np.hstack([corner[b], mid[b]])

    @cached_property
    def sparsity(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(indptr, indices, slot) of the 3n × 3n Hessian: element entry (e, r, c) adds into
        data[slot[e*900 + r*30 + c]]."""
        dof = (3 * self.tets[:, :, None] + np.arange(3)).reshape(-1, 30).astype(np.int64)
        return element_pattern(dof, 3 * self.n_nodes)


_Mat30 = wp.types.matrix(shape=(30, 30), dtype=wp.float64)
_Vec30 = wp.types.vector(length=30, dtype=wp.float64)

# how the volumetric energy U(J) = κ/2 (J − 1)² is integrated: at each quadrature point, or once
# per element from the element's volume ratio θ = v/V (mean dilatation; module docstring)
VOLUMETRIC = ("mean_dilatation", "pointwise")

# what the element kernel computes besides the energy and gradient
NO_HESSIAN, ASSEMBLED, WITH_ELEMENTS = 0, 1, 2


@wp.func
def _shape_gradients(l: wp.vec4d, g0: wp.vec3d, g1: wp.vec3d, g2: wp.vec3d, g3: wp.vec3d) -> _MatN:
    """∇N (10, 3) of the P2 shape functions at barycentric point l, from the corners' ∇λ."""
    one = wp.float64(1.0)
    four = wp.float64(4.0)
    G = _MatN()
    # corner shape functions λ(2λ − 1) and edge functions 4 λa λb, differentiated
    gc0 = (four * l[0] - one) * g0
    gc1 = (four * l[1] - one) * g1
    gc2 = (four * l[2] - one) * g2
    gc3 = (four * l[3] - one) * g3
    ge01 = four * (l[0] * g1 + l[1] * g0)
    ge02 = four * (l[0] * g2 + l[2] * g0)
    ge03 = four * (l[0] * g3 + l[3] * g0)
    ge12 = four * (l[1] * g2 + l[2] * g1)
    ge13 = four * (l[1] * g3 + l[3] * g1)
    ge23 = four * (l[2] * g3 + l[3] * g2)
    for k in range(3):
        G[0, k] = gc0[k]
        G[1, k] = gc1[k]
        G[2, k] = gc2[k]
        G[3, k] = gc3[k]
        G[4, k] = ge01[k]
        G[5, k] = ge02[k]
        G[6, k] = ge03[k]
        G[7, k] = ge12[k]
        G[8, k] = ge13[k]
        G[9, k] = ge23[k]
    return G


@wp.func
def _geometry_jacobian(X: wp.array(dtype=wp.vec3d), tets: wp.array2d(dtype=wp.int32), e: int, Gr: _MatN) -> wp.mat33d:
    """∂X/∂ξ of the element's (possibly curved) reference map at a point, from ∂N/∂ξ (10, 3)."""
    Jx = wp.mat33d()
    for n in range(10):
        Jx += wp.outer(X[tets[e, n]], wp.vec3d(Gr[n, 0], Gr[n, 1], Gr[n, 2]))
    return Jx


@wp.func
def _physical_gradients(Gr: _MatN, Jinv: wp.mat33d) -> _MatN:
    """∇_X N = ∂N/∂ξ · (∂X/∂ξ)⁻¹."""
    G = _MatN()
    for n in range(10):
        for k in range(3):
            G[n, k] = Gr[n, 0] * Jinv[0, k] + Gr[n, 1] * Jinv[1, k] + Gr[n, 2] * Jinv[2, k]
    return G


@wp.func
def _deformation_gradient(u: wp.array(dtype=wp.vec3d), tets: wp.array2d(dtype=wp.int32), e: int, G: _MatN) -> wp.mat33d:
    F = wp.identity(n=3, dtype=wp.float64)
    for n in range(10):
        F += wp.outer(u[tets[e, n]], wp.vec3d(G[n, 0], G[n, 1], G[n, 2]))
    return F


@wp.kernel
def _p2_element(
    X: wp.array(dtype=wp.vec3d),
    u: wp.array(dtype=wp.vec3d),
    tets: wp.array2d(dtype=wp.int32),
    params: wp.array2d(dtype=wp.float64),
    qbary: wp.array(dtype=wp.vec4d),
    qw: wp.array(dtype=wp.float64),
    mode: int,
    mean_dilatation: int,
    slot: wp.array2d(dtype=wp.int32),
    offset: int,
    energy: wp.array(dtype=wp.float64),
    grad: wp.array2d(dtype=wp.float64),
    hess_data: wp.array(dtype=wp.float64),
    hess: wp.array3d(dtype=wp.float64),
    min_det: wp.array(dtype=wp.float64),
):
    e = wp.tid() + offset
    # isoparametric: the geometry is interpolated by the same P2 functions, so curved (midside
    # nodes off the chord) elements get their Jacobian at each quadrature point. ξ = (λ1, λ2, λ3)
    one = wp.float64(1.0)
    zero = wp.float64(0.0)
    gx0 = wp.vec3d(-one, -one, -one)
    gx1 = wp.vec3d(one, zero, zero)
    gx2 = wp.vec3d(zero, one, zero)
    gx3 = wp.vec3d(zero, zero, one)
    sixth = one / wp.float64(6.0)
    c1 = params[e, 0]
    c2 = params[e, 1]
    c3 = params[e, 2]
    kappa = params[e, 3]
    E = wp.float64(0.0)
    jmin = wp.float64(1.0e30)
    K = _Mat30()
    # mean dilatation: the element's pressure p = U'(θ) from its volume ratio θ = v/V, a pass
    # over the quadrature points before the main one (the pointwise form needs neither)
    vol = wp.float64(0.0)
    theta = one
    if mean_dilatation != 0:
        v = wp.float64(0.0)
        for q in range(4):
            Gr = _shape_gradients(qbary[q], gx0, gx1, gx2, gx3)
            Jx = _geometry_jacobian(X, tets, e, Gr)
            dV = qw[q] * wp.determinant(Jx) * sixth
            vol += dV
            v += dV * wp.determinant(_deformation_gradient(u, tets, e, _physical_gradients(Gr, wp.inverse(Jx))))
        theta = v / vol
    p_elem = kappa * (theta - one)
    k_local = kappa
    if mean_dilatation != 0:
        k_local = wp.float64(0.0)
    B = _Vec30()  # ∂v/∂u: the element volume's gradient, Σ_q w_q J_q F_q^{-T} ∇N
    for q in range(4):
        Gr = _shape_gradients(qbary[q], gx0, gx1, gx2, gx3)
        Jx = _geometry_jacobian(X, tets, e, Gr)
        w = qw[q] * wp.determinant(Jx) * sixth
        G = _physical_gradients(Gr, wp.inverse(Jx))
        F = _deformation_gradient(u, tets, e, G)
        J = wp.determinant(F)
        jmin = wp.min(jmin, J)
        p = p_elem
        if mean_dilatation == 0:
            p = kappa * (J - one)
            E += w * strain_energy(F, c1, c2, c3, kappa)
        else:
            E += w * strain_energy(F, c1, c2, c3, wp.float64(0.0))
        t = tangent_with_pressure(F, c1, c2, c3, p, k_local)
        P = first_piola(t)
        for n in range(10):
            for i in range(3):
                grad[e, 3 * n + i] += w * (P[i, 0] * G[n, 0] + P[i, 1] * G[n, 1] + P[i, 2] * G[n, 2])
            if mean_dilatation != 0:
                dv = w * J * (t.T @ wp.vec3d(G[n, 0], G[n, 1], G[n, 2]))
                for i in range(3):
                    B[3 * n + i] = B[3 * n + i] + dv[i]
        if mode != NO_HESSIAN:
            # the tangent contracted with two nodes' gradients, block (a, b) of K (materials.py):
            # w [d_a ⊗ p_b + t_a ⊗ r_b + c_outer t_b ⊗ t_a + c_e (G_a·G_b) I], from the per-node
            # d = D G, t = F^{-T} G, p = c_dd d − c_dt t, r = c_tt t − c_dt F G formed once
            # (1.5× faster than contracting the tangent's nine columns pair by pair: a scratch
            # comparison on the 92/2 membrane, in issue 4's notes)
            Dg = _MatN()
            Tg = _MatN()
            Pg = _MatN()
            Rg = _MatN()
            for a in range(10):
                ga = wp.vec3d(G[a, 0], G[a, 1], G[a, 2])
                da = t.D @ ga
                ta = t.T @ ga
                pa = t.c_dd * da - t.c_dt * ta
                ra = t.c_tt * ta - t.c_dt * (t.F @ ga)
                for i in range(3):
                    Dg[a, i] = da[i]
                    Tg[a, i] = ta[i]
                    Pg[a, i] = pa[i]
                    Rg[a, i] = ra[i]
            for a in range(10):  # blocks b ≥ a (K is symmetric)
                da = wp.vec3d(Dg[a, 0], Dg[a, 1], Dg[a, 2])
                ta = wp.vec3d(Tg[a, 0], Tg[a, 1], Tg[a, 2])
                ga = wp.vec3d(G[a, 0], G[a, 1], G[a, 2])
                for b in range(a, 10):
                    tb = wp.vec3d(Tg[b, 0], Tg[b, 1], Tg[b, 2])
                    pb = wp.vec3d(Pg[b, 0], Pg[b, 1], Pg[b, 2])
                    rb = wp.vec3d(Rg[b, 0], Rg[b, 1], Rg[b, 2])
                    block = stiffness_block(t, w, da, ta, ga, tb, pb, rb, wp.vec3d(G[b, 0], G[b, 1], G[b, 2]))
                    for i in range(3):
                        for j in range(3):
                            K[3 * a + i, 3 * b + j] = K[3 * a + i, 3 * b + j] + block[i, j]
    if mean_dilatation != 0:
        # V·U(θ), and its stiffness U''(θ)/V · B Bᵀ (θ = v/V, ∂v/∂u = B)
        E += vol * wp.float64(0.5) * kappa * (theta - one) * (theta - one)
        if mode != NO_HESSIAN:
            kv = kappa / vol
            for a in range(10):
                for b in range(a, 10):
                    for i in range(3):
                        for j in range(3):
                            K[3 * a + i, 3 * b + j] = K[3 * a + i, 3 * b + j] + kv * B[3 * a + i] * B[3 * b + j]
    energy[e] = E
    min_det[e] = jmin
    if mode != NO_HESSIAN:
        for a in range(10):
            for b in range(a + 1, 10):
                for i in range(3):
                    for j in range(3):
                        K[3 * b + j, 3 * a + i] = K[3 * a + i, 3 * b + j]
        for r in range(30):
            for c in range(30):
                at = int(slot[e, 30 * r + c])
                if at >= 0:  # −1: an entry the target leaves out
                    wp.atomic_add(hess_data, at, K[r, c])
                if mode == WITH_ELEMENTS:
                    hess[e, r, c] = K[r, c]


@dataclass
class ElementState:
    """Per-element energy (m,), gradient (m, 30) and smallest det F over the quadrature points
    (m,) (≤ 0: the element inverted); the assembled Hessian (3n × 3n CSR on the mesh's pattern)
    or None; the per-element Hessians (m, 30, 30) when asked for, else None; the Hessian's
    values assembled into a :class:`HessianTarget` when one was given (``hessian`` is then None)."""

    energy: np.ndarray
    grad: np.ndarray
    hessian: sp.csr_matrix | None
    min_det: np.ndarray
    element_hessians: np.ndarray | None = None
    values: np.ndarray | None = None


@dataclass(frozen=True, eq=False)
class HessianTarget:
    """Where the kernel adds the element Hessians: entry (e, r, c) into ``values[slot[e, 30 r + c]]``
    of a values array of length ``size``, or nowhere where the slot is −1. The mesh's own CSR
    pattern is one target; a Newton system's free upper triangle is another, which the kernel
    then fills directly (no full matrix assembled, half the additions, no gather after)."""

    slot: wp.array
    size: int


class ElementKernel:
    """Warp arrays for one P2 mesh and per-element material parameters, reused across calls."""

    def __init__(
        self,
        mesh: P2Mesh,
        materials: Material | list[Material],
        material_of: np.ndarray | None = None,
        device: str = "cpu",
        volumetric: str = "pointwise",
    ):
        if volumetric not in VOLUMETRIC:
            raise ValueError(f"volumetric = {volumetric!r}: allowed values are {VOLUMETRIC}")
        self.mesh = mesh
        self.device = warp_device(device)
        self.volumetric = volumetric
        mats = [materials] if isinstance(materials, Material) else list(materials)
        idx = np.zeros(mesh.n_tets, int) if material_of is None else np.asarray(material_of)
        params = np.array([[m.c1, m.c2, m.c3, m.bulk] for m in mats])[idx]
        if np.any(mesh.jacobians <= 0):
            raise ValueError("mesh: elements must be positively oriented (call TetMesh.oriented()) and curved midside nodes must not fold them")
        self._X = wp.array(mesh.nodes, dtype=wp.vec3d, device=device)
        self._tets = wp.array(mesh.tets, dtype=wp.int32, device=device)
        self._params = wp.array(params, dtype=wp.float64, device=device)
        self._qb = wp.array(QUAD_BARY, dtype=wp.vec4d, device=device)
        self._qw = wp.array(QUAD_W, dtype=wp.float64, device=device)
        m = mesh.n_tets
        indptr, indices, slot = mesh.sparsity
        self._indptr, self._indices = indptr, indices
        self._slot = wp.array(slot.reshape(m, 900).astype(np.int32), dtype=wp.int32, device=device)
        self.pattern_target = HessianTarget(self._slot, len(indices))
        self._energy = wp.zeros(m, dtype=wp.float64, device=device)
        self._grad = wp.zeros((m, 30), dtype=wp.float64, device=device)
        self._empty1 = wp.zeros(1, dtype=wp.float64, device=device)
        self._empty3 = wp.zeros((1, 1, 1), dtype=wp.float64, device=device)
        self._mindet = wp.zeros(m, dtype=wp.float64, device=device)

    def retarget(self, pattern_slot: np.ndarray, size: int) -> HessianTarget:
        """The target that puts entry k of the mesh's CSR pattern at ``pattern_slot[k]`` of a
        values array of length ``size`` (−1: left out)."""
        _, _, slot = self.mesh.sparsity
        mapped = np.asarray(pattern_slot, np.int64)[slot].reshape(self.mesh.n_elements, -1)
        if mapped.max() >= size:
            raise ValueError(f"pattern_slot: slots must be < size = {size}")
        return HessianTarget(wp.array(mapped.astype(np.int32), dtype=wp.int32, device=self.device), int(size))

    def __call__(self, u: np.ndarray, hessian: bool = True, elements: bool = False, target: HessianTarget | None = None) -> ElementState:
        """The element quantities at displacement ``u`` (n, 3); ``elements``: also the
        per-element Hessians (for the PSD projection); ``target``: the Hessian assembled there
        (returned as ``values``) instead of as a matrix on the mesh's pattern."""
        uw = wp.array(np.ascontiguousarray(u, dtype=np.float64), dtype=wp.vec3d, device=self.device)
        hessian = hessian or target is not None
        to = target if target is not None else self.pattern_target
        self._grad.zero_()
        mode = NO_HESSIAN if not hessian else WITH_ELEMENTS if elements else ASSEMBLED
        m = self.mesh.n_tets
        hess = wp.zeros((m, 30, 30), dtype=wp.float64, device=self.device) if elements else self._empty3
        fixed = [self._X, uw, self._tets, self._params, self._qb, self._qw, mode, int(self.volumetric == "mean_dilatation"), to.slot]
        values = launch_elements(_p2_element, self.device, m, MIN_CHUNK, fixed, lambda data: [self._energy, self._grad, data, hess, self._mindet],
                                 to.size if hessian else None, self._empty1)
        H = None
        if hessian and target is None:
            n = 3 * self.mesh.n_nodes
            H, values = sp.csr_matrix((values, self._indices, self._indptr), shape=(n, n)), None
        return ElementState(
            self._energy.numpy().copy(),
            self._grad.numpy().copy(),
            H,
            self._mindet.numpy().copy(),
            hess.numpy() if elements else None,
            values,
        )


def launch_elements(kernel, device: str, m: int, min_chunk: int, inputs: list, outputs: Callable[[wp.array], list], size: int | None,
                    empty: wp.array) -> np.ndarray | None:
    """Launch an element ``kernel`` over the ``m`` elements: ``inputs`` then the chunk's first
    element; ``outputs(data)``: its outputs, with ``data`` the chunk's Hessian values buffer of
    length ``size`` (None: no Hessian; ``empty`` is passed instead). On the CPU the elements are
    split into up to KERNEL_THREADS chunks of at least ``min_chunk``, launched from as many
    threads. The Hessian values summed over the chunks, or None."""
    cpu = device == "cpu"
    chunks = max(1, min(KERNEL_THREADS, m // min_chunk)) if cpu else 1
    bounds = np.linspace(0, m, chunks + 1).astype(int)
    data = [empty] * chunks
    host: list[np.ndarray] = []
    if size is not None:
        # fresh buffers per call: the returned matrix must not change under a caller that
        # keeps it while another Hessian is evaluated. On the CPU the kernel writes straight
        # into numpy's (lazily zeroed) memory; on a GPU into one device buffer, copied back
        if cpu:
            host = [np.zeros(size) for _ in range(chunks)]
            data = [wp.array(h, dtype=wp.float64, device=device, copy=False) for h in host]
        else:
            data = [wp.zeros(size, dtype=wp.float64, device=device)]

    def launch(k: int) -> None:
        wp.launch(kernel, dim=int(bounds[k + 1] - bounds[k]), inputs=inputs + [int(bounds[k])], outputs=outputs(data[k]), device=device)

    if chunks == 1:
        launch(0)
    else:
        for f in [_pool().submit(launch, k) for k in range(chunks)]:
            f.result()
    if size is None:
        return None
    values = host[0] if cpu else data[0].numpy()
    for h in host[1:]:  # the other chunks' buffers (CPU only: elsewhere one chunk)
        values += h
    return values


def project_psd(H: np.ndarray) -> np.ndarray:
    """Clamp each element Hessian's negative eigenvalues to zero: (m, 30, 30) → same."""
    # thousands of 30 × 30 problems: a threaded LAPACK only adds synchronisation (3-6x slower
    # on 2 busy cores, measured), so BLAS runs single-threaded here
    with threadpool_limits(1, user_api="blas"):
        w, V = np.linalg.eigh(H)
    if (w >= 0).all():
        return H
    return np.einsum("mij,mj,mkj->mik", V, np.maximum(w, 0.0), V)


def assemble_hessian(mesh: P2Mesh, H: np.ndarray) -> sp.csr_matrix:
    indptr, indices, slot = mesh.sparsity
    data = np.bincount(slot, weights=H.ravel(), minlength=len(indices))
    n = 3 * mesh.n_nodes
    return sp.csr_matrix((data, indices, indptr), shape=(n, n))


def assemble_gradient(mesh: P2Mesh, g: np.ndarray) -> np.ndarray:
    dof = (3 * mesh.elements[:, :, None] + np.arange(3)).reshape(-1)
    return np.bincount(dof, weights=g.ravel(), minlength=3 * mesh.n_nodes)


class ElasticTerm:
    """The hyperelastic energy of a P2 mesh, as an energy term for the Newton solver."""

    def __init__(
        self,
        mesh: P2Mesh,
        materials: Material | list[Material],
        material_of: np.ndarray | None = None,
        device: str = "cpu",
        volumetric: str = "pointwise",
    ):
        self.mesh = mesh
        self.kernel = ElementKernel(mesh, materials, material_of, device, volumetric)
        self._targets: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # per Newton system

    def evaluate(self, u: np.ndarray, hessian: bool):
        return self._result(u, self.kernel(u, hessian))

    def evaluate_into(self, u: np.ndarray, system: NewtonSystem):
        """As :meth:`evaluate` with the Hessian, given as ``system``'s values: the kernel adds
        straight into them, which on the 92/2 membrane makes a Newton iteration's Hessian values
        1.32× faster than the matrix on the mesh's pattern and the system's gather from it
        (results/mechanics_assembly.md, medians of 10 interleaved)."""
        target = self._targets.get(system)
        if target is None:
            indptr, indices, _ = self.mesh.sparsity
            target = self._targets[system] = self.kernel.retarget(system.pattern_slots(indptr, indices), system.n_kept)
        return self._result(u, self.kernel(u, target=target), system)

    def _result(self, u: np.ndarray, s: ElementState, system: NewtonSystem | None = None):
        ok = bool((s.min_det > 0).all() and np.isfinite(s.energy).all())
        if not ok:
            return np.inf, np.zeros(u.size), None, False
        g = assemble_gradient(self.mesh, s.grad)
        H = s.hessian if s.values is None else SystemValues(system, s.values)
        return float(s.energy.sum()), g, H, True

    def projected_hessian(self, u: np.ndarray) -> sp.csr_matrix:
        """The Hessian with each element's negative eigenvalues clamped to zero (SPD-projected)."""
        return assemble_hessian(self.mesh, project_psd(self.kernel(u, True, elements=True).element_hessians))
