"""The sparse factorisations of the EIT forward and of Newton on the GPU (cuDSS through
nvmath-python, jointsim.linalg's "cudss" backend) against the CPU's, on the same matrices: the
CEM matrices of the paper's chamber at the dataset presets (P1 and P2), and the Hessians of the
dataset preset's membrane along a press (two of its Newton iterations', one pattern), plus the
last made indefinite. For each: the relative difference of the solutions from SuperLU's in double precision,
the inertia beside SuperLU's, and the seconds of a first factorisation (analysis included) and of
a refactorisation with the analysis kept (factor + solve, median), GPU against the CPU solvers.

    python benchmarks/bench_gpu_solvers.py --export DIR        # here: the matrices, ~10 MB
    python benchmarks/bench_gpu_solvers.py --check DIR --out F  # on a GPU machine: F.json, F.md

The check needs only numpy, scipy and nvmath-python (with cuDSS): jointsim.linalg and nothing
above it, so that it runs where the rest of jointsim's dependencies are not installed.
"""

from __future__ import annotations

import os

for _v in ("MKL_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS"):  # as a dataset worker runs
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from _machine import median_seconds  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
REPEATS = 5


def _upper(A):
    import scipy.sparse as sp

    U = sp.triu(sp.csr_matrix(A), format="csr")
    U.sort_indices()
    return U


def export(folder: Path) -> None:
    """The CEM matrices (two conductivities each) and a press's membrane Hessians, as upper
    triangles sharing one pattern per system, with their right-hand sides."""

    from jointsim import linalg
    from jointsim.eit.forward import ForwardModel
    from jointsim.mechanics.build import membrane_from_scene
    from jointsim.mesh.chamber import chamber_mesh
    from jointsim.scene import SCENES_DIR, load_scene

    folder.mkdir(parents=True, exist_ok=True)
    base = load_scene(SCENES_DIR / "paper_sensor.toml")
    rng = np.random.default_rng(0)
    for f in folder.glob("*.npz"):
        f.unlink()
    for preset in ("dataset", "dataset_p2"):
        s = base.with_mesh_preset(preset)
        model = ForwardModel.from_chamber(chamber_mesh(s), s)
        sig = s.saline.conductivity
        values = []
        for sigma in (np.full(model.mesh.n_tets, sig), sig * (1 + 0.1 * rng.standard_normal(model.mesh.n_tets))):
            U = _upper(model.assembler.assemble(sigma, model.z))
            values.append(U.data)
        n, L = model.assembler.n_dofs, model.n_driven
        rhs = np.zeros((U.shape[0], L))
        rhs[n + np.arange(L), np.arange(L)] = 1.0
        np.savez_compressed(folder / f"cem_{preset}.npz", indptr=U.indptr, indices=U.indices, values=np.array(values),
                            rhs=rhs, spd=True, known_definite=True, what=f"CEM matrix, chamber at the {preset} preset (P{s.mesh.element_order})")
        print(preset, U.shape, U.nnz, flush=True)

    # a press's Newton Hessians: every factorisation PatternSolver is asked for, recorded
    s = base.with_mesh_preset("dataset")
    seen: list[tuple] = []
    factor = linalg.PatternSolver.factor

    def recording(self, data):
        if self.n > 1000:
            seen.append((self.indptr.copy(), self.indices.copy(), np.asarray(data, float).copy()))
        return factor(self, data)

    linalg.PatternSolver.factor = recording
    try:
        model = membrane_from_scene(s, target_radius=7.5e-3)
        xy = np.array([3e-3, 0.0])
        model.press(np.array([*xy, model.first_contact_height(xy) - 1.5e-3]))
    finally:
        linalg.PatternSolver.factor = factor
    indptr, indices = seen[-1][0], seen[-1][1]
    same = [d for p, i, d in seen if np.array_equal(p, indptr) and np.array_equal(i, indices)]
    pick = [same[k] for k in np.unique(np.linspace(0, len(same) - 1, min(len(same), 2)).round().astype(int))]
    nfree = len(indptr) - 1
    b = rng.standard_normal(nfree)
    np.savez_compressed(folder / "hessian_dataset.npz", indptr=indptr, indices=indices, values=np.array(pick), rhs=b,
                        spd=False, known_definite=False, what="membrane Hessian along a press (dataset preset), LDLᵀ")
    print("hessians", nfree, len(indices), len(same), "of", len(seen), flush=True)


def _timed(fn) -> float:
    return median_seconds(fn, REPEATS)


def check(folder: Path) -> dict:
    import scipy.sparse as sp

    from jointsim.linalg import PatternSolver, available_backends

    have = available_backends()
    rows = []
    systems = []
    for f in sorted(folder.glob("*.npz")):
        z = dict(np.load(f))
        systems.append((f.stem, z))
        if f.stem.startswith("hessian"):  # made indefinite: minus 0.001 × its mean diagonal
            n = len(z["indptr"]) - 1
            rows_of = np.repeat(np.arange(n), np.diff(z["indptr"]))
            diag = np.flatnonzero(z["indices"] == rows_of)
            v = z["values"][-1].copy()
            v[diag] -= 0.001 * np.abs(v[diag]).mean()
            systems.append((f.stem + "_indefinite", {**z, "values": v[None], "what": "the last Hessian minus 0.001 × its mean diagonal"}))
    for name, z in systems:
        indptr, indices, values, rhs = z["indptr"], z["indices"], z["values"], z["rhs"]
        spd, known = bool(z["spd"]), bool(z["known_definite"])
        n = len(indptr) - 1
        full = [sp.csr_matrix((v, indices, indptr), shape=(n, n)) for v in values]
        full = [U + sp.triu(U, 1).T for U in full]
        cols = rhs.shape[1] if rhs.ndim == 2 else 1
        row = {"system": name, "what": str(z["what"]), "unknowns": n, "upper_entries": len(indices), "values_sets": len(values)}
        solvers = {b: PatternSolver(indptr, indices, spd=spd, backend=b, refinement=0, known_definite=known, columns=cols)
                   for b in ("superlu", "pardiso", "cudss") if b in have}
        x = {}
        for b, sol in solvers.items():
            t = time.perf_counter()
            sol.factor(values[0])
            x[b] = sol.solve(rhs)
            row[f"{b}_first_s"] = time.perf_counter() - t
            row[f"{b}_negative_pivots"] = sol.negative_eigenvalues
            k = [1 % len(values)]

            def again(sol=sol, k=k):
                sol.factor(values[k[0]])
                sol.solve(rhs)
                k[0] = (k[0] + 1) % len(values)

            row[f"{b}_refactor_solve_s"] = _timed(again)
            # every values set: the GPU's solution against SuperLU's, and the residual
            if b != "superlu":
                diffs, resid = [], []
                for v, A in zip(values, full):
                    sol.factor(v)
                    y = sol.solve(rhs)
                    solvers["superlu"].factor(v)
                    y0 = solvers["superlu"].solve(rhs)
                    diffs.append(float(np.linalg.norm(y - y0) / np.linalg.norm(y0)))
                    resid.append(float(np.linalg.norm(A @ y - rhs) / np.linalg.norm(rhs)))
                row[f"{b}_rel_diff_superlu"] = max(diffs)
                row[f"{b}_rel_residual"] = max(resid)
        row["superlu_rel_residual"] = max(float(np.linalg.norm(A @ solvers["superlu"].solve(rhs) - rhs) / np.linalg.norm(rhs))
                                          for A in full[-1:])
        if not spd and "cudss" in solvers:  # Newton's definiteness test on the GPU: LDLᵀ's inertia, and Cholesky's refusal
            test = PatternSolver(indptr, indices, spd=True, backend="cudss", refinement=0)
            row["cudss_try_factor"] = bool(test.try_factor(values[0]))
            test.free()
        for sol in solvers.values():
            sol.free()
        rows.append(row)
        print(json.dumps(row), flush=True)
    return {"backends": have, "rows": rows}


def markdown(r: dict, machine: str) -> str:
    lines = ["# Sparse factorisations on the GPU (cuDSS) against the CPU", "",
             "Command: `python benchmarks/bench_gpu_solvers.py --check DIR` on matrices written by `--export DIR`  ",
             f"Machine: {machine}; one CPU thread per solver (as a dataset worker).", "",
             " ".join(__doc__.split("\n\n")[0].split()), "",
             "| system | unknowns | upper entries | GPU vs SuperLU (rel. diff) | GPU residual | negative pivots GPU / SuperLU"
             " | first factor+solve s (SuperLU / GPU) | refactor+solve, analysis kept, s (SuperLU / PARDISO / GPU) | GPU speed-up on refactor |",
             "|---|---:|---:|---:|---:|---|---|---|---:|"]
    for x in r["rows"]:
        g = x.get("cudss_refactor_solve_s")
        best_cpu = min(v for k, v in x.items() if k.endswith("_refactor_solve_s") and not k.startswith("cudss"))
        lines.append(
            f"| {x['system']} | {x['unknowns']:,} | {x['upper_entries']:,} | {x.get('cudss_rel_diff_superlu', float('nan')):.1e} | "
            f"{x.get('cudss_rel_residual', float('nan')):.1e} | {x.get('cudss_negative_pivots')} / {x.get('superlu_negative_pivots')} | "
            f"{x['superlu_first_s']:.3f} / {x.get('cudss_first_s', float('nan')):.3f} | "
            f"{x['superlu_refactor_solve_s']:.4f} / {x.get('pardiso_refactor_solve_s', float('nan')):.4f} / {g if g is not None else float('nan'):.4f} | "
            f"{best_cpu / g if g else float('nan'):.2f} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--export", type=Path, metavar="DIR")
    ap.add_argument("--check", type=Path, metavar="DIR")
    ap.add_argument("--out", type=Path, help="with --check: write OUT.json and OUT.md")
    a = ap.parse_args()
    if a.export:
        export(a.export)
    if a.check:
        import platform

        r = check(a.check)
        machine = f"{platform.machine()} {platform.processor() or ''}, {os.cpu_count()} cores, Python {platform.python_version()}"
        try:
            import subprocess

            machine += "; " + subprocess.run(["nvidia-smi", "--query-gpu=name,driver_version", "--format=csv,noheader"],
                                             capture_output=True, text=True).stdout.strip()
        except OSError:
            pass
        r["machine"] = machine
        md = markdown(r, machine)
        print(md)
        if a.out:
            a.out.parent.mkdir(parents=True, exist_ok=True)
            a.out.with_suffix(".json").write_text(json.dumps(r, indent=1))
            a.out.with_suffix(".md").write_text(md)


if __name__ == "__main__":
    main()
