"""Helpers shared by subcommands: scene loading with mesh preset and element order overrides,
list flags, stage timing, output checks."""

from __future__ import annotations

import argparse
import math
import shutil
import tempfile
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path
from typing import Iterator

from ..scene import MESH_PRESETS, SCENES_DIR, Chamber, Scene, load_scene
from ..timing import timed

DEFAULT_SCENE = SCENES_DIR / "paper_sensor.toml"


def add_scene_arguments(p: argparse.ArgumentParser, eit: bool = True) -> None:
    """The scene file, its mesh preset, and (for a command that runs the EIT forward: ``eit``)
    the forward model's element order."""
    p.add_argument("scene", nargs="?", default=str(DEFAULT_SCENE), help="scene TOML file (default: the paper's sensor)")
    p.add_argument("--mesh", dest="mesh_preset", choices=sorted(MESH_PRESETS), help="override the scene's mesh preset")
    if eit:
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


def contact_within(chamber: Chamber, xy_mm: tuple[float, float], flag: str) -> None:
    """Refuse, naming ``flag``, a contact point ``xy_mm`` outside ``chamber``'s base."""
    if all(map(math.isfinite, xy_mm)) and chamber.inside([[xy_mm[0] * 1e-3, xy_mm[1] * 1e-3]], 1e-12)[0]:
        return
    if chamber.outline:
        where = "the base's outline (the rim of chamber.surface_file)"
    elif chamber.base_radius_y is None:
        where = f"the base radius {chamber.base_radius * 1e3:g} mm of the axis"
    else:
        where = f"the base's ellipse of semi-axes {chamber.base_radius * 1e3:g} x {chamber.base_radius_y * 1e3:g} mm"
    raise ValueError(f"{flag}: the contact must lie within {where}")


def add_progress_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument("--progress", action=argparse.BooleanOptionalAction, default=None,
                   help="show a progress bar (default: when the output is a terminal)")


def progress_off(args: argparse.Namespace) -> bool | None:
    """tqdm's ``disable`` for :func:`add_progress_argument`'s flag: None (a terminal decides) unless given."""
    return None if args.progress is None else not args.progress


def add_solver_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument("--solver", choices=("auto", "superlu", "pardiso", "cudss"), default=None,
                   help="sparse direct solver of every factorisation, the mechanics' and the forward's (default: "
                        "$JOINTSIM_SOLVER, else auto: by size, PARDISO where installed); cudss: on an NVIDIA GPU")


def use_solver(args: argparse.Namespace) -> None:
    """``--solver``, checked here, made this process's preferred backend and its workers' (they
    inherit the environment: linalg.preferred_backend)."""
    import os

    from ..linalg import SOLVER_VARIABLE, preferred_backend, require_backend

    if args.solver is not None:
        os.environ[SOLVER_VARIABLE] = require_backend(args.solver, "--solver")
    preferred_backend()  # a bad $JOINTSIM_SOLVER stops here, naming it


def add_overwrite_argument(p: argparse.ArgumentParser, what: str) -> None:
    p.add_argument("--overwrite", action="store_true",
                   help=f"discard what --out holds ({what}, finished or in progress, of any settings) and start afresh "
                        "(default: resume it, or refuse one of other settings)")


def overwrite(args: argparse.Namespace, store: Path) -> None:
    """With ``--overwrite``: remove the store ``store`` (and its run in progress), saying so."""
    from ..io.store import discard

    if args.overwrite and discard(store):
        print(f"  --overwrite: removed {store} and its run in progress", flush=True)


def float_list(flag: str, text: str, lo: float = -math.inf, hi: float = math.inf, *, count: int | None = None,
               increasing: bool = False) -> tuple[float, ...]:
    """The numbers of a comma-separated list flag (every list flag is written so: "8,15,30"), each
    in (``lo``, ``hi``]; ``count`` of them, or at least one; strictly ``increasing`` if asked.
    A ValueError naming ``flag`` and what is allowed."""
    try:
        vals = tuple(float(v) for v in text.split(",") if v.strip())
    except ValueError:
        vals = ()
    want = (f"{count} comma-separated numbers" if count else "comma-separated numbers") + \
        (f" in ({lo:g}, {hi:g}]" if math.isfinite(lo) or math.isfinite(hi) else "") + (", increasing" if increasing else "")
    if not vals or (count is not None and len(vals) != count) or any(not lo < v <= hi for v in vals) \
            or (increasing and any(b <= a for a, b in zip(vals, vals[1:]))):
        raise ValueError(f"{flag} = {text!r}: {want}")
    return vals


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
