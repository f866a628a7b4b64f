"""Do the two mesh paths agree on δV? Presses of the paper's 15 mm target (geometric indentation)
on the axis and over the electrode ring, each imaged through the fixed-topology morph and
through the remesh path as palpation frames take it (fTetWild remesh, pulled back onto the
reference chamber, δV = V(remesh) − V(its pull-back)), against the instrument's noise.

    python benchmarks/bench_path_agreement.py                  # paper preset (~15 min here)
    python benchmarks/bench_path_agreement.py --preset dataset # writes ..._dataset.{md,json}
    python benchmarks/bench_path_agreement.py --order 2        # P2 forward: ..._paper_p2.{md,json}

Beside each press: the saline's height over the electrode nearest the press (the membrane's
inner surface straight above the electrode's centre, pressed and at rest), and the share of the
difference on the measurements of that electrode. Remeshes go to a fresh
cache folder, so fTetWild really runs (one remesh per press: it is not deterministic, and the
spread between remeshes of one press is part of what the difference measures).
"""

from __future__ import annotations

import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from _machine import machine, write_pair

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
TARGET_RADIUS = 7.5e-3
# (x mm, y mm, depth mm): on the axis, then over electrode 0 (ring at 15 mm) ever deeper
PRESSES = ((0.0, 0.0, 2.0), (0.0, 0.0, 3.0), (13.0, 0.0, 1.5), (13.0, 0.0, 2.0), (13.0, 0.0, 2.5), (13.0, 0.0, 3.0))


def height_over(vertices: np.ndarray, faces: np.ndarray, point: np.ndarray) -> float:
    """Height (m) of the surface (``vertices``, ``faces``) straight above ``point`` on the base."""
    import trimesh

    scale = 1e3  # trimesh's ray tolerances are absolute: work in mm
    surf = trimesh.Trimesh(vertices * scale, faces, process=False)
    hits, _, _ = surf.ray.intersects_location([[point[0] * scale, point[1] * scale, -1.0]], [[0.0, 0.0, 1.0]])
    return float(hits[:, 2].min() / scale) if len(hits) else float("nan")


def run(preset: str, order: int = 1) -> dict:
    from jointsim.eit.forward import ForwardModel
    from jointsim.eit.protocol import skip_protocol
    from jointsim.geometry import dome_from_scene, electrode_layout
    from jointsim.mechanics.geometric import indent_dome
    from jointsim.mesh.chamber import chamber_mesh
    from jointsim.mesh.morph import ChamberMorpher, deform_chamber
    from jointsim.scene import load_scene

    from dataclasses import replace

    scene = load_scene(ROOT / "scenes" / "paper_sensor.toml").with_mesh_preset(preset)
    scene = replace(scene, mesh=replace(scene.mesh, element_order=order))
    ch = chamber_mesh(scene)  # the user's cache: the reference mesh
    os.environ["JOINTSIM_CACHE"] = tempfile.mkdtemp(prefix="jointsim-bench-agree-")
    dome = dome_from_scene(scene)
    layout = electrode_layout(scene)
    ring = slice(0, scene.electrodes.count)
    protocol = skip_protocol(scene.electrodes.count, scene.drive.skip, scene.drive.current)
    n_el = scene.electrodes.count

    def volts(chamber):
        return ForwardModel.from_chamber(chamber, scene).solve(scene.saline.conductivity).voltages(protocol)

    v_ref = volts(ch)
    mean_v = float(np.abs(v_ref).mean())
    noise = mean_v / 10 ** (scene.noise.snr_db / 20)
    rms = lambda x: float(np.sqrt(np.mean(np.square(x))))  # noqa: E731
    rows = []
    with ChamberMorpher(ch, dome) as morpher:
        for x, y, depth in PRESSES:
            pressed = indent_dome(dome, (x * 1e-3, y * 1e-3), depth * 1e-3, TARGET_RADIUS, scene.chamber.membrane_thickness).dome
            m = deform_chamber(morpher, pressed, scene.mesh, "morph")
            t = time.perf_counter()
            r = deform_chamber(morpher, pressed, scene.mesh, "remesh")
            t_remesh = time.perf_counter() - t
            dv_m = volts(m.chamber) - v_ref
            dv_r = r.change(volts, v_ref) - v_ref
            diff = (dv_m - dv_r).reshape(n_el, n_el)  # injection × measured electrode
            nearest = int(np.argmin(np.hypot(layout.centres[ring, 0] - x * 1e-3, layout.centres[ring, 1] - y * 1e-3)))
            c = layout.centres[nearest]
            rows.append({
                "xy_mm": [x, y], "depth_mm": depth,
                "height_over_electrode_mm": height_over(pressed.vertices, pressed.faces, c) * 1e3,
                "height_at_rest_mm": height_over(dome.vertices, dome.faces, c) * 1e3,
                "morph_path": m.path, "morph_shape_ratio": m.quality.min_shape / morpher.reference_quality.min_shape,
                "remesh_reason": r.reason, "remesh_tets": r.chamber.mesh.n_tets, "remesh_s": t_remesh,
                "dv_morph_uV": rms(dv_m) * 1e6, "dv_remesh_uV": rms(dv_r) * 1e6,
                "difference_uV": rms(diff) * 1e6, "difference_vs_noise": rms(diff) / noise,
                "nearest_electrode": nearest,
                "share_on_nearest": float(np.sum(diff[:, nearest] ** 2) / max(np.sum(diff**2), 1e-300)),
                "difference_elsewhere_uV": rms(np.delete(diff, nearest, axis=1)) * 1e6,
            })
            print(f"  ({x:g}, {y:g}) mm, {depth:g} mm: height over electrode {nearest} {rows[-1]['height_over_electrode_mm']:.2f} mm, "
                  f"difference {rows[-1]['difference_uV']:.2f} µV = {rows[-1]['difference_vs_noise']:.2f}× noise", flush=True)
    return {"preset": preset, "element_order": order, "tets": ch.mesh.n_tets, "mean_standing_uV": mean_v * 1e6, "instrument_snr_db": scene.noise.snr_db,
            "instrument_noise_uV": noise * 1e6, "presses": rows}


def _markdown(meta: dict, r: dict) -> str:
    L = ["# Do the morph and remesh paths agree on δV?", "",
         f"Command: `{meta['command']}`  ",
         f"Machine: {meta['machine']}; run {meta['date']}.  ",
         f"Chamber of `scenes/paper_sensor.toml` at the {r['preset']} preset: {r['tets']:,} tets, "
         f"P{r.get('element_order', 1)} elements in the forward model. "
         f"Rigid {2e3 * TARGET_RADIUS:g} mm target, geometric indentation. Instrument noise at "
         f"{r['instrument_snr_db']} dB re the mean standing |V| ({r['mean_standing_uV'] / 1e3:.2f} mV): "
         f"{r['instrument_noise_uV']:.2f} µV RMS.", "",
         "Morph: the reference chamber mesh morphed. Remesh: fTetWild on the pressed chamber, its δV against its own "
         "pull-back onto the reference chamber (as a palpation frame that falls back takes it). Height: of the pressed "
         "membrane's inner surface over the centre of the electrode nearest the press (at rest). Share: of the squared "
         "difference, the part on the measurements of that electrode.", "",
         "| press (x, y) mm | depth mm | height over nearest electrode mm | RMS δV morph µV | RMS δV remesh µV | RMS difference µV | × noise | "
         "share on nearest electrode | difference elsewhere µV | morph min η / reference |",
         "|---|---|---|---|---|---|---|---|---|---|"]
    for p in r["presses"]:
        L.append(f"| ({p['xy_mm'][0]:g}, {p['xy_mm'][1]:g}) | {p['depth_mm']:g} | "
                 f"{p['height_over_electrode_mm']:.2f} ({p['height_at_rest_mm']:.2f}) | "
                 f"{p['dv_morph_uV']:.1f} | {p['dv_remesh_uV']:.1f} | {p['difference_uV']:.2f} | "
                 f"{p['difference_vs_noise']:.2f} | {p['share_on_nearest']:.0%} (electrode {p['nearest_electrode']}) | "
                 f"{p['difference_elsewhere_uV']:.2f} | {p['morph_shape_ratio']:.3f} |")
    L += ["", "Remesh notes: " + "; ".join(f"({p['xy_mm'][0]:g}, {p['depth_mm']:g} mm) {p['remesh_reason']}" for p in r["presses"]), ""]
    return "\n".join(L)


def main() -> int:
    preset = sys.argv[sys.argv.index("--preset") + 1] if "--preset" in sys.argv else "paper"
    order = int(sys.argv[sys.argv.index("--order") + 1]) if "--order" in sys.argv else 1
    meta = {"command": "python benchmarks/bench_path_agreement.py" + (f" --preset {preset}" if preset != "paper" else "")
            + (f" --order {order}" if order != 1 else ""),
            "machine": machine(),
            "date": time.strftime("%Y-%m-%d")}
    r = run(preset, order)
    out = ROOT / "results" / (f"path_agreement_{preset}" + (f"_p{order}" if order != 1 else ""))
    text = _markdown(meta, r)
    write_pair(out, {"meta": meta, "result": r}, text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
