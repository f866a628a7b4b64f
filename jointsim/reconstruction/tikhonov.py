"""Tikhonov difference imaging with the regularisation chosen from one SVD: zeroth order, or a
prior ‖x‖²_P (NOSER, a smoothness Laplacian) through the generalized factors (:meth:`SVD.generalized`).

    x_λ = argmin ‖J x − δv‖² + λ²‖x‖² = V diag(s / (s² + λ²)) Uᵀ δv,   J = U S Vᵀ.

The hat matrix H_λ = U diag(f) Uᵀ with filter factors f = s²/(s² + λ²) gives every selection
score for a whole λ grid without refitting:

- leave-one-out CV: e_i = r_i / (1 − H_ii);
- k-fold CV: the held-out residuals of fold F are (I − H_FF)⁻¹ r_F (exact for ridge regression);
- GCV: n‖r‖² / (n − tr H)²;
- L-curve: the corner (maximum curvature) of (log ‖r‖, log ‖x‖).

Once λ is fixed, the reconstruction matrix R (n_cells, n_meas) is stored and one frame's image
costs a matrix–vector product.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

__all__ = ["PRIORS", "LAPLACIAN_RIDGE", "prior_matrix", "SVD", "LambdaChoice", "Reconstructor", "choose_lambda", "lambda_grid", "tikhonov_solve"]

METHODS = ("kfold", "loo", "gcv", "lcurve")
# the image's prior ‖x‖²_P: "tikhonov" P = I (zeroth order, the paper's); "noser" P = diag(JᵀJ)
# (Cheney et al. 1990: each cell weighed by its sensitivity, which undoes the zeroth order's
# pull of the image towards the electrodes); "laplacian" P = L + εI, L the voxel graph
# Laplacian (first-order smoothness; ε = 1e-3 × its mean diagonal keeps P definite); "depth"
# P = diag(((z + z₀)/H)^−q), z a cell's height above the base (where the electrodes are), H the
# highest cell's, z₀ half a voxel, q the exponent: a cell near the base costs more, which counters
# the pull of the image towards the electrodes (its CoM sits ~3 mm low under Tikhonov;
# results/image_priors.md), as geophysics' depth weighting does for surface sensors; "tv" total
# variation (jointsim.reconstruction.tv), started from the Laplacian's image
PRIORS = ("tikhonov", "noser", "laplacian", "depth", "tv")
LAPLACIAN_RIDGE = 1e-3  # "laplacian"'s ε (and "tv"'s), × L's mean diagonal
DEPTH_EXPONENT = 2.0  # [reconstruction] depth_exponent's default


def prior_matrix(name: str, J: np.ndarray, laplacian: sp.spmatrix | None = None, heights: np.ndarray | None = None,
                 exponent: float = DEPTH_EXPONENT, half_voxel: float = 0.0) -> sp.csr_matrix | None:
    """P of the prior ``name`` (:data:`PRIORS`; None for "tikhonov", the identity) for the
    Jacobian ``J`` (n_meas, n_cells) on cells with graph Laplacian ``laplacian``, at
    ``heights`` (n_cells,) m above the base ("depth", with ``exponent`` and ``half_voxel``, m)."""
    if name == "tikhonov":
        return None
    if name == "depth":
        if heights is None:
            raise ValueError("prior 'depth': the cells' heights are needed")
        z = np.asarray(heights, float) + half_voxel
        return sp.diags((z / z.max()) ** (-float(exponent))).tocsr()
    if name == "noser":
        return sp.diags(np.einsum("ij,ij->j", J, J)).tocsr()
    if name in ("laplacian", "tv"):  # tv: its smooth start (jointsim.reconstruction.tv)
        if laplacian is None:
            raise ValueError(f"prior {name!r}: the cells' graph Laplacian is needed")
        eps = LAPLACIAN_RIDGE * float(laplacian.diagonal().mean())
        return (laplacian + eps * sp.identity(laplacian.shape[0])).tocsr()
    raise ValueError(f"prior = {name!r}: one of {', '.join(PRIORS)}")


@dataclass(frozen=True, eq=False)
class SVD:
    """Thin SVD of the Jacobian: ``U`` (n_meas, r), ``s`` (r,), ``Vt`` (r, n_cells)."""

    U: np.ndarray
    s: np.ndarray
    Vt: np.ndarray

    @classmethod
    def of(cls, J: np.ndarray) -> "SVD":
        J = np.asarray(J, float)
        if J.ndim != 2 or not np.isfinite(J).all():
            raise ValueError("J: expected a finite 2-D Jacobian (n_meas, n_cells)")
        U, s, Vt = np.linalg.svd(J, full_matrices=False)
        return cls(U, s, Vt)

    @classmethod
    def generalized(cls, J: np.ndarray, P: sp.spmatrix, rtol: float = 1e-13) -> "SVD":
        """The factors for the prior xᵀPx (P (n_cells, n_cells) sparse, symmetric positive
        definite): with Y = P⁻¹Jᵀ and JY = U S² Uᵀ, Vt = S⁻¹UᵀYᵀ makes
        :meth:`reconstruction_matrix` R = P⁻¹Jᵀ(JP⁻¹Jᵀ + λ²I)⁻¹ = argmin ‖Jx − δv‖² + λ²xᵀPx,
        and the data-space quantities (U, s) every λ score needs are those of J P^{-1/2}.
        Singular values below ``rtol`` × the largest are dropped."""
        from scipy.sparse.linalg import splu

        J = np.asarray(J, float)
        Y = splu(sp.csc_matrix(P)).solve(np.ascontiguousarray(J.T))
        M = J @ Y
        w, U = np.linalg.eigh(0.5 * (M + M.T))
        order = np.argsort(w)[::-1]
        w, U = w[order], U[:, order]
        keep = w > rtol * w[0]
        s = np.sqrt(w[keep])
        U = U[:, keep]
        return cls(U, s, ((Y @ U) / s).T)

    def filters(self, lam: np.ndarray) -> np.ndarray:
        """Filter factors f = s²/(s² + λ²), shape (n_lambda, r)."""
        s2 = self.s**2
        return s2 / (s2 + np.asarray(lam, float)[:, None] ** 2)

    def reconstruction_matrix(self, lam: float) -> np.ndarray:
        """R = V diag(s/(s² + λ²)) Uᵀ, (n_cells, n_meas)."""
        g = self.s / (self.s**2 + lam**2)
        return (self.Vt.T * g) @ self.U.T


def lambda_grid(svd: SVD, n: int = 600, decades_below: float = 6.0, decades_above: float = 1.0) -> np.ndarray:
    """Log-spaced λ from s_max·10^-decades_below to s_max·10^decades_above."""
    smax = float(svd.s[0])
    return np.logspace(np.log10(smax) - decades_below, np.log10(smax) + decades_above, n)


@dataclass(frozen=True)
class LambdaChoice:
    """The chosen ``lam``, the ``method``, the ``grid`` and each λ's ``score`` (lower is better;
    for the L-curve, minus the curvature)."""

    lam: float
    method: str
    grid: np.ndarray
    score: np.ndarray

    def plot(self, ax=None):
        import matplotlib.pyplot as plt

        ax = ax or plt.gca()
        ax.loglog(self.grid, self.score if self.method != "lcurve" else -self.score + 1e-300)
        ax.axvline(self.lam, color="k", ls="--", lw=0.8)
        ax.set_xlabel("λ")
        ax.set_ylabel({"kfold": "k-fold CV error", "loo": "LOO CV error", "gcv": "GCV", "lcurve": "curvature"}[self.method])
        return ax


def choose_lambda(
    svd: SVD,
    dv: np.ndarray,
    method: str = "kfold",
    grid: np.ndarray | None = None,
    k: int = 10,
    seed: int = 0,
) -> LambdaChoice:
    """Select λ for the data ``dv`` (n_meas,), or several frames (n_frames, n_meas) whose
    scores are summed, by ``method`` in ("kfold", "loo", "gcv", "lcurve")."""
    if method not in METHODS:
        raise ValueError(f"method = {method!r}: allowed values are {METHODS}")
    grid = lambda_grid(svd) if grid is None else np.asarray(grid, float)
    if grid.ndim != 1 or len(grid) < 2 or not (np.isfinite(grid).all() and (grid > 0).all()):
        raise ValueError("grid: λ values must be a 1-D array of at least 2 finite values > 0")
    dv = np.atleast_2d(np.asarray(dv, float))
    n = svd.U.shape[0]
    if dv.shape[1] != n:
        raise ValueError(f"dv: expected {n} measurements per frame, got {dv.shape[1]}")
    if not np.any(dv):
        raise ValueError("dv: all-zero voltage change; there is nothing to reconstruct")
    F = svd.filters(grid)  # (L, r)
    c = dv @ svd.U  # (frames, r): data in the singular basis
    outside = dv - c @ svd.U.T  # the part of dv no λ can fit
    # residuals r = dv − H dv for every λ and frame: (L, frames, n), as a batched matrix product
    # (BLAS): numpy's einsum of three operands loops in C instead (choose_lambda ~10× slower with it)
    r = (c[None] * (1 - F)[:, None, :]) @ svd.U.T + outside[None]
    if method == "loo":
        h = F @ (svd.U**2).T  # (L, n) diagonal of H
        score = ((r / (1 - h)[:, None, :]) ** 2).sum(axis=(1, 2))
    elif method == "gcv":
        tr = F.sum(axis=1)
        score = n * (r**2).sum(axis=(1, 2)) / (n - tr) ** 2
    elif method == "kfold":
        if not 2 <= k <= n:
            raise ValueError(f"k = {k}: must be in [2, {n}]")
        folds = np.array_split(np.random.default_rng(seed).permutation(n), k)
        score = np.zeros(len(grid))
        for idx in folds:
            Uf = svd.U[idx]  # (m, r)
            Hff = (Uf[None] * F[:, None, :]) @ Uf.T  # (L, m, m): the fold's block of each H
            A = np.eye(len(idx))[None] - Hff
            e = np.linalg.solve(A, np.swapaxes(r[:, :, idx], 1, 2))  # (L, m, frames)
            score += (e**2).sum(axis=(1, 2))
    else:  # lcurve
        rn = np.log(np.sqrt((r**2).sum(axis=(1, 2))))
        g = svd.s / (svd.s**2 + grid[:, None] ** 2)
        xn = np.log(np.sqrt(((c[None] * g[:, None, :]) ** 2).sum(axis=(1, 2))))
        t = np.log(grid)
        d1r, d1x = np.gradient(rn, t), np.gradient(xn, t)
        d2r, d2x = np.gradient(d1r, t), np.gradient(d1x, t)
        kappa = (d1r * d2x - d2r * d1x) / (d1r**2 + d1x**2) ** 1.5
        score = -kappa
    i = int(np.argmin(score))
    return LambdaChoice(float(grid[i]), method, grid, score)


def tikhonov_solve(J: np.ndarray, dv: np.ndarray, lam: float) -> np.ndarray:
    """x = (JᵀJ + λ²I)⁻¹ Jᵀ dv through the SVD (reference path for one-off solves)."""
    return SVD.of(J).reconstruction_matrix(lam) @ dv


@dataclass(frozen=True, eq=False)
class Reconstructor:
    """A fixed reconstruction: ``R`` (n_cells, n_meas) for the chosen ``choice``.

    ``image(dv)`` maps (n_meas,) or (n_frames, n_meas) voltage changes to conductivity
    changes per cell in S/m."""

    R: np.ndarray
    choice: LambdaChoice

    @classmethod
    def build(cls, J: np.ndarray, dv_for_lambda: np.ndarray, method: str = "kfold", **kw) -> "Reconstructor":
        svd = SVD.of(J)
        choice = choose_lambda(svd, dv_for_lambda, method, **kw)
        return cls(svd.reconstruction_matrix(choice.lam), choice)

    @property
    def lam(self) -> float:
        return self.choice.lam

    def image(self, dv: np.ndarray) -> np.ndarray:
        dv = np.asarray(dv, float)
        return dv @ self.R.T if dv.ndim == 2 else self.R @ dv

    def noise_std(self, sigma_noise: float | np.ndarray) -> np.ndarray:
        """Per-cell standard deviation of the image under white noise of std ``sigma_noise``
        (scalar, or per measurement (n_meas,)): sqrt(Σ_j R_ij² σ_j²)."""
        s2 = np.broadcast_to(np.asarray(sigma_noise, float) ** 2, (self.R.shape[1],))
        return np.sqrt((self.R**2) @ s2)

    def normalised_image(self, dv: np.ndarray, sigma_noise: float | np.ndarray) -> np.ndarray:
        """The image divided by its per-cell noise standard deviation."""
        return self.image(dv) / self.noise_std(sigma_noise)
