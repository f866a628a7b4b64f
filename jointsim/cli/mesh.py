"""Mesh a scene's chamber (cached by content hash) and print the mesh quality report."""

from __future__ import annotations

import argparse
from pathlib import Path

from .common import add_scene_arguments, scene_from_args, stage

HELP = "mesh a scene's chamber and report its quality"


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_scene_arguments(p)
    p.add_argument("--vtu", type=Path, help="also write the mesh to this VTU file")


def run(args: argparse.Namespace) -> int:
    from ..mesh.chamber import cache_dir
    from ..instrument import deployed_chamber

    scene = scene_from_args(args)
    t: dict[str, float] = {}
    print(f"scene {scene.name}, mesh preset {scene.mesh.preset} (cache: {cache_dir()})")
    flat = scene.membrane.moulding == "flat"
    with stage("inflate the flat-moulded membrane, mesh its chamber" if flat else "mesh", t):
        ch = deployed_chamber(scene)
    print("  " + ch.quality().summary())
    areas = [e.total_area * 1e6 for e in ch.electrodes]
    print(f"  electrode areas {min(areas):.4f}-{max(areas):.4f} mm^2 (ring), ground {areas[ch.ground]:.4f} mm^2")
    if args.vtu:
        from ..io.export import write_vtu

        write_vtu(args.vtu, ch.mesh)
        print(f"  wrote {args.vtu}")
    return 0
