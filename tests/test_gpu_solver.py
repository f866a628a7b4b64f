"""The "cudss" backend (sparse factorisations on an NVIDIA GPU) and the process-wide solver choice
(JOINTSIM_SOLVER, the commands' --solver).

Without a GPU, the backend's glue (jointsim._cudss and linalg's cudss branches: the upper triangle
handed over with its view, the analysis done once per pattern, the inertia read for Newton, the
definiteness test, right-hand sides of any width) is run against a stand-in for nvmath-python's
DirectSolver that does the same algebra densely; on a machine with cuDSS, the real one is
checked against SuperLU (benchmarks/bench_gpu_solvers.py measures it at the dataset presets)."""

from __future__ import annotations

import subprocess
import sys
import types
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp

from jointsim import _cudss, linalg

ROOT = Path(__file__).resolve().parents[1]


def _symmetric(n: int, shift: float, seed: int = 0) -> sp.csr_matrix:
    """A sparse symmetric matrix, definite or not by ``shift`` on its diagonal."""
    A = sp.random(n, n, density=0.08, random_state=seed)
    return ((A + A.T) + shift * sp.eye(n)).tocsr()


def _upper(A):
    U = sp.triu(A, format="csr")
    U.sort_indices()
    return U


class _DenseDirectSolver:
    """nvmath.sparse.advanced.DirectSolver's calls as jointsim makes them, done densely: the
    matrix is read as its UPPER view (the lower part ignored), SPD systems fail (info > 0)
    where they are not positive definite, SYMMETRIC ones report their inertia."""

    plans = 0

    def __init__(self, a, b, options):
        self.a, self.b, self.options = a, b, options

    def reset_operands(self, a=None, b=None):
        self.a = self.a if a is None else a
        self.b = self.b if b is None else b

    def plan(self):
        type(self).plans += 1

    def factorize(self):
        assert self.options.sparse_system_view == "UPPER"
        U = sp.triu(self.a)
        self._A = (U + sp.triu(U, 1).T).toarray()
        w = np.linalg.eigvalsh(self._A)
        info = int(self.options.sparse_system_type == "SPD" and w.min() <= 0)
        return types.SimpleNamespace(info=info, inertia=np.array([(w > 0).sum(), (w < 0).sum()]))

    def solve(self):
        return np.linalg.solve(self._A, self.b)

    def free(self):
        pass


@pytest.fixture
def stand_in(monkeypatch):
    """The cudss backend on the dense stand-in, as if a GPU and nvmath-python were here."""
    advanced = types.SimpleNamespace(
        DirectSolver=_DenseDirectSolver,
        DirectSolverOptions=lambda **kw: types.SimpleNamespace(**kw),
        DirectSolverMatrixType=types.SimpleNamespace(SPD="SPD", SYMMETRIC="SYMMETRIC"),
        DirectSolverMatrixViewType=types.SimpleNamespace(UPPER="UPPER"),
    )
    nvmath = types.ModuleType("nvmath")
    nvmath.sparse = types.ModuleType("nvmath.sparse")
    nvmath.sparse.advanced = advanced
    monkeypatch.setitem(sys.modules, "nvmath", nvmath)
    monkeypatch.setitem(sys.modules, "nvmath.sparse", nvmath.sparse)
    monkeypatch.setitem(sys.modules, "nvmath.sparse.advanced", advanced)
    monkeypatch.setattr(_cudss, "unavailable", lambda: None)
    _DenseDirectSolver.plans = 0
    return _DenseDirectSolver


def test_pattern_solver_on_cudss_solves_and_counts_negative_pivots_as_superlu(stand_in):
    """Newton's use: one pattern, factored three times with the analysis done once; the LDLᵀ's
    negative pivots are the matrix's negative eigenvalues (SuperLU's diagonal pivots, the same
    inertia); solutions agree with SuperLU's to round-off."""
    n = 60
    A = _symmetric(n, 0.5)
    U = _upper(A)
    gpu = linalg.PatternSolver(U.indptr, U.indices, spd=False, backend="cudss")
    cpu = linalg.PatternSolver(U.indptr, U.indices, spd=False, backend="superlu")
    b = np.random.default_rng(1).standard_normal(n)
    for scale in (1.0, 2.0, -1.0):
        gpu.factor(scale * U.data)
        cpu.factor(scale * U.data)
        assert gpu.negative_eigenvalues == cpu.negative_eigenvalues == int((np.linalg.eigvalsh(scale * A.toarray()) < 0).sum())
        np.testing.assert_allclose(gpu.solve(b), cpu.solve(b), rtol=0, atol=1e-10 * np.abs(cpu.solve(b)).max())
    assert stand_in.plans == 1


def test_definiteness_test_on_cudss_refuses_an_indefinite_matrix_and_solves_with_a_definite_one(stand_in):
    """Newton's regularised step: try_factor is False on an indefinite matrix (no factor held),
    True on a positive definite one, whose factor then solves."""
    n = 50
    definite = _upper(_symmetric(n, 10.0))
    indefinite = definite.copy()
    indefinite.data[definite.indices == np.repeat(np.arange(n), np.diff(definite.indptr))] -= 12.0
    assert np.linalg.eigvalsh((indefinite + sp.triu(indefinite, 1).T).toarray()).min() < 0
    solver = linalg.PatternSolver(definite.indptr, definite.indices, spd=True, backend="cudss")
    assert not solver.try_factor(indefinite.data)
    with pytest.raises(RuntimeError, match="factor"):
        solver.solve(np.ones(n))
    assert solver.try_factor(definite.data)
    A = (definite + sp.triu(definite, 1).T).toarray()
    np.testing.assert_allclose(A @ solver.solve(np.ones(n)), np.ones(n), atol=1e-12)
    with pytest.raises(RuntimeError, match="not positive definite"):
        solver.factor(indefinite.data)


def test_factorize_on_cudss_takes_right_hand_sides_of_any_width(stand_in):
    """The CEM's 16 lead fields at once (a solver made for k columns), a vector, and another width."""
    n = 40
    A = _symmetric(n, 8.0)
    B = np.random.default_rng(2).standard_normal((n, 5))
    f = linalg.factorize(A, "cudss")
    for b in (B, B[:, 0], B[:, :3]):
        np.testing.assert_allclose(A @ f(b), b, atol=1e-12)
    U = _upper(A)
    wide = linalg.PatternSolver(U.indptr, U.indices, spd=True, backend="cudss", known_definite=True, columns=5)
    wide.factor(U.data)
    for b in (B, B[:, 1], B[:, :2]):
        np.testing.assert_allclose(A @ wide.solve(b), b, atol=1e-12)


def test_the_process_solver_is_what_auto_resolves_to(monkeypatch):
    """JOINTSIM_SOLVER sets "auto" everywhere: the size rule, the large systems' backend, Newton's
    pattern solvers; unset, the size rule decides; a bad value is refused naming the variable."""
    monkeypatch.setenv(linalg.SOLVER_VARIABLE, "superlu")
    assert linalg.default_backend(10**6, 10**8) == "superlu"
    assert linalg.large_backend() == "superlu"
    U = _upper(_symmetric(6000, 10.0))
    assert linalg.PatternSolver(U.indptr, U.indices, spd=False).backend == "superlu"
    monkeypatch.delenv(linalg.SOLVER_VARIABLE)
    assert linalg.default_backend(100, 1000) == "superlu"
    monkeypatch.setenv(linalg.SOLVER_VARIABLE, "magma")
    with pytest.raises(ValueError, match="JOINTSIM_SOLVER = 'magma': not a solver jointsim knows"):
        linalg.preferred_backend()


def test_a_chosen_solver_is_part_of_a_stores_identity(monkeypatch, paper_scene):
    """Another solver gives other bits (round-off): a store started with one resumes only with it.
    Left to "auto", the identity is what it was before solvers could be chosen."""
    from jointsim.dataset.generate import dataset_params
    from jointsim.palpation.pipeline import program_params

    monkeypatch.delenv(linalg.SOLVER_VARIABLE, raising=False)
    assert "solver" not in dataset_params(paper_scene, 6, "x") and "solver" not in program_params(paper_scene)
    monkeypatch.setenv(linalg.SOLVER_VARIABLE, "superlu")
    assert dataset_params(paper_scene, 6, "x")["solver"] == program_params(paper_scene)["solver"] == "superlu"


@pytest.mark.skipif(_cudss.unavailable() is None, reason="this machine has cuDSS: the refusal is not shown")
def test_cudss_without_a_gpu_is_refused_in_one_line_naming_the_flag(tmp_path):
    p = subprocess.run([sys.executable, "-m", "jointsim", "dataset", "--mesh", "test", "--n", "2", "--solver", "cudss",
                        "--out", str(tmp_path / "d.h5")], capture_output=True, text=True, cwd=ROOT)
    assert p.returncode == 2, p.stderr
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("jointsim dataset: error: --solver = 'cudss': "), p.stderr
    assert "available here: auto, superlu" in lines[0]


@pytest.mark.skipif(_cudss.unavailable() is not None, reason="needs an NVIDIA GPU with nvmath-python and cuDSS")
def test_cudss_agrees_with_superlu_on_a_gpu():
    """The real cuDSS: solutions to 1e-10 of SuperLU's, the same inertia."""
    for shift in (10.0, 0.3):
        A = _symmetric(3000, shift, seed=3)
        U = _upper(A)
        gpu = linalg.PatternSolver(U.indptr, U.indices, spd=False, backend="cudss")
        cpu = linalg.PatternSolver(U.indptr, U.indices, spd=False, backend="superlu")
        gpu.factor(U.data)
        cpu.factor(U.data)
        b = np.random.default_rng(4).standard_normal(3000)
        x, y = gpu.solve(b), cpu.solve(b)
        assert np.linalg.norm(x - y) <= 1e-10 * np.linalg.norm(y)
        assert gpu.negative_eigenvalues == cpu.negative_eigenvalues
