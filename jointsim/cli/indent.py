"""Force–indentation sweep of the dome membrane (hyperelastic FEM in Warp): a spherical target
(rigid, or soft as the scene's [target] says) comes down vertically at (x, y) in steps past
first contact; writes the curve (CSV, PNG) and each step's deformed membrane (VTU) and inner
chamber surface (npz) to --out."""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

from tqdm import tqdm

from ..scene import membrane_layers, membrane_rim_vertices
from .common import (
    add_progress_argument, add_scene_arguments, add_target_size_arguments, contact_within, progress_off, scene_from_args,
    target_radius_mm,
)

OUTPUT = "folder"  # what --out names (checked before any work: cli.common.check_output)
HELP = "force-indentation sweep of the dome membrane (FEM): CSV, PNG, VTU"


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_scene_arguments(p, eit=False)
    p.add_argument("--out", type=Path, default=Path("out/indentation"), help="output folder (default out/indentation; the committed results are written with --out results/indentation)")
    add_target_size_arguments(p, "the scene's [target]")
    p.add_argument("--x-mm", type=float, default=0.0, help="contact position x (default 0)")
    p.add_argument("--y-mm", type=float, default=0.0, help="contact position y (default 0)")
    p.add_argument("--depth-mm", type=float, default=3.0, help="final indentation past first contact (default 3)")
    p.add_argument("--step-mm", type=float, default=0.5, help="step (default 0.5: one 50 Hz frame at 25 mm/s)")
    p.add_argument("--rim-vertices", type=int, help="membrane resolution: vertices on the rim (default: the scene's membrane.rim_vertices)")
    p.add_argument("--layers", type=int, help="element layers through the thickness (default: the scene's)")
    p.add_argument("--device", default="cpu", help="Warp device of the element kernel: cpu (default) or cuda / cuda:N where a GPU is")
    add_progress_argument(p)


def run(args: argparse.Namespace) -> int:
    from ..mechanics.fem import warp_device
    from ..studies.indentation import indentation_sweep

    scene = scene_from_args(args)
    contact_within(scene.chamber, (args.x_mm, args.y_mm), f"--x-mm, --y-mm = {args.x_mm:g}, {args.y_mm:g}")
    if not args.depth_mm > 0:
        raise ValueError(f"--depth-mm = {args.depth_mm}: must be > 0")
    device = warp_device(args.device, "--device")
    radius = target_radius_mm(args, scene.target.radius * 1e3)
    if not 0 < args.step_mm <= args.depth_mm:
        raise ValueError(f"--step-mm = {args.step_mm}: must be in (0, --depth-mm = {args.depth_mm}]")
    if args.rim_vertices is not None:
        scene = replace(scene, membrane=replace(scene.membrane, rim_vertices=membrane_rim_vertices(args.rim_vertices, scene.membrane.element, "--rim-vertices")))
    if args.layers is not None:
        scene = replace(scene, membrane=replace(scene.membrane, layers=membrane_layers(args.layers, "--layers")))
    out: Path = args.out
    steps = int(round(args.depth_mm / args.step_mm))
    with tqdm(total=steps, unit="step", desc="indentation", disable=progress_off(args)) as bar:
        rows = indentation_sweep(scene, radius, (args.x_mm, args.y_mm), args.depth_mm, args.step_mm, out, device=device,
                                 progress=bar.update, announce=lambda s: print(f"jointsim indent: scene {scene.name}, {s}"))
    for r in rows:
        print(f"  {r['depth_mm']:.2f} mm: F {r['force_N'] * 1e3:7.2f} mN, displaced {r['displaced_volume_mm3']:6.1f} mm^3, "
              f"{r['newton_iterations']} Newton iterations")
    print(f"  wrote {out}/force_indentation.csv, .png, membrane_*.vtu, inner_surface_*.npz")
    return 0
