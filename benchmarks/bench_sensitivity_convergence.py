"""How a press's derivatives (jointsim.design.sensitivity) converge with the membrane's
resolution about the contact, the membrane's and the chamber's resolution elsewhere, and the
difference step, and what that does to the size bound.

    python benchmarks/bench_sensitivity_convergence.py   # writes results/design_study/convergence.{md,json}
    python benchmarks/bench_sensitivity_convergence.py --report-only   # the .md again from the .json
    python benchmarks/bench_sensitivity_convergence.py --finer   # adds the 8 mm sphere at 0.125 mm to the .json

Presses: spheres of 8, 15 and 30 mm diameter on the axis and at (6, 3) mm, 1 and 2 mm past first
contact, on the paper's sensor. Cases (chamber mesh preset / membrane rim vertices / levels of
refinement about the contact / probe µm): the dataset preset's membrane (64 rim vertices) refined
0 to 3 times about the contact (jointsim.design.sensitivity.contact_membrane); refined twice on a
128-rim membrane (a second resolution away from the contact), on the paper preset's chamber, and
with a 5 µm probe instead of 10. Per press and target parameter (x, y, depth, radius at fixed
depth): the relative change ‖J_a − J_b‖/‖J_b‖ of its column against the finest case
(dataset/64/3/10), and the diameter's Cramér–Rao bound (nuisances known, 74.2 dB) in each case.

``--soft``: a soft (neo-Hookean) 15 mm sphere of 300 kPa at (6, 0) mm, 1 and 2 mm deep, refined
1, 2 and 3 times about the contact and on the paper preset's chamber, and with the sphere's own
cells at the contact coarser or finer, layered or graded: how its columns (ln E among them) and
the modulus bound converge.

``--finer``: the smallest sphere (8 mm, whose contact is the fewest nodes) a level further,
0.125 mm at the contact two ways (64 rim vertices refined 4 times, 128 refined 3 times), against
which the three levels the design study reads at are measured.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from _machine import atomic_write, machine

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from jointsim.design.bounds import fisher, nuisance_prior, press_bounds  # noqa: E402
from jointsim.design.sensitivity import TARGET, TARGET_MODULUS, contact_membrane, press_sensitivity, target_names  # noqa: E402
from jointsim.instrument import Instrument  # noqa: E402
from jointsim.scene import SCENES_DIR, load_scene  # noqa: E402

DIAMETERS = (8e-3, 15e-3, 30e-3)
POSITIONS = ((0.0, 0.0), (6e-3, 3e-3))
DEPTHS = (1e-3, 2e-3)
CASES = (("dataset", 64, 0, 10e-6), ("dataset", 64, 1, 10e-6), ("dataset", 64, 2, 10e-6), ("dataset", 64, 2, 5e-6),
         ("dataset", 128, 2, 10e-6), ("paper", 64, 2, 10e-6), ("dataset", 64, 3, 10e-6))
REFERENCE = "dataset/64/3/10"
FINER = (("dataset", 64, 4, 10e-6), ("dataset", 128, 3, 10e-6))  # the 8 mm sphere only
FINER_PAIRS = (("dataset/64/3/10", "dataset/64/4/10", "three levels (the design study's default) against four"),
               ("dataset/128/3/10", "dataset/64/4/10", "0.125 mm at the contact two ways (128 rim three times, 64 rim "
                "four times)"))
# the last two entries: the sphere's cells where it touches, m (None: half the membrane's median
# edge, the model's default: 0.25 mm at two levels), and whether the sphere is graded
# (graded_hemisphere_mesh: those cells uniform over the membrane's refined zone, coarser inside)
# or layered (hemisphere_mesh: every layer repeats the surface, whose cells grow from the lowest
# point on, 3-4x by the contact's edge). At three levels the default's 0.125 mm layered sphere is
# ~135 k P2 nodes, a ~16 GB factorisation that did not finish in 72 min here: the three-level
# cases keep the sphere at 0.25 mm, and a coarser sphere at two levels says what that holds
SOFT = (("dataset", 64, 1, 10e-6, None, False), ("dataset", 64, 2, 10e-6, None, False), ("paper", 64, 2, 10e-6, None, False),
        ("dataset", 64, 2, 10e-6, 0.5e-3, False), ("dataset", 64, 3, 10e-6, 0.25e-3, False),
        ("dataset", 64, 2, 10e-6, 0.5e-3, True), ("dataset", 64, 2, 10e-6, 0.25e-3, True),
        ("dataset", 64, 3, 10e-6, 0.25e-3, True))
SOFT_PRESS = (15e-3, (6e-3, 0.0), 3e5)  # diameter m, centre m, Young's modulus Pa
SOFT_PAIRS = (("dataset/64/1/10", "dataset/64/2/10", "one level against two"),
              ("dataset/64/2/10", "dataset/64/3/10/t0.25", "two levels (the soft study's) against three, the layered "
               "sphere's cells 0.25 mm at its lowest point in both: at three levels coarser than the membrane over most "
               "of the contact"),
              ("dataset/64/2/10/t0.5", "dataset/64/2/10", "the sphere's cells at the contact, 0.5 against 0.25 mm (two "
               "levels)"),
              ("dataset/64/2/10/g0.5", "dataset/64/2/10/g0.25", "a graded sphere's cells over the contact zone, 0.5 "
               "against 0.25 mm (two levels)"),
              ("dataset/64/2/10/g0.25", "dataset/64/3/10/g0.25", "two levels against three, the graded sphere's cells "
               "0.25 mm in both"),
              ("dataset/64/2/10", "dataset/64/2/10/g0.25", "the sphere layered against graded, 0.25 mm at its lowest "
               "point (two levels)"),
              ("paper/64/2/10", "dataset/64/2/10", "the chamber mesh, paper against dataset preset"))
# what a soft case's row says that its figures do not
SOFT_NOTES = {"dataset/64/3/10/t0.25": "not a finer press: its x, depth and radius columns at 2 mm deep are 11-21x every other "
                                       "case's. Here, and only here, the layered sphere's contact nodes (its cells 0.25 mm "
                                       "at its lowest point, 0.8-1.0 mm by the contact's edge) are coarser than the "
                                       "membrane's facets (0.25 mm), which a node-to-surface contact does not resolve (its "
                                       "slave side must be the finer); not diagnosed further"}
OUT = ROOT / "results" / "design_study"


def run_case(preset: str, rim: int, levels: int, probe: float, diameters: tuple[float, ...] = DIAMETERS,
             positions: tuple = POSITIONS, modulus: float | None = None, target_mesh_size: float | None = None,
             graded_target: bool = False) -> dict:
    """Each press of ``diameters`` × ``positions`` (rigid, or soft of Young's ``modulus`` Pa,
    its cells ``target_mesh_size`` m where it touches, ``graded_target`` or layered) through
    DEPTHS: its target columns of ∂V/∂θ and its diameter (and modulus) bounds."""
    scene = load_scene(SCENES_DIR / "paper_sensor.toml").with_mesh_preset(preset)
    scene = replace(scene, membrane=replace(scene.membrane, rim_vertices=rim))
    t0 = time.perf_counter()
    inst = Instrument.build(scene, imaging=False)
    out = {"setup_s": time.perf_counter() - t0, "presses": [], "machine": machine()}
    for d in diameters:
        for xy in positions:
            t = time.perf_counter()
            model = contact_membrane(scene, d / 2, np.array(xy), max(DEPTHS), levels, modulus,
                                     target_mesh_size=target_mesh_size, graded_target=graded_target)
            on = inst.on_membrane(model)
            ps = press_sensitivity(on, model, np.array(xy), np.array(DEPTHS), probe=probe)
            prior = nuisance_prior(scene, ps.names)
            bounds = []
            for k in range(len(DEPTHS)):
                J = ps.jacobian[k]
                F = fisher(ps.jacobian_ref.T @ ps.jacobian_ref, J.T @ J, ps.noise_std, reference_frames=50)
                bounds.append(press_bounds(F, prior, ps.contact_jacobian[k]))
            press = {"diameter": d, "xy": list(xy), "target_jacobian": ps.jacobian[:, :, :len(target_names(ps.names))].tolist(),
                     "diameter_bound_known": [b.rms("known")["diameter"] for b in bounds],
                     "seconds": time.perf_counter() - t, "membrane_nodes": int(model.mesh.n_nodes)}
            if modulus is not None:
                press.update(modulus=modulus, target_mesh_size=model.target.mesh_size,
                             target_nodes=int(model.target.mesh.n_nodes), modulus_bound={kind: [b.rms(kind)["modulus"] for b in bounds]
                                                            for kind in ("known", "marginal")})
            out["presses"].append(press)
    inst.free()
    return out


# (case, against, what the pair measures)
PAIRS = (("dataset/64/2/5", "dataset/64/2/10", "the probe, 5 against 10 µm"),
         ("paper/64/2/10", "dataset/64/2/10", "the chamber mesh, paper against dataset preset"),
         ("dataset/128/2/10", "dataset/64/3/10", "two membranes with the same 0.25 mm edge at the contact (128 rim twice "
          "refined, 64 rim three times): the membrane away from the contact"),
         ("dataset/64/1/10", "dataset/64/2/10", "one level of refinement against two"),
         ("dataset/64/2/10", "dataset/64/3/10", "two levels (the design study's default) against three"))


def pair_changes(results: dict, a: str, b: str) -> tuple[np.ndarray, np.ndarray]:
    """(largest, median) over the presses both cases hold and their depths of ‖J_a − J_b‖/‖J_b‖
    per target column."""
    rel = []
    for pb in results[b]["presses"]:
        pa = next(p for p in results[a]["presses"] if p["diameter"] == pb["diameter"] and p["xy"] == pb["xy"])
        Ja, Jb = np.asarray(pa["target_jacobian"]), np.asarray(pb["target_jacobian"])
        rel += list(np.linalg.norm(Ja - Jb, axis=1) / np.linalg.norm(Jb, axis=1))
    return np.max(rel, axis=0), np.median(rel, axis=0)


def _machine_of(results: dict) -> str:
    """The machine the cases ran on: stored with each case (cases from before it was stored: the
    one the report named)."""
    stored = next((r["machine"] for r in results.values() if "machine" in r), None)
    if stored is None and (OUT / "convergence.md").exists():
        stored = next((ln.split("Machine: ", 1)[1].strip() for ln in (OUT / "convergence.md").read_text().splitlines()
                       if ln.startswith("Machine: ")), None)
    return stored or machine()


def _save(results: dict, finer: dict, soft: dict) -> None:
    """convergence.json with every case computed so far: a run stopped loses only its case."""
    OUT.mkdir(parents=True, exist_ok=True)
    atomic_write(OUT / "convergence.json", json.dumps({**results, **({"finer": finer} if finer else {}),
                                                      **({"soft": soft} if soft else {})}))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--report-only", action="store_true", help="rewrite convergence.md from the stored convergence.json")
    ap.add_argument("--finer", action="store_true", help="add the 8 mm sphere at 0.125 mm at the contact to the stored .json")
    ap.add_argument("--soft", action="store_true", help="add a soft sphere's convergence (its modulus column) to the stored .json")
    ap.add_argument("--soft-max-levels", type=int, default=3,
                    help="only the soft cases refined at most this many times")
    args = ap.parse_args()
    finer, soft = {}, {}
    if args.report_only or args.finer or args.soft:
        results = json.loads((OUT / "convergence.json").read_text())
        finer, soft = results.pop("finer", {}), results.pop("soft", {})
        for preset, rim, levels, probe in FINER if args.finer else ():
            key = f"{preset}/{rim}/{levels}/{probe * 1e6:g}"
            print("case", key, flush=True)
            finer[key] = run_case(preset, rim, levels, probe, DIAMETERS[:1])
            _save(results, finer, soft)
        d, xy, e = SOFT_PRESS
        for preset, rim, levels, probe, cell, graded in SOFT if args.soft else ():
            key = f"{preset}/{rim}/{levels}/{probe * 1e6:g}" + (f"/{'g' if graded else 't'}{cell * 1e3:g}" if cell else "")
            if key in soft or levels > args.soft_max_levels:  # stored by an earlier run, or left for a later one
                continue
            print("soft case", key, flush=True)
            soft[key] = run_case(preset, rim, levels, probe, (d,), (xy,), e, cell, graded)
            _save(results, finer, soft)
    else:
        results = {}
        for preset, rim, levels, probe in CASES:
            key = f"{preset}/{rim}/{levels}/{probe * 1e6:g}"
            print("case", key, flush=True)
            results[key] = run_case(preset, rim, levels, probe)
            _save(results, finer, soft)
    ref = REFERENCE
    lines = ["# Convergence of the press derivatives (jointsim.design.sensitivity)", "",
             "Command: `python benchmarks/bench_sensitivity_convergence.py`  ", f"Machine: {_machine_of(results)}", "",
             "Cases: chamber mesh preset / membrane rim vertices / levels of refinement about the contact / probe µm. "
             f"Relative change of each target column of ∂V/∂θ against `{ref}` (the finest membrane, same chamber), "
             "per press and depth; the last columns "
             "give the diameter's RMS Cramér–Rao bound (nuisances known, 74.2 dB) in mm.", ""]
    cases = list(results)
    hdr = "| press | depth mm | " + " | ".join(f"{c}: x, y, depth, radius" for c in cases if c != ref) + " | " + \
          " | ".join(f"bound {c}" for c in cases) + " |"
    lines += [hdr, "|" + "---|" * (2 + len(cases) - 1 + len(cases))]
    worst = {c: np.zeros(4) for c in cases}
    for i, p in enumerate(results[ref]["presses"]):
        Jr = np.asarray(p["target_jacobian"])
        for k, d in enumerate(DEPTHS):
            cells = []
            for c in cases:
                if c == ref:
                    continue
                Jc = np.asarray(results[c]["presses"][i]["target_jacobian"])
                rel = np.linalg.norm(Jc[k] - Jr[k], axis=0) / np.linalg.norm(Jr[k], axis=0)
                worst[c] = np.maximum(worst[c], rel)
                cells.append(", ".join(f"{100 * r:.1f} %" for r in rel))
            bounds = [f"{results[c]['presses'][i]['diameter_bound_known'][k] * 1e3:.3g}" for c in cases]
            lines.append(f"| {p['diameter'] * 1e3:g} mm at {tuple(round(v * 1e3, 1) for v in p['xy'])} mm | {d * 1e3:g} | "
                         + " | ".join(cells) + " | " + " | ".join(bounds) + " |")
    lines += ["", "Largest change over the presses (x, y, depth, radius):", ""]
    for c in cases:
        if c != ref:
            lines.append(f"- `{c}` against `{ref}`: " + ", ".join(f"{n} {100 * w:.1f} %" for n, w in zip(TARGET, worst[c])))
    lines += ["", "Pairs (largest / median change over the presses and depths; x, y, depth, radius):", ""]
    for a, b, what in PAIRS:
        big, med = pair_changes(results, a, b)
        lines.append(f"- `{a}` against `{b}` ({what}): " + ", ".join(
            f"{n} {100 * w:.2g} / {100 * m:.2g} %" for n, w, m in zip(TARGET, big, med)))
    if finer:
        both = {**results, **finer}
        lines += ["", "The 8 mm sphere a level finer (on the axis and at (6, 3) mm, 1 and 2 mm deep; largest / median "
                  "change, x, y, depth, radius; `python benchmarks/bench_sensitivity_convergence.py --finer`):", ""]
        for a, b, what in FINER_PAIRS:
            big, med = pair_changes(both, a, b)
            lines.append(f"- `{a}` against `{b}` ({what}): " + ", ".join(
                f"{n} {100 * w:.2g} / {100 * m:.2g} %" for n, w, m in zip(TARGET, big, med)))
        lines += ["", "Their diameter bounds (mm, nuisances known), per press and depth: " + "; ".join(
            f"{p['diameter'] * 1e3:g} mm at {tuple(round(v * 1e3, 1) for v in p['xy'])} mm: "
            + ", ".join(f"`{c}` " + "/".join(f"{x * 1e3:.3g}" for x in next(
                q for q in both[c]["presses"] if q["xy"] == p["xy"] and q["diameter"] == p["diameter"])["diameter_bound_known"])
                for c in ("dataset/64/3/10", *finer))
            for p in next(iter(finer.values()))["presses"])]
    if soft:
        d, xy, e = SOFT_PRESS
        lines += ["", f"## A soft target: {d * 1e3:g} mm, {e * 1e-3:g} kPa at {tuple(v * 1e3 for v in xy)} mm", "",
                  "`python benchmarks/bench_sensitivity_convergence.py --soft`, the sphere's mesh turned off the membrane's "
                  "rings (GENERIC_TURN, as the design study builds it). Largest / median change over the two "
                  "depths of each target column (x, y, depth, radius, ln E):", ""]
        names = (*TARGET, TARGET_MODULUS)
        for a, b, what in SOFT_PAIRS:
            if a not in soft or b not in soft:
                lines.append(f"- `{a}` against `{b}` ({what}): not computed yet")
                continue
            big, med = pair_changes(soft, a, b)
            lines.append(f"- `{a}` against `{b}` ({what}): " + ", ".join(
                f"{n} {100 * w:.2g} / {100 * m:.2g} %" for n, w, m in zip(names, big, med)))
        lines += ["", "The modulus bound (relative RMS error of E, one frame, 74.2 dB; nuisances known / marginalised) "
                  "at 1 and 2 mm deep:", "", "| case | 1 mm | 2 mm |", "|---|---|---|"]
        for c, r in soft.items():
            mb = r["presses"][0]["modulus_bound"]
            lines.append(f"| `{c}` | " + " | ".join(f"{100 * k:.3g} / {100 * m:.3g} %" for k, m in zip(mb["known"], mb["marginal"])) + " |")
        lines += [""] + [f"`{c}`: {note}." for c, note in SOFT_NOTES.items() if c in soft]
        lines += ["", f"Ran on {_machine_of(soft)}: " + ", ".join(
            f"`{c}` {r['presses'][0]['seconds']:.0f} s, {r['presses'][0]['membrane_nodes']} nodes"
            + (f" (the sphere's {r['presses'][0]['target_nodes']} nodes, cells {r['presses'][0]['target_mesh_size'] * 1e3:g} mm)"
               if "target_nodes" in r["presses"][0] else "") for c, r in soft.items())]
    lines += ["", "Time per press (2 depths' derivatives, the refined membrane built, s) and the membrane's nodes (mean): " + ", ".join(
        f"`{c}` {np.mean([p['seconds'] for p in r['presses']]):.1f} s, "
        f"{np.mean([p['membrane_nodes'] for p in r['presses']]):.0f}" for c, r in results.items())]
    if finer:
        lines += ["", f"The finer cases ran on {_machine_of(finer)}: " + ", ".join(
            f"`{c}` {np.mean([p['seconds'] for p in r['presses']]):.1f} s, "
            f"{np.mean([p['membrane_nodes'] for p in r['presses']]):.0f}" for c, r in finer.items())]
    atomic_write(OUT / "convergence.md", "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
