"""Reconstruction throughput: once R (n_cells × 256) is set up, one frame's image is a
matrix–vector product. Measures frames per second on ONE core (BLAS threads pinned to 1
before numpy loads), one frame at a time and in batches, against the cost of the set-up
(SVD, λ by k-fold CV over 600 values, forming R), on the paper chamber's Jacobian.

    python benchmarks/bench_reconstruction.py [--mesh dataset] [--cells 7000]

Writes results/reconstruction_benchmark.md and .json.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_v] = "1"

import argparse  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from _machine import write_pair  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def main(argv: list[str] | None = None) -> int:
    from jointsim.eit.forward import ForwardModel
    from jointsim.eit.jacobian import jacobian
    from jointsim.eit.noise import noise_std
    from jointsim.eit.protocol import skip_protocol
    from jointsim.mesh.chamber import chamber_mesh
    from jointsim.reconstruction.grid import ChamberGrid
    from jointsim.reconstruction.tikhonov import SVD, choose_lambda
    from jointsim.scene import load_scene

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--mesh", default="dataset", choices=["test", "dataset", "paper"])
    ap.add_argument("--cells", type=int, default=7000)
    ap.add_argument("--out", type=Path, default=ROOT / "results" / "reconstruction_benchmark")
    args = ap.parse_args(argv)

    scene = load_scene(ROOT / "scenes" / "paper_sensor.toml").with_mesh_preset(args.mesh)
    ch = chamber_mesh(scene)
    p = skip_protocol(16, scene.drive.skip, scene.drive.current)
    f = ForwardModel.from_chamber(ch, scene).solve(scene.saline.conductivity)
    grid = ChamberGrid.over(ch.mesh, args.cells)
    J = jacobian(f, p, coarse=grid.C)
    v0 = f.voltages(p)
    rng = np.random.default_rng(0)
    dv = J @ (-0.37 * (rng.random(grid.n_cells) < 0.01)) + rng.normal(0, noise_std(v0, 74.2), 256)

    t0 = time.perf_counter()
    svd = SVD.of(J)
    t_svd = time.perf_counter() - t0
    t0 = time.perf_counter()
    choice = choose_lambda(svd, dv, "kfold")
    t_cv = time.perf_counter() - t0
    t0 = time.perf_counter()
    R = np.ascontiguousarray(svd.reconstruction_matrix(choice.lam))
    t_R = time.perf_counter() - t0

    frames = rng.normal(size=(2000, 256))
    n1 = 3000
    t0 = time.perf_counter()
    for i in range(n1):
        x = R @ frames[i % 2000]
    single = n1 / (time.perf_counter() - t0)
    t0 = time.perf_counter()
    reps = 5
    for _ in range(reps):
        X = frames @ R.T
    batch = reps * len(frames) / (time.perf_counter() - t0)
    del x, X
    res = {
        "command": " ".join(["python benchmarks/bench_reconstruction.py", *(argv if argv is not None else sys.argv[1:])]),
        "machine": f"{platform.machine()}, 1 BLAS thread, Python {platform.python_version()}, numpy {np.__version__}",
        "date": time.strftime("%Y-%m-%d"),
        "mesh_tets": ch.mesh.n_tets,
        "cells": grid.n_cells,
        "voxel_mm": float(grid.grid.spacing[0] * 1e3),
        "svd_s": t_svd,
        "kfold_cv_600_lambdas_s": t_cv,
        "form_R_s": t_R,
        "frames_per_s_single": single,
        "frames_per_s_batch2000": batch,
        "goal_frames_per_s": 5000,
    }
    write_pair(args.out, res, _md(res))
    print(_md(res))
    return 0


def _md(r: dict) -> str:
    return "\n".join(
        [
            "# Reconstruction benchmark",
            "",
            f"Command: `{r['command']}`  ",
            f"Machine: {r['machine']}; run {r['date']}.  ",
            f"Jacobian of the paper chamber ({r['mesh_tets']:,} tets, skip-8) on {r['cells']} cells of {r['voxel_mm']:.2f} mm.",
            "",
            "| step | time / rate |",
            "|---|---|",
            f"| SVD of J (256 × {r['cells']}) | {r['svd_s']:.2f} s |",
            f"| λ by 10-fold CV over 600 values | {r['kfold_cv_600_lambdas_s']:.2f} s |",
            f"| form R | {r['form_R_s']:.3f} s |",
            f"| one frame (R @ δv), frames/s | {r['frames_per_s_single']:,.0f} (goal ≥ {r['goal_frames_per_s']:,}) |",
            f"| batches of 2000 frames, frames/s | {r['frames_per_s_batch2000']:,.0f} |",
            "",
        ]
    )


if __name__ == "__main__":
    sys.exit(main())
