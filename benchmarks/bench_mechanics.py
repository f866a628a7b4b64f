"""Mechanics benchmark and mesh-convergence study: quasi-static 0.5 mm steps (one 50 Hz frame
at 25 mm/s) of a rigid 15 mm target pressed on the axis of the paper's dome, warm-started, on
uniform membrane meshes of increasing resolution (P2 tetrahedra, the pointwise volumetric form,
validated on the dome in results/dome_apex_load.md; `--wedge`: the scene's default element, 15-node
wedges). Reports the contact force and the
displaced volume at 1, 2 and 3 mm against the finest mesh, an extrapolation of the force to zero
mesh size, wall time per step, Newton iterations, and the split between the Warp element kernel
(which also assembles the elastic Hessian into its sparse pattern), the sparse factorisations
and the rest.

    python benchmarks/bench_mechanics.py            # writes results/mechanics_benchmark.{md,json}
    python benchmarks/bench_mechanics.py --wedge    # the same study on 15-node wedges ([membrane] element =
                                                    # "wedge15"): results/mechanics_benchmark_wedge15.{md,json}
    python benchmarks/bench_mechanics.py --flat     # the same study of the membrane moulded flat and
                                                    # inflated: results/mechanics_flat_benchmark.{md,json}
    python benchmarks/bench_mechanics.py --flat --wedge  # the flat moulding on the wedges:
                                                    # results/mechanics_flat_benchmark_wedge15.{md,json}
    python benchmarks/bench_mechanics.py --report   # rewrites the .md files from the .json
    python benchmarks/bench_mechanics.py --solvers [N]  # the solver settings on one mesh, N runs each:
                                                    # results/mechanics_solvers.{md,json}
    python benchmarks/bench_mechanics.py --pair SETTING [N]  # the default and one SOLVERS setting in N
                                                    # adjacent pairs, ratios per pair (for gains
                                                    # below the spread between runs on a busy
                                                    # machine): results/mechanics_pair_<setting>.{md,json}
    python benchmarks/bench_mechanics.py --assembly [N]  # one iteration's Hessian by both assembly
                                                    # routes, N times: results/mechanics_assembly.{md,json}
    python benchmarks/bench_mechanics.py --first-contact [N]  # the first 0.5 mm frame solved with and without
                                                    # the touch sub-step (dome.FIRST_CONTACT), 3 target
                                                    # radii × 5 positions on 64/2, N rounds interleaved:
                                                    # results/mechanics_first_contact.{md,json}; with
                                                    # --wedge on 64/1 wedges: mechanics_first_contact_wedge15
    python benchmarks/bench_mechanics.py --cuda     # where Warp sees a GPU: the wedge press with the element kernel on
                                                    # the CPU and on cuda:0, forces compared: results/mechanics_cuda.{md,json}
    python benchmarks/bench_mechanics.py --one 92 2 0 pointwise [SETTING] [--device cuda:0] [--moulding flat] [--backend superlu]
                                                    # one mesh's press, printed as JSON (the element
                                                    # kernel on that Warp device, default cpu; the
                                                    # sparse solves by SuperLU as without PARDISO)

Each mesh runs in its own process; finished rows are kept in results/mechanics_benchmark.partial.json,
so an interrupted run resumes where it stopped (delete that file to start over).
"""

from __future__ import annotations

import json
import os
import re
import sys
import time
from pathlib import Path

import numpy as np
from _machine import (
    atomic_write,
    cpu_counters,
    machine,
    speed_reference,
    steal_share,
    write_pair,
)

ROOT = Path(__file__).resolve().parents[1]
# (rim vertices, layers through the thickness, apex edge mm or 0 for uniform, volumetric form);
# the last is the reference: the finest mesh this machine solves in minutes. The two-layer
# meshes refine the in-plane edge at fixed layer thickness; the three-layer ones show what a
# finer through-thickness division changes
RESOLUTIONS = [(48, 2, 0.0, "pointwise"), (64, 2, 0.0, "pointwise"), (72, 2, 0.0, "pointwise"), (80, 2, 0.0, "pointwise"),
               (88, 2, 0.0, "pointwise"), (92, 2, 0.0, "pointwise"), (96, 2, 0.0, "pointwise"), (64, 3, 0.0, "pointwise"), (96, 3, 0.0, "pointwise"),
               (128, 3, 0.0, "pointwise"), (128, 2, 0.0, "pointwise"), (160, 2, 0.0, "pointwise")]
# `--solvers`: the Newton solves' settings compared on one mesh, each run REPEATS times
# interleaved (load drift falls on all alike): (single precision, 2×2 pivots, Cholesky first,
# element-kernel threads or 0 for the package's KERNEL_THREADS, the elastic Hessian assembled
# by the kernel into the Newton system or as a matrix the system gathers from, PARDISO's two-level
# factorisation, Newton's chord steps); the first is the package default, every RESOLUTIONS row's. "LDLᵀ only, one
# kernel thread" is the default before Cholesky-first and the threaded kernel (results of
# 2026-11-21) in its solver settings
SOLVERS = {"default": (True, True, True, 0, True, True, False), "LDLᵀ only": (True, True, False, 0, True, True, False),
           "one kernel thread": (True, True, True, 1, True, True, False), "double precision": (False, True, True, 0, True, True, False),
           "Hessian gathered from a matrix": (True, True, True, 0, False, True, False),
           "LDLᵀ only, one kernel thread": (True, True, False, 1, True, True, False),
           "one-level factorisation": (True, True, True, 0, True, False, False), "chord steps": (True, True, True, 0, True, True, True)}
SOLVER_MESH, REPEATS = (92, 2, 0.0, "pointwise"), 2
# `--flat`: the same press on the membrane moulded flat and inflated to the dome ([membrane]
# moulding = "flat"); the last is the reference
FLAT_RESOLUTIONS = [(32, 2, 0.0, "pointwise"), (48, 2, 0.0, "pointwise"), (64, 2, 0.0, "pointwise"), (92, 2, 0.0, "pointwise"),
                    (64, 3, 0.0, "pointwise"), (128, 2, 0.0, "pointwise"), (160, 2, 0.0, "pointwise")]
# `--wedge`: the membrane's 15-node wedges (the form field "wedge15": MembraneModel element =
# "wedge15"); one and two layers, the last the reference
WEDGE_RESOLUTIONS = [(48, 1, 0.0, "wedge15"), (64, 1, 0.0, "wedge15"), (72, 1, 0.0, "wedge15"), (80, 1, 0.0, "wedge15"), (92, 1, 0.0, "wedge15"),
                     (128, 1, 0.0, "wedge15"), (160, 1, 0.0, "wedge15"), (64, 2, 0.0, "wedge15"), (92, 2, 0.0, "wedge15"), (128, 2, 0.0, "wedge15"),
                     (160, 2, 0.0, "wedge15")]
# `--flat --wedge`: the flat moulding on the default wedges; one layer, the last (two) the reference
FLAT_WEDGE_RESOLUTIONS = [(32, 1, 0.0, "wedge15"), (48, 1, 0.0, "wedge15"), (64, 1, 0.0, "wedge15"), (92, 1, 0.0, "wedge15"),
                          (128, 1, 0.0, "wedge15"), (160, 1, 0.0, "wedge15"), (160, 2, 0.0, "wedge15")]
GOAL_S, CONVERGED = 1.0, 0.02  # the goal: ≤ 1 s per step at a mesh within 2 % in force
DEPTHS_MM = (0.5, 1.0, 1.5, 2.0, 2.5, 3.0)


def run(n_rim: int, layers: int, apex_mm: float, volumetric: str = "mean_dilatation", linear: str = "default", device: str = "cpu",
        moulding: str = "cap", backend: str = "auto") -> dict:
    import jointsim.linalg as solver
    import jointsim.mechanics.fem as fem
    import jointsim.mechanics.newton as newton
    import jointsim.mechanics.wedge as wedge

    newton.SINGLE_PRECISION, newton.PIVOT_2X2, newton.CHOLESKY_FIRST, threads, into, solver.PARDISO_TWO_LEVEL, newton.CHORD_STEPS = SOLVERS[linear]
    fem.KERNEL_THREADS = threads or fem.KERNEL_THREADS
    if backend == "superlu":  # as on a machine without PARDISO (aarch64, macOS on Arm)
        solver.available_backends = lambda: ["superlu"]
    elif backend != "auto":
        raise SystemExit(f"--backend = {backend!r}: 'auto' or 'superlu'")
    if not into:  # Newton then takes the Hessian on the mesh's pattern and gathers its values
        del fem.ElasticTerm.evaluate_into

    timers = {"kernel": 0.0, "factorise+solve": 0.0}
    factorisations = [0]

    def timed(name, f, count=None):
        def g(*a, **k):
            t0 = time.perf_counter()
            try:
                return f(*a, **k)
            finally:
                timers[name] += time.perf_counter() - t0
                if count is not None:
                    count[0] += 1
        return g

    fem.ElementKernel.__call__ = timed("kernel", fem.ElementKernel.__call__)
    wedge.WedgeKernel.__call__ = timed("kernel", wedge.WedgeKernel.__call__)
    # try_factor (Cholesky that may fail) calls factor: each attempt counts once
    solver.PatternSolver.factor = timed("factorise+solve", solver.PatternSolver.factor, factorisations)
    solver.PatternSolver.solve = timed("factorise+solve", solver.PatternSolver.solve)

    model, setup = _membrane(n_rim, layers, apex_mm, volumetric, device, moulding)
    top = model.first_contact_height((0.0, 0.0))
    steps = []
    for d in np.array(DEPTHS_MM) * 1e-3:
        for k in timers:
            timers[k] = 0.0
        factorisations[0] = 0
        t0 = time.perf_counter()
        st = model.press(np.array([0.0, 0.0, top - d]))
        wall = time.perf_counter() - t0
        steps.append({"depth_mm": d * 1e3, "wall_s": wall, "iterations": st.iterations, "factorisations": factorisations[0],
                      **{f"{k}_s": v for k, v in timers.items()},
                      "force_mN": st.force[2] * 1e3, "displaced_mm3": st.displaced_volume * 1e9, "penetration_um": st.penetration * 1e6})
    return {"n_rim": n_rim, "layers": layers, "apex_mm": apex_mm, "volumetric": volumetric, "linear": linear, "device": device,
            "moulding": moulding, "backend": solver.default_backend(), "p2_nodes": model.mesh.n_nodes, "tets": model.mesh.n_elements, "setup_s": setup,
            "pressure_pa": model.pressure.pressure, "chamber_mm3": model.V0 * 1e9, "steps": steps}


def _membrane(n_rim: int, layers: int, apex_mm: float, volumetric: str, device: str = "cpu", moulding: str = "cap", radius: float = 7.5e-3):
    """The paper's membrane on a cap of ``n_rim`` rim vertices under the 15 mm target (or one of ``radius``; its element
    kernel on the Warp ``device``), and the seconds MembraneModel.from_scene took (meshing, inflation).
    ``moulding`` "flat": a flat disc of ``n_rim`` rim vertices inflated to the dome's height. ``volumetric``
    "wedge15": the membrane of 15-node wedges (their own volumetric form), else P2 tetrahedra with that form."""
    from dataclasses import replace

    from jointsim.geometry import flat_disc, isotropic_cap
    from jointsim.mechanics.build import membrane_from_scene
    from jointsim.scene import load_scene

    scene = load_scene(ROOT / "scenes" / "paper_sensor.toml")
    element = "wedge15" if volumetric == "wedge15" else "p2_tet"
    form = "pointwise" if element == "wedge15" else volumetric
    scene = replace(scene, membrane=replace(scene.membrane, layers=layers, volumetric=form, moulding=moulding, element=element))
    c = scene.chamber
    if moulding == "flat":
        dome = flat_disc(c.base_radius, n_rim)
    else:
        dome = isotropic_cap(c.base_radius, c.dome_height, n_rim, apex_mm * 1e-3 if apex_mm else None)
    t0 = time.perf_counter()
    model = membrane_from_scene(scene, radius, dome=dome, device=device)
    return model, time.perf_counter() - t0


def _at(r: dict, depth: float, key: str = "force_mN") -> float:
    return next(x[key] for x in r["steps"] if abs(x["depth_mm"] - depth) < 1e-9)


def _label(r: dict) -> str:
    return f"{r['n_rim']}/{r['layers']}"


def extrapolate(h: list[float], f: list[float]) -> tuple[float, float] | None:
    """(limit, order p) of f = f∞ + C·hᵖ through three points of decreasing h (any ratios), or
    None when the differences change sign or the order leaves [0.25, 8] (not in the asymptotic
    range)."""
    (h1, h2, h3), (f1, f2, f3) = h, f
    if (f1 - f2) * (f2 - f3) <= 0:
        return None
    q = (f1 - f2) / (f2 - f3)
    g = lambda p: (h1**p - h2**p) / (h2**p - h3**p) - q
    lo, hi = 0.25, 8.0
    if g(lo) * g(hi) > 0:
        return None
    for _ in range(100):  # bisection: g is monotone in p for h1 > h2 > h3
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if g(lo) * g(mid) > 0 else (lo, mid)
    p = 0.5 * (lo + hi)
    C = (f2 - f3) / (h2**p - h3**p)
    return f3 - C * h3**p, p


def main() -> int:
    if len(sys.argv) > 1 and sys.argv[1] == "--report":
        for out in (OUT, FLAT_OUT, WEDGE_OUT, FLAT_WEDGE_OUT):
            if out.with_suffix(".json").exists():
                saved = json.loads(out.with_suffix(".json").read_text())
                write(saved["rows"], saved["meta"], out)
        if SOLVERS_OUT.with_suffix(".json").exists():
            saved = json.loads(SOLVERS_OUT.with_suffix(".json").read_text())
            write_solvers(saved["runs"], saved["meta"])
        if CUDA_OUT.with_suffix(".json").exists():
            saved = json.loads(CUDA_OUT.with_suffix(".json").read_text())
            write_cuda(saved["rows"], saved["meta"])
        for path in sorted((ROOT / "results").glob(PAIR_PREFIX + "*.json")):
            saved = json.loads(path.read_text())
            write_pair_study(saved["runs"], saved["meta"])
        return 0
    if len(sys.argv) > 1 and sys.argv[1] == "--one":
        args = sys.argv[2:]
        opts = {"device": "cpu", "moulding": "cap", "backend": "auto"}
        for name in opts:
            if f"--{name}" in args:
                i = args.index(f"--{name}")
                opts[name] = args[i + 1]
                del args[i : i + 2]
        print(json.dumps(run(int(args[0]), int(args[1]), float(args[2]), args[3], *args[4:5], **opts)))
        return 0
    if len(sys.argv) > 1 and sys.argv[1] == "--cuda":
        return cuda()
    if len(sys.argv) > 1 and sys.argv[1] == "--assembly":
        return assembly(int(sys.argv[2]) if len(sys.argv) > 2 else 10)
    if len(sys.argv) > 1 and sys.argv[1] == "--first-contact":
        args = [a for a in sys.argv[2:] if a != "--wedge"]
        return first_contact(int(args[0]) if args else 2, wedge="--wedge" in sys.argv)
    if len(sys.argv) > 1 and sys.argv[1] == "--solvers":
        return solvers(int(sys.argv[2]) if len(sys.argv) > 2 else REPEATS)
    if len(sys.argv) > 2 and sys.argv[1] == "--pair":
        return pair(sys.argv[2], int(sys.argv[3]) if len(sys.argv) > 3 else 4)
    if sys.argv[1:3] in (["--flat", "--wedge"], ["--wedge", "--flat"]):
        return study(FLAT_WEDGE_RESOLUTIONS, FLAT_WEDGE_OUT, "flat", "python benchmarks/bench_mechanics.py --flat --wedge")
    if len(sys.argv) > 1 and sys.argv[1] == "--wedge":
        return study(WEDGE_RESOLUTIONS, WEDGE_OUT, "cap", "python benchmarks/bench_mechanics.py --wedge")
    if len(sys.argv) > 1 and sys.argv[1] == "--flat":
        return study(FLAT_RESOLUTIONS, FLAT_OUT, "flat", "python benchmarks/bench_mechanics.py --flat")
    return study(RESOLUTIONS, OUT, "cap", "python benchmarks/bench_mechanics.py")


def study(resolutions: list[tuple], out: Path, moulding: str, command: str) -> int:
    """The press on each mesh of ``resolutions`` (one process each), written to ``out``.{md,json};
    finished rows kept in its .partial.json (an interrupted run resumes)."""
    partial = out.with_suffix(".partial.json")
    saved = json.loads(partial.read_text()) if partial.exists() else {"rows": [], "meta": {}}
    meta = saved["meta"] or {**_new_meta(command), "moulding": moulding, "speed_reference_s_start_end": [speed_reference(), None]}
    rows = saved["rows"]
    for n_rim, layers, apex, volumetric in resolutions:
        if any((r["n_rim"], r["layers"], r["apex_mm"], r["volumetric"]) == (n_rim, layers, apex, volumetric) for r in rows):
            continue
        row = _one_press(n_rim, layers, apex, volumetric, "--moulding", moulding)
        if row is None:
            return 1
        rows.append(row)
        atomic_write(partial, json.dumps({"meta": meta, "rows": rows}, indent=2))
        s = rows[-1]["steps"]
        print(f"{n_rim} rim, {layers} layers, apex {apex} mm, {volumetric}: {np.mean([x['wall_s'] for x in s[1:]]):.2f} s/step, F(3 mm) {s[-1]['force_mN']:.2f} mN", flush=True)
    _finish_meta(meta)
    meta["speed_reference_s_start_end"][1] = speed_reference()
    order = {k: i for i, k in enumerate(resolutions)}
    rows.sort(key=lambda r: order.get((r["n_rim"], r["layers"], r["apex_mm"], r["volumetric"]), -1))
    write(rows, meta, out)
    partial.unlink()
    return 0


OUT = ROOT / "results" / "mechanics_benchmark"
FLAT_OUT = ROOT / "results" / "mechanics_flat_benchmark"
WEDGE_OUT = ROOT / "results" / "mechanics_benchmark_wedge15"
FLAT_WEDGE_OUT = ROOT / "results" / "mechanics_flat_benchmark_wedge15"
SOLVERS_OUT = ROOT / "results" / "mechanics_solvers"
CUDA_OUT = ROOT / "results" / "mechanics_cuda"
# `--cuda`: the dataset's and the paper's default wedge meshes (160/1 was tried too: without PARDISO,
# which the GPU machine here lacked, SuperLU's factorisations took it past that machine's 10-minute limit)
CUDA_MESHES = [(64, 1, 0.0, "wedge15"), (92, 1, 0.0, "wedge15")]


def cuda(device: str = "cuda:0") -> int:
    """``--cuda``: the press on each of CUDA_MESHES twice, the element kernel on Warp's CPU device
    and on ``device`` (one process each; everything else, the sparse solves included, on the CPU);
    results/mechanics_cuda.{md,json}, rewritten after every run (a run cut short keeps its rows)."""
    import jointsim.linalg as solver
    from jointsim._warp import wp

    if not wp.is_cuda_available():
        print("--cuda: Warp sees no CUDA device on this machine", file=sys.stderr)
        return 2
    meta = {**_new_meta("python benchmarks/bench_mechanics.py --cuda"), "gpu": wp.get_device(device).name,
            "warp": wp.config.version, "linear_backend": solver.default_backend()}
    rows = []
    for mesh in CUDA_MESHES:
        for dev in ("cpu", device):
            row = _one_press(*mesh, "--device", dev)
            if row is None:
                return 1
            rows.append(row)
            s = rows[-1]["steps"][1:]
            print(f"{_label(rows[-1])} on {dev}: {np.mean([x['wall_s'] for x in s]):.2f} s/step, kernel {np.mean([x['kernel_s'] for x in s]):.3f} s", flush=True)
            _finish_meta(meta)
            write_cuda(rows, meta)
    return 0


def write_cuda(rows: list[dict], meta: dict) -> None:
    """results/mechanics_cuda.{json,md}: per mesh and Warp device, the step's time and its split,
    and how far the GPU's forces and volumes are from the CPU's."""
    cpu = {_label(r): r for r in rows if r["device"] == "cpu"}
    lines = ["# The element kernel on Warp's CUDA device", "", f"Command: `{meta['command']}`  ",
             f"Machine: {meta['machine']}; GPU {meta['gpu']}; Warp {meta['warp']}; run {meta['date']}.  ",
             "The press of results/mechanics_benchmark_wedge15 (rigid 15 mm sphere on the axis of the paper's dome, 0.5 mm steps to",
             "3 mm, 15-node wedges), run twice per mesh: the Warp element kernel (energy, gradient, SPD-projected Hessian assembled",
             "into the Newton system) on the CPU and on the GPU; the sparse factorisations stay on the CPU "
             f"({meta['linear_backend']} here{'' if meta['linear_backend'] == 'pardiso' else ': PARDISO was not installed on this machine'}).",
             "Per-step means exclude the first step. Kernel s includes the host–device copies of the displacement and of the results.",
             "Force and volume differences: the largest over the six steps, GPU against CPU.", "",
             "| rim / layers | device | nodes | s / step | Newton its / step | kernel s | factorise+solve s | F 1 / 2 / 3 mm, mN | max force difference | max volume difference |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        s, ref = r["steps"][1:], cpu.get(_label(r))
        diff = ("—", "—")
        if ref is not None and ref is not r:
            diff = tuple(f"{max(abs(x[k] / y[k] - 1) for x, y in zip(r['steps'], ref['steps'])):.1e}" for k in ("force_mN", "displaced_mm3"))
        lines.append(f"| {_label(r)} | {r['device']} | {r['p2_nodes']:,} | {np.mean([x['wall_s'] for x in s]):.2f} | "
                     f"{np.mean([x['iterations'] for x in s]):.1f} | {np.mean([x['kernel_s'] for x in s]):.3f} | "
                     f"{np.mean([x['factorise+solve_s'] for x in s]):.2f} | " + " / ".join(f"{_at(r, d):.2f}" for d in (1.0, 2.0, 3.0))
                     + f" | {diff[0]} | {diff[1]} |")
    pairs = [(cpu[_label(r)], r) for r in rows if r["device"] != "cpu" and _label(r) in cpu]
    if pairs:
        kernel = lambda r: np.mean([x["kernel_s"] for x in r["steps"][1:]])  # noqa: E731
        share = lambda r: np.mean([x["factorise+solve_s"] for x in r["steps"][1:]]) / np.mean([x["wall_s"] for x in r["steps"][1:]])  # noqa: E731
        lines += ["", "Kernel time, CPU over GPU (the same machine, the same run): "
                  + ", ".join(f"{_label(a)} {kernel(a) / kernel(b):.1f}×" for a, b in pairs)
                  + ". The GPU's Newton iterations and factorisations are the CPU's, step for step"
                  + ("" if all([(x["iterations"], x["factorisations"]) for x in a["steps"]] == [(x["iterations"], x["factorisations"]) for x in b["steps"]]
                                for a, b in pairs) else " **except where they differ above**")
                  + "; the factorisations and solves, on the CPU either way, are "
                  + ", ".join(f"{100 * share(b):.0f} %" for _, b in pairs) + " of the GPU runs' steps."]
    atomic_write(CUDA_OUT.with_suffix(".json"), json.dumps({"meta": meta, "rows": rows}, indent=2))
    atomic_write(CUDA_OUT.with_suffix(".md"), "\n".join(lines) + "\n")


def solvers(repeats: int = REPEATS) -> int:
    """The linear-solver comparison on SOLVER_MESH (``--solvers``): results/mechanics_solvers.{md,json},
    finished runs kept in its .partial.json (an interrupted run resumes)."""
    partial = SOLVERS_OUT.with_suffix(".partial.json")
    saved = json.loads(partial.read_text()) if partial.exists() else {"runs": [], "meta": {}}
    meta = saved["meta"] or {**_new_meta(f"python benchmarks/bench_mechanics.py --solvers {repeats}"), "speed_reference_s": speed_reference()}
    runs = saved["runs"]
    meta.setdefault("repeats", repeats)
    for i in range(meta["repeats"] * len(SOLVERS)):
        if i < len(runs):
            continue
        linear = list(SOLVERS)[i % len(SOLVERS)]
        r = _press_run(linear)
        if r is None:
            return 1
        runs.append(r)
        atomic_write(partial, json.dumps({"meta": meta, "runs": runs}, indent=2))
        print(f"{linear}: {np.mean([x['wall_s'] for x in runs[-1]['steps'][1:]]):.2f} s/step", flush=True)
    _finish_meta(meta)
    write_solvers(runs, meta)
    partial.unlink()
    return 0


PAIR_PREFIX = "mechanics_pair_"


def pair_out(setting: str) -> Path:
    """results/mechanics_pair_<setting, as a file name> (no suffix): where ``--pair`` writes."""
    return ROOT / "results" / (PAIR_PREFIX + re.sub(r"[^a-z0-9]+", "_", setting.lower()).strip("_"))


def _one_press(*args) -> dict | None:
    """``--one *args`` (a mesh, then its options) in a fresh process: its row, or None where it
    failed (its stderr's tail printed)."""
    import subprocess

    r = subprocess.run([sys.executable, __file__, "--one", *map(str, args)], capture_output=True, text=True)
    if r.returncode:
        print(r.stderr[-2000:], file=sys.stderr)
        return None
    return json.loads(r.stdout.strip().splitlines()[-1])


def _press_run(linear: str) -> dict | None:
    """SOLVER_MESH's press with the ``linear`` setting, in a fresh process (None: it failed)."""
    return _one_press(*SOLVER_MESH, linear)


def pair(setting: str, pairs: int) -> int:
    """``--pair``: the default and ``setting`` run back to back ``pairs`` times (the order
    alternating), so that each pair sees nearly the same machine; results/mechanics_pair_<setting>."""
    if setting not in SOLVERS or setting == "default":
        print(f"SETTING = {setting!r}: one of {[k for k in SOLVERS if k != 'default']}", file=sys.stderr)
        return 2
    meta = {**_new_meta(f"python benchmarks/bench_mechanics.py --pair {setting!r} {pairs}"), "speed_reference_s": speed_reference(),
            "setting": setting, "pairs": pairs}
    runs = []
    for i in range(pairs):
        order = ("default", setting) if i % 2 == 0 else (setting, "default")
        for linear in order:
            r = _press_run(linear)
            if r is None:
                return 1
            r["pair"] = i
            runs.append(r)
            print(f"pair {i + 1}/{pairs} {linear}: {np.mean([x['wall_s'] for x in r['steps'][1:]]):.2f} s/step", flush=True)
    _finish_meta(meta)
    write_pair_study(runs, meta)
    return 0


def _factorisations(steps: list[dict]) -> float | None:
    """The mean factorisations per step of ``steps``; None for runs before 2026-11-23, which did
    not count them (one per Newton iteration then)."""
    return float(np.mean([x["factorisations"] for x in steps])) if all("factorisations" in x for x in steps) else None


def _per_step(runs: list[dict], key: str) -> float:
    """The mean of ``key`` over the runs' steps after the first (the first: first contact)."""
    return float(np.mean([x[key] for r in runs for x in r["steps"][1:]]))


def write_pair_study(runs: list[dict], meta: dict) -> None:
    """results/mechanics_pair_<setting>.{md,json} from the runs of :func:`pair`."""
    step = lambda r, key: _per_step([r], key)  # noqa: E731
    setting = meta["setting"]
    lines = [f"# Mechanics: \"{setting}\" against the default, in adjacent pairs", "", f"Command: `{meta['command']}`  ",
             f"Machine: {meta['machine']}; run {meta['date']}; 1-min load average {meta['load_average_start_end'][0]:.1f} at the start, "
             f"{meta['load_average_start_end'][1]:.1f} at the end{_steal(meta)}; speed_reference {meta['speed_reference_s']:.3f} s (`benchmarks/_machine.py`).  ",
             f"The press of results/mechanics_solvers.md on the {_label(runs[0])} membrane (settings there), run with the package default "
             f"and with \"{setting}\" back to back, each in its own process, {meta['pairs']} pairs, the order alternating. Per-step means "
             "over the steps after the first; ratio: the setting's over the default's of the same pair. This shared machine's speed "
             "drifts between runs by more than such a gain, and much less within a pair.", "",
             "| pair | default s / step | setting s / step | ratio | default factorise+solve s | setting | ratio | Newton its / step | factorisations / step | F 1 / 2 / 3 mm, mN (setting) |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    facts = lambda r: "–" if _factorisations(r["steps"][1:]) is None else f"{_factorisations(r['steps'][1:]):.1f}"  # noqa: E731
    ratios, lin = [], []
    for i in range(meta["pairs"]):
        d = next(r for r in runs if r["pair"] == i and r["linear"] == "default")
        x = next(r for r in runs if r["pair"] == i and r["linear"] == setting)
        ratios.append(step(x, "wall_s") / step(d, "wall_s"))
        lin.append(step(x, "factorise+solve_s") / step(d, "factorise+solve_s"))
        lines.append(f"| {i + 1} | {step(d, 'wall_s'):.2f} | {step(x, 'wall_s'):.2f} | {ratios[-1]:.3f} | {step(d, 'factorise+solve_s'):.2f} | "
                     f"{step(x, 'factorise+solve_s'):.2f} | {lin[-1]:.3f} | {step(d, 'iterations'):.1f} / {step(x, 'iterations'):.1f} | {facts(d)} / {facts(x)} | "
                     + " / ".join(f"{_at(x, dd):.2f}" for dd in (1.0, 2.0, 3.0)) + " |")
    same = all(abs(_at(r, dd) - _at(runs[0], dd)) < 5e-3 for r in runs for dd in (1.0, 2.0, 3.0))
    lines += ["", f"Ratio of the setting to the default: wall time median {np.median(ratios):.3f} (range {min(ratios):.3f}–{max(ratios):.3f}), "
              f"factorise+solve median {np.median(lin):.3f} (range {min(lin):.3f}–{max(lin):.3f}). Forces "
              + ("the same to 0.01 mN in every run." if same else "differ between runs: see the .json.")]
    write_pair(pair_out(setting), {"meta": meta, "runs": runs}, "\n".join(lines) + "\n")
    print("\n".join(lines))


def write_solvers(runs: list[dict], meta: dict) -> None:
    """results/mechanics_solvers.{md,json} from the runs of :func:`solvers`."""
    mean = _per_step
    by = {k: [r for r in runs if r["linear"] == k] for k in SOLVERS if any(r["linear"] == k for r in runs)}
    base = by["default"]
    lines = ["# Mechanics: the Newton solves' linear-solver and kernel settings", "", f"Command: `{meta['command']}`  ",
             f"Machine: {meta['machine']}; run {meta['date']}; 1-min load average {meta['load_average_start_end'][0]:.1f} at the start, "
             f"{meta['load_average_start_end'][1]:.1f} at the end{_steal(meta)}; speed_reference {meta.get('speed_reference_s', float('nan')):.3f} s "
             "(`benchmarks/_machine.py`).  ",
             f"The press of results/mechanics_benchmark.md (rigid 15 mm target, 0.5 mm steps to 3 mm) on the {_label(runs[0])} membrane, "
             f"each setting run {meta['repeats']} times interleaved; per-step means over the steps after the first. PARDISO, the ordering and "
             "symbolic analysis once per model. Ratios against the package default: single precision; each Hessian (and each shifted one) "
             "factored by Cholesky first, by Bunch–Kaufman LDLᵀ (1×1 and 2×2 pivots) with its inertia only where Cholesky fails; the Warp "
             f"element kernel launched in {meta.get('kernel_threads', '?')} chunks from as many threads; PARDISO's two-level "
             "factorisation. \"LDLᵀ only, one kernel thread\" is the default of results/mechanics_benchmark.md before 2026-11-22 in its "
             "solver settings; the pressure Hessian's assembly (a fixed linear map since 2026-11-22) and the two-level factorisation "
             "(since 2026-11-22; \"one-level factorisation\" is the classic one, jointsim/linalg.py PARDISO_TWO_LEVEL) are the "
             "package's in that row, so it is faster than that default was. \"Hessian gathered from a matrix\": the element kernel assembles the Hessian on the mesh's pattern and the Newton "
             "system gathers its free upper triangle, as before 2026-11-22, instead of adding straight into it.", "",
             "| setting | s / step | ratio | runs' s / step, min–max | factorise+solve s / step | ratio | kernel s / step | ratio | Newton its / step | F 1 / 2 / 3 mm, mN |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for k, rs in by.items():
        spread = [mean([r], "wall_s") for r in rs]
        lines.append(f"| {k} | {mean(rs, 'wall_s'):.2f} | {mean(rs, 'wall_s') / mean(base, 'wall_s'):.2f} | {min(spread):.2f}–{max(spread):.2f} | "
                     f"{mean(rs, 'factorise+solve_s'):.2f} | "
                     f"{mean(rs, 'factorise+solve_s') / mean(base, 'factorise+solve_s'):.2f} | {mean(rs, 'kernel_s'):.2f} | "
                     f"{mean(rs, 'kernel_s') / mean(base, 'kernel_s'):.2f} | {mean(rs, 'iterations'):.1f} | "
                     + " / ".join(f"{_at(rs[0], d):.2f}" for d in (1.0, 2.0, 3.0)) + " |")
    lines += ["", "Where a setting's runs spread wider than the settings differ (the min–max column: this shared machine's load "
              "drifts within a run), the run cannot rank them; `--pair SETTING` runs one setting and the default back to back "
              "(results/mechanics_pair_<setting>.md)."]
    write_pair(SOLVERS_OUT, {"meta": meta, "runs": runs}, "\n".join(lines) + "\n")
    print("\n".join(lines))


# `--first-contact`: the mesh, target radii (m) and positions (x, y mm) of the first-frame comparison
CONTACT_MESH, CONTACT_RADII = (64, 2, 0.0, "pointwise"), (4e-3, 7.5e-3, 12e-3)
CONTACT_MESH_WEDGE = (64, 1, 0.0, "wedge15")  # `--first-contact N --wedge`: the dataset fidelity's default membrane
CONTACT_XY = ((0, 0), (5, 0), (0, 8), (-6, 6), (10, 3))


def first_contact(rounds: int, wedge: bool = False) -> int:
    """The first 0.5 mm frame of a press from the touch, on CONTACT_MESH (``wedge``:
    CONTACT_MESH_WEDGE) for every target radius and position, solved with the touch sub-step
    (the package's) and in one step (dome.FIRST_CONTACT out of reach), the two alternating
    ``rounds`` times on the same models: factorisations, Newton iterations, wall time and the
    force each reaches. results/mechanics_first_contact{,_wedge15}.{md,json}."""
    import jointsim.linalg as solver
    import jointsim.mechanics.dome as dome_mod

    factors = [0]
    factor = solver.PatternSolver.factor

    def counted(*a, **k):
        factors[0] += 1
        return factor(*a, **k)

    solver.PatternSolver.factor = counted
    split = dome_mod.FIRST_CONTACT
    mesh = CONTACT_MESH_WEDGE if wedge else CONTACT_MESH
    meta = {**_new_meta(f"python benchmarks/bench_mechanics.py --first-contact {rounds}" + (" --wedge" if wedge else "")),
            "speed_reference_s_start_end": [speed_reference(), None], "rounds": rounds, "mesh": list(mesh)}
    models = {}
    for R in CONTACT_RADII:  # one model per radius, its untouched state restored before each press
        m = _membrane(*mesh, radius=R)[0]
        models[R] = (m, m.get_state())
    runs = []
    for k in range(rounds):
        for variant, value in (("touch sub-step", split), ("one step", 1e3)):
            dome_mod.FIRST_CONTACT = value
            for R, (m, rest) in models.items():
                for xy in CONTACT_XY:
                    m.set_state(rest)  # the target parked: the press starts at the touch
                    xy_m = np.array(xy, float) * 1e-3
                    top = m.first_contact_height(xy_m)
                    factors[0] = 0
                    t0 = time.perf_counter()
                    st = m.press(np.array([xy_m[0], xy_m[1], top - 0.5e-3]))
                    runs.append({"round": k, "variant": variant, "radius_mm": R * 1e3, "xy_mm": list(xy), "wall_s": time.perf_counter() - t0,
                                 "factorisations": factors[0], "iterations": st.iterations, "force_mN": st.force[2] * 1e3})
        print(f"round {k + 1}/{rounds}", flush=True)
    dome_mod.FIRST_CONTACT = split
    meta["load_average_start_end"][1] = os.getloadavg()[0]
    meta["speed_reference_s_start_end"][1] = speed_reference()
    write_first_contact(runs, meta)
    return 0


def write_first_contact(runs: list[dict], meta: dict) -> None:
    by = {v: [r for r in runs if r["variant"] == v] for v in ("touch sub-step", "one step")}
    total = lambda rs, key: float(sum(r[key] for r in rs))
    one = by["one step"]
    split, whole = (np.array([r["force_mN"] for r in by[v] if r["round"] == 0]) for v in by)
    mesh = meta.get("mesh", CONTACT_MESH)  # runs before the wedges' (2026-11-23) were on CONTACT_MESH
    element = "15-node wedges" if mesh[3] == "wedge15" else "P2 tetrahedra"
    lines = ["# Mechanics: the first contact frame", "", f"Command: `{meta['command']}`  ",
             f"Machine: {meta['machine']}; run {meta['date']}; 1-min load average {meta['load_average_start_end'][0]:.1f} at the start, "
             f"{meta['load_average_start_end'][1]:.1f} at the end; speed_reference {meta['speed_reference_s_start_end'][0]:.3f} / "
             f"{meta['speed_reference_s_start_end'][1]:.3f} s at the start / end (`benchmarks/_machine.py`).  ",
             f"The first 0.5 mm frame of a press from the touch on the {_label(dict(zip(('n_rim', 'layers'), mesh)))} membrane of {element} "
             f"(the dataset fidelity's), rigid targets of radius {', '.join(f'{R * 1e3:g}' for R in CONTACT_RADII)} mm at "
             f"{len(CONTACT_XY)} positions each ({'; '.join(f'{x}, {y}' for x, y in CONTACT_XY)} mm), {len(CONTACT_RADII) * len(CONTACT_XY)} "
             f"presses per variant and round, {meta['rounds']} rounds, the variants alternating on the same models. Touch sub-step (the "
             f"package's): the move solved first {meta['first_contact']:g} × thickness past the touch, then on from there with the tangent "
             "predictor (`jointsim/mechanics/dome.py` FIRST_CONTACT); one step: the whole 0.5 mm from the untouched state, as before "
             "2026-11-22. Newton iterations summed over the sub-steps.", "",
             "| variant | factorisations | ratio | Newton iterations | wall s | ratio |", "|---|---|---|---|---|---|"]
    for v, rs in by.items():
        lines.append(f"| {v} | {total(rs, 'factorisations'):.0f} | {total(rs, 'factorisations') / total(one, 'factorisations'):.2f} | "
                     f"{total(rs, 'iterations'):.0f} | {total(rs, 'wall_s'):.1f} | {total(rs, 'wall_s') / total(one, 'wall_s'):.2f} |")
    worse = sum(a["factorisations"] > b["factorisations"] for a, b in zip(by["touch sub-step"], one))
    lines += ["", f"Per press, the sub-step took more factorisations than one step in {worse} of {len(one)}. "
              f"Forces: the largest difference between the variants is {np.max(np.abs(split - whole) / whole):.1e} of the force "
              f"(Newton stops at 1e-3 of the contact force); forces {whole.min():.1f}–{whole.max():.1f} mN."]
    stem = "mechanics_first_contact" + ("_wedge15" if mesh[3] == "wedge15" else "")
    write_pair(ROOT / "results" / stem, {"meta": meta, "runs": runs}, "\n".join(lines) + "\n")
    print("\n".join(lines))


def assembly(repeats: int) -> int:
    """One Newton iteration's Hessian values on SOLVER_MESH pressed 1 mm (``--assembly N``), by
    the two routes, interleaved N times (a few seconds apart, so the machine's drift falls on
    both alike): the element kernel adding into the Newton system, and the kernel assembling the
    matrix on the mesh's pattern for the system to gather from. Each route includes the pressure
    and contact terms. results/mechanics_assembly.{md,json}."""
    import jointsim.mechanics.newton as newton

    model, _ = _membrane(*SOLVER_MESH)
    top = model.first_contact_height((0.0, 0.0))
    for d in (0.5e-3, 1e-3):
        model.press(np.array([0.0, 0.0, top - d]))
    u, terms, system = model.u, model.terms, model.system
    routes = {"into the system": lambda: system.data(newton._total(terms, u, True, system)[2]),
              "matrix, gathered": lambda: system.data(newton._total(terms, u, True)[2])}
    same = bool(np.array_equal(*(f() for f in routes.values())))
    times = {k: [] for k in routes}
    for _ in range(repeats):
        for k, f in routes.items():
            t0 = time.perf_counter()
            f()
            times[k].append(time.perf_counter() - t0)
    meta = {**_new_meta(f"python benchmarks/bench_mechanics.py --assembly {repeats}"), "speed_reference_s": speed_reference()}
    meta["load_average_start_end"][1] = os.getloadavg()[0]
    med = {k: float(np.median(v)) for k, v in times.items()}
    base = med["into the system"]
    lines = ["# Mechanics: assembling one Newton iteration's Hessian", "", f"Command: `{meta['command']}`  ",
             f"Machine: {meta['machine']}; run {meta['date']}; speed_reference {meta['speed_reference_s']:.3f} s (`benchmarks/_machine.py`); "
             f"the element kernel in {meta['kernel_threads']} chunks.  ",
             f"The {_label(dict(zip(('n_rim', 'layers', 'apex_mm', 'volumetric'), SOLVER_MESH)))} membrane pressed 1 mm by the "
             "rigid 15 mm target; the values of the elastic, pressure and contact Hessians in the Newton system's free upper triangle, by "
             f"each route, {repeats} times interleaved. Both routes give the same values bit for bit: {same}.", "",
             "| route | median ms | min ms | ratio of medians |", "|---|---|---|---|"]
    for k, v in times.items():
        lines.append(f"| {k} | {med[k] * 1e3:.1f} | {min(v) * 1e3:.1f} | {med[k] / base:.2f} |")
    out = ROOT / "results" / "mechanics_assembly"
    write_pair(out, {"meta": meta, "times_s": times, "bitwise_equal": same}, "\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0 if same else 1


def _new_meta(command: str) -> dict:
    """A run's provenance: command, machine, date, the load average at the start, and the
    package settings the writers describe (the kernel's threads, the touch sub-step)."""
    from jointsim.mechanics.dome import FIRST_CONTACT
    from jointsim.mechanics.fem import KERNEL_THREADS

    return {"command": command, "machine": machine(), "date": time.strftime("%Y-%m-%d"), "kernel_threads": KERNEL_THREADS,
            "first_contact": FIRST_CONTACT, "load_average_start_end": [os.getloadavg()[0], None], "cpu_counters_start": cpu_counters()}


def _finish_meta(meta: dict) -> None:
    """The end of a run into ``meta``: the load average, and the CPU steal over the run."""
    meta["load_average_start_end"][1] = os.getloadavg()[0]
    meta["cpu_steal"] = steal_share(meta.get("cpu_counters_start"), cpu_counters())


def _steal(meta: dict) -> str:
    """"; CPU steal x % over the run" where the run recorded it (runs before 2026-11-23 did not)."""
    share = meta.get("cpu_steal")
    return "" if share is None else f"; {100 * share:.0f} % of the CPU time stolen by other guests over the run"


def write(rows: list[dict], meta: dict, out: Path = OUT) -> None:
    """``out``.{json,md} (results/mechanics_benchmark, or mechanics_flat_benchmark for the flat
    moulding) from the measured rows (``--report``: from the JSON)."""
    flat = meta.get("moulding", "cap") == "flat"
    wedges = rows[-1]["volumetric"] == "wedge15"
    ref = rows[-1]
    depths = (1.0, 2.0, 3.0)
    per_step = {_label(r): np.mean([x["wall_s"] for x in r["steps"][1:]]) for r in rows}
    two = sorted((r for r in rows if r["layers"] == ref["layers"] and not r["apex_mm"]), key=lambda r: r["n_rim"])
    limit = {}
    if len(two) >= 3:
        a, b, c = two[-3:]
        for d in depths:
            e = extrapolate([1 / a["n_rim"], 1 / b["n_rim"], 1 / c["n_rim"]], [_at(a, d), _at(b, d), _at(c, d)])
            if e is not None:
                limit[d] = e
    # runs before the touch sub-step (2026-11-22) record no first_contact: their first step was one solve
    touch = meta.get("first_contact")
    first = (f"solved {touch:g} × thickness past the touch, then on from there with the predictor" if touch
             else "one solve from the untouched state, no predictor")
    if flat:
        setting = ["Rigid 15 mm sphere pressed on the axis of the paper's dome **moulded flat** ([membrane] moulding = \"flat\": a 2 mm",
                   "sheet bonded at its edge face, inflated until its inner apex stands 10 mm above the base; the reservoir then holds",
                   "that pressure), neo-Hookean μ 22 kPa, κ = 1000 μ; 0.5 mm steps to 3 mm, each warm-started from the previous",
                   f"(tangent predictor). Per-step means exclude the first step (first contact: {first}; its own column).",
                   "Membrane meshes: the flat disc triangulated as the",
                   "isotropic cap's limit (edge 2π·20 mm / rim vertices), "
                   + ("15-node wedges (the scene default) in prism layers through the thickness, their dilatation projected per element."
                      if wedges else "P2 tetrahedra in prism layers through the thickness, the volumetric energy pointwise."),
                   "Deploy pressure and chamber volume: the inflated, untouched state.",
                   "Setup s includes the inflation."]
    else:
        setting = ["Rigid 15 mm sphere pressed on the axis of the paper's dome (neo-Hookean μ 22 kPa, κ = 1000 μ, 50 Pa reservoir), 0.5 mm steps",
                   "to 3 mm, each warm-started from the previous (tangent predictor). Per-step means exclude the first step (first contact:",
                   f"{first}; its own column). Membrane meshes: the inner surface as a uniform isotropic cap of edge 2π·20 mm / rim vertices,",
                   "P2 tetrahedra (isoparametric, on the true spheres) in prism layers through the 2 mm thickness, the volumetric energy",
                   "pointwise ([membrane] element = \"p2_tet\", the scene default before 2026-11-23; validated on this dome against an",
                   "axisymmetric reference in results/dome_apex_load.md)."]
        if wedges:
            setting[-3:] = ["15-node quadratic wedges (isoparametric, on the true spheres), one per surface triangle and prism layer through the 2 mm",
                            "thickness, the volumetric energy of the dilatation projected per element onto linear polynomials ([membrane] element =",
                            "\"wedge15\", the scene default, jointsim/mechanics/wedge.py; validated on this dome against an axisymmetric reference in",
                            "results/dome_apex_load.md)."]
    title = "Mechanics benchmark and mesh convergence" + (": the membrane moulded flat" if flat else "")
    lines = ["# " + title, "", f"Command: `{meta['command']}`  ", f"Machine: {meta['machine']}; run {meta['date']}.  ",
             *setting,
             f"Kernel s: the Warp element kernel's calls ({meta.get('kernel_threads', 1)} chunks launched from as many threads), which include "
             "the elastic Hessian's assembly into the Newton system's values; factorise+solve s: PARDISO's, in single precision, each Hessian by "
             "Cholesky first and by LDLᵀ where that fails (jointsim/mechanics/newton.py SINGLE_PRECISION, CHOLESKY_FIRST).",
             f"Errors: against the last row ({_label(ref)}: rim vertices / layers).  ",
             f"1-min load average {meta['load_average_start_end'][0]:.1f} at the start, {meta['load_average_start_end'][1]:.1f} at the end"
             f"{_steal(meta)} (on 2 cores a load above 1 inflates the times; the forces do not depend on it).  ",
             "Reference workload (`benchmarks/_machine.py` speed_reference, a fixed sparse factorisation): "
             f"{meta['speed_reference_s_start_end'][0]:.3f} s at the start, {meta['speed_reference_s_start_end'][1]:.3f} s at the end; "
             "to compare with a run of another day, scale by the ratio of this figure.", "",
             f"| rim / layers | {'nodes' if wedges else 'P2 nodes'} | s / step | Newton its / step (factorisations, where counted) | kernel s | factorise+solve s | first step s (its) | F 1 / 2 / 3 mm, mN | force error 1 / 2 / 3 mm | displaced mm³ at 3 mm | its error |"
             + (" setup s | deploy pressure Pa | chamber mm³ |" if flat else ""),
             "|---|---|---|---|---|---|---|---|---|---|---|" + ("---|---|---|" if flat else "")]
    for r in rows:
        s = r["steps"][1:]
        err = " / ".join(f"{100 * (_at(r, d) / _at(ref, d) - 1):+.1f} %" for d in depths)
        vol = _at(r, 3.0, "displaced_mm3")
        facts = "" if _factorisations(s) is None else f" ({_factorisations(s):.1f})"
        lines.append(f"| {_label(r)} | {r['p2_nodes']:,} | {per_step[_label(r)]:.2f} | {np.mean([x['iterations'] for x in s]):.1f}{facts} | "
                     f"{np.mean([x['kernel_s'] for x in s]):.2f} | {np.mean([x['factorise+solve_s'] for x in s]):.2f} | "
                     f"{r['steps'][0]['wall_s']:.2f} ({r['steps'][0]['iterations']}) | "
                     + " / ".join(f"{_at(r, d):.2f}" for d in depths) + f" | {err} | {vol:.1f} | {100 * (vol / _at(ref, 3.0, 'displaced_mm3') - 1):+.1f} % |"
                     + (f" {r['setup_s']:.0f} | {r['pressure_pa']:.1f} | {r['chamber_mm3']:.0f} |" if flat else ""))
    if len(limit) == len(depths):
        a, b, c = two[-3:]
        lines += ["", f"Extrapolated to zero mesh size from {_label(a)}, {_label(b)} and {_label(c)} (f = f∞ + C·hᵖ through the three, h the edge): "
                  + " / ".join(f"{limit[d][0]:.2f}" for d in depths) + " mN at 1 / 2 / 3 mm (observed order "
                  + " / ".join(f"{limit[d][1]:.1f}" for d in depths) + "); the reference is "
                  + " / ".join(f"{100 * (_at(ref, d) / limit[d][0] - 1):+.1f} %" for d in depths) + " from it."]
        target = {d: limit[d][0] for d in depths}
        against = "the extrapolated force"
    else:
        lines += ["", f"The three finest {ref['layers']}-layer meshes do not converge monotonically at every depth: no extrapolation."
                  if len(two) >= 3 else f"Fewer than three {ref['layers']}-layer meshes (the reference's): no extrapolation."]
        target = {d: _at(ref, d) for d in depths}
        against = "the reference"
    ok = [r for r in rows if r is not ref and all(abs(_at(r, d) / target[d] - 1) <= CONVERGED for d in depths)]
    if flat:
        # the goal's "converged to 2 %" does not apply: the force does not converge monotonically
        # (the contact's discretisation scatters it) and the deployed state is still moving
        # the coarsest rim from which every finer mesh is within CONVERGED of the reference
        err = {r["n_rim"]: 0.0 for r in rows}
        for r in rows:
            if r is not ref:
                err[r["n_rim"]] = max(err[r["n_rim"]], max(abs(_at(r, d) / _at(ref, d) - 1) for d in depths))
        rims = sorted(err)
        within = [n for i, n in enumerate(rims) if all(err[m] <= CONVERGED for m in rims[i:])]
        fine = [r for r in rows if r is not ref and r["n_rim"] >= 48]
        spread = max(abs(_at(r, d) / _at(ref, d) - 1) for r in fine for d in depths) if fine else float("nan")
        lines += ["", f"Force: from 48 rim vertices on, every mesh is within {100 * spread:.1f} % of the finest at 1, 2 and 3 mm, without a "
                  "monotone trend (the contact's discretisation scatters it)"
                  + (f"; from {within[0]} rim vertices on within {CONVERGED:.0%} (at most "
                     f"{100 * max(err[m] for m in rims if m >= within[0]):.1f} %)." if within and within[0] < rims[-1] else
                     f": no mesh is shown converged to {CONVERGED:.0%}.")]
    elif ok:
        best = min(ok, key=lambda r: per_step[_label(r)])
        lines += ["", f"Within {CONVERGED:.0%} of {against} at 1, 2 and 3 mm: "
                  + ", ".join(f"{_label(r)} ({per_step[_label(r)]:.2f} s/step)" for r in ok)
                  + f". The fastest, {_label(best)}, takes {per_step[_label(best)]:.2f} s per step: "
                  + ("meets" if per_step[_label(best)] <= GOAL_S else "misses") + f" the {GOAL_S:g} s goal."]
    else:
        lines += ["", f"No mesh is within {CONVERGED:.0%} of {against} at 1, 2 and 3 mm."]
    if flat and len(two) >= 3:
        a, b, c = two[-3:]
        h = [1 / a["n_rim"], 1 / b["n_rim"], 1 / c["n_rim"]]
        deploy = {k: extrapolate(h, [a[k], b[k], c[k]]) for k in ("pressure_pa", "chamber_mm3")}
        if all(deploy.values()):
            (p_inf, p_order), (v_inf, v_order) = deploy["pressure_pa"], deploy["chamber_mm3"]
            lines += ["", f"The inflated state converges smoothly but slowly, at an order near 1 (the sheet bends sharply at its bonded edge): extrapolated from "
                      f"{_label(a)}, {_label(b)} and {_label(c)}, the deploy pressure is {p_inf:.0f} Pa (order {p_order:.1f}) and the chamber "
                      f"{v_inf:.0f} mm³ (order {v_order:.1f}); per mesh: "
                      + ", ".join(f"{_label(r)} {100 * (r['pressure_pa'] / p_inf - 1):+.1f} % / {100 * (r['chamber_mm3'] / v_inf - 1):+.1f} %"
                                  for r in two) + " (pressure / chamber)."]
    layered = [(r, q) for r in rows for q in rows if r["n_rim"] == q["n_rim"] and q["layers"] > r["layers"] and not r["apex_mm"] and not q["apex_mm"]]
    if layered:
        lines += ["", "Layers through the thickness, same in-plane mesh (force at 3 mm): "
                  + ", ".join(f"{_label(q)} is {100 * (_at(q, 3.0) / _at(r, 3.0) - 1):+.1f} % on {_label(r)}" for r, q in layered)
                  + (". The reference has two layers: the force changes by this much between one and two." if wedges else
                     f". The errors above are against a {ref['layers']}-layer reference, so they leave out this through-thickness "
                     "part: against a mesh refined in both directions a mesh's force is that much further off (pointwise P2 at "
                     "κ = 1000 μ stiffens a little on fewer layers; results/dome_apex_load.md).")]
    write_pair(out, {"meta": meta, "rows": rows}, "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    sys.exit(main())
