"""The membrane's mesh: prism layers through the thickness on the inner chamber surface, split
into conforming tetrahedra, and the placement of the P2 and wedge elements' midside nodes (on
the concentric spheres of a spherical dome, on the rim's circle of a flat sheet). Below the
element modules (fem, wedge) and the models (dome, soft_target), which all build on it."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ..geometry import DomeSurface
from ..mesh.tetmesh import TetMesh

__all__ = ["membrane_mesh", "split_prisms", "vertex_normals", "is_flat", "sphere_centre", "on_spheres", "on_rim_circle"]


def vertex_normals(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Unit normals (n, 3) of a triangulated surface's vertices (v (n, 3), f (m, 3)), each the
    normalised sum of its faces' area-weighted normals."""
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    vn = np.zeros_like(v)
    for k in range(3):
        np.add.at(vn, f[:, k], n)
    return vn / np.linalg.norm(vn, axis=1, keepdims=True)


def is_flat(dome: DomeSurface) -> bool:
    """Whether ``dome`` lies in the base plane: a membrane moulded flat (:func:`~jointsim.geometry.flat_disc`)."""
    return not np.any(np.asarray(dome.vertices)[:, 2])


def sphere_centre(dome: DomeSurface, rtol: float = 1e-6) -> np.ndarray | None:
    """The centre of the sphere the dome's vertices lie on (to ``rtol`` of its radius), or None
    when they do not (an inflated or otherwise deformed surface)."""
    if is_flat(dome):  # a plane: a sphere of infinite radius
        return None
    v = np.asarray(dome.vertices, float)
    # |v|² = 2 c·v + (R² − |c|²): linear in c and the constant
    A = np.column_stack([2 * v, np.ones(len(v))])
    sol = np.linalg.lstsq(A, (v**2).sum(axis=1), rcond=None)[0]
    c = sol[:3]
    r = np.linalg.norm(v - c, axis=1)
    return c if np.ptp(r) <= rtol * r.mean() else None


def on_spheres(centre: np.ndarray, base_tol: float) -> Callable[[np.ndarray], np.ndarray]:
    """Midside-node placement for a membrane on a spherical dome (for ``P2Mesh.from_linear``):
    each edge's node on the sphere about ``centre`` through the mean distance of its ends — the
    concentric inner, layer and outer surfaces, and straight through the thickness — except edges
    in the base plane (|z| ≤ ``base_tol``), whose nodes follow the rim's circles in that plane."""
    c = np.asarray(centre, float)

    def place(ends: np.ndarray) -> np.ndarray:
        mid = ends.mean(axis=1)
        d = mid - c
        r = np.linalg.norm(ends - c, axis=2).mean(axis=1)
        out = c + r[:, None] * d / np.linalg.norm(d, axis=1, keepdims=True)
        flat = np.all(np.abs(ends[:, :, 2]) <= base_tol, axis=1)
        rho = np.linalg.norm(ends[flat, :, :2], axis=2).mean(axis=1)
        xy = mid[flat, :2]
        out[flat] = np.column_stack([rho[:, None] * xy / np.linalg.norm(xy, axis=1, keepdims=True), mid[flat, 2]])
        return out

    return place


def on_rim_circle(radius: float) -> Callable[[np.ndarray], np.ndarray]:
    """Midside-node placement for a membrane moulded flat (for ``P2Mesh.from_linear``): edge
    midpoints, except on the edge face, where edges between two nodes on the cylinder of
    ``radius`` get their node on it: the sheet is a true disc, and the whole face is bonded (a
    node left on a chord inside it would be free and let the clamp rotate: +7-9 % deflection of
    a clamped plate, converging slowly)."""

    def place(ends: np.ndarray) -> np.ndarray:
        mid = ends.mean(axis=1)
        on = np.all(np.hypot(ends[:, :, 0], ends[:, :, 1]) >= radius * (1 - 1e-9), axis=1)
        mid[on, :2] *= radius / np.hypot(mid[on, 0], mid[on, 1])[:, None]
        return mid

    return place


def membrane_mesh(dome: DomeSurface, thickness: float, layers: int = 2, centre: np.ndarray | None = None) -> tuple[TetMesh, int]:
    """Tetrahedra of the membrane: ``layers`` prism layers from the inner surface ``dome``
    outward by ``thickness`` along the vertex normals — radial from ``centre`` when the dome is a
    sphere about it — kept horizontal at the rim so the bonded edge stays on the base plane (on
    a sphere, out to where each concentric layer sphere meets that plane).
    Layer l's copy of dome vertex i is node l·n + i. Returns the mesh and n (the number of dome
    vertices)."""
    if thickness <= 0:
        raise ValueError(f"thickness = {thickness}: must be > 0 m")
    v, f = np.asarray(dome.vertices, float), np.asarray(dome.faces)
    n = len(v)
    normal = vertex_normals(v, f) if centre is None else (v - centre) / np.linalg.norm(v - centre, axis=1, keepdims=True)
    if not is_flat(dome):  # a flat sheet's edge stands upright through its thickness
        normal[dome.rim, 2] = 0.0  # the rim grows outward in the base plane
        normal[dome.rim] /= np.linalg.norm(normal[dome.rim], axis=1, keepdims=True)
    offsets = (np.arange(layers + 1) / layers * thickness)[:, None] * np.ones(n)  # (layer, vertex)
    if centre is not None:
        # a shell of concentric spheres cut by the base plane: the rim's layer l sits where the
        # sphere of radius R + s_l meets that plane, so the membrane keeps its full thickness to
        # the bond (grown by s_l in the plane it would thin to s_l·ρ/R there)
        rim = v[dome.rim]
        R = np.linalg.norm(rim - centre, axis=1)
        rho = np.linalg.norm(rim[:, :2] - centre[:2], axis=1)
        h2 = R**2 - rho**2  # the centre's squared height off the plane, each rim vertex
        offsets[:, dome.rim] = np.sqrt((R + offsets[:, dome.rim]) ** 2 - h2) - rho
    nodes = np.vstack([v + offsets[l, :, None] * normal for l in range(layers + 1)])
    tets = []
    for l in range(layers):
        a, b = l * n + f, (l + 1) * n + f  # bottom and top triangles of each prism
        # split each prism into 3 tets by the rule "start from the smallest vertex index", which
        # makes the diagonals on shared quad faces agree between neighbouring prisms
        tets.append(split_prisms(a, b))
    t = np.vstack(tets)
    return TetMesh(nodes, t).oriented(), n


def split_prisms(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Prisms (a0 a1 a2 / b0 b1 b2), ai below bi and every b index above every a index, into 3
    tetrahedra each, conforming: each quad side face is cut along the diagonal from its smaller
    bottom index to the other corner's top copy, a rule that depends on the face alone, so two
    prisms sharing the face cut it alike (a cut that depended on the prism would leave the two
    sides' triangles, and their P2 midside nodes, unshared: a mesh cracked along every face)."""
    # rotate each triangle so its smallest global index comes first
    r = np.argmin(a, axis=1)
    idx = (r[:, None] + np.arange(3)) % 3
    a = np.take_along_axis(a, idx, 1)
    b = np.take_along_axis(b, idx, 1)
    a0, a1, a2 = a.T
    b0, b1, b2 = b.T
    # a0 is the smallest: the two faces through it are cut a0–b1 and a0–b2, which leaves the
    # tetrahedron (a0 b0 b1 b2) and the pyramid a0 over the quad (a1 a2 b2 b1), cut by the rule
    use1 = (a1 < a2)[:, None]  # the quad's cut: a1–b2, else a2–b1
    t1 = np.column_stack([a0, b0, b1, b2])
    t2 = np.where(use1, np.column_stack([a0, a1, a2, b2]), np.column_stack([a0, a1, a2, b1]))
    t3 = np.where(use1, np.column_stack([a0, a1, b2, b1]), np.column_stack([a0, a2, b2, b1]))
    return np.vstack([t1, t2, t3])
