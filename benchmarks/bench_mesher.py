"""The chamber mesher: gmsh (the package's, since 2026-11-27) against fTetWild (the package's
before, loaded from git at FTETWILD_COMMIT and run through pytetwild), on the paper's chamber at
the three presets: tetrahedra, seconds to mesh, element quality, whether a second run gives the
same mesh, and the mesh-noise floor of the voltages.

    python benchmarks/bench_mesher.py          # writes results/mesher.{md,json}; needs pytetwild
    python benchmarks/bench_mesher.py --report # re-renders the Markdown from the JSON

Each mesher meshes each preset four times, without the cache: the chamber, the same chamber
again, the chamber with its electrode ring turned by one pitch (22.5°, a symmetry of the
physical sensor), and the chamber with its dome's vertices moved by at most 1 µm (a jitter far
below the physical scale). The floors are the RMS difference of the 256 skip-8 voltages (P1, against
ground; the turned chamber's permuted back) in dB re the mean standing |V|, the instrument's
SNR convention (74.2 dB): `again` is the run-to-run floor (infinite for a deterministic mesher);
`rotate` and `jitter` are floors of meshing itself, each blind to what a mesher repeats under
that change (a mesher that meshes the turned chamber as the turned mesh has no `rotate` floor
whatever its discretisation error). fTetWild meshes at its own presets (max edge 3.0 / 2.2 /
1.1 mm), gmsh at the package's (2.6 / 1.9 / 0.97 mm): each as tuned to similar tetrahedron counts.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
import types
from dataclasses import replace
from pathlib import Path

import numpy as np

from _machine import machine, write_pair

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
FTETWILD_COMMIT = "e831c57"  # the last commit whose jointsim/mesh/chamber.py meshed with fTetWild
FTETWILD_PRESETS = {"test": (3.0, 4.0), "dataset": (2.2, 6.0), "paper": (1.1, 10.0)}  # max edge mm, refinement
FTETWILD_OPTIONS = {"epsilon_rel": 3e-4, "stop_energy": 30.0, "max_opt_iter": 20}
PRESETS = ("test", "dataset", "paper")
STEM = ROOT / "results" / "mesher"


def _ftetwild_module():
    r = subprocess.run(["git", "show", f"{FTETWILD_COMMIT}:jointsim/mesh/chamber.py"], cwd=ROOT, capture_output=True, text=True)
    if r.returncode:
        raise SystemExit(f"bench_mesher: git show {FTETWILD_COMMIT}:jointsim/mesh/chamber.py failed: {r.stderr.strip()}")
    mod = types.ModuleType("jointsim.mesh._chamber_ftetwild")
    mod.__package__ = "jointsim.mesh"
    sys.modules[mod.__name__] = mod  # its dataclasses look their module up
    exec(compile(r.stdout, f"chamber.py@{FTETWILD_COMMIT}", "exec"), mod.__dict__)
    return mod


def _meshers():
    from jointsim.geometry import chamber_from_scene, electrode_layout
    from jointsim.mesh.chamber import chamber_mesh, mesh_chamber, reference_surface

    def gmsh(scene, surface=None):
        if surface is None:
            return chamber_mesh(scene, use_cache=False)
        return mesh_chamber(surface, electrode_layout(scene), scene.mesh, use_cache=False)

    old = _ftetwild_module()

    def ftetwild(scene, surface=None):
        edge, refine = FTETWILD_PRESETS[scene.mesh.preset]
        spec = types.SimpleNamespace(max_edge=edge * 1e-3, electrode_refinement=refine, refinement_zone=scene.mesh.refinement_zone,
                                     grading=scene.mesh.grading, **FTETWILD_OPTIONS)
        return old.mesh_chamber(chamber_from_scene(scene) if surface is None else surface, electrode_layout(scene), spec, use_cache=False)

    return {"gmsh": (gmsh, reference_surface), "fTetWild": (ftetwild, chamber_from_scene)}


def _voltages(chamber, scene) -> np.ndarray:
    from jointsim.eit.forward import ForwardModel
    from jointsim.eit.protocol import skip_protocol

    fields = ForwardModel.from_chamber(chamber, scene).solve(scene.saline.conductivity)
    return fields.voltages(skip_protocol(scene.electrodes.count, 8, scene.drive.current))


def _floor_db(v: np.ndarray, other: np.ndarray) -> float:
    d = float(np.sqrt(np.mean((other - v) ** 2)))
    return float("inf") if d == 0 else float(20 * np.log10(np.abs(v).mean() / d))


def run() -> dict:
    from jointsim.scene import SCENES_DIR, load_scene
    from jointsim.studies.protocol_study import jitter_surface

    base = load_scene(SCENES_DIR / "paper_sensor.toml")
    rows = []
    for name, (mesh, surface_of) in _meshers().items():
        for preset in PRESETS:
            scene = base.with_mesh_preset(preset)
            n = scene.electrodes.count
            turned = replace(scene, electrodes=replace(scene.electrodes, first_angle_deg=scene.electrodes.first_angle_deg + 360.0 / n))
            t0 = time.perf_counter()
            ch = mesh(scene)
            seconds = time.perf_counter() - t0
            again, rot, jit = mesh(scene), mesh(turned), mesh(scene, jitter_surface(surface_of(scene), 1e-6))
            q = ch.quality()
            v = _voltages(ch, scene)
            # electrode l of the turned ring sits where l + 1 was: injection i, electrode j of the
            # original is injection i − 1, electrode j − 1 of the turned one
            vr = np.roll(np.roll(_voltages(rot, turned).reshape(n, n), 1, axis=0), 1, axis=1).ravel()
            same = bool(np.array_equal(again.mesh.nodes, ch.mesh.nodes) and np.array_equal(again.mesh.tets, ch.mesh.tets))
            rows.append({"mesher": name, "preset": preset, "tets": ch.mesh.n_tets, "seconds": seconds,
                         "min_dihedral_deg": q.min_dihedral_deg, "max_dihedral_deg": q.max_dihedral_deg,
                         "mean_radius_ratio": q.mean_radius_ratio, "volume_m3": q.volume, "same_mesh_again": same,
                         "floor_again_db": _floor_db(v, _voltages(again, scene)), "floor_rotate_db": _floor_db(v, vr),
                         "floor_jitter_db": _floor_db(v, _voltages(jit, scene))})
            print(json.dumps(rows[-1]), flush=True)
    return {"machine": machine(), "ftetwild_commit": FTETWILD_COMMIT, "rows": rows}


def markdown(r: dict) -> str:
    lines = [
        "# The chamber mesher: gmsh against fTetWild",
        "",
        f"`python benchmarks/bench_mesher.py` on {r['machine']}. The paper's chamber "
        f"(`scenes/paper_sensor.toml`) at each preset; fTetWild as the package ran it until "
        f"{r['ftetwild_commit']} (through pytetwild), gmsh as it runs it now. Floors: RMS change of "
        "the 256 skip-8 voltages (P1) in dB re the mean standing |V| (the instrument: 74.2 dB); "
        "`again`: the same chamber meshed a second time; `rotate`: the electrode ring turned by one "
        "pitch and the voltages permuted back; `jitter`: the dome's vertices moved by at most 1 µm.",
        "",
        "| mesher | preset | tets | mesh s | min / max dihedral ° | mean radius ratio | same mesh again | floor again dB | floor rotate dB | floor jitter dB |",
        "|---|---|---:|---:|---|---:|---|---:|---:|---:|",
    ]
    for x in r["rows"]:
        lines.append(f"| {x['mesher']} | {x['preset']} | {x['tets']:,} | {x['seconds']:.1f} | "
                     f"{x['min_dihedral_deg']:.1f} / {x['max_dihedral_deg']:.1f} | {x['mean_radius_ratio']:.3f} | "
                     f"{'yes' if x['same_mesh_again'] else 'no'} | {x['floor_again_db']:.1f} | {x['floor_rotate_db']:.1f} | {x['floor_jitter_db']:.1f} |")
    lines += ["", "An infinite `again` floor: the second mesh is the first bit for bit. The `rotate` and "
              "`jitter` floors measure how much the voltages depend on which mesh of the same chamber "
              "is drawn; each is blind to what the mesher repeats under its change (gmsh's dome and base "
              "are near-symmetric under a turn by one pitch, so its `rotate` floor is an upper bound on "
              "its SNR, not the distance to the converged voltages). The morphed (fixed-topology) frame "
              "path, which palpation and datasets take, has no such floor at all."]
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--report", action="store_true", help="re-render the Markdown from results/mesher.json")
    args = ap.parse_args()
    data = json.loads(STEM.with_suffix(".json").read_text()) if args.report else run()
    write_pair(STEM, data, markdown(data))
    print(f"wrote {STEM.with_suffix('.md')}")


if __name__ == "__main__":
    main()
