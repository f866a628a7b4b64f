"""The membrane's inner (chamber) surface at the resolution of its P2 nodes: where the
mechanics hands a frame to the EIT side. The chamber mesh follows this surface, so the
chamber's volume change matches the FEM's displaced volume (the vertex-only
``MembraneState.dome`` drops the midside nodes)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry import DomeSurface, anticlockwise, axis_turn
from ..scene import Chamber
from .dome import MembraneModel

__all__ = ["InnerSurface"]


@dataclass(frozen=True)
class InnerSurface:
    """The membrane's inner surface as the linear sub-triangles of its 6-node faces (the
    surface the FEM's saline volume is integrated over): P2 node indices ``nodes`` (n,),
    ``faces`` (m, 3) into them (normals out of the chamber), ``rim`` (k,) anticlockwise, and the
    reference positions ``X`` (n, 3) with the rim's edge midpoints moved onto the base's outline
    (the circle, or a pad's ellipse; they never move).

    The reference is the moulded surface (the moulded cap; the morph then takes the chamber to
    the reservoir's inflation), or, for a membrane moulded flat, the inflated one: ``u0`` (n, 3)
    is the membrane's displacement included in ``X`` (zero for the cap)."""

    nodes: np.ndarray
    faces: np.ndarray
    rim: np.ndarray
    X: np.ndarray
    u0: np.ndarray

    @classmethod
    def of(cls, model: MembraneModel, chamber: Chamber, inflated: bool = False) -> "InnerSurface":
        """The inner surface of ``model`` on the base of ``chamber`` (its rim put back on the
        base's circle or a pad's ellipse; a user's polygon left as it is, its edge midpoints on
        it); ``inflated``: its reference is the model's current (inflated, untouched) state
        instead of the moulded one."""
        # the model's inner sub-triangles (the pressure term's surface)
        tris = np.asarray(model.inner_tris)
        nodes, local = np.unique(tris, return_inverse=True)
        faces = local.reshape(-1, 3)[:, ::-1]  # the FEM's point into the chamber; a DomeSurface's out
        u0 = model.u[nodes] if inflated else np.zeros((len(nodes), 3))
        X = model.mesh.nodes[nodes] + u0
        # the rim: the surface's nodes the model bonds (by the base plane for a cap, by the rim
        # circle for a flat sheet, whose whole inner surface lies in the base plane)
        rim = np.flatnonzero(model.fixed[nodes, 0])
        rim = anticlockwise(rim, X)
        a = chamber.base_radius
        if chamber.outline:  # a user's chamber: its rim is the file's polygon
            pass
        elif chamber.base_radius_y is None:
            X[rim, :2] *= a / np.hypot(X[rim, 0], X[rim, 1])[:, None]
        else:  # onto the ellipse along the ray from the axis
            X[rim, :2] /= np.hypot(X[rim, 0] / a, X[rim, 1] / (a * chamber.y_scale))[:, None]
        X[rim, 2] = 0.0
        return cls(nodes, np.ascontiguousarray(faces), rim, X, u0)

    def turned(self, m: np.ndarray) -> "InnerSurface":
        """This surface turned about the axis by the rotation ``m`` (2, 2): the inner surface of
        the membrane whose mesh is this one's turned (the same nodes and faces; its rim sorted
        anticlockwise again). Only a round base maps onto itself under every turn."""
        r = axis_turn(m)
        X = self.X @ r.T
        return type(self)(self.nodes, self.faces, anticlockwise(self.rim, X), X, self.u0 @ r.T)

    def dome(self, u: np.ndarray | None) -> DomeSurface:
        """The surface displaced by the membrane's ``u`` (n_P2, 3) (None: the reference)."""
        v = self.X.copy() if u is None else self.X + (u[self.nodes] - self.u0)
        if u is not None:
            v[self.rim] = self.X[self.rim]  # bonded: zero displacement, kept bit-exact
        return DomeSurface(v, self.faces, self.rim)
