"""Force–indentation sweep of the dome membrane (hyperelastic FEM in Warp): a spherical target
(rigid, or soft as the scene's [target] says) comes down vertically at (x, y) in steps past
first contact; writes the curve (CSV, PNG) and each step's deformed membrane (VTU) and inner
chamber surface (npz) to --out."""

from __future__ import annotations

import argparse
import csv
import io
import json
from dataclasses import replace
from pathlib import Path

import numpy as np
from tqdm import tqdm

from .. import __version__
from ..io.export import atomic_path, write_npz, write_vtu
from ..io.figures import pyplot
from ..scene import membrane_layers, membrane_rim_vertices
from .common import (
    add_scene_arguments,
    add_target_size_arguments,
    scene_from_args,
    target_radius_mm,
)

OUTPUT = "folder"  # what --out names (checked before any work: cli.common.check_output)
HELP = "force-indentation sweep of the dome membrane (FEM): CSV, PNG, VTU"


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_scene_arguments(p)
    p.add_argument("--out", type=Path, default=Path("results/indentation"), help="output folder")
    add_target_size_arguments(p, "the scene's [target]")
    p.add_argument("--x-mm", type=float, default=0.0, help="contact position x (default 0)")
    p.add_argument("--y-mm", type=float, default=0.0, help="contact position y (default 0)")
    p.add_argument("--depth-mm", type=float, default=3.0, help="final indentation past first contact (default 3)")
    p.add_argument("--step-mm", type=float, default=0.5, help="step (default 0.5: one 50 Hz frame at 25 mm/s)")
    p.add_argument("--dome-rim", type=int, help="membrane resolution: vertices on the rim (default: the scene's membrane.rim_vertices)")
    p.add_argument("--layers", type=int, help="element layers through the thickness (default: the scene's)")
    p.add_argument("--device", default="cpu", help="Warp device of the element kernel: cpu (default) or cuda / cuda:N where a GPU is")


def run(args: argparse.Namespace) -> int:
    from ..mechanics.build import membrane_from_scene
    from ..mechanics.fem import warp_device
    from ..mesh.tetmesh import TetMesh

    scene = scene_from_args(args)
    device = warp_device(args.device, "--device")
    radius = target_radius_mm(args, scene.target.radius * 1e3)
    if not args.depth_mm > 0:
        raise ValueError(f"--depth-mm = {args.depth_mm}: must be > 0")
    if not 0 < args.step_mm <= args.depth_mm:
        raise ValueError(f"--step-mm = {args.step_mm}: must be in (0, --depth-mm = {args.depth_mm}]")
    if args.dome_rim is not None:
        scene = replace(scene, membrane=replace(scene.membrane, rim_vertices=membrane_rim_vertices(args.dome_rim, scene.membrane.element, "--dome-rim")))
    if args.layers is not None:
        scene = replace(scene, membrane=replace(scene.membrane, layers=membrane_layers(args.layers, "--layers")))
    c = scene.chamber
    model = membrane_from_scene(scene, radius * 1e-3, device=device)
    xy = np.array([args.x_mm, args.y_mm]) * 1e-3
    top = model.first_contact_height(xy)
    depths = np.arange(1, int(round(args.depth_mm / args.step_mm)) + 1) * args.step_mm
    if depths[-1] * 1e-3 > top - radius * 1e-3 - c.membrane_thickness:
        raise ValueError(
            f"--depth-mm = {args.depth_mm}: beyond what the dome can take here "
            f"(at most {(top - radius * 1e-3 - c.membrane_thickness) * 1e3:.2f} mm)"
        )
    out: Path = args.out
    rows = []
    corners = TetMesh(model.mesh.nodes, model.mesh.corner_tets)  # ParaView's view of the quadratic elements
    print(
        f"jointsim indent: scene {scene.name}, target r = {radius:g} mm at ({args.x_mm:g}, {args.y_mm:g}) mm, "
        f"membrane {model.mesh.n_nodes} nodes ({scene.membrane.element}, {scene.membrane.rim_vertices} rim vertices, "
        f"{scene.membrane.layers} layer{'' if scene.membrane.layers == 1 else 's'})"
    )
    for i, d in enumerate(tqdm(depths, unit="step", disable=None)):
        st = model.press(np.array([xy[0], xy[1], top - d * 1e-3]))
        rows.append(
            {
                "depth_mm": float(d),
                "force_N": float(st.force[2]),
                "force_x_N": float(st.force[0]),
                "force_y_N": float(st.force[1]),
                "contact_area_mm2": st.contact_area * 1e6,
                "displaced_volume_mm3": st.displaced_volume * 1e9,
                "peak_strain": st.peak_strain,
                "penetration_um": st.penetration * 1e6,
                "newton_iterations": st.iterations,
                "residual_N": st.residual,
            }
        )
        write_vtu(out / f"membrane_{i:03d}.vtu", corners, point_data={"displacement": st.u})
        write_npz(out / f"inner_surface_{i:03d}.npz", vertices=st.dome.vertices, faces=st.dome.faces, rim=st.dome.rim)
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(rows[0]))
    w.writeheader()
    w.writerows(rows)
    with atomic_path(out / "force_indentation.csv") as tmp:
        tmp.write_text(buf.getvalue())
    _plot(out / "force_indentation.png", rows, radius, scene.target)
    with atomic_path(out / "indentation.json") as tmp:
        tmp.write_text(json.dumps({"jointsim": __version__, "scene": scene.to_dict(), "target_radius_mm": radius,
                                   "xy_mm": [args.x_mm, args.y_mm], "rim_vertices": scene.membrane.rim_vertices, "rows": rows}, indent=2, default=float))
    for r in rows:
        print(f"  {r['depth_mm']:.2f} mm: F {r['force_N'] * 1e3:7.2f} mN, displaced {r['displaced_volume_mm3']:6.1f} mm^3, "
              f"{r['newton_iterations']} Newton iterations")
    print(f"  wrote {out}/force_indentation.csv, .png, membrane_*.vtu, inner_surface_*.npz")
    return 0


def _plot(path: Path, rows: list[dict], radius: float, target) -> None:
    plt = pyplot()

    d = [r["depth_mm"] for r in rows]
    fig, ax = plt.subplots(figsize=(5, 3.5))
    ax.plot([0] + d, [0] + [r["force_N"] * 1e3 for r in rows], "o-", color="tab:red")
    ax.set_xlabel("indentation past first contact (mm)")
    ax.set_ylabel("force (mN)", color="tab:red")
    ax2 = ax.twinx()
    ax2.plot(d, [r["displaced_volume_mm3"] for r in rows], "s--", color="tab:blue")
    ax2.set_ylabel("displaced saline (mm³)", color="tab:blue")
    kind = f"soft sphere (E {target.youngs_modulus / 1e3:g} kPa)" if target.kind == "soft" else "rigid sphere"
    ax.set_title(f"{kind} r = {radius:g} mm on the dome")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=120)
    plt.close(fig)
