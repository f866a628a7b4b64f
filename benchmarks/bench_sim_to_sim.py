"""The sim-to-sim gap of a reference frame, before and after fitting the sensor to it.

    python benchmarks/bench_sim_to_sim.py [--mesh dataset]   # writes results/sim_to_sim.{md,json}
    python benchmarks/bench_sim_to_sim.py --mesh dataset_p2 --out results/sim_to_sim_dataset_p2

"Measured": the paper's sensor at rest as another simulator would give it: the chamber meshed
again (its dome's vertices jittered by 1 µm: the deterministic mesher then gives another
mesh), P2 elements, the saline 4 % off (0.355 S/m), every contact impedance drawn log-uniform
over ×0.5–2 of the scene's, every ring electrode moved up to 0.1 mm (seed 0). The model:
the scene's own instrument at that fidelity (its mesh and elements, nominal values). The relative misfit
‖V_model − V_meas‖/‖V_meas‖ of the reference frame, in dB re the instrument's noise (74.2 dB
re the mean |V|), before and after `jointsim.eit.fit.fit_reference`, and the parameters it
recovers against the truth. What remains after the fit is the model's own error (its mesh,
and P1 against P2 where it is P1): the gap a map trained on this simulator carries to that one.
"""

from __future__ import annotations

import argparse
import platform
import sys
import time
from pathlib import Path

import numpy as np

from _machine import cpu_name, write_pair

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from jointsim.eit.fit import fit_reference  # noqa: E402
from jointsim.eit.forward import ForwardModel  # noqa: E402
from jointsim.eit.protocol import scene_protocol  # noqa: E402
from jointsim.instrument import Instrument  # noqa: E402
from jointsim.mesh.electrodes import disc_patches  # noqa: E402
from jointsim.scene import SCENES_DIR, load_scene  # noqa: E402
from jointsim.studies.protocol_study import jittered_chamber  # noqa: E402


def db(rel: float, noise_rel: float) -> float:
    """A relative misfit in dB above the noise (positive: above it)."""
    return 20 * np.log10(rel / noise_rel)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mesh", default="dataset")
    ap.add_argument("--out", type=Path, default=ROOT / "results" / "sim_to_sim")
    args = ap.parse_args()
    scene = load_scene(SCENES_DIR / "paper_sensor.toml").with_mesh_preset(args.mesh)
    protocol = scene_protocol(scene)
    e = scene.electrodes
    rng = np.random.default_rng(0)

    t0 = time.perf_counter()
    other = jittered_chamber(scene, 1e-6)  # the "other simulator's" chamber mesh
    lay = other.layout
    n = len(lay.radii)
    z0 = e.contact_impedances
    z_true = z0 * np.exp(rng.uniform(np.log(0.5), np.log(2.0), n))
    ring = [l for l in range(n) if l != other.ground]
    c_true = lay.centres.copy()
    r, a = 0.1e-3 * np.sqrt(rng.uniform(size=len(ring))), rng.uniform(0, 2 * np.pi, len(ring))
    c_true[ring, 0] += r * np.cos(a)
    c_true[ring, 1] += r * np.sin(a)
    sigma_true = 0.355
    meas = ForwardModel(other.mesh, disc_patches(other.mesh, c_true, lay.radii, quadratic=True), other.ground, z_true,
                        order=2).solve(sigma_true).voltages(protocol)
    t_meas = time.perf_counter() - t0

    inst = Instrument.build(scene, imaging=False)
    ch = inst.reference
    noise_rel = inst.readout.noise_std / np.sqrt(np.mean(meas**2))
    t0 = time.perf_counter()
    order = scene.mesh.element_order
    fit = fit_reference(ch.mesh, ch.layout.centres, ch.layout.radii, ch.ground, protocol, meas, scene.saline.conductivity,
                        z0, inst.readout.noise_std, order=order)
    t_fit = time.perf_counter() - t0
    # the same fit on the "measured" simulator's own model (its mesh, P2): how well the data pin the parameters
    own = fit_reference(other.mesh, lay.centres, lay.radii, other.ground, protocol, meas, scene.saline.conductivity, z0,
                        inst.readout.noise_std, order=2)
    inst.free()

    def errors(f) -> dict:
        return {"conductivity_rel": float(f.conductivity / sigma_true - 1),
                "contact_impedance_rel_median": float(np.median(np.abs(f.contact_impedance / z_true - 1))),
                "contact_impedance_rel_max": float(np.max(np.abs(f.contact_impedance / z_true - 1))),
                "centre_error_um_max": float(np.abs(f.centres[ring, :2] - c_true[ring, :2]).max() * 1e6),
                "misfit_before": f.before, "misfit_after": f.after, "iterations": f.iterations}

    result = {"mesh": args.mesh, "machine": f"{platform.machine()}, {cpu_name()}", "noise_rel": noise_rel,
              "truth": {"conductivity": sigma_true, "contact_impedance": z_true.tolist(),
                        "centre_offsets_um": (np.linalg.norm(c_true - lay.centres, axis=1) * 1e6).tolist()},
              "model_instrument": errors(fit), "model_order": order, "model_p2_its_own_mesh": errors(own),
              "seconds": {"measured_frame": t_meas, "fit": t_fit}}
    m, o = result["model_instrument"], result["model_p2_its_own_mesh"]
    L = ["# Sim-to-sim: a reference frame before and after fitting the sensor", "",
         f"`python benchmarks/bench_sim_to_sim.py --mesh {args.mesh}` on {result['machine']}. \"Measured\": the paper's "
         "sensor at rest from another simulator (the chamber meshed again, P2, saline 0.355 S/m, contact impedances "
         "×0.5–2 each, ring electrodes moved up to 0.1 mm); the model: the instrument's own (its mesh, "
         f"P{order}, the scene's values). Misfit: ‖V_model − V_meas‖/‖V_meas‖; the instrument's noise is {noise_rel:.2e} of it (74.2 dB).", "",
         "| model | misfit before | after | after, dB above the noise | saline error | contact impedance error (median / max) "
         "| electrode centres, largest error (µm) | iterations |", "|---|---|---|---|---|---|---|---|"]
    for name, r_ in ((f"the instrument's (P{order}, its mesh)", m), ("the measuring simulator's own (P2, its mesh)", o)):
        L.append(f"| {name} | {r_['misfit_before']:.2e} | {r_['misfit_after']:.2e} | {db(r_['misfit_after'], noise_rel):+.1f} | "
                 f"{r_['conductivity_rel']:+.2%} | {r_['contact_impedance_rel_median']:.1%} / {r_['contact_impedance_rel_max']:.1%} | "
                 f"{r_['centre_error_um_max']:.1f} | {r_['iterations']} |")
    L += ["", f"Fit on the instrument's model: {t_fit:.0f} s. The first row is the gap a map trained on this simulator "
          "carries to a sensor like the measured one once the sensor is fitted; the second, fitted on the measuring "
          "simulator's own model, how well a reference frame pins the sensor's parameters when the model is right."]
    write_pair(args.out, result, "\n".join(L) + "\n")
    print("\n".join(L))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
