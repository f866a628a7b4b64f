"""Image priors compared on the paper's metrics and on the CoM's bias in 3-D.

    python benchmarks/bench_priors.py [--mesh dataset]   # writes results/image_priors.{md,json}

The paper's sensor, each [reconstruction] prior ("tikhonov": zeroth order, the paper's;
"noser"; "laplacian": voxel smoothness; "depth": cells near the base weighted up by
((z + z₀)/H)^−q, for q = 1, 2 (the default) and 3; "tv": total variation from the Laplacian's
image), λ chosen by each instrument's own rule (k-fold CV on its representative press; for
"tv", the discrepancy principle on it). Presses: a 15 mm sphere 2 mm past first contact (geometric, on the
inflated dome) at 0, 5, 10 and 13 mm off the axis and at (7, 7) mm; each imaged from 20 frames at
the instrument's noise (74.2 dB). Per prior and press, means over the frames: the in-plane
distance of the image's CoM from the dent's centroid (:func:`jointsim.instrument.dent_centroid`),
the CoM's height minus the centroid's (the 3-D bias), Σσ and the cluster's equivalent diameter.
"""

from __future__ import annotations

import argparse
import platform
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from _machine import cpu_name, write_pair

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from jointsim.instrument import Instrument, dent_centroid  # noqa: E402
from jointsim.mechanics.geometric import indent_dome  # noqa: E402
from jointsim.reconstruction.tikhonov import PRIORS  # noqa: E402
from jointsim.scene import SCENES_DIR, load_scene  # noqa: E402

PRESSES_MM = ((0.0, 0.0), (5.0, 0.0), (10.0, 0.0), (13.0, 0.0), (7.0, 7.0))
FRAMES = 20
DEPTH_EXPONENTS = (1.0, 2.0, 3.0)  # the "depth" prior's q, each a row


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mesh", default="dataset")
    ap.add_argument("--out", type=Path, default=ROOT / "results" / "image_priors")
    args = ap.parse_args()
    base = load_scene(SCENES_DIR / "paper_sensor.toml").with_mesh_preset(args.mesh)
    rows, timings = [], {}
    configs = [(p, 2.0) for p in PRIORS if p != "depth"] + [("depth", q) for q in DEPTH_EXPONENTS]
    labels = [p if p != "depth" else f"depth (q = {q:g})" for p, q in configs]
    for (prior, q), label in zip(configs, labels):
        scene = replace(base, reconstruction=replace(base.reconstruction, prior=prior, depth_exponent=q))
        t0 = time.perf_counter()
        inst = Instrument.build(scene)
        timings[label] = time.perf_counter() - t0
        ro = inst.readout
        for k, (x, y) in enumerate(PRESSES_MM):
            dent = indent_dome(inst.reference_dome, (x * 1e-3, y * 1e-3), 2e-3, 7.5e-3, scene.chamber.membrane_thickness)
            centre = dent_centroid(inst.reference_dome, dent.dome)
            clean = ro.change(inst.deform(dent.dome)) - ro.v_ref
            rng = np.random.default_rng([0, k])  # the same noise draws for every prior
            m = []
            for _ in range(FRAMES):
                _, _, met = inst.imager.image(clean + rng.normal(0.0, ro.dv_noise_std, ro.n_meas))
                m.append((np.linalg.norm(met.com[:2] - centre[:2]), met.com[2] - centre[2], met.sum_sigma,
                          met.diameter_equivalent))
            m = np.array(m)
            rows.append({"prior": label, "x_mm": x, "y_mm": y, "lambda": inst.imager.reconstructor.lam,
                         "com_xy_error_mm": 1e3 * float(m[:, 0].mean()), "com_z_bias_mm": 1e3 * float(m[:, 1].mean()),
                         "sum_sigma": float(m[:, 2].mean()), "diameter_mm": 1e3 * float(m[:, 3].mean())})
        inst.free()
    result = {"mesh": args.mesh, "machine": f"{platform.machine()}, {cpu_name()}", "frames": FRAMES, "rows": rows,
              "instrument_build_s": timings}
    L = ["# Image priors on the paper's metrics", "",
         f"`python benchmarks/bench_priors.py --mesh {args.mesh}` on {result['machine']}: a 15 mm sphere 2 mm past first "
         f"contact (geometric) at each place, {FRAMES} frames at 74.2 dB each, means. CoM errors against the dent's "
         "centroid; z bias: the image CoM's height minus the dent centroid's.", "",
         "| prior | press (mm) | CoM xy error (mm) | CoM z bias (mm) | Σσ (S/m·voxel) | image diameter (mm) |",
         "|---|---|---|---|---|---|"]
    for r in rows:
        L.append(f"| {r['prior']} | ({r['x_mm']:g}, {r['y_mm']:g}) | {r['com_xy_error_mm']:.2f} | {r['com_z_bias_mm']:+.2f} | "
                 f"{r['sum_sigma']:.3g} | {r['diameter_mm']:.1f} |")
    L += ["", "Means over the five presses:", "", "| prior | CoM xy error (mm) | |CoM z bias| (mm) | instrument set-up (s) |",
          "|---|---|---|---|"]
    for prior in labels:
        sel = [r for r in rows if r["prior"] == prior]
        L.append(f"| {prior} | {np.mean([r['com_xy_error_mm'] for r in sel]):.2f} | "
                 f"{np.mean([abs(r['com_z_bias_mm']) for r in sel]):.2f} | {timings[prior]:.0f} |")
    write_pair(args.out, result, "\n".join(L) + "\n")
    print("\n".join(L))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
