"""Electrode designs side by side: what each sensor reads of the same presses, what it costs.

    python benchmarks/bench_designs.py [--mesh dataset]   # writes results/designs.{md,json}

Designs: the shipped scenes ``paper_sensor`` (16-electrode ring, central ground), ``ring16_inner8``
(the ring plus 8 internal electrodes), ``grid5x5`` (a floating 5 × 5 grid), ``membrane16`` (the
ring's 16 electrodes on the membrane, stretching with it), ``small_dome8`` (half the paper's dome,
8 electrodes) and ``elongated_pad`` (a 40 × 24 mm elliptical pad, 12 electrodes), each at the
same drive current and noise level (74.2 dB re its own mean standing |V|). Per design:
electrodes, measurements, chamber tets, the instrument's set-up stages; for one press (a 15 mm
sphere, 2 mm past first contact, geometric, on the inflated membrane; on a smaller dome scaled
with its base radius) at 0, 5, 10 and 13 mm off the axis (scaled likewise): RMS δV, the whole frame's δV against the instrument's noise
(‖δV‖ / σ, in dB: how far above the noise the press stands when every channel is used) and the
frame step's time (morph + forward + δV, no image); J_sens = Σᵢ ‖J[:, i]‖ / V_chamber; the
mesh-noise floor (the chamber as meshed against it meshed with a 1 µm jitter of its dome), dB
re the mean standing |V|; and each symmetry of the ideal sensor (``jointsim.geometry.symmetries``)
held by the transfer impedances, to that mesh's noise. Set-up and frame times are wall times on this machine, excluded from each other.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

from _machine import atomic_write, cpu_name

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from jointsim.eit.jacobian import jacobian  # noqa: E402
from jointsim.geometry import symmetries  # noqa: E402
from jointsim.instrument import Instrument, Readout  # noqa: E402
from jointsim.mechanics.geometric import indent_dome  # noqa: E402
from jointsim.metrics import rms, sensitivity_total  # noqa: E402
from jointsim.reconstruction.grid import ChamberGrid  # noqa: E402
from jointsim.scene import SCENES_DIR, load_scene  # noqa: E402
from jointsim.studies.protocol_study import jittered_chamber  # noqa: E402

DESIGNS = ("paper_sensor", "ring16_inner8", "grid5x5", "membrane16", "small_dome8", "elongated_pad")
OFFSETS_MM = (0.0, 5.0, 10.0, 13.0)
RADIUS, DEPTH = 7.5e-3, 2e-3


def bench(name: str, preset: str) -> dict:
    scene = load_scene(SCENES_DIR / f"{name}.toml").with_mesh_preset(preset)
    t0 = time.perf_counter()
    inst = Instrument.build(scene, imaging=False)
    setup = time.perf_counter() - t0
    ro = inst.readout
    grid = ChamberGrid.over(inst.reference.mesh, scene.reconstruction.cells)
    J = jacobian(ro.fields(inst.reference, True), ro.protocol, coarse=grid.C)
    presses = []
    k = scene.chamber.base_radius / 20e-3  # a smaller dome: the press scaled with its base radius
    for x in OFFSETS_MM:
        dome = indent_dome(inst.reference_dome, (k * x * 1e-3, 0.0), k * DEPTH, k * RADIUS, scene.chamber.membrane_thickness).dome
        t = time.perf_counter()
        r = inst.measure(dome, None, image=False)
        presses.append({"x_mm": x, "frame_s": time.perf_counter() - t, "mesh_path": r.chamber.path,
                        "rms_dv_uV": 1e6 * rms(r.dv_clean),
                        "frame_snr_dB": 20 * np.log10(np.linalg.norm(r.dv_clean) / ro.noise_std)})
    # each symmetry of the ideal sensor: the transfer impedances it permutes, against themselves
    Z = ro.fields(inst.reference, True).transfer
    residual = {}
    for what, P in symmetries(inst.reference.layout, scene.chamber).items():
        d = P[: len(Z)]  # the driven electrodes (the reference, last, stays)
        residual[what] = float(20 * np.log10(np.abs(Z).mean() / rms(Z[np.ix_(d, d)] - Z)))
    # the floor of the chamber as meshed (the moulded cap; the reference is its morph to the inflation)
    meshed, jit = (Readout.on(c, scene, ro.protocol, rng=None, reference_frames=1) for c in (inst.chamber, jittered_chamber(scene, 1e-6)))
    floor = 20 * np.log10(np.abs(meshed.v_ref).mean() / rms(jit.v_ref - meshed.v_ref))
    meshed.free()
    jit.free()
    out = {
        "design": name, "description": scene.name, "electrodes": scene.electrodes.count + 1,
        "reference": ("central disc" if scene.electrodes.is_ring else "floating" if not scene.electrodes.reference
                      else f"electrode {scene.electrodes.count} (r = {1e3 * np.hypot(*scene.electrodes.discs[-1][:2]):g} mm)"),
        "protocol": f"skip-{scene.drive.skip}, {scene.drive.measure}" if scene.drive.stim is None else "as data",
        "lead_fields": ro.forward.n_driven, "measurements": ro.n_meas, "tets": int(inst.reference.mesh.n_tets),
        "setup_s": setup, "setup_stages_s": dict(inst.setup_timings), "mean_standing_mV": 1e3 * float(np.abs(ro.v_ref).mean()),
        "noise_uV": 1e6 * ro.noise_std, "j_sens": sensitivity_total(J, grid), "floor_jitter_dB": float(floor), "presses": presses,
        "symmetry_dB": residual,
    }
    inst.free()
    return out


def report(rows: list[dict], preset: str, machine: str) -> str:
    lines = [
        "# Electrode designs side by side",
        "",
        f"`python benchmarks/bench_designs.py --mesh {preset}`; {machine}. Drive current and noise level (74.2 dB re "
        "each design's mean standing |V|) are the paper sensor's; the electrodes, the protocol and, for small_dome8 "
        "(half the paper's dome) and elongated_pad (a 40 x 24 mm elliptical pad), the chamber differ. The press: a "
        "15 mm sphere 2 mm past first contact (geometric indentation of the inflated membrane), on the x axis at the "
        "offsets below; on small_dome8 all of it scaled by its base radius (7.5 mm sphere, 1 mm, half the offsets). "
        "‖δV‖/σ: the whole frame's clean change against one frame's noise std.",
        "",
        "| design | electrodes | reference | protocol | lead fields | measurements | tets | mean standing mV | noise µV | J_sens | mesh floor (1 µm jitter) dB | set-up s |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(f"| {r['design']} | {r['electrodes']} | {r['reference']} | {r['protocol']} | {r['lead_fields']} | "
                     f"{r['measurements']} | {r['tets']:,} | {r['mean_standing_mV']:.2f} | {r['noise_uV']:.2f} | "
                     f"{r['j_sens']:.3g} | {r['floor_jitter_dB']:.1f} | {r['setup_s']:.1f} |")
    lines += ["", "| design | " + " | ".join(f"x = {x:g} mm: RMS δV µV, ‖δV‖/σ dB" for x in OFFSETS_MM) + " | frame step s (median) |",
              "|---|" + "---|" * (len(OFFSETS_MM) + 1)]
    for r in rows:
        cells = [f"{p['rms_dv_uV']:.0f}, {p['frame_snr_dB']:.1f}" for p in r["presses"]]
        lines.append(f"| {r['design']} | " + " | ".join(cells) + f" | {np.median([p['frame_s'] for p in r['presses']]):.2f} |")
    lines += ["", "Symmetry: the isometries of the ideal sensor (its chamber outline and layout, the reference kept) "
              "permute the transfer impedances Z; the chamber mesh is not symmetric, so each holds to the mesh's noise: "
              "mean |Z| over the RMS of Z permuted minus Z, dB (the worst symmetry; beside it the 1 µm jitter floor, re "
              "the mean standing |V|).", "",
              "| design | symmetries | worst (which) dB | median dB | mesh floor (1 µm jitter) dB |", "|---|---|---|---|---|"]
    for r in rows:
        sym = r["symmetry_dB"]
        if sym:
            worst = min(sym, key=sym.get)
            lines.append(f"| {r['design']} | {len(sym)} | {sym[worst]:.1f} ({worst}) | {np.median(list(sym.values())):.1f} | "
                         f"{r['floor_jitter_dB']:.1f} |")
        else:
            lines.append(f"| {r['design']} | 0 | – | – | {r['floor_jitter_dB']:.1f} |")
    lines += ["", "Set-up stages (s): " + "; ".join(
        f"{r['design']}: " + ", ".join(f"{k} {v:.1f}" for k, v in r["setup_stages_s"].items()) for r in rows), ""]
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mesh", default="dataset", choices=["test", "dataset", "paper"])
    ap.add_argument("--out", type=Path, default=ROOT / "results")
    args = ap.parse_args()
    rows = [bench(d, args.mesh) for d in DESIGNS]
    machine = f"{cpu_name()}, Python {platform.python_version()}"
    suffix = "" if args.mesh == "dataset" else f"_{args.mesh}"
    atomic_write(args.out / f"designs{suffix}.json", json.dumps({"preset": args.mesh, "machine": machine, "designs": rows},
                                                                 indent=2, default=float))
    atomic_write(args.out / f"designs{suffix}.md", report(rows, args.mesh, machine))
    print(report(rows, args.mesh, machine))


if __name__ == "__main__":
    main()
