"""How a frame's cost grows with the electrode count: rings of 8, 16, 32 and 64 discs on the
paper's chamber, each with the central ground.

    python benchmarks/bench_electrode_count.py [--mesh dataset]   # writes results/electrode_count.{md,json}

Per ring (1 mm discs at r = 15 mm, skip-N/2, the paper's chamber and membrane at the preset):
the chamber's tets (every disc refines the mesh around it), and a morphed frame's forward
(a 15 mm sphere 2 mm deep at the centre, geometric), split into its parts as a dataset worker
runs them (one thread; the solver's analysis kept): the CEM matrix assembled, factorised, and
the L lead fields solved (L = the driven electrodes). Medians of 5, wall time. The factor and
the assembly grow with the mesh only; the lead fields with L × the factor's size.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from _machine import machine, median_seconds, write_pair

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from jointsim.instrument import Instrument  # noqa: E402
from jointsim.linalg import factorize  # noqa: E402
from jointsim.mechanics.geometric import indent_dome  # noqa: E402
from jointsim.scene import MESH_PRESETS, SCENES_DIR, scene_data, scene_from_dict  # noqa: E402

COUNTS = (8, 16, 32, 64)
REPEATS = 5


def ring_scene(n: int, preset: str):
    data = scene_data(SCENES_DIR / "paper_sensor.toml")
    e = {k: v for k, v in data["electrodes"].items() if k not in ("count", "ring_radius_mm", "diameter_mm", "ground_diameter_mm",
                                                                    "first_angle_deg", "contact_impedance_ohm_m2")}
    e |= {"reference": n, "ring": [{"count": n, "radius_mm": 15.0, "diameter_mm": 1.0}], "disc": [{"xy_mm": [0.0, 0.0], "diameter_mm": 4.0}]}
    data = {**data, "electrodes": e, "drive": {**data["drive"], "skip": n // 2}, "name": f"ring{n}"}
    data["dataset"] = {**data.get("dataset", {}), "electrode_jitter_mm": 0.0}
    return scene_from_dict(data).with_mesh_preset(preset)


def median_time(f, repeats: int = REPEATS) -> float:
    return median_seconds(f, repeats)


def bench(n: int, preset: str) -> dict:
    scene = ring_scene(n, preset)
    inst = Instrument.build(scene, imaging=False)
    ro = inst.readout
    dome = indent_dome(inst.reference_dome, (0.0, 0.0), 2e-3, 7.5e-3, scene.chamber.membrane_thickness).dome
    chamber = inst.deform(dome).chamber
    model = ro.model(chamber, True)
    L = model.n_driven
    with threadpool_limits(1):
        A = model.assembler.assemble(ro.conductivity, model.z)
        assemble = median_time(lambda: model.assembler.assemble(ro.conductivity, model.z))
        rhs = np.zeros((A.shape[0], L))
        rhs[model.assembler.n_dofs + np.arange(L), np.arange(L)] = 1.0
        factor = median_time(lambda: factorize(A, "superlu").free())
        f = factorize(A, "superlu")
        solve = median_time(lambda: f(rhs))
        one = median_time(lambda: f(rhs[:, :1]))
        f.free()
        frame = median_time(lambda: model.solve(ro.conductivity))
    inst.free()
    row = {"electrodes": n + 1, "lead_fields": L, "measurements": ro.n_meas, "tets": int(chamber.mesh.n_tets),
           "unknowns": int(A.shape[0]), "assemble_s": assemble, "factor_s": factor, "lead_fields_s": solve,
           "one_field_s": one, "frame_forward_s": frame}
    print(f"  {n} + 1 electrodes: {row['tets']:,} tets, assemble {assemble:.4f} s, factor {factor:.4f} s, "
          f"{L} lead fields {solve:.4f} s ({one:.5f} s each alone), forward {frame:.4f} s", flush=True)
    return row


def markdown(rows: list[dict], preset: str, seconds: float) -> str:
    lines = ["# A frame's cost against the electrode count", "",
             f"`python benchmarks/bench_electrode_count.py --mesh {preset}` ({machine()}; {seconds:.0f} s). Rings of 1 mm discs at "
             "r = 15 mm on the paper's chamber with the central ground, skip-N/2; a morphed frame (15 mm sphere, 2 mm, at the "
             "centre). One thread, SuperLU for the split (the forward column: the instrument's own solver), medians of 5.", "",
             "| electrodes | lead fields | measurements | tets | unknowns | assemble s | factorise s | lead fields s | one field s | frame's forward s |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    lines += [f"| {r['electrodes']} | {r['lead_fields']} | {r['measurements']} | {r['tets']:,} | {r['unknowns']:,} | {r['assemble_s']:.4f} | "
              f"{r['factor_s']:.4f} | {r['lead_fields_s']:.4f} | {r['one_field_s']:.5f} | {r['frame_forward_s']:.4f} |" for r in rows]
    a, b = rows[0], rows[-1]
    lines += ["", f"From {a['electrodes']} to {b['electrodes']} electrodes the mesh grows {b['tets'] / a['tets']:.2f}× (each disc refines "
              f"its neighbourhood), the factorisation {b['factor_s'] / a['factor_s']:.2f}×, the lead fields' solves "
              f"{b['lead_fields_s'] / a['lead_fields_s']:.2f}× ({b['lead_fields'] / a['lead_fields']:.0f}× the fields) and the frame's "
              f"forward {b['frame_forward_s'] / a['frame_forward_s']:.2f}×.", ""]
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--mesh", default="dataset", choices=sorted(MESH_PRESETS), help="mesh preset")
    ap.add_argument("--out", type=Path, default=ROOT / "results" / "electrode_count", help="output stem")
    args = ap.parse_args()
    t0 = time.perf_counter()
    rows = [bench(n, args.mesh) for n in COUNTS]
    seconds = time.perf_counter() - t0
    write_pair(args.out, {"machine": machine(), "mesh": args.mesh, "rows": rows}, markdown(rows, args.mesh, seconds))
    print(f"wrote {args.out}.md/.json")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
