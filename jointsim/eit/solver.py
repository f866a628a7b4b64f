"""Sparse direct factorisation of the SPD CEM system, factorised once and solved for many
right-hand sides. SuperLU from scipy is always there; CHOLMOD (scikit-sparse) or PARDISO
(pypardiso) are used when installed and asked for."""

from __future__ import annotations

from typing import Callable

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

__all__ = ["factorize", "available_backends"]


def available_backends() -> list[str]:
    out = ["superlu"]
    try:
        import sksparse.cholmod  # noqa: F401

        out.append("cholmod")
    except ImportError:
        pass
    try:
        import pypardiso  # noqa: F401

        out.append("pardiso")
    except ImportError:
        pass
    return out


def factorize(A: sp.spmatrix, backend: str = "superlu") -> Callable[[np.ndarray], np.ndarray]:
    """Factorise the SPD matrix A once; return solve(B) for B (n,) or (n, k)."""
    A = sp.csc_matrix(A)
    if backend == "superlu":
        # a symmetric fill-reducing ordering and no pivoting: A is SPD, so LU = LDLᵀ in effect
        lu = spla.splu(
            A,
            permc_spec="MMD_AT_PLUS_A",
            diag_pivot_thresh=0.0,
            options={"SymmetricMode": True},
        )
        return lambda b: lu.solve(np.asarray(b, float))
    if backend == "cholmod":
        from sksparse.cholmod import cholesky

        f = cholesky(A)
        return lambda b: f(np.asarray(b, float))
    if backend == "pardiso":
        import pypardiso

        solver = pypardiso.PyPardisoSolver(mtype=2)  # real SPD
        Au = sp.triu(A, format="csr")
        solver.factorize(Au)
        return lambda b: solver.solve(Au, np.asarray(b, float))
    raise ValueError(f"backend = {backend!r}: allowed values are {available_backends()}")
