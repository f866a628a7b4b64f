"""Palpation frame benchmark: the wall time of each stage of one coupled frame (MuJoCo step,
FEM mechanics, chamber mesh, EIT forward, reconstruction + metrics) at the dataset chamber
resolution (~45 k tets) and the paper's (≥ 300 k), with the scene's membrane settings.

    python benchmarks/bench_palpation.py            # writes results/palpation_benchmark.{md,json}
    python benchmarks/bench_palpation.py --quick    # dataset only, fewer frames (a smoke run)

Frames: the paper's 15 mm target on the dome's axis, position control at 25 mm/s (0.5 mm per
50 Hz frame) to 2 mm past first contact and a hold; the first frames of that program run
through :func:`jointsim.palpation.run_palpation` exactly as ``jointsim palpate`` runs them.
Frame 0 (the rig at rest at first contact: nothing to solve) is left out of the statistics.
The set-up (membrane inflation, chamber mesh from the cache, reference forward, Jacobian on
the voxel grid, λ) is timed once per resolution. The machine's 2 cores are shared with other
jobs, so times are noisy: the load average is recorded before and after each resolution.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from _machine import atomic_write, cpu_name, speed_reference

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from jointsim.palpation import STAGES, Palpation, run_palpation  # noqa: E402
from jointsim.scene import load_scene  # noqa: E402

GOALS = {"dataset": 1.0, "paper": 5.0}  # s per frame (issue 5)
MESH_GOAL = 0.3  # s, the mesh step on the fixed-topology path




def _cores() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 0


def bench(preset: str, n_frames: int) -> dict:
    scene = load_scene(ROOT / "scenes" / "paper_sensor.toml").with_mesh_preset(preset)
    spec = replace(scene.palpation, target_radii=(7.5e-3,), depth=2e-3, hold=0.5)
    load0 = os.getloadavg()
    t0 = time.perf_counter()
    pal = Palpation(scene, spec)
    setup = time.perf_counter() - t0
    n_press = int(round(spec.depth / spec.speed * pal.frame_rate))  # frames 1 … n_press move the target
    rows = []
    for f in run_palpation(pal):
        r = f.record
        rows.append({
            "frame": f.frame, "depth_mm": 1e3 * r["depth"], "force_mN": 1e3 * r["force"][2],
            "newton_iterations": int(r["newton_iterations"]), "mesh_path": f.chamber.path,
            "mesh_min_shape_ratio": f.chamber.quality.min_shape / pal.instrument.morpher.reference_quality.min_shape,
            **{s: f.timings[s] for s in STAGES}, "total": sum(f.timings.values()),
        })
        print(f"  {preset} frame {f.frame}: depth {rows[-1]['depth_mm']:.2f} mm, "
              + ", ".join(f"{s} {f.timings[s]:.3f}" for s in STAGES) + f" s; total {rows[-1]['total']:.2f} s", flush=True)
        if len(rows) >= n_frames:
            break
    out = {
        "preset": preset,
        "chamber_tets": int(pal.instrument.reference.mesh.n_tets),
        "chamber_nodes": int(pal.instrument.reference.mesh.n_nodes),
        "membrane_p2_nodes": int(pal.membrane_nodes),
        "membrane": {"rim_vertices": scene.membrane.rim_vertices, "layers": scene.membrane.layers, "element": scene.membrane.element},
        "grid_cells": int(pal.instrument.grid.n_cells),
        "setup_s": setup,
        "setup_stages_s": pal.setup_timings,
        "frames": rows,
        "load_average_before": load0,
        "load_average_after": os.getloadavg(),
    }
    pal.free()
    timed = rows[1:]  # frame 0: at rest at first contact, nothing solved
    press = [r for r in timed if r["frame"] <= n_press]
    out["n_press_frames"] = n_press
    out["stats"] = _stats(timed)
    out["stats_press"] = _stats(press)
    out["stats_hold"] = _stats([r for r in timed if r["frame"] > n_press]) if len(press) < len(timed) else None
    out["without_mechanics_median"] = float(np.median([r["total"] - r["mechanics"] for r in timed]))
    return out


def _stats(rows: list[dict]) -> dict:
    return {
        k: {"median": float(np.median([r[k] for r in rows])), "min": float(np.min([r[k] for r in rows])),
            "max": float(np.max([r[k] for r in rows])), "n": len(rows)}
        for k in (*STAGES, "total")
    }


def write(results: list[dict], command: str, speed: list[float], machine: str | None = None, date: str | None = None) -> None:
    """results/palpation_benchmark.{json,md}; ``machine`` and ``date`` default to this run's
    (given: a report re-rendered from the JSON)."""
    machine = machine or f"{platform.machine()} {cpu_name()}, {_cores()} cores, Python {platform.python_version()}"
    date = date or time.strftime("%Y-%m-%d")
    res = ROOT / "results"
    atomic_write(res / "palpation_benchmark.json", json.dumps(
        {"command": command, "machine": machine, "date": date, "goals_s": GOALS, "mesh_goal_s": MESH_GOAL,
         "speed_reference_s_start_end": speed, "results": results},
        indent=2, default=float))
    lines = [
        "# Palpation frame benchmark",
        "",
        f"Command: `{command}`  ",
        f"Machine: {machine}; run {date}. The 2 cores are shared with other jobs: times are noisy "
        "(load averages below).  ",
        "Reference workload (`benchmarks/_machine.py` speed_reference, a fixed sparse factorisation): "
        f"{speed[0]:.3f} s at the start, {speed[1]:.3f} s at the end; to compare with a run of another day, scale by the "
        "ratio of this figure.  ",
        "Frames: the paper's 15 mm target on the axis, position control at 25 mm/s (0.5 mm per frame) to 2 mm past first "
        "contact, then the hold; the scene's membrane (neo-Hookean, 50 Pa reservoir). Statistics over the frames after "
        "frame 0 (at rest at first contact, nothing to solve).",
        "",
        "## Per-stage time per frame, median (min–max), ms",
        "",
        "Press: frames that move the target 0.5 mm into the dome; hold: frames at constant depth.",
        "",
        "| chamber | tets | membrane nodes | frames | MuJoCo | mechanics | mesh | forward | reconstruction | total | total without mechanics | goal | load avg before → after |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        for which, st in (("all", r["stats"]), ("press", r["stats_press"]), ("hold", r["stats_hold"])):
            if st is None:
                continue
            cell = lambda k: f"{1e3 * st[k]['median']:.0f} ({1e3 * st[k]['min']:.0f}–{1e3 * st[k]['max']:.0f})" if st[k]['median'] >= 0.01 else f"{1e3 * st[k]['median']:.2f} ({1e3 * st[k]['min']:.2f}–{1e3 * st[k]['max']:.2f})"  # noqa: E731
            first = which == "all"
            lines.append(
                (f"| {r['preset']} | {r['chamber_tets']:,} | {r['membrane_p2_nodes']:,} ({r['membrane'].get('element', 'p2_tet')}, "
                 f"{r['membrane']['rim_vertices']} rim, {r['membrane']['layers']} layer{'' if r['membrane']['layers'] == 1 else 's'}) | "
                 if first else "| | | | ")
                + f"{which}: {st['total']['n']} | " + " | ".join(cell(k) for k in (*STAGES, "total"))
                + (f" | {1e3 * r['without_mechanics_median']:.0f} | ≤ {1e3 * GOALS[r['preset']]:g} | "
                   f"{r['load_average_before'][0]:.1f} → {r['load_average_after'][0]:.1f} |" if first else " | | | |")
            )
    lines += ["", "## Set-up (once per run), s", "", "| chamber | total | " + " | ".join(results[0]["setup_stages_s"]) + " |",
              "|---|---|" + "---|" * len(results[0]["setup_stages_s"])]
    for r in results:
        lines.append(f"| {r['preset']} | {r['setup_s']:.1f} | " + " | ".join(f"{v:.2f}" for v in r["setup_stages_s"].values()) + " |")
    lines += ["", "## Frames", "", "| chamber | frame | depth mm | force mN | Newton its | mesh path | min η / reference | "
              + " | ".join(STAGES) + " | total |", "|---|---|---|---|---|---|---|" + "---|" * (len(STAGES) + 1)]
    for r in results:
        for f in r["frames"]:
            lines.append(f"| {r['preset']} | {f['frame']} | {f['depth_mm']:.2f} | {f['force_mN']:.1f} | {f['newton_iterations']} | "
                         f"{f['mesh_path']} | {f['mesh_min_shape_ratio']:.3f} | " + " | ".join(f"{f[s]:.3f}" for s in STAGES)
                         + f" | {f['total']:.2f} |")
    lines += ["", "## Reading", ""]
    for r in results:
        st = r["stats"]
        goal = GOALS[r["preset"]]
        ok = "meets" if st["total"]["median"] <= goal else "misses"
        sp, sh = r["stats_press"], r["stats_hold"]
        split = (f" (frames that move the target {sp['total']['median']:.2f} s, hold frames {sh['total']['median']:.2f} s)"
                 if sh is not None else "")
        lines.append(
            f"- {r['preset']} ({r['chamber_tets']:,} tets): {st['total']['median']:.2f} s per frame (median){split}, which {ok} "
            f"the {goal:g} s goal; without the mechanics {r['without_mechanics_median']:.2f} s. The mechanics step takes "
            f"{st['mechanics']['median']:.2f} s ({st['mechanics']['median'] / st['total']['median']:.0%} of the frame; "
            f"{sp['mechanics']['median']:.2f} s when the target moves); the mesh step (fixed-topology morph) "
            f"{st['mesh']['median'] * 1e3:.0f} ms against the {MESH_GOAL:g} s goal; the forward solve (CEM assembly, "
            f"factorisation, 16 lead fields) {st['forward']['median']:.2f} s; the image and its metrics "
            f"{st['reconstruction']['median'] * 1e3:.0f} ms; MuJoCo {st['mujoco']['median'] * 1e3:.1f} ms."
        )
    largest = {r["preset"]: max(STAGES, key=lambda k: r["stats"][k]["median"]) for r in results}
    lines.append("- The largest stage: " + ", ".join(f"{k} at the {p} resolution" for p, k in largest.items())
                 + ". The membrane's Newton solve does not depend on the chamber resolution, only on the membrane mesh "
                 "(results/mechanics_benchmark_wedge15.md for the default element). Hold frames need fewer Newton "
                 "iterations than pressing frames.")
    atomic_write(res / "palpation_benchmark.md", "\n".join(lines) + "\n")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="dataset resolution only, 4 frames; does not write results/")
    p.add_argument("--frames", type=int, default=8, help="frames per resolution incl. frame 0 (default 8: press to 2 mm, 3 hold)")
    p.add_argument("--paper-frames", type=int, default=8, help="frames at the paper's resolution (default 8)")
    p.add_argument("--report", action="store_true", help="rewrite results/palpation_benchmark.md from its .json")
    args = p.parse_args(argv)
    if args.report:
        d = json.loads((ROOT / "results" / "palpation_benchmark.json").read_text())
        write(d["results"], d["command"], d["speed_reference_s_start_end"], d["machine"], d["date"])
        return 0
    if args.quick:
        bench("dataset", 4)
        return 0
    speed0 = speed_reference()
    results = [bench("dataset", args.frames), bench("paper", args.paper_frames)]
    cmd = "python benchmarks/bench_palpation.py" + ("" if argv is None and len(sys.argv) == 1 else " " + " ".join(sys.argv[1:] if argv is None else argv))
    write(results, cmd, [speed0, speed_reference()])
    print(Path(ROOT / "results" / "palpation_benchmark.md").read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
