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

__all__ = ["SphereContact", "SphereFriction", "nodal_areas"]


def nodal_areas(X: np.ndarray, tris: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(nodes, weights): the surface nodes of the linear triangles ``tris`` and their areas."""
    p = X[tris]
    a = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    w = np.bincount(tris.ravel(), weights=np.repeat(a / 3, 3), minlength=len(X))
    nodes = np.unique(tris)
    return nodes, w[nodes]


def _moved_nodes_response(H: sp.spmatrix, nodes: np.ndarray, dc: np.ndarray) -> np.ndarray:
    """H · v with v = ``dc`` on each of ``nodes`` (zero elsewhere): for an energy of x − c, the
    gradient's change −∂g/∂c · dc when the sphere's centre moves by ``dc``."""
    v = np.zeros(H.shape[0])
    v[(3 * np.asarray(nodes)[:, None] + np.arange(3)).ravel()] = np.tile(np.asarray(dc, float), len(nodes))
    return H @ v


class SphereContact:
    """A rigid sphere of ``radius`` at ``centre`` (set between solves to move it) against the
    surface nodes ``nodes`` (k,) with area weights ``weights`` (k,) of a mesh with reference
    positions ``X`` (n, 3)."""

    def __init__(self, X: np.ndarray, nodes: np.ndarray, weights: np.ndarray, radius: float, stiffness: float, curvature_cap: float = np.inf):
        if radius <= 0:
            raise ValueError(f"radius = {radius}: must be > 0 m")
        if stiffness <= 0:
            raise ValueError(f"stiffness = {stiffness}: must be > 0 Pa/m")
        self.X = np.asarray(X, float)
        self.nodes = np.asarray(nodes)
        self.weights = np.asarray(weights, float)
        self.radius = float(radius)
        self.stiffness = float(stiffness)
        self.curvature_cap = float(curvature_cap)
        self.centre = np.zeros(3)
        self._n = 3 * len(X)

    def _gap(self, u):
        d = self.X[self.nodes] + u[self.nodes] - self.centre
        r = np.linalg.norm(d, axis=1)
        return d, r, self.radius - r  # penetration > 0 inside the sphere

    def evaluate(self, u: np.ndarray, hessian: bool, exact: bool = False):
        """(energy, gradient, Hessian, True). The Hessian is Σ k w (∇pen ∇penᵀ + min(pen, cap)
        ∇²pen) with cap = ``curvature_cap`` (∞: exact; 0: Gauss–Newton), or exact when
        ``exact``. The second term, the sphere's curvature, is negative definite tangentially:
        small at equilibrium (pen ~ µm) but in a trial state with the target moved half a
        millimetre into the membrane it makes hundreds of the Hessian's eigenvalues negative
        and costs Newton regularised steps; the cap keeps it exact where it matters for
        quadratic convergence and bounded where it does not."""
        return self._evaluate(u, hessian, np.inf if exact else self.curvature_cap)

    def _evaluate(self, u: np.ndarray, hessian: bool, cap: float):
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
            if cap > 0:
                bent = np.minimum(pen[act], cap)
                blocks = blocks - (k * w * bent / r[act])[:, None, None] * (np.eye(3) - nn)
            rows = np.repeat(3 * self.nodes[act, None] + np.arange(3), 3, axis=1).ravel()
            cols = np.tile(3 * self.nodes[act, None] + np.arange(3), (1, 3)).ravel()
            H = sp.csr_matrix((blocks.ravel(), (rows, cols)), shape=(self._n, self._n))
        return E, g, H, True

    def projected_hessian(self, u: np.ndarray) -> sp.csr_matrix:
        """The Gauss–Newton Hessian Σ k w ∇pen ∇penᵀ (positive semi-definite)."""
        return self._evaluate(u, True, 0.0)[2]

    def centre_sensitivity(self, u: np.ndarray, dc: np.ndarray) -> np.ndarray:
        """−∂g/∂c · dc (3n,): the change of the nodal forces the sphere exerts when its centre
        moves by ``dc`` with the nodes held (the energy depends on x − c only)."""
        return _moved_nodes_response(self.evaluate(u, True)[2], self.nodes, dc)

    def parameter_gradients(self, u: np.ndarray) -> np.ndarray:
        """∂g/∂(c_x, c_y, c_z, R) (3n, 4): how the contact's gradient (the nodal forces, with
        the nodes held) changes with the sphere's centre and radius. The energy depends on
        x − c, so ∂g/∂c = −H·(c's move on every node) with the exact Hessian; and
        g_n = −k w (R − r_n) n̂_n on the nodes inside, so ∂g_n/∂R = −k w n̂_n."""
        out = np.zeros((self._n, 4))
        H = self.evaluate(u, True, exact=True)[2]
        for a in range(3):
            out[:, a] = -_moved_nodes_response(H, self.nodes, np.eye(3)[a])
        d, r, pen = self._gap(u)
        act = pen > 0
        idx = (3 * self.nodes[act, None] + np.arange(3)).ravel()
        out[idx, 3] = -((self.stiffness * self.weights[act] / r[act])[:, None] * d[act]).ravel()
        return out

    def force(self, u: np.ndarray) -> np.ndarray:
        """Total force (3,) N that the body exerts on the sphere."""
        d, r, pen = self._gap(u)
        act = pen > 0
        n = d[act] / r[act, None]
        return -((self.stiffness * self.weights[act] * pen[act])[:, None] * n).sum(axis=0)

    def contact_area(self, u: np.ndarray) -> float:
        return float(self.weights[self._gap(u)[2] > 0].sum())

    def centre_of_pressure(self, u: np.ndarray) -> np.ndarray:
        """The contact's centre of pressure (3,) m: the nodes in contact (deformed), weighted
        by the normal force each carries; NaN when none is."""
        _, _, pen = self._gap(u)
        act = pen > 0
        w = self.weights[act] * pen[act]
        if not act.any() or w.sum() <= 0:
            return np.full(3, np.nan)
        x = self.X[self.nodes[act]] + u[self.nodes[act]]
        return (w[:, None] * x).sum(axis=0) / w.sum()

    def penetration(self, u: np.ndarray) -> float:
        return float(max(self._gap(u)[2].max(), 0.0))


class SphereFriction:
    """Coulomb friction between the sphere of ``contact`` and its surface nodes, as a lagged,
    smoothed dissipation potential (the incremental-potential form of Li et al., IPC 2020):

        D = Σ_n μ λ_n f(‖T_n (Δx_n − Δc)‖),  f(s) = s²/(2ε) for s < ε, s − ε/2 beyond,

    with Δx_n the node's motion and Δc the sphere's over the load step, T_n = I − n nᵀ the
    tangent projector and λ_n the normal force, both frozen at the start of the step (call
    :meth:`lag`). Below a slip of ε a node sticks elastically; beyond it the tangential force
    is μ λ_n, opposing the slip. ``updates`` re-lagging passes make λ_n consistent with the
    end of the step.

    Stick persists from step to step: :meth:`commit` (after a step is accepted) keeps each node's
    anchor — where on the sphere its slip is measured from, in the sphere's frame — and drags it
    only by the slip beyond ε (a return map: Coulomb friction with a tangential compliance ε).
    A fresh anchor at every step's start would release the stored stick force each step: under a
    held target the membrane crept, its tangential force relaxing step by step (on the 48/1 test
    dome, pressed 1 mm at 4 mm off axis, 79 % of it in 10 steps at rest)."""

    def __init__(self, contact: SphereContact, coefficient: float, slip: float = 1e-6):
        if coefficient < 0:
            raise ValueError(f"friction coefficient = {coefficient}: must be >= 0")
        if slip <= 0:
            raise ValueError(f"slip = {slip}: must be > 0 m")
        self.contact = contact
        self.mu = float(coefficient)
        self.eps = float(slip)
        self._lam = np.zeros(0)
        self._act = np.zeros(0, int)
        self._T = np.zeros((0, 3, 3))
        self._x0 = np.zeros((0, 3))
        self._c0 = np.zeros(3)
        # committed anchors: contact-node indices (sorted) and their anchor − sphere centre
        self.anchor_nodes = np.zeros(0, np.int64)
        self.anchors = np.zeros((0, 3))

    def lag(self, u_start: np.ndarray, centre_start: np.ndarray, u_normal: np.ndarray | None = None) -> None:
        """Freeze the step's reference: positions at its start (``u_start``, sphere at
        ``centre_start``) and normal forces and directions from ``u_normal`` (default the start)."""
        c = self.contact
        un = u_start if u_normal is None else u_normal
        d = c.X[c.nodes] + un[c.nodes] - c.centre
        r = np.linalg.norm(d, axis=1)
        pen = c.radius - r
        act = pen > 0
        n = d[act] / r[act, None]
        self._act = c.nodes[act]
        self._lam = c.stiffness * c.weights[act] * pen[act]
        self._T = np.eye(3) - np.einsum("ki,kj->kij", n, n)
        self._c0 = np.asarray(centre_start, float).copy()
        # a node that stuck at the last commit slips from its anchor, a new contact from where it is
        self._x0 = c.X[self._act] + u_start[self._act]
        held, where = self._anchored(self._act)
        self._x0[held] = self._c0 + self.anchors[where]

    def _anchored(self, nodes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(which of ``nodes`` have a committed anchor, the anchors' rows for those)."""
        if len(self.anchor_nodes) == 0:
            return np.zeros(len(nodes), bool), np.zeros(0, np.int64)
        pos = np.minimum(np.searchsorted(self.anchor_nodes, nodes), len(self.anchor_nodes) - 1)
        held = self.anchor_nodes[pos] == nodes
        return held, pos[held]

    def commit(self, u: np.ndarray) -> None:
        """Keep the anchors of the step just solved at ``u`` (the sphere at ``contact.centre``):
        each node in contact keeps its anchor dragged by its slip beyond ε, so the stick force
        it carries is there at the next step's start; nodes out of contact lose theirs."""
        if len(self._act) == 0:
            self.anchor_nodes, self.anchors = np.zeros(0, np.int64), np.zeros((0, 3))
            return
        t, s = self._slip(u)
        beyond = np.maximum(s - self.eps, 0.0) / np.maximum(s, 1e-300)
        anchor = self._x0 - self._c0 + beyond[:, None] * t
        order = np.argsort(self._act)
        self.anchor_nodes, self.anchors = self._act[order].astype(np.int64), anchor[order]

    def _slip(self, u):
        dx = self.contact.X[self._act] + u[self._act] - self._x0 - (self.contact.centre - self._c0)
        t = np.einsum("kij,kj->ki", self._T, dx)
        return t, np.linalg.norm(t, axis=1)

    def evaluate(self, u: np.ndarray, hessian: bool, projected: bool = False):
        n3 = 3 * len(self.contact.X)
        if self.mu == 0 or len(self._act) == 0:
            return 0.0, np.zeros(n3), (sp.csr_matrix((n3, n3)) if hessian else None), True
        t, s = self._slip(u)
        eps, ml = self.eps, self.mu * self._lam
        stick = s < eps
        E = float(np.where(stick, ml * s**2 / (2 * eps), ml * (s - eps / 2)).sum())
        # f'(s)/s: 1/ε sticking, 1/s slipping; the gradient is μλ f'(s)/s · Tᵀ t (T symmetric)
        fs = np.where(stick, 1 / eps, 1 / np.maximum(s, eps))
        gi = (ml * fs)[:, None] * np.einsum("kij,kj->ki", self._T, t)
        g = np.zeros(n3)
        idx = (3 * self._act[:, None] + np.arange(3)).ravel()
        np.add.at(g, idx, gi.ravel())
        H = None
        if hessian:
            # sticking: μλ/ε TᵀT; slipping: μλ/s Tᵀ(I − t̂t̂ᵀ)T (PSD: f is convex in the slip)
            that = t / np.maximum(s, 1e-300)[:, None]
            P = np.eye(3) - np.where(stick[:, None, None], 0.0, np.einsum("ki,kj->kij", that, that))
            blocks = (ml * fs)[:, None, None] * np.einsum("kji,kjl,klm->kim", self._T, P, self._T)
            rows = np.repeat(3 * self._act[:, None] + np.arange(3), 3, axis=1).ravel()
            cols = np.tile(3 * self._act[:, None] + np.arange(3), (1, 3)).ravel()
            H = sp.csr_matrix((blocks.ravel(), (rows, cols)), shape=(n3, n3))
        return E, g, H, True

    def projected_hessian(self, u: np.ndarray) -> sp.csr_matrix:
        return self.evaluate(u, True)[2]

    def centre_sensitivity(self, u: np.ndarray, dc: np.ndarray) -> np.ndarray:
        """−∂g/∂c · dc (3n,), as :meth:`SphereContact.centre_sensitivity`: the slip is measured
        in the sphere's frame (Δx − Δc), so moving the sphere is moving every node the other way."""
        return _moved_nodes_response(self.evaluate(u, True)[2], self._act, dc)

    def force(self, u: np.ndarray) -> np.ndarray:
        """Friction force (3,) N that the body exerts on the sphere (opposing its slip)."""
        if self.mu == 0 or len(self._act) == 0:
            return np.zeros(3)
        g = self.evaluate(u, False)[1]
        return g.reshape(-1, 3).sum(axis=0)
