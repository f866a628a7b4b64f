"""Lagrange finite elements (P1, or P2 on the same straight-sided tetrahedra) with the complete
electrode model (CEM), assembled without Python loops over elements.

Unknowns are the potential's degrees of freedom u (the nodes; for P2 the edges' midpoints
too) and the electrode potentials U (one per electrode except the ground, whose potential is
the reference U_g = 0). The CEM weak form:

    Σ_k σ_k ∫_k ∇u·∇w + Σ_l (1/z_l) ∫_{e_l} (u − U_l)(w − W_l) dS = Σ_l I_l W_l

gives the symmetric positive definite block system

    [ K + Σ_l M_l/z_l      −b_l/z_l  ] [u]   [0]
    [ −b_lᵀ/z_l         |e_l|/z_l    ] [U] = [I]

with M_l = ∫_{e_l} φ_i φ_j, b_l = ∫_{e_l} φ_i, K_k = ∫_k ∇φ ∇φᵀ (V_k ∇λ ∇λᵀ for P1).

P2 converges much faster than P1 on the same mesh, at ~7× the unknowns: on the box with disc
electrodes of tests/test_eit.py, P2 on 12 cells across errs 2.3 %, P1 on 24 cells 5.5 %
(test_p2_converges_faster_than_p1).
"""

from __future__ import annotations

import copy
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from .._warp import wp
from ..linalg import element_pattern
from ..mesh.electrodes import FACE_EDGES, ElectrodePatch
from ..mesh.kernels import p1_stiffness
from ..mesh.tetmesh import KEAST_POINTS, TET_EDGES, TetMesh, unique_edges

__all__ = ["CEMAssembler", "ORDERS", "Dofs", "dofs", "element_stiffness", "p2_gradients"]

ORDERS = (1, 2)


def _check_order(order: int) -> int:
    if order not in ORDERS:
        raise ValueError(f"order = {order!r}: element order must be one of {list(ORDERS)}")
    return int(order)


def p2_gradients(g: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """Gradients of the ten P2 basis functions (vertices, then edges in ``TET_EDGES`` order) at
    barycentrics ``lam`` (4,), from the barycentrics' gradients ``g`` (m, 4, 3): (m, 10, 3).
    ∇[λ_a(2λ_a − 1)] = (4λ_a − 1)∇λ_a, ∇[4λ_aλ_b] = 4(λ_a∇λ_b + λ_b∇λ_a)."""
    a, b = TET_EDGES.T
    vertex = (4 * lam - 1)[None, :, None] * g
    edge = 4 * (lam[a][None, :, None] * g[:, b] + lam[b][None, :, None] * g[:, a])
    return np.concatenate([vertex, edge], axis=1)


wp.set_module_options({"enable_backward": False})


def element_stiffness(mesh: TetMesh, order: int = 1) -> np.ndarray:
    """Unit-conductivity local stiffness ∫_k ∇φ_a·∇φ_b: (n_tets, 4, 4) for P1 (V_k ∇λ_a·∇λ_b),
    (n_tets, 10, 10) for P2."""
    if _check_order(order) == 1:
        return p1_stiffness(mesh.gradients, mesh.signed_volumes)
    g = mesh.gradients
    G = np.einsum("kai,kbi->kab", g, g).reshape(-1, 16)  # ∇λ_i·∇λ_j
    return (mesh.volumes[:, None] * (G @ _P2_FROM_GRADIENTS)).reshape(-1, 10, 10)


def _p2_stiffness_map() -> np.ndarray:
    """(16, 100): the P2 element stiffness per unit volume as a linear map of the products
    ∇λ_i·∇λ_j. ∇φ_a = Σ_i c_ai(λ) ∇λ_i with c linear in λ, so the 4-point rule (exact for the
    degree-2 integrand) gives K_ab = V/4 Σ_q Σ_ij c_ai(λ_q) c_bj(λ_q) ∇λ_i·∇λ_j: one matrix
    product per mesh instead of four (n, 10, 3) contractions."""
    eye = np.eye(4)[None]  # the barycentrics' "gradients" as unit vectors: p2_gradients gives c
    c = np.stack([p2_gradients(eye, lam)[0] for lam in KEAST_POINTS])  # (q, 10, 4)
    return np.einsum("qai,qbj->ijab", c, c).reshape(16, 100) / len(KEAST_POINTS)


_P2_FROM_GRADIENTS = _p2_stiffness_map()


@dataclass(frozen=True)
class Dofs:
    """The degrees of freedom of a mesh's elements of ``order``: ``elements`` (n_tets, 4 | 10),
    ``n`` in all. P2 numbers the nodes first (their dofs are the nodal values), then the unique
    edges (``edges`` (k, 2), sorted node pairs)."""

    order: int
    elements: np.ndarray
    edges: np.ndarray
    n: int
    n_nodes: int

    def faces(self, faces: np.ndarray) -> np.ndarray:
        """The dofs of boundary triangles ``faces`` (k, 3): (k, 3) for P1, (k, 6) for P2 (the
        vertices, then the edges in :data:`~jointsim.mesh.electrodes.FACE_EDGES` order)."""
        faces = np.asarray(faces)
        if self.order == 1:
            return faces
        key = self.edges[:, 0].astype(np.int64) * self.n_nodes + self.edges[:, 1]
        e = np.sort(faces[:, FACE_EDGES], axis=2)
        wanted = e[..., 0].astype(np.int64) * self.n_nodes + e[..., 1]
        at = np.minimum(np.searchsorted(key, wanted), len(key) - 1)
        if not np.array_equal(key[at], wanted):
            raise ValueError("faces: a face has an edge that is not an edge of the mesh's elements")
        return np.hstack([faces, self.n_nodes + at])


def dofs(mesh: TetMesh, order: int = 1) -> Dofs:
    """:class:`Dofs` of ``mesh`` for elements of ``order`` (1 or 2)."""
    if _check_order(order) == 1:
        return Dofs(1, mesh.tets, np.zeros((0, 2), np.int64), mesh.n_nodes, mesh.n_nodes)
    edges, index = unique_edges(mesh)
    return Dofs(2, np.hstack([mesh.tets, mesh.n_nodes + index]), edges, mesh.n_nodes + len(edges), mesh.n_nodes)


@dataclass(frozen=True, eq=False)
class CEMAssembler:
    """Holds the sparsity pattern of the CEM system for one mesh and electrode set, so that
    assembling for a new conductivity or contact impedance is a weighted ``bincount``.

    ``electrodes`` lists all electrodes; ``ground`` is the index of the reference one. The
    driven electrodes are the others, in order; the system has n_dofs + n_driven rows
    (n_dofs: the nodes for ``order`` 1, nodes and edges for 2)."""

    mesh: TetMesh
    electrodes: tuple[ElectrodePatch, ...]
    ground: int
    order: int = 1

    def __post_init__(self) -> None:
        L = len(self.electrodes) - 1
        if not 0 <= self.ground <= L:
            raise ValueError(f"ground = {self.ground}: must index one of the {L + 1} electrodes")
        if self.order == 2 and any(e.q1 is None for e in self.electrodes):
            raise ValueError("electrodes: order 2 needs the P2 moments of every patch (disc_patches(..., quadratic=True))")
        d = dofs(self.mesh, self.order)
        n = d.n
        el = d.elements
        rows, cols = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)]  # the electrodes' entries, after the elements'
        face_dofs = tuple(d.faces(e.faces) for e in self.electrodes)
        for l, f in enumerate(face_dofs):
            nf = f.shape[1]
            rows.append(np.repeat(f, nf, axis=1).ravel())
            cols.append(np.tile(f, (1, nf)).ravel())
            j = self._driven_index(l)
            if j is not None:
                rows += [f.ravel(), np.full(f.size, n + j), [n + j]]
                cols += [np.full(f.size, n + j), f.ravel(), [n + j]]
        N = n + L
        # the elements' part is remembered (a dataset's groups share the chamber's topology and
        # differ in their electrodes' faces), so a new electrode set sorts only its own entries
        indptr, indices, slot = element_pattern(el, N, np.concatenate(rows), np.concatenate(cols))
        object.__setattr__(self, "dofs", d)
        object.__setattr__(self, "_face_dofs", face_dofs)
        object.__setattr__(self, "_shape", (N, N))
        object.__setattr__(self, "_indices", indices)
        object.__setattr__(self, "_indptr", indptr.astype(np.int32))
        object.__setattr__(self, "_slot", slot)
        object.__setattr__(self, "_k_local", element_stiffness(self.mesh, self.order).ravel())

    def on(self, mesh: TetMesh, electrodes: Sequence[ElectrodePatch]) -> "CEMAssembler":
        """The assembler of ``mesh`` and ``electrodes``; where they have this one's topology (a
        morphed mesh: the same tets and electrode faces) the pattern is kept and only the element
        stiffnesses are recomputed (the pattern is a sort of every element's entries; with it and
        the solver's analysis kept, see :mod:`~jointsim.eit.forward` for what that saves)."""
        electrodes = tuple(electrodes)
        same = (
            mesh.tets.shape == self.mesh.tets.shape
            and np.array_equal(mesh.tets, self.mesh.tets)
            and len(electrodes) == len(self.electrodes)
            and all(np.array_equal(a.faces, b.faces) for a, b in zip(electrodes, self.electrodes))
        )
        if not same:
            return CEMAssembler(mesh, electrodes, self.ground, self.order)
        moved = copy.copy(self)
        object.__setattr__(moved, "mesh", mesh)
        object.__setattr__(moved, "electrodes", electrodes)
        object.__setattr__(moved, "_k_local", element_stiffness(mesh, self.order).ravel())
        return moved

    @property
    def pattern(self) -> tuple[np.ndarray, np.ndarray]:
        """(indptr, indices) of the CSR matrices :meth:`assemble` returns (columns sorted in each row)."""
        return self._indptr, self._indices

    def same_pattern(self, other: "CEMAssembler") -> bool:
        """Whether ``other`` assembles into this one's sparsity pattern (one is :meth:`on` the other)."""
        return other._indices is self._indices or (
            np.array_equal(other._indptr, self._indptr) and np.array_equal(other._indices, self._indices)
        )

    @property
    def n_driven(self) -> int:
        return len(self.electrodes) - 1

    @property
    def n_dofs(self) -> int:
        """Unknowns of the potential (the system's first rows)."""
        return self.dofs.n

    @property
    def size(self) -> int:
        return self._shape[0]

    def _driven_index(self, l: int) -> int | None:
        if l == self.ground:
            return None
        return l if l < self.ground else l - 1

    def electrode_values(self, z: np.ndarray) -> np.ndarray:
        """The contact-impedance entries, in pattern order, for z (n_electrodes,) in Ω·m²."""
        vals = []
        for l, e in enumerate(self.electrodes):
            m1, m2 = e.moments(self.order)
            vals.append((m2 / z[l]).ravel())
            if self._driven_index(l) is not None:
                b = -(m1 / z[l]).ravel()
                vals += [b, b, [e.total_area / z[l]]]
        return np.concatenate(vals)

    def assemble(self, sigma: np.ndarray | float, z: np.ndarray) -> sp.csr_matrix:
        """The CEM matrix for element conductivities ``sigma`` (n_tets,) in S/m and contact
        impedances ``z`` (n_electrodes,) in Ω·m²."""
        sigma = np.broadcast_to(np.asarray(sigma, float), (self.mesh.n_tets,))
        z = np.asarray(z, float)
        if z.shape != (len(self.electrodes),):
            raise ValueError(f"z: expected {len(self.electrodes)} contact impedances, got shape {z.shape}")
        if not (z > 0).all():
            raise ValueError("z: contact impedances must be > 0 Ω·m²")
        if not (np.isfinite(sigma).all() and (sigma > 0).all()):
            raise ValueError("sigma: element conductivities must be finite and > 0 S/m")
        nl = self.dofs.elements.shape[1]
        w = np.concatenate([np.repeat(sigma, nl * nl) * self._k_local, self.electrode_values(z)])
        data = np.bincount(self._slot, weights=w, minlength=len(self._indices))
        return sp.csr_matrix((data, self._indices, self._indptr), shape=self._shape)

    def electrode_currents(self, u: np.ndarray, U: np.ndarray, z: np.ndarray) -> np.ndarray:
        """Current (A) through every electrode into the saline, ground included:
        I_l = (|e_l|·U_l − ∫_{e_l} u dS)/z_l. u (n_dofs, k), U (n_driven, k) → (n_el, k)."""
        u = np.atleast_2d(u.T).T
        U = np.atleast_2d(U.T).T
        out = np.empty((len(self.electrodes), u.shape[1]))
        for l, (e, f) in enumerate(zip(self.electrodes, self._face_dofs)):
            j = self._driven_index(l)
            Ul = 0.0 if j is None else U[j]
            integral = np.einsum("fa,fak->k", e.moments(self.order)[0], u[f])
            out[l] = (e.total_area * Ul - integral) / z[l]
        return out
