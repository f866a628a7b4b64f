"""Sensitivity of the measurements to element conductivities, by the adjoint method.

For piecewise-constant σ, ∂A/∂σ_k = ∫_k ∇φ∇φᵀ on element k, so

    ∂(meas·U_s)/∂σ_k = −∫_k ∇u_s · ∇v_m,

V_k ∇u_s·∇v_m for P1 (constant gradients); for P2 the integrand is quadratic and Keast's
4-point rule integrates it exactly.

with u_s the field of injection s and v_m the field of the measurement pattern driven as a
current (reciprocity). Both are combinations of the lead fields: ∇u_s = Σ_l stim[s,l] ∇v_l and ∇v_m = Σ_l meas[s,m,l] ∇v_l.
Elements are processed in chunks so memory stays bounded (1 M tets fit in a few GB).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from ..mesh.tetmesh import KEAST_POINTS
from .fem import p2_gradients
from .forward import LeadFields
from .protocol import Protocol

__all__ = ["jacobian", "lead_gradients"]


def lead_gradients(fields: LeadFields, elements: slice | np.ndarray = slice(None), lam: np.ndarray | None = None) -> np.ndarray:
    """∇v_l on each element of the selection: (n_sel, L, 3) in V/(A·m); for P2 fields at the
    barycentrics ``lam`` (4,) (default: the centroid)."""
    model = fields.model
    g = model.mesh.gradients[elements]  # (c, 4, 3)
    dofs = model.assembler.dofs.elements[elements]
    if model.order == 2:
        g = p2_gradients(g, np.full(4, 0.25) if lam is None else np.asarray(lam, float))
    return np.matmul(fields.nodal[dofs].transpose(0, 2, 1), g)


def jacobian(
    fields: LeadFields,
    protocol: Protocol,
    *,
    coarse: sp.spmatrix | None = None,
    chunk: int = 32768,
    dtype: np.dtype = np.float64,
) -> np.ndarray:
    """∂(measurements)/∂σ: (n_meas, n_tets) in V·m/S, or (n_meas, n_coarse) when ``coarse``
    (n_tets, n_coarse) maps elements onto coarse cells (the sum of fine columns per cell)."""
    fields.model._check_protocol(protocol)
    mesh = fields.model.mesh
    n_out = mesh.n_tets if coarse is None else coarse.shape[1]
    J = np.zeros((protocol.n_meas, n_out), dtype=dtype)
    if coarse is not None:
        coarse = sp.csr_matrix(coarse)
        if coarse.shape[0] != mesh.n_tets:
            raise ValueError(f"coarse: expected {mesh.n_tets} rows (one per element), got {coarse.shape[0]}")
    vol = mesh.volumes
    shared_meas = bool((protocol.meas == protocol.meas[:1]).all())
    points = [None] if fields.model.order == 1 else list(KEAST_POINTS)  # P2: ∫_k = V_k/4 Σ over Keast's points
    for start in range(0, mesh.n_tets, chunk):
        sl = slice(start, min(start + chunk, mesh.n_tets))
        block = 0.0
        for lam in points:
            G = lead_gradients(fields, sl, lam).transpose(2, 1, 0)  # (3, L, c): elements last, contiguous
            gu = np.matmul(protocol.stim, G)  # injection fields (3, S, c)
            if shared_meas:
                gv = np.matmul(protocol.meas[0], G)[:, None]  # measurement fields (3, 1, M, c)
            else:
                gv = np.matmul(protocol.meas[None], G[:, None])  # (3, S, M, c)
            # a sum of three outer products beats a batched 16×3·3×16 matmul by ~10× in numpy
            block = block + gu[0, :, None] * gv[0]
            block += gu[1, :, None] * gv[1]
            block += gu[2, :, None] * gv[2]
        block = block.reshape(protocol.n_meas, -1) * (-vol[sl] / len(points))  # (n_meas, c)
        if coarse is None:
            J[:, sl] = block
        else:
            J += (coarse[sl].T @ block.T).T
    return J
