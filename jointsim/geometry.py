"""Sensor geometry: the domed saline chamber's surface and the electrode layout on its base.

The chamber is a flat base (z = 0, outward normal −z; a disc, or for an elongated pad an
ellipse) closed by a dome. The dome is passed around as a :class:`DomeSurface` (a triangle mesh
whose boundary is the rim), so the parametric cap (:func:`chamber_cap`: the spherical cap, or
that cap stretched along y for a pad) and a mechanically deformed membrane go through the same
path: ``chamber_surface(dome)`` welds any dome to the base and returns a watertight trimesh.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from ._surface import SurfaceFile, top_height
from .scene import Chamber, Scene, read_surface, ring_positions

__all__ = ["DomeSurface", "axis_turn", "anticlockwise", "ElectrodeLayout", "symmetries", "isometries", "cap_height", "chamber_cap", "user_dome", "user_surface", "spherical_cap", "isotropic_cap", "refine_near", "flat_disc", "chamber_surface", "chamber_from_scene", "dome_from_scene", "electrode_layout"]


@dataclass(frozen=True)
class DomeSurface:
    """The dome's inner surface: ``vertices`` (n, 3) in m, ``faces`` (m, 3), ``rim`` (k,) the
    indices of the boundary loop, which lies on the base's outline (the circle r = base_radius,
    or a pad's ellipse) in z = 0, ordered anticlockwise seen from +z."""

    vertices: np.ndarray
    faces: np.ndarray
    rim: np.ndarray

    def turned(self, m: np.ndarray) -> "DomeSurface":
        """This surface turned about the axis by the rotation ``m`` (2, 2), its rim sorted
        anticlockwise again."""
        v = self.vertices @ axis_turn(m).T
        return DomeSurface(v, self.faces, anticlockwise(self.rim, v))


def axis_turn(m: np.ndarray) -> np.ndarray:
    """The rotation (3, 3) about the chamber's axis (z) whose in-plane part is ``m`` (2, 2)."""
    r = np.eye(3)
    r[:2, :2] = m
    return r


def anticlockwise(rim: np.ndarray, points: np.ndarray) -> np.ndarray:
    """The indices ``rim`` into ``points`` (n, ≥2) ordered by their angle about the axis."""
    return rim[np.argsort(np.arctan2(points[rim, 1], points[rim, 0]))]


@dataclass(frozen=True)
class ElectrodeLayout:
    """Disc electrodes: ``centres`` (n_el, 3), ``radii`` (n_el,), on the base plane or, where
    ``on_membrane`` (n_el,) is set, on the membrane's inner surface: there centred where the dome
    lies above (x, y) (z: on the nominal cap), moving with the membrane, stretching with it or
    rigid (``membrane_patch``, :data:`~jointsim.mesh.electrodes.MEMBRANE_PATCHES`). Where
    ``face_z`` (n_el,) is finite, the electrode is a whole face of the chamber instead: every
    boundary face on the plane z = face_z (a user's chamber's end plates).

    The driven electrodes come first (the paper's ring: 0 … count−1, anticlockwise from
    ``first_angle_deg``; a layout given as data: in the order its generators made them), the
    reference (the paper's central ground) last, index ``ground``."""

    centres: np.ndarray
    radii: np.ndarray
    ground: int
    on_membrane: np.ndarray | None = None
    membrane_patch: str = "stretch"
    face_z: np.ndarray | None = None

    @property
    def n_electrodes(self) -> int:
        return len(self.radii)

    @property
    def membrane(self) -> np.ndarray:
        """(n_el,) bool: the electrodes on the membrane."""
        return np.zeros(len(self.radii), bool) if self.on_membrane is None else np.asarray(self.on_membrane, bool)

    @property
    def face(self) -> np.ndarray:
        """(n_el,) bool: the full-face electrodes (every face of the chamber's surface on the
        plane z = ``face_z``)."""
        return np.zeros(len(self.radii), bool) if self.face_z is None else np.isfinite(self.face_z)

    @property
    def clipped(self) -> np.ndarray:
        """(n_el,) bool: the discs clipped on the base plane (neither on the membrane nor faces)."""
        return ~self.membrane & ~self.face


def electrode_layout(scene: Scene) -> ElectrodeLayout:
    """The electrodes of ``scene``'s [electrodes]: the paper's ring and central ground, or its discs."""
    e = scene.electrodes
    if e.discs:
        d = np.asarray(e.discs, float)
        if any(z is not None for z in e.face_z):
            face_z = np.array([np.nan if z is None else z for z in e.face_z])
            centres = np.column_stack([d[:, :2], np.nan_to_num(face_z)])
            on = np.asarray(e.on_membrane, bool) if e.on_membrane else None
            return ElectrodeLayout(centres, d[:, 2].copy(), len(d) - 1, on, e.membrane_patch, face_z)
        if not any(e.on_membrane):
            return ElectrodeLayout(np.column_stack([d[:, :2], np.zeros(len(d))]), d[:, 2].copy(), ground=len(d) - 1)
        on = np.asarray(e.on_membrane, bool)
        c = scene.chamber
        if c.surface_file is not None:  # a user's top: its height above each footprint
            z = np.where(on, top_height(read_surface(c.surface_file, c.surface_unit), d[:, :2]), 0.0)
        else:
            rho = np.hypot(d[:, 0], d[:, 1] / c.y_scale)  # on a pad: where on the round cap the point came from
            z = np.where(on, cap_height(c.base_radius, c.dome_height, rho), 0.0)
        return ElectrodeLayout(np.column_stack([d[:, :2], z]), d[:, 2].copy(), len(d) - 1, on, e.membrane_patch)
    ring = np.column_stack([ring_positions(e.count, e.ring_radius, e.first_angle_deg), np.zeros(e.count)])
    centres = np.vstack([ring, np.zeros((1, 3))])
    radii = np.append(np.full(e.count, e.diameter / 2), e.ground_diameter / 2)
    return ElectrodeLayout(centres, radii, ground=e.count)


def symmetries(layout: ElectrodeLayout, chamber: Chamber, max_order: int = 64, tol: float = 1e-9) -> dict[str, np.ndarray]:
    """The isometries of the base plane that map the ideal chamber (its outline: the circle, a
    pad's ellipse, a user's polygon) and the electrode layout onto themselves while keeping the
    reference electrode in place: turns about the axis by 360°/k (k ≤ ``max_order``) and mirrors
    in lines through it (the x and y axes, and through each electrode and midway between two),
    each as the permutation P of the electrodes it makes (electrode i goes to P[i]), by name
    ("turn 22.5 deg", "mirror 0 deg"). Positions match to ``tol`` × the base radius."""
    return {name: P for name, (_, P) in isometries(layout, chamber, max_order, tol).items()}


def isometries(layout: ElectrodeLayout, chamber: Chamber, max_order: int = 64, tol: float = 1e-9,
               keep_reference: bool = True) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """:func:`symmetries` with each isometry's matrix: name → (the 2 × 2 orthogonal matrix
    acting on base-plane points, the electrode permutation P). ``keep_reference=False``: the
    reference electrode may move too (a floating reference, whose choice changes no
    measurement)."""
    xy = layout.centres[:, :2]
    key = np.column_stack([layout.radii, layout.membrane, layout.face, np.nan_to_num(layout.centres[:, 2]) * layout.face])
    scale = tol * chamber.base_radius
    outline = np.asarray(chamber.outline) if chamber.outline else None

    def permutation(m: np.ndarray) -> np.ndarray | None:
        moved = xy @ m.T
        d = np.linalg.norm(moved[:, None] - xy[None], axis=2) + 1e9 * (np.abs(key[:, None] - key[None]) > tol).any(axis=2)
        P = np.argmin(d, axis=1)
        if d[np.arange(len(P)), P].max() > scale or len(set(P.tolist())) < len(P) or (keep_reference and P[layout.ground] != layout.ground):
            return None
        if outline is not None:  # the user's polygon onto itself
            q = outline @ m.T
            if np.linalg.norm(q[:, None] - outline[None], axis=2).min(axis=1).max() > scale:
                return None
        elif chamber.base_radius_y is not None and not (np.allclose(np.abs(m), np.eye(2), atol=1e-12)):
            return None  # a pad: only its two mirrors and the half turn
        return P

    out: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for k in range(2, max_order + 1):
        t = 2 * np.pi / k
        m = np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]])
        P = permutation(m)
        if P is not None:
            out[f"turn {360 / k:g} deg"] = m, P
    angles = {0.0, np.pi / 2} | {float(np.arctan2(y, x) % np.pi) for x, y in xy if np.hypot(x, y) > scale}
    ring = sorted(angles)
    angles |= {(a + b) / 2 for a, b in zip(ring, ring[1:] + [ring[0] + np.pi])}
    for a in sorted({round(a % np.pi, 12) for a in angles}):
        c, s_ = np.cos(2 * a), np.sin(2 * a)
        m = np.array([[c, s_], [s_, -c]])
        P = permutation(m)
        if P is not None:
            out[f"mirror {np.degrees(a):.4g} deg"] = m, P
    return out


def cap_height(base_radius: float, height: float, rho: np.ndarray) -> np.ndarray:
    """Height of the spherical cap of ``base_radius`` and apex ``height`` above the base at the
    distances ``rho`` from its axis (all m)."""
    R = (base_radius**2 + height**2) / (2 * height)
    return np.sqrt(np.maximum(R * R - np.asarray(rho, float) ** 2, 0.0)) - (R - height)


def spherical_cap(base_radius: float, height: float, n_rim: int = 192, n_rings: int | None = None) -> DomeSurface:
    """Spherical cap of base radius ``base_radius`` and apex height ``height`` (m).

    Structured in polar rings; the apex is a single vertex. Sphere radius R = (a² + h²)/(2h).
    """
    a, h = base_radius, height
    R = (a * a + h * h) / (2 * h)
    zc = h - R
    theta_max = np.arcsin(min(a / R, 1.0))  # polar angle of the rim seen from the sphere centre
    if n_rings is None:
        n_rings = max(4, int(np.ceil(R * theta_max / (2 * np.pi * a / n_rim))))
    theta = theta_max * np.arange(n_rings, 0, -1) / n_rings  # rim first, apex excluded
    phi = 2 * np.pi * np.arange(n_rim) / n_rim
    st, ct = np.sin(theta)[:, None], np.cos(theta)[:, None]
    x = R * st * np.cos(phi)
    y = R * st * np.sin(phi)
    z = zc + R * ct * np.ones_like(phi)
    verts = np.column_stack([x.ravel(), y.ravel(), z.ravel()])
    verts[:n_rim, 2] = 0.0  # the rim is exactly on the base plane
    verts[:n_rim, :2] = a * np.column_stack([np.cos(phi), np.sin(phi)])
    verts = np.vstack([verts, [0.0, 0.0, h]])
    apex = len(verts) - 1

    ring = np.arange(n_rings)[:, None] * n_rim
    j = np.arange(n_rim)[None, :]
    j1 = (j + 1) % n_rim
    a0, a1 = ring[:-1] + j, ring[:-1] + j1
    b0, b1 = ring[1:] + j, ring[1:] + j1
    # outward (away from the chamber interior) normals point up/out
    quads = np.concatenate(
        [np.stack([a0, a1, b1], -1).reshape(-1, 3), np.stack([a0, b1, b0], -1).reshape(-1, 3)]
    )
    last = (n_rings - 1) * n_rim + np.arange(n_rim)
    cap = np.column_stack([last, np.roll(last, -1), np.full(n_rim, apex)])
    faces = np.vstack([quads, cap])
    return DomeSurface(verts, faces.astype(np.int64), np.arange(n_rim))


def isotropic_cap(base_radius: float, height: float, n_rim: int = 96, apex_edge: float | None = None) -> DomeSurface:
    """Spherical cap triangulated with near-equilateral triangles of edge ≈ 2π·base_radius/n_rim,
    or graded from ``apex_edge`` (m) at the apex linearly (in geodesic distance) to that at the rim.

    Rings at equal geodesic spacing from the apex, each with a vertex count proportional to its
    circumference (unlike :func:`spherical_cap`, whose rings all have n_rim vertices and whose
    triangles near the apex become slivers — exactly where a target presses). Ring counts are
    multiples of the largest power of two ≤ 16 dividing ``n_rim`` and rings are stitched by exact
    integer comparison of angles, so the triangulation has that rotational symmetry exactly.
    The rim is vertices 0 … n_rim−1, anticlockwise seen from +z."""
    if base_radius <= 0 or height <= 0:
        raise ValueError(f"base_radius = {base_radius}, height = {height}: both must be > 0 m")
    if n_rim < 8:
        raise ValueError(f"n_rim = {n_rim}: must be >= 8")
    a, h = base_radius, height
    R = (a * a + h * h) / (2 * h)
    # min(·, 1): for a hemisphere (h = a) a / R rounds to 1 + 1 ulp for some radii
    theta_max = np.arcsin(min(a / R, 1.0)) if h <= R else np.pi - np.arcsin(min(a / R, 1.0))
    edge = 2 * np.pi * a / n_rim
    sym = next(s for s in (16, 8, 4, 2, 1) if n_rim % s == 0)
    S = R * theta_max  # geodesic distance apex → rim
    e0 = edge if apex_edge is None else float(apex_edge)
    if not 0 < e0 <= S:
        raise ValueError(f"apex_edge = {apex_edge}: must be in (0, {S:.3g}] m")

    def spacing(s):  # the edge length at geodesic distance s from the apex
        return e0 + (edge - e0) * s / S

    rings = [0.0]
    while rings[-1] < S - 0.5 * spacing(rings[-1]):
        rings.append(rings[-1] + spacing(rings[-1]))
    s_ring = np.array(rings[1:]) * S / rings[-1] if len(rings) > 2 else np.array([0.5 * S, S])
    n_rings = len(s_ring)
    theta = s_ring[::-1] / R  # rim first, apex excluded
    counts = np.maximum(sym, sym * np.round(2 * np.pi * R * np.sin(theta) / (sym * spacing(R * theta)))).astype(int)
    counts[0] = n_rim
    # alternate rings are rotated by half a spacing, so stitched triangles are not right-angled
    half = np.arange(n_rings) % 2
    start = np.concatenate([[0], np.cumsum(counts)])
    verts = []
    for k in range(n_rings):
        phi = 2 * np.pi * (np.arange(counts[k]) + 0.5 * half[k]) / counts[k]
        r, z = R * np.sin(theta[k]), h - R + R * np.cos(theta[k])
        verts.append(np.column_stack([r * np.cos(phi), r * np.sin(phi), np.full(counts[k], z)]))
    verts = np.vstack(verts + [np.array([[0.0, 0.0, h]])])
    verts[:n_rim, 2] = 0.0  # the rim is exactly on the base plane, on the circle r = a
    verts[:n_rim, :2] *= a / np.hypot(verts[:n_rim, 0], verts[:n_rim, 1])[:, None]
    faces = [_stitch_rings(start[k], counts[k], half[k], start[k + 1], counts[k + 1], half[k + 1]) for k in range(n_rings - 1)]
    last = start[n_rings - 1] + np.arange(counts[-1])
    faces.append(np.column_stack([last, np.roll(last, -1), np.full(counts[-1], len(verts) - 1)]))
    return DomeSurface(verts, np.vstack(faces).astype(np.int64), np.arange(n_rim))


def refine_near(cap: DomeSurface, about: np.ndarray, radius: float, levels: int) -> DomeSurface:
    """``cap`` (a spherical cap, :func:`isotropic_cap`) refined ``levels`` times about the
    in-plane point ``about`` (2,) m: each level splits every face whose centroid lies within
    its radius of ``about`` (seen from above) into four (red), and a neighbour left with one
    split edge into two (green), so the surface stays conforming; a neighbour with two or three
    split edges is split into four too. The finest level covers ``radius`` m; each coarser one
    reaches two of its own edges further, so a level's green faces lie outside the next
    level's region and are never split again (their angles stay those of one bisection). New
    vertices lie on the cap's sphere (on the rim circle for a rim edge). Faces keep their
    orientation, the rim stays anticlockwise, and the vertices of ``cap`` keep their indices."""
    if levels < 0:
        raise ValueError(f"levels = {levels}: must be >= 0")
    if not radius > 0:
        raise ValueError(f"radius = {radius}: must be > 0 m")
    v = np.asarray(cap.vertices, float)
    f = np.asarray(cap.faces, np.int64)
    rim = np.asarray(cap.rim, np.int64)
    a = float(np.hypot(v[rim, 0], v[rim, 1]).mean())
    # the cap's sphere: centre (0, 0, zc) through the rim circle and the apex
    h = float(v[:, 2].max())
    zc = h - (a * a + h * h) / (2 * h)
    about = np.asarray(about, float)
    near = np.hypot(*(v[f].mean(axis=1)[:, :2] - about).T) <= radius + 1.5 * _mean_edge(v, f)
    edge = _mean_edge(v, f[near]) if near.any() else _mean_edge(v, f)
    reach = [radius + 2 * edge * sum(0.5**j for j in range(l, levels - 1)) for l in range(levels)]
    for l in range(levels):
        v, f, rim = _split_within(v, f, rim, about, reach[l], a, zc)
    return DomeSurface(v, f, rim)


def _mean_edge(v: np.ndarray, f: np.ndarray) -> float:
    return float(np.linalg.norm(v[f] - v[np.roll(f, 1, axis=1)], axis=2).mean())


def _split_within(v: np.ndarray, f: np.ndarray, rim: np.ndarray, about: np.ndarray, reach: float, a: float,
                  zc: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One level of :func:`refine_near`: red faces within ``reach`` of ``about``, closed by red
    and green faces."""
    red = np.hypot(*(v[f].mean(axis=1)[:, :2] - about).T) <= reach
    e = np.sort(np.stack([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]], axis=1), axis=2)  # (m, 3, 2), edge k opposite corner k+2
    edges, inv = np.unique(e.reshape(-1, 2), axis=0, return_inverse=True)
    inv = inv.reshape(-1, 3)
    while True:  # closure: a face with two or more split edges is split into four
        split = np.zeros(len(edges), bool)
        split[inv[red].ravel()] = True
        more = ~red & (split[inv].sum(axis=1) >= 2)
        if not more.any():
            break
        red |= more
    # the new vertices: split edges' midpoints on the sphere, a rim edge's on the rim circle
    ends = v[edges[split]]
    mid = ends.mean(axis=1)
    on_rim = np.all(ends[:, :, 2] == 0.0, axis=1)
    c = np.array([0.0, 0.0, zc])
    R = np.linalg.norm(ends[:, 0] - c, axis=1)
    d = mid - c
    mid[~on_rim] = c + (R[:, None] * d / np.linalg.norm(d, axis=1, keepdims=True))[~on_rim]
    mid[on_rim, :2] *= a / np.hypot(mid[on_rim, 0], mid[on_rim, 1])[:, None]
    mid[on_rim, 2] = 0.0
    index = np.full(len(edges), -1)
    index[split] = len(v) + np.arange(split.sum())
    m = index[inv]  # (faces, 3): the midpoint of edge (k, k+1), or -1
    A, B, C = f[:, 0], f[:, 1], f[:, 2]
    ab, bc, ca = m[:, 0], m[:, 1], m[:, 2]
    r = red
    out = [f[~red & (m.max(axis=1) < 0)],
           np.column_stack([A[r], ab[r], ca[r]]), np.column_stack([ab[r], B[r], bc[r]]),
           np.column_stack([ca[r], bc[r], C[r]]), np.column_stack([ab[r], bc[r], ca[r]])]
    green = ~red & (m.max(axis=1) >= 0)
    k = np.argmax(m[green], axis=1)  # the split edge (k, k+1)
    g = np.take_along_axis(f[green], (k[:, None] + np.arange(3)) % 3, axis=1)  # rotated so it is edge (0, 1)
    mg = m[green, k]
    out += [np.column_stack([g[:, 0], mg, g[:, 2]]), np.column_stack([mg, g[:, 1], g[:, 2]])]
    # the rim: a split rim edge's midpoint between its ends
    nxt = np.roll(rim, -1)
    key = {tuple(sorted(p)): i for i, p in enumerate(edges[split].tolist())}
    new_rim = []
    for p, q in zip(rim.tolist(), nxt.tolist()):
        new_rim.append(p)
        i = key.get((min(p, q), max(p, q)))
        if i is not None:
            new_rim.append(len(v) + i)
    return np.vstack([v, mid]), np.vstack(out).astype(np.int64), np.asarray(new_rim, np.int64)


def chamber_cap(chamber: Chamber, n_rim: int = 96, apex_edge: float | None = None) -> DomeSurface:
    """The dome of ``chamber`` as :func:`isotropic_cap` triangulates it: the spherical cap of its
    base radius and height, or, for an elongated pad, that cap stretched along y to the pad's
    semi-axis (its triangles stretched with it); for a user's surface (``surface_file``) its top
    as the file triangulates it (:func:`user_dome`; ``n_rim`` then has no say)."""
    if chamber.surface_file is not None:
        return user_dome(chamber)
    return _as_pad(isotropic_cap(chamber.base_radius, chamber.dome_height, n_rim, apex_edge), chamber)


def _as_pad(cap: DomeSurface, chamber: Chamber) -> DomeSurface:
    """The round ``cap`` stretched along y to ``chamber``'s pad (itself for a round dome)."""
    if chamber.base_radius_y is None:
        return cap
    v = cap.vertices.copy()
    v[:, 1] *= chamber.y_scale
    return DomeSurface(v, cap.faces, cap.rim)


def user_dome(chamber: Chamber) -> DomeSurface:
    """The top of a user's chamber (``chamber.surface_file``): its faces off z = 0, as the file
    triangulates them, outward, the rim its loop on the base."""
    sf = _surface(chamber)
    top = sf.faces[~sf.base]
    used, faces = np.unique(top, return_inverse=True)
    index = np.full(len(sf.vertices), -1)
    index[used] = np.arange(len(used))
    return DomeSurface(sf.vertices[used], faces.reshape(-1, 3).astype(np.int64), index[sf.rim])


def user_surface(chamber: Chamber) -> trimesh.Trimesh:
    """A user's chamber (``chamber.surface_file``) as the closed, outward surface the mesher takes."""
    sf = _surface(chamber)
    return trimesh.Trimesh(sf.vertices, sf.faces, process=False)


def _surface(chamber: Chamber) -> SurfaceFile:
    sf = read_surface(chamber.surface_file, chamber.surface_unit)
    if sf.sha256 != chamber.surface_sha256:
        raise ValueError(f"chamber.surface_file = {chamber.surface_file!r}: the file changed since the scene was read")
    return sf


def flat_disc(base_radius: float, n_rim: int = 96) -> DomeSurface:
    """A flat disc of radius ``base_radius`` in the base plane, triangulated as
    :func:`isotropic_cap` in its limit of zero height (the same rings and symmetry): the inner
    surface of a membrane moulded flat, before it is inflated into a dome."""
    cap = isotropic_cap(base_radius, 1e-9 * base_radius, n_rim)
    v = cap.vertices.copy()
    v[:, 2] = 0.0
    return DomeSurface(v, cap.faces, cap.rim)


def _stitch_rings(s0: int, n0: int, o0: int, s1: int, n1: int, o1: int) -> np.ndarray:
    """Triangles between an outer ring (first vertex s0, n0 vertices, half-offset o0) and the
    next ring inward, walking both by angle. Angles are compared as exact fractions
    (2j + o)/(2n), so every symmetry sector is stitched identically."""
    # unwrapped angles × 2·n0·n1: outer (2i + o0)·n1, inner (2j + o1)·n0; the walk starts at
    # the inner vertex at or just before outer vertex 0, so the seam is stitched like any sector
    j0 = -1 if o1 * n0 > o0 * n1 else 0
    tris = []
    i, j = 0, j0
    while i < n0 or j < j0 + n1:
        ai = (2 * (i + 1) + o0) * n1
        aj = (2 * (j + 1) + o1) * n0
        a, b = s0 + i % n0, s1 + j % n1
        if j >= j0 + n1 or (i < n0 and ai <= aj):
            tris.append((a, s0 + (i + 1) % n0, b))
            i += 1
        else:
            tris.append((a, s1 + (j + 1) % n1, b))
            j += 1
    return np.array(tris)


def chamber_surface(dome: DomeSurface) -> trimesh.Trimesh:
    """Close ``dome`` with the flat base (a fan from the centre to the rim) into a watertight,
    outward-oriented surface. Raises ValueError naming what is wrong if it is not closed."""
    v = np.asarray(dome.vertices, float)
    rim = np.asarray(dome.rim)
    if len(rim) < 8 or np.abs(v[rim, 2]).max() > 1e-9:
        raise ValueError("dome.rim: must be a loop of >= 8 vertices in the base plane z = 0")
    # the base is a fan from the axis: its rim must turn once around it, anticlockwise
    turn = np.diff(np.unwrap(np.arctan2(v[rim, 1], v[rim, 0])))
    if not (turn > 0).all():
        raise ValueError("dome.rim: must run once around the axis, anticlockwise seen from +z (a star-shaped base)")
    centre = len(v)
    verts = np.vstack([v, [0.0, 0.0, 0.0]])
    # base normal must point −z: the rim runs anticlockwise seen from +z, so reverse it
    base = np.column_stack([np.full(len(rim), centre), np.roll(rim, -1), rim])
    faces = np.vstack([dome.faces, base])
    surf = trimesh.Trimesh(verts, faces, process=True, validate=False)
    if not surf.is_watertight:
        raise ValueError("chamber surface is not watertight: the dome's boundary must be exactly its rim loop")
    if not surf.is_winding_consistent:
        raise ValueError("chamber surface has inconsistent face winding")
    if surf.volume <= 0:
        surf.invert()
    return surf


DOME_RIM_VERTICES = 96  # a multiple of 16: a 22.5° rotation maps the dome triangulation onto itself


def dome_from_scene(scene: Scene, n_rim: int = DOME_RIM_VERTICES) -> DomeSurface:
    """The undeformed inner dome surface of ``scene``: structured in polar rings (a pad's
    stretched along y), or a user's top as its file triangulates it."""
    c = scene.chamber
    if c.surface_file is not None:
        return user_dome(c)
    return _as_pad(spherical_cap(c.base_radius, c.dome_height, n_rim), c)


def chamber_from_scene(scene: Scene, n_rim: int = DOME_RIM_VERTICES) -> trimesh.Trimesh:
    """The undeformed chamber surface of ``scene``."""
    return chamber_surface(dome_from_scene(scene, n_rim))
