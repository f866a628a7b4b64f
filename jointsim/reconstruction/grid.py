"""The coarse reconstruction grid: axis-aligned voxels over the chamber, and the exact map from
fine forward-mesh elements onto it (each element belongs to the voxel holding its centroid)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from .._warp import on_host, wp
from ..mesh.tetmesh import TetMesh

__all__ = ["VoxelGrid", "element_voxel_map"]


@dataclass(frozen=True)
class VoxelGrid:
    """Voxels of size ``spacing`` (3,) from ``origin`` (3,), ``shape`` (nx, ny, nz) cells."""

    origin: np.ndarray
    spacing: np.ndarray
    shape: tuple[int, int, int]

    @classmethod
    def covering(cls, mesh: TetMesh, n_cells: int = 7000, volume: float | None = None) -> "VoxelGrid":
        """Cubic voxels over the mesh's bounding box, sized so that ``volume`` (default: the
        box's) holds about ``n_cells`` of them."""
        if n_cells < 1:
            raise ValueError(f"n_cells = {n_cells}: must be >= 1")
        lo, hi = mesh.nodes.min(axis=0), mesh.nodes.max(axis=0)
        ext = hi - lo
        h = float(np.cbrt((np.prod(ext) if volume is None else volume) / n_cells))
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


def _child_barycentres(levels: int) -> np.ndarray:
    """Barycentric coordinates (8**levels, 4) of the centroids of the children of ``levels``
    uniform (red) refinements of a tetrahedron: equal-volume sample points."""
    from ..mesh.tetmesh import refine_uniform

    ref = TetMesh(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]]), np.array([[0, 1, 2, 3]]))
    for _ in range(levels):
        ref = refine_uniform(ref)
    c = ref.centroids
    return np.column_stack([1 - c.sum(axis=1), c])


wp.set_module_options({"enable_backward": False})


@wp.kernel
def _child_cells(x: wp.array(dtype=wp.vec3d), tets: wp.array2d(dtype=wp.int64), bary: wp.array(dtype=wp.vec4d),
                 origin: wp.vec3d, spacing: wp.vec3d, shape: wp.vec3i, cells: wp.array2d(dtype=wp.int32)):
    # the flat index of the voxel holding child s of element k (VoxelGrid.cell_of, clamped)
    k, s = wp.tid()
    b = bary[s]
    p = b[0] * x[tets[k, 0]] + b[1] * x[tets[k, 1]] + b[2] * x[tets[k, 2]] + b[3] * x[tets[k, 3]]
    q = wp.cw_div(p - origin, spacing)
    i = wp.clamp(int(wp.floor(q[0])), 0, shape[0] - 1)
    j = wp.clamp(int(wp.floor(q[1])), 0, shape[1] - 1)
    m = wp.clamp(int(wp.floor(q[2])), 0, shape[2] - 1)
    cells[k, s] = wp.int32((i * shape[1] + j) * shape[2] + m)


def _cells_of_children(mesh: TetMesh, grid: VoxelGrid, bary: np.ndarray) -> np.ndarray:
    """(n_tets, s) int32: the cell of each element's children at barycentrics ``bary`` (s, 4).
    One Warp kernel: the same in numpy (points, floor, clip, flat index) took ~6 s per pass
    over the paper's 323 k elements × 64 children."""
    if grid.n_cells >= 2**31:
        raise ValueError(f"grid: {grid.n_cells} cells, more than a 32-bit index holds")
    cells = np.empty((mesh.n_tets, len(bary)), np.int32)
    wp.launch(_child_cells, cells.shape, device="cpu", inputs=[
        on_host(mesh.nodes, wp.vec3d), on_host(mesh.tets, wp.int64), on_host(np.ascontiguousarray(bary, float), wp.vec4d),
        wp.vec3d(*grid.origin), wp.vec3d(*grid.spacing), wp.vec3i(*grid.shape), on_host(cells, wp.int32)])
    return cells


def element_voxel_map(mesh: TetMesh, grid: VoxelGrid) -> sp.csr_matrix:
    """C (n_tets, n_cells), C[k, c] = 1 when element k's centroid lies in cell c. Then
    J_coarse = J·C is the exact Jacobian for σ_k = σ_cell(k), and σ_fine = C·σ_coarse."""
    cell = grid.cell_of(mesh.centroids)
    return sp.csr_matrix((np.ones(mesh.n_tets), (np.arange(mesh.n_tets), cell)), shape=(mesh.n_tets, grid.n_cells))


@dataclass(frozen=True, eq=False)
class ChamberGrid:
    """The voxels of ``grid`` that hold saline, for reconstruction.

    ``active`` (n,) flat indices into the full grid; ``volume`` (n,) saline volume in each
    (a cell cut by the chamber wall holds less than a full voxel: volume fraction =
    volume / voxel volume); ``centroid`` (n, 3) the centroid of the saline in each cell;
    ``C`` (n_tets, n) the exact element → cell map (J_cells = J · C)."""

    grid: VoxelGrid
    active: np.ndarray
    volume: np.ndarray
    centroid: np.ndarray
    C: sp.csr_matrix

    @classmethod
    def over(cls, mesh: TetMesh, n_cells: int = 7000, grid: VoxelGrid | None = None, levels: int = 2) -> "ChamberGrid":
        """The cells of ``grid`` that hold saline; by default cubic voxels sized so that about
        ``n_cells`` of them fill the chamber (the paper's 7 k).

        Elements larger than a voxel straddle several, so each element is split among the
        cells by volume: it is subdivided ``levels`` times into 8 equal-volume children
        (64 for levels = 2) and each child goes to the cell holding its centroid. C[k, c] is
        then the fraction of element k in cell c (rows sum to 1), σ_fine = C σ_cells, and
        J_cells = J C is the exact Jacobian of that parametrisation."""
        if grid is None:
            # cut cells at the wall add to the count: size once, then correct the spacing
            volume = float(mesh.volumes.sum())
            first = cls.over(mesh, grid=VoxelGrid.covering(mesh, n_cells, volume=volume), levels=levels)
            g = VoxelGrid.covering(mesh, n_cells, volume=volume * first.n_cells / n_cells)
            return cls.over(mesh, grid=g, levels=levels)
        bary = _child_barycentres(levels)  # (s, 4)
        cells = _cells_of_children(mesh, grid, bary)
        active = np.flatnonzero(np.bincount(cells.ravel(), minlength=grid.n_cells))
        local = np.full(grid.n_cells, -1, np.int32)
        local[active] = np.arange(len(active), dtype=np.int32)
        # row k holds element k's children (s entries, a cell repeated as often as it has children)
        C = sp.csr_matrix(
            (np.full(cells.size, 1.0 / len(bary)), local[cells].ravel(), np.arange(0, cells.size + 1, len(bary))),
            shape=(mesh.n_tets, len(active)),
        )
        C.sum_duplicates()
        vol = mesh.volumes
        volume = C.T @ vol
        centroid = (C.T @ (vol[:, None] * mesh.centroids)) / volume[:, None]
        return cls(grid, active, volume, centroid, C)

    @property
    def n_cells(self) -> int:
        return len(self.active)

    def laplacian(self) -> sp.csr_matrix:
        """The graph Laplacian (n, n) of the saline cells, edges between face neighbours:
        xᵀLx = Σ over neighbouring cells of (x_i − x_j)², the smoothness prior's form."""
        shape = self.grid.shape
        ijk = np.stack(np.unravel_index(self.active, shape), axis=1)
        local = np.full(int(np.prod(shape)), -1, np.int64)
        local[self.active] = np.arange(self.n_cells)
        rows, cols = [], []
        for a in range(3):
            nb = ijk.copy()
            nb[:, a] += 1
            inside = nb[:, a] < shape[a]
            j = np.full(self.n_cells, -1)
            j[inside] = local[np.ravel_multi_index(nb[inside].T, shape)]
            ok = j >= 0
            rows.append(np.flatnonzero(ok))
            cols.append(j[ok])
        i, j = np.concatenate(rows), np.concatenate(cols)
        A = sp.coo_matrix((np.ones(len(i)), (i, j)), shape=(self.n_cells, self.n_cells))
        A = (A + A.T).tocsr()
        return (sp.diags(np.asarray(A.sum(axis=1)).ravel()) - A).tocsr()

    @property
    def voxel_volume(self) -> float:
        return float(np.prod(self.grid.spacing))

    @property
    def volume_fraction(self) -> np.ndarray:
        return self.volume / self.voxel_volume

    def to_full(self, values: np.ndarray, fill: float = np.nan) -> np.ndarray:
        """Values on the active cells scattered into the full (nx, ny, nz) grid."""
        out = np.full(self.grid.n_cells, fill, dtype=float)
        out[self.active] = values
        return out.reshape(self.grid.shape)
