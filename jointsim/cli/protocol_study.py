"""Reproduce the paper's protocol-optimisation study (Fig. 2 G–H): skip-0…8 with a geometric
indentation at several contact positions; RMS δV, J_sens, CoM error, Σσ and the images, plus
the mesh-noise floor of meshing. Writes PNG, CSV, Markdown, VTU and JSON to --out."""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path

from tqdm import tqdm

from ..scene import SNR_RANGE_DB
from .common import add_progress_argument, add_scene_arguments, add_target_size_arguments, progress_off, scene_from_args, target_radius_mm

OUTPUT = "folder"  # what --out names (checked before any work: cli.common.check_output)
HELP = "the paper's protocol study (Fig. 2 G-H): skip-0..8 metrics and images"


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_scene_arguments(p)
    p.add_argument("--out", type=Path, default=Path("out/protocol_study"), help="output folder (default out/protocol_study; the committed results are written with --out results/protocol_study)")
    add_target_size_arguments(p, "7.5 mm")
    p.add_argument("--depth-mm", type=float, default=2.0, help="indentation beyond first contact (default 2)")
    p.add_argument("--snr-db", type=float, help="noise level (default: the scene's)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--cells", type=int, default=7000, help="reconstruction voxels in the bounding box (default 7000)")
    p.add_argument("--lambda-method", choices=["kfold", "loo", "gcv", "lcurve"], default="kfold")
    p.add_argument("--skips", help="skip-N protocols to compare, comma-separated (default: 0 to n/2 for the layout's n electrodes)")
    p.add_argument("--no-mesh-floor", action="store_true", help="skip the mesh-noise floor (two extra meshings)")
    add_progress_argument(p)


def run(args: argparse.Namespace) -> int:
    from ..studies.protocol_study import StudyConfig, run_protocol_study
    from ..studies.report import write_study

    scene = scene_from_args(args)
    radius = target_radius_mm(args, 7.5)
    if not 0 < args.depth_mm < scene.chamber.dome_height * 1e3:
        raise ValueError(f"--depth-mm = {args.depth_mm}: must be in (0, {scene.chamber.dome_height * 1e3:g}) (the dome height)")
    if args.cells < 100:
        raise ValueError(f"--cells = {args.cells}: must be >= 100")
    lo, hi = SNR_RANGE_DB
    if args.snr_db is not None and not lo <= args.snr_db <= hi:
        raise ValueError(f"--snr-db = {args.snr_db:g}: must be in [{lo:g}, {hi:g}] dB (as [noise] snr_db)")
    n = scene.electrodes.n_active
    skips = tuple(range(n // 2 + 1))
    if args.skips is not None:
        try:
            skips = tuple(int(v) for v in args.skips.split(",") if v.strip())
        except ValueError:
            skips = ()
        if not skips or any(not 0 <= k <= n // 2 for k in skips):
            raise ValueError(f"--skips = {args.skips!r}: comma-separated integers in [0, {n // 2}] for {n} driven electrodes")
    cfg = StudyConfig(
        skips=skips,
        target_radius=radius * 1e-3,
        depth=args.depth_mm * 1e-3,
        snr_db=scene.noise.snr_db if args.snr_db is None else args.snr_db,
        seed=args.seed,
        n_cells=args.cells,
        lambda_method=args.lambda_method,
        mesh_floor=not args.no_mesh_floor,
    )
    steps = 2 + len(cfg.positions) + len(cfg.skips) + int(cfg.mesh_floor)
    print(f"jointsim protocol-study: scene {scene.name}, mesh {scene.mesh.preset}, target r = {radius:g} mm, depth {args.depth_mm:g} mm")
    with tqdm(total=steps, unit="step", desc="protocol study (mesh, fields, positions, skips, floor)", disable=progress_off(args)) as bar:
        result = run_protocol_study(scene, cfg, progress=bar.update)
    command = "jointsim protocol-study " + " ".join(shlex.quote(a) for a in sys.argv[2:]) if sys.argv[1:2] == ["protocol-study"] else "jointsim protocol-study"
    written = write_study(result, args.out, command)
    for r in result.table():
        print(
            f"  skip {r['skip']}: RMS dV {r['rms_dV_uV']:7.1f} uV ({r['snr_dV_dB']:.1f} dB over noise), "
            f"CoM err {r['com_error_mm_mean']:.2f} mm (max {r['com_error_mm_max']:.2f}), sum sigma {r['sum_sigma']:.3g}"
        )
    for k, v in result.floor.items():
        print(f"  mesh-noise floor ({k}): " + ", ".join(f"skip {s}: {db:.1f} dB" for s, db in v.items()))
    print(f"  wrote {len(written)} files to {args.out}")
    return 0
