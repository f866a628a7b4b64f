"""Accuracy per second of the EIT forward: how far a frame's voltages and δV are from their
converged limit, against what the frame's forward costs, for P1 and P2 elements on the mesh
presets and on meshes graded at the electrodes' rims.

    python benchmarks/bench_forward_accuracy.py            # ~10 min here; writes results/forward_accuracy.{md,json}

The chamber of ``scenes/paper_sensor.toml``; the 256 skip-8 voltages of the untouched chamber
(V) and their change (δV) under three presses of the paper's 15 mm target (geometric
indentation, the fixed-topology morph every palpation and dataset frame takes). The limit is
P2 on a mesh refined 20× at the rims, its dome's dent sampled by 256 rim vertices (its
distance from the next coarser configuration is reported). Cost: the frame's forward as a dataset worker runs it (one thread; the CEM pattern
and PARDISO's analysis kept from the reference chamber: assembly + numeric factorisation + the
lead-field solves), median of the presses; the one-off set-up per reference chamber (meshing;
the model, electrode patches and first factorisation) beside it. Floors in dB re the mean
standing |V| (the instrument: 74.2 dB): the distance to the limit, the chamber turned by one
electrode pitch (voltages permuted back) and its dome jittered by ≤ 1 µm.
"""

from __future__ import annotations

import os

for _v in ("MKL_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS"):  # as a dataset worker runs
    os.environ[_v] = "1"

import argparse  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from dataclasses import replace  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from _machine import machine, write_pair  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
TARGET_RADIUS = 7.5e-3
PRESSES = ((0.0, 0.0, 2.0), (13.0, 0.0, 2.0), (6.0, 4.0, 1.0))  # (x mm, y mm, depth mm)
# label: (max edge mm, electrode refinement, rim refinement, grading, element order, dome rim
# vertices (0: from the max edge)); a preset's name stands for its sizes as
# jointsim.scene.MESH_PRESETS defines them
CONFIGS: dict[str, tuple] = {
    "test P1": ("test", 1), "dataset P1": ("dataset", 1), "paper P1": ("paper", 1),
    "test P2": ("test", 2), "dataset P2": ("dataset", 2), "paper P2": ("paper", 2),
    "rim P1 2.6/2/40": (2.6, 2.0, 40.0, 0.35, 1, 0), "rim P1 1.9/2/40 dome 144": (1.9, 2.0, 40.0, 0.35, 1, 144),
    "rim P2 3.5/1/12 g0.7": (3.5, 1.0, 12.0, 0.7, 2, 0), "rim P2 3.5/1/12 g0.7 dome 144": (3.5, 1.0, 12.0, 0.7, 2, 144),
    "rim P2 3.0/1.5/10 g0.6 dome 144": (3.0, 1.5, 10.0, 0.6, 2, 144),
    "dataset_p2 (2.6/2/10 g0.6 dome 144)": ("dataset_p2", 2),
    "rim P2 3.0/1.5/10 g0.6 dome 192": (3.0, 1.5, 10.0, 0.6, 2, 192),
    "rim P2 1.9/6/20 dome 192": (1.9, 6.0, 20.0, 0.35, 2, 192),
}
REFERENCE = ("rim P2 1.9/6/20 dome 256", (1.9, 6.0, 20.0, 0.35, 2, 256))

def scene_of(config) -> object:
    from jointsim.scene import MM, SCENES_DIR, load_scene

    base = load_scene(SCENES_DIR / "paper_sensor.toml")
    if isinstance(config[0], str):
        preset, order = config
        s = base.with_mesh_preset(preset)
        return replace(s, mesh=replace(s.mesh, element_order=order))
    edge, refine, rim, grading, order, dome_rim = config
    return replace(base, mesh=replace(base.mesh, preset="custom", max_edge=edge * MM, electrode_refinement=refine,
                                      rim_refinement=rim, grading=grading, element_order=order, dome_rim_vertices=dome_rim))


def measure(scene) -> dict:
    """V, δV per press, floors and costs of ``scene``'s chamber mesh and element order."""
    from jointsim.eit.forward import ForwardModel
    from jointsim.eit.protocol import skip_protocol
    from jointsim.geometry import dome_from_scene
    from jointsim.mechanics.geometric import indent_dome
    from jointsim.mesh.chamber import chamber_mesh
    from jointsim.mesh.morph import ChamberMorpher, deform_chamber
    from jointsim.studies.protocol_study import mesh_noise_floor

    n = scene.electrodes.count
    order = scene.mesh.element_order
    protocol = skip_protocol(n, 8, scene.drive.current)
    sigma = scene.saline.conductivity
    t = time.perf_counter()
    ch = chamber_mesh(scene)
    mesh_s = time.perf_counter() - t
    t = time.perf_counter()
    model = ForwardModel.from_chamber(ch, scene).shared()
    fields = model.solve(sigma)
    v = fields.voltages(protocol)
    setup_s = time.perf_counter() - t
    dofs = model.assembler.n_dofs
    patches = ch.patches(order)
    dome = dome_from_scene(scene)
    dv, frame_s = [], []
    with ChamberMorpher(ch, dome) as morpher:
        for x, y, depth in PRESSES:
            pressed = indent_dome(dome, (x * 1e-3, y * 1e-3), depth * 1e-3, TARGET_RADIUS, scene.chamber.membrane_thickness).dome
            dc = deform_chamber(morpher, pressed, scene.mesh, "morph")
            t = time.perf_counter()
            v1 = model.on(dc.chamber.mesh, patches).solve(sigma).voltages(protocol)
            frame_s.append(time.perf_counter() - t)
            dv.append(v1 - v)
    model.free()
    floor = mesh_noise_floor(scene, fields, {8: protocol})  # the ring turned by one pitch; the dome jittered by 1 µm
    return {"tets": ch.mesh.n_tets, "dofs": dofs, "mesh_s": mesh_s, "setup_s": setup_s,
            "frame_forward_s": float(np.median(frame_s)), "v": v.tolist(), "dv": [d.tolist() for d in dv],
            "floor_rotate_db": floor["rotate"][8], "floor_jitter_db": floor["jitter"][8]}


def floor_db(v: np.ndarray, other: np.ndarray) -> float:
    d = float(np.sqrt(np.mean((np.asarray(other) - v) ** 2)))
    return float("inf") if d == 0 else float(20 * np.log10(np.abs(v).mean() / d))


def errors(row: dict, limit: dict, carrying: np.ndarray) -> dict:
    v, vl = np.asarray(row["v"]), np.asarray(limit["v"])
    rel = lambda a, b, m=slice(None): float(np.linalg.norm((a - b)[m]) / np.linalg.norm(b[m]))  # noqa: E731
    dv = [rel(np.asarray(a), np.asarray(b)) for a, b in zip(row["dv"], limit["dv"])]
    dv_other = [rel(np.asarray(a), np.asarray(b), ~carrying) for a, b in zip(row["dv"], limit["dv"])]
    return {"v_err": rel(v, vl), "v_err_carrying": rel(v, vl, carrying), "v_err_other": rel(v, vl, ~carrying),
            "dv_err": dv, "dv_err_other": dv_other, "limit_db": floor_db(vl, v)}


def run(names: list[str]) -> dict:
    from jointsim.eit.protocol import skip_protocol

    os.environ["JOINTSIM_CACHE"] = tempfile.mkdtemp(prefix="jointsim-bench-accuracy-")  # meshing timed from empty
    p = skip_protocol(16, 8, 120e-6)
    carrying = (np.abs(p.stim) > 0).reshape(-1)  # all-vs-ground: measurement (s, l) is electrode l
    label, config = REFERENCE
    limit = measure(scene_of(config))
    print(f"{label}: {limit['tets']} tets, {limit['frame_forward_s']:.2f} s", flush=True)
    rows = []
    for name in names:
        r = measure(scene_of(CONFIGS[name]))
        r.update(errors(r, limit, carrying), name=name, config=list(CONFIGS[name]))
        rows.append(r)
        print(f"{name}: {r['tets']} tets, V {100 * r['v_err']:.2f} %, dV {', '.join(f'{100 * e:.2f}' for e in r['dv_err'])} %, "
              f"{r['frame_forward_s']:.3f} s", flush=True)
    return {"machine": machine(), "reference": {"name": label, "config": list(config), **limit}, "rows": rows}


def markdown(r: dict) -> str:
    ref = r["reference"]
    lines = [
        "# Accuracy per second of the EIT forward",
        "",
        "Command: `python benchmarks/bench_forward_accuracy.py`  ",
        f"Machine: {r['machine']}; one thread (as a dataset worker).",
        "",
        __doc__.split("\n\n", 2)[2].strip().replace("\n", " "),
        "",
        f"Limit ({ref['name']}; max edge mm / electrode refinement / rim refinement, grading, dome rim vertices): "
        f"{ref['tets']:,} tets, {ref['dofs']:,} unknowns. Errors: relative 2-norm against it; δV per press "
        "(x, y, depth mm) " + ", ".join(f"({x:g}, {y:g}, {d:g})" for x, y, d in PRESSES) + "; `carrying`: the "
        "32 of 256 measurements on the two current-carrying electrodes of their injection, `other`: the rest.",
        "",
        "| configuration | tets | unknowns | V err % | on carrying % | other % | δV err % (3 presses) | δV other % | "
        "limit dB | rotate dB | jitter dB | frame forward s | set-up s | mesh s |",
        "|---|---:|---:|---:|---:|---:|---|---|---:|---:|---:|---:|---:|---:|",
    ]
    for x in r["rows"]:
        lines.append(
            f"| {x['name']} | {x['tets']:,} | {x['dofs']:,} | {100 * x['v_err']:.2f} | {100 * x['v_err_carrying']:.2f} | "
            f"{100 * x['v_err_other']:.3f} | {' / '.join(f'{100 * e:.2f}' for e in x['dv_err'])} | "
            f"{' / '.join(f'{100 * e:.2f}' for e in x['dv_err_other'])} | {x['limit_db']:.1f} | {x['floor_rotate_db']:.1f} | "
            f"{x['floor_jitter_db']:.1f} | {x['frame_forward_s']:.3f} | {x['setup_s']:.2f} | {x['mesh_s']:.1f} |")
    lines += ["", f"The limit's own floors: rotate {ref['floor_rotate_db']:.1f} dB, jitter {ref['floor_jitter_db']:.1f} dB; "
              f"its frame forward {ref['frame_forward_s']:.2f} s."]
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--configs", default=",".join(CONFIGS), help="comma-separated labels of CONFIGS")
    ap.add_argument("--out", default=str(ROOT / "results" / "forward_accuracy"), help="output stem (.md, .json)")
    a = ap.parse_args()
    names = [c for c in a.configs.split(",") if c]
    unknown = [c for c in names if c not in CONFIGS]
    if unknown:
        ap.error(f"--configs: unknown {unknown}; known: {list(CONFIGS)}")
    r = run(names)
    write_pair(Path(a.out), r, markdown(r))


if __name__ == "__main__":
    main()
