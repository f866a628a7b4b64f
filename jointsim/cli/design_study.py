"""What each sensor design can measure: Cramér–Rao bounds on a target's position, depth and size
through the coupled model (membrane, chamber, CEM), over a grid of presses, for one or more
scenes side by side. Each design's derivatives are stored (resumable) in OUT/<scene>/
sensitivities.h5; its bounds table and maps beside them; OUT/summary.md compares the designs."""

from __future__ import annotations

import argparse
import shlex
import sys
import time
from dataclasses import replace
from pathlib import Path

from tqdm import tqdm

from .._cores import available_cores
from ..scene import SNR_RANGE_DB
from .common import DEFAULT_SCENE, add_overwrite_argument, add_progress_argument, float_list, overwrite, progress_off

OUTPUT = "folder"
HELP = "what each design can measure: Cramer-Rao bounds of position, depth and size, designs side by side"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("scenes", nargs="*", default=[str(DEFAULT_SCENE)], metavar="SCENE",
                   help="scene TOML files, one per design (default: the paper's sensor)")
    p.add_argument("--mesh", dest="mesh_preset", help="override every scene's mesh preset")
    p.add_argument("--out", type=Path, default=Path("out/design_study"), help="output folder (default out/design_study)")
    add_overwrite_argument(p, "each design's sensitivities.h5")
    p.add_argument("--diameters-mm", default="8,15,30", help="target sphere diameters (default 8,15,30: the paper's)")
    p.add_argument("--depths-mm", default="1,2,3", help="depths past first contact, increasing (default 1,2,3)")
    p.add_argument("--spacing-mm", type=float, default=6.0,
                   help="spacing of the polar grid of target centres (default 6: 21 centres x 3 sizes on the paper's sensor, "
                        "4 centres computed by its symmetry)")
    p.add_argument("--r-max-mm", type=float, help="grid radius (default: the outermost electrode's centre)")
    p.add_argument("--hold-frames", type=int, default=1, help="frames averaged per press (default 1)")
    p.add_argument("--contact-levels", type=int, default=3,
                   help="read each press through a membrane this many times finer about its contact (default 3: "
                        "0.25 mm edges there on a 64-rim membrane, where the size derivative has converged; 2 is ~4x "
                        "cheaper and its on-axis size bounds up to a third optimistic; 0: the scene's membrane as "
                        "meshed, whose coarse contact makes size bounds optimistic). A round dome "
                        "moulded as a cap only: other designs are read at 0, and said so")
    p.add_argument("--target-moduli-kpa", default="",
                   help="press soft (neo-Hookean) spheres of these Young's moduli, comma-separated, instead of rigid "
                        "ones: their modulus is then bounded too (each soft press costs ~10x a rigid one: use a coarse "
                        "grid, e.g. --diameters-mm 15 --ray)")
    mesh = p.add_mutually_exclusive_group()
    mesh.add_argument("--graded-target", dest="target_mesh", action="store_const", const="graded",
                      help="mesh each soft sphere graded (gmsh), its cells uniform over the refined contact zone (the "
                           "default with --target-moduli-kpa and --contact-levels >= 1)")
    mesh.add_argument("--layered-target", dest="target_mesh", action="store_const", const="layered",
                      help="mesh each soft sphere in layers instead, whose cells grow 3-4x towards the contact's edge, "
                           "coarser there than the refined membrane: its size and modulus bounds are optimistic "
                           "(results/design_study/convergence.md); the soft study before graded spheres")
    p.add_argument("--ray", action="store_true",
                   help="target centres along the +x axis, --spacing-mm apart, instead of the polar grid (a survey for "
                        "costly presses: the soft ones)")
    p.add_argument("--no-symmetry", dest="symmetric", action="store_false",
                   help="press every centre of the grid, each solved on its own membrane (default: one press per set of "
                        "centres the design's symmetries, protocol included, map onto each other, the others taking its "
                        "bounds; and a round dome's mechanics solved once per target and ring, turned to each centre)")
    p.add_argument("--snr-db", default="", help="further SNRs to tabulate, comma-separated (the scene's is always)")
    p.add_argument("--workers", type=int, help="local worker processes (default: one per core)")
    p.add_argument("--estimators", type=Path, metavar="GOALS_CSV",
                   help="a calibration's goals.csv (jointsim calibrate) to set its estimators beside the first design's bound")
    add_progress_argument(p)


def store_wall(run: dict) -> float:
    """Seconds from a store's creation to its finalisation (its sessions' wall, and any pause
    between them)."""
    from datetime import datetime

    return (datetime.fromisoformat(run["finalised"]) - datetime.fromisoformat(run["created"])).total_seconds()


def run(args: argparse.Namespace) -> int:
    from ..design.report import goals_of, required_snr, summarise, write_comparison, write_design
    from ..design.sensitivity import unrefinable
    from ..design.study import MAX_CONTACT_LEVELS, Plan, plan_presses, press_groups, press_joint_bounds, press_layout, run_design
    from ..io.records import open_records
    from ..scene import MESH_PRESETS, load_scene, scene_toml

    if args.mesh_preset is not None and args.mesh_preset not in MESH_PRESETS:
        raise ValueError(f"--mesh = {args.mesh_preset!r}: one of {sorted(MESH_PRESETS)}")
    diameters = float_list("--diameters-mm", args.diameters_mm, 0.0, 200.0)
    depths = float_list("--depths-mm", args.depths_mm, 0.0, 100.0)
    if list(depths) != sorted(set(depths)):
        raise ValueError(f"--depths-mm = {args.depths_mm!r}: increasing")
    if not args.spacing_mm > 0:
        raise ValueError(f"--spacing-mm = {args.spacing_mm:g}: must be > 0")
    if args.hold_frames < 1:
        raise ValueError(f"--hold-frames = {args.hold_frames}: must be >= 1")
    if not 0 <= args.contact_levels <= MAX_CONTACT_LEVELS:
        raise ValueError(f"--contact-levels = {args.contact_levels}: must be in 0..{MAX_CONTACT_LEVELS}")
    if args.workers is not None and args.workers < 1:
        raise ValueError(f"--workers = {args.workers}: must be >= 1")
    if args.estimators is not None and not args.estimators.is_file():
        raise ValueError(f"--estimators = {args.estimators}: no such file (a goals.csv written by jointsim calibrate)")
    lo, hi = SNR_RANGE_DB
    snrs = float_list("--snr-db", args.snr_db, lo - 1e-9, hi) if args.snr_db.strip() else ()
    moduli = float_list("--target-moduli-kpa", args.target_moduli_kpa, 0.0, 1e6) if args.target_moduli_kpa.strip() else ()
    if args.target_mesh and not (moduli and args.contact_levels):
        raise ValueError(f"--{args.target_mesh}-target: only with --target-moduli-kpa (soft spheres) and --contact-levels >= 1")
    plan = Plan(tuple(d * 1e-3 for d in diameters), tuple(d * 1e-3 for d in depths), args.spacing_mm * 1e-3,
                None if args.r_max_mm is None else args.r_max_mm * 1e-3, hold_frames=args.hold_frames,
                contact_levels=args.contact_levels, target_moduli=tuple(e * 1e3 for e in moduli), ray=args.ray,
                symmetric=args.symmetric, ring_mechanics=args.symmetric, graded_target=args.target_mesh != "layered")
    scenes = []
    for path in args.scenes:
        scene = load_scene(path)
        if args.mesh_preset:
            scene = scene.with_mesh_preset(args.mesh_preset)
        if depths[-1] * 1e-3 >= 0.9 * scene.chamber.dome_height:
            raise ValueError(f"--depths-mm: {depths[-1]:g} mm is past 0.9 x the dome height of {path}")
        scenes.append((path, scene, plan))
        if plan.contact_levels and unrefinable(scene):
            print(f"jointsim design-study: {scene.name}: read at --contact-levels 0 ({unrefinable(scene)}); "
                  "its size bounds are optimistic")
            scenes[-1] = (path, scene, replace(plan, contact_levels=0))
    names = [s.name for _, s, _ in scenes]
    if len(set(names)) != len(names):
        raise ValueError(f"scenes: two designs share a name ({names}); give each scene its own name")
    command = "jointsim design-study " + " ".join(shlex.quote(a) for a in sys.argv[2:]) if sys.argv[1:2] == ["design-study"] else "jointsim design-study"
    rows, needed, timings, where, joint, joint_moduli, pressed = [], {}, {}, {}, {}, {}, {}
    for path, scene, plan in scenes:
        n, lay = len(plan_presses(scene, plan)), press_layout(scene, plan)
        solves = len(press_groups(scene, plan))
        pressed[scene.name] = n, n * len(lay.grid) // len(lay.computed), solves
        print(f"jointsim design-study: {scene.name} (mesh {scene.mesh.preset}, membrane refined {plan.contact_levels}x about "
              f"the contact), {n} presses x {len(depths)} depths, standing for {pressed[scene.name][1]} by symmetry"
              + (f"; {solves} mechanical solves, one per target and ring" if solves < n else ""))
        todo = [0]  # presses this run computes (the rest were stored)
        t0 = time.perf_counter()
        with tqdm(total=n, unit="press", desc=f"design study {scene.name}", disable=progress_off(args)) as bar:
            def started(done: int, left: int) -> None:
                bar.update(done)
                todo[0] = left
            overwrite(args, args.out / scene.name / "sensitivities.h5")
            missed: list[str] = []
            h5 = run_design(scene, plan, args.out / scene.name / "sensitivities.h5", workers=args.workers,
                            scene_toml=scene_toml(path), progress=bar.update, on_start=started,
                            on_missed=lambda i, why: missed.append(f"press {i}: {why}"))
        if missed:
            print(f"  {len(missed)} press(es) the mechanics could not take, stored as not reached; the first: {missed[0]}")
        workers = min(args.workers or available_cores(), max(todo[0], 1))
        wall = time.perf_counter() - t0
        study = open_records(h5)  # read once: every table and SNR below is computed from it
        if todo[0] == 0:  # nothing computed here: the cost is the run that wrote the store (its workers not recorded)
            workers, wall = None, store_wall(study.run)
        timings[scene.name] = (study["seconds"], wall, todo[0] or len(study["seconds"]), workers, study.data_sha256)
        frames = {"reference_frames": plan.reference_frames, "hold_frames": plan.hold_frames}
        written, summaries, where[scene.name] = write_design(args.out / scene.name, scene, study, snrs, **frames)
        rows += summaries
        needed[scene.name] = required_snr(study, scene, goals_of(where[scene.name]), **frames)
        jb = press_joint_bounds(study, scene, **frames)
        joint[scene.name] = summarise(scene.name, jb)
        joint_moduli[scene.name] = [(f"E {e * 1e-3:g} kPa", summarise(scene.name, jb, modulus=e)) for e in plan.target_moduli]
        s = summaries[0][0]
        print(f"  at {s.snr_db:g} dB, efficient median error (nuisances marginalised): position "
              f"{s.median['position_marginal'] * 1e3:.3g} mm, depth {s.median['depth_marginal'] * 1e3:.3g} mm, "
              f"diameter {s.median['diameter_marginal'] * 1e3:.3g} mm ({s.reached}/{s.presses} reached)")
    est = None if args.estimators is None else (scenes[0][1].name, args.estimators)
    written = write_comparison(args.out, rows, needed, command, timings, est, where,
                               {scene.name: plan.contact_levels for _, scene, plan in scenes}, joint, joint_moduli, pressed)
    print(f"  wrote {written[0]}")
    return 0
