"""A geometric indentation of the dome by a sphere: no forces, only shape.

The target presses the outer membrane surface, which lies ``thickness`` outside the inner
chamber surface, so the inner surface is kept outside the inflated sphere of radius
R + thickness: vertices inside it are projected radially onto it, and the rest of the dome
follows by harmonic extension (the P1 Laplace–Beltrami problem on the dome with the contact
vertices and the bonded rim as Dirichlet data), the small-slope shape of a membrane under
uniform tension. Vertices the extension pushes into the sphere join the contact set and the
extension is repeated.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from ..geometry import DomeSurface

__all__ = ["Indentation", "indent_dome", "surface_stiffness", "first_contact_height"]


@dataclass(frozen=True, eq=False)
class Indentation:
    """The result: the ``dome`` after indentation, the target ``centre`` (3,) m and ``radius``,
    the ``contact`` vertex mask, the displaced saline ``volume`` (m³) and its ``centroid`` (3,)
    (the true centre of the perturbation that an image should find)."""

    dome: DomeSurface
    centre: np.ndarray
    radius: float
    contact: np.ndarray
    volume: float
    centroid: np.ndarray


def surface_stiffness(vertices: np.ndarray, faces: np.ndarray) -> sp.csr_matrix:
    """P1 stiffness ∫∇φ_a·∇φ_b on a triangle surface: (e_a·e_b)/(4A) per triangle, with e_a the
    edge opposite vertex a (the cotangent Laplacian)."""
    p = vertices[faces]
    e = np.stack([p[:, 2] - p[:, 1], p[:, 0] - p[:, 2], p[:, 1] - p[:, 0]], axis=1)  # (m, 3, 3)
    area = 0.5 * np.linalg.norm(np.cross(e[:, 0], e[:, 1]), axis=1)
    k = np.einsum("mai,mbi->mab", e, e) / (4 * area[:, None, None])
    rows = np.repeat(faces, 3, axis=1).ravel()
    cols = np.tile(faces, (1, 3)).ravel()
    n = len(vertices)
    return sp.csr_matrix((k.ravel(), (rows, cols)), shape=(n, n))


def first_contact_height(dome: DomeSurface, xy: np.ndarray, radius: float) -> float:
    """Height of the centre of a sphere of ``radius`` coming down vertically at ``xy`` when it
    first touches the dome's vertices (radius already including the membrane thickness)."""
    v = dome.vertices
    d2 = ((v[:, :2] - np.asarray(xy)[None]) ** 2).sum(axis=1)
    near = d2 < radius**2
    if not near.any():
        raise ValueError(f"target at xy = {np.asarray(xy) * 1e3} mm with radius {radius * 1e3:.3g} mm misses the dome")
    return float((v[near, 2] + np.sqrt(radius**2 - d2[near])).max())


def indent_dome(
    dome: DomeSurface,
    xy: tuple[float, float] | np.ndarray,
    depth: float,
    radius: float,
    thickness: float = 2e-3,
    max_rounds: int = 8,
) -> Indentation:
    """Press a sphere of ``radius`` (m) vertically into the dome at horizontal position ``xy``
    (m) to ``depth`` (m) beyond first contact with the outer membrane surface."""
    if radius <= 0:
        raise ValueError(f"radius = {radius}: must be > 0 m")
    if depth <= 0:
        raise ValueError(f"depth = {depth}: must be > 0 m (the target must touch the dome)")
    v0 = np.asarray(dome.vertices, float)
    R = radius + thickness
    zc = first_contact_height(dome, xy, R) - depth
    c = np.array([xy[0], xy[1], zc])
    if depth > 0.9 * (v0[:, 2].max()):
        raise ValueError(
            f"depth = {depth * 1e3:.3g} mm: must be below 90 % of the dome height "
            f"({0.9 * v0[:, 2].max() * 1e3:.3g} mm) so the chamber keeps a volume"
        )
    K = surface_stiffness(v0, dome.faces)
    fixed_rim = np.zeros(len(v0), bool)
    fixed_rim[dome.rim] = True
    contact = np.zeros(len(v0), bool)
    v = v0.copy()
    for _ in range(max_rounds):
        d = np.linalg.norm(v - c, axis=1)
        inside = d < R * (1 - 1e-9)
        if not inside.any():
            break
        contact |= inside
        target = v.copy()
        target[inside] = c + R * (v[inside] - c) / d[inside, None]
        u = np.zeros_like(v0)
        u[contact] = target[contact] - v0[contact]
        fixed = contact | fixed_rim
        free = ~fixed
        Kff = K[free][:, free].tocsc()
        Kfc = K[free][:, fixed]
        u[free] = spla.splu(Kff).solve(-(Kfc @ u[fixed]))
        v = v0 + u
    else:
        raise RuntimeError(f"indentation did not settle in {max_rounds} rounds of contact updates")
    if not contact.any():
        raise ValueError("the target does not touch the dome at this depth")
    deformed = DomeSurface(v, dome.faces, dome.rim)
    vol, cen = displaced_volume(dome, deformed)
    return Indentation(deformed, c, radius, contact, vol, cen)


def displaced_volume(dome: DomeSurface, deformed: DomeSurface) -> tuple[float, np.ndarray]:
    """Volume between the two surfaces (m³, positive when the chamber shrinks) and its centroid,
    from the signed volumes of the tetrahedra each surface triangle spans with the origin."""
    def cone(v):
        p = v[dome.faces]
        vol = np.einsum("mi,mi->m", p[:, 0], np.cross(p[:, 1], p[:, 2])) / 6
        return vol, p.sum(axis=1) / 4  # each cone's centroid: (0 + p0 + p1 + p2)/4

    v_a, c_a = cone(dome.vertices)
    v_b, c_b = cone(deformed.vertices)
    dvol = v_a.sum() - v_b.sum()
    moment = (v_a[:, None] * c_a).sum(0) - (v_b[:, None] * c_b).sum(0)
    return float(dvol), moment / dvol if dvol != 0 else np.full(3, np.nan)
