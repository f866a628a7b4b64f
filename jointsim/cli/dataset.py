"""Synthetic dataset generation: press trajectories drawn from the scene's [dataset] section
(target radius, contact position, depth, stiffness, and domain randomisation of the membrane,
saline, contact impedance, electrode positions and noise), one labelled sample per depth along
each press: labels, force, displaced volume, clean and noisy voltages, dV, image metrics and
optionally the image; or the presses of a list (--presses CSV: a calibration rig's raster).
Writes OUT.h5 (schema "dataset", provenance, data_sha256). The same seed
gives the same data whatever the workers; a run killed at any moment resumes when run again
with the same settings. Local worker processes by default; --scheduler runs the groups on an
existing Dask distributed cluster whose workers see OUT's folder."""

from __future__ import annotations

import argparse
import shlex
import sys
from dataclasses import replace
from pathlib import Path

from tqdm import tqdm

from .._cores import available_cores
from ..scene import scene_toml
from .common import add_overwrite_argument, add_progress_argument, add_solver_argument, add_scene_arguments, overwrite, progress_off, scene_from_args, use_solver

OUTPUT = "file"  # what --out names (checked before any work: cli.common.check_output)
HELP = "synthetic labelled dataset (voltages, labels, force, image metrics) in one resumable HDF5 file"


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_scene_arguments(p)
    p.add_argument("--n", type=int, help="number of labelled samples (required unless --presses gives them)")
    p.add_argument("--presses", type=Path, metavar="CSV",
                   help="press these presses instead of drawn ones: a CSV with contact_x_mm, contact_y_mm (or the targets' "
                        "centres x_mm, y_mm), diameter_mm, optionally modulus_kpa and depth_mm (one row per sample)")
    p.add_argument("--out", type=Path, default=Path("out/dataset.h5"), help="output file (default out/dataset.h5)")
    add_overwrite_argument(p, "the dataset store")
    p.add_argument("--seed", type=int, help="dataset seed (default: the scene's [noise] seed)")
    p.add_argument("--workers", type=int, help=f"local worker processes (default: one per core, here {available_cores()})")
    p.add_argument("--scheduler", metavar="ADDRESS",
                   help="Dask distributed scheduler address (e.g. tcp://host:8786): run the groups on that cluster")
    p.add_argument("--images", action=argparse.BooleanOptionalAction, default=None,
                   help="store each reconstructed image (default: the scene's [dataset] images)")
    add_progress_argument(p)
    add_solver_argument(p)


def run(args: argparse.Namespace) -> int:
    from ..dataset import generate_dataset

    use_solver(args)
    from ..io.records import final_path

    if args.out.is_file() and final_path(args.out) != args.out:
        raise ValueError(f"--out {args.out}: an existing file that is not an HDF5 store (.h5); the store would be written "
                         f"to {final_path(args.out)}: give that name, or another")
    scene = scene_from_args(args)
    if args.images is not None:
        scene = replace(scene, dataset=replace(scene.dataset, images=args.images))
    presses = None
    if args.presses is not None:
        from ..dataset.presses import read_presses

        try:
            presses = read_presses(args.presses)
        except ValueError as e:
            raise ValueError(f"--presses: {e}") from None
        k_list = presses.samples_per_press or scene.dataset.samples_per_press
        scene = replace(scene, dataset=replace(scene.dataset, samples_per_press=k_list))
        if args.n is None:
            args.n = len(presses) * k_list
        elif args.n != len(presses) * k_list:
            raise ValueError(f"--n = {args.n}: the press list {args.presses} has {len(presses)} presses x {k_list} depths "
                             f"= {len(presses) * k_list} samples (leave --n out to take them all)")
    if args.n is None:
        raise ValueError("--n: the number of labelled samples is required (or --presses CSV)")
    if args.n < 1:
        raise ValueError(f"--n = {args.n}: must be >= 1 (labelled samples)")
    if args.seed is not None and not 0 <= args.seed <= 2**63 - 1:
        raise ValueError(f"--seed = {args.seed}: must be in [0, 2^63 - 1]")
    if args.workers is not None and args.workers < 1:
        raise ValueError(f"--workers = {args.workers}: must be >= 1")
    d = scene.dataset
    k = d.samples_per_press
    where = f"Dask scheduler {args.scheduler}" if args.scheduler else f"{args.workers or available_cores()} local worker(s)"
    what = (f"the presses of {args.presses}" if presses is not None else
            f"radius {d.radius[0] * 1e3:g}-{d.radius[1] * 1e3:g} mm, depth {d.depth[0] * 1e3:g}-{d.depth[1] * 1e3:g} mm, "
            f"contact points r <= {d.r_max * 1e3:g} mm")
    print(f"jointsim dataset: scene {scene.name}, mesh {scene.mesh.preset} P{scene.mesh.element_order}, {args.n} samples "
          f"({-(-args.n // k)} presses x {k} depths), {what}, {where} -> {args.out}")
    bar = tqdm(total=args.n, unit="sample", desc="dataset", disable=progress_off(args), smoothing=0.1)

    def start(done: int, todo: int) -> None:
        if done:
            print(f"  resuming: {done} of {args.n} samples already stored", flush=True)
        bar.update(done)

    overwrite(args, final_path(args.out))
    command = ["jointsim", "dataset", *(sys.argv[2:] if sys.argv[1:2] == ["dataset"] else [])]
    with bar:
        res = generate_dataset(scene, args.n, args.out, seed=args.seed, workers=args.workers, scheduler=args.scheduler,
                               scene_toml=scene_toml(args.scene), command=command, progress=bar.update,
                               on_start=start, presses=presses)
    if res.groups_run == 0:
        print(f"  {res.path} is complete ({res.n_samples} samples): nothing to do")
    else:
        rate = (res.n_samples - res.samples_resumed) / res.wall_s * 3600
        print(f"  {res.groups_run} presses in {res.wall_s:.1f} s ({rate:.0f} samples/h), {res.rejected_draws} draw(s) "
              "rejected and redrawn")
        for why in res.rejections[:3]:
            print(f"    rejected: {why}")
    print(f"  wrote {res.path} (data_sha256 {res.data_sha256[:16]}...); command: {shlex.join(command)}")
    return 0
