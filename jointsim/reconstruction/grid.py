"""The coarse reconstruction grid: axis-aligned voxels over the chamber, and the exact map from
fine forward-mesh elements onto it (each element belongs to the voxel holding its centroid)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ..mesh.tetmesh import TetMesh

__all__ = ["VoxelGrid", "element_voxel_map"]


@dataclass(frozen=True)
class VoxelGrid:
    """Voxels of size ``spacing`` (3,) from ``origin`` (3,), ``shape`` (nx, ny, nz) cells."""

    origin: np.ndarray
    spacing: np.ndarray
    shape: tuple[int, int, int]

    @classmethod
    def covering(cls, mesh: TetMesh, n_cells: int = 7000) -> "VoxelGrid":
        """Cubic voxels over the mesh's bounding box, about ``n_cells`` of them in the box."""
        lo, hi = mesh.nodes.min(axis=0), mesh.nodes.max(axis=0)
        ext = hi - lo
        h = float(np.cbrt(np.prod(ext) / n_cells))
        shape = tuple(int(max(1, np.ceil(e / h - 1e-9))) for e in ext)
        return cls(lo.copy(), np.full(3, h), shape)

    @property
    def n_cells(self) -> int:
        return int(np.prod(self.shape))

    def cell_of(self, points: np.ndarray) -> np.ndarray:
        """Flat cell index of each point (n, 3); points outside are clamped to the edge cells."""
        ijk = np.floor((points - self.origin) / self.spacing).astype(np.int64)
        ijk = np.clip(ijk, 0, np.array(self.shape) - 1)
        return np.ravel_multi_index(ijk.T, self.shape)

    def centres(self) -> np.ndarray:
        idx = np.indices(self.shape).reshape(3, -1).T
        return self.origin + (idx + 0.5) * self.spacing


def element_voxel_map(mesh: TetMesh, grid: VoxelGrid) -> sp.csr_matrix:
    """C (n_tets, n_cells), C[k, c] = 1 when element k's centroid lies in cell c. Then
    J_coarse = J·C is the exact Jacobian for σ_k = σ_cell(k), and σ_fine = C·σ_coarse."""
    cell = grid.cell_of(mesh.centroids)
    return sp.csr_matrix((np.ones(mesh.n_tets), (np.arange(mesh.n_tets), cell)), shape=(mesh.n_tets, grid.n_cells))
