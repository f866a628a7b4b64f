"""The EIT forward model: one factorisation per conductivity, then the lead fields of the
driven electrodes (unit current in, out through the ground). Every injection pattern is a
combination of lead fields, so all skip-N protocols cost the same 16 solves, and the same
fields give the Jacobian by the adjoint method."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..mesh.chamber import ChamberMesh
from ..mesh.electrodes import ElectrodePatch, disc_patches
from ..mesh.tetmesh import TetMesh
from ..scene import Scene
from .fem import CEMAssembler
from .protocol import Protocol
from .solver import factorize

__all__ = ["ForwardModel", "LeadFields"]


@dataclass(frozen=True, eq=False)
class LeadFields:
    """Potentials for a unit current into each driven electrode (out through the ground).

    ``nodal`` (n_dofs, L) in V/A (the nodes' values first; P2 adds the edges'), ``transfer``
    (L, L): electrode potentials, the transfer impedance matrix Z (symmetric by reciprocity).
    ``sigma`` (n_tets,), ``z`` (n_el,)."""

    model: "ForwardModel"
    sigma: np.ndarray
    z: np.ndarray
    nodal: np.ndarray
    transfer: np.ndarray

    def electrode_voltages(self, protocol: Protocol) -> np.ndarray:
        """Electrode potentials against ground for each injection, (n_stim, L)."""
        self.model._check_protocol(protocol)
        return protocol.stim @ self.transfer.T

    def voltages(self, protocol: Protocol) -> np.ndarray:
        """The protocol's measurements (n_meas,) in V, injection-major."""
        return protocol.measure(self.electrode_voltages(protocol))

    def potentials(self, protocol: Protocol) -> np.ndarray:
        """Potentials at the mesh's nodes for each injection, (n_nodes, n_stim)."""
        self.model._check_protocol(protocol)
        return self.nodal[: self.model.mesh.n_nodes] @ protocol.stim.T

    def electrode_currents(self, protocol: Protocol) -> np.ndarray:
        """Current through every electrode (ground included) per injection, (n_stim, n_el)."""
        self.model._check_protocol(protocol)
        u = self.nodal @ protocol.stim.T
        U = self.electrode_voltages(protocol).T
        return self.model.assembler.electrode_currents(u, U, self.z).T


class ForwardModel:
    """CEM forward model with P1 or P2 elements on a tetrahedral mesh, electrodes as boundary
    patches.

    Parameters
    ----------
    mesh : TetMesh
    electrodes : list of ElectrodePatch, all electrodes including the ground
    ground : index of the reference electrode in ``electrodes``
    contact_impedance : (n_el,) Ω·m², one per electrode (ground included)
    backend : sparse direct solver, see :func:`jointsim.eit.solver.factorize`
    order : element order, 1 (P1) or 2 (P2 on the same tetrahedra; see :mod:`jointsim.eit.fem`)
    """

    def __init__(
        self,
        mesh: TetMesh,
        electrodes: list[ElectrodePatch],
        ground: int,
        contact_impedance: np.ndarray | float,
        backend: str = "auto",
        order: int = 1,
    ):
        self.mesh = mesh
        self.assembler = CEMAssembler(mesh, tuple(electrodes), ground, order)
        z = np.broadcast_to(np.asarray(contact_impedance, float), (len(electrodes),)).copy()
        if not (z > 0).all():
            raise ValueError("contact_impedance: must be > 0 Ω·m² for every electrode")
        self.z = z
        self.backend = backend

    @classmethod
    def from_chamber(cls, chamber: ChamberMesh, scene: Scene, backend: str = "auto", order: int | None = None) -> "ForwardModel":
        """The model of ``chamber`` with the scene's contact impedances and, unless ``order``
        is given, its ``mesh.element_order``."""
        e = scene.electrodes
        z = np.append(np.asarray(e.contact_impedance), e.ground_contact_impedance)
        order = scene.mesh.element_order if order is None else order
        electrodes = chamber.electrodes
        if order == 2 and any(e.q1 is None for e in electrodes):
            # a chamber's patches carry P1 moments only; the P2 ones come from the same discs
            electrodes = disc_patches(chamber.mesh, chamber.layout.centres, chamber.layout.radii, quadratic=True)
        return cls(chamber.mesh, electrodes, chamber.ground, z, backend, order)

    @property
    def order(self) -> int:
        return self.assembler.order

    @property
    def n_driven(self) -> int:
        return self.assembler.n_driven

    def _check_protocol(self, protocol: Protocol) -> None:
        if protocol.n_el != self.n_driven:
            raise ValueError(
                f"protocol has {protocol.n_el} electrodes, the model drives {self.n_driven} (ground excluded)"
            )

    def solve(self, sigma: np.ndarray | float, z: np.ndarray | None = None) -> LeadFields:
        """Factorise once for element conductivities ``sigma`` (S/m) and solve the L lead fields."""
        z = self.z if z is None else np.asarray(z, float)
        sigma = np.broadcast_to(np.asarray(sigma, float), (self.mesh.n_tets,))
        A = self.assembler.assemble(sigma, z)
        n, L = self.assembler.n_dofs, self.n_driven
        rhs = np.zeros((n + L, L))
        rhs[n + np.arange(L), np.arange(L)] = 1.0
        with factorize(A, self.backend) as solve:
            x = solve(rhs)
        return LeadFields(self, np.array(sigma), z, x[:n], x[n:])

    def voltages(self, sigma: np.ndarray | float, protocol: Protocol) -> np.ndarray:
        return self.solve(sigma).voltages(protocol)

    def voltages_by_frequency(
        self, sigma: np.ndarray | float, protocol: Protocol, z_by_freq: np.ndarray, freq_of_stim: np.ndarray
    ) -> np.ndarray:
        """FDM drive: injection s runs at carrier ``freq_of_stim[s]`` whose contact impedances
        are ``z_by_freq[f]`` (n_el,). One factorisation per distinct carrier used."""
        z_by_freq = np.asarray(z_by_freq, float)
        freq_of_stim = np.asarray(freq_of_stim)
        U = np.empty((protocol.n_stim, self.n_driven))
        for f in np.unique(freq_of_stim):
            s = freq_of_stim == f
            U[s] = protocol.stim[s] @ self.solve(sigma, z_by_freq[f]).transfer.T
        return protocol.measure(U)
