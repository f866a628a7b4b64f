"""Virtual palpation (paper III.C, Fig. 4): the MuJoCo bench rig presses each target into the FEM
dome at 50 Hz; every frame records the 256 noisy voltages, pose, contact force, displaced
volume, the difference image and its metrics. Writes OUT/palpation.h5 (all frames, with the
scene, settings, seed and package versions), a VTU time series (OUT/*.pvd, OUT/vtu/), Fig. 4-like
PNGs and OUT/summary.{json,md}. An interrupted run resumes where it stopped when run again with
the same settings; nothing is half-written."""

from __future__ import annotations

import argparse
import json
import os
import shlex
import sys
from dataclasses import replace
from pathlib import Path

from tqdm import tqdm

from ..scene import PALPATION_MODES, membrane_layers, membrane_rim_vertices, scene_toml
from .common import (add_overwrite_argument, add_progress_argument, add_solver_argument, add_scene_arguments, contact_within, float_list,
                     overwrite, progress_off, scene_from_args, use_solver)

OUTPUT = "folder"  # what --out names (checked before any work: cli.common.check_output)
HELP = "virtual palpation with the MuJoCo rig (paper Fig. 4): HDF5 frames, VTU series, PNG, summary"


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_scene_arguments(p)
    p.add_argument("--out", type=Path, default=Path("out/palpation"), help="output folder (default out/palpation)")
    add_overwrite_argument(p, "palpation.h5")
    p.add_argument("--target-diameters-mm", metavar="D,D,...",
                   help="target diameters, comma-separated (default: the scene's [palpation], 8,15,30)")
    p.add_argument("--depth-mm", type=float, help="indentation past first contact (position and compliant modes)")
    p.add_argument("--mode", choices=PALPATION_MODES, help="stage control (default: the scene's, position)")
    p.add_argument("--force-n", type=float, help="press force (force mode)")
    p.add_argument("--speed-mm-per-s", type=float, help="stage speed (default 25)")
    p.add_argument("--hold-s", type=float, help="hold at depth or force")
    p.add_argument("--xy-mm", metavar="X,Y", help="where the target comes down (default 0,0)")
    p.add_argument("--seed", type=int, help="noise seed (default: the scene's [noise] seed)")
    p.add_argument("--rim-vertices", type=int, help="membrane resolution: vertices on its rim (default: the scene's)")
    p.add_argument("--layers", type=int, help="membrane element layers through the thickness (default: the scene's)")
    p.add_argument("--device", default="cpu", help="Warp device of the membrane's element kernel: cpu (default) or cuda / cuda:N where a GPU is")
    p.add_argument("--vtu-every", type=int, default=5, help="write the VTU series every N frames of each target and its last (0: none; default 5)")
    p.add_argument("--calibration", type=Path, metavar="MAP",
                   help="calibration map (jointsim calibrate): adds calibrated position, depth, size and stiffness per frame "
                        "(OUT/calibrated.csv, summary.json); refused when built for another sensor")
    add_progress_argument(p)
    add_solver_argument(p)


def configure(args: argparse.Namespace):
    """The scene with the command line's overrides applied (validated as scene values)."""
    scene = scene_from_args(args)
    m = scene.membrane
    if args.rim_vertices is not None:
        m = replace(m, rim_vertices=membrane_rim_vertices(args.rim_vertices, m.element, "--rim-vertices"))
    if args.layers is not None:
        m = replace(m, layers=membrane_layers(args.layers, "--layers"))
    spec = scene.palpation
    c = scene.chamber
    if args.target_diameters_mm is not None:
        d = float_list("--target-diameters-mm", args.target_diameters_mm, 0.0, 10 * c.base_radius * 1e3)
        spec = replace(spec, target_radii=tuple(v * 1e-3 / 2 for v in d))
    if args.mode is not None:
        spec = replace(spec, mode=args.mode)
    if args.depth_mm is not None:
        hi = c.dome_height * 1e3  # as palpation.depth_mm: beyond it the sphere would press the membrane onto the base
        if not 0 < args.depth_mm <= hi:
            raise ValueError(f"--depth-mm = {args.depth_mm}: must be in (0, {hi:g}] mm (the dome's height)")
        spec = replace(spec, depth=args.depth_mm * 1e-3)
    if args.force_n is not None:
        if not 0 < args.force_n <= 10:
            raise ValueError(f"--force-n = {args.force_n}: must be in (0, 10] N")
        spec = replace(spec, force=args.force_n)
    if args.speed_mm_per_s is not None:
        if not 0 < args.speed_mm_per_s <= 1000:
            raise ValueError(f"--speed-mm-per-s = {args.speed_mm_per_s}: must be in (0, 1000] mm/s")
        spec = replace(spec, speed=args.speed_mm_per_s * 1e-3)
    if args.hold_s is not None:
        if not 0 <= args.hold_s <= 60:
            raise ValueError(f"--hold-s = {args.hold_s}: must be in [0, 60] s")
        spec = replace(spec, hold=args.hold_s)
    if args.xy_mm is not None:
        xy = float_list("--xy-mm", args.xy_mm, count=2)
        contact_within(c, xy, f"--xy-mm = {args.xy_mm!r}")
        spec = replace(spec, xy=(xy[0] * 1e-3, xy[1] * 1e-3))
    noise = scene.noise
    if args.seed is not None:
        if not 0 <= args.seed <= 2**63 - 1:
            raise ValueError(f"--seed = {args.seed}: must be in [0, 2^63 - 1] (as [noise] seed)")
        noise = replace(noise, seed=args.seed)
    return replace(scene, membrane=m, palpation=spec, noise=noise)


def run(args: argparse.Namespace) -> int:
    # threaded MKL (PARDISO, in the mechanics and the forward solves) is not reproducible from run
    # to run unless its conditional numerical reproducibility is on; a resumed run must give the
    # frames an uninterrupted one gives. Read by MKL when it first runs, i.e. after this line.
    os.environ.setdefault("MKL_CBWR", "AUTO")
    use_solver(args)
    from ..mechanics.fem import warp_device
    from ..palpation.job import palpate
    from ..palpation.pipeline import program_params
    from ..palpation.report import summarise

    scene = configure(args)
    if args.vtu_every < 0:
        raise ValueError(f"--vtu-every = {args.vtu_every}: must be >= 0")
    device = warp_device(args.device, "--device")
    cmap = None
    if args.calibration is not None:  # refused before any work when built for another sensor
        from ..calibration import load_map

        cmap = load_map(args.calibration)
        cmap.check_scene(scene, f"calibration map {args.calibration}")
    spec = scene.palpation
    out: Path = args.out
    command = "jointsim palpate " + " ".join(shlex.quote(a) for a in (sys.argv[2:] if sys.argv[1:2] == ["palpate"] else []))
    n = program_params(scene, spec)["n_records"]
    diam = ", ".join(f"{2e3 * r:g}" for r in spec.target_radii)
    print(f"jointsim palpate: scene {scene.name}, mesh {scene.mesh.preset} P{scene.mesh.element_order}, {spec.mode} mode, targets {diam} mm, "
          f"{n} frames at {scene.noise.frame_rate_hz:g} Hz -> {out}")
    overwrite(args, out / "palpation.h5")
    with tqdm(total=n, unit="frame", desc="palpation", disable=progress_off(args)) as bar:
        def progress(k, f):
            bar.update(k)
            if f is not None:
                bar.set_postfix_str(f"target {2e3 * f.segment.radius:g} mm, depth {f.record['depth'] * 1e3:.2f} mm, "
                                    f"F {f.state.force[2] * 1e3:.1f} mN", refresh=False)

        job = palpate(scene, out, scene_text=scene_toml(args.scene), command=command, device=device,
                      vtu_every=args.vtu_every, say=tqdm.write, progress=progress)
    rec, written = job.records, job.written
    for r in summarise(rec):
        print(f"  {r['diameter_mm']:g} mm: depth {r['max_depth_mm']:.2f} mm, F {r['max_force_mN']:.1f} mN, "
              f"displaced {r['max_displaced_mm3']:.0f} mm^3, peak RMS dV {r['peak_rms_dv_uV']:.0f} uV, "
              f"image diameter {r['peak_image_diameter_mm']:.1f} mm, sum sigma {r['peak_sum_sigma']:.3g}")
    if cmap is not None:
        from ..calibration.apply import write_calibrated

        written += write_calibrated(out, rec, cmap, args.calibration)
        for r in json.loads((out / "calibrated.json").read_text())["targets"]:
            why = r.get("why_nan", {})
            size = f"diameter {r['cal_diameter_mm']:.1f} mm" if "diameter" not in why else f"diameter n/a ({why['diameter']})"
            modulus = f"modulus {r['modulus_kPa']:.3g} kPa" if "modulus" not in why else f"modulus n/a ({why['modulus']})"
            print(f"  calibrated, target {r['target']} at its deepest frame: x {r['cal_x_mm']:.2f} y {r['cal_y_mm']:.2f} mm, "
                  f"depth {r['cal_depth_mm']:.2f} mm (true {r['true_depth_mm']:.2f}), {size} (true {r['true_diameter_mm']:.1f}), "
                  f"{modulus}" + (f"; {r['outside_trained_region']} outside the map's trained region" if r["outside_trained_region"] else ""))
    print(f"  wrote {out / 'palpation.h5'}, {len(written)} report files to {out}")
    return 0
