"""Fixed-topology chamber meshes: the reference chamber mesh morphed by a dome displacement,
with a fallback to a full remesh.

Boundary nodes on the dome take the displacement of the closest point of the reference dome
surface (barycentric interpolation of its vertex displacements); base nodes stay put, so the
electrode patches are unchanged; interior nodes follow by harmonic extension (the P1 Laplace
problem on the reference mesh, one factorisation for the three components). Because the
topology and the electrode integrals do not change, a difference of voltages between the
morphed and the reference mesh carries no remeshing noise: no deformation gives the
reference nodes bit for bit.

For a sequence of frames, :class:`ChamberMorpher` does the closest-point map and the
factorisation once, so a frame costs an interpolation, one solve with three right-hand sides
and a vectorised quality check (:func:`element_quality`). :func:`deform_chamber` is the one
policy by which a chamber follows the membrane: it morphs and, when the morph inverts elements
or degrades them past a threshold, remeshes the deformed chamber instead and says which path it
took and why.
"""

from __future__ import annotations

import copy
import hashlib
from dataclasses import dataclass, replace
from typing import Callable

import numpy as np
import scipy.sparse as sp
import trimesh

from ..geometry import DomeSurface
from ..linalg import factorize
from ..scene import MeshSpec
from .chamber import ChamberMesh, mesh_chamber
from .kernels import p1_stiffness, tet_quality
from .tetmesh import TetMesh

__all__ = [
    "MeshInversionError",
    "ChamberCollapse",
    "ElementQuality",
    "element_quality",
    "shape_measure",
    "ChamberMorpher",
    "DeformedChamber",
    "PulledBack",
    "pull_back",
    "remeshed",
    "deform_chamber",
    "morph_chamber",
    "dome_nodes",
    "closest_on_surface",
    "untangle",
    "untangled_note",
    "MODES",
    "MIN_QUALITY_RATIO",
    "MIN_CHAMBER_GAP",
]

MODES = ("auto", "morph", "remesh")
# a morph whose smallest shape measure falls below this × the reference mesh's is remeshed in
# "auto" (results/mesh_step_benchmark.md)
MIN_QUALITY_RATIO = 0.05
MIN_CHAMBER_GAP = 0.2e-3  # m: inner surface to base; closer, the chamber cannot be meshed over the electrodes
REGULAR_DIHEDRAL_DEG = float(np.degrees(np.arccos(1 / 3)))  # 70.53°, the largest possible minimum
UNTANGLE_RATIO = 0.05  # untangling aims at least this × the reference's smallest shape measure
UNTANGLED_KEY = "-untangled"  # the end of a morphed chamber's key when its interior nodes were untangled


def untangled_note(chamber: ChamberMesh) -> str:
    """"; interior nodes untangled" for a chamber :meth:`ChamberMorpher.morph` untangled, else
    "": what a morph's reason says of it."""
    return "; interior nodes untangled" if chamber.key.endswith(UNTANGLED_KEY) else ""


class MeshInversionError(RuntimeError):
    """The morphed mesh has inverted or degenerate elements: remesh instead."""


class ChamberCollapse(MeshInversionError):
    """The deformed dome comes so close to the base that no chamber can be meshed over the
    electrodes: the press is too deep (a property of the pose; a dataset draws again)."""


def dome_nodes(mesh: TetMesh, tol: float = 1e-9) -> np.ndarray:
    """Indices of the boundary nodes not on the base plane z = 0."""
    b = np.unique(mesh.boundary_faces)
    return b[np.abs(mesh.nodes[b, 2]) > tol]


@dataclass(frozen=True)
class ElementQuality:
    """Worst-element summary of a tet mesh: inverted (signed volume ≤ 0) count, extreme
    dihedral angles, and the smallest shape measure η = 6√2·V / l_rms³ (1 for a regular
    tetrahedron, → 0 for any flat one, negative when inverted)."""

    n_inverted: int
    min_dihedral_deg: float
    max_dihedral_deg: float
    min_shape: float


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    # np.cross on (m, 3) rows spends most of its time moving axes; components are cheaper
    return np.stack(
        [a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1], a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2], a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]],
        axis=1,
    )


def shape_measure(nodes: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """η = 6√2·V / l_rms³ of each element (m,): 1 for a regular tetrahedron, 0 for a flat one,
    negative when inverted."""
    p0, p1, p2, p3 = (nodes[tets[:, a]] for a in range(4))
    e01, e02, e03, e12, e13, e23 = p1 - p0, p2 - p0, p3 - p0, p2 - p1, p3 - p1, p3 - p2
    vol6 = np.einsum("mi,mi->m", e01, _cross(e02, e03))
    l2 = sum(np.einsum("mi,mi->m", e, e) for e in (e01, e02, e03, e12, e13, e23)) / 6.0
    with np.errstate(invalid="ignore", divide="ignore"):
        eta = np.sqrt(2.0) * vol6 / l2**1.5
    return np.nan_to_num(eta, nan=0.0)


def element_quality(nodes: np.ndarray, tets: np.ndarray) -> ElementQuality:
    """:class:`ElementQuality` of nodes (n, 3), tets (m, 4): signed volumes by triple
    products, dihedral angles from the outward face normals, η from the six edge lengths, in
    one Warp kernel (:func:`~jointsim.mesh.kernels.tet_quality`). The minimum dihedral angle
    agrees with :func:`~jointsim.mesh.tetmesh.mesh_quality`, η with :func:`shape_measure`."""
    if len(tets) == 0:
        raise ValueError("tets: the mesh has no elements")
    vol6, cos_min, cos_max, eta = tet_quality(nodes, tets)
    return ElementQuality(
        n_inverted=int((vol6 <= 0).sum()),
        min_dihedral_deg=float(np.degrees(np.arccos(np.clip(cos_max.max(), -1, 1)))),
        max_dihedral_deg=float(np.degrees(np.arccos(np.clip(cos_min.min(), -1, 1)))),
        min_shape=float(eta.min()),
    )


def closest_on_surface(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(triangle (k,), barycentric coordinates (k, 3), distance (k,)) of each point's closest
    point on the triangle surface (``vertices``, ``faces``).

    The query runs on the surface scaled to unit size: trimesh's degeneracy tolerances are
    absolute, and in metres the dome's triangles near the apex (areas ~1e-7 m²) fall under them
    and are skipped — 776 of the 1186 dome nodes of the dataset chamber got a closest point up
    to 1.3 mm away."""
    v = np.asarray(vertices, float)
    origin = v.min(axis=0)
    scale = float(np.ptp(v, axis=0).max()) or 1.0
    surf = trimesh.Trimesh((v - origin) / scale, faces, process=False)
    closest, dist, tri = trimesh.proximity.closest_point(surf, (np.asarray(points, float) - origin) / scale)
    bary = trimesh.triangles.points_to_barycentric(surf.triangles[tri], closest)
    return tri, bary, dist * scale


def _check_dihedral(min_dihedral_deg: float) -> float:
    v = float(min_dihedral_deg)
    if not 0.0 <= v < REGULAR_DIHEDRAL_DEG:
        raise ValueError(f"min_dihedral_deg = {min_dihedral_deg}: must be in [0, {REGULAR_DIHEDRAL_DEG:.2f}) degrees")
    return v


class ChamberMorpher:
    """The chamber mesh prepared for morphing by many deformations of ``dome``.

    Parameters
    ----------
    chamber : the reference ChamberMesh (its dome boundary lies on ``dome``)
    dome : the reference DomeSurface, vertices (n_v, 3), faces (n_f, 3)
    min_dihedral_deg : a morphed element with a smaller dihedral angle (or inverted) raises
        :class:`MeshInversionError`; in [0, 70.53)
    backend : sparse direct solver of the interior Laplacian, see
        :func:`jointsim.linalg.factorize`

    Built once: the dome nodes' closest points on ``dome`` as barycentric weights (n_top, 3)
    on triangles (n_top, 3) (``surface_gap``: their largest distance, m), the interior
    Laplacian factorised, and its coupling to the dome nodes. ``free()`` (or a ``with`` block)
    releases the factor now; garbage collection releases it otherwise.
    """

    def __init__(self, chamber: ChamberMesh, dome: DomeSurface, *, min_dihedral_deg: float = 1.0, backend: str = "auto"):
        self.chamber = chamber
        self.min_dihedral_deg = _check_dihedral(min_dihedral_deg)
        mesh = chamber.mesh
        self.top = dome_nodes(mesh)
        self._map_onto(dome)
        self._free = np.ones(mesh.n_nodes, bool)
        self._free[np.unique(mesh.boundary_faces)] = False
        self._solve = None
        self._owner = True  # whether free() releases the factor (a remapped copy shares it)
        if self._free.any():
            K = _stiffness(mesh)[self._free]
            self._K_ft = K[:, self.top].tocsr()  # the only fixed nodes that move
            self._solve = factorize(K[:, self._free], backend)
        self.reference_quality = element_quality(mesh.nodes, mesh.tets)

    def remapped(self, dome: DomeSurface) -> "ChamberMorpher":
        """This morpher for another reference surface ``dome`` of the same chamber (a membrane
        meshed otherwise): the dome nodes' closest points are found anew, the interior
        Laplacian's factor is shared (freeing the copy leaves it to this morpher)."""
        other = copy.copy(self)
        other._map_onto(dome)
        other._owner = False
        return other

    def _map_onto(self, dome: DomeSurface) -> None:
        """The chamber's dome nodes as barycentric points of ``dome``, the reference surface."""
        self.dome = dome
        tri, self._bary, dist = closest_on_surface(dome.vertices, dome.faces, self.chamber.mesh.nodes[self.top])
        self.surface_gap = float(dist.max()) if len(dist) else 0.0  # m: how far the chamber's dome lies off ``dome``
        self._corners = np.asarray(dome.faces)[tri]  # (n_top, 3) dome vertex indices

    def displacement(self, deformed: DomeSurface) -> np.ndarray:
        """Nodal displacement (n_nodes, 3) of the chamber mesh that follows ``deformed``."""
        v, v0 = np.asarray(deformed.vertices, float), np.asarray(self.dome.vertices, float)
        if v.shape != v0.shape or not np.array_equal(deformed.faces, self.dome.faces):
            raise ValueError("deformed: must have the same vertices and faces as the reference dome")
        u_top = np.einsum("na,nai->ni", self._bary, (v - v0)[self._corners])
        u = np.zeros_like(self.chamber.mesh.nodes)
        u[self.top] = u_top
        # zero dome displacement skips the solve, so it gives the reference nodes exactly
        if self._solve is not None and np.abs(u_top).max() > 0:
            u[self._free] = self._solve(-(self._K_ft @ u_top))
        return u

    def morph(self, deformed: DomeSurface, min_quality_ratio: float = 0.0) -> tuple[ChamberMesh, ElementQuality]:
        """The morphed chamber and its :class:`ElementQuality`. Where the harmonic extension
        inverts an element, takes a dihedral angle below ``min_dihedral_deg`` or a shape
        measure below ``min_quality_ratio`` × the reference mesh's smallest, the interior nodes
        of those elements are first moved by :func:`untangle` (the chamber's key then ends in
        "-untangled"; a morph that passes is the harmonic extension, untouched). Raises
        :class:`MeshInversionError` when an element is still inverted or below
        ``min_dihedral_deg``."""
        mesh = self.chamber.mesh
        nodes = mesh.nodes + self.displacement(deformed)
        q = element_quality(nodes, mesh.tets)
        floor = self.reference_quality.min_shape
        untangled = bool(q.n_inverted or q.min_dihedral_deg < self.min_dihedral_deg or q.min_shape < min_quality_ratio * floor)
        if untangled:
            # near the surface a deep dent can fold a thin element the harmonic extension made
            # (on the finest meshes first): its interior nodes can still be moved
            nodes = untangle(nodes, mesh.tets, self._free, max(min_quality_ratio, UNTANGLE_RATIO) * floor)
            q = element_quality(nodes, mesh.tets)
        if q.n_inverted or q.min_dihedral_deg < self.min_dihedral_deg:
            raise MeshInversionError(
                f"morphed chamber mesh: {q.n_inverted} inverted elements, smallest dihedral angle "
                f"{q.min_dihedral_deg:.2f} deg (limit min_dihedral_deg = {self.min_dihedral_deg} deg); "
                "remesh this deformation"
            )
        key = f"{self.chamber.key}-morph-{_digest(deformed.vertices)}{UNTANGLED_KEY if untangled else ''}"
        return replace(self.chamber, mesh=mesh.moved(nodes), key=key), q

    def __call__(self, deformed: DomeSurface) -> ChamberMesh:
        """The morphed chamber (see :meth:`morph`)."""
        return self.morph(deformed)[0]

    def free(self) -> None:
        """Release the factorisation; the morpher cannot morph afterwards."""
        if self._solve is not None and self._owner:
            self._solve.free()

    def __enter__(self) -> "ChamberMorpher":
        return self

    def __exit__(self, *exc) -> None:
        self.free()


def morph_chamber(
    chamber: ChamberMesh,
    dome: DomeSurface,
    deformed: DomeSurface,
    min_dihedral_deg: float = 1.0,
) -> ChamberMesh:
    """The chamber mesh moved so that its dome follows ``deformed`` (same vertices and faces
    as the reference ``dome``), for one-off use: a sequence of frames should build one
    :class:`ChamberMorpher`. Raises :class:`MeshInversionError` when an element inverts or
    its smallest dihedral angle falls below ``min_dihedral_deg``."""
    with ChamberMorpher(chamber, dome, min_dihedral_deg=min_dihedral_deg) as morpher:
        return morpher(deformed)


@dataclass(frozen=True, eq=False)
class PulledBack:
    """A remeshed chamber's tetrahedra in two configurations: ``deformed`` (the frame's) and
    ``reference`` (moved back onto the reference chamber by :func:`pull_back`). A voltage
    change taken between the two carries no remeshing noise: both are the same mesh.
    ``dropped``: surface slivers left out of both (all four nodes on the dome, flattened or
    inverted by the pull-back), ``dropped_volume`` their volume in the deformed configuration, m³."""

    deformed: ChamberMesh
    reference: ChamberMesh
    dropped: int
    dropped_volume: float


def pull_back(chamber: ChamberMesh, deformed: DomeSurface, reference: DomeSurface, min_quality_ratio: float = 0.05) -> PulledBack:
    """The tetrahedra of ``chamber``, a mesh of the chamber under the dome ``deformed`` (e.g. a
    remesh), moved onto the chamber under ``reference`` (same vertices and faces): each dome
    node by the displacement ``reference − deformed`` at its closest point on ``deformed``
    (barycentric), base nodes fixed (the electrodes do not move), interior nodes by harmonic
    extension: the morph's rule, in the other direction.

    Where the dome's curvature changes sign (the rim of a dent), a tetrahedron with all four
    nodes on the dome flattens or inverts going back, and a near-flat element ruins a solve
    (one at η ~ 1e-17 moved a 3 mm press's δV by ~1 mV); elements whose shape measure η falls
    below ``min_quality_ratio`` × the remesh's smallest are dropped from both meshes when they
    are such surface slivers (a negligible volume, reported; nodes only they used go with
    them). Raises :class:`MeshInversionError` when any other element does."""
    if not np.array_equal(deformed.faces, reference.faces) or np.shape(deformed.vertices) != np.shape(reference.vertices):
        raise ValueError("pull_back: deformed and reference must have the same vertices and faces")
    if np.array_equal(deformed.vertices, reference.vertices):
        return PulledBack(chamber, chamber, 0, 0.0)  # no deformation: the change is exactly zero
    mesh = chamber.mesh
    # the morph from ``deformed`` to ``reference``: a dome node off the surface (a chord of a
    # coarser one, fTetWild's envelope) keeps its offset instead of being snapped onto it
    with ChamberMorpher(chamber, deformed, min_dihedral_deg=0.0) as morpher:
        back = TetMesh(mesh.nodes + morpher.displacement(reference), mesh.tets)
        top, interior, smallest = morpher.top, morpher._free, morpher.reference_quality.min_shape
    floor = min_quality_ratio * smallest
    eta = shape_measure(back.nodes, mesh.tets)
    on_dome = np.zeros(mesh.n_nodes, bool)
    on_dome[top] = True
    all_dome = on_dome[mesh.tets].all(axis=1)
    if ((eta < floor) & ~all_dome).any():
        # the harmonic extension tangled a few elements near the dent's rim: the pulled-back
        # mesh only has to be a valid mesh of the reference chamber, so its interior nodes may
        # move (the remesh's own stay where they are)
        back = TetMesh(untangle(back.nodes, mesh.tets, interior, floor), mesh.tets)
        eta = shape_measure(back.nodes, mesh.tets)
    bad = eta < floor
    sliver = bad & all_dome
    if (bad & ~sliver).any():
        raise MeshInversionError(
            f"pull-back: {int((bad & ~sliver).sum())} elements with interior or base nodes invert or fall below "
            f"min_quality_ratio = {min_quality_ratio} x the remesh's smallest shape measure"
        )
    if not sliver.any():
        return PulledBack(chamber, replace(chamber, mesh=back, key=f"{chamber.key}-pulled-back"), 0, 0.0)
    return PulledBack(
        _without(chamber, mesh.nodes, ~sliver, "without-slivers"),
        _without(chamber, back.nodes, ~sliver, "pulled-back"),
        int(sliver.sum()),
        float(mesh.volumes[sliver].sum()),
    )


def untangle(nodes: np.ndarray, tets: np.ndarray, movable: np.ndarray, floor: float, rounds: int = 4,
             max_nodes: int = 500) -> np.ndarray:
    """``nodes`` (n, 3) with the ``movable`` (n,) bool nodes of the elements ``tets`` (m, 4)
    whose shape measure η is below ``floor`` moved, one node at a time, to where the worst
    element around it is best (a derivative-free search over the node's position: η is not
    smooth at the minimum), for at most ``rounds`` sweeps or until none is below ``floor``.
    Only the elements around a moved node change, and the worst of them never gets worse, so
    the mesh's smallest η does not fall. A sweep with more than ``max_nodes`` movable nodes
    to move is not repairing a local defect (a folded mesh) and is not run: before the first
    sweep, ``nodes`` come back unchanged, at no cost. A copy; ``nodes`` is not modified."""
    from scipy.optimize import minimize

    nodes = np.array(nodes, dtype=float)
    star = sp.csr_matrix((np.ones(tets.size), (tets.ravel(), np.repeat(np.arange(len(tets)), 4))), shape=(len(nodes), len(tets)))
    eta = shape_measure(nodes, tets)
    for _ in range(rounds):
        low = np.flatnonzero(eta < floor)
        todo = np.unique(tets[low])
        todo = todo[movable[todo]]
        if not len(todo) or len(todo) > max_nodes:
            break
        for i in todo:
            els = star.indices[star.indptr[i]:star.indptr[i + 1]]
            local = tets[els]
            at_i = local == i
            flat = np.arange(local.size).reshape(local.shape)

            def worst(x: np.ndarray) -> float:
                p = nodes[local]
                p[at_i] = x
                return -float(shape_measure(p.reshape(-1, 3), flat).min())

            # start from the better of where it is and the centroid of its neighbours (inside
            # the star for any reasonable one, where a node pushed through it is not)
            ring = nodes[local][~at_i]
            # starts: where it is, the ring's centroid, and the centroid of each face opposite
            # it (the node's own element then flat, the others as they would be)
            faces = nodes[local][~at_i].reshape(-1, 3, 3).mean(axis=1)
            c = ring.mean(axis=0)
            x0 = min([nodes[i].copy(), c, *(0.5 * (faces + c))], key=worst)
            h = float(np.sqrt(np.mean(np.sum((ring - ring.mean(axis=0)) ** 2, axis=1))))
            best = worst(x0)
            for _ in range(2):  # a restart from where the first search stopped, with a fresh simplex
                simplex = x0 + np.vstack([np.zeros(3), 0.25 * h * np.eye(3)])
                res = minimize(worst, x0, method="Nelder-Mead",
                               options={"initial_simplex": simplex, "xatol": 1e-4 * h, "fatol": 1e-6, "maxiter": 400})
                if res.fun < best:
                    x0, best = res.x, float(res.fun)
            if best < worst(nodes[i]):
                nodes[i] = x0
                eta[els] = shape_measure(nodes, local)
    return nodes


def _without(chamber: ChamberMesh, nodes: np.ndarray, keep: np.ndarray, tag: str) -> ChamberMesh:
    """``chamber`` at ``nodes`` with only the elements ``keep``; nodes no element uses any more
    (dome nodes of dropped slivers) are removed and the electrodes renumbered."""
    tets = chamber.mesh.tets[keep]
    used = np.zeros(len(nodes), bool)
    used[tets] = True
    if any(not used[e.faces].all() for e in chamber.electrodes):
        raise MeshInversionError("pull-back: a dropped surface sliver touches an electrode")
    new = np.cumsum(used) - 1
    electrodes = [replace(e, faces=new[e.faces]) for e in chamber.electrodes]
    carried = None
    if chamber.carried is not None:  # a node dropped here is no longer where it was carried to
        at = np.maximum(chamber.carried, 0)
        carried = np.where((chamber.carried >= 0) & used[at], new[at], -1)
    return replace(chamber, mesh=TetMesh(nodes[used], new[tets]), electrodes=electrodes, key=f"{chamber.key}-{tag}",
                   carried=carried)


@dataclass(frozen=True, eq=False)
class DeformedChamber:
    """What :func:`deform_chamber` returns: the deformed ``chamber``, the ``path`` taken
    ("morph" or "remesh"), the ``reason`` (provenance, one line) and the mesh's ``quality``.
    ``pulled_back``: on the remesh path, the remesh and its :func:`pull_back` onto the
    reference chamber, the pair to take the frame's voltage change on (None on the morph path,
    whose change is against the reference mesh itself, or when the pull-back failed: the change
    then carries the remeshing floor, and ``reason`` says why)."""

    chamber: ChamberMesh
    path: str
    reason: str
    quality: ElementQuality
    pulled_back: PulledBack | None = None

    def change(self, voltages: Callable[[ChamberMesh], np.ndarray], v_ref: np.ndarray) -> np.ndarray:
        """The frame's voltages as the reference's ``v_ref`` plus the change: V(chamber) on the
        morph path (the same tetrahedra as the reference), else V_ref + V(deformed) − V(pulled
        back) of the remesh, which cancels the remeshing noise (``voltages``: chamber → V)."""
        if self.pulled_back is None:
            return voltages(self.chamber)
        pb = self.pulled_back
        return v_ref + (voltages(pb.deformed) - voltages(pb.reference))


def deform_chamber(
    morpher: ChamberMorpher,
    deformed: DomeSurface,
    mesh: MeshSpec,
    mode: str = "auto",
    *,
    reference: DomeSurface | None = None,
    min_quality_ratio: float = MIN_QUALITY_RATIO,
    use_cache: bool = True,
) -> DeformedChamber:
    """The chamber whose dome is ``deformed``: the one policy by which a chamber mesh follows
    the membrane (palpation, datasets, studies, benchmarks).

    Parameters
    ----------
    morpher : the prepared reference chamber (:class:`ChamberMorpher`)
    deformed : the deformed dome, same vertices and faces as ``morpher.dome``
    mesh : the mesh spec of a remesh (:class:`~jointsim.scene.MeshSpec`)
    mode : "auto" morphs, and remeshes when the morph raises :class:`MeshInversionError` or its
        smallest shape measure η falls below ``min_quality_ratio`` × the reference mesh's;
        "morph" only morphs (and raises); "remesh" always remeshes
    reference : the dome a remesh is pulled back onto (:func:`pull_back`; default
        ``morpher.dome``): the untouched sensor's, so that the frame's change is taken on one
        mesh without the remeshing floor (:meth:`DeformedChamber.change`)
    min_quality_ratio : in [0, 1]; 0 falls back on inversion only. The default keeps the morph
        down to the worst quality checked against a remesh in results/mesh_step_benchmark.md (a
        15 mm target 3 mm deep over the electrode ring: η at 0.057 of the reference; its
        voltages agree with the remesh to within the remesh floor)
    use_cache : passed to :func:`~jointsim.mesh.chamber.mesh_chamber` for a remesh

    A remesh tetrahedralises the morphed chamber's boundary (the same surface, base and
    electrode outlines included; new tetrahedra; deterministic and cached by its hash).
    Raises :class:`ChamberCollapse` when the dome comes within ``MIN_CHAMBER_GAP`` of the base.
    """
    if mode not in MODES:
        raise ValueError(f"mode = {mode!r}: allowed values are {list(MODES)}")
    if not 0.0 <= min_quality_ratio <= 1.0:
        raise ValueError(f"min_quality_ratio = {min_quality_ratio}: must be in [0, 1]")
    free = np.ones(len(deformed.vertices), bool)
    free[deformed.rim] = False
    gap = float(deformed.vertices[free, 2].min()) if free.any() else np.inf
    if gap < MIN_CHAMBER_GAP:
        raise ChamberCollapse(
            f"the membrane's inner surface is {gap * 1e3:.2f} mm above the base at its lowest (the chamber collapses onto "
            f"the electrodes; at least {MIN_CHAMBER_GAP * 1e3:g} mm is needed): the press is too deep for this target"
        )
    reference = morpher.dome if reference is None else reference
    why = "mode = 'remesh'"
    if mode != "remesh":
        try:
            chamber, q = morpher.morph(deformed, min_quality_ratio if mode == "auto" else 0.0)
            ref = morpher.reference_quality
            summary = (f"min shape {q.min_shape:.3g} (reference {ref.min_shape:.3g}), min dihedral {q.min_dihedral_deg:.1f} deg"
                       + untangled_note(chamber))
            if mode == "morph" or q.min_shape >= min_quality_ratio * ref.min_shape:
                return DeformedChamber(chamber, "morph", f"morphed: {summary}", q)
            why = f"morph quality too low: {summary}, below min_quality_ratio = {min_quality_ratio} x reference"
        except MeshInversionError as e:
            if mode == "morph":
                raise
            why = f"morph failed: {e}"
    return remeshed(_remesh(morpher, deformed, mesh, use_cache), deformed, reference, why)


def remeshed(chamber: ChamberMesh, deformed: DomeSurface, reference: DomeSurface, why: str) -> DeformedChamber:
    """The remesh path's result for ``chamber``, a fresh mesh of the chamber under ``deformed``:
    with its :func:`pull_back` onto ``reference`` when that succeeds."""
    m = chamber.mesh
    try:
        pb = pull_back(chamber, deformed, reference)
        note = f"; pulled back to the reference, {pb.dropped} surface slivers dropped ({pb.dropped_volume * 1e9:.2g} mm³)"
    except MeshInversionError as e:
        pb, note = None, f"; {e}: the change carries the remeshing floor"
    return DeformedChamber(chamber, "remesh", f"remeshed ({why}){note}", element_quality(m.nodes, m.tets), pb)


def _remesh(morpher: ChamberMorpher, deformed: DomeSurface, spec: MeshSpec, use_cache: bool) -> ChamberMesh:
    """A new mesh of the reference chamber's boundary moved onto ``deformed`` (electrodes on the
    membrane carried over from the morph, whose dome faces the new mesh keeps)."""
    mesh = morpher.chamber.mesh
    moved = mesh.nodes + morpher.displacement(deformed)
    surface = trimesh.Trimesh(moved, mesh.boundary_faces, process=True, validate=False)
    surface.fix_normals()
    carry = replace(morpher.chamber, mesh=mesh.moved(moved)) if morpher.chamber.layout.membrane.any() else None
    return mesh_chamber(surface, morpher.chamber.layout, spec, use_cache=use_cache, carry_from=carry)


def _digest(a: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(a, dtype=np.float64).tobytes()).hexdigest()[:12]


def _stiffness(mesh: TetMesh) -> sp.csr_matrix:
    k = p1_stiffness(mesh.gradients, mesh.signed_volumes)
    rows = np.repeat(mesh.tets, 4, axis=1).ravel()
    cols = np.tile(mesh.tets, (1, 4)).ravel()
    return sp.csr_matrix((k.ravel(), (rows, cols)), shape=(mesh.n_nodes, mesh.n_nodes))
