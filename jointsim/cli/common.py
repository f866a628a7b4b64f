"""Helpers shared by subcommands: scene loading with mesh preset and element order overrides,
stage timing."""

from __future__ import annotations

import argparse
import shutil
import tempfile
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path
from typing import Iterator

from ..scene import MESH_PRESETS, SCENES_DIR, Scene, load_scene
from ..timing import timed

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
    """:func:`~jointsim.timing.timed`, announced on stdout ("  name ... 1.23 s")."""
    if not quiet:
        print(f"  {name} ...", end="", flush=True)
    with timed(timings, name):
        yield
    if not quiet:
        print(f" {timings[name]:.2f} s", flush=True)


def check_output(path: Path, kind: str, flag: str = "--out") -> None:
    """Refuse, before any work, an output that cannot be written: ``kind`` "folder" (written
    into) or "file" (an .h5 store, resumed when it exists). Raises ValueError naming ``flag``,
    the path and why. Probes by making and removing a folder in the nearest existing ancestor,
    so nothing is left behind and a read-only or virtual file system (/proc) is found out."""
    path = Path(path)
    if kind == "file":
        if path.is_dir():
            raise ValueError(f"{flag} {path}: is a folder; give the store's file name (e.g. {path / 'dataset.h5'})")
        if path.exists() and not path.is_file():
            raise ValueError(f"{flag} {path}: exists and is not a regular file")
    elif path.exists() and not path.is_dir():
        raise ValueError(f"{flag} {path}: exists and is not a folder")
    ancestor = (path.parent if kind == "file" else path).absolute()
    while not ancestor.exists():
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        raise ValueError(f"{flag} {path}: {ancestor} is a file, not a folder")
    try:
        shutil.rmtree(tempfile.mkdtemp(prefix=".jointsim-probe-", dir=ancestor))
    except OSError as e:
        raise ValueError(f"{flag} {path}: cannot write in {ancestor} ({e.strerror or e})") from None
