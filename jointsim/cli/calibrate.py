"""Calibration maps from a labelled dataset: size curves (Σσ, image diameter, RMS δV,
|F| against target diameter at fixed depth and at fixed force, with their inverse), a CoM map
(reconstructed CoM → x, y, depth; thin-plate spline), a direct regression from the 256
voltages, and stiffness where the data allows it, each evaluated on held-out presses (split by
press, seeded). Writes OUT/calibration_map.h5 (versioned, loads without pickle; use it with
`jointsim palpate --calibration`), CSV tables, PNG curves and error maps, and OUT/report.md
saying which goals are met, not met, or undetermined (too few held-out samples)."""

from __future__ import annotations

import argparse
import shlex
from pathlib import Path

from .common import add_progress_argument, float_list, progress_off

OUTPUT = "folder"  # what --out names (checked before any work: cli.common.check_output)
STAGES = 4  # what calibrate() announces: size curves, CoM map, direct regression, stiffness
HELP = "build calibration maps (size, CoM, direct regression, stiffness) from a dataset, evaluated on held-out presses"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("dataset", type=Path, help="finished dataset store NAME.h5 (jointsim dataset)")
    p.add_argument("--out", type=Path, default=Path("out/calibration"), help="output folder (default out/calibration)")
    p.add_argument("--test-fraction", type=float, default=0.2, help="fraction of presses held out (default 0.2)")
    p.add_argument("--seed", type=int, default=0, help="split and fit seed (default 0)")
    p.add_argument("--depths-mm", metavar="D,D,...", help="size-curve depths, comma-separated (default: from the data)")
    p.add_argument("--forces-n", metavar="F,F,...", help="size-curve forces, comma-separated (default: from the data)")
    p.add_argument("--regressor", choices=("mlp", "ridge"), default="mlp", help="direct regression model (default mlp)")
    p.add_argument("--goal-snr-db", type=float, default=74.2, help="SNR the goals are judged at (default 74.2)")
    p.add_argument("--snr-band-db", type=float, default=4.0, help="held-out samples within this many dB of --goal-snr-db (default 4)")
    p.add_argument("--max-com-points", type=int, default=3000, help="CoM map points fitted at most (default 3000)")
    p.add_argument("--noise-copies", type=int, default=30,
                   help="fresh noise draws of each training sample for the direct regression, 0-1000 (default 30; 0: stored samples only)")
    add_progress_argument(p)
    p.add_argument("--symmetry", action="store_true",
                   help="move the noise draws about the electrode ring by the sensor's turns and mirrors (default: off)")
    p.add_argument("--no-emulator", action="store_true",
                   help="skip the model-based estimator (the emulator of the coupled model): a quicker map without it")


def _command(args: argparse.Namespace) -> str:
    """The command line that reproduces this run (every setting spelled out)."""
    parts = ["jointsim calibrate", str(args.dataset), "--out", str(args.out), "--test-fraction", f"{args.test_fraction:g}",
             "--seed", str(args.seed), "--regressor", args.regressor, "--goal-snr-db", f"{args.goal_snr_db:g}",
             "--snr-band-db", f"{args.snr_band_db:g}", "--max-com-points", str(args.max_com_points),
             "--noise-copies", str(args.noise_copies)] + (["--symmetry"] if args.symmetry else [])
    parts += [f"--depths-mm {args.depths_mm}"] if args.depths_mm else []
    parts += [f"--forces-n {args.forces_n}"] if args.forces_n else []
    return " ".join(shlex.quote(p) if " " not in p else p for p in parts)


def _levels(text: str | None, flag: str, scale: float) -> tuple[float, ...] | None:
    """Size-curve levels (SI) from a list flag in its unit (× ``scale``); None when not given."""
    return None if text is None else tuple(v * scale for v in float_list(flag, text, 0.0, increasing=True))


def run(args: argparse.Namespace) -> int:
    from ..calibration import Settings, calibrate, load_samples, save_map
    from ..calibration.report import write_report

    if not 0 < args.test_fraction < 1:
        raise ValueError(f"--test-fraction = {args.test_fraction}: must be in (0, 1)")
    if args.seed < 0:
        raise ValueError(f"--seed = {args.seed}: must be >= 0")
    if args.max_com_points < 50:
        raise ValueError(f"--max-com-points = {args.max_com_points}: must be >= 50")
    if not 0 <= args.noise_copies <= 1000:
        raise ValueError(f"--noise-copies = {args.noise_copies}: must be in [0, 1000]")
    settings = Settings(
        test_fraction=args.test_fraction, seed=args.seed, depth_levels=_levels(args.depths_mm, "--depths-mm", 1e-3),
        force_levels=_levels(args.forces_n, "--forces-n", 1.0), regressor=args.regressor, goal_snr_db=args.goal_snr_db,
        snr_band_db=args.snr_band_db, max_com_points=args.max_com_points, noise_copies=args.noise_copies,
        symmetry=args.symmetry, emulator=not args.no_emulator,
    )
    command = _command(args)
    samples = load_samples(args.dataset)
    print(f"jointsim calibrate: {args.dataset}, {len(samples)} samples of {len(set(samples.group.tolist()))} presses -> {args.out}")
    from tqdm import tqdm

    # the fit's stages (size curves, CoM map, direct regression, stiffness) and the report
    with tqdm(total=STAGES + 1, unit="stage", desc="calibrate", disable=progress_off(args)) as bar:
        def stage(name: str) -> None:
            if bar.n or bar.disable:
                bar.update(1)
            bar.set_postfix_str(name.split(" (")[0], refresh=True)
            if bar.disable:
                print(f"  {name}", flush=True)

        cal = calibrate(samples, settings, progress=stage)
        stage("report")
        path = save_map(cal.map, args.out / "calibration_map.h5")
        files = write_report(args.out, cal, command)
        bar.update(bar.total - bar.n)
    for g in cal.evaluation["goals"]:
        v = g["value"]
        print(f"  goal {g['goal']} ({g['route']}) {g['statistic']} <= {g['limit']:g} {g['unit']}: "
              f"{'n/a' if v != v else f'{v:.3g}'} -> {g['verdict']}{(' (' + g['note'] + ')') if g['note'] else ''}")
    for w in cal.evaluation.get("warnings", []):
        print(f"  warning: {w}")
    print(f"  wrote {path} and {len(files)} report files to {args.out}")
    return 0
