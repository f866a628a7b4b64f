"""The membrane's body: its moulding meshed as a solid and its bonded boundary.

Owns how a membrane is made: prism layers through the thickness on the inner surface it was
moulded on (a spherical cap, or a flat sheet), as 15-node wedges or P2 tetrahedra curved onto
the true spheres of a cap (isoparametric), the faces the loads act on (the inner surface the
saline presses, the outer one the target touches) and the nodes bonded to the base (a cap's
rim in the base plane; a flat sheet's edge face through its thickness). A new moulding is a
new case here; the loads (:mod:`.loads`) and the solver (:mod:`.dome`) take any body.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry import DomeSurface
from ..scene import MEMBRANE_ELEMENTS, MEMBRANE_LAYERS, membrane_layers
from .fem import P2Mesh
from .pressure import linear_subtriangles
from .prisms import is_flat, membrane_mesh, on_rim_circle, on_spheres, sphere_centre
from .wedge import WedgeMesh

__all__ = ["MembraneBody", "membrane_body"]


@dataclass(frozen=True, eq=False)
class MembraneBody:
    """A membrane meshed: the moulded inner surface ``dome``, its ``thickness`` m in ``layers``
    prism layers of ``element`` ("wedge15" or "p2_tet") as ``mesh`` (WedgeMesh or P2Mesh; the
    first ``n_surface`` nodes are the inner surface's vertices), the ``outer_faces`` (6-node,
    every corner on the outermost layer), the inner surface's linear sub-triangles
    ``inner_tris`` (pointing into the chamber), the bonded nodes ``fixed`` (n_nodes, 3), the
    ``rim_radius`` m and whether the moulding is ``flat``."""

    dome: DomeSurface
    thickness: float
    layers: int
    element: str
    mesh: object
    n_surface: int
    outer_faces: np.ndarray
    inner_tris: np.ndarray
    fixed: np.ndarray
    rim_radius: float
    flat: bool


def membrane_body(dome: DomeSurface, thickness: float, layers: int | None = None, element: str = "wedge15",
                  isoparametric: bool = True) -> MembraneBody:
    """The membrane moulded on ``dome`` (a cap, or a flat disc), ``thickness`` m thick in
    ``layers`` (default: the element's, scene.MEMBRANE_LAYERS). ``isoparametric``: on a
    spherical cap the elements are curved onto the true inner, layer and outer spheres instead
    of faceted chords."""
    if element not in MEMBRANE_ELEMENTS:
        raise ValueError(f"element = {element!r}: allowed values are {MEMBRANE_ELEMENTS}")
    layers = membrane_layers(MEMBRANE_LAYERS[element] if layers is None else layers, "layers")
    centre = sphere_centre(dome) if isoparametric else None
    lin, n_surface = membrane_mesh(dome, thickness, layers, centre)
    flat = is_flat(dome)
    rim_radius = float(np.hypot(*dome.vertices[dome.rim, :2].T).min())
    place = on_rim_circle(rim_radius) if flat else None if centre is None else on_spheres(centre, 1e-9 * np.ptp(lin.nodes))
    mesh = WedgeMesh.on_membrane(dome, thickness, layers, centre, place) if element == "wedge15" else P2Mesh.from_linear(lin, place)
    X = mesh.nodes
    bf = mesh.boundary_faces
    n = n_surface
    on_inner = np.all(bf[:, :3] < n, axis=1)
    on_outer = np.all(bf[:, :3] >= layers * n, axis=1) & np.all(bf[:, :3] < (layers + 1) * n, axis=1)
    fixed = np.zeros_like(X, bool)
    if flat:  # a flat sheet bonded at its edge face, through its thickness
        fixed[np.hypot(X[:, 0], X[:, 1]) >= rim_radius * (1 - 1e-9)] = True
    else:  # the bonded rim
        fixed[np.abs(X[:, 2]) < 1e-9 * np.ptp(X)] = True
    # the inner faces point into the chamber (out of the solid): the chamber volume has sign −1
    return MembraneBody(dome, thickness, layers, element, mesh, n_surface, bf[on_outer], linear_subtriangles(bf[on_inner]),
                        fixed, rim_radius, flat)
