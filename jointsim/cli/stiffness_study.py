"""How far a target's Young's modulus moves the force, displaced volume and contact area of an
on-axis press, against the membrane's own modulus: the sensitivities S_E and S_μ and the modulus
error they imply (the physics limit of elastography with this sensor). Writes CSV, JSON,
Markdown and PNG to --out."""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path

from tqdm import tqdm

from ..studies.stiffness_sensitivity import DEFAULT_DEPTHS_MM, DEFAULT_MODULI_KPA, run_study, write_report
from .common import add_progress_argument, add_scene_arguments, add_target_size_arguments, float_list, progress_off, scene_from_args, target_radius_mm

OUTPUT = "folder"  # what --out names (checked before any work: cli.common.check_output)
HELP = "stiffness identifiability: force sensitivity to target and membrane moduli"


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_scene_arguments(p, eit=False)
    p.add_argument("--out", type=Path, default=Path("out/stiffness_sensitivity"), help="output folder (default out/stiffness_sensitivity; the committed results are written with --out results/stiffness_sensitivity)")
    add_target_size_arguments(p, "7.5 mm")
    p.add_argument("--moduli-kpa", metavar="E,E,...", default=",".join(f"{v:g}" for v in DEFAULT_MODULI_KPA),
                   help="soft target moduli, comma-separated (a rigid one is added)")
    p.add_argument("--depths-mm", metavar="D,D,...", default=",".join(f"{v:g}" for v in DEFAULT_DEPTHS_MM),
                   help="stage depths past first contact, comma-separated")
    p.add_argument("--workers", type=int, default=1, help="local worker processes (default 1)")
    add_progress_argument(p)


def run(args: argparse.Namespace) -> int:
    scene = scene_from_args(args)
    radius = target_radius_mm(args, 7.5)
    moduli = float_list("--moduli-kpa", args.moduli_kpa, 0.0)
    if len(moduli) < 2:
        raise ValueError(f"--moduli-kpa = {args.moduli_kpa!r}: at least two moduli, each > 0 kPa")
    height = scene.chamber.dome_height * 1e3
    depths = float_list("--depths-mm", args.depths_mm, 0.0, height * (1 - 1e-9), increasing=True)
    print(f"jointsim stiffness-study: scene {scene.name}, target r = {radius:g} mm")
    with tqdm(unit="press", desc="stiffness study", disable=progress_off(args)) as bar:

        def progress(done: int, total: int) -> None:
            bar.total = total
            bar.update(done - bar.n)

        result = run_study(scene, radius * 1e-3, list(moduli), list(depths), args.workers, progress=progress)
    command = "jointsim stiffness-study " + " ".join(shlex.quote(a) for a in sys.argv[2:]) if sys.argv[1:2] == ["stiffness-study"] else "jointsim stiffness-study"
    written = write_report(result, args.out, command)
    print(f"  wrote {len(written)} files to {args.out}")
    return 0
