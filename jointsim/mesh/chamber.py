"""The chamber mesh: tetrahedra of the saline volume from its surface (pytetwild / fTetWild),
graded toward the electrodes by a sizing field, with electrodes tagged exactly and meshes
cached on disk by content hash so one scene is never meshed twice."""

from __future__ import annotations

import contextlib
import hashlib
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial import Delaunay

from ..geometry import ElectrodeLayout, chamber_from_scene, electrode_layout
from ..scene import MeshSpec, Scene
from .electrodes import ElectrodePatch, disc_patches
from .tetmesh import MeshQuality, TetMesh, mesh_quality

__all__ = ["ChamberMesh", "mesh_chamber", "chamber_mesh", "sizing_field", "cache_dir"]

_MESHER_VERSION = "1"  # bump when the meshing recipe changes, so cached meshes are rebuilt


@dataclass(frozen=True, eq=False)
class ChamberMesh:
    """A meshed chamber: ``mesh``, ``electrodes`` (one patch per electrode, ring first, ground
    last), ``layout`` and the ``ground`` electrode index."""

    mesh: TetMesh
    electrodes: list[ElectrodePatch]
    layout: ElectrodeLayout
    key: str = ""

    @property
    def ground(self) -> int:
        return self.layout.ground

    def quality(self) -> MeshQuality:
        return mesh_quality(self.mesh)


def cache_dir() -> Path:
    """Mesh cache folder: $JOINTSIM_CACHE, else ~/.cache/jointsim/meshes."""
    root = os.environ.get("JOINTSIM_CACHE")
    return Path(root) if root else Path.home() / ".cache" / "jointsim" / "meshes"


def sizing_field(layout: ElectrodeLayout, spec: MeshSpec, bounds: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Background tetrahedra carrying the target edge length for fTetWild.

    h = h_max / refinement within ``refinement_zone`` of an electrode disc, growing linearly
    with distance at slope ``grading`` up to h_max. Points are dense only where h varies.
    Returns (points (n, 3), tets (m, 4), h (n,)).
    """
    h_max, h_min = spec.max_edge, spec.max_edge / spec.electrode_refinement
    lo, hi = bounds[0] - h_max, bounds[1] + h_max
    coarse = 2.0 * h_max
    axes = [np.arange(lo[i], hi[i] + coarse, coarse) for i in range(3)]
    pts = [np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)]
    # graded rings around each electrode: radial and vertical spacing growing from h_min
    steps = np.cumsum(h_min * 1.5 ** np.arange(40))
    steps = steps[steps < (h_max - h_min) / spec.grading + h_max]
    for c, r in zip(layout.centres, layout.radii):
        radii = np.concatenate([[0.0], r + spec.refinement_zone * np.linspace(-0.5, 1.0, 4), r + spec.refinement_zone + steps])
        zs = np.concatenate([[0.0], steps])
        for rr in radii:
            n = 1 if rr == 0 else max(6, int(np.ceil(2 * np.pi * rr / max(3 * h_min, 0.2 * rr))))
            a = 2 * np.pi * np.arange(n) / n
            ring = np.column_stack([c[0] + rr * np.cos(a), c[1] + rr * np.sin(a)])
            pts.append(np.column_stack([np.repeat(ring, len(zs), 0), np.tile(zs, len(ring))]))
    p = np.unique(np.round(np.vstack(pts), 12), axis=0)
    h = _target_size(p, layout, spec)
    tets = Delaunay(p).simplices.astype(np.int32)
    return p, tets, h


def _target_size(p: np.ndarray, layout: ElectrodeLayout, spec: MeshSpec) -> np.ndarray:
    h_max, h_min = spec.max_edge, spec.max_edge / spec.electrode_refinement
    rho = np.hypot(p[:, None, 0] - layout.centres[None, :, 0], p[:, None, 1] - layout.centres[None, :, 1])
    d = np.hypot(np.maximum(rho - layout.radii - spec.refinement_zone, 0.0), p[:, 2:3]).min(axis=1)
    return np.minimum(h_max, h_min + spec.grading * d)


def mesh_chamber(
    surface: trimesh.Trimesh,
    layout: ElectrodeLayout,
    spec: MeshSpec,
    *,
    use_cache: bool = True,
    num_threads: int = 0,
) -> ChamberMesh:
    """Tetrahedralise a watertight chamber surface (base on z = 0) and tag its electrodes.

    The result is cached under :func:`cache_dir` by a hash of the surface, the electrode layout
    and the mesh spec; a second call with the same inputs loads it instead of meshing."""
    if not surface.is_watertight:
        raise ValueError("surface: the chamber surface must be watertight")
    key = _hash(surface, layout, spec)
    path = cache_dir() / f"chamber-{key}.npz"
    if use_cache and path.is_file():
        with np.load(path) as d:
            mesh = TetMesh(d["nodes"], d["tets"])
    else:
        mesh = _tetrahedralise(surface, layout, spec, num_threads)
        if use_cache:
            _atomic_savez(path, nodes=mesh.nodes, tets=mesh.tets)
    return ChamberMesh(mesh, disc_patches(mesh, layout.centres, layout.radii), layout, key)


def chamber_mesh(scene: Scene, **kw) -> ChamberMesh:
    """The undeformed chamber of ``scene`` at its mesh resolution."""
    return mesh_chamber(chamber_from_scene(scene), electrode_layout(scene), scene.mesh, **kw)


def _tetrahedralise(surface: trimesh.Trimesh, layout: ElectrodeLayout, spec: MeshSpec, num_threads: int) -> TetMesh:
    import pytetwild  # imported here: it pulls in pyvista/vtk, which is slow to load

    bg_p, bg_t, bg_h = sizing_field(layout, spec, surface.bounds)
    diag = float(np.linalg.norm(np.ptp(surface.vertices, axis=0)))
    # fTetWild writes a side file (__tracked_surface.stl) into the working directory: keep it
    # out of the user's folder
    with tempfile.TemporaryDirectory() as scratch, contextlib.chdir(scratch):
        v, t = pytetwild.tetrahedralize(
            np.asarray(surface.vertices, float),
            np.asarray(surface.faces, np.int32),
            edge_length_abs=spec.max_edge,
            epsilon=spec.epsilon_rel,
            stop_energy=spec.stop_energy,
            num_opt_iter=spec.max_opt_iter,
            num_threads=num_threads,
            bg_vertices=bg_p,
            bg_tets=bg_t,
            bg_values=bg_h,
        )
    mesh = TetMesh(v, t).oriented()
    # fTetWild keeps the boundary within an envelope of the input; put the base back on z = 0
    # exactly so the electrode integrals are taken on the true plane
    f = mesh.boundary_faces
    snap_tol = 2 * spec.epsilon_rel * diag
    near = np.all(np.abs(mesh.nodes[f][..., 2]) <= snap_tol, axis=1)
    nodes = mesh.nodes.copy()
    nodes[np.unique(f[near]), 2] = 0.0
    mesh = TetMesh(nodes, mesh.tets)
    if (mesh.signed_volumes <= 0).any():
        raise RuntimeError("chamber mesh has inverted elements after snapping the base plane")
    return mesh


def _hash(surface: trimesh.Trimesh, layout: ElectrodeLayout, spec: MeshSpec) -> str:
    h = hashlib.sha256()
    h.update(_MESHER_VERSION.encode())
    for a in (surface.vertices, surface.faces, layout.centres, layout.radii):
        h.update(np.ascontiguousarray(a, dtype=np.float64).tobytes())
    h.update(repr((spec.max_edge, spec.electrode_refinement, spec.refinement_zone, spec.grading, spec.epsilon_rel, spec.stop_energy, spec.max_opt_iter)).encode())
    return h.hexdigest()[:20]


def _atomic_savez(path: Path, **arrays: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".tmp.npz")
    os.close(fd)
    try:
        np.savez_compressed(tmp, **arrays)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
