"""Mechanics benchmark and mesh-convergence study: quasi-static 0.5 mm steps (one 50 Hz frame
at 25 mm/s) of a rigid 15 mm target pressed on the axis of the paper's dome, warm-started, at
several membrane meshes (uniform isotropic caps, and caps graded from a fine apex) and both
volumetric forms of the P2 elements (pointwise penalty, mean dilatation). Reports the
contact force at 1, 2 and 3 mm against the finest mesh, wall time per step, Newton iterations,
and the split between the Warp element kernel (which also assembles the elastic Hessian into
its sparse pattern), the sparse factorisations and the rest.

    python benchmarks/bench_mechanics.py            # writes results/mechanics_benchmark.{md,json}
    python benchmarks/bench_mechanics.py --report   # rewrites the .md from the .json
"""

from __future__ import annotations

import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

from _machine import speed_reference

ROOT = Path(__file__).resolve().parents[1]
# (rim vertices, layers through the thickness, apex edge mm or 0 for uniform, volumetric form);
# the last is the reference: the finest mesh this machine solves in minutes, with elements about
# as tall as wide (on flat elements both volumetric forms stiffen, the pointwise one far more)
RESOLUTIONS = [(64, 2, 0.0, "pointwise"), (96, 2, 0.0, "pointwise"), (48, 2, 0.0, "mean_dilatation"), (64, 2, 0.0, "mean_dilatation"),
               (96, 2, 0.0, "mean_dilatation"), (128, 2, 0.0, "mean_dilatation"), (32, 2, 0.9, "mean_dilatation"), (48, 2, 1.3, "mean_dilatation"),
               (64, 3, 0.7, "mean_dilatation"), (96, 3, 0.0, "mean_dilatation"), (144, 3, 0.0, "mean_dilatation")]
GOAL_S, CONVERGED = 1.0, 0.02  # the goal: ≤ 1 s per step at a mesh within 2 % in force
DEPTHS_MM = (0.5, 1.0, 1.5, 2.0, 2.5, 3.0)


def run(n_rim: int, layers: int, apex_mm: float, volumetric: str = "mean_dilatation") -> dict:
    import jointsim.eit.solver as solver
    import jointsim.mechanics.fem as fem
    from jointsim.geometry import isotropic_cap
    from jointsim.mechanics.dome import MembraneModel
    from jointsim.scene import load_scene

    timers = {"kernel": 0.0, "factorise+solve": 0.0}

    def timed(name, f):
        def g(*a, **k):
            t0 = time.perf_counter()
            try:
                return f(*a, **k)
            finally:
                timers[name] += time.perf_counter() - t0
        return g

    fem.ElementKernel.__call__ = timed("kernel", fem.ElementKernel.__call__)
    solver.PatternSolver.factor = timed("factorise+solve", solver.PatternSolver.factor)
    solver.PatternSolver.solve = timed("factorise+solve", solver.PatternSolver.solve)

    from dataclasses import replace

    scene = load_scene(ROOT / "scenes" / "paper_sensor.toml")
    scene = replace(scene, membrane=replace(scene.membrane, layers=layers, volumetric=volumetric))
    c = scene.chamber
    dome = isotropic_cap(c.base_radius, c.dome_height, n_rim, apex_mm * 1e-3 if apex_mm else None)
    t0 = time.perf_counter()
    model = MembraneModel.from_scene(scene, 7.5e-3, dome=dome)
    setup = time.perf_counter() - t0
    top = model.first_contact_height((0.0, 0.0))
    steps = []
    for d in np.array(DEPTHS_MM) * 1e-3:
        for k in timers:
            timers[k] = 0.0
        t0 = time.perf_counter()
        st = model.press(np.array([0.0, 0.0, top - d]))
        wall = time.perf_counter() - t0
        steps.append({"depth_mm": d * 1e3, "wall_s": wall, "iterations": st.iterations, **{f"{k}_s": v for k, v in timers.items()},
                      "force_mN": st.force[2] * 1e3, "displaced_mm3": st.displaced_volume * 1e9, "penetration_um": st.penetration * 1e6})
    return {"n_rim": n_rim, "layers": layers, "apex_mm": apex_mm, "volumetric": volumetric, "p2_nodes": model.mesh.n_nodes, "tets": model.mesh.n_tets,
            "setup_s": setup, "steps": steps}


def _force(r: dict, depth: float) -> float:
    return next(x["force_mN"] for x in r["steps"] if abs(x["depth_mm"] - depth) < 1e-9)


def main() -> int:
    if len(sys.argv) > 1 and sys.argv[1] == "--report":
        saved = json.loads(OUT.with_suffix(".json").read_text())
        write(saved["rows"], saved["meta"])
        return 0
    if len(sys.argv) > 1 and sys.argv[1] == "--one":
        print(json.dumps(run(int(sys.argv[2]), int(sys.argv[3]), float(sys.argv[4]), sys.argv[5])))
        return 0
    import subprocess

    rows = []
    load0 = os.getloadavg()[0]
    speed0 = speed_reference()
    for n_rim, layers, apex, volumetric in RESOLUTIONS:
        r = subprocess.run([sys.executable, __file__, "--one", str(n_rim), str(layers), str(apex), volumetric], capture_output=True, text=True)
        if r.returncode:
            print(r.stderr[-2000:], file=sys.stderr)
            continue
        rows.append(json.loads(r.stdout.strip().splitlines()[-1]))
        s = rows[-1]["steps"]
        print(f"{n_rim} rim, {layers} layers, apex {apex} mm, {volumetric}: {np.mean([x['wall_s'] for x in s[1:]]):.2f} s/step, F(3 mm) {s[-1]['force_mN']:.2f} mN", flush=True)
    meta = {"command": "python benchmarks/bench_mechanics.py", "machine": f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}",
            "date": time.strftime("%Y-%m-%d"), "load_average_start_end": [load0, os.getloadavg()[0]],
            "speed_reference_s_start_end": [speed0, speed_reference()]}
    write(rows, meta)
    return 0


OUT = ROOT / "results" / "mechanics_benchmark"


def write(rows: list[dict], meta: dict) -> None:
    """results/mechanics_benchmark.{json,md} from the measured rows (``--report``: from the JSON)."""
    ref = rows[-1]
    out = OUT
    lines = ["# Mechanics benchmark and mesh convergence", "", f"Command: `{meta['command']}`  ", f"Machine: {meta['machine']}; run {meta['date']}.  ",
             "Rigid 15 mm sphere pressed on the axis of the paper's dome (neo-Hookean μ 22 kPa, κ = 1000 μ, 50 Pa reservoir), 0.5 mm steps",
             "to 3 mm, each warm-started from the previous (tangent predictor). Per-step means exclude the first step (first contact,",
             "no predictor yet). Membrane meshes: the inner surface as an isotropic cap of edge 2π·20 mm / rim vertices, either",
             "uniform or graded from the apex edge to the rim edge; P2 tetrahedra in prism layers through the 2 mm thickness.",
             "Volumetric form: the pointwise penalty (the scene default), which locks in bending, or mean dilatation (P2–P0",
             "mixed; jointsim/mechanics/fem.py).",
             "Kernel s: the Warp element kernel's calls, which include the elastic Hessian's assembly into its sparse pattern.",
             f"Force error: against the last row ({ref['n_rim']} rim, {ref['layers']} layers, uniform, {ref['volumetric']}).  ",
             f"1-min load average {meta['load_average_start_end'][0]:.1f} at the start, {meta['load_average_start_end'][1]:.1f} at the end "
             "(on 2 cores a load above 1 inflates the times; the forces do not depend on it).  ",
             "Reference workload (`benchmarks/_machine.py` speed_reference, a fixed sparse factorisation): "
             f"{meta['speed_reference_s_start_end'][0]:.3f} s at the start, {meta['speed_reference_s_start_end'][1]:.3f} s at the end; "
             "to compare with a run of another day, scale by the ratio of this figure.", "",
             "| rim | layers | apex edge mm | volumetric | P2 nodes | s / step | Newton its / step | kernel s | factorise+solve s | F 1 mm | F 2 mm | F 3 mm, mN | error at 1 / 2 / 3 mm |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    per_step = {id(r): np.mean([x["wall_s"] for x in r["steps"][1:]]) for r in rows}
    for r in rows:
        s = r["steps"][1:]
        err = " / ".join(f"{100 * (_force(r, d) / _force(ref, d) - 1):+.1f} %" for d in (1.0, 2.0, 3.0))
        lines.append(f"| {r['n_rim']} | {r['layers']} | {r['apex_mm'] or 'uniform'} | {r['volumetric'].replace('_', ' ')} | {r['p2_nodes']:,} | {per_step[id(r)]:.2f} | "
                     f"{np.mean([x['iterations'] for x in s]):.1f} | {np.mean([x['kernel_s'] for x in s]):.2f} | {np.mean([x['factorise+solve_s'] for x in s]):.2f} | "
                     f"{_force(r, 1.0):.2f} | {_force(r, 2.0):.2f} | {_force(r, 3.0):.2f} | {err} |")
    ok = [r for r in rows[:-1] if all(abs(_force(r, d) / _force(ref, d) - 1) <= CONVERGED for d in (1.0, 2.0, 3.0))]
    if ok:
        best = min(ok, key=lambda r: per_step[id(r)])
        label = lambda r: f"{r['n_rim']}/{r['layers']}/{r['apex_mm'] or 'uniform'} {r['volumetric'].replace('_', ' ')}"
        lines += ["", f"Within {CONVERGED:.0%} of the reference at 1, 2 and 3 mm: "
                  + ", ".join(f"{label(r)} ({per_step[id(r)]:.2f} s/step)" for r in ok)
                  + f". The fastest, {label(best)}, takes {per_step[id(best)]:.2f} s per step: "
                  + ("meets" if per_step[id(best)] <= GOAL_S else "misses") + f" the {GOAL_S:g} s goal."]
    else:
        lines += ["", f"No mesh but the reference is within {CONVERGED:.0%} of it at 1, 2 and 3 mm."]
    # the two uniform mean-dilatation meshes with the reference's element shape (edge / layer
    # thickness): a first-order (P2–P0) extrapolation along that refinement path
    from jointsim.scene import load_scene

    c = load_scene(ROOT / "scenes" / "paper_sensor.toml").chamber  # the scene run() presses
    shape = lambda r: 2 * np.pi * c.base_radius / r["n_rim"] / (c.membrane_thickness / r["layers"])
    path = sorted((r for r in rows if r["volumetric"] == ref["volumetric"] and not r["apex_mm"] and abs(shape(r) / shape(ref) - 1) < 0.02),
                  key=lambda r: r["n_rim"])
    if len(path) >= 2:
        a, b = path[-2], path[-1]
        ha, hb = 1 / a["n_rim"], 1 / b["n_rim"]
        limit = {d: _force(b, d) - (_force(a, d) - _force(b, d)) * hb / (ha - hb) for d in (1.0, 2.0, 3.0)}
        lines += ["", f"Extrapolated to zero mesh size from {a['n_rim']}/{a['layers']} and {b['n_rim']}/{b['layers']} (same element shape), "
                  "assuming first-order convergence: " + " / ".join(f"{limit[d]:.2f}" for d in (1.0, 2.0, 3.0))
                  + " mN at 1 / 2 / 3 mm; the reference is " + " / ".join(f"{100 * (_force(ref, d) / limit[d] - 1):+.1f} %" for d in (1.0, 2.0, 3.0))
                  + " from it (an estimate of the reference's own discretisation error)."]
    uniform = sorted((r for r in rows if r["volumetric"] == ref["volumetric"] and not r["apex_mm"]), key=shape, reverse=True)
    lines += ["", f"Force at 3 mm against the element shape (in-plane edge / layer thickness) of the uniform {ref['volumetric'].replace('_', ' ')} meshes: "
              + ", ".join(f"{shape(r):.2f} ({r['n_rim']}/{r['layers']}): {_force(r, 3.0):.2f} mN" for r in uniform)
              + ". The force follows the elements' shape more than their size (stiffer on flatter elements; a straight cantilever "
              "with mean dilatation does not do this, 0.996–1.020 of beam theory for shapes 4 to 0.5 in results/locking_cantilever.md, "
              "so the suspect is the curved "
              "dome's straight-sided, faceted elements), so "
              "agreement with the reference along its own shape does not show convergence: the spread over these shapes, "
              f"{min(_force(r, 3.0) for r in uniform):.1f}–{max(_force(r, 3.0) for r in uniform):.1f} mN, is the uncertainty left."]
    lines += ["", "The graded meshes are refined at the apex, where this benchmark presses: off the axis a press meets their "
              "coarser rim-ward cells, so they stand for a mesh graded around the contact, not for the uniform default the "
              "datasets and palpation use."]
    for suffix, text in ((".json", json.dumps({"meta": meta, "rows": rows}, indent=2)), (".md", "\n".join(lines) + "\n")):
        tmp = out.with_suffix(suffix + ".tmp")
        tmp.write_text(text)
        os.replace(tmp, out.with_suffix(suffix))
    print("\n".join(lines))


if __name__ == "__main__":
    sys.exit(main())
