"""Tetrahedral meshes as plain arrays: geometry (volumes, shape-function gradients), boundary
faces and a quality report. Everything here is vectorised over elements."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from .kernels import tet_geometry

__all__ = ["TetMesh", "MeshQuality", "mesh_quality", "refine_uniform", "edge_midpoints", "unique_edges", "TET_EDGES", "KEAST_POINTS"]

# the six edges of a tetrahedron, in the order P2 midpoint nodes follow
TET_EDGES = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])
# Keast's 4-point rule on the tetrahedron, exact to degree 2 (products of P2 gradients):
# barycentric points (4, 4), each of weight 1/4
KEAST_POINTS = np.full((4, 4), 0.1381966011250105) + np.eye(4) * (0.5854101966249685 - 0.1381966011250105)
_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])  # face i is opposite vertex i, outward


@dataclass(frozen=True, eq=False)
class TetMesh:
    """``nodes`` (n_nodes, 3) in m, ``tets`` (n_tets, 4) node indices, positively oriented."""

    nodes: np.ndarray
    tets: np.ndarray

    def __post_init__(self) -> None:
        nodes = np.ascontiguousarray(self.nodes, dtype=np.float64)
        tets = np.ascontiguousarray(self.tets, dtype=np.int64)
        if nodes.ndim != 2 or nodes.shape[1] != 3:
            raise ValueError(f"nodes: expected shape (n, 3), got {nodes.shape}")
        if tets.ndim != 2 or tets.shape[1] != 4:
            raise ValueError(f"tets: expected shape (m, 4), got {tets.shape}")
        if len(tets) and (tets.min() < 0 or tets.max() >= len(nodes)):
            raise ValueError("tets: node index out of range")
        object.__setattr__(self, "nodes", nodes)
        object.__setattr__(self, "tets", tets)

    @property
    def n_nodes(self) -> int:
        return len(self.nodes)

    @property
    def n_tets(self) -> int:
        return len(self.tets)

    @cached_property
    def _geometry(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return tet_geometry(self.nodes, self.tets)

    @property
    def signed_volumes(self) -> np.ndarray:
        return self._geometry[0]

    @property
    def volumes(self) -> np.ndarray:
        return np.abs(self.signed_volumes)

    @property
    def centroids(self) -> np.ndarray:
        return self._geometry[2]

    @property
    def gradients(self) -> np.ndarray:
        """∇λ_a of the four barycentric (P1) shape functions, shape (n_tets, 4, 3), constant per
        element: the columns of the inverse edge matrix, with ∇λ_0 = −Σ ∇λ_{1..3}. A mesh with a
        flat element has none (ValueError naming it)."""
        volume, g, _ = self._geometry
        flat = volume == 0
        if flat.any():
            raise ValueError(f"mesh: {int(flat.sum())} of {self.n_tets} elements have zero volume (first: element "
                             f"{int(np.argmax(flat))}); shape-function gradients need every element of nonzero volume")
        return g

    @cached_property
    def boundary_faces(self) -> np.ndarray:
        """Faces that belong to one tetrahedron only, (k, 3), oriented outward."""
        f = self.tets[:, _FACES].reshape(-1, 3)
        s = np.sort(f, axis=1)
        n = np.int64(self.n_nodes)
        # one integer per face (its sorted corners in base n) where that fits, rows otherwise:
        # a 1-D unique is ~5x faster than one over rows
        key = (s[:, 0] * n + s[:, 1]) * n + s[:, 2] if self.n_nodes < 2**21 else s
        _, inv, cnt = np.unique(key, axis=0, return_inverse=True, return_counts=True)
        return f[cnt[inv.ravel()] == 1]

    def moved(self, nodes: np.ndarray) -> "TetMesh":
        """This mesh with its nodes at ``nodes`` (a morph: the same tetrahedra), sharing what
        depends on the connectivity alone (the boundary faces; their outward orientation holds
        while no element inverts, which a morph checks)."""
        moved = TetMesh(nodes, self.tets)
        if "boundary_faces" in self.__dict__:
            moved.__dict__["boundary_faces"] = self.boundary_faces
        return moved

    def oriented(self) -> "TetMesh":
        """A copy with negatively oriented elements flipped."""
        neg = self.signed_volumes < 0
        if not neg.any():
            return self
        t = self.tets.copy()
        t[neg, 2], t[neg, 3] = self.tets[neg, 3], self.tets[neg, 2]
        return TetMesh(self.nodes, t)


@dataclass(frozen=True)
class MeshQuality:
    n_tets: int
    n_nodes: int
    n_inverted: int
    min_dihedral_deg: float
    max_dihedral_deg: float
    min_radius_ratio: float
    mean_radius_ratio: float
    volume: float

    def summary(self) -> str:
        return (
            f"{self.n_tets} tets, {self.n_nodes} nodes, volume {self.volume * 1e9:.1f} mm^3; "
            f"dihedral angles {self.min_dihedral_deg:.1f}-{self.max_dihedral_deg:.1f} deg; "
            f"radius ratio min {self.min_radius_ratio:.3f} mean {self.mean_radius_ratio:.3f}; "
            f"{self.n_inverted} inverted"
        )


def mesh_quality(mesh: TetMesh) -> MeshQuality:
    """Dihedral angles and the normalised radius ratio 3·r_in/r_circ (1 for a regular tet)."""
    g = mesh.gradients  # face normals are ∝ −∇λ of the opposite vertex
    n = g / np.linalg.norm(g, axis=2, keepdims=True)
    # the dihedral angle on the edge (a, b) lies between the faces opposite the other two vertices
    other = np.array([[2, 3], [1, 3], [1, 2], [0, 3], [0, 2], [0, 1]])
    cosang = -np.einsum("mij,mij->mi", n[:, other[:, 0]], n[:, other[:, 1]])
    dihedral = np.degrees(np.arccos(np.clip(cosang, -1, 1)))
    vol = mesh.volumes
    p = mesh.nodes[mesh.tets]
    face_area = 0.5 * np.linalg.norm(
        np.cross(p[:, _FACES[:, 1]] - p[:, _FACES[:, 0]], p[:, _FACES[:, 2]] - p[:, _FACES[:, 0]]), axis=2
    ).sum(axis=1)
    r_in = 3 * vol / face_area
    r_circ = _circumradius(p)
    rr = 3 * r_in / r_circ
    return MeshQuality(
        n_tets=mesh.n_tets,
        n_nodes=mesh.n_nodes,
        n_inverted=int((mesh.signed_volumes <= 0).sum()),
        min_dihedral_deg=float(dihedral.min()),
        max_dihedral_deg=float(dihedral.max()),
        min_radius_ratio=float(rr.min()),
        mean_radius_ratio=float(rr.mean()),
        volume=float(vol.sum()),
    )


def _circumradius(p: np.ndarray) -> np.ndarray:
    a = p[:, 1:] - p[:, :1]  # (m, 3, 3)
    rhs = 0.5 * np.einsum("mij,mij->mi", a, a)
    c = np.linalg.solve(a, rhs[..., None])[..., 0]
    return np.linalg.norm(c, axis=1)


def unique_edges(mesh: TetMesh) -> tuple[np.ndarray, np.ndarray]:
    """The mesh's k unique edges (k, 2) (node pairs, sorted), and for each element the index
    (m, 6) of each of its edges, in the order of ``TET_EDGES``."""
    pair = np.sort(mesh.tets[:, TET_EDGES].reshape(-1, 2), axis=1)
    n = np.int64(mesh.n_nodes)
    # one integer per edge, a·n + b (b < n): its order is the pairs' lexicographic one, and a 1-D
    # unique is ~5x faster than one over rows
    uniq, inv = np.unique(pair[:, 0] * n + pair[:, 1], return_inverse=True)
    return np.column_stack([uniq // n, uniq % n]), inv.reshape(-1, 6)


def edge_midpoints(mesh: TetMesh) -> tuple[np.ndarray, np.ndarray]:
    """The midpoints (k, 3) of the mesh's k unique edges, and for each element the index (m, 6)
    of the midpoint of each of its edges, in the order of ``TET_EDGES``."""
    uniq, index = unique_edges(mesh)
    return mesh.nodes[uniq].mean(axis=1), index


def refine_uniform(mesh: TetMesh) -> TetMesh:
    """Red refinement: every tetrahedron split into 8 through its edge midpoints (the inner
    octahedron cut along one diagonal). Boundary faces stay in their planes, so flat electrodes
    can be re-clipped exactly on the refined mesh."""
    t = mesh.tets
    points, index = edge_midpoints(mesh)
    mid = mesh.n_nodes + index  # midpoint node of each of the 6 edges
    nodes = np.vstack([mesh.nodes, points])
    m01, m02, m03, m12, m13, m23 = mid.T
    v0, v1, v2, v3 = t.T
    children = np.stack(
        [
            [v0, m01, m02, m03], [m01, v1, m12, m13], [m02, m12, v2, m23], [m03, m13, m23, v3],
            [m01, m02, m03, m13], [m01, m02, m12, m13], [m02, m03, m13, m23], [m02, m12, m13, m23],
        ],
        axis=0,
    )  # (8, 4, n_tets)
    return TetMesh(nodes, children.transpose(2, 0, 1).reshape(-1, 4)).oriented()
