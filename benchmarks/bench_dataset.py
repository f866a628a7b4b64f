"""Dataset generation benchmark: labelled samples per hour of ``jointsim dataset`` with 1 and
with 2 local worker processes at the dataset resolution (the paper scene: "dataset" chamber
mesh, its 64-rim membrane, its [dataset] sampling), and the parallel efficiency
rate(2) / (2 · rate(1)). Goals (issue 6): ≥ 3000 samples/h, ≥ 80 % efficiency.

    python benchmarks/bench_dataset.py              # writes results/dataset_benchmark.{md,json}
    python benchmarks/bench_dataset.py --mesh dataset_p2 --n 120   # results/dataset_benchmark_dataset_p2.*
    python benchmarks/bench_dataset.py --quick      # a smoke run: test mesh, coarse membrane, tiny N; writes nothing

Each run is a whole ``generate_dataset`` call with the same seed, so both give the same data
(their ``data_sha256`` are compared). Two rates are reported: the **total** (N over the wall
time, including spawning the workers, their set-up and the last group's tail) and the
**steady** one (the samples stored after each worker has stored its first group, over the time
from then to the last group), which is what a long run approaches; it needs more groups than
workers. Per-stage times are the means
of the records' ``timings``. The machine's cores may be shared with other jobs: the load
average is recorded before and after each run, and an efficiency measured under load says
little.
"""

from __future__ import annotations

import argparse
import os
import platform
import shlex
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from _machine import cpu_name, speed_reference, write_pair

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from jointsim.dataset import STAGES, generate_dataset  # noqa: E402
from jointsim.io.store import open_records  # noqa: E402
from jointsim.scene import MESH_PRESETS, load_scene  # noqa: E402

GOAL_RATE = 3000.0  # labelled samples per hour (issue 6)
GOAL_EFFICIENCY = 0.80


def _scene(quick: bool, preset: str = "dataset"):
    scene = load_scene(ROOT / "scenes" / "paper_sensor.toml")
    if not quick:
        return scene.with_mesh_preset(preset)
    scene = scene.with_mesh_preset("test")
    return replace(scene, membrane=replace(scene.membrane, rim_vertices=24, layers=1),
                   palpation=replace(scene.palpation, cells=1000),
                   dataset=replace(scene.dataset, samples_per_press=3, depth=(0.3e-3, 1.5e-3)))


def bench(scene, n: int, workers: int, seed: int, folder: Path) -> dict:
    stamps: list[tuple[float, int]] = []
    load0 = os.getloadavg()
    t0 = time.perf_counter()
    run = generate_dataset(scene, n, folder / f"w{workers}", seed=seed, workers=workers,
                           progress=lambda k: stamps.append((time.perf_counter() - t0, k)))
    wall = time.perf_counter() - t0
    rec = open_records(run.path, fields=["timings", "depth", "force"])
    t = np.array([s for s, _ in stamps])
    k = np.array([c for _, c in stamps])
    # from the moment every worker has stored its first group: set-up and start-up left out
    w = min(workers, len(t))
    steady = float(k[w:].sum() / (t[-1] - t[w - 1]) * 3600) if len(t) > w else float("nan")
    return {
        "workers": workers,
        "samples": n,
        "groups": len(stamps),
        "wall_s": wall,
        "rate_total_per_h": n / wall * 3600,
        "rate_steady_per_h": steady,
        "first_group_s": float(t[0]) if len(t) else float("nan"),
        "stage_mean_s": dict(zip(STAGES, rec["timings"].mean(axis=0).tolist())),
        "sample_s": float(rec["timings"].sum(axis=1).mean()),
        "rejected_draws": run.rejected_draws,
        "data_sha256": run.data_sha256,
        "load_average_before": load0,
        "load_average_after": os.getloadavg(),
    }


def write(summary: dict, res: Path, stem: str = "dataset_benchmark") -> None:
    rows = summary["runs"]
    lines = [
        "# Dataset generation benchmark",
        "",
        f"Command: `{summary['command']}`  ",
        f"Machine: {summary['machine']['cpu']}, {summary['machine']['cores']} cores, Python {summary['machine']['python']}  ",
        "Reference workload (`benchmarks/_machine.py` speed_reference, a fixed sparse factorisation): "
        + " s at the start, ".join(f"{x:.3f}" for x in summary["speed_reference_s_start_end"])
        + " s at the end; to compare with a run of another day, scale by the ratio of this figure.  ",
        f"Scene: {summary['scene']} (mesh preset {summary['mesh']}, membrane {summary['membrane']}), "
        f"{summary['samples_per_press']} samples per press, seed {summary['seed']}  ",
        f"Goals: >= {GOAL_RATE:.0f} samples/h, >= {GOAL_EFFICIENCY:.0%} efficiency from 1 to 2 workers",
        "",
        "| workers | samples | wall s | total samples/h | steady samples/h | s per sample (sum of stages) | load before | load after |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['workers']} | {r['samples']} | {r['wall_s']:.0f} | {r['rate_total_per_h']:.0f} | {r['rate_steady_per_h']:.0f} "
            f"| {r['sample_s']:.2f} | {' '.join(f'{x:.1f}' for x in r['load_average_before'])} "
            f"| {' '.join(f'{x:.1f}' for x in r['load_average_after'])} |"
        )
    lines += [
        "",
        f"Efficiency 1 -> 2 workers: total {summary['efficiency_total']:.0%}, steady {summary['efficiency_steady']:.0%}.  ",
        f"Same data from 1 and 2 workers (data_sha256): {summary['same_data']}.",
        "",
        "Mean time per sample and stage (s; group_setup is the group's membrane inflation, reference chamber and "
        "reference forward, shared among its samples):",
        "",
        "| workers | " + " | ".join(STAGES) + " |",
        "|---|" + "---|" * len(STAGES),
    ]
    for r in rows:
        lines.append(f"| {r['workers']} | " + " | ".join(f"{r['stage_mean_s'][s]:.3f}" for s in STAGES) + " |")
    write_pair(res / stem, summary, "\n".join(lines) + "\n")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--n", type=int, default=48, help="samples per run (default 48: 8 presses of 6)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--workers", default="1,2", help="worker counts to run, comma-separated (default 1,2)")
    p.add_argument("--quick", action="store_true", help="test mesh, coarse membrane, 12 samples; writes only with --results")
    p.add_argument("--results", type=Path, help="folder for dataset_benchmark.{md,json} (default results/; --quick writes only here)")
    p.add_argument("--mesh", default="dataset", choices=sorted(MESH_PRESETS),
                   help="the fidelity (default dataset, P1; another writes dataset_benchmark_MESH.{md,json})")
    args = p.parse_args(argv)
    scene = _scene(args.quick, args.mesh)
    n = 12 if args.quick and args.n == 48 else args.n
    counts = [int(w) for w in args.workers.split(",")]
    runs = []
    speed0 = speed_reference()
    with tempfile.TemporaryDirectory(prefix="bench_dataset_") as tmp:
        for w in counts:
            r = bench(scene, n, w, args.seed, Path(tmp))
            runs.append(r)
            print(f"{w} worker(s): {n} samples in {r['wall_s']:.1f} s, {r['rate_total_per_h']:.0f}/h total, "
                  f"{r['rate_steady_per_h']:.0f}/h steady, load {r['load_average_after'][0]:.1f}", flush=True)
    by = {r["workers"]: r for r in runs}
    eff = lambda key: by[2][key] / (2 * by[1][key]) if 1 in by and 2 in by else float("nan")  # noqa: E731
    summary = {
        "command": shlex.join(["python", "benchmarks/bench_dataset.py", *(sys.argv[1:] if argv is None else argv)]),
        "machine": {"cpu": cpu_name(), "cores": os.cpu_count(), "python": platform.python_version(), "host": platform.node()},
        "scene": scene.name, "mesh": scene.mesh.preset,
        "membrane": f"{scene.membrane.element}, {scene.membrane.rim_vertices} rim vertices, {scene.membrane.layers} "
                    + ("layer" if scene.membrane.layers == 1 else "layers"),
        "samples_per_press": scene.dataset.samples_per_press, "seed": args.seed,
        "runs": runs,
        "efficiency_total": eff("rate_total_per_h"),
        "efficiency_steady": eff("rate_steady_per_h"),
        "same_data": len({r["data_sha256"] for r in runs}) == 1,
        "goals": {"rate_per_h": GOAL_RATE, "efficiency": GOAL_EFFICIENCY},
        "speed_reference_s_start_end": [speed0, speed_reference()],
    }
    print(f"efficiency 1 -> 2 workers: total {summary['efficiency_total']:.0%}, steady {summary['efficiency_steady']:.0%}; "
          f"same data: {summary['same_data']}")
    res = args.results if args.results is not None else (None if args.quick else ROOT / "results")
    if res is not None:
        stem = "dataset_benchmark" if args.mesh == "dataset" else f"dataset_benchmark_{args.mesh}"
        write(summary, res, stem)
        print(f"wrote {res / stem}.md")
    return 0


if __name__ == "__main__":
    sys.exit(main())
