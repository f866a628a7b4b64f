"""Writing a palpation run to disk: the VTU time series for ParaView (deformed membrane, chamber
mesh, voxel image per frame, with ``.pvd`` collections), the set-up record, the Fig. 4-like
PNGs, and the JSON/Markdown summary. Every file is written under a temporary name and renamed.

The figures and summary are made from the finalised record file (``palpation.h5``) and the
set-up record (``setup.json`` + ``grid.npz``) alone, so they can be regenerated without
recomputing anything."""

from __future__ import annotations

import json
import platform
import re
import time
from pathlib import Path
from typing import Any

import numpy as np

from .. import __version__
from ..io.export import atomic_path, write_npz, write_voxels_vtu, write_vtu
from ..io.figures import pyplot
from ..io.records import Records
from ..mechanics.dome import membrane_material
from ..mechanics.fem import tet_fields
from ..mesh.electrodes import electrode_tags
from ..mesh.tetmesh import TetMesh
from ..metrics import largest_cluster
from ..reconstruction.grid import ChamberGrid, VoxelGrid
from ..scene import UNRECORDED_ELEMENT
from .pipeline import MESH_PATHS, STAGES, Frame, Palpation

__all__ = ["VtuSeries", "write_pvd", "write_setup", "load_grid", "summarise", "write_report"]

VTU_KINDS = ("membrane", "chamber", "image")


# ---------------------------------------------------------------------------------------------
# Per-frame VTU
# ---------------------------------------------------------------------------------------------


class VtuSeries:
    """``export`` hook for :func:`run_palpation`: writes ``out/vtu/{membrane,chamber,image}_NNNNN.vtu``
    for every ``every``-th frame of each target (and its last), NNNNN the record index.

    membrane: the membrane's corner tetrahedra at their deformed positions, point data
    ``displacement`` (m); chamber: the chamber mesh of the frame, cell data ``dsigma`` (the
    image mapped onto the elements, S/m; morph path only) and point data ``displacement``
    (morph path only); image: the voxel grid with ``dsigma`` (S/m), ``dsigma_normalised``
    (in units of its noise std) and ``cluster`` (1 in the perturbation)."""

    def __init__(self, out: str | Path, pal: Palpation, every: int = 1):
        if not (isinstance(every, int) and every >= 1):
            raise ValueError(f"every = {every!r}: must be an integer >= 1 (frames between VTU exports)")
        self.dir = Path(out) / "vtu"
        self.pal = pal
        self.every = every
        self.material = membrane_material(pal.scene.membrane)

    def wants(self, frame: Frame) -> bool:
        return frame.frame % self.every == 0 or frame.frame == frame.segment.n_frames - 1

    def __call__(self, frame: Frame) -> None:
        if not self.wants(frame):
            return
        pal, i = self.pal, frame.index
        inst = pal.instrument
        m = pal.membrane_mesh
        u = frame.state.u[: m.n_nodes]
        write_vtu(self.dir / f"membrane_{i:05d}.vtu", TetMesh(m.nodes + u, m.tets), point_data={"displacement": u},
                  cell_data=tet_fields(m.nodes, m.tets, u, self.material))
        ch = frame.chamber.chamber.mesh
        cell, point = {}, {"electrode": electrode_tags(ch.n_nodes, frame.chamber.chamber.electrodes)}
        if frame.chamber.path == "morph":
            cell["dsigma"] = inst.grid.C @ frame.image
            point["displacement"] = ch.nodes - inst.reference.mesh.nodes
        write_vtu(self.dir / f"chamber_{i:05d}.vtu", ch, cell_data=cell, point_data=point)
        data = {"dsigma": frame.image, "dsigma_normalised": frame.image_normalised}
        data["cluster"] = (largest_cluster(inst.grid, frame.image_normalised).astype(float)
                           if np.any(frame.image) else np.zeros(inst.grid.n_cells))
        write_voxels_vtu(self.dir / f"image_{i:05d}.vtu", inst.grid, data)


def write_pvd(out: str | Path, frame_rate: float) -> list[Path]:
    """``out/{membrane,chamber,image}.pvd``: ParaView collections of the VTU files present,
    time = record index / frame rate (the targets' programs back to back)."""
    out = Path(out)
    written = []
    for kind in VTU_KINDS:
        files = sorted((out / "vtu").glob(f"{kind}_*.vtu"))
        rx = re.compile(rf"{kind}_(\d+)\.vtu$")
        rows = [
            f'    <DataSet timestep="{int(rx.search(f.name)[1]) / frame_rate:.6g}" part="0" file="vtu/{f.name}"/>'
            for f in files if rx.search(f.name)
        ]
        if not rows:
            continue
        text = "\n".join(['<?xml version="1.0"?>', '<VTKFile type="Collection" version="0.1">', "  <Collection>",
                          *rows, "  </Collection>", "</VTKFile>", ""])
        path = out / f"{kind}.pvd"
        with atomic_path(path) as tmp:
            tmp.write_text(text)
        written.append(path)
    return written


# ---------------------------------------------------------------------------------------------
# Set-up record
# ---------------------------------------------------------------------------------------------


def write_setup(out: str | Path, pal: Palpation) -> list[Path]:
    """``out/setup.json`` (λ, noise, mesh sizes, set-up timings, the representative press)
    and ``out/grid.npz`` (the voxel grid, the reference voltages, the image noise per cell)."""
    out = Path(out)
    inst = pal.instrument
    g, ro, rec = inst.grid, inst.readout, inst.imager.reconstructor
    grid = write_npz(
        out / "grid.npz", origin=g.grid.origin, spacing=g.grid.spacing, shape=np.array(g.grid.shape),
        active=g.active, volume=g.volume, centroid=g.centroid, v_ref=ro.v_ref, v_ref_measured=ro.v_ref_measured,
        cell_noise=inst.imager.cell_noise, lambda_grid=rec.choice.grid, lambda_score=rec.choice.score,
    )
    info = {
        "lambda": rec.lam,
        "lambda_method": rec.choice.method,
        "lambda_press": inst.lambda_press,
        "noise_std_V": ro.noise_std,
        "dv_noise_std_V": ro.dv_noise_std,
        "mean_standing_V": float(np.abs(ro.v_ref).mean()),
        "chamber_tets": int(inst.reference.mesh.n_tets),
        "chamber_nodes": int(inst.reference.mesh.n_nodes),
        "membrane_p2_nodes": int(pal.membrane_nodes),
        "grid_cells": int(g.n_cells),
        "voxel_mm": float(g.grid.spacing[0] * 1e3),
        "reference_min_shape": float(inst.morpher.reference_quality.min_shape),
        "setup_timings_s": pal.setup_timings,
        "segments": [{"target": s.target, "radius_m": s.radius, "start": s.start, "n_frames": s.n_frames} for s in pal.segments],
        "frame_rate_hz": pal.frame_rate,
    }
    path = out / "setup.json"
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(info, indent=2, default=float))
    return [grid, path]


def load_grid(out: str | Path) -> ChamberGrid:
    """The voxel grid saved by :func:`write_setup` (without the element map C)."""
    with np.load(Path(out) / "grid.npz") as z:
        vg = VoxelGrid(z["origin"], z["spacing"], tuple(int(n) for n in z["shape"]))
        return ChamberGrid(vg, z["active"], z["volume"], z["centroid"], None)


# ---------------------------------------------------------------------------------------------
# Summary
# ---------------------------------------------------------------------------------------------


def _hold(depth: np.ndarray) -> np.ndarray:
    """Frames at ≥ 90 % of the segment's deepest indentation (the hold plateau)."""
    return depth >= 0.9 * depth.max() if depth.max() > 0 else np.zeros(len(depth), bool)


def _brief(params: dict[str, Any]) -> dict[str, Any]:
    """The run's params for summary.json: the protocol's pattern matrices by their shapes (the
    matrices themselves are in palpation.h5's provenance)."""
    proto = params.get("protocol")
    if not isinstance(proto, dict):
        return params
    short = {k: (f"{np.shape(v)} array: palpation.h5 provenance params.protocol.{k}" if isinstance(v, list) else v)
             for k, v in proto.items()}
    return {**params, "protocol": short}


def summarise(rec: Records) -> list[dict[str, Any]]:
    """One row per target: the frame of maximum change and its figures, and means over the
    hold (frames at ≥ 90 % of the deepest indentation)."""
    rows = []
    for t in np.unique(rec["target"]):
        sel = np.flatnonzero(rec["target"] == t)
        k = sel[np.argmax(rec["rms_dv_clean"][sel])]
        hold = sel[_hold(rec["depth"][sel])]
        row = {
            "target": int(t),
            "diameter_mm": 2e3 * float(rec["target_radius"][k]),
            "frames": int(len(sel)),
            "max_depth_mm": 1e3 * float(rec["depth"][sel].max()),
            "max_force_mN": 1e3 * float(rec["force"][sel, 2].max()),
            "max_displaced_mm3": 1e9 * float(rec["displaced_volume"][sel].max()),
            "peak_frame": int(rec["frame"][k]),
            "peak_rms_dv_uV": 1e6 * float(rec["rms_dv_clean"][k]),
            "peak_rms_dv_noisy_uV": 1e6 * float(rec["rms_dv"][k]),
            "peak_max_abs_dv_uV": 1e6 * float(np.abs(rec["dv_clean"][k]).max()),
            "peak_image_diameter_mm": 1e3 * float(rec["diameter"][k]),
            "peak_sum_sigma": float(rec["sum_sigma"][k]),
            "peak_com_error_xy_mm": 1e3 * float(rec["com_error_xy"][k]),
            "peak_com_error_mm": 1e3 * float(rec["com_error"][k]),
            "hold_frames": int(len(hold)),
            "hold_image_diameter_mm": 1e3 * float(np.nanmean(rec["diameter"][hold])) if len(hold) else float("nan"),
            "hold_image_diameter_std_mm": 1e3 * float(np.nanstd(rec["diameter"][hold])) if len(hold) else float("nan"),
            "hold_sum_sigma": float(np.nanmean(rec["sum_sigma"][hold])) if len(hold) else float("nan"),
            "hold_sum_sigma_std": float(np.nanstd(rec["sum_sigma"][hold])) if len(hold) else float("nan"),
            "hold_com_error_xy_mm": 1e3 * float(np.nanmean(rec["com_error_xy"][hold])) if len(hold) else float("nan"),
            "hold_com_error_mm": 1e3 * float(np.nanmean(rec["com_error"][hold])) if len(hold) else float("nan"),
            "remeshed_frames": int((rec["mesh_path"][sel] == MESH_PATHS.index("remesh")).sum()),
            "volume_mismatch_max": float(np.nanmax(np.where(
                rec["displaced_volume"][sel] > 1e-9,
                np.abs(rec["chamber_volume_change"][sel] / np.maximum(rec["displaced_volume"][sel], 1e-30) - 1), np.nan)))
            if (rec["displaced_volume"][sel] > 1e-9).any() else float("nan"),
        }
        rows.append(row)
    return rows


def _timing_table(rec: Records) -> dict[str, dict[str, float]]:
    T = np.asarray(rec["timings"])
    total = T.sum(axis=1)
    out = {}
    for name, col in [*zip(STAGES, T.T), ("total", total)]:
        out[name] = {"median_s": float(np.median(col)), "mean_s": float(np.mean(col)), "max_s": float(np.max(col))}
    return out


def write_report(out: str | Path, rec: Records, command: str) -> list[Path]:
    """The figures, ``summary.json`` and ``summary.md`` of the finalised run ``rec`` in ``out``."""
    out = Path(out)
    setup = json.loads((out / "setup.json").read_text())
    grid = load_grid(out)
    rows = summarise(rec)
    timing = _timing_table(rec)
    written = _figures(out, rec, grid, rows)
    ident = rec.provenance
    meta = {
        "command": command,
        "jointsim": __version__,
        "machine": f"{platform.machine()}, {_cores()} cores, Python {platform.python_version()}",
        "date": time.strftime("%Y-%m-%d"),
        "data_sha256": rec.data_sha256,
        "seed": ident["seed"],
        "params": _brief(ident["params"]),
        "versions": ident["versions"],
        "setup": setup,
        "targets": rows,
        "frame_timings": timing,
        "sessions": len(rec.run.get("sessions", [])),
    }
    with atomic_path(out / "summary.json") as tmp:
        tmp.write_text(json.dumps(meta, indent=2, default=float))
    written.append(out / "summary.json")
    written.append(_markdown(out / "summary.md", meta))
    return written


def _cores() -> int:
    import os

    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 0


def _markdown(path: Path, meta: dict[str, Any]) -> Path:
    p = meta["params"]["palpation"]
    s = meta["setup"]
    mode = p["mode"]
    prog = (f"press force {p['force'] * 1e3:g} mN (ramp {p['force_ramp']:g} s, hold {p['hold']:g} s)" if mode == "force"
            else f"{p['depth'] * 1e3:g} mm past first contact at {p['speed'] * 1e3:g} mm/s, hold {p['hold']:g} s, gap {p['gap'] * 1e3:g} mm")
    lines = [
        "# Virtual palpation (paper Fig. 4)",
        "",
        f"Command: `{meta['command']}`  ",
        f"Machine: {meta['machine']}; jointsim {meta['jointsim']}; run {meta['date']}; seed {meta['seed']}; "
        f"data SHA-256 `{meta['data_sha256'][:16]}…`.  ",
        f"Mode **{mode}**: {prog}, at (x, y) = ({p['xy'][0] * 1e3:g}, {p['xy'][1] * 1e3:g}) mm, frames at "
        f"{s['frame_rate_hz']:g} Hz.  ",
        f"Chamber mesh: {s['chamber_tets']:,} tets (preset `{meta['params']['mesh']['preset']}`); membrane "
        f"{s['membrane_p2_nodes']:,} nodes ({meta['params']['membrane'].get('element', UNRECORDED_ELEMENT)}, "
        f"{meta['params']['membrane']['rim_vertices']} rim vertices, "
        f"{meta['params']['membrane']['layers']} layers); image on {s['grid_cells']:,} voxels of {s['voxel_mm']:.2f} mm, "
        f"λ = {s['lambda']:.3g} ({s['lambda_method']} CV on a geometric {s['lambda_press']['depth'] * 1e3:g} mm press "
        f"of a {s['lambda_press']['radius'] * 2e3:g} mm target).  ",
        f"Noise: {meta['params']['noise']['snr_db']:g} dB re the mean standing |V| = {s['mean_standing_V'] * 1e3:.2f} mV, "
        f"i.e. {s['noise_std_V'] * 1e6:.2f} µV per frame; the reference is the mean of {p['reference_frames']} frames. "
        "Mesh-noise floor: zero on the morph path (no deformation gives the reference mesh bit for bit); "
        "a remeshed frame takes its change between the remesh and its pull-back onto the reference chamber, "
        "which cancels the remeshing floor (results/mesh_step_benchmark.md).",
        "",
        "## Per target",
        "",
        "Peak: the frame of largest RMS δV (clean). Hold: mean ± std over frames at ≥ 90 % of the deepest indentation. "
        "Image figures from the noise-normalised image (cluster ≥ 75 % of its maximum, as the paper), Σσ from the Δσ image "
        "(S/m·voxel). CoM error against the dent's centroid (the saline displaced where the membrane moved in), in the "
        "base plane (XY) and in 3-D.",
        "",
        "| target mm | frames | depth mm | force mN | displaced mm³ | peak RMS δV µV | peak max δV µV | image diameter mm (peak; hold) | Σσ (peak; hold) | CoM err XY mm (peak; hold) | CoM err 3-D mm (peak; hold) | remeshed | chamber/FEM volume − 1 |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in meta["targets"]:
        lines.append(
            f"| {r['diameter_mm']:g} | {r['frames']} | {r['max_depth_mm']:.2f} | {r['max_force_mN']:.1f} | {r['max_displaced_mm3']:.0f} "
            f"| {r['peak_rms_dv_uV']:.0f} | {r['peak_max_abs_dv_uV']:.0f} | {r['peak_image_diameter_mm']:.1f}; "
            f"{r['hold_image_diameter_mm']:.1f} ± {r['hold_image_diameter_std_mm']:.1f} | {r['peak_sum_sigma']:.3g}; "
            f"{r['hold_sum_sigma']:.3g} ± {r['hold_sum_sigma_std']:.2g} | {r['peak_com_error_xy_mm']:.2f}; {r['hold_com_error_xy_mm']:.2f} "
            f"| {r['peak_com_error_mm']:.2f}; {r['hold_com_error_mm']:.2f} | {r['remeshed_frames']} | {r['volume_mismatch_max']:.2%} |"
        )
    t = meta["frame_timings"]
    lines += [
        "",
        "## Time per frame (ms)",
        "",
        "Hold frames need few Newton iterations: the median is a hold frame's, the mean weighs in the moving ones.",
        "",
        "| stage | median | mean | max |",
        "|---|---|---|---|",
        *[f"| {k} | {1e3 * v['median_s']:.1f} | {1e3 * v['mean_s']:.1f} | {1e3 * v['max_s']:.1f} |" for k, v in t.items()],
        "",
        "Set-up (once): " + ", ".join(f"{k} {v:.1f} s" for k, v in s["setup_timings_s"].items()) + ".",
        "",
        "Files: `palpation.h5` (every frame's record, provenance: scene, params, seed, package versions), "
        "`fig4a_voltages.png`, `fig4b_images.png`, `fig4c_metrics.png`, `timeline.png`, `summary.json`, "
        "`setup.json`, `grid.npz`, and the VTU series `membrane.pvd`, `chamber.pvd`, `image.pvd` (vtu/).",
        "",
    ]
    with atomic_path(path) as tmp:
        tmp.write_text("\n".join(lines))
    return path


# ---------------------------------------------------------------------------------------------
# Figures
# ---------------------------------------------------------------------------------------------


def _figures(out: Path, rec: Records, grid: ChamberGrid, rows: list[dict]) -> list[Path]:
    plt = pyplot()

    targets = [r["target"] for r in rows]
    n = len(targets)
    written = []
    rate = 1.0 / np.median(np.diff(rec["time"][rec["target"] == targets[0]])) if (rec["target"] == targets[0]).sum() > 1 else 50.0

    # (A) voltage changes, δV highlighted: the paper's δV is the RMS change over the channels
    # (Fig. 2G); the signed mean of a skip-8 frame's changes nearly cancels
    fig, axes = plt.subplots(1, n, figsize=(4.2 * n, 3.4), sharey=True, squeeze=False)
    for ax, r in zip(axes[0], rows):
        sel = rec["target"] == r["target"]
        t, dv = rec["time"][sel], 1e3 * rec["dv"][sel]
        ax.plot(t, dv, color="0.6", lw=0.4)
        ax.plot(t, 1e3 * rec["rms_dv"][sel], color="tab:red", lw=2.2, label="δV (RMS over channels)")
        ax.set_title(f"{r['diameter_mm']:g} mm target")
        ax.set_xlabel("time (s)")
    axes[0, 0].set_ylabel(f"δV (mV), {rec['dv'].shape[1]} channels")
    axes[0, 0].legend(loc="upper left", fontsize=8)
    fig.suptitle("Voltage changes with δV highlighted (cf. paper Fig. 4A)", fontsize=10)
    fig.tight_layout()
    written.append(_save(fig, out / "fig4a_voltages.png", plt))

    # (B) reconstructed perturbation at maximum change, noise-normalised (where the paper's cluster
    # is found; the raw Δσ of 0th-order Tikhonov peaks at the electrodes): XY and XZ slices
    # through the cluster's CoM
    with np.load(out / "grid.npz") as z:
        cell_noise = z["cell_noise"]
    fig, axes = plt.subplots(2, n, figsize=(3.4 * n + 1.2, 5.0), squeeze=False, gridspec_kw={"height_ratios": [2, 1]})
    g = grid.grid
    lo, hi = g.origin * 1e3, (g.origin + np.array(g.shape) * g.spacing) * 1e3
    peaks = [int(np.flatnonzero((rec["target"] == r["target"]) & (rec["frame"] == r["peak_frame"]))[0]) for r in rows]
    images = [np.asarray(rec["image"][k], float) / cell_noise for k in peaks]
    vmax = max(float(np.abs(x).max()) for x in images) or 1.0
    for j, (r, x, k) in enumerate(zip(rows, images, peaks)):
        full = grid.to_full(x)
        com = rec["com"][k]
        if not np.isfinite(com).all():
            com = grid.centroid[np.argmax(np.abs(x))]
        c = np.clip(np.floor((com - g.origin) / g.spacing).astype(int), 0, np.array(g.shape) - 1)
        im = axes[0, j].imshow(full[:, :, c[2]].T, origin="lower", extent=[lo[0], hi[0], lo[1], hi[1]], cmap="RdBu_r", vmin=-vmax, vmax=vmax)
        axes[0, j].set_title(f"{r['diameter_mm']:g} mm, frame {r['peak_frame']}\nXY at z = {(g.origin[2] + (c[2] + 0.5) * g.spacing[2]) * 1e3:.1f} mm", fontsize=9)
        axes[1, j].imshow(full[:, c[1], :].T, origin="lower", extent=[lo[0], hi[0], lo[2], hi[2]], cmap="RdBu_r", vmin=-vmax, vmax=vmax)
        axes[1, j].set_title(f"XZ at y = {(g.origin[1] + (c[1] + 0.5) * g.spacing[1]) * 1e3:.1f} mm", fontsize=9)
        axes[1, j].set_xlabel("x (mm)")
        tc = rec["true_centre"][k] * 1e3
        if np.isfinite(tc).all():
            axes[0, j].plot(tc[0], tc[1], "k+", ms=10)
            axes[1, j].plot(tc[0], tc[2], "k+", ms=10)
    axes[0, 0].set_ylabel("y (mm)")
    axes[1, 0].set_ylabel("z (mm)")
    fig.colorbar(im, ax=axes, shrink=0.7, label="Δσ / its noise std")
    fig.suptitle("Reconstructed perturbation at maximum change (+: the dent's centroid; cf. Fig. 4B)", fontsize=10)
    written.append(_save(fig, out / "fig4b_images.png", plt))

    # (C) image metrics against target size
    d = np.array([r["diameter_mm"] for r in rows])
    fig, ax = plt.subplots(figsize=(5, 3.6))
    ax.errorbar(d, [r["hold_image_diameter_mm"] for r in rows], yerr=[r["hold_image_diameter_std_mm"] for r in rows],
                fmt="o-", color="tab:red", capsize=3, label="object diameter (hold)")
    ax.plot(d, [r["peak_image_diameter_mm"] for r in rows], "s", color="tab:red", mfc="none", label="at max change")
    ax.plot(d, d, ":", color="0.5", lw=1, label="target diameter")
    ax.set_xlabel("target diameter (mm)")
    ax.set_ylabel("reconstructed diameter (mm)", color="tab:red")
    ax2 = ax.twinx()  # displaced saline images as a decrease: plot the magnitude, −Σσ
    ax2.errorbar(d, [-r["hold_sum_sigma"] for r in rows], yerr=[r["hold_sum_sigma_std"] for r in rows], fmt="o-", color="tab:blue", capsize=3)
    ax2.plot(d, [-r["peak_sum_sigma"] for r in rows], "s", color="tab:blue", mfc="none")
    ax2.set_ylabel("−Σσ (S/m·voxel)", color="tab:blue")
    ax.legend(fontsize=7, loc="upper left")
    ax.set_title("Image metrics against target size (cf. Fig. 4C)", fontsize=10)
    fig.tight_layout()
    written.append(_save(fig, out / "fig4c_metrics.png", plt))

    # timeline: depth, force, displaced volume and RMS δV of each target
    fig, axes = plt.subplots(4, 1, figsize=(6.5, 8), sharex=True)
    for r in rows:
        sel = rec["target"] == r["target"]
        t = rec["time"][sel]
        lab = f"{r['diameter_mm']:g} mm"
        line, = axes[0].plot(t, 1e3 * rec["depth"][sel], label=lab)
        axes[1].plot(t, 1e3 * rec["force"][sel, 2], color=line.get_color())
        commanded = rec["command_force"][sel]
        if np.isfinite(commanded).any():  # force mode: what the stage was told, beside what it got
            axes[1].plot(t, 1e3 * commanded, "--", lw=0.8, color=line.get_color())
        axes[2].plot(t, 1e9 * rec["displaced_volume"][sel])
        axes[3].plot(t, 1e6 * rec["rms_dv_clean"][sel])
    if np.isfinite(rec["command_force"]).any():
        axes[1].plot([], [], "k-", lw=1, label="contact")
        axes[1].plot([], [], "k--", lw=0.8, label="commanded")
        axes[1].legend(fontsize=7, loc="lower left")
    for ax, yl in zip(axes, ["depth (mm)", "force (mN)", "displaced (mm³)", "RMS δV clean (µV)"]):
        ax.set_ylabel(yl)
    axes[0].legend(fontsize=8)
    axes[-1].set_xlabel(f"time (s), frames at {rate:.0f} Hz")
    fig.tight_layout()
    written.append(_save(fig, out / "timeline.png", plt))
    return written


def _save(fig, path: Path, plt) -> Path:
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)
    return path
