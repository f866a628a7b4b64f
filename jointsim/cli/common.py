"""Helpers shared by subcommands: scene loading with mesh preset and element order overrides,
stage timing."""

from __future__ import annotations

import argparse
import time
from contextlib import contextmanager
from dataclasses import replace
from typing import Iterator

from ..scene import MESH_PRESETS, SCENES_DIR, Scene, load_scene

DEFAULT_SCENE = SCENES_DIR / "paper_sensor.toml"


def add_scene_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("scene", nargs="?", default=str(DEFAULT_SCENE), help="scene TOML file (default: the paper's sensor)")
    p.add_argument("--mesh", dest="mesh_preset", choices=sorted(MESH_PRESETS), help="override the scene's mesh preset")
    p.add_argument("--order", dest="element_order", type=int, choices=(1, 2),
                   help="override the scene's mesh.element_order: P1 or P2 elements in the EIT forward model")


def add_target_size_arguments(p: argparse.ArgumentParser, default: str) -> None:
    """--target-radius-mm or --target-diameter-mm (one of them); ``default`` says in the help
    what applies without either."""
    g = p.add_mutually_exclusive_group()
    g.add_argument("--target-radius-mm", type=float, help=f"target sphere radius (default: {default})")
    g.add_argument("--target-diameter-mm", type=float, help="target sphere diameter (instead of the radius)")


def target_radius_mm(args: argparse.Namespace, default: float) -> float:
    """The target radius (mm) from :func:`add_target_size_arguments`, else ``default``."""
    if args.target_radius_mm is not None:
        radius = args.target_radius_mm
    elif args.target_diameter_mm is not None:
        radius = args.target_diameter_mm / 2
    else:
        radius = default
    if not 0 < radius <= 100:
        raise ValueError(f"target radius = {radius} mm: must be in (0, 100]")
    return radius


def scene_from_args(args: argparse.Namespace) -> Scene:
    scene = load_scene(args.scene)
    if args.mesh_preset:
        scene = scene.with_mesh_preset(args.mesh_preset)
    if getattr(args, "element_order", None):
        scene = replace(scene, mesh=replace(scene.mesh, element_order=args.element_order))
    return scene


@contextmanager
def stage(name: str, timings: dict[str, float], quiet: bool = False) -> Iterator[None]:
    if not quiet:
        print(f"  {name} ...", end="", flush=True)
    t0 = time.perf_counter()
    yield
    timings[name] = time.perf_counter() - t0
    if not quiet:
        print(f" {timings[name]:.2f} s", flush=True)
