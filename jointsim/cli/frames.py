"""Measured frames in: voltages from a real sensor (or another simulator) in CSV, HDF5 or
EIDORS .mat, imaged with the scene's instrument against the mean of reference frames of the
untouched sensor, with the paper's image metrics per frame and, given a calibration map, its
estimates (position, depth, size; flagged outside the map's trained region); --fit-reference
fits the sensor's conductivity, contact impedances and electrode positions to the reference
frames; --refine fits the frames, one press at several depths, through the simulator from the
map's estimate (jointsim.calibration.refine: minutes, not milliseconds); --known-presses fits
the membrane's modulus scale to the forces a rig read on known presses
(jointsim.calibration.membrane_fit). The channel order
is voltages[s * n_meas_per_stim + m] (measurement m of injection s); patterns carried by the
files are checked against the scene's protocol first. Writes OUT/frames.csv, OUT/images.vtu
(the first frames' images) and OUT/summary.json."""

from __future__ import annotations

import argparse
import hashlib
import json
import math
from pathlib import Path

from .common import add_progress_argument, add_scene_arguments, progress_off, scene_from_args

OUTPUT = "folder"  # what --out names (checked before any work: cli.common.check_output)
HELP = "image measured frames (CSV, HDF5, EIDORS .mat) with the scene's instrument; apply a calibration map"
VTU_FRAMES = 20  # frames whose images go into images.vtu (all are in frames.csv)


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_scene_arguments(p)
    p.add_argument("--frames", type=Path, required=True, help="the measured frames (.csv, .h5, .mat)")
    p.add_argument("--reference", type=Path, required=True,
                   help="frames of the untouched sensor (.csv, .h5, .mat): their mean is the reference")
    p.add_argument("--calibration", type=Path, metavar="MAP", help="calibration map (jointsim calibrate) to apply")
    p.add_argument("--out", type=Path, default=Path("out/frames"), help="output folder (default out/frames)")
    p.add_argument("--fit-reference", action="store_true",
                   help="fit the sensor's conductivity, contact impedances and electrode positions to the mean reference "
                        "frame and report them (summary.json)")
    p.add_argument("--refine", action="store_true",
                   help="the frames are one press (a target held at several depths): fit them through the simulator, "
                        "from the calibration map's estimate, with the sensor's modulus scale, saline, contact "
                        "impedances and electrode positions (a few minutes; needs --calibration and 2+ reference frames)")
    p.add_argument("--soft-target", type=float, metavar="KPA",
                   help="with --refine: the target is soft (a neo-Hookean sphere): fit its Young's modulus too, from KPA "
                        "kPa (~6x the time of a rigid target's fit)")
    p.add_argument("--known-presses", type=Path, metavar="CSV",
                   help="a rig's known presses of rigid spheres (x_mm, y_mm: the sphere's centre; diameter_mm, depth_mm past "
                        "first contact, force_n read there; a line per depth): fit the membrane's modulus scale to the "
                        "forces (summary.json; a load cell's sigma of 1 %% + 0.1 mN)")
    add_progress_argument(p)


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from ..io.export import atomic_path, write_voxels_vtu
    from ..io.frames import read_frames
    from ..calibration.report import write_csv
    from ..studies.measured import check_frames, image_frames, reference_snr_db
    from ..instrument import Instrument

    scene = scene_from_args(args)
    frames, reference = read_frames(args.frames), read_frames(args.reference)
    check_frames(scene, frames, reference)  # before the instrument is built (seconds)
    if args.refine and args.calibration is None:
        raise ValueError("--refine: starts from a calibration map's estimate; give --calibration MAP")
    if args.refine and len(reference) < 2:
        raise ValueError(f"--refine: weighs the frames by the noise the reference frames scatter with; {args.reference} "
                         f"holds {len(reference)} frame(s), give 2 or more")
    if args.soft_target is not None and not args.refine:
        raise ValueError("--soft-target: the modulus is fitted by --refine; give --refine too")
    if args.soft_target is not None and not (math.isfinite(args.soft_target) and args.soft_target > 0):
        raise ValueError(f"--soft-target = {args.soft_target}: a Young's modulus to start from, kPa > 0")
    known = None
    if args.known_presses is not None:  # read and checked before any work
        from ..calibration.membrane_fit import known_presses
        from ..dataset.presses import read_presses

        known = known_presses(read_presses(args.known_presses), f"--known-presses {args.known_presses}")
    snr = reference_snr_db(reference.voltages)  # the noise the emulator's fits weigh
    if args.refine and snr is None:
        raise ValueError(f"--refine: the reference frames in {args.reference} do not scatter (copies of one frame?): "
                         "their noise weighs the fit; give the instrument's own frames of the untouched sensor")
    cmap = None
    if args.calibration is not None:  # refused before any work when built for another sensor
        from ..calibration import load_map

        cmap = load_map(args.calibration)
        cmap.check_scene(scene, f"calibration map {args.calibration}")
        if args.refine and cmap.emulator is None:
            raise ValueError(f"--refine: calibration map {args.calibration} has no emulator to start from "
                             "(rebuild it with jointsim calibrate)")
    print(f"jointsim frames: scene {scene.name}, {len(frames)} frame(s) of {frames.voltages.shape[1]} channels, "
          f"reference the mean of {len(reference)} -> {args.out}")
    from tqdm import tqdm

    inst = Instrument.build(scene)
    try:
        with tqdm(total=len(frames), unit="frame", desc="frames", disable=progress_off(args)) as bar:
            res = image_frames(scene, frames, reference, instrument=inst, progress=bar.update)
        grid = inst.grid
        fit = _fit(inst, res.reference, len(reference)) if args.fit_reference else None
        membrane = None if known is None else _membrane(scene, inst, known)
        est = refined = None
        if cmap is not None:
            from ..calibration.apply import calibrate_measured

            est = calibrate_measured(cmap, res.voltages, res.dv, res.com, res.sum_sigma, res.diameter, snr,
                                     one_press=args.refine)
            if args.refine:
                refined = _refine(inst, est, res, snr, len(reference), args.soft_target)
    finally:
        inst.free()
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    table = {"frame": np.arange(len(frames)), "com_x": res.com[:, 0], "com_y": res.com[:, 1], "com_z": res.com[:, 2],
             "sum_sigma": res.sum_sigma, "diameter": res.diameter, "rms_dv": np.sqrt(np.mean(res.dv**2, axis=1))}
    if est is not None:
        table.update({k: est[k] for k in ("cal_x", "cal_y", "cal_depth", "direct_x", "direct_y", "direct_depth",
                                          "direct_diameter", "outside")})
        if cmap.emulator is not None:  # the model-based fit per frame, with its σ
            table.update({k: est[k] for k in est if k.startswith("model_")})
        if args.refine:
            table.update({k: est[k] for k in est if k.startswith("press_")})
    if refined is not None:
        table.update(refined.pop("columns"))
    written = [write_csv(out / "frames.csv", table)]
    k = min(VTU_FRAMES, len(frames))
    written.append(write_voxels_vtu(out / "images.vtu", grid, {f"frame{i}": res.images[i] for i in range(k)}))
    summary = {"scene": scene.name, "units": "SI (m, S/m, V)", "frames": {"path": str(args.frames), "sha256": _sha256(args.frames),
               "n": len(frames)}, "reference": {"path": str(args.reference), "sha256": _sha256(args.reference), "n": len(reference)},
               "calibration": None if cmap is None else {"map": str(args.calibration), "trained_region": cmap.region},
               "channel_order": "voltages[s * n_meas_per_stim + m] = measurement m of injection s",
               "reference_snr_db": snr,
               "fitted_sensor": fit,
               "membrane_from_known_presses": membrane,
               "refined_through_the_simulator": refined}
    with atomic_path(out / "summary.json") as tmp:
        tmp.write_text(json.dumps(summary, indent=2))
    written.append(out / "summary.json")
    for i in range(min(3, len(frames))):
        line = (f"  frame {i}: image CoM {np.round(res.com[i] * 1e3, 2).tolist()} mm, sum sigma {res.sum_sigma[i]:.3g}, "
                f"diameter {res.diameter[i] * 1e3:.1f} mm")
        if cmap is not None:
            line += (f"; calibrated x {table['direct_x'][i] * 1e3:.2f} y {table['direct_y'][i] * 1e3:.2f} mm, depth "
                     f"{table['direct_depth'][i] * 1e3:.2f} mm" + (f" ({table['outside'][i]} outside the map's region)"
                                                                   if table["outside"][i] else ""))
        print(line)
    if fit is not None:
        print(f"  fitted to the reference: saline {fit['conductivity_s_per_m']:.4g} S/m, contact impedance "
              f"{min(fit['contact_impedance_ohm_m2']):.3g}-{max(fit['contact_impedance_ohm_m2']):.3g} ohm m^2, electrodes moved "
              f"up to {fit['largest_move_mm']:.3f} mm; misfit {fit['misfit_before']:.2e} -> {fit['misfit_after']:.2e} of the frame")
    if membrane is not None:
        print(f"  membrane modulus from {membrane['presses']} known press(es): x{membrane['scale']:.4f} +- "
              f"{membrane['scale_sd']:.4f}; force misfit {membrane['misfit']:.2f} sigma")
    if refined is not None:
        print(f"  refined through the simulator ({refined['trials']} presses, {refined['seconds']:.0f} s): diameter "
              f"{refined['diameter_mm']:.2f} +- {refined['diameter_sd_mm']:.2f} mm, membrane modulus x{refined['modulus_scale']:.3f} "
              f"+- {refined['modulus_scale_sd']:.3f}; "
              + (f"target modulus {refined['target_modulus_kpa']:.3g} kPa +- {100 * refined['target_modulus_sd_relative']:.0f} %; "
                 if "target_modulus_kpa" in refined else "") +
              f"misfit {refined['misfit_before']:.3g} -> {refined['misfit_after']:.3g} noise sd per channel")
    print(f"  wrote {', '.join(p.name for p in written)} to {out}")
    return 0


def _fit(inst, v_ref, n_frames: int) -> dict:
    """The sensor fitted to the mean reference frame (jointsim.eit.fit), JSON-ready (mm, SI)."""
    import numpy as np

    from ..calibration.refine import fit_electrical

    ch = inst.reference
    f = fit_electrical(inst, v_ref, n_frames, inst.readout.noise_std)
    move = np.linalg.norm(f.centres[:, :2] - ch.layout.centres[:, :2], axis=1)
    return {"conductivity_s_per_m": f.conductivity, "contact_impedance_ohm_m2": f.contact_impedance.tolist(),
            "centres_mm": np.round(f.centres * 1e3, 6).tolist(), "largest_move_mm": float(move.max() * 1e3),
            "misfit_before": f.before, "misfit_after": f.after, "iterations": f.iterations}


def _membrane(scene, inst, known: list) -> dict:
    """The membrane's modulus scale fitted to the known presses' forces, JSON-ready (mm, N)."""
    from ..calibration.membrane_fit import FORCE_SD_TEXT, fit_membrane_scale

    f = fit_membrane_scale(scene, known, inflate_from=inst.inflated_u)
    return {"scale": f.scale, "scale_sd": f.scale * f.sd_ln, "sd_ln": f.sd_ln, "misfit": f.misfit, "iterations": f.iterations,
            "presses": len(known), "force_sd": FORCE_SD_TEXT,
            "forces_n": [{"diameter_mm": 2e3 * k.radius, "xy_mm": (k.xy * 1e3).tolist(), "depth_mm": (k.depths * 1e3).tolist(),
                          "measured": k.forces.tolist(), "fitted": m.tolist()} for k, m in zip(known, f.forces)]}


def _refine(inst, est: dict, res, snr_db: float, n_reference: int, soft_kpa: float | None = None) -> dict:
    """The frames of ``res`` fitted as one press through the simulator (jointsim.calibration.refine)
    from the map's press fit ``est`` (a soft target's modulus from ``soft_kpa`` kPa); per-frame
    columns (SI) and the fit's summary, JSON-ready (mm, kPa)."""
    import numpy as np

    from ..calibration.refine import fit_electrical, refine_press
    from ..eit.noise import noise_std

    def joint(name: str) -> np.ndarray:  # the press fit's, else (a frame it left out) the regression's
        return np.where(np.isfinite(est[f"press_{name}"]), est[f"press_{name}"], est[f"direct_{name}"])

    depth = joint("depth")
    sigma = noise_std(res.reference, snr_db)
    electrical = fit_electrical(inst, res.reference, n_reference, sigma)
    start = np.array([np.mean(joint("x")), np.mean(joint("y"))])
    f = refine_press(inst, res.voltages, res.reference, n_reference, start, depth, float(np.mean(joint("diameter"))),
                     electrical=electrical, noise_std=sigma, modulus=None if soft_kpa is None else 1e3 * soft_kpa)
    n = len(res.voltages)
    columns = {"refined_x": f.contact[:, 0], "refined_y": f.contact[:, 1], "refined_depth": f.depth,
               "refined_diameter": np.full(n, f.diameter), "refined_sd_x": f.contact_sd[:, 0], "refined_sd_y": f.contact_sd[:, 1],
               "refined_sd_depth": f.depth_sd, "refined_sd_diameter": np.full(n, f.diameter_sd)}
    return {"columns": columns, "diameter_mm": f.diameter * 1e3, "diameter_sd_mm": f.diameter_sd * 1e3,
            "centre_mm": (f.centre * 1e3).tolist(), "modulus_scale": f.scale, "modulus_scale_sd": f.scale_sd,
            "misfit_before": f.misfit[0], "misfit_after": f.misfit[1], "trials": f.trials, "seconds": f.seconds,
            "noise_sd_v": sigma, "snr_db": snr_db,
            **({"target_modulus_kpa": f.modulus / 1e3, "target_modulus_sd_relative": math.expm1(f.ln_modulus_sd),
                "target_modulus_start_kpa": soft_kpa} if soft_kpa is not None else {})}
