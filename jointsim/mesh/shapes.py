"""Simple structured tetrahedral meshes for closed-form checks and quick studies."""

from __future__ import annotations

import numpy as np

from .tetmesh import TetMesh

__all__ = ["box_mesh", "grid_mesh", "graded_axis", "cylinder_mesh", "octant_triangles", "shell_octant", "spherical_midsides"]

# Kuhn subdivision of the unit cube into 6 tetrahedra sharing the diagonal 0-7; conforming
# across neighbouring cubes because every cube is split the same way.
_KUHN = np.array([[0, 1, 3, 7], [0, 1, 5, 7], [0, 2, 3, 7], [0, 2, 6, 7], [0, 4, 5, 7], [0, 4, 6, 7]])


def box_mesh(size: tuple[float, float, float], shape: tuple[int, int, int], origin=(0.0, 0.0, 0.0)) -> TetMesh:
    """Box [origin, origin + size] split into shape = (nx, ny, nz) cubes of 6 tets each."""
    return grid_mesh(*[np.linspace(o, o + s, n + 1) for o, s, n in zip(origin, size, shape)])


def graded_axis(length: float, h0: float, ratio: float) -> np.ndarray:
    """Coordinates 0 … length with the first cell h0 and each next one ``ratio`` times larger
    (the last cell absorbs the remainder)."""
    if not (0 < h0 < length and ratio >= 1):
        raise ValueError("graded_axis: need 0 < h0 < length and ratio >= 1")
    x = [0.0]
    h = h0
    while x[-1] + h < length - 0.5 * h:
        x.append(x[-1] + h)
        h *= ratio
    x.append(length)
    return np.array(x)


def grid_mesh(xs: np.ndarray, ys: np.ndarray, zs: np.ndarray) -> TetMesh:
    """Tensor-product grid with the given node coordinates along each axis, 6 tets per cell."""
    axes = [np.asarray(a, float) for a in (xs, ys, zs)]
    nx, ny, nz = (len(a) - 1 for a in axes)
    X, Y, Z = np.meshgrid(*axes, indexing="ij")
    nodes = np.column_stack([X.ravel(), Y.ravel(), Z.ravel()])
    idx = np.arange(nodes.shape[0]).reshape(nx + 1, ny + 1, nz + 1)
    i, j, k = np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij")
    corners = np.stack(
        [idx[i + (c & 1), j + ((c >> 1) & 1), k + ((c >> 2) & 1)].ravel() for c in range(8)], axis=1
    )
    tets = corners[:, _KUHN].reshape(-1, 4)
    return TetMesh(nodes, tets).oriented()


def cylinder_mesh(radius: float, length: float, n_radial: int, n_axial: int) -> TetMesh:
    """Cylinder along z from 0 to ``length``: a box mesh of the square [-1, 1]² mapped onto the
    disc (concentric squares to circles), so the cross-section is a polygon close to the disc."""
    m = box_mesh((2.0, 2.0, length), (2 * n_radial, 2 * n_radial, n_axial), origin=(-1.0, -1.0, 0.0))
    x, y = m.nodes[:, 0], m.nodes[:, 1]
    # the elliptical grid mapping: smooth, bijective, keeps the square's edges on the circle
    u = x * np.sqrt(1 - y * y / 2)
    v = y * np.sqrt(1 - x * x / 2)
    nodes = np.column_stack([radius * u, radius * v, m.nodes[:, 2]])
    return TetMesh(nodes, m.tets).oriented()


def octant_triangles(n: int) -> tuple[np.ndarray, np.ndarray]:
    """The flat triangle with its corners on the three axes cut into n² triangles, its vertices
    projected onto the unit sphere: (unit directions (k, 3), triangles (n², 3) with sorted
    vertex numbers). Vertices on the coordinate planes lie on them exactly."""
    i, j = np.triu_indices(n + 1)  # (i, j - i): every pair with i + (j - i) ≤ n
    j = j - i
    flat = np.column_stack([i, j, n - i - j]) / n
    direction = flat / np.linalg.norm(flat, axis=1, keepdims=True)
    idx = np.full((n + 1, n + 1), -1)
    idx[i, j] = np.arange(len(i))
    a, b = np.triu_indices(n)  # cells (a, b - a) with a + (b - a) ≤ n − 1
    b = b - a
    up = np.column_stack([idx[a, b], idx[a + 1, b], idx[a, b + 1]])
    d = a + b < n - 1
    down = np.column_stack([idx[a + 1, b][d], idx[a + 1, b + 1][d], idx[a, b + 1][d]])
    return direction, np.sort(np.vstack([up, down]), axis=1)


def shell_octant(inner: float, outer: float, n: int, layers: int) -> TetMesh:
    """The octant x, y, z ≥ 0 of the spherical shell inner ≤ r ≤ outer about the origin:
    :func:`octant_triangles` extruded through ``layers`` equal radial layers (level l's copy of
    vertex i is node l·k + i), each prism cut into three tets. The cuts of a prism's side faces
    follow the node numbers (the diagonal from the larger-numbered bottom node to the
    smaller-numbered top one), so neighbouring prisms conform. Nodes on the coordinate planes
    lie on them exactly: symmetry conditions apply there."""
    if not (0 < inner < outer and n >= 1 and layers >= 1):
        raise ValueError("shell_octant: need 0 < inner < outer, n >= 1 and layers >= 1")
    direction, tri = octant_triangles(n)
    ns = len(direction)
    nodes = (np.linspace(inner, outer, layers + 1)[:, None, None] * direction).reshape(-1, 3)
    lo = (ns * np.arange(layers))[:, None, None] + tri[None]  # (layers, k, 3) bottom corners
    hi = lo + ns
    p, q, r = np.moveaxis(lo, 2, 0)
    P, Q, R = np.moveaxis(hi, 2, 0)
    tets = np.stack([np.stack(t, -1) for t in ((p, q, r, P), (q, r, P, Q), (r, P, Q, R))], 2)
    return TetMesh(nodes, tets.reshape(-1, 4)).oriented()


def spherical_midsides(ends: np.ndarray) -> np.ndarray:
    """Midside nodes for :meth:`P2Mesh.from_linear` on a mesh of spherical shells about the
    origin: each at its edge's mean radius, in the direction of the great-circle midpoint, so
    the isoparametric elements follow the spheres."""
    r = np.linalg.norm(ends, axis=2)
    d = (ends / r[:, :, None]).sum(axis=1)
    return r.mean(axis=1)[:, None] * d / np.linalg.norm(d, axis=1, keepdims=True)
