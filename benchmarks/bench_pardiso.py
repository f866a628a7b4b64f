"""PARDISO's two-level factorisation (iparm(24) = 1) against the classic one-level, on the two
systems the package factors most:

- the Newton Hessian of the pressed 92/2 membrane (the press of results/mechanics_benchmark.md,
  at 1 mm), as Newton factors it: single precision, the analysis once, Cholesky (PatternSolver
  spd) and Bunch–Kaufman LDLᵀ with its inertia;
- the CEM matrix of the paper's chamber at the "paper" mesh preset (the "dataset" one is solved
  by SuperLU), as the EIT forward factors it: Cholesky in double precision, then the 16
  lead-field solves, with a fresh analysis (one forward: ForwardModel) and with the analysis
  reused (the morphed chambers of a palpation: the forward's _SharedSolver).

The package takes the two-level factorisation for both (jointsim.linalg.PARDISO_TWO_LEVEL);
`python benchmarks/bench_mechanics.py --solvers` measures a whole press with either.

    python benchmarks/bench_pardiso.py [repeats]     # writes results/pardiso_two_level.{json,md}
    python benchmarks/bench_pardiso.py --report      # rewrites the .md from the .json

The settings alternate within each repeat (medians of the repeats). Checks beside the times:
both give the same inertia of an indefinite matrix (the Hessian shifted down), both Cholesky
factorisations break down on it, and the solutions agree to the precision factored in.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import machine, speed_reference, write_pair  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "results" / "pardiso_two_level"
MEMBRANE, DEPTHS_MM = (92, 2), (0.5, 1.0)
SETTINGS = {"one-level": False, "two-level": True}
SOLVES = 4  # Newton solves timed per factor (a median of each)


def hessian_case() -> tuple:
    """(NewtonSystem, values of the free Hessian, −gradient) of the pressed membrane."""
    from bench_mechanics import _membrane

    from jointsim.mechanics.newton import _total

    model, _ = _membrane(*MEMBRANE, 0.0, "pointwise")
    top = model.first_contact_height((0.0, 0.0))
    for d in DEPTHS_MM:
        model.press(np.array([0.0, 0.0, top - d * 1e-3]))
    system = model.system
    _, g, Hs, _ = _total(model.terms, model.u, True, system)
    return system, system.data(Hs), -g[system.free], model.mesh.n_nodes


def _pattern_timing(indptr, indices, data: np.ndarray, b: np.ndarray, solves: int, **kw):
    """(PatternSolver(indptr, indices, **kw) still holding its factor, numerical factorisation s,
    median solve s, solution): the analysis done first and left out, as a model's later
    factorisations reuse it."""
    from jointsim.linalg import PatternSolver

    s = PatternSolver(indptr, indices, **kw)
    s.factor(data)
    t0 = time.perf_counter()
    s.factor(data)
    factor = time.perf_counter() - t0
    times = []
    for _ in range(solves):
        t0 = time.perf_counter()
        x = s.solve(b)
        times.append(time.perf_counter() - t0)
    return s, factor, float(np.median(times)), x


def time_hessian(system, data: np.ndarray, b: np.ndarray, spd: bool, two_level: bool) -> dict:
    """A numerical factorisation and SOLVES solves as Newton's, timed; the solution; and what
    the factor says about the Hessian shifted to indefinite."""
    from jointsim.mechanics.newton import SINGLE_PRECISION

    s, factor, solve, x = _pattern_timing(system.full.indptr, system.full.indices, data, b, SOLVES, spd=spd, refinement=0,
                                          single=SINGLE_PRECISION, two_level=two_level)
    shifted = data.copy()
    shifted[system.diagonal] -= 1e-3 * np.abs(data[system.diagonal])  # σ = −1e-3: a few thousand negative pivots
    if spd:
        indefinite = {"cholesky_breaks_down": not s.try_factor(shifted)}
    else:
        s.factor(shifted)
        indefinite = {"negative_eigenvalues": s.negative_eigenvalues}
    s.free()
    return {"factor_s": factor, "solve_s": solve, "x": x, **indefinite}


def chamber_case() -> tuple:
    from jointsim.eit.forward import ForwardModel
    from jointsim.mesh.chamber import chamber_mesh
    from jointsim.scene import load_scene

    scene = load_scene(ROOT / "scenes" / "paper_sensor.toml").with_mesh_preset("paper")
    ch = chamber_mesh(scene)
    z = scene.electrodes.contact_impedances
    model = ForwardModel(ch.mesh, ch.electrodes, ch.ground, z)
    A = model.assembler.assemble(np.full(ch.mesh.n_tets, scene.saline.conductivity), z)
    n, L = ch.mesh.n_nodes, model.n_driven
    rhs = np.zeros((n + L, L))
    rhs[n + np.arange(L), np.arange(L)] = 1.0
    return A, rhs, ch.mesh.n_tets


def time_chamber(A, rhs, two_level: bool) -> dict:
    """One forward's linear algebra: analysis and factorisation, then the 16 solves at once."""
    import jointsim.linalg as solver

    package, solver.PARDISO_TWO_LEVEL = solver.PARDISO_TWO_LEVEL, two_level  # what factorize reads
    try:
        t0 = time.perf_counter()
        solve = solver.factorize(A, "pardiso")
        factor = time.perf_counter() - t0
    finally:
        solver.PARDISO_TWO_LEVEL = package
    t0 = time.perf_counter()
    x = solve(rhs)
    solves = time.perf_counter() - t0
    solve.free()
    return {"factor_s": factor, "solve_s": solves, "x": x,
            "rel_residual": float(np.linalg.norm(A @ x - rhs) / np.linalg.norm(rhs))}


def time_chamber_shared(A, rhs, two_level: bool) -> dict:
    """A palpation frame's: the analysis done before (another frame's), the numerical
    factorisation and the 16 solves timed."""
    import scipy.sparse as sp

    from jointsim.linalg import SPD_REFINEMENT

    U = sp.triu(A, format="csr")
    U.sort_indices()
    s, factor, solves, x = _pattern_timing(U.indptr, U.indices, U.data, rhs, 1, spd=True, backend="pardiso", refinement=SPD_REFINEMENT,
                                           two_level=two_level)
    s.free()
    return {"factor_s": factor, "solve_s": solves, "x": x}


def main(argv: list[str]) -> int:
    from jointsim.linalg import available_backends

    if argv[:1] == ["--report"]:
        import json

        d = json.loads(OUT.with_suffix(".json").read_text())
        write_pair(OUT, d, markdown(d))
        return 0
    if "pardiso" not in available_backends():
        print("PARDISO (pypardiso) is not installed: nothing to compare")
        return 1
    repeats = int(argv[0]) if argv else 9
    meta = {"command": "python benchmarks/bench_pardiso.py" + (f" {repeats}" if argv else ""), "machine": machine(),
            "date": time.strftime("%Y-%m-%d"), "repeats": repeats}
    meta["speed_reference_start_s"] = speed_reference()
    system, data, b, nodes = hessian_case()
    A, rhs, tets = chamber_case()
    meta["membrane"] = {"rim": MEMBRANE[0], "layers": MEMBRANE[1], "p2_nodes": nodes, "unknowns": int(system.free.sum())}
    meta["chamber"] = {"tets": tets, "unknowns": A.shape[0]}
    cases = {"cholesky": lambda two: time_hessian(system, data, b, True, two),
             "ldlt": lambda two: time_hessian(system, data, b, False, two),
             "chamber": lambda two: time_chamber(A, rhs, two),
             "chamber_shared": lambda two: time_chamber_shared(A, rhs, two)}
    runs: dict = {name: {case: [] for case in cases} for name in SETTINGS}
    keep: dict = {}
    for rep in range(repeats):
        for name, two in SETTINGS.items():
            for case, f in cases.items():
                r = f(two)
                keep[(name, case)] = r.pop("x")
                runs[name][case].append(r)
            print(f"repeat {rep + 1}/{repeats} {name}: " + ", ".join(
                f"{c} {runs[name][c][-1]['factor_s']:.3f} + {runs[name][c][-1]['solve_s']:.4f} s" for c in runs[name]), flush=True)
    meta["speed_reference_end_s"] = speed_reference()
    agree = {case: float(np.linalg.norm(keep[("two-level", case)] - keep[("one-level", case)]) / np.linalg.norm(keep[("one-level", case)]))
             for case in cases}
    data_out = {"meta": meta, "runs": runs, "agreement": agree}
    write_pair(OUT, data_out, markdown(data_out))
    print(OUT.with_suffix(".md").read_text())
    return 0


def _median(rs: list[dict], key: str) -> float:
    return float(np.median([r[key] for r in rs]))


def markdown(d: dict) -> str:
    m, runs, agree = d["meta"], d["runs"], d["agreement"]
    mem, ch = m["membrane"], m["chamber"]
    rows = []
    labels = {"cholesky": f"Newton Hessian, {mem['rim']}/{mem['layers']} pressed 1 mm ({mem['unknowns']:,} unknowns), Cholesky",
              "ldlt": "the same, LDLᵀ with inertia",
              "chamber": f"CEM matrix, paper chamber ({ch['tets']:,} tets, {ch['unknowns']:,} unknowns): analysis + Cholesky; 16 solves",
              "chamber_shared": "the same, the analysis reused: Cholesky; 16 solves"}
    for case in labels:
        one, two = runs["one-level"][case], runs["two-level"][case]
        f1, f2 = _median(one, "factor_s"), _median(two, "factor_s")
        s1, s2 = _median(one, "solve_s"), _median(two, "solve_s")
        rows.append(f"| {labels[case]} | {f1:.3f} | {f2:.3f} | {f2 / f1:.2f} | {s1 * 1e3:.1f} | {s2 * 1e3:.1f} | {s2 / s1:.2f} | {agree[case]:.1e} |")
    ldlt = {k: runs[k]["ldlt"][0]["negative_eigenvalues"] for k in runs}
    chol = {k: all(r["cholesky_breaks_down"] for r in runs[k]["cholesky"]) for k in runs}
    res = {k: max(r["rel_residual"] for r in runs[k]["chamber"]) for k in runs}
    return "\n".join([
        "# PARDISO: two-level against one-level factorisation",
        "",
        f"Command: `{m['command']}`  ",
        f"Machine: {m['machine']}; run {m['date']}; speed_reference {m['speed_reference_start_s']:.3f} s at the start, "
        f"{m['speed_reference_end_s']:.3f} s at the end (`benchmarks/_machine.py`).  ",
        f"Medians of {m['repeats']} repeats, the two settings alternating. Newton's Hessian as Newton factors it (single precision, "
        "the ordering and symbolic analysis once, then the numerical factorisation timed; a solve: one right-hand side, the "
        f"median of {SOLVES}). The chamber's as the EIT forward factors it (double precision, the 16 lead-field right-hand sides "
        "solved at once): one forward's, with a fresh analysis (ForwardModel), and a palpation frame's, its analysis done by an "
        "earlier frame (the forward's _SharedSolver for morphed chambers). Solutions: the relative difference of the two settings'; the Hessian's "
        "are single-precision solves of an ill-conditioned matrix, whose own error is of this order (2e-5 to 2e-3: "
        "jointsim/mechanics/newton.py, SINGLE_PRECISION).",
        "",
        "| system | factorise s, one-level | two-level | ratio | solve ms, one-level | two-level | ratio | solutions differ |",
        "|---|---|---|---|---|---|---|---|",
        *rows,
        "",
        f"The Hessian shifted down by 1e-3·|diag| (indefinite): LDLᵀ inertia {ldlt['one-level']} negative pivots one-level, "
        f"{ldlt['two-level']} two-level; Cholesky breaks down on it in every repeat: one-level {chol['one-level']}, two-level "
        f"{chol['two-level']}. The chamber's relative residual: at most {res['one-level']:.1e} one-level, {res['two-level']:.1e} two-level.",
        "",
        "The package takes the two-level factorisation for both (jointsim/linalg.py PARDISO_TWO_LEVEL); a whole press with "
        "either: results/mechanics_solvers.md.",
        "",
    ])


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
