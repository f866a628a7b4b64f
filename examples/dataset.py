"""Tutorial 2: a synthetic labelled dataset from Python.

Each press draws a target (its size, where it first touches, rigid or soft), randomises the
sensor (membrane moduli, saline, contact impedance, electrode placement, SNR), presses it and
takes labelled samples at several depths: voltages, δV, force, displaced volume, image
metrics. One resumable HDF5 file; the same seed gives the same data whatever the workers.
Here 48 samples on the coarse "test" mesh (about a minute on 2 cores); `jointsim dataset
--n 1500` is the calibration's.

    python examples/dataset.py              # writes out/tutorial/dataset.h5
"""

from pathlib import Path

import numpy as np

from jointsim.dataset import generate_dataset
from jointsim.io.records import open_records
from jointsim.scene import SCENES_DIR, load_scene

OUT = Path("out/tutorial/dataset.h5")


def main() -> None:
    scene = load_scene(SCENES_DIR / "paper_sensor.toml").with_mesh_preset("test")
    run = generate_dataset(scene, 48, OUT, seed=1, workers=2)  # 8 presses x 6 depths
    rec = open_records(run.path)
    r = np.hypot(*rec["contact_point"].T) * 1e3
    print(f"{run.n_samples} samples ({run.groups_run} presses computed now) in {run.wall_s:.0f} s; "
          f"data_sha256 {run.data_sha256[:16]}...")
    print(f"contact points {r.min():.1f}-{r.max():.1f} mm from the axis, depths "
          f"{rec['depth'].min() * 1e3:.2f}-{rec['depth'].max() * 1e3:.2f} mm, "
          f"forces up to {rec['force'][:, 2].max() * 1e3:.0f} mN")


if __name__ == "__main__":  # workers are spawned processes: a script needs this guard
    main()
