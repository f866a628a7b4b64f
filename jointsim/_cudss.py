"""cuDSS, NVIDIA's sparse direct solver on the GPU, through nvmath-python: the "cudss" backend of
:mod:`jointsim.linalg`, for machines with an NVIDIA GPU and ``nvmath-python`` with cuDSS
installed (``pip install 'nvmath-python[cu13]'``, which brings cuDSS). Nothing here is imported on a
machine without them.

One :class:`CudssPattern` holds one symmetric sparsity pattern (its upper triangle, CSR): the
fill-reducing reordering and symbolic factorisation (cuDSS's analysis) are done on the first
:meth:`~CudssPattern.factor` and kept; every later factor call copies the new values to the GPU
and refactorises numerically only — Newton's Hessians of one membrane, the CEM matrices of one
chamber under morphing. The matrices and right-hand sides stay in host (numpy / scipy) memory on
the caller's side; nvmath copies them across.

``definite="cholesky"`` factors by Cholesky (the CEM matrix: SPD by construction);
``definite="inertia"`` factors by LDLᵀ and reads the inertia (positive and negative pivots), which
is what Newton's tests of definiteness and its indefinite steps need. Double precision throughout.
"""

from __future__ import annotations

import functools
import logging

import numpy as np
import scipy.sparse as sp

__all__ = ["CudssPattern", "unavailable"]

# nvmath logs to the root logger unless given one: at WARNING it would print, on every
# refactorisation, that a reset matrix needs factorize() again (which is what we do) and that no
# multithreading layer was named (used by the one-off analysis only)
_LOG = logging.getLogger("jointsim.cudss")
_LOG.setLevel(logging.ERROR)


@functools.lru_cache(maxsize=1)
def unavailable() -> str | None:
    """Why cuDSS cannot run in this process (None when it can): nvmath-python missing, no CUDA
    device, or the cuDSS library not found."""
    import importlib.util

    if importlib.util.find_spec("nvmath") is None:
        return "nvmath-python is not installed (pip install 'nvmath-python[cu13]', which brings cuDSS)"
    try:
        from cuda.bindings import runtime

        err, count = runtime.cudaGetDeviceCount()
        if int(err) != 0 or count < 1:
            return "no CUDA device is visible"
        from nvmath.bindings import cudss

        cudss.get_property(0)  # loads libcudss
    except Exception as e:  # the driver, CUDA runtime or libcudss missing: their own words say which
        return f"cuDSS cannot start ({type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''})"
    return None


class CudssPattern:
    """cuDSS on one n × n symmetric pattern, given by its upper triangle (CSR, columns sorted).
    ``columns``: the right-hand sides a :meth:`solve` takes at once (others are solved a column
    at a time)."""

    def __init__(self, indptr: np.ndarray, indices: np.ndarray, definite: str = "inertia", columns: int = 1):
        import nvmath.sparse.advanced as nsa

        if definite not in ("cholesky", "inertia"):
            raise ValueError(f"definite = {definite!r}: 'cholesky' or 'inertia'")
        self.n = len(indptr) - 1
        self.definite = definite
        self._indptr = np.asarray(indptr, np.int32)
        self._indices = np.asarray(indices, np.int32)
        self._A = self._csr(np.ones(len(self._indices)))
        self.columns = int(columns)
        self._b = np.zeros(self.n) if self.columns == 1 else np.zeros((self.n, self.columns), order="F")
        kind = nsa.DirectSolverMatrixType.SPD if definite == "cholesky" else nsa.DirectSolverMatrixType.SYMMETRIC
        options = nsa.DirectSolverOptions(sparse_system_type=kind, sparse_system_view=nsa.DirectSolverMatrixViewType.UPPER,
                                          blocking=True, logger=_LOG)
        self._solver = nsa.DirectSolver(self._A, self._b, options=options)
        self._planned = False
        self.info = 0  # cuDSS's status of the last factorisation (0: no failure)
        self.inertia: tuple[int, int] | None = None  # (positive, negative) pivots of the last LDLᵀ

    def _csr(self, data: np.ndarray) -> sp.csr_matrix:
        return sp.csr_matrix((np.asarray(data, np.float64), self._indices, self._indptr), shape=(self.n, self.n))

    def factor(self, data: np.ndarray) -> None:
        """Factorise the matrix of this pattern with values ``data`` (the upper triangle's, in CSR
        order); the analysis is done on the first call only."""
        self._A = self._csr(data)
        self._solver.reset_operands(a=self._A)
        if not self._planned:
            self._solver.plan()
            self._planned = True
        info = self._solver.factorize()
        self.info = int(info.info)
        self.inertia = None if self.definite == "cholesky" else tuple(int(k) for k in info.inertia)

    @property
    def positive_definite(self) -> bool:
        """Whether the last factorisation found the matrix positive definite: Cholesky met no
        non-positive pivot, or LDLᵀ's pivots are all positive."""
        if self.info != 0:
            return False
        return True if self.inertia is None else self.inertia == (self.n, 0)

    def solve(self, b: np.ndarray) -> np.ndarray:
        """A⁻¹ b for b (n,) or (n, k), with the last factor."""
        b = np.asarray(b, np.float64)
        if b.shape == self._b.shape:
            self._solver.reset_operands(b=np.asfortranarray(b))
            return np.array(self._solver.solve()).reshape(b.shape)
        if b.ndim == 1:  # a vector for a solver made for k columns
            wide = np.zeros((self.n, self.columns), order="F")
            wide[:, 0] = b
            return self.solve(wide)[:, 0]
        return np.column_stack([self.solve(b[:, j]) for j in range(b.shape[1])]).reshape(b.shape)

    def free(self) -> None:
        if self._solver is not None:
            self._solver.free()
            self._solver = None


def upper(A: sp.spmatrix) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(indptr, indices, data) of the upper triangle of the symmetric ``A``, columns sorted."""
    U = sp.triu(sp.csr_matrix(A), format="csr")
    U.sort_indices()
    return U.indptr, U.indices, U.data
