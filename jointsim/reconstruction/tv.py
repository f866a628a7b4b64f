"""Total-variation images by lagged diffusivity (Vogel & Oman's fixed-point iteration).

The image x (n_cells,) of a frame's δV (n_meas,) minimises

    ‖J x − δV‖² + λ Σ_e √((D x)_e² + β²)  (+ the smooth prior's small ridge ε‖x‖²)

with D the voxel graph's difference operator (one row per pair of neighbouring cells, weighted
as the graph Laplacian L = DᵀD is) and β a small smoothing of the corner at zero. Each step
freezes the weights of the TV term at the last image and solves the quadratic problem

    (JᵀJ + Dᵀ W D) x = Jᵀ δV,   W = diag(λ / (2 √((D x_k)² + β²))) (+ ε I for a definite matrix),

in the measurement space by the Woodbury identity (x = Q⁻¹Jᵀ (I + J Q⁻¹ Jᵀ)⁻¹ δV, Q = DᵀWD + εI
sparse, factorised once per step): each step decreases the objective (the fixed point of a
majorise–minimise scheme). It starts from the smooth image (the Laplacian prior's, whose λ the
instrument chose), and λ is set so that at that image's median edge the TV weight equals the
Laplacian's: the two priors then pull alike where the smooth image is typical, and TV lets the
edges that stand out through.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ..linalg import factorize

__all__ = ["difference_operator", "TVImager", "tv_objective"]

ITERATIONS = 12  # lagged-diffusivity steps at most (the image changes < TOL after ~5–10 here)
TOL = 1e-3  # stop when a step changes the image by less than this × its norm
BETA = 1e-2  # × the smooth image's largest edge difference: the corner's smoothing


def difference_operator(laplacian: sp.spmatrix) -> sp.csr_matrix:
    """D (n_edges, n_cells) with DᵀD = ``laplacian`` (a weighted graph Laplacian: off-diagonal
    −w_ij ≤ 0): one row √w_ij (e_i − e_j) per pair of neighbouring cells i < j."""
    L = sp.triu(sp.csr_matrix(laplacian), k=1).tocoo()
    keep = L.data < 0
    i, j, w = L.row[keep], L.col[keep], np.sqrt(-L.data[keep])
    e = np.arange(len(w))
    return sp.csr_matrix((np.concatenate([w, -w]), (np.concatenate([e, e]), np.concatenate([i, j]))),
                         shape=(len(w), laplacian.shape[0]))


def tv_objective(J: np.ndarray, D: sp.spmatrix, x: np.ndarray, dv: np.ndarray, lam: float, beta: float, ridge: float = 0.0) -> float:
    """‖J x − δV‖² + λ Σ √((D x)² + β²) + ridge ‖x‖²."""
    r = J @ x - dv
    return float(r @ r + lam * np.sqrt((D @ x) ** 2 + beta**2).sum() + ridge * x @ x)


@dataclass(frozen=True, eq=False)
class TVImager:
    """Total-variation images on the cells of ``J`` (n_meas, n_cells) with difference operator
    ``D``, λ matched to the smooth prior's weight ``lam_smooth`` on ‖Dx‖² (module docstring),
    with the smooth prior's ``ridge`` × ‖x‖² kept (its εI), from the smooth image given to
    :meth:`image`."""

    J: np.ndarray
    D: sp.csr_matrix
    lam_smooth: float
    ridge: float
    iterations: int = ITERATIONS

    def image(self, dv: np.ndarray, x0: np.ndarray) -> np.ndarray:
        """The TV image of ``dv`` (n_meas,) from the smooth image ``x0`` (n_cells,)."""
        g0 = np.abs(self.D @ x0)
        if not g0.max() > 0:
            return x0.copy()
        beta = BETA * float(g0.max())
        lam = 2 * self.lam_smooth * float(np.median(np.sqrt(g0**2 + beta**2)))
        x = x0.copy()
        for _ in range(self.iterations):
            w = lam / (2 * np.sqrt((self.D @ x) ** 2 + beta**2))
            Q = (self.D.T @ sp.diags(w) @ self.D + self.ridge * sp.identity(self.J.shape[1])).tocsc()
            with factorize(Q) as solve:
                QJt = solve(self.J.T)  # Q⁻¹Jᵀ (n_cells, n_meas)
            new = QJt @ np.linalg.solve(np.eye(len(dv)) + self.J @ QJt, dv)
            step = np.linalg.norm(new - x)
            x = new
            if step < TOL * np.linalg.norm(x):
                break
        return x
