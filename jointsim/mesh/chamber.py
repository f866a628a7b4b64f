"""The chamber mesh: tetrahedra of the saline volume from its surface (gmsh), graded toward the
electrodes by a sizing field, with the electrode outlines embedded in the base, electrodes
tagged exactly, and meshes cached on disk by content hash.

The mesher is deterministic: the same surface, layout and mesh spec give the same nodes and
tetrahedra bit for bit, from an empty cache, on any machine (gmsh runs on one thread, reads no
configuration file, and takes its sizes from a closed-form field). fTetWild, used before, gave
a different mesh on every run, even on one thread, so every figure downstream depended on
which run had meshed first.

Two gmsh passes: the base (the surface's faces on z = 0) is re-meshed as a plane bounded by its
rim, with each electrode's circle embedded and sizes from the field; then the volume is filled
inside the given non-base faces (kept as they are: the saline volume is the surface's) and the
new base, and optimised (gmsh's and Netgen's passes). Sizes follow
h(x) = min(h_max, h_min + grading · d(x)), d the distance to the nearest electrode's disc
widened by ``refinement_zone``; h_min = h_max / electrode_refinement."""

from __future__ import annotations

import hashlib
import importlib.metadata
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from ..geometry import DOME_RIM_VERTICES, ElectrodeLayout, chamber_cap, chamber_surface, electrode_layout, user_surface
from ..scene import MeshSpec, Scene
from .electrodes import ElectrodePatch, carry_patches, disc_patches, layout_patches
from .gmsh_session import compact, gmsh_session, size_field
from .tetmesh import MeshQuality, TetMesh, mesh_quality

__all__ = ["ChamberMesh", "mesh_chamber", "chamber_mesh", "reference_surface", "cache_dir"]

_MESHER_VERSION = "2-gmsh"  # bump when the meshing recipe changes, so cached meshes are rebuilt


@dataclass(frozen=True, eq=False)
class ChamberMesh:
    """A meshed chamber: ``mesh``, ``electrodes`` (one patch per electrode, ring first, ground
    last; those on the membrane as they were placed, see :meth:`patches`), ``layout`` and the
    ``ground`` electrode index. ``carried``: on a remesh of a deformed chamber with electrodes
    on the membrane, the index here of each node of the chamber it was made from (−1: none), by
    which patches placed on that one are carried here (:meth:`carry`)."""

    mesh: TetMesh
    electrodes: list[ElectrodePatch]
    layout: ElectrodeLayout
    key: str = ""
    carried: np.ndarray | None = None

    @property
    def ground(self) -> int:
        return self.layout.ground

    def quality(self) -> MeshQuality:
        return mesh_quality(self.mesh)

    def patches(self, order: int) -> list[ElectrodePatch]:
        """The electrode patches for elements of ``order`` where the nodes are now: the
        chamber's own (P1 moments), or for P2 clipped again from the same discs with P2
        moments; those on the membrane (which have both) followed to the nodes
        (:meth:`ElectrodePatch.follow`)."""
        patches = list(self.electrodes)
        if order == 2 and any(p.q1 is None for p in patches):
            base = np.flatnonzero(self.layout.clipped)
            for i, p in zip(base, disc_patches(self.mesh, self.layout.centres[base], self.layout.radii[base], quadratic=True)):
                patches[i] = p
        return [p.follow(self.mesh.nodes) for p in patches]

    def carry(self, patches: list[ElectrodePatch], order: int) -> list[ElectrodePatch]:
        """``patches`` (placed on the chamber this one was remeshed from; one per electrode)
        here: those on the membrane carried over (:attr:`carried`) and followed to the nodes,
        the others as :meth:`patches` has them."""
        own = self.patches(order)
        if self.carried is None or not self.layout.membrane.any():
            return own
        moved = carry_patches(patches, self.carried)
        return [own[i] if m is None else m.follow(self.mesh.nodes) for i, m in enumerate(moved)]


def cache_dir() -> Path:
    """Mesh cache folder: $JOINTSIM_CACHE, else ~/.cache/jointsim/meshes."""
    root = os.environ.get("JOINTSIM_CACHE")
    return Path(root) if root else Path.home() / ".cache" / "jointsim" / "meshes"


def _size_expression(layout: ElectrodeLayout, spec: MeshSpec) -> str:
    """The size field h(x) = min(h_max, h_min + grading · d(x)) (module docstring) as a gmsh
    MathEval expression in x, y, z; with ``rim_refinement`` > 1 also
    min(·, h_max / rim_refinement + grading · d_rim(x)), d_rim the distance to the nearest
    electrode's outline (its rim circle)."""
    d = d_rim = None
    for (x0, y0, z0), r, up, face in zip(layout.centres, layout.radii, layout.membrane, layout.face):
        if face:  # a whole face of the chamber: no rim to grade towards
            continue
        if up:  # on the membrane: from the 3-D distance to its centre, on the nominal cap
            dist = f"Sqrt((x-({x0:.17g}))^2+(y-({y0:.17g}))^2+(z-({z0:.17g}))^2)"
            term = f"Max({dist}-{r + spec.refinement_zone:.17g},0)"
            rim = f"Abs({dist}-{r:.17g})"
        else:
            rho = f"Sqrt((x-({x0:.17g}))^2+(y-({y0:.17g}))^2)"
            term = f"Sqrt(Max({rho}-{r + spec.refinement_zone:.17g},0)^2+z^2)"
            rim = f"Sqrt(Abs({rho}-{r:.17g})^2+z^2)"
        d = term if d is None else f"Min({d},{term})"
        d_rim = rim if d_rim is None else f"Min({d_rim},{rim})"
    if d is None:  # whole-face electrodes only: nothing to grade towards
        return f"{spec.max_edge:.17g}"
    h = f"Min({spec.max_edge:.17g},{spec.max_edge / spec.electrode_refinement:.17g}+{spec.grading:.17g}*{d})"
    if spec.rim_refinement > 1.0:
        h = f"Min({h},{spec.max_edge / spec.rim_refinement:.17g}+{spec.grading:.17g}*{d_rim})"
    return h


def mesh_chamber(
    surface: trimesh.Trimesh,
    layout: ElectrodeLayout,
    spec: MeshSpec,
    *,
    use_cache: bool = True,
    carry_from: ChamberMesh | None = None,
) -> ChamberMesh:
    """Tetrahedralise a watertight chamber surface (base on z = 0) and tag its electrodes.

    The faces on z = 0 (the base) are re-meshed with the electrode outlines embedded; the
    others are kept as they are. The result is cached under :func:`cache_dir` by a hash
    of the surface, the electrode layout and the mesh spec; a second call with the same inputs
    loads it instead of meshing (and meshing again would give the same mesh).

    Electrodes on the membrane are placed on the dome's faces (where the layout puts them), or,
    for a remesh of ``carry_from`` (a deformed chamber whose boundary is ``surface``), carried
    over from it by its dome nodes, which the mesher keeps (:attr:`ChamberMesh.carried`)."""
    if not surface.is_watertight:
        raise ValueError("surface: the chamber surface must be watertight")
    if len(surface.faces) == 0 or not np.all(np.isfinite(surface.vertices)):
        raise ValueError("surface: the chamber surface has no faces or a non-finite vertex")
    key = _hash(surface, layout, spec)
    path = cache_dir() / f"chamber-{key}.npz"
    if use_cache and path.is_file():
        with np.load(path) as d:
            mesh = TetMesh(d["nodes"], d["tets"])
    else:
        mesh = _tetrahedralise(surface, layout, spec)
        if use_cache:
            _atomic_savez(path, nodes=mesh.nodes, tets=mesh.tets)
    if carry_from is None or not layout.membrane.any():
        return ChamberMesh(mesh, layout_patches(mesh, layout), layout, key)
    carried = _node_map(carry_from.mesh.nodes, mesh.nodes)
    own = layout_patches(mesh, layout, only=~layout.membrane)
    patches = [p if p is not None else o for p, o in zip(carry_patches(carry_from.electrodes, carried), own)]
    return ChamberMesh(mesh, patches, layout, key, carried)


def _node_map(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """For each point of ``source`` (n, 3), the index of the point of ``target`` at the same place
    (to 1e-9 of the extent), −1 where none is."""
    from scipy.spatial import cKDTree

    tol = 1e-9 * float(np.ptp(target, axis=0).max())
    dist, index = cKDTree(target).query(source, distance_upper_bound=tol)
    return np.where(np.isfinite(dist), index, -1)


def chamber_mesh(scene: Scene, **kw) -> ChamberMesh:
    """The undeformed chamber of ``scene`` at its mesh resolution (:func:`reference_surface`)."""
    return mesh_chamber(reference_surface(scene), electrode_layout(scene), scene.mesh, **kw)


def reference_surface(scene: Scene) -> trimesh.Trimesh:
    """The undeformed chamber surface given to the mesher: the dome as near-equilateral
    triangles with ``[mesh] dome_rim_vertices`` on the rim, or where that is 0 of edge ≤
    max_edge, at least ``DOME_RIM_VERTICES`` on the rim (kept by the mesher: they bound the
    saline volume)."""
    c = scene.chamber
    if c.surface_file is not None:  # a user's chamber: its own surface, base and top as the file has them
        return user_surface(c)
    if scene.mesh.dome_rim_vertices:
        return chamber_surface(chamber_cap(c, scene.mesh.dome_rim_vertices))
    n_rim = 16 * int(np.ceil(2 * np.pi * c.base_radius / scene.mesh.max_edge / 16))
    return chamber_surface(chamber_cap(c, max(DOME_RIM_VERTICES, n_rim)))


def _tetrahedralise(surface: trimesh.Trimesh, layout: ElectrodeLayout, spec: MeshSpec) -> TetMesh:
    v = np.asarray(surface.vertices, float)
    f = np.asarray(surface.faces, np.int64)
    tol = 1e-9 * float(np.ptp(v, axis=0).max())
    on_base = np.all(np.abs(v[f][..., 2]) <= tol, axis=1)
    if not on_base.any():
        raise ValueError("surface: the chamber surface has no base (no faces on z = 0)")
    rim = _boundary_loop(f[on_base])
    base_xy, base_tri, rim_nodes = _mesh_base(v[rim, :2], layout, spec)
    # the base's own nodes after the surface's; its rim nodes are the surface's rim vertices
    index = np.full(len(base_xy), -1)
    index[rim_nodes] = rim
    inner = index < 0
    index[inner] = len(v) + np.arange(inner.sum())
    vertices = np.vstack([v, np.column_stack([base_xy[inner], np.zeros(inner.sum())])])
    faces = np.vstack([f[~on_base], index[base_tri]])
    mesh = _fill(vertices, faces, layout, spec)
    if (mesh.signed_volumes <= 0).any():
        raise RuntimeError("chamber mesh: gmsh returned inverted elements")
    return mesh




def _boundary_loop(faces: np.ndarray) -> np.ndarray:
    """The vertices of the boundary of a disc-like triangle set, in order around it: (n,)."""
    e = faces[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2)
    key = np.sort(e, axis=1)
    _, inverse, count = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    edges = e[count[inverse.ravel()] == 1]  # boundary edges, as oriented in their face
    nxt = dict(zip(edges[:, 0].tolist(), edges[:, 1].tolist()))
    if len(nxt) != len(edges):
        raise ValueError("surface: the base's boundary is not one simple loop")
    loop = [int(edges[0, 0])]
    while len(loop) <= len(edges):
        loop.append(nxt[loop[-1]])
        if loop[-1] == loop[0]:
            break
    if len(loop) != len(edges) + 1:
        raise ValueError("surface: the base's boundary is not one simple loop")
    return np.array(loop[:-1])


def _mesh_base(rim: np.ndarray, layout: ElectrodeLayout, spec: MeshSpec) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The base as a plane triangulated inside the polygon ``rim`` (n, 2) (its sides not split),
    with every electrode's circle embedded. Returns nodes (m, 2), triangles (k, 3) facing −z,
    and the node index of each rim vertex (n,)."""
    with gmsh_session("chamber") as gmsh:
        geo = gmsh.model.geo
        corners = [geo.addPoint(x, y, 0.0) for x, y in rim]
        sides = [geo.addLine(corners[i], corners[(i + 1) % len(corners)]) for i in range(len(corners))]
        plane = geo.addPlaneSurface([geo.addCurveLoop(sides)])
        arcs = []
        for (x0, y0, _), r in zip(layout.centres[layout.clipped], layout.radii[layout.clipped]):
            centre = geo.addPoint(x0, y0, 0.0)
            q = [geo.addPoint(x0 + r * c, y0 + r * s, 0.0) for c, s in ((1, 0), (0, 1), (-1, 0), (0, -1))]
            arcs += [geo.addCircleArc(q[i], centre, q[(i + 1) % 4]) for i in range(4)]
        geo.synchronize()
        if arcs:  # (gmsh aborts on an empty embedding)
            gmsh.model.mesh.embed(1, arcs, 2, plane)
        for side in sides:
            gmsh.model.mesh.setTransfiniteCurve(side, 2)  # the rim stays the surface's rim
        size_field(gmsh, _size_expression(layout, spec))
        gmsh.model.mesh.generate(2)
        tags, xyz, _ = gmsh.model.mesh.getNodes()
        _, tri = gmsh.model.mesh.getElementsByType(2, plane)
        rim_tags = [int(gmsh.model.mesh.getNodes(0, c)[0][0]) for c in corners]
    # the circle centres are geometry only, on no triangle: dropped
    nodes, tri, index_of_tag = compact(tags, xyz, tri, 3)
    xy = nodes[:, :2]
    a, b, c = xy[tri[:, 0]], xy[tri[:, 1]], xy[tri[:, 2]]
    up = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0]) > 0
    tri[up] = tri[up][:, ::-1]  # the base's normal is −z, outward
    return xy, tri, index_of_tag[rim_tags]


def _fill(vertices: np.ndarray, faces: np.ndarray, layout: ElectrodeLayout, spec: MeshSpec) -> TetMesh:
    """Tetrahedra filling the closed triangle surface (vertices, faces), its faces kept."""
    with gmsh_session("chamber") as gmsh:
        shell = gmsh.model.addDiscreteEntity(2)
        gmsh.model.mesh.addNodes(2, shell, np.arange(1, len(vertices) + 1), vertices.ravel())
        gmsh.model.mesh.addElementsByType(shell, 2, [], (faces + 1).ravel())
        gmsh.model.geo.addVolume([gmsh.model.geo.addSurfaceLoop([shell])])
        gmsh.model.geo.synchronize()
        size_field(gmsh, _size_expression(layout, spec))
        gmsh.model.mesh.generate(3)
        tags, xyz, _ = gmsh.model.mesh.getNodes()
        _, tets = gmsh.model.mesh.getElementsByType(4)
    if len(tets) == 0:
        raise ValueError("surface: gmsh could not fill the chamber surface (self-intersecting or not closed?)")
    nodes, tets, _ = compact(tags, xyz, tets, 4)
    return TetMesh(nodes, tets).oriented()


def _hash(surface: trimesh.Trimesh, layout: ElectrodeLayout, spec: MeshSpec) -> str:
    h = hashlib.sha256()
    h.update(f"{_MESHER_VERSION} gmsh {importlib.metadata.version('gmsh')}".encode())
    for a in (surface.vertices, surface.faces, layout.centres, layout.radii):
        h.update(np.ascontiguousarray(a, dtype=np.float64).tobytes())
    h.update(repr((spec.max_edge, spec.electrode_refinement, spec.refinement_zone, spec.grading)).encode())
    if spec.rim_refinement > 1.0:  # off, the field and the key are what they were before the rim term
        h.update(repr(("rim", spec.rim_refinement)).encode())
    if layout.membrane.any() or layout.face.any():  # (the patches are not in the cached file; the size field is)
        h.update(layout.membrane.tobytes() + layout.face.tobytes())
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
