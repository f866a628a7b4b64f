"""Where a dataset sample's time goes: one worker's presses profiled (cProfile), its time split
by what the code does, at a mesh preset.

    python benchmarks/bench_sample_profile.py                     # dataset preset, ~1 min
    python benchmarks/bench_sample_profile.py --mesh dataset_p2   # writes results/sample_profile_dataset_p2.{md,json}

A worker as `jointsim dataset` runs it (one thread; the nominal instrument built once, as each
worker does), the first press left out (it warms the caches every later press finds), then
``--presses`` presses of the scene's samples per press, seed 0. Each share is the cumulative
time of the named functions (cProfile: the profiler's own cost inflates many small calls, so the
total is a little above the run's wall time without it, which is given too). The mechanics
rows count Newton wherever it runs: the group's inflation (in its membrane's set-up) too.
"""

from __future__ import annotations

import os

for _v in ("MKL_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS"):  # as a dataset worker runs
    os.environ[_v] = "1"

import argparse  # noqa: E402
import cProfile  # noqa: E402
import pstats  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

from _machine import machine, write_pair  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
# what the code does → the functions (file:function, as cProfile names them) whose cumulative
# time it is; listed from the outside in, each share excluding the ones nested under it later
PARTS = (
    ("group set-up: the group's membrane (moduli scaled, inflated)", "generate.py", "_membrane"),
    ("group set-up: the group's readout (electrodes clipped, reference forward)", "instrument.py", "on"),
    ("mechanics: Newton's factorisations of the membrane Hessian", "newton.py", "factor_hessian"),
    ("mechanics: regularised steps (where the Hessian is not positive definite)", "newton.py", "_regularised_step"),
    ("mechanics: element energies, gradients, Hessians (Warp)", "fem.py", "launch_elements"),
    ("mechanics: line searches", "newton.py", "_line_search"),
    ("mechanics: a press's steps, all told", "dome.py", "press"),
    ("frame: the chamber morphed", "morph.py", "deform_chamber"),
    ("the forward (assembly, factorisation, solves; the group's reference too)", "forward.py", "solve"),
    ("frame: the image and its metrics", "instrument.py", "image"),
    ("frame: measure, all told", "instrument.py", "measure"),
)


def cumulative(stats: pstats.Stats, file: str, function: str) -> float:
    """The cumulative seconds of ``function`` in ``file`` (the outermost where the file has two
    of that name, one calling the other: forward.py's model and shared-solver solve)."""
    return max((v[3] for (f, _, name), v in stats.stats.items() if f.endswith(file) and name == function), default=0.0)


def run(preset: str, presses: int) -> dict:
    from jointsim.dataset.generate import DatasetSetup
    from jointsim.instrument import deployed_chamber
    from jointsim.scene import SCENES_DIR, load_scene

    os.environ["JOINTSIM_CACHE"] = tempfile.mkdtemp(prefix="jointsim-bench-profile-")
    scene = load_scene(SCENES_DIR / "paper_sensor.toml").with_mesh_preset(preset)
    setup = DatasetSetup(scene, deployed_chamber(scene), 0)
    setup.group(0)
    t = time.perf_counter()
    n = sum(len(setup.group(g)[0]) for g in range(1, presses + 1))
    wall = time.perf_counter() - t
    profile = cProfile.Profile()
    profile.enable()
    n_profiled = sum(len(setup.group(g)[0]) for g in range(1, presses + 1))
    profile.disable()
    stats = pstats.Stats(profile)
    total = cumulative(stats, "generate.py", "group")
    parts = [{"part": label, "s_per_sample": cumulative(stats, f, fn) / n_profiled} for label, f, fn in PARTS]
    return {"machine": machine(), "preset": preset, "element_order": scene.mesh.element_order, "presses": presses,
            "samples": n, "wall_s_per_sample": wall / n, "profiled_s_per_sample": total / n_profiled,
            "samples_per_hour_one_worker": 3600 * n / wall, "parts": parts}


def markdown(r: dict) -> str:
    lines = [f"# Where a dataset sample's time goes ({r['preset']} preset, P{r['element_order']})", "",
             f"Command: `python benchmarks/bench_sample_profile.py --mesh {r['preset']}`  ",
             f"Machine: {r['machine']}; one thread (a dataset worker).", "",
             __doc__.split("\n\n", 2)[2].strip().replace("\n", " "), "",
             f"{r['samples']} samples ({r['presses']} presses): **{r['wall_s_per_sample']:.3f} s per sample** without the "
             f"profiler ({r['samples_per_hour_one_worker']:.0f} samples/h on one worker), {r['profiled_s_per_sample']:.3f} s "
             "with it.", "",
             "| what | s per sample | share of the profiled sample |", "|---|---:|---:|"]
    for p in r["parts"]:
        lines.append(f"| {p['part']} | {p['s_per_sample']:.3f} | {100 * p['s_per_sample'] / r['profiled_s_per_sample']:.0f} % |")
    lines += ["", "Nested rows (\"all told\") include the rows above them of the same stage."]
    return "\n".join(lines) + "\n"


def main() -> None:
    from jointsim.scene import MESH_PRESETS

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--mesh", default="dataset", choices=sorted(MESH_PRESETS))
    ap.add_argument("--presses", type=int, default=5, help="presses profiled after the first (default 5)")
    a = ap.parse_args()
    if a.presses < 1:
        ap.error(f"--presses = {a.presses}: must be >= 1")
    r = run(a.mesh, a.presses)
    stem = "sample_profile" if a.mesh == "dataset" else f"sample_profile_{a.mesh}"
    write_pair(ROOT / "results" / stem, r, markdown(r))


if __name__ == "__main__":
    main()
