"""Run the EIT forward model on a scene's undeformed chamber: mesh (cached), solve the complete
electrode model once, and write the 256 standing voltages (clean and noisy), the Jacobian on
the coarse voxel grid, the potentials as VTU for ParaView and an EIDORS-style .mat file."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from .. import __version__
from .common import add_scene_arguments, scene_from_args, stage

OUTPUT = "folder"  # what --out names (checked before any work: cli.common.check_output)
HELP = "EIT forward solve of a scene's chamber: voltages, Jacobian, VTU and .mat"


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_scene_arguments(p)
    p.add_argument("--out", type=Path, default=Path("out/forward"), help="output folder (default: out/forward)")
    p.add_argument("--skip", type=int, help="override the scene's skip-N injection protocol")
    p.add_argument("--voxels", type=int, default=7000, help="reconstruction voxels in the chamber for the Jacobian (default 7000)")
    p.add_argument("--no-jacobian", action="store_true", help="skip the Jacobian")
    p.add_argument("--solver", default="auto", help="sparse direct backend: auto (default: pardiso if installed), pardiso, cholmod, superlu")


def run(args: argparse.Namespace) -> int:
    from ..eit.forward import ForwardModel
    from ..eit.jacobian import jacobian
    from ..eit.noise import add_noise, noise_std
    from ..eit.protocol import skip_protocol
    from ..io.export import atomic_path, write_mat, write_npz, write_vtu
    from ..palpation.pipeline import deployed_chamber
    from ..reconstruction.grid import ChamberGrid

    scene = scene_from_args(args)
    skip = scene.drive.skip if args.skip is None else args.skip
    if not 0 <= skip <= scene.electrodes.count // 2:
        raise ValueError(f"--skip = {skip}: must be in [0, {scene.electrodes.count // 2}]")
    if args.voxels < 1:
        raise ValueError(f"--voxels = {args.voxels}: must be >= 1")
    out: Path = args.out
    t: dict[str, float] = {}
    print(f"jointsim forward: scene {scene.name}, mesh preset {scene.mesh.preset}, P{scene.mesh.element_order} elements, skip-{skip}")
    flat = scene.membrane.moulding == "flat"
    with stage("chamber mesh (cached after the first run)" + (", on the flat moulding inflated" if flat else ""), t):
        ch = deployed_chamber(scene)
    print("  " + ch.quality().summary())
    protocol = skip_protocol(scene.electrodes.count, skip, scene.drive.current)
    model = ForwardModel.from_chamber(ch, scene, backend=args.solver)
    sigma = np.full(ch.mesh.n_tets, scene.saline.conductivity)
    with stage("factorise + 16 lead fields", t):
        fields = model.solve(sigma)
    zf = scene.electrodes.contact_impedance_by_freq
    if zf is None:
        v = fields.voltages(protocol)
    else:
        # FDM: injection s runs on carrier s, each carrier with its own contact impedances
        z_by_freq = np.column_stack([np.asarray(zf), np.full(len(zf), scene.electrodes.ground_contact_impedance)])
        with stage(f"per-carrier contact impedance ({len(zf)} factorisations)", t):
            v = model.voltages_by_frequency(sigma, protocol, z_by_freq, np.arange(protocol.n_stim) % len(zf))
    noisy = add_noise(v, scene.noise.snr_db, scene.noise.seed)
    std = noise_std(v, scene.noise.snr_db)
    print(
        f"  {v.size} voltages: mean |V| {np.abs(v).mean() * 1e3:.2f} mV, max |V| {np.abs(v).max() * 1e3:.1f} mV; "
        f"noise std {std * 1e6:.2f} uV at {scene.noise.snr_db} dB"
    )
    arrays = dict(voltages=v, voltages_noisy=noisy, stim=protocol.stim, meas=protocol.meas, transfer=fields.transfer)
    J = None
    if not args.no_jacobian:
        grid = ChamberGrid.over(ch.mesh, args.voxels)
        with stage(f"Jacobian on {grid.n_cells} voxels", t):
            J = jacobian(fields, protocol, coarse=grid.C)
        arrays.update(
            jacobian_voxels=J,
            voxel_active=grid.active,
            voxel_volume=grid.volume,
            voxel_origin=grid.grid.origin,
            voxel_spacing=grid.grid.spacing,
            voxel_shape=np.array(grid.grid.shape),
        )
    with stage("write outputs", t):
        write_npz(out / "forward.npz", **arrays)
        pot = fields.potentials(protocol)
        write_vtu(out / "chamber.vtu", ch.mesh, {"sigma": sigma}, {"potential_inj": pot})
        write_mat(
            out / "forward_eidors.mat", ch.mesh, sigma, v, protocol.stim, protocol.meas,
            ch.electrodes, model.z, ch.ground,
        )
        meta = {
            "jointsim": __version__,
            "scene": scene.to_dict(),
            "skip": skip,
            "mesh_key": ch.key,
            "quality": ch.quality().__dict__,
            "timings_s": t,
        }
        with atomic_path(out / "forward.json") as tmp:
            tmp.write_text(json.dumps(meta, indent=2, default=float))
    print(f"  wrote {out}/forward.npz, chamber.vtu, forward_eidors.mat, forward.json")
    return 0
