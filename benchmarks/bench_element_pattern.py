"""What the membrane's element choice costs the Newton solve's factorisation: the sparsity
pattern of the free Hessian for the package's discretisation (each prism of the membrane split
into three P2 tetrahedra: 10-node elements, with a midside node on each quad face's diagonal)
against the 15-node serendipity wedge on the same prisms (no diagonal nodes), on the paper's
dome at several in-plane resolutions, two layers, the rim fixed.

Only the linear algebra is measured: a symmetric positive definite matrix on each pattern
(diagonally dominant; a Cholesky factorisation's cost depends on the pattern, not the values)
factorised as Newton's first try factorises its Hessian (PARDISO Cholesky in single
precision, jointsim.mechanics.newton.NewtonSystem), the median of REPEATS. The wedge is not an
element of the package: this bounds what it could save in the factorisations, which are ~60 %
of a 92/2 press step (results/mechanics_benchmark.md), not what a wedge kernel would cost.

Each factorisation's floating-point operations (PARDISO's count from its analysis) over its
time give the rate PARDISO reaches, reported beside this machine's dense single-precision
matrix product (numpy's BLAS) in the same run: how far the sparse factorisation is from what
the cores can do, and so how much any solver setting could still save.

    python benchmarks/bench_element_pattern.py      # writes results/element_pattern.{md,json}
"""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

import numpy as np
import scipy.sparse as sp
from _machine import machine, speed_reference, write_pair

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "results" / "element_pattern"
RIMS, LAYERS, REPEATS = (64, 92, 128), 2, 5
GEMM_N = 2000  # the dense product's size: large enough for the BLAS to reach its peak rate
# the wedge's edges in its node order (a0 a1 a2 / b0 b1 b2): bottom, top, vertical
WEDGE_EDGES = np.array([(0, 1), (1, 2), (2, 0), (3, 4), (4, 5), (5, 3), (0, 3), (1, 4), (2, 5)])


def membrane(n_rim: int):
    """(P2 mesh, 15-node wedges (P, 15), wedge-mesh node count, in-plane vertices) of the paper's
    membrane on a uniform cap of ``n_rim`` rim vertices; the wedges' first n_linear nodes are
    the P2 mesh's corner nodes, so both share the fixed rim's numbering there."""
    from jointsim.geometry import isotropic_cap
    from jointsim.mechanics.fem import P2Mesh
    from jointsim.mechanics.prisms import membrane_mesh, sphere_centre
    from jointsim.scene import load_scene

    scene = load_scene(ROOT / "scenes" / "paper_sensor.toml")
    c = scene.chamber
    dome = isotropic_cap(c.base_radius, c.dome_height, n_rim, None)
    lin, n = membrane_mesh(dome, c.membrane_thickness, LAYERS, sphere_centre(dome))
    f = np.asarray(dome.faces)
    prisms = np.vstack([np.hstack([l * n + f, (l + 1) * n + f]) for l in range(LAYERS)])
    edges = np.sort(prisms[:, WEDGE_EDGES], axis=2).reshape(-1, 2)
    uniq, inv = np.unique(edges, axis=0, return_inverse=True)
    wedges = np.hstack([prisms, len(lin.nodes) + inv.reshape(-1, 9)])
    wedge_nodes = np.vstack([lin.nodes, lin.nodes[uniq].mean(axis=1)])
    return P2Mesh.from_linear(lin), wedges, wedge_nodes, n


def free_upper(cells: np.ndarray, nodes: np.ndarray) -> sp.csr_matrix:
    """An SPD matrix on the free upper triangle of the element pattern of ``cells`` (the nodes on
    the base plane fixed, as the bonded rim)."""
    from jointsim.linalg import csr_pattern

    k = 3 * cells.shape[1]
    dof = (3 * cells[:, :, None] + np.arange(3)).reshape(-1, k)
    n = 3 * len(nodes)
    indptr, indices, _ = csr_pattern(np.repeat(dof, k, axis=1).ravel(), np.tile(dof, (1, k)).ravel(), n)
    A = sp.csr_matrix((np.ones(len(indices)), indices, indptr), shape=(n, n))
    free = np.repeat(np.abs(nodes[:, 2]) > 1e-9 * np.ptp(nodes), 3)
    A = A[free][:, free].tocsr()
    A.data = -np.random.default_rng(0).uniform(0.5, 1.0, A.nnz)
    A = (A + A.T) * 0.5
    A.setdiag(0.0)
    A.eliminate_zeros()
    A = A + sp.diags(1.0 - np.asarray(A.sum(axis=1)).ravel())  # strictly diagonally dominant
    U = sp.triu(A, format="csr")
    U.sort_indices()
    return U


def factor_cost(U: sp.csr_matrix) -> dict:
    from jointsim.linalg import PatternSolver

    solver = PatternSolver(U.indptr, U.indices, spd=True, refinement=0, single=True)
    times = []
    for _ in range(REPEATS):
        t0 = time.perf_counter()
        if not solver.try_factor(U.data):
            raise RuntimeError("the test matrix is not positive definite")
        times.append(time.perf_counter() - t0)
    t0 = time.perf_counter()
    solver.solve(np.ones(U.shape[0]))
    solve = time.perf_counter() - t0
    fill = int(solver._solver.iparm[17])  # iparm(18), 1-based: nonzeros in the factor
    solver.free()
    mflop = factor_mflop(U)
    return {"unknowns": U.shape[0], "nnz_upper": int(U.nnz), "fill": fill, "factor_s": float(np.median(times)), "solve_s": solve,
            "factor_mflop": mflop, "factor_gflop_per_s": mflop / 1e3 / float(np.median(times))}


def factor_mflop(U: sp.csr_matrix) -> int:
    """PARDISO's count (10⁶ operations) for the Cholesky factorisation of ``U``'s pattern with the
    package's settings: a fresh analysis with the count requested (iparm(19) < 0 on entry), which
    PatternSolver does not ask for since it slows the ordering."""
    from jointsim.linalg import _pardiso_solver, _release_pardiso, _set_iparm

    s = _pardiso_solver(2)
    _set_iparm(s, 0, single=True)
    s.iparm[18] = -1
    s.set_phase(11)
    s._call_pardiso(U.astype(np.float32), np.zeros(U.shape[0], np.float32))
    mflop = int(s.iparm[18])
    _release_pardiso(s)
    return mflop


def dense_gflop_per_s(repeats: int = 5) -> float:
    """This machine's single-precision dense matrix product rate (best of ``repeats``), the
    kernel a supernodal factorisation spends its time in."""
    a = np.random.default_rng(0).random((GEMM_N, GEMM_N), dtype=np.float32)
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        a @ a
        best = min(best, time.perf_counter() - t0)
    return 2 * GEMM_N**3 / best / 1e9


def floor(rows: list[dict]) -> list[str]:
    """What the factorisations alone cost a press step of results/mechanics_benchmark.json on the
    meshes both runs have: its fewest Newton iterations after the first step (one factorisation
    each) at this run's times."""
    path = ROOT / "results" / "mechanics_benchmark.json"
    if not path.exists():
        return []
    bench = {(r["n_rim"], r["layers"]): r for r in json.loads(path.read_text())["rows"] if not r["apex_mm"]}
    both = [(r, min(x["iterations"] for x in bench[r["n_rim"], LAYERS]["steps"][1:])) for r in rows if (r["n_rim"], LAYERS) in bench]
    if not both:
        return []
    cost = lambda key: " / ".join(f"{k * r[key]['factor_s']:.2f}" for r, k in both)
    return ["", "The factorisations' floor per press step: the fewest Newton iterations a step after the first took in "
            "results/mechanics_benchmark.json (" + " / ".join(f"{k} at {r['n_rim']}/{LAYERS}" for r, k in both) + "), one "
            f"factorisation each at this run's times, cost {cost('p2_tets')} s with the package's element and {cost('wedge15')} s "
            "with the wedge's pattern. The element kernel and the rest of a step come on top."]


def main() -> int:
    meta = {"command": "python benchmarks/bench_element_pattern.py", "machine": machine(), "date": time.strftime("%Y-%m-%d"),
            "load_average_start": os.getloadavg()[0], "speed_reference_s": speed_reference(), "repeats": REPEATS,
            "dense_gflop_per_s": dense_gflop_per_s()}
    rows = []
    for n_rim in RIMS:
        p2, wedges, wedge_nodes, n = membrane(n_rim)
        tet = factor_cost(free_upper(p2.tets, p2.nodes))
        wedge = factor_cost(free_upper(wedges, wedge_nodes))
        rows.append({"n_rim": n_rim, "in_plane_vertices": n, "p2_tets": {"nodes": p2.n_nodes, **tet}, "wedge15": {"nodes": len(wedge_nodes), **wedge}})
        print(f"{n_rim}/{LAYERS}: P2 tets {tet['factor_s']:.3f} s, wedges {wedge['factor_s']:.3f} s", flush=True)
    lines = ["# The element's sparsity pattern and the Newton factorisation", "", f"Command: `{meta['command']}`  ",
             f"Machine: {meta['machine']}; run {meta['date']}; 1-min load average {meta['load_average_start']:.1f} at the start; "
             f"speed_reference (`benchmarks/_machine.py`) {meta['speed_reference_s']:.3f} s; "
             f"a dense single-precision matrix product ({GEMM_N}², numpy's BLAS) runs at {meta['dense_gflop_per_s']:.0f} GFLOP/s.", "",
             "The paper's membrane (uniform cap, 2 mm in two prism layers, rim fixed). Each prism as three P2 tetrahedra (the package) "
             "or as one 15-node serendipity wedge (not in the package: the pattern only). An SPD matrix on each free upper-triangle "
             f"pattern, factorised by PARDISO's Cholesky in single precision as Newton's first try is; median of {REPEATS}. "
             "Fill: nonzeros in the factor (PARDISO iparm(18)); GFLOP: the factorisation's operations as PARDISO counts them "
             "(iparm(19)), and the rate they were done at.", "",
             "| rim / layers | element | nodes | unknowns | nnz (upper) | fill | GFLOP | factorise s | GFLOP/s | solve s | factorise, P2 / wedge |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        for key, name in (("p2_tets", "3 P2 tets per prism"), ("wedge15", "15-node wedge")):
            x = r[key]
            ratio = f"{r['p2_tets']['factor_s'] / r['wedge15']['factor_s']:.2f}×" if key == "wedge15" else ""
            lines.append(f"| {r['n_rim']}/{LAYERS} | {name} | {x['nodes']:,} | {x['unknowns']:,} | {x['nnz_upper']:,} | {x['fill']:,} | "
                         f"{x['factor_mflop'] / 1e3:.1f} | {x['factor_s']:.3f} | {x['factor_gflop_per_s']:.0f} | {x['solve_s']:.3f} | {ratio} |")
    lines += floor(rows)
    write_pair(OUT, {"meta": meta, "rows": rows}, "\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
