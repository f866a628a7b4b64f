"""Frictionless contact between two deformable bodies: a quadratic penalty on the gap of
*slave* nodes against the *master* surface's linear triangles (node-to-surface):

    E_c = Σ_s w_s k/2 ⟨−g_s⟩²,   g_s = (x_s − Σ_i λ_i x_{m_i}) · n_s

with w_s the slave node's share of its surface area, (m_0, m_1, m_2) the master triangle
holding the point closest to x_s, λ that point's barycentric coordinates and n_s that
triangle's outward face normal, also when the closest point is on an edge or a corner (the
unit vector from there to x_s, tried before, turns through large angles as a penetrating
slave crosses the edge, and Newton cycled between the two directions). The triangle, λ and n are *lagged*: found
at each Hessian evaluation (once per Newton iteration) and frozen in between, so that the
line search minimises one smooth energy. With λ and n frozen g is linear in the positions,
its gradient (k w ⟨−g⟩ (1, −λ₀, −λ₁, −λ₂) ⊗ n over the four nodes) is the exact gradient of
the point-to-plane gap at the closest point (the terms from moving λ and rotating n vanish
there: ∂λ moves the point in the face plane, ∂n ⟂ n), and the Hessian k w JᵀJ is exact up to
the normal's rotation, a term of relative size penetration / edge length (~1 %).

The closest triangle is searched among *candidates*: for each slave node within ``margin``
of the master surface, the master triangles whose centroid lies within ``reach`` plus the
triangle's size of the slave's closest point on that surface
(:meth:`SurfaceContact.update_candidates`). The candidates fix which slave and master nodes
may couple, so a Newton solve runs on one sparsity pattern (:meth:`SurfaceContact.couplings`);
callers refresh them between solves and check :meth:`SurfaceContact.covers` after one.

Why about the closest point and not the slave: each candidate couples its slave with the
triangle's nodes in the Hessian, which the factorisation fills in: a ball of ``margin`` about
each slave holds far more triangles on a finely meshed surface than the few about its closest
point, and made the soft press's factorisation run out of memory. The closest triangle holds the closest point,
so it is a candidate while that point slides less than ``reach`` within a solve; when it
slides further, :meth:`SurfaceContact.covers` says so and the caller solves again."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

__all__ = ["SurfaceContact", "closest_points"]


def _segment(p, a, b):
    """Closest points on segments ab to p: parameter t (k,) in [0, 1] and the points (k, 3)."""
    e = b - a
    t = np.clip(np.einsum("ki,ki->k", p - a, e) / np.maximum(np.einsum("ki,ki->k", e, e), 1e-300), 0.0, 1.0)
    return t, a + t[:, None] * e


def closest_points(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closest points of triangles (a, b, c) to points p, all (k, 3): barycentric coordinates
    λ (k, 3), the points y (k, 3), and whether y lies inside the face (k,) bool (else on an
    edge or a corner)."""
    e1, e2, v = b - a, c - a, p - a
    d00, d01, d11 = (np.einsum("ki,ki->k", x, y) for x, y in ((e1, e1), (e1, e2), (e2, e2)))
    d20, d21 = np.einsum("ki,ki->k", v, e1), np.einsum("ki,ki->k", v, e2)
    den = np.maximum(d00 * d11 - d01 * d01, 1e-300)
    beta = (d11 * d20 - d01 * d21) / den
    gamma = (d00 * d21 - d01 * d20) / den
    lam = np.column_stack([1.0 - beta - gamma, beta, gamma])
    inside = (lam >= 0).all(axis=1)
    out = ~inside
    if out.any():
        po, ao, bo, co = p[out], a[out], b[out], c[out]
        t_ab, y_ab = _segment(po, ao, bo)
        t_bc, y_bc = _segment(po, bo, co)
        t_ca, y_ca = _segment(po, co, ao)
        d = np.stack([((po - y) ** 2).sum(axis=1) for y in (y_ab, y_bc, y_ca)], axis=1)
        best = np.argmin(d, axis=1)
        z = np.zeros_like(t_ab)
        cand = np.stack(
            [
                np.column_stack([1 - t_ab, t_ab, z]),
                np.column_stack([z, 1 - t_bc, t_bc]),
                np.column_stack([t_ca, z, 1 - t_ca]),
            ],
            axis=1,
        )  # (k, 3 edges, 3 coordinates)
        lam[out] = cand[np.arange(len(best)), best]
    y = lam[:, :1] * a + lam[:, 1:2] * b + lam[:, 2:] * c
    return lam, y, inside


def _nearest_of_each(s: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Index, into candidate pairs with slaves ``s`` (k,), of each slave's pair of least ``dist``."""
    order = np.lexsort((dist, s))
    return order[np.r_[True, s[order][1:] != s[order][:-1]]]


class SurfaceContact:
    """Node-to-surface penalty contact (module docstring) between ``slaves`` (k,) node indices
    with area weights ``weights`` (k,) and the master surface's linear triangles ``tris``
    (t, 3), outward-oriented, all indexing one set of unknowns whose reference positions are
    ``X`` (n, 3) (assign ``X`` to move a body rigidly between solves). ``stiffness`` k in
    Pa/m; ``margin`` m: slaves farther than this from the master surface are not candidates;
    ``reach`` m: a slave's candidate triangles lie within this (plus their size) of its
    closest point on the master surface (None: ``margin`` / 4)."""

    def __init__(self, X: np.ndarray, slaves: np.ndarray, weights: np.ndarray, tris: np.ndarray, stiffness: float, margin: float,
                 reach: float | None = None):
        if stiffness <= 0:
            raise ValueError(f"stiffness = {stiffness}: must be > 0 Pa/m")
        if margin <= 0:
            raise ValueError(f"margin = {margin}: must be > 0 m")
        reach = margin / 4 if reach is None else reach
        if not reach > 0:
            raise ValueError(f"reach = {reach}: must be > 0 m")
        self.reach = float(reach)
        self.X = np.asarray(X, float)
        self.slaves = np.asarray(slaves, np.int64)
        self.weights = np.asarray(weights, float)
        self.tris = np.asarray(tris, np.int64)
        self.stiffness = float(stiffness)
        self.margin = float(margin)
        self._n = 3 * len(self.X)
        # candidate pairs (slave position in self.slaves, triangle), sorted by slave
        self.cand_s = np.zeros(0, np.int64)
        self.cand_t = np.zeros(0, np.int64)
        self._lagged = None
        self._seen: list[np.ndarray] = []  # each lag's triangles since the candidates were updated
        self._pinned = np.zeros(len(self.slaves), bool)  # slaves held to their triangle until then

    # -- candidates and the coupling pattern --------------------------------------------------

    def _candidate_pairs(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        x = self.X + u
        p = x[self.tris]
        cen = p.mean(axis=1)
        size = np.linalg.norm(p - cen[:, None], axis=2).max(axis=1)  # circumscribing radius about the centroid
        tree = cKDTree(cen)
        xs = x[self.slaves]
        hits = tree.query_ball_point(xs, self.margin + size.max())
        cnt = np.fromiter((len(h) for h in hits), np.int64, len(hits))
        s = np.repeat(np.arange(len(self.slaves)), cnt)
        t = np.fromiter((j for h in hits for j in h), np.int64, int(cnt.sum()))
        keep = np.linalg.norm(xs[s] - cen[t], axis=1) <= self.margin + size[t]
        s, t = s[keep], t[keep]
        if len(s):  # each slave's closest point on the master: slaves within the margin keep the triangles about it
            _, y, _ = closest_points(xs[s], p[t, 0], p[t, 1], p[t, 2])
            d = np.linalg.norm(xs[s] - y, axis=1)
            pick = _nearest_of_each(s, d)
            foot = np.zeros((len(self.slaves), 3))
            near = np.zeros(len(self.slaves), bool)
            foot[s[pick]] = y[pick]
            near[s[pick]] = d[pick] <= self.margin
            keep = near[s] & (np.linalg.norm(foot[s] - cen[t], axis=1) <= self.reach + size[t])
            s, t = s[keep], t[keep]
        order = np.lexsort((t, s))
        return s[order], t[order]

    def update_candidates(self, u: np.ndarray) -> None:
        """Candidate (slave, triangle) pairs for displacements ``u`` (n, 3)."""
        self.cand_s, self.cand_t = self._candidate_pairs(u)
        self._lagged = None
        self._seen = []
        self._pinned = np.zeros(len(self.slaves), bool)

    def covers(self, u: np.ndarray) -> bool:
        """Whether the current candidates hold every slave's closest triangle at ``u`` (n, 3)
        (else refresh them and solve again)."""
        s, t = self._candidate_pairs(u)
        if len(s) == 0:
            return True
        tri_now = self._choose(u, s, t)[0]
        tri_cand = self._choose(u, self.cand_s, self.cand_t)[0] if len(self.cand_s) else np.full(len(self.slaves), -1)
        return bool(np.array_equal(tri_now, tri_cand))

    def couplings(self) -> tuple[np.ndarray, np.ndarray]:
        """Node pairs (rows, cols) (k,) that the candidates may couple: each candidate's slave
        and triangle nodes, all with all (the Hessian's 12 × 12 blocks)."""
        quad = np.column_stack([self.slaves[self.cand_s], self.tris[self.cand_t]])  # (c, 4)
        quad = np.unique(quad, axis=0)
        return np.repeat(quad, 4, axis=1).ravel(), np.tile(quad, (1, 4)).ravel()

    # -- lagging ------------------------------------------------------------------------------

    def _choose(self, u, s, t):
        """For each slave (k,): its closest candidate triangle (−1: none), λ (k, 3), the lagged
        normal n (k, 3) and the gap (k,)."""
        k = len(self.slaves)
        tri = np.full(k, -1, np.int64)
        lam = np.zeros((k, 3))
        nrm = np.zeros((k, 3))
        gap = np.full(k, np.inf)
        if len(s) == 0:
            return tri, lam, nrm, gap
        x = self.X + u
        p = x[self.tris[t]]
        xs = x[self.slaves[s]]
        L, y, _ = closest_points(xs, p[:, 0], p[:, 1], p[:, 2])
        fn = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
        fn /= np.linalg.norm(fn, axis=1, keepdims=True)
        r = xs - y
        dist = np.linalg.norm(r, axis=1)
        # first candidate of each slave with the least distance (pairs are sorted by slave)
        pick = _nearest_of_each(s, dist)
        ss = s[pick]
        tri[ss] = t[pick]
        lam[ss] = L[pick]
        nrm[ss] = fn[pick]
        gap[ss] = np.einsum("ki,ki->k", r[pick], fn[pick])
        return tri, lam, nrm, gap

    def lag(self, u: np.ndarray) -> None:
        """Freeze each slave's closest triangle, λ and normal at ``u`` (n, 3).

        A slave that would go back to a triangle it has already left since the candidates were
        last updated is pinned to its current one (λ and normal taken on it at ``u``) until
        they are updated again. Why: a slave on a ridge between facets can flip between them
        from one Newton iteration to the next, each choice pushing it towards the other, and
        the iteration then cycles for ever (measured: an off-axis soft press at 3 mm alternating
        between residuals 1.0e-3 and 2.9e-4 N; forgetting the flips after 4 lags only lengthened
        the cycle to 10). The facets meet at the ridge, so which one a pinned slave is measured
        against changes its gap by the ridge's sag, far below the penetration."""
        tri, lam, nrm, _ = self._choose(u, self.cand_s, self.cand_t)
        if self._seen:
            last = self._seen[-1]
            back = (tri >= 0) & (last >= 0) & (tri != last) & np.any([tri == r for r in self._seen[:-1]], axis=0)
            self._pinned |= back
            self._hold_pinned(u, tri, lam, nrm)
        self._seen.append(tri)
        self._lagged = self._frozen(tri, lam, nrm)

    def _hold_pinned(self, u: np.ndarray, tri: np.ndarray, lam: np.ndarray, nrm: np.ndarray) -> None:
        """Each pinned slave back on the triangle it was last lagged to (λ and normal taken on
        it at ``u``), in place."""
        last = self._seen[-1]
        s = np.flatnonzero(self._pinned & (tri != last) & (last >= 0))
        if len(s):
            t2, l2, n2, _ = self._choose(u, s, last[s])
            tri[s], lam[s], nrm[s] = t2[s], l2[s], n2[s]

    def _frozen(self, tri: np.ndarray, lam: np.ndarray, nrm: np.ndarray) -> tuple:
        has = tri >= 0
        return np.flatnonzero(has), self.tris[tri[has]], lam[has], nrm[has]

    # -- energy -------------------------------------------------------------------------------

    def _gaps(self, u):
        if self._lagged is None:
            self.lag(u)
        idx, mt, lam, n = self._lagged
        x = self.X + u
        y = np.einsum("ki,kij->kj", lam, x[mt])
        g = np.einsum("ki,ki->k", x[self.slaves[idx]] - y, n)
        return idx, mt, lam, n, g

    RELINEARISES = True  # Newton judges convergence on the gradient after a re-lag

    def evaluate(self, u: np.ndarray, hessian: bool):
        """(energy, gradient (3n,), Hessian (3n, 3n) or None, True); a Hessian evaluation
        re-lags the closest points first (once per Newton iteration)."""
        if hessian:
            self.lag(u)
        idx, mt, lam, n, g = self._gaps(u)
        act = g < 0
        k = self.stiffness
        w = self.weights[idx[act]]
        pen = -g[act]
        E = float((0.5 * k * w * pen**2).sum())
        nodes = np.column_stack([self.slaves[idx[act]], mt[act]])  # (a, 4)
        coef = np.column_stack([np.ones(act.sum()), -lam[act]])  # dg/dx_node = coef · n
        # dE/dx = −k w pen · coef ⊗ n
        gi = -(k * w * pen)[:, None, None] * coef[:, :, None] * n[act][:, None, :]
        gvec = np.bincount((3 * nodes[:, :, None] + np.arange(3)).ravel(), weights=gi.ravel(), minlength=self._n)
        H = None
        if hessian:
            H = self._hessian(nodes, coef, n[act], k * w)
        return E, gvec, H, True

    def _hessian(self, nodes, coef, n, kw):
        """k w (coef ⊗ n)(coef ⊗ n)ᵀ over each active pair's four nodes, as a (3n, 3n) matrix."""
        J = (coef[:, :, None] * n[:, None, :]).reshape(-1, 12)
        blocks = kw[:, None, None] * J[:, :, None] * J[:, None, :]
        dof = (3 * nodes[:, :, None] + np.arange(3)).reshape(-1, 12)
        rows = np.repeat(dof, 12, axis=1).ravel()
        cols = np.tile(dof, (1, 12)).ravel()
        return sp.csr_matrix((blocks.ravel(), (rows, cols)), shape=(self._n, self._n))

    def assignment(self, u: np.ndarray) -> np.ndarray:
        """Each slave's triangle (k,) at ``u`` (−1: none), a pinned slave's held as Newton holds
        it (:meth:`lag`), the lag, its history and the pins left as they were."""
        tri, lam, nrm, _ = self._choose(u, self.cand_s, self.cand_t)
        if self._seen:
            self._hold_pinned(u, tri, lam, nrm)
        return tri

    def held_gradient(self, u: np.ndarray, tri: np.ndarray) -> np.ndarray:
        """The gradient (3n,) with each slave on its triangle of ``tri`` (:meth:`assignment`),
        its closest point λ and the triangle's normal taken at ``u`` (not lagged): smooth in
        the positions while the assignment holds, so a difference of it along a move is the
        energy's tangent with the normals' turning and the closest points' sliding, which
        Newton's lagged Hessian leaves out. A difference that let slaves change triangles
        within its step would add their jumps over the step (on a symmetric press, a ring of
        slaves on facet edges: GMRES then diverged)."""
        kept = self._lagged
        s = np.flatnonzero(tri >= 0)
        t2, lam, nrm, _ = self._choose(u, s, tri[s])
        self._lagged = self._frozen(t2, lam, nrm)
        try:
            return self.evaluate(u, False)[1]
        finally:
            self._lagged = kept

    def projected_hessian(self, u: np.ndarray) -> sp.csr_matrix:
        """Already positive semi-definite (a sum of rank-one blocks)."""
        return self.evaluate(u, True)[2]

    # -- outputs ------------------------------------------------------------------------------

    def force_on(self, u: np.ndarray, nodes: np.ndarray) -> np.ndarray:
        """Total contact force (3,) N on the nodes ``nodes`` (e.g. one body's), at the lagged
        closest points."""
        g = self.evaluate(u, False)[1].reshape(-1, 3)
        return -g[np.asarray(nodes)].sum(axis=0)

    def centre_of_pressure(self, u: np.ndarray) -> np.ndarray:
        """The slave nodes in contact (deformed), weighted by their penalty forces at the
        lagged closest points: (3,) m, NaN when none is."""
        idx, _, _, _, g = self._gaps(u)
        act = g < 0
        w = self.weights[idx[act]] * -g[act]
        if not act.any() or w.sum() <= 0:
            return np.full(3, np.nan)
        x = self.X[self.slaves[idx[act]]] + u[self.slaves[idx[act]]]
        return (w[:, None] * x).sum(axis=0) / w.sum()

    def penetration(self, u: np.ndarray) -> float:
        """Largest penetration (m) of a slave node into the master surface (0 when none)."""
        tri, _, _, gap = self._choose(u, self.cand_s, self.cand_t)
        return float(max(-gap[tri >= 0].min(), 0.0)) if (tri >= 0).any() else 0.0

    def contact_area(self, u: np.ndarray) -> float:
        """Area (m²) of the slave nodes in contact."""
        tri, _, _, gap = self._choose(u, self.cand_s, self.cand_t)
        return float(self.weights[(tri >= 0) & (gap < 0)].sum())
