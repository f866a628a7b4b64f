"""How much a press's derivatives depend on the membrane mesh's layout about the contact: the
design study's turned press (one ring's mechanics solved at its first centre and turned to the
next, jointsim.design.study.press_groups) against the same press solved on a membrane refined
about its own centre, at the study's contact margin and a wider one.

    python benchmarks/bench_turned_presses.py   # writes results/design_study/turned_presses.{md,json}
    python benchmarks/bench_turned_presses.py --levels 4 --ring-mm 12   # ... turned_presses_levels4.{md,json}

The paper's sensor at the dataset preset, three levels of refinement (the study's default), the
15 mm sphere at 1, 2 and 3 mm past first contact; on the rings 6 and 12 mm from the axis of the
study's 6 mm grid, the ring's first centre turned to its second. Per case and depth: the
relative change ‖J_turned − J_own‖/‖J_own‖ of the target columns (x, y, depth, radius). Both are
equally fine discretisations (the turned one is exactly the press solved on the turned mesh:
tests/test_design.py), so the change is the mesh's own spread at that resolution. The cases run
in two processes (about 6 minutes on 2 cores). ``--levels 4 --ring-mm 12``: the ring where that
spread is largest, the study's contact margin, a level finer (does the spread shrink with the
mesh?).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from _machine import machine, write_pair

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

OUT = ROOT / "results" / "design_study" / "turned_presses"
DIAMETER = 15e-3
DEPTHS = (1e-3, 2e-3, 3e-3)
CASES = ((6e-3, 1e-3), (12e-3, 1e-3), (6e-3, 2.5e-3), (12e-3, 2.5e-3))  # (ring radius, contact margin) m


def case(ring: float, margin: float, levels: int = 3) -> dict:
    """The first two centres of the study's grid on ``ring``: the second's press solved on its
    own membrane refined ``levels`` times and turned from the first's, with the refined zone
    ``margin`` m past the contact."""
    import jointsim.design.sensitivity as sens
    from jointsim.design.study import press_grid
    from jointsim.instrument import Instrument
    from jointsim.scene import SCENES_DIR, load_scene

    sens.CONTACT_MARGIN = margin  # read by contact_zone in this process only
    scene = load_scene(SCENES_DIR / "paper_sensor.toml").with_mesh_preset("dataset")  # the design study's fidelity
    grid = press_grid(15e-3, 6e-3, order=4)  # the paper's study grid (16-fold ring: order 4)
    a, b = [p for p in grid if abs(math.hypot(*p) - ring) < 1e-9][:2]
    inst = Instrument.build(scene, imaging=False)
    moves = sens.electrode_moves(inst, sens.ELECTRODE_STEP)
    depths, R = np.array(DEPTHS), DIAMETER / 2
    t = time.perf_counter()
    own_model = sens.contact_membrane(scene, R, b, max(DEPTHS), levels)
    own = sens.press_sensitivity(inst.on_membrane(own_model), own_model, b, depths, moves=moves)
    model = sens.contact_membrane(scene, R, a, max(DEPTHS), levels)
    mech = sens.press_mechanics(model, a, depths)
    turn = math.atan2(b[1], b[0]) - math.atan2(a[1], a[0])
    m = np.array([[math.cos(turn), -math.sin(turn)], [math.sin(turn), math.cos(turn)]])
    mech = mech.turned(m)
    turned = sens.press_electrical(inst.on_surface(inst.on_membrane(model).surface.turned(m), mech.u_ref), mech, moves=moves)
    J_own, J_turned = own.jacobian[..., :4], turned.jacobian[..., :4]
    rel = np.linalg.norm(J_turned - J_own, axis=1) / np.linalg.norm(J_own, axis=1)
    inst.free()
    return {"ring_mm": ring * 1e3, "margin_mm": margin * 1e3, "from_xy_mm": (a * 1e3).tolist(), "to_xy_mm": (b * 1e3).tolist(),
            "membrane_nodes": [int(own_model.mesh.n_nodes), int(model.mesh.n_nodes)],
            "change_by_depth": rel.tolist(), "seconds": time.perf_counter() - t}


def run(levels: int = 3, ring_mm: float | None = None) -> dict:
    """The CASES (those on ``ring_mm`` and at the study's margin, where it is given) at ``levels``."""
    todo = [c for c in CASES if ring_mm is None or (abs(c[0] * 1e3 - ring_mm) < 1e-9 and c[1] == CASES[0][1])]
    if not todo:
        raise SystemExit(f"--ring-mm {ring_mm:g}: not a ring of the cases (allowed: "
                         + ", ".join(sorted({f"{c[0] * 1e3:g}" for c in CASES})) + ")")
    with ProcessPoolExecutor(min(2, len(todo))) as pool:
        cases = list(pool.map(case, *zip(*todo), [levels] * len(todo)))
    return {"diameter_mm": DIAMETER * 1e3, "depths_mm": [d * 1e3 for d in DEPTHS], "levels": levels, "cases": cases,
            "machine": machine()}


def markdown(r: dict) -> str:
    lines = ["# A turned press against the press solved on its own membrane", "",
             f"`{command(r)}`: the paper's sensor, dataset preset, {LEVELS.get(r.get('levels', 3), r.get('levels'))} "
             f"levels about the contact, a {r['diameter_mm']:g} mm sphere; on each ring of the study's grid its first centre's press turned "
             "to the second centre against the second solved on a membrane refined about itself. Relative change of "
             "the target columns of ∂V/∂θ, ‖J_turned − J_own‖/‖J_own‖, %.", "",
             "| ring mm | contact margin mm | depth mm | x | y | depth | radius | membrane nodes |", "|---|---|---|---|---|---|---|---|"]
    for c in r["cases"]:
        for d, row in zip(r["depths_mm"], c["change_by_depth"]):
            lines.append(f"| {c['ring_mm']:g} | {c['margin_mm']:g} | {d:g} | " + " | ".join(f"{100 * v:.2f}" for v in row)
                         + f" | {c['membrane_nodes'][0]} |")
    lines += ["", f"Ran on {r['machine']}: " + ", ".join(f"{c['seconds']:.0f} s" for c in r["cases"]) + " per case."]
    return "\n".join(lines) + "\n"


LEVELS = {3: "three", 4: "four", 5: "five"}


def command(r: dict) -> str:
    """The command that wrote ``r``."""
    cmd = "python benchmarks/bench_turned_presses.py"
    if r.get("levels", 3) != 3 or len(r["cases"]) < len(CASES):
        cmd += f" --levels {r['levels']}" + (f" --ring-mm {r['cases'][0]['ring_mm']:g}" if len(r["cases"]) < len(CASES) else "")
    return cmd


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--levels", type=int, default=3, choices=(3, 4, 5), help="refinements about the contact (default: 3, the study's)")
    ap.add_argument("--ring-mm", type=float, default=None, help="only this ring's case at the study's margin (default: all cases)")
    args = ap.parse_args()
    r = run(args.levels, args.ring_mm)
    stem = OUT if args.levels == 3 and args.ring_mm is None else OUT.with_name(f"{OUT.name}_levels{args.levels}")
    write_pair(stem, r, markdown(r))


if __name__ == "__main__":
    main()
