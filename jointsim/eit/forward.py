"""The EIT forward model: one factorisation per conductivity, then the lead fields of the
driven electrodes (unit current in, out through the ground). Every injection pattern is a
combination of lead fields, so all skip-N protocols cost the same 16 solves, and the same
fields give the Jacobian by the adjoint method.

A model made ``like`` an earlier one of the same mesh topology (a morphed chamber, frame after
frame) keeps its CEM pattern and, where that one is ``shared()``, its PARDISO solver, whose
ordering and symbolic analysis are then done once: a palpation frame's forward stage at the
paper's 323 k tets took 3.24 s before and 1.64 s after (results/palpation_benchmark.md as
committed in 1a24a27 and b81002b, in git; later runs have the Warp kernels too)."""

from __future__ import annotations

import copy
from dataclasses import dataclass

import numpy as np

from ..linalg import SPD_REFINEMENT, PatternSolver, available_backends, factorize, preferred_backend
from ..mesh.chamber import ChamberMesh
from ..mesh.electrodes import ElectrodePatch
from ..mesh.tetmesh import TetMesh
from ..scene import Scene
from .fem import CEMAssembler
from .protocol import Protocol

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
    backend : sparse direct solver, see :func:`jointsim.linalg.factorize`
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
        self.z = _contact_impedances(contact_impedance, len(electrodes))
        self.backend = backend
        self._shared: _SharedSolver | None = None

    @classmethod
    def from_chamber(cls, chamber: ChamberMesh, scene: Scene, backend: str = "auto", order: int | None = None,
                     like: "ForwardModel | None" = None) -> "ForwardModel":
        """The model of ``chamber`` with the scene's contact impedances and, unless ``order``
        is given, its ``mesh.element_order``. ``like``: an earlier model of the run (same
        scene, backend and order); where ``chamber`` has its topology the new model keeps its
        pattern, and shares its solver if it was made :meth:`shared` (module docstring). Free
        that solver with :meth:`free` on any of them."""
        e = scene.electrodes
        z = e.contact_impedances
        order = scene.mesh.element_order if order is None else order
        return cls.like_or_new(like, chamber.mesh, chamber.patches(order), chamber.ground, z, backend, order)

    @classmethod
    def like_or_new(cls, like: "ForwardModel | None", mesh: TetMesh, electrodes: list[ElectrodePatch], ground: int,
                    contact_impedance: np.ndarray | float, backend: str, order: int) -> "ForwardModel":
        """The model of ``mesh`` and ``electrodes``: made :meth:`on` ``like``, an earlier model of
        the run, where that has this ``order``, ``backend`` and ``ground`` (its pattern and shared
        solver kept where the topology is its); else a new one."""
        if like is not None and like.order == order and like.backend == backend and like.assembler.ground == ground:
            return like.on(mesh, electrodes, contact_impedance)
        return cls(mesh, electrodes, ground, contact_impedance, backend, order)

    def on(self, mesh: TetMesh, electrodes: list[ElectrodePatch], contact_impedance: np.ndarray | float | None = None) -> "ForwardModel":
        """This model (ground, backend, order; contact impedances unless given) on ``mesh`` and
        ``electrodes``. Where they have this model's topology (a morph of its mesh, the same
        electrode faces) the new model keeps the CEM pattern and, if this model is
        :meth:`shared`, its solver (module docstring)."""
        model = copy.copy(self)
        model.mesh = mesh
        model.assembler = self.assembler.on(mesh, electrodes)
        model.z = _contact_impedances(self.z if contact_impedance is None else contact_impedance, len(electrodes))
        if self._shared is not None and not model.assembler.same_pattern(self.assembler):
            model._shared = None
        return model

    def shared(self) -> "ForwardModel":
        """This model, from now on solving with a PARDISO solver whose ordering and symbolic
        analysis are kept, and shared with the models made :meth:`on` it of the same topology
        (so that all of them solve alike, to the last bit; they hold one factor, so one solve at
        a time). The same on the GPU where cuDSS is asked for (the model's backend, or the
        process's preferred one). Without PARDISO, or with another backend asked for, the model is
        left as it is."""
        backend = preferred_backend() if self.backend == "auto" else self.backend
        if backend == "auto" and "pardiso" in available_backends():
            backend = "pardiso"
        if self._shared is None and backend in ("pardiso", "cudss"):
            self._shared = _SharedSolver(self.assembler, backend, self.n_driven)
        return self

    def free(self) -> None:
        """Release the shared solver's factor (a later solve analyses afresh)."""
        if self._shared is not None:
            self._shared.free()

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
        if self._shared is not None:
            x = self._shared.solve(A, rhs)
        else:
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


def _contact_impedances(z: np.ndarray | float, n: int) -> np.ndarray:
    z = np.broadcast_to(np.asarray(z, float), (n,)).copy()
    if not (z > 0).all():
        raise ValueError("contact_impedance: must be > 0 Ω·m² for every electrode")
    return z


class _SharedSolver:
    """PARDISO's (or cuDSS's) Cholesky on one CEM pattern, its ordering and symbolic analysis done
    on the first factorisation and kept: the models of a morphed chamber share it."""

    def __init__(self, assembler: CEMAssembler, backend: str = "pardiso", columns: int = 1):
        indptr, indices = assembler.pattern
        n = len(indptr) - 1
        rows = np.repeat(np.arange(n), np.diff(indptr))
        self._upper = indices >= rows  # the upper triangle, in the order of the assembled values
        upper_indptr = np.concatenate([[0], np.cumsum(np.bincount(rows[self._upper], minlength=n))])
        self._solver = PatternSolver(upper_indptr, indices[self._upper], spd=True, backend=backend, refinement=SPD_REFINEMENT,
                                     known_definite=True, columns=columns)

    def solve(self, A, rhs: np.ndarray) -> np.ndarray:
        self._solver.factor(A.data[self._upper])
        return self._solver.solve(rhs)

    def free(self) -> None:
        self._solver.free()
