"""Regenerate results/calibration/synthetic/: `jointsim calibrate` on a SYNTHETIC store whose
measurements are known functions of the labels (jointsim.calibration.synthetic; no physics is
simulated). It shows the outputs' format and that the fits recover known transforms; its
numbers say nothing about the sensor.

    python results/calibration/synthetic_demo.py
"""

import os
import sys
import tempfile
from pathlib import Path

from jointsim.calibration.synthetic import write_synthetic_dataset
from jointsim.cli.main import main

ROOT = Path(__file__).resolve().parents[2]
N_GROUPS, SEED, SOFT = 300, 0, 0.5

if __name__ == "__main__":
    os.chdir(ROOT)  # relative paths in the report's command line
    with tempfile.TemporaryDirectory() as d:
        store = write_synthetic_dataset(Path(d) / "synthetic.h5", (ROOT / "scenes" / "paper_sensor.toml").read_text(),
                                        n_groups=N_GROUPS, seed=SEED, soft_fraction=SOFT, snr_db=(40.0, 80.0))
        sys.exit(main(["calibrate", str(store), "--out", "results/calibration/synthetic"]))
