"""Which sparse direct solver "auto" should pick: SuperLU, PARDISO (and CHOLMOD where it is
installed) on the same CEM matrices of the paper's chamber, factorisation + the 16 lead-field
solves, the symbolic analysis included on every side, one thread, the median of 5 runs.

    python benchmarks/bench_solver_choice.py     # ~2 min here; writes results/solver_choice.{md,json}

PARDISO's one-off cost of loading MKL in a new process is measured apart (the first
factorisation of a 2 × 2 matrix in a fresh interpreter, against the same with SuperLU) and left
out of the per-matrix times on both sides; PARDISO with its analysis kept (what a morphed frame
pays: jointsim.eit.forward's shared solver) is shown beside them.
"""

from __future__ import annotations

import os

for _v in ("MKL_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS"):  # as a dataset worker runs
    os.environ[_v] = "1"

import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from dataclasses import replace  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from _machine import machine, run_and_write  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
SYSTEMS = (("test", 1), ("dataset", 1), ("test", 2), ("dataset_p2", 2), ("dataset", 2), ("paper", 1))
REPEATS = 5
_FIRST_CALL = """
import time, numpy as np, scipy.sparse as sp
t = time.perf_counter()
from jointsim.linalg import factorize
with factorize(sp.csr_matrix(np.array([[2.0, -1.0], [-1.0, 2.0]])), "{backend}") as f:
    f(np.ones(2))
print(time.perf_counter() - t)
"""


def first_call_s(backend: str) -> float:
    """Seconds from importing jointsim.linalg to a first solve with ``backend``, in a new process."""
    out = subprocess.run([sys.executable, "-c", _FIRST_CALL.format(backend=backend)], capture_output=True, text=True,
                         check=True, cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)})
    return float(out.stdout.split()[-1])


def timed(fn, repeats: int = REPEATS) -> float:
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return float(np.median(times))


def run() -> dict:
    from jointsim.eit.forward import ForwardModel
    from jointsim.linalg import PatternSolver, available_backends, default_backend, factorize
    from jointsim.mesh.chamber import chamber_mesh
    from jointsim.scene import SCENES_DIR, load_scene

    os.environ["JOINTSIM_CACHE"] = tempfile.mkdtemp(prefix="jointsim-bench-solvers-")
    backends = [b for b in ("superlu", "pardiso", "cholmod") if b in available_backends()]
    first = {b: first_call_s(b) for b in backends}
    base = load_scene(SCENES_DIR / "paper_sensor.toml")
    rows = []
    for preset, order in SYSTEMS:
        s = base.with_mesh_preset(preset)
        s = replace(s, mesh=replace(s.mesh, element_order=order))
        model = ForwardModel.from_chamber(chamber_mesh(s), s)
        A = model.assembler.assemble(np.full(model.mesh.n_tets, s.saline.conductivity), model.z).tocsc()
        n, L = model.assembler.n_dofs, model.n_driven
        rhs = np.zeros((A.shape[0], L))
        rhs[n + np.arange(L), np.arange(L)] = 1.0

        def solve_with(backend: str) -> None:
            with factorize(A, backend) as f:
                f(rhs)

        row = {"preset": preset, "order": order, "unknowns": A.shape[0], "nnz": A.nnz,
               "auto": default_backend(A.shape[0], A.nnz)}
        for b in backends:
            row[f"{b}_s"] = timed(lambda: solve_with(b))
        indptr, indices = model.assembler.pattern
        rows_of = np.repeat(np.arange(A.shape[0]), np.diff(indptr))
        upper = indices >= rows_of
        Acsr = A.tocsr()
        Acsr.sort_indices()
        up_indptr = np.concatenate([[0], np.cumsum(np.bincount(rows_of[upper], minlength=A.shape[0]))])
        if "pardiso" in backends:
            kept = PatternSolver(up_indptr, indices[upper], spd=True, backend="pardiso", refinement=0)
            kept.factor(Acsr.data[upper])  # the analysis, once

            def numeric() -> None:
                kept.factor(Acsr.data[upper])
                kept.solve(rhs)

            row["pardiso_kept_analysis_s"] = timed(numeric)
            kept.free()
        rows.append(row)
        print(row, flush=True)
    return {"machine": machine(), "first_call_s": first, "rows": rows}


def markdown(r: dict) -> str:
    backends = [b for b in ("superlu", "pardiso", "cholmod") if f"{b}_s" in r["rows"][0]]
    lines = ["# Sparse direct solvers on the CEM matrices", "",
             "Command: `python benchmarks/bench_solver_choice.py`  ", f"Machine: {r['machine']}; one thread.", "",
             __doc__.split("\n\n", 2)[2].strip().replace("\n", " "), "",
             "First solve in a new process (import of jointsim.linalg, loading the library, a 2 × 2 solve): "
             + ", ".join(f"{b} {s:.2f} s" for b, s in r["first_call_s"].items()) + ".", "",
             "| chamber preset | order | unknowns | stored entries | " + " | ".join(f"{b} s" for b in backends)
             + " | PARDISO, analysis kept, s | fastest | ratio slowest / fastest | auto picks |",
             "|---|---:|---:|---:|" + "---:|" * len(backends) + "---:|---|---:|---|"]
    for x in r["rows"]:
        t = {b: x[f"{b}_s"] for b in backends}
        best = min(t, key=t.get)
        lines.append(f"| {x['preset']} | P{x['order']} | {x['unknowns']:,} | {x['nnz']:,} | "
                     + " | ".join(f"{t[b]:.3f}" for b in backends)
                     + f" | {x.get('pardiso_kept_analysis_s', float('nan')):.3f} | {best} | {max(t.values()) / t[best]:.1f} | {x['auto']} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    run_and_write(__doc__, ROOT / "results" / "solver_choice", run, markdown)


if __name__ == "__main__":
    main()
