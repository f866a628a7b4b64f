"""A press refined through the simulator (jointsim.calibration.refine) against the emulator it
starts from and the direct regression, on held-out presses of a dataset at the goals' 74.2 dB.

    python benchmarks/bench_simulator_refine.py DATASET.h5 MAP.h5 [--presses 40] [--workers 2]
        # writes results/calibration/simulator_refine.{md,json}; the presses done so far are kept
        # in --work (default out/simulator_refine) and a rerun resumes from them

The map is `jointsim calibrate DATASET --seed S`'s (its held-out presses: split seed S, 20 %); the
first --presses of them by group id are refitted. Each press's noise-free frames and reference are
re-noised at 74.2 dB (the reference the mean of the store's reference frames; seeded by the
group); the direct regression and the emulator's press fit (the map's) read them; the
simulator's fit starts from the emulator's estimate: the sensor's saline, contact impedances and
electrode centres fitted to the reference frame, then the target, every frame's depth, the
membrane's modulus scale, the saline and the contact impedances by Levenberg–Marquardt through
the coupled model, first with the electrode centres held there, then with them free too.
Errors: the contact's centre of pressure in the plane, depth, diameter (median, P95), the
reported σ's coverage (within 1σ, 2σ; RMS error in σ), seconds per press. "Where it pays":
the emulator's estimate kept for a press whose σ meets the position and depth goals
(jointsim.calibration.refine.worth_refining), the simulator's elsewhere. A store of soft
targets: each press's Young's modulus fitted too, from the geometric mean of the scene's
[dataset] range among its starts (the map's stiffness model needs the force, which the frames
do not carry). Each fit's misfit beside the misfit of the simulator at the press's true
parameters on the same frames: a fit above it stopped short of its optimum.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

from _machine import machine, write_pair

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

GOAL_SNR_DB = 74.2
# x, y (the position median's), depth: the goals, which "where it pays" asks the emulator's σ to meet
GOALS = np.array([0.3e-3, 0.3e-3, 0.05e-3])
_STATE: dict = {}


def _init(map_path: str, scene) -> None:
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    from jointsim.calibration import load_map
    from jointsim.instrument import Instrument

    _STATE["map"] = load_map(map_path)
    _STATE["inst"] = Instrument.build(scene, imaging=False)


def _noised(job: dict) -> tuple[np.ndarray, np.ndarray, float]:
    """The press's frames and reference re-noised at the goal SNR (seeded by its group)."""
    from jointsim.eit.noise import noise_std

    clean, ref_clean, r = np.asarray(job["clean"]), np.asarray(job["ref_clean"]), int(job["reference_frames"])
    rng = np.random.default_rng([2026, job["group"]])
    sigma = noise_std(ref_clean, GOAL_SNR_DB)
    frames = clean + rng.normal(0.0, sigma, clean.shape)
    v_ref = ref_clean + rng.normal(0.0, sigma / math.sqrt(r), ref_clean.shape)
    return frames, v_ref, sigma


def truth_misfit(job: dict) -> dict:
    """The misfit per channel in noise σ (the fit's measure, √(Φ_data / n)) of the simulator at
    the press's true parameters (its sphere, depths, modulus, membrane scale, saline, contact
    impedance, electrode jitter) on the same noised frames: a fit whose misfit lies above this
    stopped short of its optimum (over ~60 parameters the optimum lies ~1/60 of a channel's
    misfit² below the truth's)."""
    from jointsim.calibration.refine import _Press

    inst = _STATE["inst"]
    frames, v_ref, sigma = _noised(job)
    K, r = len(frames), int(job["reference_frames"])
    soft = math.isfinite(job.get("modulus", math.inf))
    n_el = len(inst.reference.layout.radii)
    jitter = np.asarray(job["jitter"])
    offsets = np.zeros((n_el, 2))
    offsets[: len(jitter)] = jitter  # the ground electrode's is the layout's
    sim = _Press(inst, K, offsets, soft)
    p = np.concatenate([job["xy"], [job["radius"]], np.asarray(job["truth"])[:, 2], [math.log(job["modulus"])] if soft else [],
                        [math.log(job["scale"]), math.log(job["conductivity"])], np.full(sim.n_el, math.log(job["contact_impedance"]))])
    v0, V = sim(p)[:2]
    w = np.concatenate([np.full(len(v0), math.sqrt(r)), np.ones(V.size)]) / sigma
    res = w * (np.concatenate([v0, V.ravel()]) - np.concatenate([v_ref, frames.ravel()]))
    return {"group": job["group"], "truth_misfit": math.sqrt(float(res @ res) / len(res))}


def press(job: dict) -> dict:
    """One held-out press: its three estimates (mm-free SI lists)."""
    from jointsim.calibration.data import voltage_features
    from jointsim.calibration.emulator import fit_presses, sigmas
    from jointsim.calibration.refine import fit_electrical, refine_press

    cmap, inst = _STATE["map"], _STATE["inst"]
    frames, v_ref, sigma = _noised(job)
    r = int(job["reference_frames"])
    F = voltage_features(frames, frames - v_ref)
    K = len(frames)
    direct = cmap.regressor(F)[:, :4]
    emu, cov = fit_presses(cmap.emulator, F, direct, np.zeros(K, int), snr_db=GOAL_SNR_DB)
    soft = math.isfinite(job.get("modulus", math.inf))
    start_modulus = float(np.exp(np.mean(np.log(inst.scene.dataset.target_modulus)))) if soft else None
    t0 = time.perf_counter()
    electrical = fit_electrical(inst, v_ref, r, sigma)
    t_el = time.perf_counter() - t0
    try:
        fit = refine_press(inst, frames, v_ref, r, emu[0, :2], emu[:, 2], float(emu[0, 3]), electrical=electrical,
                           noise_std=sigma, modulus=start_modulus)
    except Exception as e:  # a press the fit cannot take is a result too: counted, not a stopped run
        return {"group": job["group"], "error": f"{type(e).__name__}: {e}", "seconds": time.perf_counter() - t0}
    truth = truth_misfit(job)["truth_misfit"]
    refined = np.column_stack([fit.contact, fit.depth, np.full(K, fit.diameter)])
    refined_sd = np.column_stack([fit.contact_sd, fit.depth_sd, np.full(K, fit.diameter_sd)])
    return {"group": job["group"], "truth": job["truth"], "direct": direct.tolist(), "emulator": emu.tolist(),
            "emulator_sd": sigmas(cov).tolist(), "refined": refined.tolist(), "refined_sd": refined_sd.tolist(),
            "scale": [fit.scale, fit.scale_sd, job["scale"]], "misfit": list(fit.misfit), "trials": fit.trials,
            "iterations": fit.iterations, "seconds": t_el + fit.seconds, "seconds_electrical": t_el, "truth_misfit": truth,
            **({"modulus": [fit.modulus, fit.ln_modulus_sd, job["modulus"], start_modulus]} if soft else {})}


def _stats(e: np.ndarray) -> dict:
    e = np.abs(e) * 1e3
    return {"median_mm": float(np.median(e)), "p95_mm": float(np.percentile(e, 95))}


def _scores(P: np.ndarray, T: np.ndarray, S: np.ndarray | None) -> dict:
    inside = np.hypot(T[:, 0], T[:, 1]) <= 15e-3
    out = {"xy": _stats(np.hypot(*(P[:, :2] - T[:, :2]).T)[inside]), "depth": _stats(P[:, 2] - T[:, 2]),
           "diameter": _stats(P[:, 3] - T[:, 3])}
    if S is not None:
        z = np.abs(P - T) / S
        out["within_1sd"] = (z <= 1).mean(axis=0).tolist()
        out["within_2sd"] = (z <= 2).mean(axis=0).tolist()
        out["rms_z"] = np.sqrt((z**2).mean(axis=0)).tolist()
        out["median_sd_mm"] = (np.median(S, axis=0) * 1e3).tolist()
    return out


def summarise(rows: list[dict]) -> dict:
    from jointsim.calibration.refine import worth_refining

    failed = [r for r in rows if "error" in r]
    rows = [r for r in rows if "error" not in r]
    cat = {k: np.concatenate([np.asarray(r[k], float) for r in rows]) for k in ("truth", "direct", "emulator", "emulator_sd",
                                                                                "refined", "refined_sd")}
    flag = worth_refining(cat["emulator_sd"][:, :3], GOALS)
    # a press is refined whole: where any of its frames asks for it
    per_press = np.concatenate([np.full(len(r["truth"]), worth_refining(np.asarray(r["emulator_sd"])[:, :3], GOALS).any())
                                for r in rows])
    pays = np.where(per_press[:, None], cat["refined"], cat["emulator"])
    pays_sd = np.where(per_press[:, None], cat["refined_sd"], cat["emulator_sd"])
    sec = np.array([r["seconds"] for r in rows])
    return {"presses": len(rows), "failed": [{"group": r["group"], "error": r["error"]} for r in failed],
            "frames": int(len(cat["truth"])), "flagged_frames": float(flag.mean()),
            "refined_presses": float(np.mean([worth_refining(np.asarray(r["emulator_sd"])[:, :3], GOALS).any() for r in rows])),
            "direct": _scores(cat["direct"], cat["truth"], None),
            "emulator": _scores(cat["emulator"], cat["truth"], cat["emulator_sd"]),
            "refined": _scores(cat["refined"], cat["truth"], cat["refined_sd"]),
            "where_it_pays": _scores(pays, cat["truth"], pays_sd),
            "seconds_per_press": {"median": float(np.median(sec)), "max": float(sec.max()), "sum": float(sec.sum()),
                                  "electrical_fit_median": float(np.median([r["seconds_electrical"] for r in rows]))},
            "trials_median": float(np.median([r["trials"] for r in rows])),
            "misfit_after_median": float(np.median([r["misfit"][1] for r in rows])),
            "misfit_after_max": float(np.max([r["misfit"][1] for r in rows])),
            "scale_error_median": float(np.median([abs(math.log(r["scale"][0] / r["scale"][2])) for r in rows])),
            # the scale's error in its own σ (sd of s; of ln s, sd/s)
            "scale_rms_z": float(np.sqrt(np.mean([(math.log(r["scale"][0] / r["scale"][2]) * r["scale"][0] / r["scale"][1]) ** 2
                                                  for r in rows]))),
            # a fit whose misfit lies above the truth's stopped short of its optimum (truth_misfit)
            "short_of_optimum": [r["group"] for r in rows if "truth_misfit" in r and r["misfit"][1] > r["truth_misfit"]],
            "truth_misfit_presses": sum("truth_misfit" in r for r in rows),
            **({"modulus": _modulus_scores(rows)} if any("modulus" in r for r in rows) else {})}


def _modulus_scores(rows: list[dict]) -> list[dict]:
    """A soft target's fitted modulus per press (E, its ln σ, the truth, the start), sorted by
    the true modulus: its relative error, its error in its own σ (of ln E) and the σ as a
    relative error (the press's bound, with the nuisances fitted)."""
    out = []
    for r in sorted((r for r in rows if "modulus" in r), key=lambda r: r["modulus"][2]):
        E, sd, true, start = r["modulus"]
        out.append({"group": r["group"], "true_kpa": true / 1e3, "fit_kpa": E / 1e3, "start_kpa": start / 1e3,
                    "relative_error": E / true - 1.0, "sd_relative": math.expm1(sd), "z": math.log(E / true) / sd,
                    "misfit": r["misfit"][1], "truth_misfit": r.get("truth_misfit", math.nan)})
    return out


def markdown(s: dict, a: argparse.Namespace, head: dict) -> str:
    L = ["# A press refined through the simulator", "",
         f"Command: `python benchmarks/bench_simulator_refine.py DATASET MAP --presses {a.presses} --workers {a.workers} --seed {a.seed}`  ",
         f"Machine: {head['machine']}. Dataset: {head['n']} samples, data_sha256 `{head['data_sha256'][:16]}…`; map: "
         f"`{head['map']}` (its held-out presses: {head['held_out']}).", "",
         " ".join(__doc__.split("\n\n")[2].split()), "",
         f"{s['presses']} presses, {s['frames']} frames, at {GOAL_SNR_DB} dB"
         + (f" ({len(s['failed'])} more the simulator's fit could not take: "
            + "; ".join(f"group {f['group']}, {f['error']}" for f in s["failed"]) + ")" if s["failed"] else "") + ". Goals: position median ≤ 0.3 mm and P95 ≤ 0.8 mm over "
         "r ≤ 15 mm, depth median ≤ 0.05 mm. σ: each estimator's own (the emulator's recalibrated; the simulator's fit's "
         "covariance at its estimate, the Cramér–Rao bound of that press read whole with the sensor's nuisances fitted, "
         "so RMS error / σ is the fit's efficiency, 1 where it reaches its bound). The presses are read through the "
         "dataset's own membrane, as meshed, which made them: the design study reads presses through a membrane refined "
         "about the contact, where the size signal has converged, and bounds the diameter of a press read whole at 0.48 mm "
         "median (results/design_study/summary.md); the mesh's coarser contact carries more size signal than the physics.", "",
         "| estimator | xy median / P95 mm | depth median / P95 mm | diameter median / P95 mm | within 1σ (x, y, depth, diameter) | within 2σ | RMS error / σ | median σ mm |",
         "|---|---|---|---|---|---|---|---|"]
    names = {"direct": "direct regression (the map's MLP)", "emulator": "emulator, a press's frames jointly (the map's)",
             "refined": "the simulator, from the emulator's estimate",
             "where_it_pays": f"where it pays: the simulator for the {100 * s['refined_presses']:.0f} % of presses whose emulator σ misses the position or depth goal"}
    for k, label in names.items():
        x = s[k]
        cov = ((" / ".join(f"{v:.0%}" for v in x["within_1sd"]), " / ".join(f"{v:.0%}" for v in x["within_2sd"]),
                " / ".join(f"{v:.2g}" for v in x["rms_z"]), " / ".join(f"{v:.3g}" for v in x["median_sd_mm"]))
               if "within_1sd" in x else ("–",) * 4)
        L.append(f"| {label} | {x['xy']['median_mm']:.3f} / {x['xy']['p95_mm']:.3f} | {x['depth']['median_mm']:.4f} / "
                 f"{x['depth']['p95_mm']:.3f} | {x['diameter']['median_mm']:.2f} / {x['diameter']['p95_mm']:.1f} | "
                 + " | ".join(cov) + " |")
    t = s["seconds_per_press"]
    L += ["", f"The simulator's fit: {t['median']:.0f} s per press (median; at most {t['max']:.0f} s; the electrical "
          f"nuisances' fit to the reference {t['electrical_fit_median']:.0f} s of it), {s['trials_median']:.0f} presses "
          f"through the simulator (median); the misfit after, per channel in noise σ: median {s['misfit_after_median']:.3f}, "
          f"largest {s['misfit_after_max']:.3f} (1 where the model fits to the noise); the membrane's modulus scale to "
          f"{100 * s['scale_error_median']:.1f} % (median |ln error|; RMS error / σ {s['scale_rms_z']:.2g}). {a.workers} worker processes, {t['sum'] / 3600:.2f} CPU-hours in all."]
    if s["truth_misfit_presses"]:
        L += ["", f"Did each fit find its optimum? The simulator at each press's true parameters (its sphere, depths, "
              "membrane scale, saline, contact impedance, electrode jitter) on the same noised frames: a fit whose misfit lies "
              f"above the truth's stopped short of its optimum. {len(s['short_of_optimum'])} of {s['truth_misfit_presses']}"
              + (f" (groups {', '.join(map(str, s['short_of_optimum']))})." if s["short_of_optimum"] else ".")]
    if "modulus" in s:
        m = s["modulus"]
        rel = np.abs([x["relative_error"] for x in m])
        z = np.array([x["z"] for x in m])
        L += ["", "A soft target's Young's modulus, fitted with the rest after the press's rigid fit, from the best of the "
              "geometric mean of the scene's range and 4 values over it (jointsim.calibration.refine.refine_press) "
              f"(the goal: within 20 %): median relative error {100 * np.median(rel):.0f} %, RMS error / σ "
              f"{np.sqrt(np.mean(z ** 2)):.2g} (σ of ln E, the press's own bound with the nuisances fitted).", "",
              "| group | true E kPa | fitted E kPa | relative error | σ (relative) | error / σ | misfit: the fit's / the truth's |",
              "|---|---:|---:|---:|---:|---:|---|"]
        L += [f"| {x['group']} | {x['true_kpa']:.4g} | {x['fit_kpa']:.4g} | {100 * x['relative_error']:+.1f} % | "
              f"{100 * x['sd_relative']:.1f} % | {x['z']:+.2f} | {x['misfit']:.4f} / {x['truth_misfit']:.4f} |" for x in m]
    return "\n".join(L) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dataset", type=Path)
    ap.add_argument("map", type=Path)
    ap.add_argument("--presses", type=int, default=40)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0, help="the split seed the map was calibrated with (jointsim calibrate --seed)")
    ap.add_argument("--scene", type=Path, default=None, help="the simulator's scene (default: the one the dataset was made with)")
    ap.add_argument("--work", type=Path, default=ROOT / "out" / "simulator_refine")
    ap.add_argument("--out", type=Path, default=ROOT / "results" / "calibration" / "simulator_refine")
    a = ap.parse_args()
    from jointsim.calibration import scene_from_provenance
    from jointsim.calibration.data import split_groups
    from jointsim.scene import load_scene
    from jointsim.io.records import open_records

    fields = ["group", "contact_centre", "depth", "radius", "voltages_clean", "reference_clean", "membrane_scale", "xy",
              "electrode_jitter", "conductivity", "contact_impedance"]
    try:  # a soft target's modulus (inf for a rigid one); not in a store older than the schema's field
        rec = open_records(a.dataset, fields=fields + ["target_modulus"])
    except KeyError:
        rec = open_records(a.dataset, fields=fields)
    scene = load_scene(a.scene) if a.scene else scene_from_provenance(rec.provenance)
    g = np.asarray(rec["group"])
    test_ids = np.unique(g[split_groups(g, 0.2, a.seed)[1]])[: a.presses]
    r_frames = int((rec.provenance.get("params", {}).get("scene", {}).get("dataset", {}) or {}).get("reference_frames", 50))
    a.work.mkdir(parents=True, exist_ok=True)
    done_path = a.work / f"presses_{rec.data_sha256[:16]}_split{a.seed}.jsonl"
    rows = [json.loads(line) for line in done_path.read_text().splitlines()] if done_path.is_file() else []
    done = {r["group"]: r for r in rows}
    jobs, truth_jobs = [], []
    for G in test_ids:
        i = np.flatnonzero(g == G)
        cc, d, rad = np.asarray(rec["contact_centre"])[i], np.asarray(rec["depth"])[i], np.asarray(rec["radius"])[i]
        job = {"group": int(G), "clean": np.asarray(rec["voltages_clean"])[i].tolist(),
                "ref_clean": np.asarray(rec["reference_clean"])[i[0]].tolist(), "reference_frames": r_frames,
                "truth": np.column_stack([cc[:, :2], d, 2 * rad]).tolist(),
                "scale": float(np.asarray(rec["membrane_scale"])[i[0]]), "xy": rec["xy"][i[0]].tolist(),
                "radius": float(rad[0]), "jitter": rec["electrode_jitter"][i[0]].tolist(),
                "conductivity": float(rec["conductivity"][i[0]]), "contact_impedance": float(rec["contact_impedance"][i[0]]),
                **({"modulus": float(rec["target_modulus"][i[0]])} if "target_modulus" in rec.fields
                   and math.isfinite(rec["target_modulus"][i[0]]) else {})}
        if int(G) not in done:
            jobs.append(job)
        elif "error" not in done[int(G)] and "truth_misfit" not in done[int(G)]:
            truth_jobs.append(job)  # fitted by a run before this diagnostic: the misfit at the truth only
    print(f"{len(done)} presses done, {len(jobs)} to go", flush=True)
    if jobs or truth_jobs:
        import multiprocessing as mp

        for v in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):  # one core per worker process
            os.environ[v] = "1"

        with mp.get_context("spawn").Pool(a.workers, _init, (str(a.map), scene)) as pool, done_path.open("a") as fh:
            for row in pool.imap_unordered(press, jobs):
                fh.write(json.dumps(row) + "\n")
                fh.flush()  # a press is kept as soon as it is done: a killed run resumes after it
                rows.append(row)
                print(f"group {row['group']}: {row['seconds']:.0f} s, " + (row["error"] if "error" in row else
                      f"{row['trials']} trials, misfit {row['misfit'][1]:.3f}"), flush=True)
            extra = {t["group"]: t["truth_misfit"] for t in pool.imap_unordered(truth_misfit, truth_jobs)}
        if extra:  # the rows done before, with the misfit at their truth added: the file rewritten whole
            rows = [{**r, "truth_misfit": extra[r["group"]]} if r["group"] in extra else r for r in rows]
            tmp = done_path.with_suffix(".tmp")
            tmp.write_text("".join(json.dumps(r) + "\n" for r in rows))
            os.replace(tmp, done_path)
    rows = [r for r in rows if r["group"] in set(int(x) for x in test_ids)]
    s = summarise(rows)
    head = {"machine": machine(), "n": int(len(g)), "data_sha256": rec.data_sha256, "map": str(a.map),
            "held_out": f"split seed {a.seed}, {len(np.unique(g[split_groups(g, 0.2, a.seed)[1]]))} presses, the first {len(rows)} refitted"}
    write_pair(a.out, {**head, "summary": s, "presses": rows}, markdown(s, a, head))
    print(markdown(s, a, head))


if __name__ == "__main__":
    main()
