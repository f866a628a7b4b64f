"""The ``jointsim`` command line: a thin layer over the Python API, one module per subcommand.
A subcommand module imports the package's solvers inside its ``run``, not at module level, so
that building the parser (``--help``, a mistyped flag) loads none of them (tested)."""

from __future__ import annotations

import argparse
import sys
import warnings

from .. import __version__
from ..scene import SceneError
from . import calibrate, dataset, design_study, forward, frames, indent, mesh, palpate, protocol_study, stiffness_study
from .common import check_output

SUBCOMMANDS = {"forward": forward, "mesh": mesh, "protocol-study": protocol_study, "indent": indent, "palpate": palpate,
               "dataset": dataset, "calibrate": calibrate, "stiffness-study": stiffness_study,
               "design-study": design_study, "frames": frames}


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="jointsim",
        description=(
            "Coupled mechanics-EIT simulator of a saline-filled soft tactile sensor. "
            "Scenes are TOML files (see scenes/paper_sensor.toml)."
        ),
    )
    p.add_argument("--version", action="version", version=f"jointsim {__version__}")
    sub = p.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, mod in SUBCOMMANDS.items():
        sp = sub.add_parser(name, help=mod.HELP, description=mod.__doc__)
        mod.add_arguments(sp)
        sp.set_defaults(handler=mod.run, output=getattr(mod, "OUTPUT", None), parser=sp)
    return p


# a solver that could not reach a valid state: (module, error class). Looked up where they are
# already imported, as an error of a module not loaded cannot have been raised: `jointsim --help`
# and a bad argument then answer without loading the solvers (scipy, PARDISO, Warp: seconds)
SOLVER_ERRORS = (("jointsim.mechanics.newton", "NewtonError"), ("jointsim.mesh.morph", "MeshInversionError"))


def _reported(e: Exception) -> bool:
    """Whether ``e`` is reported in one line (bad input, a solver failure, or the system refusing
    a read or write: a full disk, a permission, with its path), not a traceback."""
    loaded = tuple(getattr(sys.modules[m], name) for m, name in SOLVER_ERRORS if m in sys.modules)
    return isinstance(e, (SceneError, ValueError, OSError) + loaded)


def _warning_line(command: str):
    """warnings.showwarning as one line like the errors' (the package's advice on a setting, such as
    a membrane too coarse for its force), not a source location and its code line."""
    def show(message, category, filename, lineno, file=None, line=None):
        kind = "" if category is UserWarning else f"{category.__name__}: "
        print(f"jointsim {command}: warning: {kind}{message}", file=sys.stderr)
    return show


# flags renamed to the one convention (units in the name as in scene keys, one name per thing);
# the others' old names are prefixes of their new ones, which argparse still takes
RENAMED = {"--targets": "--target-diameters-mm", "--membrane-rim": "--rim-vertices", "--dome-rim": "--rim-vertices",
           "--membrane-layers": "--layers"}


def main(argv: list[str] | None = None) -> int:
    args, extra = build_parser().parse_known_args(argv)
    if extra:  # refused by the subcommand's parser: its usage, not the top level's
        old = [f"{a} is now {RENAMED[a.split('=')[0]]}" for a in extra if a.split("=")[0] in RENAMED]
        args.parser.error(f"unrecognized arguments: {' '.join(extra)}" + (f" ({'; '.join(old)})" if old else ""))
    try:
        with warnings.catch_warnings():
            warnings.showwarning = _warning_line(args.command)
            if args.output is not None:
                check_output(args.out, args.output)
            return int(args.handler(args) or 0)
    except Exception as e:
        if not _reported(e):
            raise
        print(f"jointsim {args.command}: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
