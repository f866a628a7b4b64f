"""Quasi-static equilibrium as energy minimisation: Newton's method with a backtracking
(Armijo) line search that also rejects inverted elements. Where the Hessian is indefinite the
step is taken with a positive definite modification of it: H + σ·diag|H| (Levenberg–Marquardt)
when the linear solver reports the inertia, else each term's PSD-projected Hessian. With
PARDISO each Hessian is factored by Cholesky first, which succeeds exactly where it is positive
definite (nearly every Newton iteration of a press), and by LDLᵀ, whose inertia decides the
rest, only where Cholesky fails; the shifted Hessians by Cholesky alone. Optionally
(CHORD_STEPS), once a full step from a positive definite factor lands in Newton's quadratic
regime, the next iterations first try that factor again with the new gradient.

The total energy is a sum of terms (elastic, pressure, contact), each returning its energy,
gradient and Hessian over all 3n displacement components. Dirichlet components are fixed to
given values; Newton runs on the free ones."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
import scipy.sparse as sp

from ..linalg import PatternSolver, factorize, large_backend

__all__ = ["EnergyTerm", "SystemValues", "NodalForce", "NewtonResult", "NewtonError", "NewtonSystem", "minimize_energy", "step_to"]


class NewtonError(RuntimeError):
    """Equilibrium was not reached (no descent, inverted elements, or too many iterations)."""


class EnergyTerm(Protocol):
    """A term may also have ``evaluate_into(u, system)``: the same with the Hessian given as
    that :class:`NewtonSystem`'s values (:class:`SystemValues`), which Newton then uses."""

    def evaluate(self, u: np.ndarray, hessian: bool) -> tuple[float, np.ndarray, sp.spmatrix | None, bool]:
        """(energy, gradient (3n,), Hessian (3n, 3n) or None, admissible)."""


@dataclass(frozen=True, eq=False)
class SystemValues:
    """A Hessian given as ``system``'s free upper-triangle values, in its pattern's order."""

    system: "NewtonSystem"
    values: np.ndarray


class NodalForce:
    """Dead loads ``f`` (n, 3) N on the nodes, as the energy term −f·u."""

    def __init__(self, f: np.ndarray):
        self.f = np.asarray(f, float).ravel()

    def evaluate(self, u: np.ndarray, hessian: bool):
        n = self.f.size
        return -float(self.f @ u.ravel()), -self.f, (sp.csr_matrix((n, n)) if hessian else None), True


@dataclass
class NewtonResult:
    u: np.ndarray  # (n, 3)
    energy: float
    gradient: np.ndarray  # (3n,) total, reactions on the fixed components
    iterations: int  # steps taken, chord steps included
    residual: float  # norm of the free gradient at the end
    history: list[float]
    chord_steps: int = 0  # of the iterations, those that re-used the last factor (no factorisation)


# elasticity Hessians (3 dofs per node, P2 coupling) fill in far more than the EIT matrix:
# PARDISO beats SuperLU already at ~30 k unknowns (0.8 s against 2.3 s for a 5 k-tet P2 shell),
# so the one-off factorisations below take linalg.large_backend() (the preferred one where set)


# Newton's linear systems factored in single precision (PARDISO only). A solve's relative residual
# on the pressed 92/2 membrane's Hessian is 2e-5 for the predictor's right-hand side and 2e-3 for
# a random one (a scratch check, issue 4's notes of session 26): a Newton direction needs no more,
# as in double precision the 64/2 press's iterations reduce the gradient by the same ratios
SINGLE_PRECISION = True
# Bunch–Kaufman 1×1 and 2×2 pivots in the indefinite LDLᵀ (1×1 only measured no faster on the
# 92-rim membrane: results/mechanics_solvers.md as of 2026-11-21, in git)
PIVOT_2X2 = True
# factor the Hessian (and its shifts) by Cholesky first, LDLᵀ only where that fails
CHOLESKY_FIRST = True
# chord steps (off by default): after a full Newton step from a positive definite factor, taken
# whole, that left at most CHORD_AFTER of the gradient it started from, the next iteration first
# solves with that factor again — a solve and a gradient (~0.06 s on the 92/2 membrane) instead
# of a Hessian and its factorisation (~0.4 s). A press step's full steps leave 0.2 of their
# gradient even where no node enters the contact (the volumetric energy κ/2 (J − 1)² curving
# along the step, results/newton_anatomy.md), and one chord step then leaves ~0.03 of it. A chord
# step is kept where it lowers the energy and the gradient, another may follow while each leaves
# at most CHORD_GAIN; otherwise Newton takes a fresh Hessian. Why off: on the 92/2 press it saves
# (3.2 factorisations per step instead of 3.6, 1/1.056 of the wall time over 4 adjacent pairs:
# results/mechanics_pair_no_chord_steps.md, run at 1a4fec2 while it was the default), but the
# convergence study there (bench_mechanics.py; issue 4's notes of session 30) took more iterations on most other
# meshes, e.g. 64/2 4.6 per step (3.8 factorisations) against 3.2, and single steps of 15–39
# factorisations on 48/2, 128/2 and 160/2: the states it ends on (the factor not at the final
# point) make later steps' Hessians harder to regularise
CHORD_STEPS = False
CHORD_AFTER, CHORD_GAIN = 0.5, 0.25


def csr_rows(indptr: np.ndarray) -> np.ndarray:
    """The row (int64) of each stored entry of a CSR pattern."""
    return np.repeat(np.arange(len(indptr) - 1, dtype=np.int64), np.diff(indptr))


def find_keys(keys: np.ndarray, k: np.ndarray) -> np.ndarray | None:
    """Positions of the keys ``k`` in the sorted ``keys`` (row · n + column of a pattern's
    entries), or None when any is missing."""
    if len(k) == 0:
        return np.zeros(0, np.int64)
    pos = np.minimum(np.searchsorted(keys, k), len(keys) - 1)
    return pos if np.array_equal(keys[pos], k) else None


class NewtonSystem:
    """Newton's linear systems on a fixed sparsity pattern ``(indptr, indices)`` of the full
    3n × 3n Hessian (a superset of every term's entries: the P2 element pattern covers the
    pressure's face couplings and the contact's nodal blocks), restricted to the ``free``
    components. The fill-reducing ordering and symbolic analysis are done once per model, not
    once per iteration (:class:`PatternSolver`)."""

    def __init__(self, indptr: np.ndarray, indices: np.ndarray, free: np.ndarray):
        n = len(indptr) - 1
        rows = csr_rows(indptr)
        cols = np.asarray(indices, np.int64)
        self.n, self._indptr, self._cols = n, np.asarray(indptr), cols
        self.keys = rows * n + cols  # sorted: CSR rows in order, columns sorted within rows
        self.free = np.asarray(free, bool)
        keep = self.free[rows] & self.free[cols] & (cols >= rows)
        self.n_kept = int(keep.sum())
        self.slot = np.full(len(cols), -1, np.int64)
        self.slot[keep] = np.arange(self.n_kept)
        self._kept = np.flatnonzero(keep)  # kept entries in pattern order are the slots 0, 1, …
        new = np.cumsum(self.free) - 1
        r = new[rows[keep]]
        indptr_f = np.concatenate([[0], np.cumsum(np.bincount(r, minlength=int(self.free.sum())))])
        cols_f = new[cols[keep]]
        # no iterative refinement, and single precision: a Newton step needs no 1e-13 accuracy
        # (the residual test is on g, in double). Without refinement the solve is ~5× faster (6
        # against 32 ms on the 64-rim membrane), in single precision the factorisation ~1.6×
        self.full = PatternSolver(indptr_f, cols_f, spd=False, refinement=0, single=SINGLE_PRECISION, two_by_two=PIVOT_2X2)
        # Cholesky: positive definite matrices only (it fails on any other, which is the test),
        # for the projected Hessians and, with CHOLESKY_FIRST, the Hessians and their shifts
        self.projected = PatternSolver(indptr_f, cols_f, spd=True, refinement=0, single=SINGLE_PRECISION)
        # upper triangle, columns sorted: each row's diagonal is its first entry (None: a
        # pattern without every diagonal entry, which cannot be shifted)
        first = indptr_f[:-1]
        has_diag = np.all(np.diff(indptr_f) > 0) and np.array_equal(cols_f[first], np.arange(len(first)))
        self.diagonal = first if has_diag else None
        self.shift = SHIFT_START  # Levenberg–Marquardt σ, carried from one regularised step to the next
        # True while `tangent` holds the factor of a positive definite, unmodified Hessian (the
        # last equilibrium's tangent, for predictors: solve_tangent)
        self.tangent_ready = False
        self.tangent_u: np.ndarray | None = None  # the displacement that factor was taken at
        # what else the caller's Hessian depended on when it is factored (set by the caller before
        # a solve: the membrane's target centre and saline pressure), recorded with the tangent so
        # that a checkpoint can factor the same matrix again
        self.context: np.ndarray | None = None
        self.tangent_context: np.ndarray | None = None
        self.tangent: PatternSolver = self.full  # the solver holding it
        self._placements: dict[int, tuple[np.ndarray, ...]] = {}  # see _placement

    def pattern_slots(self, indptr: np.ndarray, indices: np.ndarray) -> np.ndarray:
        """The slot in :meth:`data`'s values of each stored entry of a matrix with the CSR
        pattern ``(indptr, indices)``: −1 for entries on fixed components or below the diagonal."""
        if np.array_equal(indptr, self._indptr) and np.array_equal(indices, self._cols):
            return self.slot.copy()
        pos = find_keys(self.keys, csr_rows(indptr) * self.n + np.asarray(indices, np.int64))
        if pos is None:
            raise RuntimeError("a Hessian term has entries outside the system's sparsity pattern")
        return self.slot[pos]

    def data(self, matrices: list) -> np.ndarray:
        """The free upper-triangle values of Σ matrices, in the pattern's order (a
        :class:`SystemValues` of this system counts as its values)."""
        out = None  # the first full-length term's values start the sum (no zeros to add to)
        for i, H in enumerate(matrices):
            if isinstance(H, SystemValues):
                if H.system is not self:
                    raise ValueError("matrices: values of another Newton system")
                out = H.values.copy() if out is None else np.add(out, H.values, out=out)
                continue
            if H is None or H.nnz == 0:
                continue
            H = sp.csr_matrix(H)
            if H.nnz == len(self._cols) and np.array_equal(H.indptr, self._indptr) and np.array_equal(H.indices, self._cols):
                kept = H.data[self._kept]  # assembled on the pattern itself (the elastic term)
                out = kept if out is None else np.add(out, kept, out=out)
                continue
            if not H.has_canonical_format:  # duplicate entries would share a slot below
                H = H.copy()
                H.sum_duplicates()
            entries, where = self._placement(i, H)
            if out is None:
                out = np.zeros(self.n_kept)
            # distinct entries of a canonical matrix have distinct slots: a scatter-add in place,
            # instead of a full-length bincount added after (the pressure's and contact's terms)
            out[where] += H.data[entries]
        return np.zeros(self.n_kept) if out is None else out

    def _placement(self, i: int, H: sp.csr_matrix) -> tuple[np.ndarray, np.ndarray]:
        """(entries of H.data kept, their slots) for the ``i``-th matrix, cached while its
        pattern stays (a term's pattern rarely changes between Newton iterations: the
        pressure's never, the contact's with its active set), as the search costs ~10 ms."""
        hit = self._placements.get(i)
        if hit is not None and np.array_equal(hit[0], H.indptr) and np.array_equal(hit[1], H.indices):
            return hit[2], hit[3]
        slot = self.pattern_slots(H.indptr, H.indices)
        entries = np.flatnonzero(slot >= 0)
        self._placements[i] = (H.indptr.copy(), H.indices.copy(), entries, slot[entries])
        return entries, slot[entries]

    def factor_tangent(self, terms: list, u: np.ndarray) -> None:
        """Factor the full Hessian of ``terms`` at ``u`` as the last Newton iteration there
        would have (restoring a checkpoint bit for bit)."""
        _, _, Hs, ok = _total(terms, u, True, self)
        if not ok:
            raise ValueError("factor_tangent: the displacement inverts elements")
        self.factor_hessian(self.data(Hs), u)

    def factor_hessian(self, data: np.ndarray, u: np.ndarray) -> bool:
        """Factor the free Hessian with values ``data`` taken at ``u``; whether it is positive
        definite (then it is the tangent ``solve_tangent`` uses). Cholesky first where
        CHOLESKY_FIRST: cheaper than LDLᵀ (0.24 against 0.37 s on the 92/2 membrane), and after
        a press's first step every full Newton step's Hessian was positive definite (traced
        there, 0.5 mm steps to 3 mm); where it fails, LDLᵀ and its inertia."""
        self.tangent_ready, self.tangent_u = False, u
        self.tangent_context = None if self.context is None else self.context.copy()
        # SuperLU's one factorisation is both tests (its pivots are the LDLᵀ's): no Cholesky first
        if CHOLESKY_FIRST and self.projected.backend == "pardiso" and self.projected.try_factor(data):
            self.tangent, self.tangent_ready = self.projected, True
            return True
        self.full.factor(data)
        self.tangent, self.tangent_ready = self.full, self.full.negative_eigenvalues == 0
        return self.tangent_ready

    def solve(self, b: np.ndarray) -> np.ndarray:
        """Solve with the last factor :meth:`factor_hessian` took."""
        return self.tangent.solve(b)

    def solve_tangent(self, b: np.ndarray) -> np.ndarray:
        """Solve with the held tangent (``tangent_ready`` must be True)."""
        if not self.tangent_ready:
            raise RuntimeError("no positive definite tangent factor held")
        return self.tangent.solve(b)

    def free_factors(self) -> None:
        self.full.free()
        self.projected.free()


# σ of H + σ·diag|H|: the first try (and the floor it decays back to), and the tries (×10 each)
SHIFT_START, SHIFT_TRIES = 1e-3, 8


def _summed(Hs: list) -> sp.csr_matrix:
    return sp.csr_matrix(sum(Hs[1:], Hs[0]))


def _descent(d: np.ndarray, g_free: np.ndarray) -> bool:
    return bool(np.all(np.isfinite(d)) and g_free @ d < 0)


def _full_step(u, Hs, free, g, system, data=None) -> tuple[np.ndarray | None, bool]:
    """The Newton step with the full Hessian (None when it is not a descent direction), and
    whether the free Hessian is known to be positive definite (Cholesky succeeded, or the LDLᵀ inertia).
    ``data``: the system's values of Σ Hs when already gathered."""
    try:
        if system is not None:
            spd = system.factor_hessian(system.data(Hs) if data is None else data, u)
            d = system.solve(-g[free])
        else:
            with factorize(_summed(Hs)[free][:, free], large_backend(), spd=False) as solve:
                d = solve(-g[free])
            spd = False
    except Exception:  # singular or the factorisation broke down
        return None, False
    ok = _descent(d, g[free])
    return (d if ok else None), bool(ok and spd)


def _regularised_step(data: np.ndarray, free, g, system: NewtonSystem) -> np.ndarray | None:
    """The step of H + σ·diag|H| (Levenberg–Marquardt), σ raised tenfold from ``system.shift``
    until the LDLᵀ inertia shows it positive definite; the next one starts a decade lower, but
    not below ``SHIFT_START`` (below it the pressed membrane nearly always needed raising again:
    a wasted factorisation per load step; a σ kept where one hard step put it damps the later
    ones into dozens of iterations). None when no σ tried does.

    Why not the per-element PSD projection: the stressed, pressurised membrane has small
    negative eigenvalues in ~98 % of its element Hessians (down to ~1e-3 of the largest), so
    the projection needs a batched 30 × 30 eigendecomposition of every element each time —
    three factorisations' worth — while one or two shifted factorisations do (measured on the
    64-rim membrane: 0.47 s against 0.1–0.2 s per step, same Newton iteration counts)."""
    if system.diagonal is None:
        return None
    diag = system.diagonal
    scale = np.abs(data[diag])
    sigma = system.shift
    for _ in range(SHIFT_TRIES):
        shifted = data.copy()
        shifted[diag] += sigma * scale
        if CHOLESKY_FIRST:
            solver = system.projected
            definite = solver.try_factor(shifted)
        else:
            solver = system.full
            solver.factor(shifted)
            if solver.negative_eigenvalues is None:
                return None  # no inertia to test the shift with (SuperLU left the diagonal)
            definite = solver.negative_eigenvalues == 0
        system.tangent_ready = False
        if definite:
            system.shift = max(sigma / 10, SHIFT_START)
            d = solver.solve(-g[free])
            return d if _descent(d, g[free]) else None
        sigma *= 10
    return None


def _projected_step(terms, u, free, g, system) -> np.ndarray:
    """The Newton step with every term's Hessian projected to PSD (always a descent step)."""
    Hs = [t.projected_hessian(u) if hasattr(t, "projected_hessian") else t.evaluate(u, True)[2] for t in terms]
    if system is not None:
        system.projected.factor(system.data(Hs))
        system.tangent_ready = False
        return -system.projected.solve(g[free])
    with factorize(_summed(Hs)[free][:, free], large_backend()) as solve:
        return -solve(g[free])


def _total(terms, u, hessian, system: NewtonSystem | None = None):
    """(energy, gradient, [each term's Hessian] or None, admissible); with a ``system``, the
    Hessians of terms that can give them so as that system's values."""
    E, g, Hs, ok = 0.0, None, [], True
    for t in terms:
        into = hessian and system is not None and hasattr(t, "evaluate_into")
        e, gi, Hi, oki = t.evaluate_into(u, system) if into else t.evaluate(u, hessian)
        ok &= oki
        E += e
        g = gi if g is None else g + gi
        Hs.append(Hi)
    return E, g, (Hs if hessian else None), ok


ROUNDOFF_DECREMENT = 1e-11  # a Newton decrement below this × |E| is at the energy's round-off


def _line_search(terms, u, E, g, d, it):
    """Armijo backtracking along d; (u_new, E_new, g_new, α) or None when at round-off already."""
    slope = float(g @ d)
    if -slope <= ROUNDOFF_DECREMENT * abs(E):
        # the step's predicted decrease is below what the energy's round-off resolves (a sum of
        # element energies that cancel), so Armijo's test would judge noise: the gradient
        # judges instead. The whole step is taken where it lowers the gradient (the quadratic
        # model is exact this close); where it does not, the gradient is at its round-off too
        u_try = u + d.reshape(u.shape)
        E_try, g_try, _, ok_try = _total(terms, u_try, False)
        moved = d != 0
        if ok_try and np.linalg.norm(g_try[moved]) < np.linalg.norm(g[moved]):
            return u_try, E_try, g_try, 1.0
        return None
    alpha = 1.0
    while True:
        u_try = u + alpha * d.reshape(u.shape)
        E_try, g_try, _, ok_try = _total(terms, u_try, False)
        if ok_try and E_try <= E + 1e-4 * alpha * slope:
            return u_try, E_try, g_try, alpha
        if ok_try and abs(E_try - E) <= 1e-14 * max(abs(E), 1e-300) and alpha < 1e-3:
            return None  # at round-off: no further decrease is measurable
        alpha *= 0.5
        if alpha < 1e-10:
            raise NewtonError(f"iteration {it}: line search failed (inverted elements or no decrease)")


def _chord_step(terms, u, E, g, free, system: NewtonSystem):
    """The step with the held factor and the current gradient, taken whole: (u, E, g) where it
    keeps every element, lowers the energy (Armijo; at the energy's round-off, the gradient
    judges) and lowers the gradient; else None (the caller takes a fresh Hessian)."""
    d = np.zeros(u.size)
    d[free] = system.solve_tangent(-g[free])
    if not _descent(d[free], g[free]):
        return None
    slope = float(g @ d)
    u_try = u + d.reshape(u.shape)
    E_try, g_try, _, ok = _total(terms, u_try, False)
    lower = E_try <= E + 1e-4 * slope or -slope <= ROUNDOFF_DECREMENT * abs(E)
    if ok and lower and np.linalg.norm(g_try[free]) < np.linalg.norm(g[free]):
        return u_try, E_try, g_try
    return None


def minimize_energy(
    terms: list[EnergyTerm],
    u0: np.ndarray,
    fixed: np.ndarray,
    rtol: float = 1e-9,
    atol: float = 0.0,
    max_iter: int = 50,
    system: NewtonSystem | None = None,
    regularise_first: bool = False,
    min_iter: int = 0,
) -> NewtonResult:
    """Minimise Σ terms over u (n, 3) with u[fixed] held at u0[fixed] (fixed: (n, 3) bool).

    Converged when ‖g_free‖ ≤ max(atol, rtol·‖g_free at the start‖) or the energy stops
    decreasing at round-off level. Raises :class:`NewtonError` otherwise. A ``system`` built
    for these fixed components keeps the linear solver's analysis between calls.

    ``regularise_first``: take the first step with the positive definite modification of the
    Hessian, without trying the full one. For a start from a load-step predictor: there the
    Hessian was indefinite in every 0.5 mm press step traced (not from deep penetrations: the
    predicted ones stay below the contact's curvature cap), so the full step is rejected, a
    wasted factorisation, or accepted because it lowers the energy and followed by more
    iterations (measured on the 40- and 48-rim, 3-layer membranes, 0.5 mm steps to 3 mm: 3–5
    factorisations per step instead of 4–9).

    ``min_iter``: take at least this many steps even where ‖g_free‖ is already within the
    tolerance (not where it is exactly 0): a load change below the tolerance still moves u
    (a model without a predictor for it; see SoftTargetModel)."""
    u = np.array(u0, dtype=float)
    free = ~np.asarray(fixed, bool).ravel()
    if system is not None and not np.array_equal(system.free, free):
        raise ValueError("system: built for other fixed components")
    # the Hessian is evaluated only once the gradient shows another iteration is needed: at
    # the converged state it would be wasted (~45 ms, a twentieth of a press step). Not so
    # with a term that re-linearises when its Hessian is taken (lagged contact points): its
    # gradient after that is the one convergence is judged on
    eager = any(getattr(t, "RELINEARISES", False) for t in terms)
    E, g, Hs, ok = _total(terms, u, eager, system)
    if not ok:
        raise NewtonError("the initial state has inverted elements")
    r0 = np.linalg.norm(g[free])
    tol = max(atol, rtol * r0)
    history = [r0]
    chords = 0
    # the held factor may serve the next iteration (see CHORD_STEPS). Not with a re-linearising
    # term: its gradient moves with each Hessian evaluation
    chord = False
    for it in range(max_iter):
        r = np.linalg.norm(g[free])
        if r == 0.0 or (r <= tol and it >= min_iter):
            return NewtonResult(u, E, g, it, r, history, chords)
        if chord:
            step = _chord_step(terms, u, E, g, free, system)
            if step is not None:
                u, E, g = step
                Hs = None
                history.append(float(np.linalg.norm(g[free])))
                chords += 1
                chord = history[-1] <= CHORD_GAIN * r
                continue
            chord = False
        if Hs is None:
            _, _, Hs, _ = _total(terms, u, True, system)
        # the full-Hessian step converges quadratically near equilibrium. Where the free Hessian
        # is positive definite (Cholesky, or LDLᵀ inertia) it is a descent direction and is line-searched;
        # otherwise it is taken only when the whole step lowers the energy, and a positive
        # definite modification's step is line-searched instead (active-set changes in contact,
        # large increments)
        d = np.zeros(u.size)
        data = system.data(Hs) if system is not None else None
        skip_full = regularise_first and it == 0 and system is not None
        full, spd = (None, False) if skip_full else _full_step(u, Hs, free, g, system, data)
        u_new, whole = None, False  # whole: the full step from a positive definite factor, α = 1
        if full is not None:
            d[free] = full
            if spd:
                u_new = _line_search(terms, u, E, g, d, it)
                if u_new is None:
                    return NewtonResult(u, E, g, it, r, history, chords)
                whole = u_new[3] == 1.0
            else:
                u_try = u + d.reshape(u.shape)
                E_try, g_try, _, ok_try = _total(terms, u_try, False)
                if ok_try and E_try <= E + 1e-4 * float(g @ d):
                    u_new = u_try, E_try, g_try, 1.0
        if u_new is None:
            reg = _regularised_step(data, free, g, system) if system is not None else None
            d[free] = reg if reg is not None else _projected_step(terms, u, free, g, system)
            if float(g @ d) >= 0:
                raise NewtonError(f"iteration {it}: the projected Newton direction is not a descent direction")
            u_new = _line_search(terms, u, E, g, d, it)
            if u_new is None:
                return NewtonResult(u, E, g, it, r, history, chords)
        u, E, g, _ = u_new
        Hs = None
        if eager:
            E, g, Hs, _ = _total(terms, u, True, system)
        history.append(float(np.linalg.norm(g[free])))
        chord = CHORD_STEPS and whole and not eager and system is not None and history[-1] <= CHORD_AFTER * r
    if history[-1] <= tol:  # converged by the last iteration allowed
        return NewtonResult(u, E, g, max_iter, history[-1], history, chords)
    err = NewtonError(f"no convergence in {max_iter} iterations: residual {np.linalg.norm(g[free]):.3e} > {tol:.3e}")
    err.history = history
    raise err


def step_to(
    terms: list[EnergyTerm],
    u_eq: np.ndarray,
    fixed: np.ndarray,
    target: np.ndarray,
    max_halvings: int = 6,
    **newton_kw,
) -> NewtonResult:
    """Move from the equilibrium ``u_eq`` to the equilibrium with u[fixed] = target[fixed].

    The Dirichlet increment is spread into the free components by a linear predictor (the
    tangent at ``u_eq``), then Newton corrects. When Newton fails, the increment is halved
    and taken in two sub-steps, up to ``max_halvings`` times, before the error is raised."""
    fixed = np.asarray(fixed, bool)
    try:
        return minimize_energy(terms, _predict(terms, u_eq, fixed, target), fixed, **newton_kw)
    except NewtonError:
        if max_halvings <= 0:
            raise
    mid = u_eq.copy()
    mid[fixed] = 0.5 * (u_eq[fixed] + target[fixed])
    half = step_to(terms, u_eq, fixed, mid, max_halvings - 1, **newton_kw)
    return step_to(terms, half.u, fixed, target, max_halvings - 1, **newton_kw)


def _predict(terms, u_eq, fixed, target) -> np.ndarray:
    """u_eq plus the linear response to the Dirichlet increment, scaled back if it inverts."""
    free = ~fixed.ravel()
    du = np.zeros(u_eq.size)
    du[~free] = (target - u_eq).ravel()[~free]
    if not du.any():
        return u_eq.copy()
    _, _, Hs, _ = _total(terms, u_eq, True)
    H = _summed(Hs)
    try:
        with factorize(H[free][:, free], large_backend(), spd=False) as solve:
            du[free] = solve(-(H[free][:, ~free] @ du[~free]))
    except Exception:
        du[free] = 0.0
    for scale in (1.0, 0.5, 0.25, 0.0):
        trial = u_eq + (du * np.where(free, scale, 1.0)).reshape(u_eq.shape)
        if _total(terms, trial, False)[3]:
            return trial
    return trial
