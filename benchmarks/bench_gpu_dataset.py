"""A dataset run with every sparse factorisation on the GPU (``--solver cudss``: Newton's and the
CEM forward's, through cuDSS) against the same run on the same machine's CPU cores (``--solver
auto``), and the forward's voltages on both.

    python benchmarks/bench_gpu_dataset.py --n 480 --workers 16 --out DIR   # on a machine with a GPU
    python benchmarks/bench_gpu_dataset.py --report results/gpu             # results/gpu.md from the runs' JSON

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
        m = chamber.mesh.n_tets
        sigmas = [np.full(m, sig), sig * (1 + 0.1 * rng.standard_normal(m))]
        for backend in [b for b in ("superlu", "pardiso", "cudss") if b in available_backends()]:
            model = ForwardModel.from_chamber(chamber, s, backend=backend)
            if backend != "superlu":
                model.shared()
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


def report(folder: Path) -> str:
    """results/gpu.md from the runs kept in ``folder``: solvers.json (bench_gpu_solvers.py --check),
    forward.json (this script's forward rows) and dataset_*.json (its dataset runs)."""
    solvers = json.loads((folder / "solvers.json").read_text())
    forward = json.loads((folder / "forward.json").read_text())["forward"]
    runs = [json.loads(f.read_text()) for f in sorted(folder.glob("dataset_*.json"))]
    runs.sort(key=lambda r: (-r["workers"], "p2" in r.get("mesh", "")))
    lines = ["# The GPU: sparse factorisations on cuDSS, and a dataset run against the same machine's CPU cores", "",
             "Commands, on the lent machine (the matrices exported there: `--export` writes them from the cached chambers):  ",
             "`python benchmarks/bench_gpu_solvers.py --export M && python benchmarks/bench_gpu_solvers.py --check M --out results/gpu/solvers`  ",
             "`python benchmarks/bench_gpu_dataset.py --n 480 --workers 16 [--mesh dataset_p2] --out DIR` and `--n 36 --workers 1`; "
             "the forward rows are its step 1  ",
             "This page: `python benchmarks/bench_gpu_dataset.py --report results/gpu`  ",
             f"Machine: {solvers['machine']}; backends there: {', '.join(solvers['backends'])} "
             "(PARDISO with MKL's sequential layer: a dataset worker runs one thread either way).", "",
             "## One factorisation: the same matrices on the CPU and the GPU", "",
             "Relative difference of the GPU's solution from SuperLU's (double precision on both), negative pivots of the "
             "LDLᵀ (Newton's test of definiteness), and seconds: a first factorisation + solve (the analysis included), "
             "then a refactorisation + solve with the analysis kept (what a frame or a Newton iteration pays; median of 5; SuperLU "
             "keeps none: a fresh factorisation each time).", "",
             "| system | unknowns | GPU vs SuperLU | PARDISO vs SuperLU | negative pivots GPU / SuperLU | first: SuperLU / PARDISO / GPU s "
             "| analysis kept: SuperLU / PARDISO / GPU s | GPU speed-up on PARDISO |", "|---|---:|---:|---:|---|---|---|---:|"]
    for x in solvers["rows"]:
        lines.append(f"| {x['system']} | {x['unknowns']:,} | {x['cudss_rel_diff_superlu']:.1e} | {x['pardiso_rel_diff_superlu']:.1e} | "
                     f"{x['cudss_negative_pivots']} / {x['superlu_negative_pivots']} | "
                     f"{x['superlu_first_s']:.3f} / {x['pardiso_first_s']:.3f} / {x['cudss_first_s']:.3f} | "
                     f"{x['superlu_refactor_solve_s']:.4f} / {x['pardiso_refactor_solve_s']:.4f} / {x['cudss_refactor_solve_s']:.4f} | "
                     f"{x['pardiso_refactor_solve_s'] / x['cudss_refactor_solve_s']:.1f} |")
    lines += ["", "## A frame's forward (assembly, factorisation with the analysis kept, 16 lead fields; median of 5)", "",
              "| preset | unknowns | SuperLU s | PARDISO s | GPU s | GPU speed-up on PARDISO | GPU vs SuperLU, max diff re max V |",
              "|---|---:|---:|---:|---:|---:|---:|"]
    for x in forward:
        lines.append(f"| {x['preset']} (P{x['order']}) | {x['unknowns']:,} | {x['superlu_frame_s']:.4f} | {x['pardiso_frame_s']:.4f} | "
                     f"{x['cudss_frame_s']:.4f} | {x['pardiso_frame_s'] / x['cudss_frame_s']:.1f} | {x['cudss_max_diff_re_max']:.1e} |")
    lines += ["", "## A dataset run: every factorisation on the GPU against the same machine's CPU cores", "",
              "`jointsim dataset` with the same seed and samples on both sides, `--solver auto` (PARDISO for Newton, SuperLU or "
              "PARDISO for the forward by size, as on any machine) against `--solver cudss`; wall time from the command's start to "
              "its end, worker start-up and set-up included on both sides. The stores compared: largest difference re the largest value.", "",
              "| preset | worker processes | samples | CPU s | GPU s | CPU samples/h | GPU samples/h | GPU / CPU | V | δV | force |",
              "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in runs:
        cpu, gpu = r["runs"]
        d = r["same_data"]
        lines.append(f"| {r.get('mesh', 'dataset')} | {r['workers']} | {r['n']} | {cpu['wall_s']:.1f} | {gpu['wall_s']:.1f} | "
                     f"{cpu['samples_per_h']:,.0f} | {gpu['samples_per_h']:,.0f} | **{r['ratio']:.2f}** | "
                     f"{d['voltages_clean']:.1e} | {d['dv_clean']:.1e} | {d['force']:.1e} |")
    one = [r for r in runs if r["workers"] == 1]
    many = [r for r in runs if r["workers"] > 1]
    lines += ["", "## What it says", "",
              f"- The GPU's factorisations are the CPU's numbers: the CEM solutions agree with SuperLU's to "
              f"{max(x['cudss_rel_diff_superlu'] for x in solvers['rows'] if x['system'].startswith('cem')):.0e} and a frame's voltages to "
              f"{max(x['cudss_max_diff_re_max'] for x in forward):.0e} of the largest; the membrane Hessians' to "
              f"{max(x['cudss_rel_diff_superlu'] for x in solvers['rows'] if x['system'].startswith('hessian')):.0e}, as close as PARDISO "
              "comes to SuperLU on them (their conditioning), with the same count of negative pivots.",
              f"- With the analysis kept, a refactorisation + solve is {min(x['pardiso_refactor_solve_s'] / x['cudss_refactor_solve_s'] for x in solvers['rows']):.0f}–"
              f"{max(x['pardiso_refactor_solve_s'] / x['cudss_refactor_solve_s'] for x in solvers['rows']):.0f}× faster on the GPU than "
              "PARDISO on one core; a first factorisation (the analysis included, its reordering on the CPU) takes "
              f"{min(x['cudss_first_s'] / x['pardiso_first_s'] for x in solvers['rows']):.2f}–"
              f"{max(x['cudss_first_s'] / x['pardiso_first_s'] for x in solvers['rows']):.1f}× PARDISO's time.",
              f"- A dataset worker alone gains {min(r['ratio'] for r in one):.2f}–{max(r['ratio'] for r in one):.2f}× (more at P2, where the "
              "forward's factorisation weighs more); one worker per core sharing the one GPU gains "
              f"{min(r['ratio'] for r in many):.2f}–{max(r['ratio'] for r in many):.2f}×: nothing. A sample's factorisations are about a third "
              "of its time (results/sample_profile.md: Newton's 30 %, the forward's few %), so even free factorisations leave the Warp "
              "element kernels, line searches and set-up on the cores, and sixteen processes queue on one GPU for small systems.",
              "- The GPU run's samples are not the CPU run's bit for bit: Newton stops each press at its own iterate below the force "
              "tolerance (1e-3 of the contact force), and the CPU's Newton factors in single precision; the differences are of that "
              "order in the force (within the tolerance) and far below the noise in the voltages. The factorisations themselves agree to the figures above.",
              "- What would move a dataset on a GPU: the element kernels on the device (Warp runs them there: `palpate --device cuda`), "
              "and many presses' systems factorised as one batch (cuDSS's batched API) rather than one process per core.", ""]
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", type=int, default=320)
    ap.add_argument("--workers", type=int, default=os.cpu_count())
    ap.add_argument("--mesh", default="dataset")
    ap.add_argument("--out", type=Path)
    ap.add_argument("--report", type=Path, metavar="DIR", help="write results/gpu.md from the runs' JSON in DIR")
    ap.add_argument("--skip-forward", action="store_true")
    ap.add_argument("--gpu-solver", default="cudss", help=argparse.SUPPRESS)  # another backend, to try this script without a GPU
    a = ap.parse_args()
    if a.report:
        (a.report.parent / f"{a.report.name}.md").write_text(report(a.report))
        return
    if a.out is None:
        ap.error("--out is required (or --report)")
    from jointsim.linalg import available_backends

    a.out.mkdir(parents=True, exist_ok=True)
    try:
        gpu = subprocess.run(["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"], capture_output=True, text=True).stdout.strip()
    except OSError:
        gpu = "no GPU"
    r = {"machine": f"{platform.machine()}, {os.cpu_count()} CPU cores, {gpu}, Python {platform.python_version()}",
         "backends": available_backends(), "n": a.n, "workers": a.workers, "mesh": a.mesh}
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
