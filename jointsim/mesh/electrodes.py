"""Electrodes as weighted sets of boundary triangles, with exact contact integrals.

The complete electrode model needs, per electrode e, ∫_e φ_i dS and ∫_e φ_i φ_j dS for the
basis of the forward model's elements: P1 (the face's barycentrics λ) and P2 (λ_a(2λ_a − 1) at
the vertices, 4λ_aλ_b on the edges). A boundary triangle that an electrode's outline cuts
contributes only the part inside the outline. Tagging whole triangles by centroid misplaces the area by ~2h/r, and on a
current-carrying electrode the contact term I·z/|e| dominates the voltage, so a mesh-dependent
area is mesh noise. Here each base triangle is clipped against the electrode disc
(a regular polygon with the disc's exact area, 256 sides, so the region is fixed in space and
independent of the mesh) and the moments of the barycentric coordinates are integrated
exactly over the clipped polygon (closed forms for P1, a degree-4 rule on each piece of the
polygon for P2: exact for its degree-4 products).

Electrodes on the membrane (:func:`surface_disc_patch`) lie on the chamber's curved dome: the
disc is clipped in the plane tangent to the surface at its centre (the faces projected onto it;
barycentric moments are invariant under that affine map, and each face's are scaled by its
area over its projection's), and the patch is scaled to the electrode's area πr². Such a patch
moves with the membrane (:class:`Carried`, :meth:`ElectrodePatch.follow`): a *stretching*
electrode keeps its region of each face, so its moments scale with the face's area, exactly on
the deformed triangles; a *rigid* one (a flexible printed patch) is clipped anew each frame as
the same disc at its carried centre, over a fixed superset of faces (the CEM pattern then does
not change).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from .._surface import highest_above
from ..geometry import ElectrodeLayout
from ..scene import MEMBRANE_PATCHES
from .tetmesh import TetMesh

__all__ = [
    "electrode_tags", "ElectrodePatch", "Carried", "disc_patches", "surface_disc_patch", "layout_patches", "place_discs", "carry_patches",
    "plane_face_patch", "FACE_EDGES", "p2_face_basis", "MEMBRANE_PATCHES"]

N_POLY = 256
# the polygon of N_POLY sides with the unit disc's area: R_p² · (N/2) sin(2π/N) = π
_POLY_SCALE = np.sqrt(2 * np.pi / (N_POLY * np.sin(2 * np.pi / N_POLY)))
_ANGLES = 2 * np.pi * (np.arange(N_POLY) + 0.5) / N_POLY
UNIT_POLY = _POLY_SCALE * np.column_stack([np.cos(_ANGLES), np.sin(_ANGLES)])

# a rigid patch's fixed faces: those within this × its radius of its centre at rest (room for
# the membrane under it to shrink to 1/RIGID_REACH before the disc leaves them)
RIGID_REACH = 2.0
# faces turned more than ~73° from the tangent plane are not clipped (their projection is
# degenerate; on a dome they lie far outside a disc that is small against its radius)
MIN_FACING = 0.3
FACE_EDGES = np.array([[0, 1], [1, 2], [2, 0]])  # the edges of a face's P2 basis, after its vertices
# Dunavant's 6-point rule, exact to degree 4 on a triangle: (barycentrics, weight / area)
_D4_A, _D4_B = 0.445948490915965, 0.091576213509771
_D4_POINTS = np.array([[1 - 2 * _D4_A, _D4_A, _D4_A], [_D4_A, 1 - 2 * _D4_A, _D4_A], [_D4_A, _D4_A, 1 - 2 * _D4_A],
                       [1 - 2 * _D4_B, _D4_B, _D4_B], [_D4_B, 1 - 2 * _D4_B, _D4_B], [_D4_B, _D4_B, 1 - 2 * _D4_B]])
_D4_WEIGHTS = np.array([0.223381589678011] * 3 + [0.109951743655322] * 3)


def p2_face_basis(lam: np.ndarray) -> np.ndarray:
    """The six P2 basis functions of a triangle at barycentrics ``lam`` (..., 3): the vertices'
    λ_a(2λ_a − 1), then the edges' 4λ_aλ_b in :data:`FACE_EDGES` order. (..., 6)."""
    a, b = FACE_EDGES.T
    return np.concatenate([lam * (2 * lam - 1), 4 * lam[..., a] * lam[..., b]], axis=-1)


def electrode_tags(n_nodes: int, patches: list["ElectrodePatch"]) -> np.ndarray:
    """(n_nodes,) int: the index of the electrode whose patch covers part of a face at each
    node, −1 elsewhere (for the VTU exports: the electrodes as a point field)."""
    tags = np.full(n_nodes, -1, np.int32)
    for i, p in enumerate(patches):
        tags[np.unique(np.asarray(p.faces)[np.asarray(p.area) > 0])] = i
    return tags


@dataclass(frozen=True, eq=False)
class Carried:
    """How a patch on the membrane follows its faces (:meth:`ElectrodePatch.follow`):
    ``face_area`` (k,) the full areas of the patch's faces where its moments were taken;
    ``rigid``: the same disc of ``radius`` m clipped anew at its centre (barycentrics
    ``centre_bary`` (3,) of face ``centre_face`` of the patch) instead of stretching with the faces."""

    face_area: np.ndarray
    rigid: bool = False
    radius: float = 0.0
    centre_face: int = 0
    centre_bary: np.ndarray | None = None


@dataclass(frozen=True)
class ElectrodePatch:
    """One electrode: ``faces`` (k, 3) node indices of the boundary triangles it touches and,
    per face, ``area`` (k,) of the covered part, ``m1`` (k, 3) = ∫ λ_a dS and
    ``m2`` (k, 3, 3) = ∫ λ_a λ_b dS over the covered part (λ: the face's barycentrics), and,
    where asked for, the same moments ``q1`` (k, 6), ``q2`` (k, 6, 6) of the P2 basis
    (:func:`p2_face_basis`; None otherwise: on the clipped discs they add ~30 % to the patches' cost).
    ``carried``: how a patch on the membrane follows its faces (None: it does not move)."""

    faces: np.ndarray
    area: np.ndarray
    m1: np.ndarray
    m2: np.ndarray
    q1: np.ndarray | None = None
    q2: np.ndarray | None = None
    carried: Carried | None = None

    def follow(self, nodes: np.ndarray) -> "ElectrodePatch":
        """This patch where its faces' nodes are at ``nodes`` (n, 3): itself where it does not
        move; a stretching one's moments scaled by each face's area now over its area where
        they were taken (its region of every face kept: exact on the deformed triangles); a
        rigid one clipped anew as its disc at its carried centre."""
        c = self.carried
        if c is None:
            return self
        p = nodes[self.faces]
        now = replace(c, face_area=_areas(p))
        if c.rigid:
            centre = c.centre_bary @ p[c.centre_face]
            return ElectrodePatch(self.faces, *_surface_moments(p, centre, c.radius, quadratic=self.q1 is not None), carried=now)
        s = now.face_area / c.face_area
        scaled = [m * s.reshape((-1,) + (1,) * (m.ndim - 1)) if m is not None else None
                  for m in (self.area, self.m1, self.m2, self.q1, self.q2)]
        return ElectrodePatch(self.faces, *scaled, carried=now)

    def moments(self, order: int) -> tuple[np.ndarray, np.ndarray]:
        """(∫ φ_a dS, ∫ φ_a φ_b dS) per face for the basis of elements of ``order`` (1 or 2)."""
        if order == 1:
            return self.m1, self.m2
        if self.q1 is None:
            raise ValueError("electrode patch: no P2 moments; build it with disc_patches(..., quadratic=True)")
        return self.q1, self.q2

    @property
    def total_area(self) -> float:
        return float(self.area.sum())

    @classmethod
    def from_faces(cls, nodes: np.ndarray, faces: np.ndarray) -> "ElectrodePatch":
        """Whole triangles (an electrode given as a boundary triangle set)."""
        faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
        p = nodes[faces]
        area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
        m1 = np.repeat(area[:, None] / 3, 3, axis=1)
        m2 = area[:, None, None] / 12 * (np.ones((3, 3)) + np.eye(3))
        q1, q2 = _p2_moments(area[:, None], np.broadcast_to(np.eye(3), (len(faces), 1, 3, 3)))
        return cls(faces, area, m1, m2, q1, q2)

    @classmethod
    def concat(cls, patches: list["ElectrodePatch"]) -> "ElectrodePatch":
        if any(p.carried is not None for p in patches):
            raise ValueError("ElectrodePatch.concat: patches on the membrane cannot be joined")
        fields = ("faces", "area", "m1", "m2") + (("q1", "q2") if all(p.q1 is not None for p in patches) else ())
        return cls(*(np.concatenate([getattr(p, f) for p in patches]) for f in fields))


def plane_face_patch(mesh: TetMesh, axis: int, value: float, tol: float | None = None) -> ElectrodePatch:
    """All boundary triangles lying on the plane x[axis] = value (a full-face electrode)."""
    f = mesh.boundary_faces
    x = mesh.nodes[f][..., axis]
    tol = 1e-9 * np.ptp(mesh.nodes) if tol is None else tol
    on = np.all(np.abs(x - value) <= tol, axis=1)
    if not on.any():
        raise ValueError(f"no boundary face lies on the plane x[{axis}] = {value}")
    return ElectrodePatch.from_faces(mesh.nodes, f[on])


def disc_patches(
    mesh: TetMesh, centres: np.ndarray, radii: np.ndarray, plane_tol: float = 1e-9, quadratic: bool = False,
    around: np.ndarray | None = None, reach: float = 0.0,
) -> list[ElectrodePatch]:
    """Disc electrodes on the plane z = 0 (the chamber base), clipped exactly.

    centres (n_el, 3), radii (n_el,). Boundary faces whose three nodes lie within
    ``plane_tol`` of z = 0 are candidates. ``quadratic``: the P2 moments too. Raises ValueError if an electrode is not fully
    covered by base triangles (its disc crosses the base outline).

    ``around`` (n_el, 2 or 3) with ``reach`` m: each patch keeps every base face its disc could
    cover when moved up to ``reach`` from its ``around`` point, those it does not cover with zero
    moments. Discs moved within that reach (a dataset's jittered electrodes) then have patches
    on the same faces, and their CEM systems one pattern and one solver analysis
    (:meth:`~jointsim.eit.forward.ForwardModel.on`). ValueError where a disc is moved further.
    """
    f = mesh.boundary_faces
    on = np.all(np.abs(mesh.nodes[f][..., 2]) <= plane_tol, axis=1)
    base = f[on]
    xy = mesh.nodes[base][..., :2]  # (k, 3, 2)
    unit_poly, scale = UNIT_POLY, _POLY_SCALE
    patches = []
    lo, hi = xy.min(axis=1), xy.max(axis=1)
    centres = np.asarray(centres, float)[:, :2]
    fixed = around is not None
    where = np.asarray(around, float)[:, :2] if fixed else centres
    for k, (c, r) in enumerate(zip(centres, radii)):
        if fixed and np.hypot(*(c - where[k])) > reach * (1 + 1e-12):
            raise ValueError(f"electrode {k}: moved {np.hypot(*(c - where[k])) * 1e3:.4g} mm from its place, more than "
                             f"the reach {reach * 1e3:.4g} mm its faces were kept for")
        box = r * scale + (reach if fixed else 0.0)  # half-width of the box the (moved) polygon lies in
        cand = np.all((hi >= where[k] - box) & (lo <= where[k] + box), axis=1)
        tri = (xy[cand] - c) / r  # unit-disc frame
        moments = _clip_moments(tri, unit_poly, quadratic)
        keep = np.ones(len(tri), bool) if fixed else moments[0] > 1e-14
        patch = ElectrodePatch(base[cand][keep], *(m[keep] * r * r for m in moments))
        if abs(patch.total_area / (np.pi * r * r) - 1) > 1e-9:
            raise ValueError(
                f"electrode {k}: base triangles cover {patch.total_area / (np.pi * r * r):.4%} of its "
                "disc; the disc must lie inside the meshed base plane"
            )
        patches.append(patch)
    return patches


def surface_disc_patch(mesh: TetMesh, centre_xy: np.ndarray, radius: float, *, rigid: bool = False) -> ElectrodePatch:
    """A disc electrode of ``radius`` m on the chamber's dome (its boundary faces off z = 0),
    centred where the dome lies above ``centre_xy`` (2,) m, carried by the membrane
    (:class:`Carried`; ``rigid``: a patch that keeps its shape, else one that stretches). P1 and
    P2 moments. Raises ValueError when no dome face lies above the point or the disc is not
    covered by dome faces."""
    nodes = mesh.nodes
    f = mesh.boundary_faces
    dome = f[~np.all(np.abs(nodes[f][..., 2]) <= 1e-9 * np.ptp(nodes), axis=1)]
    p = nodes[dome]
    face, bary = _above(p, np.asarray(centre_xy, float))
    centre = bary @ p[face]
    near = np.flatnonzero(np.linalg.norm(p - centre, axis=2).min(axis=1) <= RIGID_REACH * radius)
    near = np.union1d(near, [face])
    moments = _surface_moments(p[near], centre, radius, quadratic=True)
    # a stretching patch keeps the faces it covers; a rigid one all those it may come to cover
    keep = np.arange(len(near)) if rigid else np.flatnonzero(moments[0] > 1e-14 * radius * radius)
    carried = Carried(_areas(p[near[keep]]), rigid, float(radius), int(np.searchsorted(near, face)), bary)
    return ElectrodePatch(dome[near[keep]], *(m[keep] for m in moments), carried=carried)


def layout_patches(mesh: TetMesh, layout: ElectrodeLayout, quadratic: bool = False,
                   only: np.ndarray | None = None, around: np.ndarray | None = None, reach: float = 0.0) -> list[ElectrodePatch]:
    """The patches of the electrodes of ``layout`` on ``mesh``, in its order: its discs
    (:func:`place_discs`) and its full faces (:func:`plane_face_patch`); with ``only`` (n_el,)
    bool, those it marks (None for the others). ``around`` (n_el, 3), ``reach``: the base
    discs' faces kept for moves up to ``reach`` from there (:func:`disc_patches`)."""
    want = np.ones(layout.n_electrodes, bool) if only is None else np.asarray(only, bool)
    patches: list[ElectrodePatch | None] = [None] * layout.n_electrodes
    disc = np.flatnonzero(want & ~layout.face)
    placed = place_discs(mesh, layout.centres[disc], layout.radii[disc], layout.membrane[disc], layout.membrane_patch, quadratic,
                         None if around is None else np.asarray(around)[disc], reach)
    for i, patch in zip(disc, placed):
        patches[i] = patch
    for i in np.flatnonzero(want & layout.face):
        patches[i] = plane_face_patch(mesh, 2, float(layout.face_z[i]))
    return patches  # type: ignore[return-value]


def place_discs(mesh: TetMesh, centres: np.ndarray, radii: np.ndarray, membrane: np.ndarray | None = None,
                membrane_patch: str = "stretch", quadratic: bool = False, around: np.ndarray | None = None,
                reach: float = 0.0) -> list[ElectrodePatch]:
    """Disc electrodes (``centres`` (n, 3), ``radii`` (n,) m) on ``mesh``: on the base clipped
    (:func:`disc_patches`, with its ``around`` (n, 3) and ``reach``), where ``membrane`` (n,)
    bool is set on the dome above (x, y) (:func:`surface_disc_patch`, which has P2 moments
    always; ``membrane_patch`` one of :data:`MEMBRANE_PATCHES`)."""
    if membrane_patch not in MEMBRANE_PATCHES:
        raise ValueError(f"membrane_patch = {membrane_patch!r}: allowed values are {list(MEMBRANE_PATCHES)}")
    centres, radii = np.asarray(centres, float), np.asarray(radii, float)
    on = np.zeros(len(radii), bool) if membrane is None else np.asarray(membrane, bool)
    patches: list[ElectrodePatch | None] = [None] * len(radii)
    base = np.flatnonzero(~on)
    fixed = None if around is None else np.asarray(around, float)[base]
    for i, patch in zip(base, disc_patches(mesh, centres[base], radii[base], quadratic=quadratic, around=fixed, reach=reach)):
        patches[i] = patch
    for i in np.flatnonzero(on):
        patches[i] = surface_disc_patch(mesh, centres[i, :2], float(radii[i]), rigid=membrane_patch == "rigid")
    return patches  # type: ignore[return-value]


def carry_patches(patches: list[ElectrodePatch], carried: np.ndarray) -> list[ElectrodePatch]:
    """The patches on the membrane among ``patches`` renumbered onto another mesh of the same
    dome faces (``carried``: each node of theirs, its index there; −1 where it has none); the
    others as None (to be clipped on that mesh). Raises ValueError where a face is not there."""
    out: list[ElectrodePatch | None] = []
    for p in patches:
        if p.carried is None:
            out.append(None)
            continue
        faces = carried[p.faces]
        if (faces < 0).any():
            raise ValueError("carry_patches: an electrode on the membrane lies on faces the new mesh does not have")
        out.append(replace(p, faces=faces))
    return out  # type: ignore[return-value]


def _areas(p: np.ndarray) -> np.ndarray:
    """Areas (k,) of the triangles p (k, 3, 3)."""
    return 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)


def _above(p: np.ndarray, xy: np.ndarray) -> tuple[int, np.ndarray]:
    """The highest of the dome's triangles ``p`` (k, 3, 3) above ``xy`` and the point's
    barycentrics on it (:func:`~jointsim._surface.highest_above`), or the error."""
    if (hit := highest_above(p, xy)) is None:
        raise ValueError(f"electrode on the membrane at ({xy[0] * 1e3:g}, {xy[1] * 1e3:g}) mm: no dome face lies above it")
    return hit


def _surface_moments(p: np.ndarray, centre: np.ndarray, radius: float, quadratic: bool) -> tuple[np.ndarray, ...]:
    """The moments (area, m1, m2[, q1, q2]) over the triangles ``p`` (k, 3, 3) of the disc of
    ``radius`` at ``centre`` on them: clipped in the plane tangent at the centre (the mean
    normal of the faces within ``radius``), each face's moments scaled by its area over its
    projection's, the whole scaled to the disc's area πr². Raises ValueError where the faces do
    not cover the disc."""
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])  # 2·area × unit normal
    area3 = 0.5 * np.linalg.norm(n, axis=1)
    close = np.linalg.norm(p - centre, axis=2).min(axis=1) <= radius
    normal = n[close].sum(axis=0) if close.any() else n[np.argmin(np.linalg.norm(p.mean(axis=1) - centre, axis=1))]
    normal = normal / np.linalg.norm(normal)
    e1 = np.cross(normal, [1.0, 0.0, 0.0] if abs(normal[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(normal, e1)
    tri = np.stack([(p - centre) @ e1, (p - centre) @ e2], axis=-1) / radius  # the unit disc's frame
    facing = (n @ normal) > MIN_FACING * 2 * area3
    k = len(p)
    width = 6 if quadratic else 3
    out = [np.zeros(k), np.zeros((k, 3)), np.zeros((k, 3, 3))] + ([np.zeros((k, width)), np.zeros((k, width, width))] if quadratic else [])
    got = _clip_moments(tri[facing], UNIT_POLY, quadratic)
    covered = float(got[0].sum())  # of the unit polygon's area π
    if abs(covered / np.pi - 1) > 1e-9:
        raise ValueError(f"electrode on the membrane: the dome's faces cover {covered / np.pi:.4%} of its disc "
                         "(it reaches past the faces it was given)")
    projected = 0.5 * np.abs(_cross2(tri[facing, 1] - tri[facing, 0], tri[facing, 2] - tri[facing, 0]))
    to_surface = area3[facing] / projected  # m² of the face per unit area of its projection
    for o, g in zip(out, got):
        o[facing] = g * to_surface.reshape((-1,) + (1,) * (g.ndim - 1))
    total = out[0].sum()
    return tuple(o * (np.pi * radius * radius / total) for o in out)


def _clip_moments(tri: np.ndarray, poly: np.ndarray, quadratic: bool = False) -> tuple[np.ndarray, ...]:
    """Clip the convex polygon ``poly`` (N, 2) by each triangle ``tri`` (k, 3, 2) and integrate
    the triangle's barycentrics over the intersection: area (k,), m1 (k, 3), m2 (k, 3, 3), and
    with ``quadratic`` the P2 moments q1 (k, 6), q2 (k, 6, 6) too."""
    k = len(tri)
    if k == 0:
        empty = (np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3, 3)))
        return empty + ((np.zeros((0, 6)), np.zeros((0, 6, 6))) if quadratic else ())
    # orient triangles anticlockwise so "inside" is left of every edge
    cross = _cross2(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    tri = np.where((cross < 0)[:, None, None], tri[:, [0, 2, 1]], tri)
    flipped = cross < 0
    pts = np.broadcast_to(poly, (k, len(poly), 2)).copy()
    cnt = np.full(k, len(poly))
    for e in range(3):
        a, b = tri[:, e], tri[:, (e + 1) % 3]
        pts, cnt = _clip_halfplane(pts, cnt, a, b)
    # fan-triangulate the clipped polygon from its first vertex and integrate exactly
    T = np.linalg.inv(np.stack([tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]], axis=2))  # xy -> (λ1, λ2)
    lam12 = np.einsum("kij,kmj->kmi", T, pts - tri[:, None, 0])
    lam = np.concatenate([1 - lam12.sum(axis=2, keepdims=True), lam12], axis=2)  # (k, M, 3)
    M = pts.shape[1]
    i = np.arange(1, M - 1)
    valid = (i[None, :] + 1) < cnt[:, None]  # sub-triangle (0, i, i+1) exists
    p0, p1, p2 = pts[:, :1], pts[:, 1:-1], pts[:, 2:]
    sub_area = 0.5 * _cross2(p1 - p0, p2 - p0) * valid
    l0, l1, l2 = lam[:, :1], lam[:, 1:-1], lam[:, 2:]
    s = l0 + l1 + l2
    area = sub_area.sum(axis=1)
    m1 = np.einsum("km,kma->ka", sub_area, s) / 3
    second = (
        np.einsum("kma,kmb->kmab", l0.repeat(M - 2, axis=1), l0.repeat(M - 2, axis=1))
        + np.einsum("kma,kmb->kmab", l1, l1)
        + np.einsum("kma,kmb->kmab", l2, l2)
        + np.einsum("kma,kmb->kmab", s, s)
    )
    m2 = np.einsum("km,kmab->kab", sub_area, second) / 12
    # undo the reordering of vertices 1 and 2 for flipped triangles
    perm = np.array([0, 2, 1])
    m1 = np.where(flipped[:, None], m1[:, perm], m1)
    m2 = np.where(flipped[:, None, None], m2[:, perm][:, :, perm], m2)
    if not quadratic:
        return area, m1, m2
    # the pieces' corners in the barycentrics of the triangle as given (λ of a flipped one reordered back)
    lam = np.where(flipped[:, None, None], lam[..., perm], lam)
    corners = np.stack([np.broadcast_to(lam[:, :1], lam[:, 1:-1].shape), lam[:, 1:-1], lam[:, 2:]], axis=2)
    return (area, m1, m2) + _p2_moments(sub_area, corners)


def _p2_moments(piece_area: np.ndarray, corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """∫ φ_a and ∫ φ_a φ_b of the P2 basis over triangular pieces of each face: ``piece_area``
    (k, p), ``corners`` (k, p, 3, 3) the pieces' corners in the face's barycentrics. The
    degree-4 rule is exact for these degree-≤4 integrands. → (k, 6), (k, 6, 6)."""
    lam = np.einsum("qc,kpcj->kpqj", _D4_POINTS, corners)  # (k, p, 6 points, 3)
    phi = p2_face_basis(lam)
    w = piece_area[..., None] * _D4_WEIGHTS  # (k, p, q)
    return np.einsum("kpq,kpqa->ka", w, phi), np.einsum("kpq,kpqa,kpqb->kab", w, phi, phi)


def _cross2(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]


def _clip_halfplane(pts: np.ndarray, cnt: np.ndarray, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One Sutherland–Hodgman step, vectorised over polygons: keep the part left of a→b.

    pts (k, M, 2) with the first cnt[k] rows valid; returns the clipped polygons compacted to
    the front of a (k, M', 2) array."""
    k, M, _ = pts.shape
    idx = np.arange(M)
    valid = idx[None, :] < cnt[:, None]
    nxt = np.where(idx[None, :] + 1 < cnt[:, None], idx[None, :] + 1, 0)
    q = np.take_along_axis(pts, nxt[..., None].repeat(2, axis=2), axis=1)
    d = b - a
    sp = _cross2(d[:, None], pts - a[:, None])  # >= 0: inside
    sq = _cross2(d[:, None], q - a[:, None])
    inside_p, inside_q = sp >= 0, sq >= 0
    t = np.divide(sp, sp - sq, out=np.zeros_like(sp), where=(sp != sq))
    cut = pts + t[..., None] * (q - pts)
    emit_p = valid & inside_p
    emit_cut = valid & (inside_p != inside_q)
    out = np.stack([pts, cut], axis=2).reshape(k, 2 * M, 2)
    keep = np.stack([emit_p, emit_cut], axis=2).reshape(k, 2 * M)
    order = np.argsort(~keep, axis=1, kind="stable")
    new_cnt = keep.sum(axis=1)
    m_new = max(int(new_cnt.max()), 3)
    out = np.take_along_axis(out, order[:, :m_new, None].repeat(2, axis=2), axis=1)
    return out, new_cnt
