"""A user's chamber surface file, read and checked (STL, OBJ, PLY, OFF): closed, consistently
wound, not crossing itself, its flat base on z = 0 and its top meeting the base along one loop
around the axis; and the plane geometry of its base outline (inside, distance to its sides).
Below ``scene``, whose parse reads the file through it (:func:`jointsim.scene.read_surface`
turns its errors into scene errors)."""

from __future__ import annotations

import functools
import hashlib
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["SurfaceError", "SurfaceFile", "SURFACE_SUFFIXES", "surface_file", "highest_above", "top_height", "segment_distance", "in_polygon",
           "crossing_faces"]

MM = 1e-3


class SurfaceError(ValueError):
    """A surface file that cannot be a chamber; the message names ``chamber.surface_file``."""


def segment_distance(q: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """Distances (k,) from the point ``q`` (2,) to the sides of the closed polygon ``poly`` (k, 2)."""
    a, b = poly, np.roll(poly, -1, axis=0)
    d = b - a
    t = np.clip(((q - a) * d).sum(axis=1) / np.maximum((d * d).sum(axis=1), 1e-300), 0.0, 1.0)
    return np.linalg.norm(a + t[:, None] * d - q, axis=1)


def in_polygon(xy: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """Whether the points ``xy`` (n, 2) lie inside the closed polygon ``poly`` (k, 2) (even-odd rule)."""
    a, b = poly[None], np.roll(poly, -1, axis=0)[None]
    x, y = xy[:, None, 0], xy[:, None, 1]
    crosses = (a[..., 1] > y) != (b[..., 1] > y)
    at = a[..., 0] + (y - a[..., 1]) * (b[..., 0] - a[..., 0]) / np.where(b[..., 1] != a[..., 1], b[..., 1] - a[..., 1], 1.0)
    return (crosses & (x < at)).sum(axis=1) % 2 == 1


def crossing_faces(v: np.ndarray, f: np.ndarray) -> tuple[int, int] | None:
    """Two faces of the surface (v (n, 3), f (m, 3)) that cross each other, or None. Candidate
    pairs are faces whose bounding spheres overlap (a k-d tree of their centres), faces sharing
    a vertex left out; each pair is tested as Möller's triangle–triangle test does: each
    triangle's corners straddle the other's plane, and the two triangles' intervals on the line
    where the planes meet overlap. Coplanar pairs are not reported."""
    from scipy.spatial import cKDTree

    p = v[f]  # (m, 3, 3)
    centre = p.mean(axis=1)
    radius = np.linalg.norm(p - centre[:, None], axis=2).max(axis=1)
    pairs = cKDTree(centre).query_pairs(2 * float(radius.max()), output_type="ndarray")
    if not len(pairs):
        return None
    a, b = pairs.T
    apart = (f[a][:, :, None] != f[b][:, None, :]).all(axis=(1, 2))
    near = np.linalg.norm(centre[a] - centre[b], axis=1) <= radius[a] + radius[b]
    a, b = a[apart & near], b[apart & near]
    if not len(a):
        return None
    A, B = p[a], p[b]
    nA = np.cross(A[:, 1] - A[:, 0], A[:, 2] - A[:, 0])
    nB = np.cross(B[:, 1] - B[:, 0], B[:, 2] - B[:, 0])
    scale = radius.max()
    dB = np.einsum("kj,kij->ki", nA, B - A[:, :1])  # B's corners against A's plane
    dA = np.einsum("kj,kij->ki", nB, A - B[:, :1])
    tolB = 1e-12 * np.linalg.norm(nA, axis=1, keepdims=True) * scale
    tolA = 1e-12 * np.linalg.norm(nB, axis=1, keepdims=True) * scale
    straddle = ((dB > tolB).any(1) & (dB < -tolB).any(1)) & ((dA > tolA).any(1) & (dA < -tolA).any(1))
    ok = np.flatnonzero(straddle & (np.linalg.norm(np.cross(nA, nB), axis=1) > 0))
    if not ok.size:
        return None
    A, B, dA, dB, a, b = A[ok], B[ok], dA[ok], dB[ok], a[ok], b[ok]
    line = np.cross(nA[ok], nB[ok])

    def interval(T: np.ndarray, d: np.ndarray) -> np.ndarray:
        """The triangle's segment on the planes' line: its corners' projections, cut where d changes sign."""
        proj = np.einsum("kij,kj->ki", T, line)
        ends = []
        for i, j in ((0, 1), (1, 2), (2, 0)):
            cut = (d[:, i] > 0) != (d[:, j] > 0)
            t = d[:, i] / np.where(cut, d[:, i] - d[:, j], 1.0)
            ends.append(np.where(cut, proj[:, i] + t * (proj[:, j] - proj[:, i]), np.nan))
        e = np.column_stack(ends)
        return np.column_stack([np.nanmin(e, axis=1), np.nanmax(e, axis=1)])

    with np.errstate(invalid="ignore", divide="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN rows: a triangle only touching the line
        ia, ib = interval(A, dA), interval(B, dB)
    overlap = (np.minimum(ia[:, 1], ib[:, 1]) - np.maximum(ia[:, 0], ib[:, 0])) > 1e-9 * scale * np.linalg.norm(line, axis=1)
    hit = np.flatnonzero(overlap)
    return (int(a[hit[0]]), int(b[hit[0]])) if hit.size else None


@dataclass(frozen=True, eq=False)
class SurfaceFile:
    """A user's chamber read from a surface file (:func:`read_surface`): ``vertices`` (n, 3) m,
    ``faces`` (m, 3) outward, ``base`` (m,) bool: the faces of the flat base on z = 0 (the rest
    is the deformable top, the membrane's inner surface), ``rim`` (k,) the top's boundary loop,
    anticlockwise seen from +z, and ``sha256`` of the file."""

    vertices: np.ndarray
    faces: np.ndarray
    base: np.ndarray
    rim: np.ndarray
    sha256: str


SURFACE_SUFFIXES = (".stl", ".obj", ".ply", ".off")


def highest_above(p: np.ndarray, xy: np.ndarray) -> tuple[int, np.ndarray] | None:
    """The highest of the triangles ``p`` (k, 3, 3) whose projection on z = 0 holds the point
    ``xy`` (2,), and the point's barycentrics (3,) on it; None where none does."""
    t = p[..., :2]
    d1, d2 = t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]
    det = d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]
    ok = det != 0
    r = np.asarray(xy, float) - t[:, 0]
    safe = np.where(ok, det, 1.0)
    l1 = np.where(ok, (r[:, 0] * d2[:, 1] - r[:, 1] * d2[:, 0]) / safe, -1.0)
    l2 = np.where(ok, (d1[:, 0] * r[:, 1] - d1[:, 1] * r[:, 0]) / safe, -1.0)
    lam = np.column_stack([1 - l1 - l2, l1, l2])
    inside = np.flatnonzero(ok & (lam >= -1e-12).all(axis=1))
    if not inside.size:
        return None
    k = int(inside[np.argmax(np.einsum("ka,ka->k", lam[inside], p[inside, :, 2]))])
    bary = np.clip(lam[k], 0.0, 1.0)
    return k, bary / bary.sum()


def top_height(sf: SurfaceFile, xy: np.ndarray) -> np.ndarray:
    """The height (k,) m of the top of a user's chamber above the points ``xy`` (k, 2) m of its
    base (its highest face there; NaN where none is above)."""
    p = sf.vertices[sf.faces[~sf.base]]
    out = np.full(len(np.atleast_2d(xy)), np.nan)
    for i, q in enumerate(np.atleast_2d(xy)):
        if (hit := highest_above(p, q)) is not None:
            out[i] = hit[1] @ p[hit[0], :, 2]
    return out


def surface_file(path: str | Path, unit: float = MM) -> SurfaceFile:
    """Read a user's chamber (once per version of the file: :func:`_read_surface`)."""
    path = Path(path)
    if not path.is_file():
        raise SurfaceError(f"chamber.surface_file = {str(path)!r}: no such file")
    return _read_surface(str(path), float(unit), path.stat().st_mtime_ns)


@functools.lru_cache(maxsize=4)
def _read_surface(path: str, unit: float, mtime_ns: int) -> SurfaceFile:
    """Read a user's chamber: a watertight, consistently wound triangle surface (STL, OBJ, PLY,
    OFF; lengths in ``unit`` m) whose flat base lies on z = 0 and whose other faces (the top,
    where the membrane is built) meet the base along one loop around the axis. Raises
    SceneError naming what is wrong."""
    import trimesh

    path = Path(path)
    key = f"chamber.surface_file = {str(path)!r}"
    if path.suffix.lower() not in SURFACE_SUFFIXES:
        raise SurfaceError(f"{key}: a triangle surface file ({', '.join(SURFACE_SUFFIXES)})")
    try:
        data = path.read_bytes()
        mesh = trimesh.load(path, force="mesh", process=True)
    except Exception as e:  # trimesh raises what its loaders raise
        raise SurfaceError(f"{key}: cannot read it ({type(e).__name__}: {e})") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise SurfaceError(f"{key}: holds no triangles")
    mesh.merge_vertices()
    if not mesh.is_watertight:
        raise SurfaceError(f"{key}: the surface is not watertight (closed); the chamber must be a closed volume")
    if not mesh.is_winding_consistent:
        raise SurfaceError(f"{key}: the surface's faces are not consistently wound")
    if mesh.volume < 0:
        mesh.invert()
    v = np.asarray(mesh.vertices, float) * unit
    f = np.asarray(mesh.faces, np.int64)
    if (k := crossing_faces(v, f)) is not None:
        raise SurfaceError(f"{key}: the surface intersects itself (faces {k[0]} and {k[1]} cross)")
    size = float(np.ptp(v, axis=0).max())
    if abs(v[:, 2].min()) > 1e-9 * size:
        raise SurfaceError(f"{key}: its lowest point is at z = {v[:, 2].min() / MM:g} mm; the flat base must lie on z = 0")
    v[np.abs(v[:, 2]) <= 1e-9 * size, 2] = 0.0
    base = np.all(v[f][..., 2] == 0.0, axis=1)
    if not base.any():
        raise SurfaceError(f"{key}: no faces on z = 0: the chamber needs its flat base there")
    if base.all():
        raise SurfaceError(f"{key}: every face is on z = 0: there is no top")
    # the top's boundary: edges used once by the top faces; one loop, turning once around the axis
    top = f[~base]
    e = top[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2)
    _, inverse, count = np.unique(np.sort(e, axis=1), axis=0, return_inverse=True, return_counts=True)
    edges = e[count[inverse.ravel()] == 1]
    nxt = dict(zip(edges[:, 1].tolist(), edges[:, 0].tolist()))  # walked against the top's winding: anticlockwise from +z
    loop = [int(edges[0, 1])]
    while len(loop) <= len(edges) and nxt.get(loop[-1]) is not None and nxt[loop[-1]] != loop[0]:
        loop.append(nxt[loop[-1]])
    rim = np.array(loop)
    if len(nxt) != len(edges) or len(rim) != len(edges):
        raise SurfaceError(f"{key}: the top (the faces off z = 0) must meet the base along one loop")
    angle = np.unwrap(np.arctan2(v[rim, 1], v[rim, 0]))
    if not np.all(np.diff(angle) > 0) and np.all(np.diff(angle) < 0):
        rim = rim[::-1]
        angle = np.unwrap(np.arctan2(v[rim, 1], v[rim, 0]))
    if not (np.all(np.diff(angle) > 0) and abs(angle[-1] - angle[0] + np.diff(angle).mean() - 2 * np.pi) < 1e-6):
        raise SurfaceError(f"{key}: the base's rim must run once around the axis (x = y = 0), seen from it")
    return SurfaceFile(v, f, base, rim, hashlib.sha256(data).hexdigest())
