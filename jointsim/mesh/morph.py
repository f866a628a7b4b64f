"""Fixed-topology chamber meshes: the reference chamber mesh morphed by a dome displacement.

Boundary nodes on the dome take the displacement of the closest point of the reference dome
surface (barycentric interpolation of its vertex displacements); base nodes stay put, so the
electrode patches are unchanged; interior nodes follow by harmonic extension (the P1 Laplace
problem on the reference mesh, one factorisation for the three components). Because the
topology and the electrode integrals do not change, a difference of voltages between the
morphed and the reference mesh carries no remeshing noise.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import scipy.sparse as sp
import trimesh

from ..geometry import DomeSurface
from ..eit.fem import element_stiffness
from ..eit.solver import factorize
from .chamber import ChamberMesh
from .tetmesh import TetMesh, mesh_quality

__all__ = ["MeshInversionError", "morph_chamber", "dome_nodes"]


class MeshInversionError(RuntimeError):
    """The morphed mesh has inverted or degenerate elements: remesh instead."""


def dome_nodes(mesh: TetMesh, tol: float = 1e-9) -> np.ndarray:
    """Indices of the boundary nodes not on the base plane z = 0."""
    b = np.unique(mesh.boundary_faces)
    return b[np.abs(mesh.nodes[b, 2]) > tol]


def morph_chamber(
    chamber: ChamberMesh,
    dome: DomeSurface,
    deformed: DomeSurface,
    min_dihedral_deg: float = 1.0,
) -> ChamberMesh:
    """The chamber mesh moved so that its dome follows ``deformed`` (same vertices and faces
    as the reference ``dome``). Raises :class:`MeshInversionError` when an element inverts or
    its smallest dihedral angle falls below ``min_dihedral_deg``."""
    mesh = chamber.mesh
    disp = np.asarray(deformed.vertices, float) - np.asarray(dome.vertices, float)
    if disp.shape != np.shape(dome.vertices):
        raise ValueError("deformed: must have the same vertices and faces as the reference dome")
    top = dome_nodes(mesh)
    surf = trimesh.Trimesh(dome.vertices, dome.faces, process=False)
    closest, _, tri = trimesh.proximity.closest_point(surf, mesh.nodes[top])
    bary = trimesh.triangles.points_to_barycentric(surf.triangles[tri], closest)
    u_top = np.einsum("na,nai->ni", bary, disp[dome.faces[tri]])

    boundary = np.unique(mesh.boundary_faces)
    u = np.zeros_like(mesh.nodes)
    u[top] = u_top
    fixed = np.zeros(mesh.n_nodes, bool)
    fixed[boundary] = True
    free = ~fixed
    if free.any() and np.abs(u_top).max() > 0:
        K = _stiffness(mesh)
        Kff = K[free][:, free]
        with factorize(Kff) as solve:
            u[free] = solve(-(K[free][:, fixed] @ u[fixed]))
    moved = TetMesh(mesh.nodes + u, mesh.tets)
    q = mesh_quality(moved)
    if q.n_inverted or q.min_dihedral_deg < min_dihedral_deg:
        raise MeshInversionError(
            f"morphed chamber mesh: {q.n_inverted} inverted elements, smallest dihedral angle "
            f"{q.min_dihedral_deg:.2f} deg (limit {min_dihedral_deg} deg); remesh this deformation"
        )
    return replace(chamber, mesh=moved, key=f"{chamber.key}-morphed")


def _stiffness(mesh: TetMesh) -> sp.csr_matrix:
    k = element_stiffness(mesh)
    rows = np.repeat(mesh.tets, 4, axis=1).ravel()
    cols = np.tile(mesh.tets, (1, 4)).ravel()
    return sp.csr_matrix((k.ravel(), (rows, cols)), shape=(mesh.n_nodes, mesh.n_nodes))
