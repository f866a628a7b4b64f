"""A dataset run with every sparse factorisation on the GPU (``--solver cudss``: Newton's and the
CEM forward's, through cuDSS) against the same run on the same machine's CPU cores (``--solver
auto``), and the forward's voltages on both.

    python benchmarks/bench_gpu_dataset.py --n 320 --workers 16 --out DIR   # on a machine with a GPU

1. The forward: the paper chamber's 256 skip-8 voltages at the dataset presets (P1 and P2), for
   the nominal saline and a perturbed conductivity (±10 % per element, the morphed frame's kind of
   change), solved on the CPU (SuperLU, and PARDISO where installed) and on the GPU (analysis
   kept across the two, as a dataset worker's shared solver): the largest difference re the
   largest voltage, and the seconds of a frame's factor + 16 solves (median of 5).
2. The dataset: ``jointsim dataset --mesh dataset`` with the same seed, samples and worker
   processes on each side, wall time from the command's start to its end (workers' start-up and
   set-up included alike); samples per hour and their ratio; the two stores' voltages, forces and
   δV compared. A 1-worker run of a few samples first compiles Warp's kernels into its cache
   for both (left out of both).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def _env() -> dict:
    return {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}


def forward_check() -> list[dict]:
    from jointsim.eit.forward import ForwardModel
    from jointsim.eit.protocol import scene_protocol
    from jointsim.linalg import available_backends
    from jointsim.mesh.chamber import chamber_mesh
    from jointsim.scene import SCENES_DIR, load_scene

    base = load_scene(SCENES_DIR / "paper_sensor.toml")
    rows = []
    rng = np.random.default_rng(1)
    for preset in ("dataset", "dataset_p2"):
        s = base.with_mesh_preset(preset)
        chamber = chamber_mesh(s)
        protocol = scene_protocol(s)
        sig = s.saline.conductivity
        row = {"preset": preset, "order": s.mesh.element_order}
        V = {}
        for backend in [b for b in ("superlu", "pardiso", "cudss") if b in available_backends()]:
            model = ForwardModel.from_chamber(chamber, s, backend=backend)
            if backend != "superlu":
                model.shared()
            sigmas = [np.full(model.mesh.n_tets, sig), sig * (1 + 0.1 * rng.standard_normal(model.mesh.n_tets))] if not V else sigmas
            V[backend] = [model.voltages(x, protocol) for x in sigmas]
            times = []
            for k in range(5):
                t = time.perf_counter()
                model.voltages(sigmas[k % 2], protocol)
                times.append(time.perf_counter() - t)
            row[f"{backend}_frame_s"] = float(np.median(times))
            model.free()
            if backend != "superlu":
                row[f"{backend}_max_diff_re_max"] = max(float(np.abs(a - b).max() / np.abs(b).max()) for a, b in zip(V[backend], V["superlu"]))
        row["unknowns"] = int(model.assembler.n_dofs + model.n_driven)
        rows.append(row)
        print(json.dumps(row), flush=True)
    return rows


def dataset_run(out: Path, n: int, workers: int, solver: str, mesh: str) -> dict:
    cmd = [sys.executable, "-m", "jointsim", "dataset", "--mesh", mesh, "--n", str(n), "--workers", str(workers),
           "--seed", "0", "--out", str(out), "--solver", solver, "--no-progress", "--overwrite"]
    t = time.perf_counter()
    p = subprocess.run(cmd, env=_env(), capture_output=True, text=True, cwd=ROOT)
    wall = time.perf_counter() - t
    if p.returncode:
        raise RuntimeError(f"{' '.join(cmd)}: rc {p.returncode}\n{p.stdout[-2000:]}\n{p.stderr[-4000:]}")
    return {"solver": solver, "workers": workers, "n": n, "wall_s": wall, "samples_per_h": n / wall * 3600}


def compare(a: Path, b: Path) -> dict:
    from jointsim.io.records import open_records

    fields = ["voltages_clean", "dv_clean", "force", "depth"]
    ra, rb = open_records(a, fields), open_records(b, fields)
    out = {}
    for f in fields:
        x, y = np.asarray(ra.fields[f], float), np.asarray(rb.fields[f], float)
        out[f] = float(np.nanmax(np.abs(x - y)) / np.nanmax(np.abs(y)))
    return out


def markdown(r: dict) -> str:
    lines = ["# A dataset run on the GPU against the same machine's CPU cores", "",
             f"Command: `python benchmarks/bench_gpu_dataset.py --n {r['n']} --workers {r['workers']}`  ",
             f"Machine: {r['machine']}. Backends here: {', '.join(r['backends'])}.", "",
             " ".join(__doc__.split("\n\n")[0].split()), "", "## The forward (one frame: factor + 16 lead-field solves)", "",
             "| preset | unknowns | SuperLU s | PARDISO s | GPU s | GPU vs SuperLU, max diff re max |V| |",
             "|---|---:|---:|---:|---:|---:|"]
    for x in r["forward"]:
        lines.append(f"| {x['preset']} (P{x['order']}) | {x['unknowns']:,} | {x['superlu_frame_s']:.4f} | {x.get('pardiso_frame_s', float('nan')):.4f} | "
                     f"{x.get('cudss_frame_s', float('nan')):.4f} | {x.get('cudss_max_diff_re_max', float('nan')):.1e} |")
    lines += ["", "## The dataset", "", "| solver | workers | samples | wall s | samples/h |", "|---|---:|---:|---:|---:|"]
    for x in r["runs"]:
        lines.append(f"| {x['solver']} | {x['workers']} | {x['n']} | {x['wall_s']:.1f} | {x['samples_per_h']:,.0f} |")
    lines += ["", f"GPU / CPU samples per hour: **{r['ratio']:.2f}**.", "",
              "The GPU run's stores against the CPU run's (largest difference re the largest value): "
              + ", ".join(f"{k} {v:.1e}" for k, v in r["same_data"].items()) + "."]
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", type=int, default=320)
    ap.add_argument("--workers", type=int, default=os.cpu_count())
    ap.add_argument("--mesh", default="dataset")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--skip-forward", action="store_true")
    ap.add_argument("--gpu-solver", default="cudss", help=argparse.SUPPRESS)  # another backend, to try this script without a GPU
    a = ap.parse_args()
    from jointsim.linalg import available_backends

    a.out.mkdir(parents=True, exist_ok=True)
    try:
        gpu = subprocess.run(["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"], capture_output=True, text=True).stdout.strip()
    except OSError:
        gpu = "no GPU"
    r = {"machine": f"{platform.machine()}, {os.cpu_count()} CPU cores, {gpu}, Python {platform.python_version()}",
         "backends": available_backends(), "n": a.n, "workers": a.workers}
    r["forward"] = [] if a.skip_forward else forward_check()
    t = time.perf_counter()
    dataset_run(a.out / "warm.h5", 6, 1, a.gpu_solver, a.mesh)  # Warp's kernels compiled and cached (both sides use them)
    r["warm_up_s"] = time.perf_counter() - t
    print("warm-up", r["warm_up_s"], flush=True)
    runs = []
    for solver in ("auto", a.gpu_solver):
        runs.append(dataset_run(a.out / f"ds_{solver}.h5", a.n, a.workers, solver, a.mesh))
        print(json.dumps(runs[-1]), flush=True)
        (a.out / "gpu_dataset.json").write_text(json.dumps({**r, "runs": runs}, indent=1))
    r["runs"] = runs
    r["ratio"] = runs[1]["samples_per_h"] / runs[0]["samples_per_h"]
    r["same_data"] = compare(a.out / f"ds_{a.gpu_solver}.h5", a.out / "ds_auto.h5")
    (a.out / "gpu_dataset.json").write_text(json.dumps(r, indent=1))
    md = markdown(r)
    (a.out / "gpu_dataset.md").write_text(md)
    print(md)


if __name__ == "__main__":
    main()
