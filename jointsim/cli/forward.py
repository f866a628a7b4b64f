"""Read a scene's sensor at rest: the instrument built (membrane inflated, chamber meshed and
cached, the complete electrode model solved) and one frame of the untouched sensor taken by its
frame step; writes the standing voltages (clean and one noisy frame), the Jacobian and the
reconstruction matrix on the voxel grid, the potentials as VTU for ParaView and an EIDORS-style
.mat file."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from .common import add_scene_arguments, scene_from_args, stage

OUTPUT = "folder"  # what --out names (checked before any work: cli.common.check_output)
HELP = "the sensor at rest: standing voltages, Jacobian, reconstruction matrix, VTU and .mat"


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_scene_arguments(p)
    p.add_argument("--out", type=Path, default=Path("out/forward"), help="output folder (default: out/forward)")
    p.add_argument("--skip", type=int, help="override the scene's skip-N injection protocol")
    p.add_argument("--voxels", type=int, help="reconstruction voxels in the chamber (default: the scene's [reconstruction] cells, 7000)")
    p.add_argument("--no-jacobian", action="store_true", help="skip the Jacobian and the reconstruction matrix")
    p.add_argument("--solver", default="auto", help="sparse direct backend: auto (default: $JOINTSIM_SOLVER, else pardiso if installed), pardiso, cholmod, superlu, cudss (an NVIDIA GPU)")


def run(args: argparse.Namespace) -> int:
    from ..eit.protocol import scene_protocol
    from ..studies.rest import read_at_rest, write_at_rest

    from ..linalg import preferred_backend, require_backend

    scene = scene_from_args(args)
    require_backend(args.solver, "--solver")
    preferred_backend()
    n = scene.electrodes.n_active
    if args.skip is not None and not 0 <= args.skip <= n // 2:
        raise ValueError(f"--skip = {args.skip}: must be in [0, {n // 2}] for {n} driven electrodes")
    # the scene's own protocol (its patterns given as data too) unless --skip overrides it
    given = scene.drive.stim is not None and args.skip is None
    drive = "the scene's patterns" if given else f"skip-{scene.drive.skip if args.skip is None else args.skip}"
    if args.voxels is not None and args.voxels < 1:
        raise ValueError(f"--voxels = {args.voxels}: must be >= 1")
    out: Path = args.out
    t: dict[str, float] = {}
    print(f"jointsim forward: scene {scene.name}, mesh preset {scene.mesh.preset}, P{scene.mesh.element_order} elements, {drive}")
    zf = scene.electrodes.contact_impedance_by_freq
    protocol = scene_protocol(scene, args.skip)
    what = ("membrane inflated, chamber mesh (cached after the first run)" + (" on the flat moulding" if scene.membrane.moulding == "flat" else "")
            + f", {protocol.n_el} lead fields" + (f" per carrier ({len(zf)} contact impedances)" if zf is not None else "")
            + ("" if args.no_jacobian else ", Jacobian and lambda"))
    with stage(what, t):
        inst, reading = read_at_rest(scene, protocol, imaging=not args.no_jacobian, cells=args.voxels, backend=args.solver)
    print("  " + inst.reference.quality().summary())
    v = reading.voltages_clean
    print(f"  {v.size} voltages: mean |V| {np.abs(v).mean() * 1e3:.2f} mV, max |V| {np.abs(v).max() * 1e3:.1f} mV; "
          f"noise std {inst.readout.noise_std * 1e6:.2f} uV at {scene.noise.snr_db} dB")
    try:
        with stage("write outputs", {}):
            write_at_rest(out, inst, reading, t)
    finally:
        inst.free()
    print(f"  wrote {out}/forward.npz, chamber.vtu, forward_eidors.mat, forward.json")
    return 0
