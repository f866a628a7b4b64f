"""Shared sparse linear algebra, below mechanics, mesh and EIT: direct factorisation of
symmetric systems (the SPD CEM matrix, the symmetric indefinite Newton Hessians of the
mechanics, the morph's Laplacian), factorised once and solved for many right-hand sides, and
the CSR pattern helper their assemblies share.

"auto" picks by size, from results/solver_choice.md (the CEM matrices of the paper's chamber,
one thread, analysis included on both sides, MKL's loading apart): scipy's SuperLU for systems
of fewer than 150 k stored entries, where the two tie (0.019 / 0.020 s at 44 k entries, 0.065 /
0.060 s at 115 k: the dataset preset's P1), PARDISO (pypardiso) above (P2 at 573 k entries:
0.27 s against SuperLU's 0.62 s; 1.5 M: 0.94 against 3.2 s; SuperLU's fill-in grows fastest on
3-D meshes). CHOLMOD (scikit-sparse < 0.5, optional, needs SuiteSparse from the system) is used
when asked for. "cudss" factorises on an NVIDIA GPU (cuDSS through nvmath-python, where both are
installed: :mod:`jointsim._cudss`), its analysis kept across the factorisations of one pattern.

The environment variable ``JOINTSIM_SOLVER`` (auto, superlu, pardiso, cholmod, cudss) sets the
backend "auto" resolves to in this process and in the worker processes it starts (the commands'
``--solver``): every factorisation, the CEM forward's and Newton's alike, then uses it.
"""

from __future__ import annotations

import hashlib
import os
import weakref
from collections import OrderedDict
from typing import Callable

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

__all__ = [
    "Factorization", "PatternSolver", "factorize", "available_backends", "default_backend", "large_backend",
    "preferred_backend", "require_backend", "csr_pattern", "element_pattern", "SOLVERS", "SOLVER_VARIABLE",
]


def csr_pattern(rows: np.ndarray, cols: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The CSR pattern of the n × n matrix with entries at (``rows``, ``cols``), duplicates
    merged: (indptr (int64), indices (int32), slot), ``slot`` the position of each given entry in
    it, so that the values are ``np.bincount(slot, weights=entries, minlength=len(indices))``."""
    uniq, slot = np.unique(np.asarray(rows, np.int64) * n + np.asarray(cols, np.int64), return_inverse=True)
    return _csr_of_keys(uniq, slot.ravel(), n)


def _csr_of_keys(uniq: np.ndarray, slot: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(indptr, indices, slot) of the sorted unique entry keys row·n + col ``uniq``."""
    return np.searchsorted(uniq // n, np.arange(n + 1)), (uniq % n).astype(np.int32), slot


# the last few element patterns (element_pattern): a dataset worker builds the same membrane and
# chamber for every press, and the membrane Hessian's pattern alone (a sort of ~8 M entries) took
# ~0.16 s each time
_PATTERNS: OrderedDict[tuple, tuple[np.ndarray, np.ndarray]] = OrderedDict()
_PATTERNS_KEPT = 4  # a dataset worker's: the membrane's elastic and pressure terms, the chamber's CEM


def element_pattern(dof: np.ndarray, n: int, rows: np.ndarray | None = None,
                    cols: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`csr_pattern` of the n × n matrix assembled from dense blocks on the element dofs
    ``dof`` (m, k), entry (e, a, b) in slot[e·k² + a·k + b], and, after them, the entries at
    (``rows``, ``cols``) (a few, such as the electrodes' terms). The blocks' part is remembered
    by content for the next call with the same dofs: the pattern is then the union of its keys
    with the few others', the same arrays as a sort of all the entries would give. The arrays
    returned are read-only where they are shared."""
    dof = np.ascontiguousarray(dof, np.int64)
    key = (int(n), dof.shape, hashlib.sha1(dof.data).hexdigest())
    blocks = _PATTERNS.get(key)
    if blocks is None:
        k = dof.shape[1]
        uniq, slot = np.unique((np.repeat(dof, k, axis=1) * n + np.tile(dof, (1, k))).ravel(), return_inverse=True)
        blocks = (uniq, slot.ravel())
        for a in blocks:
            a.flags.writeable = False
        _PATTERNS[key] = blocks
        while len(_PATTERNS) > _PATTERNS_KEPT:
            _PATTERNS.popitem(last=False)
    else:
        _PATTERNS.move_to_end(key)
    uniq, slot = blocks
    if rows is not None and len(rows):
        extra = np.asarray(rows, np.int64) * n + np.asarray(cols, np.int64)
        wanted = np.unique(extra)
        at = np.minimum(np.searchsorted(uniq, wanted), len(uniq) - 1)
        new = wanted[uniq[at] != wanted]  # sorted, unique, none of the blocks' keys
        slot = (np.arange(len(uniq)) + np.searchsorted(new, uniq))[slot]  # the blocks' keys, moved up past the new ones
        uniq = np.insert(uniq, np.searchsorted(uniq, new), new)
        slot = np.concatenate([slot, np.searchsorted(uniq, extra)])
    return _csr_of_keys(uniq, slot, n)


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
    from ._cudss import unavailable

    if unavailable() is None:
        out.append("cudss")
    return out


SOLVER_VARIABLE = "JOINTSIM_SOLVER"
SOLVERS = ("auto", "superlu", "pardiso", "cholmod", "cudss")


def require_backend(name: str, what: str = "--solver") -> str:
    """``name`` when it is a backend this machine can run ("auto" always is), else a ValueError
    naming ``what`` (the flag or variable it came from), why and what is available here."""
    if name == "auto" or name in (here := available_backends()):
        return name
    if name == "cudss":
        from ._cudss import unavailable

        why = unavailable()
    else:
        why = "not installed here" if name in SOLVERS else "not a solver jointsim knows"
    raise ValueError(f"{what} = {name!r}: {why}; available here: auto, {', '.join(here)}")


def preferred_backend() -> str:
    """The backend "auto" resolves to in this process: ``JOINTSIM_SOLVER``'s (checked), or
    "auto" (chosen by each system's size) where it is unset."""
    name = os.environ.get(SOLVER_VARIABLE, "").strip().lower() or "auto"
    return require_backend(name, SOLVER_VARIABLE)


def large_backend() -> str:
    """The backend for large or fill-heavy systems (elasticity Hessians): the preferred one, else
    PARDISO where installed, else SuperLU."""
    chosen = preferred_backend()
    if chosen != "auto":
        return chosen
    return "pardiso" if "pardiso" in available_backends() else "superlu"


SUPERLU_MAX_NNZ = 150_000
# without the entries' count: a P1 CEM row holds ~12.5 entries (150 k / 12.5)
SUPERLU_MAX_UNKNOWNS = 12_000


def default_backend(n_unknowns: int | None = None, nnz: int | None = None) -> str:
    """The backend "auto" resolves to for a system of ``n_unknowns`` with ``nnz`` stored entries
    (large when not given): the process's preferred backend where one is set."""
    chosen = preferred_backend()
    if chosen != "auto":
        return chosen
    small = nnz < SUPERLU_MAX_NNZ if nnz is not None else n_unknowns is not None and n_unknowns < SUPERLU_MAX_UNKNOWNS
    if small:
        return "superlu"
    return "pardiso" if "pardiso" in available_backends() else "superlu"


# pypardiso searches for the MKL library (find_library, then a recursive glob of the Python
# prefix) every time a solver is constructed: ~0.2-4 s. Solvers are therefore kept and reused
# once their factor has been freed.
_PARDISO_IDLE: dict[int, list] = {}


def _pardiso_solver(mtype: int):
    idle = _PARDISO_IDLE.get(mtype)
    if idle:
        return idle.pop()
    import pypardiso

    solver = pypardiso.PyPardisoSolver(mtype=mtype)
    solver.set_statistical_info_off()
    solver.jointsim_iparm = solver.iparm.copy()  # a fresh solver's settings, restored on release
    return solver


PARDISO_REFINEMENT = 2  # iterative refinement steps per solve: MKL's default, iparm(8)
# ...which a Cholesky factor in double precision does not need (tests/test_eit.py: the lead
# fields agree with two steps' to 1e-12). In a scratch run on the paper's chamber (323 k
# tetrahedra, P1 CEM) the two steps took 0.2 s of a 0.47 s factorisation + 16 solves
SPD_REFINEMENT = 0
# PARDISO factors by its two-level algorithm (iparm(24) = 1), which MKL offers for scalability on
# many threads, instead of the classic one-level one. On these 2 cores the paper chamber's CEM
# matrix factorises in the same time and its 16 lead-field solves take 0.71×; the 92/2 membrane's
# Hessian factorises in 1.05× and a solve takes 0.47× (results/pardiso_two_level.md), and its
# press takes ~0.9× the seconds per step (results/mechanics_pair_one_level_factorisation.md: one-level 1.11×)
PARDISO_TWO_LEVEL = True


def _release_pardiso(solver) -> None:
    """Free the factor MKL holds for ``solver`` and keep the solver for reuse."""
    solver.free_memory(everything=True)
    # iparm is read and written by MKL: a reused solver must start as a fresh one, or its
    # next analysis (and the bits of every later solve) depends on who held it before
    solver.iparm[:] = solver.jointsim_iparm
    _PARDISO_IDLE.setdefault(solver.mtype, []).append(solver)


class Factorization:
    """A factorised matrix: ``fac(B)`` solves A X = B for B (n,) or (n, k). ``free()`` releases
    the factor now; it is also released when the object is garbage-collected (PARDISO keeps
    its factor inside MKL, out of Python's sight, and would leak it otherwise)."""

    def __init__(self, solve: Callable[[np.ndarray], np.ndarray], release: Callable[[], None] | None = None):
        self._solve = solve
        self._finalizer = weakref.finalize(self, release) if release is not None else None

    def __call__(self, b: np.ndarray) -> np.ndarray:
        if self._solve is None:
            raise RuntimeError("factorisation already freed")
        return self._solve(b)

    def free(self) -> None:
        self._solve = None
        if self._finalizer is not None:
            self._finalizer()

    def __enter__(self) -> "Factorization":
        return self

    def __exit__(self, *exc) -> None:
        self.free()


def factorize(A: sp.spmatrix, backend: str = "auto", spd: bool = True) -> Factorization:
    """Factorise the symmetric matrix A once, for many solves; ``spd=False`` for a symmetric
    indefinite A (PARDISO's Bunch–Kaufman LDLᵀ, or SuperLU with threshold pivoting)."""
    if backend == "auto":
        backend = default_backend(A.shape[0], A.nnz)
    A = sp.csc_matrix(A)
    if backend == "superlu":
        # no pivoting when A is SPD (LU = LDLᵀ in effect)
        lu = _superlu(A, 0.0 if spd else 0.01)
        return Factorization(lambda b: lu.solve(np.asarray(b, float)))
    if backend == "cholmod":
        if not spd:
            return factorize(A, "superlu", spd=False)
        from sksparse.cholmod import cholesky

        f = cholesky(A)
        return Factorization(lambda b: f(np.asarray(b, float)))
    if backend == "pardiso":
        # real SPD (Cholesky) or real symmetric indefinite (LDLᵀ), on the upper triangle
        mtype = 2 if spd else -2
        solver = _pardiso_solver(mtype)
        if spd:  # MKL's settings, made explicit to drop the refinement (restored on release)
            _set_iparm(solver, SPD_REFINEMENT, two_level=PARDISO_TWO_LEVEL)
        Au = sp.triu(A, format="csr")
        Au.sort_indices()
        solver.factorize(Au)

        def solve(b: np.ndarray) -> np.ndarray:
            x = solver.solve(Au, np.ascontiguousarray(b, dtype=float))
            return x.reshape(np.shape(b))

        return Factorization(solve, lambda: _release_pardiso(solver))
    if backend == "cudss":
        from ._cudss import CudssPattern, upper

        indptr, indices, data = upper(A)
        gpu = CudssPattern(indptr, indices, "cholesky" if spd else "inertia")
        gpu.factor(data)
        if spd and not gpu.positive_definite:
            gpu.free()
            raise RuntimeError(f"cuDSS: the matrix is not positive definite (info {gpu.info})")
        return Factorization(gpu.solve, gpu.free)
    raise ValueError(f"backend = {backend!r}: allowed values are {available_backends()}")


def _superlu(A: sp.csc_matrix, diag_pivot_thresh: float):
    """SuperLU of the symmetric ``A`` under a symmetric fill-reducing ordering, preferring
    diagonal pivots (all of them at ``diag_pivot_thresh`` 0)."""
    return spla.splu(A, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=diag_pivot_thresh, options={"SymmetricMode": True})


def _set_iparm(solver, refinement: int, single: bool = False, two_by_two: bool = True, two_level: bool = False) -> None:
    """MKL's defaults for a symmetric matrix, made explicit (iparm(1) = 1) so that the
    iterative refinement steps set here are honoured: with iparm(1) = 0 MKL overwrites every
    entry with its defaults on the first call, refinement included (2 steps: a Newton solve of
    the 48-rim, 3-layer membrane then costs 32 ms instead of 12). ``single``: factor and solve
    in single precision (iparm(28) = 1; the matrix and right-hand sides then float32).
    ``two_by_two``: Bunch–Kaufman 1×1 and 2×2 pivots for a symmetric indefinite matrix; without,
    1×1 pivots only, tiny ones perturbed (iparm(21) = 0; the inertia is then the perturbed
    matrix's, which differs only by pivots ~1e-8·‖A‖). ``two_level``: the two-level
    factorisation (iparm(24) = 1; see PARDISO_TWO_LEVEL)."""
    ip = solver.iparm
    ip[:] = 0
    ip[0] = 1  # user-supplied values
    ip[1] = 3  # METIS nested dissection, OpenMP version (what MKL picks by default here)
    ip[7] = refinement  # iterative refinement steps
    ip[9] = 8  # pivot perturbation 1e-8 (symmetric)
    ip[17] = -1  # report the factor's non-zeros
    ip[20] = 1 if two_by_two else 0
    ip[23] = 1 if two_level else 0
    ip[27] = 1 if single else 0


class PatternSolver:
    """Repeated factorisations of symmetric matrices that share one sparsity pattern — Newton's
    Hessians on a fixed mesh. The pattern is the upper triangle ``(indptr, indices)`` (CSR,
    sorted); PARDISO's ordering and symbolic analysis are done once and each :meth:`factor`
    is numerical only, which at 30 k unknowns of P2 elasticity saves ~40 % of a factorisation.
    Without PARDISO every factor call is a fresh SuperLU, with diagonal pivots only (see
    :meth:`_factor_superlu`), so that it too reports the inertia and can stand in for Cholesky.
    ``spd``: 2 SPD, −2 indefinite (PARDISO's mtype). ``negative_eigenvalues`` (indefinite
    solvers) is the inertia of the last factor, None where it is unknown.

    ``single``: PARDISO factors and solves in single precision (results returned in double):
    1.6× faster factorisations of P2 elasticity (the 92-rim, 2-layer membrane's press:
    results/mechanics_solvers.md), and a solve's relative residual of 1e-5 to 1e-3 on a pressed
    membrane's Hessian — for Newton directions, which need no more (the press's forces agree
    with double to four digits).
    ``two_by_two=False``: 1×1 pivots only; measured no faster there (0.97).
    ``two_level``: PARDISO's two-level factorisation (None: PARDISO_TWO_LEVEL's, when made).

    On "cudss" (the GPU) factorisations are in double precision, the analysis kept likewise;
    ``spd`` matrices are factored by LDLᵀ and tested by its inertia, unless the caller knows them
    positive definite (``known_definite``: the CEM matrix), then by Cholesky. ``columns``: the
    right-hand sides a solve takes at once there (others are solved a column at a time)."""

    def __init__(
        self, indptr: np.ndarray, indices: np.ndarray, spd: bool, backend: str = "auto", refinement: int = PARDISO_REFINEMENT, single: bool = False,
        two_by_two: bool = True, two_level: bool | None = None, known_definite: bool = False, columns: int = 1,
    ):
        self.refinement = int(refinement)
        self.single = bool(single)
        self.two_by_two = bool(two_by_two)
        self.two_level = PARDISO_TWO_LEVEL if two_level is None else bool(two_level)
        self.indptr = np.asarray(indptr, np.int64)
        self.indices = np.asarray(indices, np.int64)
        self.n = len(self.indptr) - 1
        self.spd = spd
        self.known_definite = bool(known_definite)
        self.columns = int(columns)
        if backend == "auto" and (chosen := preferred_backend()) in ("superlu", "pardiso", "cudss"):
            backend = chosen
        if backend == "auto":
            # with the analysis reused, PARDISO's numerical factorisation beats a fresh SuperLU
            # from a few thousand unknowns of P2 elasticity (its fill-in grows fastest)
            big = self.n >= 5_000 and "pardiso" in available_backends()
            backend = "pardiso" if big else "superlu"
        self.backend = backend
        # PARDISO reads the values and right-hand sides as float32 when iparm(28) = 1 (single)
        self._dtype = np.float32 if self.single and backend == "pardiso" else np.float64
        self.negative_eigenvalues: int | None = None
        self._solver = None
        self._analysed = False
        self._A: sp.csr_matrix | None = None
        self._lu = None
        self._gpu = None
        self._definite = False

    def factor(self, data: np.ndarray) -> None:
        if self.backend == "cudss":  # the values go to the GPU as given: no host matrix to keep
            self._factor_cudss(data)
            if self.spd and not self._definite:
                self._A = None
                raise RuntimeError(f"cuDSS: the matrix is not positive definite (info {self._gpu.info})")
            self._A = True  # a factor to solve with
            return
        A = sp.csr_matrix((np.asarray(data, self._dtype), self.indices, self.indptr), shape=(self.n, self.n))
        self._A = A
        if self.backend != "pardiso":
            self._factor_superlu(A)
            return
        if self._solver is None:
            self._solver = _pardiso_solver(2 if self.spd else -2)
            _set_iparm(self._solver, self.refinement, self.single, self.two_by_two, self.two_level)
        b = np.zeros(self.n, self._dtype)
        if not self._analysed:
            self._solver.set_phase(11)
            self._solver._call_pardiso(A, b)
            self._analysed = True
        self._solver.set_phase(22)
        self._solver._call_pardiso(A, b)
        # iparm(23) (1-based): the number of negative pivots of the LDLᵀ factor
        self.negative_eigenvalues = None if self.spd else int(self._solver.iparm[22])

    def _factor_superlu(self, A: sp.csr_matrix) -> None:
        """SuperLU of the symmetric matrix (``A`` its upper triangle) under a symmetric
        fill-reducing ordering, with diagonal pivots only (static pivoting, as PARDISO's): then
        PAPᵀ = LU with U = D·Lᵀ, and U's diagonal has as many negative entries as A has negative
        eigenvalues (Sylvester's law of inertia) and is all positive exactly where A is positive
        definite — what Newton's tests of definiteness read. Where SuperLU met a zero pivot and
        left the diagonal, the rows are permuted apart from the columns: inertia unknown."""
        lu = _superlu((A + sp.triu(A, k=1).T).tocsc(), 0.0)
        self._lu = lu
        pivots = lu.U.diagonal() if np.array_equal(lu.perm_r, lu.perm_c) else np.array([np.nan])
        known = bool(np.all(np.isfinite(pivots)) and np.all(pivots != 0))
        self._definite = known and bool(np.all(pivots > 0))
        self.negative_eigenvalues = None if self.spd or not known else int((pivots < 0).sum())

    def _factor_cudss(self, data: np.ndarray) -> None:
        if self._gpu is None:
            from ._cudss import CudssPattern

            mode = "cholesky" if self.spd and self.known_definite else "inertia"
            self._gpu = CudssPattern(self.indptr, self.indices, mode, self.columns)
        self._gpu.factor(data)
        self._definite = self._gpu.positive_definite
        inertia = self._gpu.inertia
        self.negative_eigenvalues = None if self.spd or inertia is None or self._gpu.info != 0 else inertia[1]

    def try_factor(self, data: np.ndarray) -> bool:
        """:meth:`factor` a matrix that may not be positive definite (``spd`` solvers):
        False where Cholesky meets a non-positive pivot (PARDISO error −4; SuperLU's diagonal
        pivots, the same test), which in exact arithmetic happens exactly when the matrix is not
        positive definite."""
        if not self.spd:
            raise ValueError("try_factor: for Cholesky solvers (spd=True) only")
        if self.backend == "cudss":
            try:
                self.factor(data)
            except RuntimeError:
                return False  # no factor to solve with
            return True
        if self.backend != "pardiso":
            try:
                self.factor(data)
            except RuntimeError:  # SuperLU: "Factor is exactly singular", not positive definite either
                self._definite = False
            if not self._definite:
                self._A, self._lu = None, None  # no factor to solve with
            return self._definite
        try:
            self.factor(data)
        except Exception as e:
            if getattr(e, "value", None) != -4:
                raise
            self._A = None  # no factor to solve with
            return False
        return True

    def solve(self, b: np.ndarray) -> np.ndarray:
        if self._A is None:
            raise RuntimeError("factor() first")
        if self.backend == "cudss":
            return self._gpu.solve(b)
        if self.backend != "pardiso":
            return self._lu.solve(np.asarray(b, float))
        self._solver.set_phase(33)
        x = self._solver._call_pardiso(self._A, np.asfortranarray(b, dtype=self._dtype))
        return x.astype(float, copy=False).reshape(np.shape(b))

    def free(self) -> None:
        if self._solver is not None:
            _release_pardiso(self._solver)
            self._solver = None
        if self._gpu is not None:
            self._gpu.free()
            self._gpu = None
        self._analysed = False
        self._lu = None

    def __del__(self):
        try:
            self.free()
        except Exception:
            pass
