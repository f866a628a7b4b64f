"""Frictionless contact with a rigid sphere, by a quadratic penalty on the sphere's signed
distance at the surface nodes:

    E_c = Σ_n w_n k/2 ⟨R − ‖x_n − c‖⟩²

with w_n the node's share of the surface area (each P2 surface triangle split into four
linear ones, a third of each to its nodes) and k the penalty stiffness (Pa/m). The contact
pressure at a node is k·penetration, so k sets the penetration; ``penetration`` reports it so
callers can stiffen k until it is below their tolerance."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

__all__ = ["SphereContact", "nodal_areas"]


def nodal_areas(X: np.ndarray, tris: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(nodes, weights): the surface nodes of the linear triangles ``tris`` and their areas."""
    p = X[tris]
    a = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    w = np.bincount(tris.ravel(), weights=np.repeat(a / 3, 3), minlength=len(X))
    nodes = np.unique(tris)
    return nodes, w[nodes]


class SphereContact:
    """A rigid sphere of ``radius`` at ``centre`` (set between solves to move it) against the
    surface nodes ``nodes`` (k,) with area weights ``weights`` (k,) of a mesh with reference
    positions ``X`` (n, 3)."""

    def __init__(self, X: np.ndarray, nodes: np.ndarray, weights: np.ndarray, radius: float, stiffness: float):
        if radius <= 0:
            raise ValueError(f"radius = {radius}: must be > 0 m")
        if stiffness <= 0:
            raise ValueError(f"stiffness = {stiffness}: must be > 0 Pa/m")
        self.X = np.asarray(X, float)
        self.nodes = np.asarray(nodes)
        self.weights = np.asarray(weights, float)
        self.radius = float(radius)
        self.stiffness = float(stiffness)
        self.centre = np.zeros(3)
        self._n = 3 * len(X)

    def _gap(self, u):
        d = self.X[self.nodes] + u[self.nodes] - self.centre
        r = np.linalg.norm(d, axis=1)
        return d, r, self.radius - r  # penetration > 0 inside the sphere

    def evaluate(self, u: np.ndarray, hessian: bool, projected: bool = False):
        d, r, pen = self._gap(u)
        act = pen > 0
        k, w = self.stiffness, self.weights[act]
        E = float((0.5 * k * w * pen[act] ** 2).sum())
        n = d[act] / r[act, None]
        f = (k * w * pen[act])[:, None] * n  # force of the sphere on each node, outward
        g = np.zeros(self._n)
        idx = (3 * self.nodes[act, None] + np.arange(3)).ravel()
        np.add.at(g, idx, -f.ravel())
        H = None
        if hessian:
            nn = np.einsum("ki,kj->kij", n, n)
            blocks = (k * w)[:, None, None] * nn
            if not projected:  # the sphere's curvature: indefinite, left out of the projected Hessian
                blocks = blocks - (k * w * pen[act] / r[act])[:, None, None] * (np.eye(3) - nn)
            rows = np.repeat(3 * self.nodes[act, None] + np.arange(3), 3, axis=1).ravel()
            cols = np.tile(3 * self.nodes[act, None] + np.arange(3), (1, 3)).ravel()
            H = sp.csr_matrix((blocks.ravel(), (rows, cols)), shape=(self._n, self._n))
        return E, g, H, True

    def projected_hessian(self, u: np.ndarray) -> sp.csr_matrix:
        return self.evaluate(u, True, projected=True)[2]

    def force(self, u: np.ndarray) -> np.ndarray:
        """Total force (3,) N that the body exerts on the sphere."""
        d, r, pen = self._gap(u)
        act = pen > 0
        n = d[act] / r[act, None]
        return -((self.stiffness * self.weights[act] * pen[act])[:, None] * n).sum(axis=0)

    def contact_area(self, u: np.ndarray) -> float:
        return float(self.weights[self._gap(u)[2] > 0].sum())

    def penetration(self, u: np.ndarray) -> float:
        return float(max(self._gap(u)[2].max(), 0.0))
