"""Soft targets: the cost of a membrane step against a soft target relative to a rigid one (same
process, same dome), and a soft sphere on a rigid flat against Hertz over d/R = 0.01 … 0.05.

    python benchmarks/bench_soft_target.py          # writes results/soft_target_cost.{md,json}

Dome: isotropic cap 20 mm base radius, 10 mm height, 32 rim vertices, one layer of the default wedges, 50 Pa
reservoir; r = 7.5 mm sphere on the axis in 0.5 mm steps, rigid and soft with E = 100× the
membrane's Young's modulus (6.6 MPa). Hertz: a neo-Hookean sphere R = 10 mm, E = 66 kPa,
ν = 0.49, 0.5 mm cells at its lowest point, its cut face bonded as in the model (the test,
tests/test_soft_target.py, lets it slide instead), pressed onto a rigid frictionless plate,
F = 4/3·E/(1 − ν²)·√R·d^1.5.
"""

from __future__ import annotations

import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

from _machine import cpu_name

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from jointsim.geometry import isotropic_cap  # noqa: E402
from jointsim.io.export import atomic_path  # noqa: E402
from jointsim.mechanics.dome import MembraneModel  # noqa: E402
from jointsim.mechanics.soft_target import SoftSphere, SoftTargetModel, press_on_rigid_flat, soft_material  # noqa: E402

DEPTHS = (0.5e-3, 1.0e-3)
HERTZ_D_OVER_R = (0.01, 0.02, 0.03, 0.05)


def step_costs() -> list[dict]:
    dome = isotropic_cap(0.02, 0.01, 32)
    rows = []
    for E in (None, 6.6e6):
        kw = dict(layers=1, pressure=50.0, target_radius=7.5e-3)
        m = MembraneModel(dome, 2e-3, **kw) if E is None else SoftTargetModel(dome, 2e-3, target_material=soft_material(E), **kw)
        top = m.first_contact_height((0.0, 0.0))
        times, forces = [], []
        for d in DEPTHS:
            t0 = time.perf_counter()
            st = m.press(np.array([0.0, 0.0, top - d]))
            times.append(time.perf_counter() - t0)
            forces.append(float(st.force[2]))
        rows.append({"target": "rigid" if E is None else f"soft, E = {E / 1e6:g} MPa",
                     "target_p2_nodes": 0 if E is None else int(m.target.mesh.n_nodes),
                     "step_s": times, "force_N": forces})
    return rows


def hertz_sweep(R: float = 10e-3, E: float = 66e3, nu: float = 0.49, h0: float = 0.5e-3) -> list[dict]:
    sph = SoftSphere(R, soft_material(E, nu), h0, growth=1.5)
    rows = []
    for ratio in HERTZ_D_OVER_R:
        d = ratio * R
        force, penetration = press_on_rigid_flat(sph, d, 100 * E / h0)
        F = float(force[2])
        hertz = 4 / 3 * E / (1 - nu**2) * np.sqrt(R) * d**1.5
        rows.append({"d_over_R": ratio, "force_N": F, "hertz_N": hertz, "penetration_over_d": penetration / d})
    return rows


def main() -> int:
    load0 = os.getloadavg()[0]
    cost = step_costs()
    hertz = hertz_sweep()
    meta = {"command": "python benchmarks/bench_soft_target.py", "machine": f"{cpu_name()}, {os.cpu_count()} cores, Python {platform.python_version()}",
            "date": time.strftime("%Y-%m-%d"), "load_average_start_end": [load0, os.getloadavg()[0]]}
    rigid = cost[0]["step_s"]
    lines = ["# Soft targets: step cost and Hertz", "", f"Command: `{meta['command']}`  ", f"Machine: {meta['machine']}; run {meta['date']}; "
             f"1-min load average {load0:.1f} at the start, {meta['load_average_start_end'][1]:.1f} at the end.  ",
             "Dome: isotropic cap 20 mm base radius, 10 mm height, 32 rim vertices, one layer of the default 15-node wedges (coarse: the test dome), 50 Pa reservoir;",
             "r = 7.5 mm sphere on the axis. Times in one process; read the ratio, not the seconds.", "",
             "| target | target P2 nodes | step to 0.5 mm (first contact) s | step to 1 mm s | ratio to rigid (1 mm step) | F 0.5 / 1.0 mm, mN |",
             "|---|---|---|---|---|---|"]
    for r in cost:
        s = r["step_s"]
        lines.append(f"| {r['target']} | {r['target_p2_nodes']:,} | {s[0]:.2f} | {s[1]:.2f} | {s[1] / rigid[1]:.1f}× | "
                     f"{r['force_N'][0] * 1e3:.2f} / {r['force_N'][1] * 1e3:.2f} |")
    lines += ["", "Soft sphere (R 10 mm, E 66 kPa, ν 0.49, 0.5 mm cells) on a rigid flat against Hertz:", "",
              "| d/R | F mN | Hertz mN | error | penetration / d |", "|---|---|---|---|---|"]
    for r in hertz:
        lines.append(f"| {r['d_over_R']:.2f} | {r['force_N'] * 1e3:.3f} | {r['hertz_N'] * 1e3:.3f} | {100 * (r['force_N'] / r['hertz_N'] - 1):+.1f} % | "
                     f"{100 * r['penetration_over_d']:.2f} % |")
    out = ROOT / "results" / "soft_target_cost"
    for suffix, text in ((".json", json.dumps({"meta": meta, "step_costs": cost, "hertz": hertz}, indent=2)), (".md", "\n".join(lines) + "\n")):
        with atomic_path(out.with_suffix(suffix)) as tmp:
            Path(tmp).write_text(text)
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
