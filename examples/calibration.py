"""Tutorial 3: a calibration map from a dataset, and its use on new frames.

From labelled samples it fits, on training presses, size curves, a CoM map, a direct regression
from δV/V to position, depth, size and force, and a stiffness model; it evaluates them on
held-out presses. The map holds the fingerprint of its sensor (another sensor's scene is
refused) and the region it was trained on (estimates outside it are flagged). Run
examples/dataset.py first; 48 samples only show the mechanics, not the accuracy
(results/calibration/ holds the maps made from 1500).

    python examples/calibration.py          # reads out/tutorial/dataset.h5, writes out/tutorial/calibration/
"""

from pathlib import Path

from jointsim.calibration import Settings, calibrate, load_map, load_samples, save_map
from jointsim.calibration.report import write_report

DATASET = Path("out/tutorial/dataset.h5")
OUT = Path("out/tutorial/calibration")


def main() -> None:
    samples = load_samples(DATASET)
    cal = calibrate(samples, Settings(seed=0, noise_copies=5), progress=lambda stage: print(" ", stage))
    path = save_map(cal.map, OUT / "calibration_map.h5")
    write_report(OUT, cal, "examples/calibration.py")
    for g in cal.evaluation["goals"]:
        print(f"  {g['goal']} {g['statistic']} ({g['route']}): {g['value']:.3g} {g['unit']} -> {g['verdict']}")

    cmap = load_map(path)  # in any later process: no pickle, plain arrays
    frames = {"com": samples.com, "voltages": samples.voltages, "dv": samples.dv, "force": samples.force,
              "sum_sigma": samples.sum_sigma, "diameter": samples.diameter}
    est = cmap.apply(frames)
    print(f"applied to {len(samples)} frames: first estimate x {est['direct_x'][0] * 1e3:.2f} mm "
          f"(true {samples.position[0, 0] * 1e3:.2f}); trained within r <= {cmap.region['r_max_m'] * 1e3:.1f} mm")


if __name__ == "__main__":
    main()
