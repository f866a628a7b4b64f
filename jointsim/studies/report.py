"""Writing a protocol study to disk: Fig. 2 G–H-like PNGs, CSV and Markdown tables, the
images as VTU for ParaView, and a JSON record with the provenance."""

from __future__ import annotations

import csv
import io
import json
import platform
import time
from pathlib import Path

import numpy as np

from .. import __version__
from ..io.export import atomic_path, write_voxels_vtu
from ..io.figures import pyplot
from .protocol_study import StudyResult

__all__ = ["write_study"]


def write_study(result: StudyResult, out: Path, command: str, *, vtu: bool = True) -> list[Path]:
    """The study's table (CSV, Markdown), figures, JSON and, with ``vtu``, its images and
    sensitivity densities on the voxels for ParaView, into ``out``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    rows = result.table()
    written = [_csv(out / "table.csv", rows), _markdown(out / "table.md", result, rows, command)]
    written += _figures(out, result, rows)
    for s in result.config.skips if vtu else ():
        data = {f"pos{i}": result.images[s][i] for i in range(len(result.config.positions))}
        data["volume_fraction"] = result.grid.volume_fraction
        if s in result.sensitivity:
            data["sensitivity_density"] = result.sensitivity[s]
        written.append(write_voxels_vtu(out / f"images_skip{s}.vtu", result.grid, data))
    meta = {
        "command": command,
        "jointsim": __version__,
        "machine": f"{platform.machine()}, Python {platform.python_version()}",
        "date": time.strftime("%Y-%m-%d"),
        "scene": result.scene.to_dict(),
        "config": {k: (list(v) if isinstance(v, tuple) else v) for k, v in result.config.__dict__.items()},
        "true_centres_m": result.true_centres.tolist(),
        "displaced_volume_m3": result.displaced_volume.tolist(),
        "floor_dB": result.floor,
        "mirror_pairs_rel_diff": result.mirror_pairs,
        "rows": rows,
        "per_position": {
            str(s): {"normalised": [m.as_dict() for m in result.metrics[s]], "raw": [m.as_dict() for m in result.metrics_raw[s]]}
            for s in result.config.skips
        },
    }
    with atomic_path(out / "study.json") as tmp:
        tmp.write_text(json.dumps(meta, indent=2, default=float))
    written.append(out / "study.json")
    return written


def _csv(path: Path, rows: list[dict]) -> Path:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(rows[0]))
    w.writeheader()
    for r in rows:
        w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})
    with atomic_path(path) as tmp:
        tmp.write_text(buf.getvalue())
    return path


def _markdown(path: Path, result: StudyResult, rows: list[dict], command: str) -> Path:
    c = result.config
    pos = ", ".join(f"({x * 1e3:.0f}, {y * 1e3:.0f})" for x, y in c.positions)
    lines = [
        "# Protocol study (paper Fig. 2 G–H)",
        "",
        f"Command: `{command}`  ",
        f"Scene `{result.scene.name}`, mesh preset `{result.scene.mesh.preset}`, {result.grid.n_cells} reconstruction cells "
        f"({result.grid.grid.spacing[0] * 1e3:.2f} mm voxels).  ",
        f"Target: sphere of radius {c.target_radius * 1e3:g} mm pressed {c.depth * 1e3:g} mm at (x, y) mm = {pos}; "
        f"geometric indentation, morphed mesh.  ",
        f"Noise {c.snr_db} dB re mean standing |V|; λ by {c.lambda_method} CV over a 600-value log grid; "
        f"perturbation threshold {c.threshold:.0%}.",
        "",
        "| skip | RMS δV µV | δV SNR dB | J_sens | CoM err mean mm | CoM err max mm | XY err mm | Z bias mm | raw-image CoM err mm | Σσ | d_eq mm | λ |"
        + "".join(f" floor {k} µV (dB) |" for k in result.floor),
        "|---|---|---|---|---|---|---|---|---|---|---|---|" + "---|" * len(result.floor),
    ]
    for r in rows:
        lines.append(
            f"| {r['skip']} | {r['rms_dV_uV']:.1f} | {r['snr_dV_dB']:.1f} | {r['J_sens']:.3g} | {r['com_error_mm_mean']:.2f} | "
            f"{r['com_error_mm_max']:.2f} | {r['com_error_xy_mm_mean']:.2f} | {r['com_dz_mm_mean']:+.2f} | {r['com_error_raw_mm_mean']:.2f} | "
            f"{r['sum_sigma']:.3g} | {r['diameter_eq_mm']:.1f} | {r['lambda']:.3g} |"
            + "".join(f" {r[f'floor_{k}_uV']:.1f} ({r[f'floor_{k}_dB']:.1f}) |" for k in result.floor)
        )
    lines += [
        "",
        "CoM errors are 3-D distances between the CoM of the perturbation in the noise-normalised image",
        "(Δσ divided by each cell's noise std) and the centroid of the displaced saline; XY err is the",
        "in-plane part and Z bias the mean signed vertical offset. The raw Δσ image peaks at the",
        "electrodes, where 0th-order Tikhonov puts the most sensitive cells (its CoM error column). Σσ",
        "sums the raw Δσ (S/m·voxel) over the perturbation found in the normalised image.",
        "",
        "Mesh-noise floor: the RMS voltage change caused by meshing alone, in µV beside RMS δV, and in",
        "dB as 20·log10(mean standing |V| / that RMS), the instrument's SNR convention (74.2 dB);",
        "`jitter` = the chamber meshed with its dome moved by at most 1 µm, `rotate` = meshed",
        "with the electrode ring rotated by one pitch and permuted back. Where the floor is not far",
        "below δV, remeshing each frame would image the mesher; the study therefore uses the morphed",
        "mesh, whose floor is exactly zero (no deformation reproduces the reference mesh).",
        "",
        "## skip-N and skip-(14 − N)",
        "",
        "On a 16-electrode ring, skip-N injection i drives (i, i+N+1) and skip-(14−N) injection i+N+1",
        "drives (i+N+1, i): the same pair reversed. With all 16 electrodes measured against ground the",
        "two protocols therefore record the same 256 numbers, permuted and negated. Largest difference",
        "of the simulated deformed-chamber voltages after that permutation (relative to max |V|):",
        "",
        *[f"- skip {k.replace('~', ' vs skip ')}: {d:.1e}" for k, d in result.mirror_pairs.items()],
        "",
        "So skip-6 and skip-8 carry identical information: their images and metrics differ only by the",
        "noise draw and the λ chosen for it. The paper's choice of skip-8 over skip-7 is a choice between",
        "distinct data; its choice of skip-8 over skip-6 is not a choice at all. Only skip 0–7 are",
        "distinct protocols here.",
    ]
    with atomic_path(path) as tmp:
        tmp.write_text("\n".join(lines) + "\n")
    return path


def _slices(axes, g, values: np.ndarray, at: np.ndarray, ylabel: bool = True, **style):
    """A cell field ``values`` on the grid ``g`` drawn on two axes: the xy slice through height
    ``at[2]`` and the xz slice through ``at[1]``, in mm (empty cells blank; y axes labelled where
    ``ylabel``); the last image."""
    full = g.to_full(values)
    o, h, n = g.grid.origin, g.grid.spacing, g.grid.shape
    k = int(np.clip((at[2] - o[2]) / h[2], 0, n[2] - 1))
    j = int(np.clip((at[1] - o[1]) / h[1], 0, n[1] - 1))
    ext_xy = np.array([o[0], o[0] + n[0] * h[0], o[1], o[1] + n[1] * h[1]]) * 1e3
    ext_xz = np.array([o[0], o[0] + n[0] * h[0], o[2], o[2] + n[2] * h[2]]) * 1e3
    axes[0].imshow(full[:, :, k].T, origin="lower", extent=ext_xy, **style)
    im = axes[1].imshow(full[:, j, :].T, origin="lower", extent=ext_xz, aspect="auto", **style)
    axes[0].set_xlabel("x (mm)", fontsize=8)
    axes[1].set_xlabel("x (mm)", fontsize=8)
    if ylabel:
        axes[0].set_ylabel(f"y (mm), slice z = {(o[2] + (k + 0.5) * h[2]) * 1e3:.1f} mm", fontsize=8)
        axes[1].set_ylabel(f"z (mm), slice y = {(o[1] + (j + 0.5) * h[1]) * 1e3:.1f} mm", fontsize=8)
    for ax in axes:
        ax.tick_params(labelsize=7)
    return im


def _figures(out: Path, result: StudyResult, rows: list[dict]) -> list[Path]:
    plt = pyplot()

    skips = [r["skip"] for r in rows]
    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 3.8))
    a.plot(skips, [r["rms_dV_uV"] for r in rows], "o-", color="tab:red")
    a.set_xlabel("skip")
    a.set_ylabel("RMS δV (µV)", color="tab:red")
    a2 = a.twinx()
    a2.plot(skips, [r["J_sens"] for r in rows], "s-", color="tab:blue")
    a2.set_ylabel("J_sens (V S⁻¹ m⁻²)", color="tab:blue")
    a.set_title("G: voltage change and sensitivity")
    b.plot(skips, [r["com_error_mm_mean"] for r in rows], "o-", color="tab:red", label="mean")
    b.plot(skips, [r["com_error_mm_max"] for r in rows], "o--", color="tab:red", alpha=0.5, label="max")
    b.axhline(1.5, color="gray", lw=0.8, ls=":")
    b.set_xlabel("skip")
    b.set_ylabel("CoM error (mm)", color="tab:red")
    b.legend(loc="upper left", fontsize=8)
    b2 = b.twinx()
    b2.plot(skips, [abs(r["sum_sigma"]) for r in rows], "s-", color="tab:blue")
    b2.set_ylabel("|Σσ| (S/m·voxel)", color="tab:blue")
    b.set_title("H: localisation and total change")
    fig.tight_layout()
    p1 = out / "fig2_GH.png"
    with atomic_path(p1) as tmp:
        fig.savefig(tmp, dpi=130)
    plt.close(fig)

    # images: slices through the first off-centre position's true centre, every skip
    g = result.grid
    i_pos = min(1, len(result.config.positions) - 1)
    centre = result.true_centres[i_pos]
    fig, axes = plt.subplots(2, len(result.config.skips), figsize=(2.2 * len(result.config.skips) + 1.5, 4.8), squeeze=False)
    # one scale for every skip: how strongly each images the same press is part of the comparison
    vmax = max(float(np.nanmax(np.abs(result.images[s][i_pos]))) for s in result.config.skips)
    for col, s in enumerate(result.config.skips):
        im = _slices(axes[:, col], g, result.images[s][i_pos], centre, ylabel=col == 0, cmap="RdBu_r", vmin=-vmax, vmax=vmax)
        axes[0, col].plot(*(centre[:2] * 1e3), "k+")
        axes[0, col].plot(*(result.metrics[s][i_pos].com[:2] * 1e3), "kx")
        axes[0, col].set_title(f"skip {s}", fontsize=9)
    fig.colorbar(im, ax=axes.ravel().tolist(), shrink=0.8, label="Δσ (S/m)")
    fig.suptitle(f"Difference images of the press at ({centre[0] * 1e3:.1f}, {centre[1] * 1e3:.1f}) mm (+ true centre, "
                 "× reconstructed CoM); blue = conductivity decrease", fontsize=9)
    p2 = out / "images.png"
    with atomic_path(p2) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)

    # the paper's Fig. 2 B/C: where the measurements are sensitive, for the first and last skip
    shown = sorted({result.config.skips[0], result.config.skips[-1]})
    fig, axes = plt.subplots(2, len(shown), figsize=(3.6 * len(shown) + 1.0, 6.0), squeeze=False)
    dens = {s: np.log10(result.sensitivity[s]) for s in shown}
    lo = min(float(np.percentile(d, 1)) for d in dens.values())
    hi = max(float(d.max()) for d in dens.values())
    mid = np.array([0.0, 0.0, 0.5 * result.true_centres[:, 2].mean()])  # half-way up to the dents
    for col, s in enumerate(shown):
        im = _slices(axes[:, col], g, dens[s], mid, ylabel=col == 0, cmap="viridis", vmin=lo, vmax=hi)
        axes[0, col].set_title(f"skip {s}: sensitivity density", fontsize=9)
    fig.colorbar(im, ax=axes.ravel().tolist(), shrink=0.8, label="log₁₀ ‖∂V/∂σᵢ‖ / Vᵢ (V S⁻¹ m⁻²)")
    fig.suptitle("Measurement sensitivity per unit volume (cf. paper Fig. 2B/C), slices through the axis", fontsize=9)
    p4 = out / "fig2_BC.png"
    with atomic_path(p4) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)
    fig, ax = plt.subplots(figsize=(5, 3.5))
    for s in result.config.skips:
        ch = result.lambdas[s]
        sc = ch.score / ch.score.min()
        ax.loglog(ch.grid, sc, lw=0.9, label=f"skip {s}")
        ax.plot(ch.lam, 1.0, "k.", ms=4)
    ax.set_xlabel("λ")
    ax.set_ylabel(f"{result.config.lambda_method} CV error / minimum")
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    p3 = out / "lambda_cv.png"
    with atomic_path(p3) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)
    return [p1, p2, p3, p4]
