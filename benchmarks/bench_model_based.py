"""Model-based estimation against the direct regression, on held-out presses of a dataset:
an emulator of the coupled model (jointsim.calibration.emulator) fitted per frame and per press
(a press's frames share x, y and the diameter), with its uncertainty per estimate, beside the
direct regression it starts from.

    python benchmarks/bench_model_based.py DATASET.h5 [--splits 0,1,2]
        # writes results/calibration/model_based.{md,json}

Per split (press groups held out as `jointsim calibrate` holds them out, 20 %): the emulator
and the direct regression as `jointsim calibrate` fits them on the training presses (the
emulator on their noise-free features, its covariance from the residuals of training presses it
holds out, their part shared by a press's frames, and the noise's draws scaled to each frame's
SNR; the training labels its prior; its σ recalibrated on the presses it held out. The
regression: its MLP, 30 fresh noise draws per sample); both evaluated on
the held-out presses, at the goals' 74.2 dB (their noise-free voltages re-noised) and at the
dataset's own SNRs (the stored noisy frames). Errors: in-plane position within r ≤ 15 mm,
depth, diameter (median, P95); the emulator's own error against the simulator (its held-out
R² in the whitened feature space); the uncertainty's calibration (the share of estimates within
1σ and 2σ of the truth: 68 % and 95 % if right; the errors' RMS in σ: 1 if right).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from _machine import machine, write_pair

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from jointsim.calibration.data import load_samples, split_groups, voltage_features  # noqa: E402
from jointsim.calibration.emulator import PARAMETERS, coverage, fit_frames, fit_presses, sigmas  # noqa: E402
from jointsim.calibration.regression import copy_groups, noisy_features  # noqa: E402

COPIES = 3  # fresh noise draws of each held-out sample at the goals' SNR
GOAL_SNR_DB = 74.2


def _stats(e: np.ndarray) -> dict:
    e = np.abs(e[np.isfinite(e)]) * 1e3
    return {"n": int(len(e)), "median_mm": float(np.median(e)), "p95_mm": float(np.percentile(e, 95))}


def _estimates(emu, reg, F: np.ndarray, groups: np.ndarray, snr_db) -> dict:
    """The three estimators' θ (n, 4) and the emulator's covariances on features ``F`` at ``snr_db``."""
    direct = reg(F)[:, :4]
    frames, cov_f = fit_frames(emu, F, direct, snr_db)
    press, cov_p = fit_presses(emu, F, direct, groups, snr_db=snr_db)
    return {"direct": (direct, None), "emulator_frame": (frames, cov_f), "emulator_press": (press, cov_p)}


def _scores(est: dict, T: np.ndarray) -> dict:
    inside = np.hypot(T[:, 0], T[:, 1]) <= 15e-3
    out = {}
    for name, (P, C) in est.items():
        row = {"xy": _stats(np.hypot(*(P[:, :2] - T[:, :2]).T)[inside]), "depth": _stats(P[:, 2] - T[:, 2]),
               "diameter": _stats(P[:, 3] - T[:, 3])}
        if C is not None:
            cov = coverage(P, C, T)
            for key in ("within_1sd", "within_2sd", "rms_z"):
                row[key] = {k: c[key] for k, c in cov.items()}
            sd = sigmas(C)
            row["median_sd_mm"] = {k: float(np.nanmedian(sd[:, j]) * 1e3) for j, k in enumerate(PARAMETERS)}
        out[name] = row
    return out


def split(samples, seed: int) -> dict:
    from jointsim.calibration.build import Settings, calibrate

    tr, te = split_groups(samples.group, 0.2, seed)
    B = samples.subset(te)
    rng = np.random.default_rng([seed, 7])
    t0 = time.perf_counter()
    cal = calibrate(samples, Settings(seed=seed), progress=lambda _: None)  # the emulator and regression as `jointsim calibrate` fits them
    t_cal = time.perf_counter() - t0
    emu, reg = cal.map.emulator, cal.map.regressor
    Zb, Tb = emu.whiten(B.clean_features), B.press
    r2 = 1.0 - float(((Zb - emu(Tb)) ** 2).sum() / ((Zb - Zb.mean(axis=0)) ** 2).sum())
    t0 = time.perf_counter()
    stored = _scores(_estimates(emu, reg, voltage_features(B.voltages, B.dv), B.group, B.snr_db), Tb)
    t_fit = time.perf_counter() - t0
    # the goals' SNR: every held-out sample re-noised at 74.2 dB, COPIES times (a press's frames one copy each)
    F = noisy_features(B.voltages_clean, B.reference_clean, (GOAL_SNR_DB, GOAL_SNR_DB), B.reference_frames, COPIES, rng)
    goal = _scores(_estimates(emu, reg, F, copy_groups(B.group, COPIES), GOAL_SNR_DB), np.tile(Tb, (COPIES, 1)))
    out = {"seed": seed, "train_presses": int(len(np.unique(samples.group[tr]))), "test_presses": int(len(np.unique(B.group))),
           "test_frames": int(len(B)), "emulator_r2": r2, "sd_scale": np.asarray(emu.sd_scale).tolist(),
           "seconds": {"calibrate": t_cal, "fits_stored_frames": t_fit}, "stored": stored, "goal_snr": goal}
    print({k: v for k, v in out.items() if k not in ("stored", "goal_snr")},
          {k: (v["xy"]["median_mm"], v["xy"]["p95_mm"], v["depth"]["median_mm"]) for k, v in goal.items()}, flush=True)
    return out


def markdown(r: dict) -> str:
    goals = "position median ≤ 0.3 mm and P95 ≤ 0.8 mm over r ≤ 15 mm, depth median ≤ 0.05 mm"
    lines = ["# Model-based estimation: an emulator of the coupled model, against the direct regression", "",
             f"Command: `python benchmarks/bench_model_based.py DATASET --splits {','.join(str(s['seed']) for s in r['splits'])}`  ",
             f"Machine: {r['machine']}. Dataset: {r['n']} samples, data_sha256 `{r['data_sha256'][:16]}…` (the store behind "
             "results/calibration/paper_sensor; its command in results/calibration/README.md).", "",
             " ".join(__doc__.split("\n\n")[0].split()), "", " ".join(__doc__.split("\n\n")[2].split()), ""]
    for key, title in (("goal_snr", f"At the goals' SNR ({GOAL_SNR_DB} dB: each held-out sample re-noised {COPIES}×; goals: {goals})"),
                       ("stored", "At the dataset's own SNRs (40–80 dB, the stored noisy frames)")):
        lines += [f"## {title}", "",
                  "| split | estimator | xy median / P95 mm (r ≤ 15 mm) | depth median / P95 mm | diameter median / P95 mm | within 1σ (x, y, depth, diameter) | within 2σ | RMS error / σ |",
                  "|---|---|---|---|---|---|---|---|"]
        for s in r["splits"]:
            for name, label in (("direct", "direct regression (`jointsim calibrate`'s MLP)"), ("emulator_frame", "emulator, per frame"),
                                ("emulator_press", "emulator, a press's frames jointly")):
                x = s[key][name]
                cov = (" / ".join(f"{v:.0%}" for v in x["within_1sd"].values()), " / ".join(f"{v:.0%}" for v in x["within_2sd"].values()),
                       " / ".join(f"{v:.2g}" for v in x["rms_z"].values())) if "within_1sd" in x else ("–", "–", "–")
                lines.append(f"| {s['seed']} | {label} | {x['xy']['median_mm']:.3f} / {x['xy']['p95_mm']:.2f} | "
                             f"{x['depth']['median_mm']:.3f} / {x['depth']['p95_mm']:.2f} | {x['diameter']['median_mm']:.2f} / "
                             f"{x['diameter']['p95_mm']:.1f} | {cov[0]} | {cov[1]} | {cov[2]} |")
        lines.append("")
    lines += ["| split | train / test presses | test frames | emulator held-out R² (whitened features) | σ scale, per frame (x, y, depth, diameter) | σ scale, press | s: calibrate (the emulator in it), fits of the stored frames |",
              "|---|---|---:|---:|---|---|---|"]
    for s in r["splits"]:
        t, sc = s["seconds"], s["sd_scale"]
        lines.append(f"| {s['seed']} | {s['train_presses']} / {s['test_presses']} | {s['test_frames']} | {s['emulator_r2']:.3f} | "
                     f"{' / '.join(f'{v:.2g}' for v in sc[0])} | {' / '.join(f'{v:.2g}' for v in sc[1])} | "
                     f"{t['calibrate']:.0f}, {t['fits_stored_frames']:.1f} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dataset", type=Path)
    ap.add_argument("--splits", default="0,1,2")
    ap.add_argument("--out", type=Path, default=ROOT / "results" / "calibration" / "model_based")
    a = ap.parse_args()
    samples = load_samples(a.dataset)
    if not samples.has_clean:
        sys.exit(f"{a.dataset}: the store has no noise-free voltages (the emulator is trained on them)")
    r = {"machine": machine(), "data_sha256": samples.source.get("data_sha256", ""), "n": len(samples),
         "splits": [split(samples, int(s)) for s in a.splits.split(",")]}
    write_pair(a.out, r, markdown(r))


if __name__ == "__main__":
    main()
