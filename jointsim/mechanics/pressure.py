"""Pressure loads as energy: a uniform pressure p on a closed surface does work p·V, so the
term −p·V(x) with V the enclosed volume gives the follower pressure force as its gradient and a
symmetric Hessian. V = s/6 Σ x_a·(x_b × x_c) over the surface's linear triangles (each 6-node
P2 triangle split into 4), s = ±1 by orientation."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from ..linalg import element_pattern

__all__ = ["PressureTerm", "linear_subtriangles", "enclosed_volume"]


def linear_subtriangles(faces6: np.ndarray) -> np.ndarray:
    """Split 6-node triangles (corners a, b, c; midpoints ab, bc, ca) into 4 linear ones."""
    a, b, c, ab, bc, ca = faces6.T
    return np.concatenate([np.column_stack(t) for t in ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))])


def enclosed_volume(x: np.ndarray, tris: np.ndarray, sign: float = 1.0) -> float:
    p = x[tris]
    return sign * float(np.einsum("ti,ti->t", p[:, 0], np.cross(p[:, 1], p[:, 2])).sum()) / 6


def _skew(v: np.ndarray) -> np.ndarray:
    z = np.zeros(len(v))
    return np.stack([np.stack([z, -v[:, 2], v[:, 1]], -1), np.stack([v[:, 2], z, -v[:, 0]], -1), np.stack([-v[:, 1], v[:, 0], z], -1)], 1)


def _volume_hessian_entries(p: np.ndarray, sign: float) -> np.ndarray:
    """∂²V/∂x² of each triangle (k, 81), [a-block row][i][b-block col][j], from its corners ``p``
    (k, 3, 3): ∂²V/∂x_a∂x_b = −s[x_c]×, ∂²V/∂x_a∂x_c = s[x_b]×, ∂²V/∂x_b∂x_c = −s[x_a]× (s = sign/6)."""
    Ka, Kb, Kc = _skew(p[:, 0]), _skew(p[:, 1]), _skew(p[:, 2])
    Z = np.zeros_like(Ka)
    blocks = np.stack([np.stack([Z, -Kc, Kb], 1), np.stack([Kc, Z, -Ka], 1), np.stack([-Kb, Ka, Z], 1)], 1)
    return (sign / 6 * blocks).transpose(0, 1, 3, 2, 4).reshape(len(p), 81)


class PressureTerm:
    """−p·V(X + u) for the volume V enclosed by ``tris`` (k, 3) linear triangles of the mesh's
    nodes ``X`` (n, 3); ``sign`` = +1 when the triangles' normals point out of that volume.
    Set ``pressure`` (Pa) between solves to load in steps."""

    def __init__(self, X: np.ndarray, tris: np.ndarray, pressure: float = 0.0, sign: float = 1.0):
        self.X = np.asarray(X, float)
        self.tris = np.asarray(tris, np.int64)
        self.pressure = float(pressure)
        self.sign = float(sign)
        n = 3 * len(X)
        t = self.tris
        dof = (3 * t[:, :, None] + np.arange(3)).reshape(-1, 9)
        # the Hessian's pattern is fixed by the triangles
        indptr, self._indices, slot = element_pattern(dof, n)
        self._indptr = indptr.astype(np.int32)
        self._n = n
        self._gradient_dof = dof.ravel()
        # ∂²V/∂x² is linear in the positions (V is cubic), so its values on that pattern are a
        # fixed sparse map of x: built once from the entries' response to each corner
        # coordinate, each Hessian is then one sparse product (a COO → CSR assembly per call,
        # with its sort and duplicate sum, took ~20× as long on the 92-rim dome's inner surface)
        k = len(t)
        rows_l, cols_l, vals_l = [], [], []
        for c in range(9):
            unit = np.zeros((k, 3, 3))
            unit[:, c // 3, c % 3] = 1.0
            entries = _volume_hessian_entries(unit, self.sign)  # (k, 81), per unit coordinate
            nz = np.nonzero(entries)
            rows_l.append(slot.reshape(k, 81)[nz])
            cols_l.append(3 * t[nz[0], c // 3] + c % 3)
            vals_l.append(entries[nz])
        self._hessian_map = sp.csr_matrix(
            (np.concatenate(vals_l), (np.concatenate(rows_l), np.concatenate(cols_l))), shape=(len(self._indices), n)
        )

    def volume(self, u: np.ndarray) -> float:
        return enclosed_volume(self.X + u, self.tris, self.sign)

    def volume_gradient(self, u: np.ndarray) -> np.ndarray:
        """∂V/∂u, flat (3n,)."""
        return self._volume_gradient((self.X + u)[self.tris])

    def _volume_gradient(self, p: np.ndarray) -> np.ndarray:
        """∂V/∂u from the triangles' corner positions ``p`` (k, 3, 3)."""
        dV = self.sign / 6 * np.stack([np.cross(p[:, 1], p[:, 2]), np.cross(p[:, 2], p[:, 0]), np.cross(p[:, 0], p[:, 1])], 1)
        return np.bincount(self._gradient_dof, weights=dV.ravel(), minlength=self._n)

    def evaluate(self, u: np.ndarray, hessian: bool):
        x = self.X + u
        p = x[self.tris]
        V = enclosed_volume(x, self.tris, self.sign)
        g = self._volume_gradient(p)
        H = None
        if hessian:
            values = self._hessian_map @ x.ravel()
            H = sp.csr_matrix((-self.pressure * values, self._indices, self._indptr), shape=(self._n, self._n))
        return -self.pressure * V, -self.pressure * g, H, True

    def projected_hessian(self, u: np.ndarray) -> sp.csr_matrix:
        """The pressure Hessian is indefinite; the projected Newton step leaves it out."""
        return sp.csr_matrix((self._n, self._n))
