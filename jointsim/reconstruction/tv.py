"""Total-variation images by lagged diffusivity (Vogel & Oman's fixed-point iteration), with λ
chosen for total variation itself by the discrepancy principle.

The image x (n_cells,) of a frame's δV (n_meas,) minimises

    ‖J x − δV‖² + λ Σ_e √((D x)_e² + β²)  (+ a small ridge ε‖x‖²)

with D the voxel graph's difference operator (one row per pair of neighbouring cells, weighted
as the graph Laplacian L = DᵀD is) and β a small smoothing of the corner at zero. Each step
freezes the weights of the TV term at the last image and solves the quadratic problem

    (JᵀJ + Dᵀ W D + εI) x = Jᵀ δV,   W = diag(λ / (2 √((D x_k)² + β²))),

in the measurement space by the Woodbury identity (x = Q⁻¹Jᵀ (I + J Q⁻¹ Jᵀ)⁻¹ δV, Q = DᵀWD + εI
sparse, factorised once per step, by PARDISO where it is installed: its solve of the n_meas
right-hand sides is 4× SuperLU's on 7000 cells): each step lowers the objective (the fixed point
of a majorise–minimise scheme). It starts from the smooth image (the Laplacian prior's).

λ (Morozov's discrepancy principle): the λ at which the images of the representative press's
noisy frames leave a residual as large as the noise, mean ‖J x − δV‖² = n_meas σ², σ the
standard deviation of one δV entry. A smaller λ fits the noise (an earlier choice, matching
the Laplacian's weight at the smooth image's median edge, did: its images' CoM went to the
electrodes); a larger one leaves signal in the residual. β is a hundredth of the smooth image's
largest edge difference on that press.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ..linalg import available_backends, factorize

__all__ = ["difference_operator", "TVImager", "tv_objective", "discrepancy_lambda"]

ITERATIONS = 12  # lagged-diffusivity steps at most (the image changes < TOL after ~5–10 here)
TOL = 1e-3  # stop when a step changes the image by less than this × its norm
BETA = 1e-2  # × the smooth image's largest edge difference: the corner's smoothing
BISECTIONS = 8  # halvings of the 10⁶-wide log-λ bracket: λ within 6 % of the root
LAMBDA_FRAMES = 2  # the representative press's frames λ is chosen on (each bisection images them all)


def difference_operator(laplacian: sp.spmatrix) -> sp.csr_matrix:
    """D (n_edges, n_cells) with DᵀD = ``laplacian`` (a weighted graph Laplacian: off-diagonal
    −w_ij ≤ 0): one row √w_ij (e_i − e_j) per pair of neighbouring cells i < j."""
    L = sp.triu(sp.csr_matrix(laplacian), k=1).tocoo()
    keep = L.data < 0
    i, j, w = L.row[keep], L.col[keep], np.sqrt(-L.data[keep])
    e = np.arange(len(w))
    return sp.csr_matrix((np.concatenate([w, -w]), (np.concatenate([e, e]), np.concatenate([i, j]))),
                         shape=(len(w), laplacian.shape[0]))


def tv_objective(J: np.ndarray, D: sp.spmatrix, x: np.ndarray, dv: np.ndarray, lam: float, beta: float,
                 ridge: float = 0.0) -> float:
    """‖J x − δV‖² + λ Σ √((D x)² + β²) + ridge ‖x‖²."""
    r = J @ x - dv
    return float(r @ r + lam * np.sqrt((D @ x) ** 2 + beta**2).sum() + ridge * x @ x)


@dataclass(frozen=True, eq=False)
class TVImager:
    """Total-variation images on the cells of ``J`` (n_meas, n_cells) with difference operator
    ``D``, weight ``lam``, corner ``beta`` and ``ridge`` ε (module docstring), each from the
    smooth image given to :meth:`image`."""

    J: np.ndarray
    D: sp.csr_matrix
    lam: float
    beta: float
    ridge: float
    iterations: int = ITERATIONS

    def image(self, dv: np.ndarray, x0: np.ndarray) -> np.ndarray:
        """The TV image of ``dv`` (n_meas,) from ``x0`` (n_cells,): the smooth image, or any
        nearer start (the objective is convex: the same image, in fewer steps)."""
        x = np.array(x0, float)
        eye = sp.identity(self.J.shape[1], format="csc")
        backend = "pardiso" if "pardiso" in available_backends() else "auto"
        for _ in range(self.iterations):
            w = self.lam / (2 * np.sqrt((self.D @ x) ** 2 + self.beta**2))
            Q = (self.D.T @ sp.diags(w) @ self.D + self.ridge * eye).tocsc()
            with factorize(Q, backend) as solve:
                QJt = solve(self.J.T)  # Q⁻¹Jᵀ (n_cells, n_meas)
            new = QJt @ np.linalg.solve(np.eye(len(dv)) + self.J @ QJt, dv)
            step = np.linalg.norm(new - x)
            x = new
            if step <= TOL * np.linalg.norm(x):
                break
        return x


def discrepancy_lambda(J: np.ndarray, D: sp.csr_matrix, frames: np.ndarray, starts: np.ndarray, noise_std: float,
                       ridge: float, lam_smooth: float) -> TVImager:
    """The imager whose λ leaves the images of ``frames`` (k, n_meas; the first LAMBDA_FRAMES)
    — started from their smooth images ``starts`` (k, n_cells), whose prior weighs ‖Dx‖² by
    ``lam_smooth`` — a mean squared residual of n_meas ``noise_std``² (module docstring):
    bisection on log λ in [lam0/1e3, lam0·1e3], lam0 the λ at which TV's weight equals the smooth
    prior's at the first smooth image's median edge; β from that image too. At a bracket's end
    (the noise above every residual, or below) λ is that end."""
    frames, starts = np.atleast_2d(frames)[:LAMBDA_FRAMES], np.atleast_2d(starts)[:LAMBDA_FRAMES]
    edges = np.abs(D @ starts[0])
    beta = BETA * float(edges.max())
    lam0 = 2 * lam_smooth * float(np.median(np.sqrt(edges**2 + beta**2))) or lam_smooth
    target = J.shape[0] * noise_std**2
    last = list(starts)  # each evaluation starts from the last one's images

    def excess(log_lam: float) -> float:
        imager = TVImager(J, D, float(np.exp(log_lam)), beta, ridge)
        last[:] = [imager.image(d, x) for d, x in zip(frames, last)]
        residuals = [J @ x - d for d, x in zip(frames, last)]
        return float(np.mean([r @ r for r in residuals])) - target

    lo, hi = np.log(lam0) - np.log(1e3), np.log(lam0) + np.log(1e3)
    if excess(lo) >= 0:
        return TVImager(J, D, float(np.exp(lo)), beta, ridge)
    if excess(hi) <= 0:
        return TVImager(J, D, float(np.exp(hi)), beta, ridge)
    for _ in range(BISECTIONS):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if excess(mid) < 0 else (lo, mid)
    return TVImager(J, D, float(np.exp(0.5 * (lo + hi))), beta, ridge)
