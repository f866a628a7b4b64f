"""P1 finite elements with the complete electrode model (CEM), assembled without Python loops
over elements.

Unknowns are the nodal potentials u (n_nodes) and the electrode potentials U (one per
electrode except the ground, whose potential is the reference U_g = 0). The CEM weak form:

    Σ_k σ_k ∫_k ∇u·∇w + Σ_l (1/z_l) ∫_{e_l} (u − U_l)(w − W_l) dS = Σ_l I_l W_l

gives the symmetric positive definite block system

    [ K + Σ_l M_l/z_l      −b_l/z_l  ] [u]   [0]
    [ −b_lᵀ/z_l         |e_l|/z_l    ] [U] = [I]

with M_l = ∫_{e_l} φ_i φ_j, b_l = ∫_{e_l} φ_i, K_k = V_k ∇λ ∇λᵀ.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ..mesh.electrodes import ElectrodePatch
from ..mesh.tetmesh import TetMesh

__all__ = ["CEMAssembler", "element_stiffness"]


def element_stiffness(mesh: TetMesh) -> np.ndarray:
    """Unit-conductivity local stiffness V_k ∇λ_a·∇λ_b, shape (n_tets, 4, 4)."""
    g = mesh.gradients
    return mesh.volumes[:, None, None] * np.einsum("kai,kbi->kab", g, g)


@dataclass(frozen=True, eq=False)
class CEMAssembler:
    """Holds the sparsity pattern of the CEM system for one mesh and electrode set, so that
    assembling for a new conductivity or contact impedance is a weighted ``bincount``.

    ``electrodes`` lists all electrodes; ``ground`` is the index of the reference one. The
    driven electrodes are the others, in order; the system has n_nodes + n_driven rows."""

    mesh: TetMesh
    electrodes: tuple[ElectrodePatch, ...]
    ground: int

    def __post_init__(self) -> None:
        n, L = self.mesh.n_nodes, len(self.electrodes) - 1
        if not 0 <= self.ground <= L:
            raise ValueError(f"ground = {self.ground}: must index one of the {L + 1} electrodes")
        tets = self.mesh.tets
        rows = [np.repeat(tets, 4, axis=1).ravel()]
        cols = [np.tile(tets, (1, 4)).ravel()]
        for l, e in enumerate(self.electrodes):
            f = e.faces
            rows.append(np.repeat(f, 3, axis=1).ravel())
            cols.append(np.tile(f, (1, 3)).ravel())
            j = self._driven_index(l)
            if j is not None:
                rows += [f.ravel(), np.full(f.size, n + j), [n + j]]
                cols += [np.full(f.size, n + j), f.ravel(), [n + j]]
        r, c = np.concatenate(rows), np.concatenate(cols)
        N = n + L
        key = r.astype(np.int64) * N + c
        uniq, slot = np.unique(key, return_inverse=True)
        indptr = np.searchsorted(uniq // N, np.arange(N + 1))
        object.__setattr__(self, "_shape", (N, N))
        object.__setattr__(self, "_indices", (uniq % N).astype(np.int32))
        object.__setattr__(self, "_indptr", indptr.astype(np.int32))
        object.__setattr__(self, "_n_el_slots", tets.size * 4)
        object.__setattr__(self, "_slot", slot.ravel())
        object.__setattr__(self, "_k_local", element_stiffness(self.mesh).ravel())

    @property
    def n_driven(self) -> int:
        return len(self.electrodes) - 1

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
            vals.append((e.m2 / z[l]).ravel())
            if self._driven_index(l) is not None:
                b = -(e.m1 / z[l]).ravel()
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
        w = np.concatenate([np.repeat(sigma, 16) * self._k_local, self.electrode_values(z)])
        data = np.bincount(self._slot, weights=w, minlength=len(self._indices))
        return sp.csr_matrix((data, self._indices, self._indptr), shape=self._shape)

    def electrode_currents(self, u: np.ndarray, U: np.ndarray, z: np.ndarray) -> np.ndarray:
        """Current (A) through every electrode into the saline, ground included:
        I_l = (|e_l|·U_l − ∫_{e_l} u dS)/z_l. u (n_nodes, k), U (n_driven, k) → (n_el, k)."""
        u = np.atleast_2d(u.T).T
        U = np.atleast_2d(U.T).T
        out = np.empty((len(self.electrodes), u.shape[1]))
        for l, e in enumerate(self.electrodes):
            j = self._driven_index(l)
            Ul = 0.0 if j is None else U[j]
            integral = np.einsum("fa,fak->k", e.m1, u[e.faces])
            out[l] = (e.total_area * Ul - integral) / z[l]
        return out
