"""Anatomy of a press step's Newton solve: why a warm-started 0.5 mm step of the membrane takes
three or more Newton iterations (one factorisation each, the larger part of a step's time in
results/mechanics_benchmark.md), and where the first full Newton step's residual comes from.

The press is bench_mechanics.py's (a rigid 15 mm sphere on the axis of the paper's dome, 0.5 mm
steps to 3 mm, tangent predictor, the package's Newton settings). For every step it records the
residual history and what each iteration took: the regularised step at the predictor (the
Hessian there is indefinite), then full Newton steps, with their line-search length and largest
nodal move. For the step's first full Newton step taken whole (α = 1) it splits the residual
left after it,

    g(u + d) = g(u) + H d + Σ_terms r_t,   r_t = g_t(u + d) − g_t(u) − H_t d,

into the linear solve's part (g + H d, PARDISO in single precision) and each energy term's
second-order remainder r_t (elastic, saline pressure, contact), all relative to ‖g(u)‖ on the
free components. The elastic remainder is evaluated again with the bulk modulus κ divided by 10
and 100 (same μ, same u and d): where it scales with κ, the step's residual is the volumetric
energy's curvature along d, which no linear solver setting changes.

    python benchmarks/bench_newton_anatomy.py              # 64/2 and 92/2: results/newton_anatomy.{md,json}
    python benchmarks/bench_newton_anatomy.py --report     # rewrites the .md from the .json

Runs in ~40 s on the 2-core Intel machine.
"""

from __future__ import annotations

import json
import sys
import time
from dataclasses import replace

import numpy as np
import scipy.sparse as sp

from _machine import atomic_write, machine, speed_reference
from bench_mechanics import DEPTHS_MM, ROOT, _membrane

OUT = ROOT / "results" / "newton_anatomy"
MESHES = [(64, 2), (92, 2)]  # (rim vertices, layers): the dataset's fidelity and the mesh converged to 2 % in force
BULK_DIVISORS = (1.0, 10.0, 100.0)


def _free_norm(g: np.ndarray, free: np.ndarray) -> float:
    return float(np.linalg.norm(g[free]))


def split_remainder(terms: list, u: np.ndarray, d: np.ndarray, free: np.ndarray) -> dict:
    """The residual after the whole step ``d`` from ``u``, split into the linear solve's part and
    each term's second-order remainder, all relative to ‖g(u)‖ (free components; "r0")."""
    g0 = [t.evaluate(u, True) for t in terms]
    g1 = [t.evaluate(u + d, False)[1] for t in terms]
    Hd = [sp.csr_matrix(e[2]) @ d.ravel() for e in g0]
    g_u = sum(e[1] for e in g0)
    r0 = _free_norm(g_u, free)
    out = {"r0": r0, "ratio": _free_norm(sum(g1), free) / r0, "linear_solve": _free_norm(g_u + sum(Hd), free) / r0}
    for t, e, gt, hd in zip(terms, g0, g1, Hd):
        out[type(t).__name__] = _free_norm(gt - e[1] - hd, free) / r0
        if hasattr(t, "_gap"):  # the sphere contact: nodes entering or leaving it along the step (its Hessian jumps there)
            out["contact_changes"] = int(np.sum((t._gap(u)[2] > 0) != (t._gap(u + d)[2] > 0)))
    return out


def elastic_remainder_by_bulk(model, material, u: np.ndarray, d: np.ndarray, free: np.ndarray, r0: float) -> dict:
    """The elastic term's remainder along ``d`` with the bulk modulus divided by each of
    BULK_DIVISORS (a fresh element kernel per material), relative to ``r0``."""
    from jointsim.mechanics.fem import ElasticTerm

    out = {}
    for div in BULK_DIVISORS:
        term = ElasticTerm(model.mesh, replace(material, bulk=material.bulk / div), volumetric=model.elastic.kernel.volumetric)
        _, g, H, _ = term.evaluate(u, True)
        g1 = term.evaluate(u + d, False)[1]
        out[f"{div:g}"] = _free_norm(g1 - g - sp.csr_matrix(H) @ d.ravel(), free) / r0
    return out


def run(n_rim: int, layers: int) -> dict:
    import jointsim.mechanics.dome as dome
    import jointsim.mechanics.newton as newton
    from jointsim.mechanics.dome import membrane_material
    from jointsim.scene import load_scene

    material = membrane_material(load_scene(ROOT / "scenes" / "paper_sensor.toml").membrane)
    events: list[dict] = []
    solves: list[dict] = []
    line_search, full_step, regularised = newton._line_search, newton._full_step, newton._regularised_step

    def on_full(u, Hs, free, g, system, data=None):
        d, spd = full_step(u, Hs, free, g, system, data)
        events.append({"kind": "full" if spd else "full, indefinite"})
        return d, spd

    def on_regularised(data, free, g, system):
        if events and events[-1]["kind"] == "full, indefinite" and "alpha" not in events[-1]:
            events[-1]["rejected"] = True  # the whole step did not lower the energy: the regularised one replaces it
        events.append({"kind": "regularised"})
        return regularised(data, free, g, system)

    def on_line_search(terms, u, E, g, d, it):
        res = line_search(terms, u, E, g, d, it)
        step = float(np.max(np.abs(d)))
        alpha = None if res is None or step == 0 else float(np.max(np.abs(res[0] - u)) / step)
        if not events or "alpha" in events[-1]:
            events.append({"kind": "?"})  # a step no hook announced (the projected fallback)
        events[-1].update(alpha=alpha, move_um=step * 1e6 * (alpha or 0.0), iteration=it, state=(u.copy(), d.copy()))
        return res

    def on_minimize(*a, **k):
        res = minimize(*a, **k)
        solves.append({"atol": k.get("atol"), "history": [float(x) for x in res.history]})
        return res

    minimize = dome.minimize_energy
    newton._full_step, newton._regularised_step, newton._line_search = on_full, on_regularised, on_line_search
    dome.minimize_energy = on_minimize
    try:
        model, _ = _membrane(n_rim, layers, 0.0, "pointwise")
        free = model.system.free
        top = model.first_contact_height((0.0, 0.0))
        steps = []
        for depth in DEPTHS_MM:
            events.clear()
            solves.clear()
            t0 = time.perf_counter()
            st = model.press(np.array([0.0, 0.0, top - depth * 1e-3]))
            wall = time.perf_counter() - t0
            row = {"depth_mm": depth, "wall_s": wall, "iterations": st.iterations, "force_mN": st.force[2] * 1e3,
                   "tolerance_N": solves[-1]["atol"], "histories": [s["history"] for s in solves],
                   "iterations_taken": [{k: v for k, v in e.items() if k != "state"} for e in events]}
            # the first full Newton step taken whole, after the regularised one (not in the first step,
            # which starts from the touch sub-step's own solve)
            first = next((e for e in events if e["kind"] == "full" and abs((e.get("alpha") or 0.0) - 1.0) < 1e-6 and e.get("iteration", 0) >= 1), None)
            if first is not None and depth > DEPTHS_MM[0]:
                u, d = first["state"]
                d = d.reshape(u.shape)
                # the terms as they were in that iteration: the target is where this step put it
                split = split_remainder(model.terms, u, d, free)
                row["first_full_step"] = {"iteration": first["iteration"], "move_um": first["move_um"], **split,
                                          "elastic_by_bulk_divisor": elastic_remainder_by_bulk(model, material, u, d, free, split["r0"])}
            steps.append(row)
    finally:
        newton._full_step, newton._regularised_step, newton._line_search = full_step, regularised, line_search
        dome.minimize_energy = minimize
    return {"n_rim": n_rim, "layers": layers, "p2_nodes": model.mesh.n_nodes, "steps": steps}


def write(rows: list[dict], meta: dict) -> None:
    """results/newton_anatomy.md from the measured rows (main writes the .json first)."""
    lines = ["# Anatomy of a press step's Newton solve", "", f"Command: `{meta['command']}`  ",
             f"Machine: {meta['machine']}; run {meta['date']}; speed_reference {meta['speed_reference_s']:.3f} s.  ",
             "The press of results/mechanics_benchmark.md (rigid 15 mm sphere on the axis, 0.5 mm steps to 3 mm, tangent predictor, "
             "the package's Newton settings; the first step starts from the touch sub-step's own solve). Residuals are the out-of-balance "
             "force on the free components, N; the step stops below its tolerance (1e-3 of the contact force, dome.FORCE_RTOL).", ""]
    for r in rows:
        lines += [f"## {r['n_rim']}/{r['layers']} ({r['p2_nodes']:,} P2 nodes)", "",
                  "| depth mm | its | tolerance N | residual history N (each Newton solve of the step) | iterations: kind, α, largest move µm |",
                  "|---|---|---|---|---|"]
        for s in r["steps"]:
            hist = " ‖ ".join(" → ".join(f"{x:.1e}" for x in h) for h in s["histories"])
            its = "; ".join(_taken(e) for e in s["iterations_taken"])
            lines.append(f"| {s['depth_mm']:.1f} | {s['iterations']} | {s['tolerance_N']:.1e} | {hist} | {its} |")
        lines += ["", "The first full Newton step taken whole (α = 1), its residual split (each relative to the residual before it):", "",
                  "| depth mm | iteration | largest move µm | contact nodes in/out | residual after | linear solve | elastic | pressure | contact | "
                  + " | ".join(f"elastic, κ/{k}" for k in ("10", "100")) + " |",
                  "|---|---|---|---|---|---|---|---|---|---|---|"]
        for s in r["steps"]:
            f = s.get("first_full_step")
            if f is None:
                continue
            b = f["elastic_by_bulk_divisor"]
            lines.append(f"| {s['depth_mm']:.1f} | {f['iteration']} | {f['move_um']:.1f} | {f['contact_changes']} | {f['ratio']:.2e} | {f['linear_solve']:.1e} | "
                         f"{f['ElasticTerm']:.2e} | {f['PressureTerm']:.1e} | {f['SphereContact']:.1e} | {b['10']:.2e} | {b['100']:.2e} |")
        lines.append("")
    lines += _reading(rows)
    atomic_write(OUT.with_suffix(".md"), "\n".join(lines) + "\n")


def _taken(e: dict) -> str:
    """One iteration as "kind α move": α None where the line search found the energy at its
    round-off (the step ends there); an indefinite full step is taken whole or rejected."""
    if e.get("rejected"):
        return f"{e['kind']}, rejected"
    if "alpha" not in e:
        return f"{e['kind']}, whole"
    if e["alpha"] is None:
        return f"{e['kind']}, at round-off"
    return f"{e['kind']} {e['alpha']:.3g} {e['move_um']:.1f}"


def _reading(rows: list[dict]) -> list[str]:
    """What the tables show, computed from them."""
    firsts = [s["first_full_step"] for r in rows for s in r["steps"] if "first_full_step" in s]
    if not firsts:
        return []
    its = [s["iterations"] for r in rows for s in r["steps"][1:]]
    # the remainder's exponent in κ over the decade κ/10 → κ (1: proportional)
    slope = [np.log10(f["elastic_by_bulk_divisor"]["1"] / f["elastic_by_bulk_divisor"]["10"]) for f in firsts]
    # what the iteration after the first full step leaves: the history of the step's (last) Newton solve
    after = [h[f["iteration"] + 2] / h[f["iteration"] + 1] for r in rows for s in r["steps"] if (f := s.get("first_full_step"))
             and len(h := s["histories"][-1]) > f["iteration"] + 2]
    still = [f for f in firsts if f["contact_changes"] == 0]
    moved = [f for f in firsts if f["contact_changes"] > 0]
    out = ["Reading:",
           f"- After the first step, a step takes {min(its)}–{max(its)} Newton iterations. Its first full Newton step, taken whole, "
           f"leaves {min(f['ratio'] for f in firsts):.2f}–{max(f['ratio'] for f in firsts):.2f} of the residual it started from "
           f"(a quadratic model of the energy would leave none); the next iteration leaves {min(after):.0e}–{max(after):.0e}.",
           f"- The linear solve (single precision) leaves at most {max(f['linear_solve'] for f in firsts):.1e} of it and the "
           f"saline pressure at most {max(f['PressureTerm'] for f in firsts):.1e}: neither is why a step takes three iterations."]
    if still:
        out.append(f"- In the {len(still)} steps where no node enters or leaves the contact along that step, the residual after it "
                   f"({min(f['ratio'] for f in still):.2f}–{max(f['ratio'] for f in still):.2f}) is the elastic term's "
                   f"second-order remainder ({min(f['ElasticTerm'] for f in still):.2f}–{max(f['ElasticTerm'] for f in still):.2f}); "
                   f"the contact's is at most {max(f['SphereContact'] for f in still):.1e}.")
    if moved:
        out.append(f"- In the {len(moved)} steps where {min(f['contact_changes'] for f in moved)}–{max(f['contact_changes'] for f in moved)} "
                   "nodes enter or leave the contact, the contact's remainder (the penalty's Hessian jumps at the sphere's surface) is "
                   f"{min(f['SphereContact'] for f in moved):.1e}–{max(f['SphereContact'] for f in moved):.1e}, beside the elastic "
                   f"{min(f['ElasticTerm'] for f in moved):.2f}–{max(f['ElasticTerm'] for f in moved):.2f}.")
    out.append(f"- The elastic remainder goes as κ^{min(slope):.2f}–κ^{max(slope):.2f} between κ/10 and κ along the same step: it is "
               "the volumetric energy κ/2 (J − 1)² curving along the step (J is cubic in the displacement gradient: a step that "
               "keeps each element's volume to first order, a rotation say, changes it to second order), amplified by κ = 1000 μ. "
               "It is a property of the energy along the step, not of how the step was solved: no linear-solver setting changes it, "
               "and only a shorter first full step or a bulk modulus far below the scene's would make it smaller.")
    return out


def main() -> int:
    if len(sys.argv) > 1 and sys.argv[1] == "--report":
        data = json.loads(OUT.with_suffix(".json").read_text())
        write(data["rows"], data["meta"])
        return 0
    meta = {"command": "python benchmarks/bench_newton_anatomy.py", "machine": machine(), "date": time.strftime("%Y-%m-%d"),
            "speed_reference_s": speed_reference()}
    rows = [run(n_rim, layers) for n_rim, layers in MESHES]
    # the measurements first: --report redoes the text from them
    atomic_write(OUT.with_suffix(".json"), json.dumps({"meta": meta, "rows": rows}, indent=2))
    write(rows, meta)
    print(OUT.with_suffix(".md").read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
