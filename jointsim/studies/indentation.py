"""The force–indentation sweep of the dome membrane (hyperelastic FEM in Warp): a spherical
target (rigid, or soft as the scene's [target] says) comes down vertically at (x, y) in steps
past first contact; the curve (CSV, PNG, JSON) and each step's deformed membrane (VTU) and inner
chamber surface (npz) are written to a folder. `jointsim indent` is its command line."""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path
from typing import Callable

import numpy as np

from .. import __version__
from ..io.export import atomic_path, write_npz, write_vtu
from ..io.figures import pyplot
from ..mechanics.build import membrane_from_scene
from ..mechanics.dome import membrane_material
from ..mechanics.fem import tet_fields
from ..mechanics.touch import depth_reach
from ..mesh.tetmesh import TetMesh
from ..scene import Scene

__all__ = ["indentation_sweep"]


def indentation_sweep(scene: Scene, radius_mm: float, xy_mm: tuple[float, float], depth_mm: float, step_mm: float,
                      out: Path, *, device: str = "cpu", progress: Callable[[int], None] | None = None,
                      announce: Callable[[str], None] | None = None) -> list[dict]:
    """Press the scene's membrane by a sphere of ``radius_mm`` at ``xy_mm`` to ``depth_mm`` past
    first contact in steps of ``step_mm``; write the results into ``out`` and return one row per
    step (depth, force, contact area, displaced volume, peak strain, penetration, Newton
    iterations). ``announce`` gets a one-line description of the model before the first step,
    ``progress`` 1 after each. A depth beyond what the dome can take is refused (ValueError)."""
    radius = radius_mm
    model = membrane_from_scene(scene, radius * 1e-3, device=device)
    xy = np.array(xy_mm) * 1e-3
    top = model.first_contact_height(xy)
    depths = np.arange(1, int(round(depth_mm / step_mm)) + 1) * step_mm
    reach = depth_reach(model, top)
    if depths[-1] * 1e-3 > reach:
        raise ValueError(f"--depth-mm = {depth_mm}: beyond what the dome can take here (at most {reach * 1e3:.2f} mm)")
    rows = []
    corners = TetMesh(model.mesh.nodes, model.mesh.corner_tets)  # ParaView's view of the quadratic elements
    material = membrane_material(scene.membrane)
    if announce is not None:
        announce(f"target r = {radius:g} mm at ({xy_mm[0]:g}, {xy_mm[1]:g}) mm, membrane {model.mesh.n_nodes} nodes "
                 f"({scene.membrane.element}, {scene.membrane.rim_vertices} rim vertices, "
                 f"{scene.membrane.layers} layer{'' if scene.membrane.layers == 1 else 's'})")
    for i, d in enumerate(depths):
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
        write_vtu(out / f"membrane_{i:03d}.vtu", corners, point_data={"displacement": st.u},
                  cell_data=tet_fields(corners.nodes, corners.tets, st.u, material))
        write_npz(out / f"inner_surface_{i:03d}.npz", vertices=st.dome.vertices, faces=st.dome.faces, rim=st.dome.rim)
        if progress is not None:
            progress(1)
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(rows[0]))
    w.writeheader()
    w.writerows(rows)
    with atomic_path(out / "force_indentation.csv") as tmp:
        tmp.write_text(buf.getvalue())
    _plot(out / "force_indentation.png", rows, radius, scene.target)
    with atomic_path(out / "indentation.json") as tmp:
        tmp.write_text(json.dumps({"jointsim": __version__, "scene": scene.to_dict(), "target_radius_mm": radius,
                                   "xy_mm": list(xy_mm), "rim_vertices": scene.membrane.rim_vertices, "rows": rows}, indent=2, default=float))
    return rows


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
