"""The paper's Fig. 2 B/C (sensitivity per unit volume) and G–H (δV, J_sens, CoM error per
skip) for each example design, side by side.

    python benchmarks/figure_designs.py [--mesh dataset]
        # writes results/designs/<design>/ (each design's protocol study, without the VTU images)
        # and results/designs/fig2_side_by_side.png

Each design is the shipped scene at the same mesh preset, its protocol study
(`jointsim protocol-study`: the scene's target pressed 2 mm past first contact, geometrically,
at the study's positions; on a smaller dome both scaled with its base radius) run for skip 0
and the scene's own skip, with the mesh-noise floor.
"""

from __future__ import annotations

import argparse
import shlex
import sys
import time
from dataclasses import replace
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from jointsim.scene import MESH_PRESETS, SCENES_DIR, load_scene  # noqa: E402
from jointsim.studies.protocol_study import StudyConfig, run_protocol_study  # noqa: E402
from jointsim.studies.report import write_study  # noqa: E402

DESIGNS = ("paper_sensor", "ring16_inner8", "grid5x5", "membrane16", "small_dome8", "elongated_pad")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--mesh", default="dataset", choices=sorted(MESH_PRESETS), help="mesh preset of every design")
    ap.add_argument("--out", type=Path, default=ROOT / "results" / "designs", help="output folder")
    args = ap.parse_args()
    command = "python benchmarks/figure_designs.py " + " ".join(shlex.quote(a) for a in sys.argv[1:])
    folders = []
    for name in DESIGNS:
        scene = load_scene(SCENES_DIR / f"{name}.toml").with_mesh_preset(args.mesh)
        t0 = time.perf_counter()
        k = scene.chamber.base_radius / 20e-3  # a smaller dome: the study's positions and depth scaled to it
        cfg = StudyConfig(skips=tuple(sorted({0, scene.drive.skip})), target_radius=scene.target.radius)
        cfg = replace(cfg, positions=tuple((x * k, y * k) for x, y in cfg.positions), depth=cfg.depth * k)
        result = run_protocol_study(scene, cfg)
        write_study(result, args.out / name, f"{command}  # {name}", vtu=False)
        folders.append(args.out / name)
        rows = result.table()
        print(f"{name}: " + "; ".join(f"skip {r['skip']}: RMS dV {r['rms_dV_uV']:.0f} uV, J_sens {r['J_sens']:.3g}" for r in rows)
              + f" ({time.perf_counter() - t0:.0f} s)", flush=True)
    tile(args.out / "fig2_side_by_side.png", folders)
    print(f"wrote {args.out}")
    return 0


def tile(path: Path, folders: list[Path]) -> None:
    """Each design's fig2_BC.png and fig2_GH.png in a row."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(folders), 2, figsize=(18, 6.2 * len(folders)))
    for row, folder in zip(axes, folders):
        for ax, name in zip(row, ("fig2_BC.png", "fig2_GH.png")):
            ax.imshow(plt.imread(folder / name))
            ax.set_axis_off()
        row[0].set_title(folder.name, fontsize=16, loc="left")
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


if __name__ == "__main__":
    raise SystemExit(main())
