"""Sensitivity of the measurements to the sensor's electrical parameters, by the adjoint method:
each electrode's contact impedance and position, and the saline's conductivity.

With X = A⁻¹E the lead fields (unit current into each driven electrode, nodal potentials and
electrode potentials together) the transfer impedances are T = EᵀA⁻¹E, so for any parameter p
of the CEM matrix

    ∂T/∂p = −Xᵀ (∂A/∂p) X,

and every protocol's voltages are linear in T (``V = measure(stim · Tᵀ)``). A enters through
electrode l only as Q_l/z_l, with the electrode's quadratic form (:mod:`.fem`)

    Q_l(x, y) = ∫_{e_l} (u − U_l)(w − W_l) dS,

so  ∂T/∂ln z_l = Q_l(X, X)/z_l  and  ∂T/∂c_l = −(1/z_l) ∂Q_l(X, X)/∂c_l,  the latter by central
differences of the clipped disc's moments (the patch moved, the fields held: no solve). The
conductivity needs nothing more: A(ασ, z/α) = αA(σ, z) gives T(ασ, z/α) = T/α, hence

    ∂T/∂ln σ = −T + Σ_l ∂T/∂ln z_l.

All of it costs one pass over the electrodes' faces per parameter on fields already solved.
"""

from __future__ import annotations

import numpy as np

from ..mesh.electrodes import ElectrodePatch, place_discs
from ..mesh.tetmesh import TetMesh
from .forward import LeadFields
from .protocol import Protocol

__all__ = ["electrode_form", "transfer_voltages", "contact_impedance_sensitivity", "conductivity_sensitivity",
           "electrode_position_sensitivity", "moved_discs"]


def electrode_form(fields: LeadFields, patch: ElectrodePatch, electrode: int) -> np.ndarray:
    """Q (L, L): ∫_e (u_i − U_i)(u_j − U_j) dS over ``patch`` of the lead fields i, j, with U the
    potential of ``electrode`` (the index its patch has in the model; the ground's is 0)."""
    model = fields.model
    asm = model.assembler
    m1, m2 = patch.moments(model.order)
    u = fields.nodal[asm.dofs.faces(patch.faces)]  # (k, nf, L)
    uMu = np.einsum("kab,kai,kbj->ij", m2, u, u)
    mu = np.einsum("ka,kai->i", m1, u)
    j = asm._driven_index(electrode)
    U = np.zeros(fields.transfer.shape[0]) if j is None else fields.transfer[j]
    cross = np.outer(U, mu)
    return uMu - cross - cross.T + patch.total_area * np.outer(U, U)


def transfer_voltages(dT: np.ndarray, protocol: Protocol) -> np.ndarray:
    """The protocol's measurements (…, n_meas) of transfer impedances ``dT`` (…, L, L): voltages
    are linear in T, so this maps ∂T/∂p to ∂V/∂p."""
    dT = np.asarray(dT)
    U = np.einsum("sl,...el->...se", protocol.stim, dT)  # electrode potentials per injection
    return np.einsum("sme,...se->...sm", protocol.meas, U).reshape(dT.shape[:-2] + (-1,))


def contact_impedance_sensitivity(fields: LeadFields, protocol: Protocol) -> np.ndarray:
    """∂V/∂ln z_l (n_el, n_meas) V: every electrode's contact impedance, the ground's included,
    in the model's patch order."""
    pats = fields.model.assembler.electrodes
    dT = np.stack([electrode_form(fields, p, l) / fields.z[l] for l, p in enumerate(pats)])
    return transfer_voltages(dT, protocol)


def conductivity_sensitivity(fields: LeadFields, protocol: Protocol, dz: np.ndarray | None = None) -> np.ndarray:
    """∂V/∂ln σ (n_meas,) V for a uniform scaling of the conductivity (the identity in the module
    docstring); ``dz``: :func:`contact_impedance_sensitivity` when already computed."""
    if dz is None:
        dz = contact_impedance_sensitivity(fields, protocol)
    return -fields.voltages(protocol) + dz.sum(axis=0)


def moved_discs(mesh: TetMesh, centres: np.ndarray, radii: np.ndarray, step: float = 1e-5,
                quadratic: bool = False, membrane: np.ndarray | None = None,
                membrane_patch: str = "stretch") -> list[list[tuple[ElectrodePatch, ElectrodePatch]]]:
    """Each disc electrode's patch clipped with its centre moved by ±``step`` m along x and y:
    ``[l][axis] = (plus, minus)``. ``centres`` (n_el, 3), ``radii`` (n_el,) m: the discs the
    model's patches were clipped from (``membrane`` (n_el,): those on the membrane, moved in
    the footprint they have on the base plane, placed on the dome). A morph keeps the base, so
    one set serves every frame; those on the membrane follow it where they are used."""
    on = np.zeros(len(radii), bool) if membrane is None else np.asarray(membrane, bool)
    out = []
    for c, r, up in zip(np.asarray(centres, float), np.asarray(radii, float), on):
        pair = []
        for a in range(2):
            d = np.zeros(3)
            d[a] = step
            plus, minus = place_discs(mesh, np.array([c + d, c - d]), np.array([r, r]), np.array([up, up]), membrane_patch, quadratic)
            pair.append((plus, minus))
        out.append(pair)
    return out


def electrode_position_sensitivity(fields: LeadFields, protocol: Protocol,
                                   moved: list[list[tuple[ElectrodePatch, ElectrodePatch]]], step: float) -> np.ndarray:
    """∂V/∂(x_l, y_l) (n_el, 2, n_meas) V/m: each disc electrode moved in the base plane, by
    central differences of its patch's moments (:func:`moved_discs` at ``step``; O(step²)),
    the fields held."""
    out = np.empty((len(moved), 2, protocol.n_meas))
    nodes = fields.model.mesh.nodes
    for l, pair in enumerate(moved):
        for a, (plus, minus) in enumerate(pair):
            plus, minus = plus.follow(nodes), minus.follow(nodes)
            dQ = (electrode_form(fields, plus, l) - electrode_form(fields, minus, l)) / (2 * step)
            out[l, a] = transfer_voltages(-dQ / fields.z[l], protocol)
    return out
