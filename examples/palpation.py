"""Tutorial 1: virtual palpation from Python.

The paper's test (Fig. 4): the MuJoCo rig presses a sphere into the sensor at 25 mm/s; every
50 Hz frame solves the membrane, morphs the chamber, measures the 256 voltages and images them.
Here on the coarse "test" mesh and membrane with one 15 mm target pressed 1.5 mm, so it runs in
seconds; drop the ``with_mesh_preset`` and ``replace`` lines for the paper's settings (what
`jointsim palpate` runs: three targets, 3 mm, about 40 s on 2 cores).

    python examples/palpation.py            # writes out/tutorial/palpation/
"""

from dataclasses import replace
from pathlib import Path

import numpy as np

from jointsim.io.records import open_records
from jointsim.palpation.job import palpate
from jointsim.scene import SCENES_DIR, load_scene

OUT = Path("out/tutorial/palpation")


def main() -> None:
    scene = load_scene(SCENES_DIR / "paper_sensor.toml")
    # coarse settings for a quick look: the "test" chamber mesh, a 32-vertex membrane rim
    scene = scene.with_mesh_preset("test")
    scene = replace(scene, membrane=replace(scene.membrane, rim_vertices=32, layers=1))
    scene = replace(scene, palpation=replace(scene.palpation, target_radii=(7.5e-3,), depth=1.5e-3, hold=0.1))

    job = palpate(scene, OUT, scene_text=f'extends = "{scene.name}"\n', command="examples/palpation.py", vtu_every=0)

    rec = open_records(OUT / "palpation.h5")  # every frame, SI units, with its provenance
    deepest = int(np.argmax(rec["depth"]))
    print(f"{len(rec)} frames; at the deepest ({rec['depth'][deepest] * 1e3:.2f} mm): "
          f"force {rec['force'][deepest, 2] * 1e3:.1f} mN, RMS dV {rec['rms_dv_clean'][deepest] * 1e6:.0f} uV, "
          f"image CoM {np.round(rec['com'][deepest] * 1e3, 1).tolist()} mm")
    print("wrote", ", ".join(p.name for p in job.written[:4]), "...")


if __name__ == "__main__":
    main()
