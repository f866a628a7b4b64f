"""Sensitivity of the measurements to element conductivities, by the adjoint method.

For piecewise-constant σ, ∂A/∂σ_k = ∫_k ∇φ∇φᵀ on element k, so

    ∂(meas·U_s)/∂σ_k = −∫_k ∇u_s · ∇v_m,

V_k ∇u_s·∇v_m for P1 (constant gradients); for P2 the integrand is quadratic and Keast's
4-point rule integrates it exactly.

with u_s the field of injection s and v_m the field of the measurement pattern driven as a
current (reciprocity). Both are combinations of the lead fields: ∇u_s = Σ_l stim[s,l] ∇v_l and ∇v_m = Σ_l meas[s,m,l] ∇v_l.

P1 with one measurement pattern for every injection (the skip protocols) runs in Warp kernels,
each element adding its (n_meas,) column straight into the coarse cells it belongs to; otherwise
elements are processed in numpy chunks. Either way memory stays bounded by a chunk of elements
(1 M tets fit in a few GB).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from .._warp import on_host, wp
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


wp.set_module_options({"enable_backward": False})


@wp.kernel
def _field_gradients(f: wp.array2d(dtype=wp.float64), tets: wp.array2d(dtype=wp.int64), grad: wp.array2d(dtype=wp.vec3d),
                     start: int, out: wp.array2d(dtype=wp.vec3d)):
    # the gradient on element start + i of the P1 field whose nodal values are column c of f
    i, c = wp.tid()
    k = start + i
    out[i, c] = (f[tets[k, 0], c] * grad[k, 0] + f[tets[k, 1], c] * grad[k, 1]
                 + f[tets[k, 2], c] * grad[k, 2] + f[tets[k, 3], c] * grad[k, 3])


@wp.kernel
def _p1_sensitivity(gu: wp.array2d(dtype=wp.vec3d), gv: wp.array2d(dtype=wp.vec3d), volume: wp.array(dtype=wp.float64),
                    start: int, indptr: wp.array(dtype=wp.int64), cells: wp.array(dtype=wp.int64),
                    share: wp.array(dtype=wp.float64), Jt: wp.array2d(dtype=wp.float64)):
    # −V_k ∇u_s·∇v_m of element k, for injection s and measurement m, added into column s·M + m
    # of the row of Jᵀ of each cell holding a share of the element (one cell per element, share
    # 1, for the fine J): a cell's measurements are contiguous there
    i = wp.tid()
    k = start + i
    n_meas = gv.shape[1]
    w = -wp.abs(volume[k])
    for j in range(int(indptr[k]), int(indptr[k + 1])):
        cell = int(cells[j])
        ws = w * share[j]
        for s in range(gu.shape[1]):
            for m in range(n_meas):
                # Warp runs a CPU kernel on one thread, so elements sharing a cell do not race
                # and the add needs no atomic
                col = s * n_meas + m
                Jt[cell, col] = Jt[cell, col] + ws * wp.dot(gu[i, s], gv[i, m])


def _p1_kernel_jacobian(fields: LeadFields, protocol: Protocol, coarse: sp.csr_matrix | None, n_out: int,
                        chunk: int) -> np.ndarray:
    """The P1 Jacobian of a protocol whose injections share one measurement pattern: the
    injection and measurement fields' nodal values first, (n, S) and (n, M), then per chunk of
    elements their gradients and each element's column (:func:`_p1_sensitivity`). Jᵀ is
    accumulated, so the result is its transpose (Fortran-ordered, no copy)."""
    mesh = fields.model.mesh
    u = np.ascontiguousarray(fields.potentials(protocol))
    v = np.ascontiguousarray(fields.nodal[: mesh.n_nodes] @ protocol.meas[0].T)
    if coarse is None:
        coarse = sp.identity(mesh.n_tets, format="csr")
    indptr, cells = coarse.indptr.astype(np.int64), coarse.indices.astype(np.int64)
    share = np.ascontiguousarray(coarse.data, float)
    tets, grad, volume = on_host(mesh.tets, wp.int64), on_host(mesh.gradients, wp.vec3d), on_host(mesh.signed_volumes)
    Jt = np.zeros((n_out, protocol.n_meas))
    args = [on_host(indptr, wp.int64), on_host(cells, wp.int64), on_host(share), on_host(Jt)]
    for start in range(0, mesh.n_tets, chunk):
        c = min(chunk, mesh.n_tets - start)
        gu, gv = np.empty((c, u.shape[1], 3)), np.empty((c, v.shape[1], 3))
        for f, g in ((u, gu), (v, gv)):
            wp.launch(_field_gradients, g.shape[:2], device="cpu", inputs=[on_host(f), tets, grad, start, on_host(g, wp.vec3d)])
        wp.launch(_p1_sensitivity, c, device="cpu", inputs=[on_host(gu, wp.vec3d), on_host(gv, wp.vec3d), volume, start, *args])
    return Jt.T


def jacobian(
    fields: LeadFields,
    protocol: Protocol,
    *,
    coarse: sp.spmatrix | None = None,
    chunk: int = 32768,
    dtype: np.dtype = np.float64,
) -> np.ndarray:
    """∂(measurements)/∂σ: (n_meas, n_tets) in V·m/S, or (n_meas, n_coarse) when ``coarse``
    (n_tets, n_coarse) maps elements onto coarse cells (the sum of fine columns per cell). P1
    with a shared measurement pattern comes Fortran-ordered (the kernels' layout)."""
    fields.model._check_protocol(protocol)
    mesh = fields.model.mesh
    n_out = mesh.n_tets if coarse is None else coarse.shape[1]
    if coarse is not None:
        coarse = sp.csr_matrix(coarse)
        if coarse.shape[0] != mesh.n_tets:
            raise ValueError(f"coarse: expected {mesh.n_tets} rows (one per element), got {coarse.shape[0]}")
    shared_meas = bool((protocol.meas == protocol.meas[:1]).all())
    if fields.model.order == 1 and shared_meas and np.dtype(dtype) == np.float64:
        return _p1_kernel_jacobian(fields, protocol, coarse, n_out, chunk)
    J = np.zeros((protocol.n_meas, n_out), dtype=dtype)
    vol = mesh.volumes
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
