"""Image metrics: the paper's perturbation cluster and its centre of mass, total change and
diameter; the voltage and sensitivity figures of the protocol study; and GREIT figures of
merit adapted to 3-D voxel images.

Definitions (a voxel image x on the active cells of a :class:`ChamberGrid`, cell saline
volumes v_i, full voxel volume v₀):

- perturbation: the largest face-connected cluster of cells whose change has the sign of the
  largest |x| and |x_i| ≥ threshold·max|x| (threshold 0.75, as the paper);
- CoM: Σ |x_i| v_i c_i / Σ |x_i| v_i over the cluster (c_i the saline centroid of cell i);
- Σσ: Σ x_i v_i / v₀ over the cluster (S/m·voxel; the plain sum of cell values on a grid of
  full voxels, as the paper);
- equivalent diameter: (6 V/π)^⅓ of the cluster's saline volume V;
- in-plane extent: the largest XY distance between two cluster cell centroids plus one voxel
  edge (a single cell has the extent of one voxel);
- δV_rms: sqrt(mean(δv²)) over the measurements;
- J_sens: Σ_cells ‖J[:, i]‖₂ / V_chamber, the volume-averaged norm of the sensitivity of all
  measurements to each cell (V/(S/m)/m³·m³ = V·m/S per cell, summed);

GREIT (Adler et al. 2009) figures of merit, in 3-D:

- amplitude response AR = Σ x_i v_i over all cells / target volume;
- position error PE = ‖CoM − true centre‖;
- resolution RES = (V_cluster / V_chamber)^⅓;
- shape deformation SD = the fraction of the cluster's volume outside the sphere of equal
  volume centred on the CoM;
- ringing RNG = −Σ x_i v_i over cells of the opposite sign to the perturbation / Σ x_i v_i
  over the cluster.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from scipy import ndimage

from .reconstruction.grid import ChamberGrid

__all__ = ["ImageMetrics", "largest_cluster", "image_metrics", "metric_fields", "rms", "sensitivity_total"]


def largest_cluster(grid: ChamberGrid, x: np.ndarray, threshold: float = 0.75) -> np.ndarray:
    """Boolean mask (n_cells,) of the perturbation: the largest face-connected cluster of cells
    with the sign of the extreme value and |x| ≥ threshold·max|x| (ties: the larger total |x|)."""
    x = np.asarray(x, float)
    if x.shape != (grid.n_cells,):
        raise ValueError(f"image: expected {grid.n_cells} cell values, got shape {x.shape}")
    if not 0 < threshold <= 1:
        raise ValueError(f"threshold = {threshold}: must be in (0, 1]")
    if not np.isfinite(x).all():
        raise ValueError("image: contains non-finite values")
    peak = np.abs(x).max()
    if peak == 0:
        raise ValueError("image: all zero, there is no perturbation to find")
    sign = np.sign(x[np.argmax(np.abs(x))])
    above = (sign * x) >= threshold * peak
    full = np.zeros(grid.grid.n_cells, bool)
    full[grid.active] = above
    labels, n = ndimage.label(full.reshape(grid.grid.shape))  # 6-connectivity: shared faces
    lab = labels.ravel()[grid.active]
    size = np.bincount(lab, weights=grid.volume, minlength=n + 1)[1:]
    mass = np.bincount(lab, weights=np.abs(x) * grid.volume, minlength=n + 1)[1:]
    best = np.lexsort((mass, size))[-1] + 1
    return lab == best


@dataclass(frozen=True)
class ImageMetrics:
    com: np.ndarray
    com_error: float
    sum_sigma: float
    volume: float
    diameter_equivalent: float
    extent_xy: float
    n_cells: int
    amplitude_response: float
    resolution: float
    shape_deformation: float
    ringing: float

    def as_dict(self) -> dict:
        d = asdict(self)
        d["com"] = [float(c) for c in self.com]
        return d


def image_metrics(
    grid: ChamberGrid,
    x: np.ndarray,
    true_centre: np.ndarray | None = None,
    target_volume: float | None = None,
    threshold: float = 0.75,
    amplitude: np.ndarray | None = None,
) -> ImageMetrics:
    """All metrics of one image (n_cells,); ``true_centre`` (3,) m and ``target_volume`` m³
    are needed for the CoM error and the amplitude response (NaN without them).

    ``amplitude`` (n_cells,), when given, is the Δσ image whose values the sums (Σσ, AR,
    ringing) are taken of, while the cluster and CoM come from ``x`` (e.g. a noise-normalised
    image, which finds the perturbation where the raw Δσ image is biased)."""
    x = np.asarray(x, float)
    mask = largest_cluster(grid, x, threshold)
    a = x if amplitude is None else np.asarray(amplitude, float)
    if a.shape != x.shape:
        raise ValueError(f"amplitude: expected shape {x.shape}, got {a.shape}")
    v = grid.volume
    w = np.abs(x[mask]) * v[mask]
    com = (w[:, None] * grid.centroid[mask]).sum(0) / w.sum()
    vol = float(v[mask].sum())
    sign = np.sign(x[mask][0])
    c = grid.centroid[mask]
    if mask.sum() > 1:
        d = np.hypot(c[:, None, 0] - c[None, :, 0], c[:, None, 1] - c[None, :, 1]).max()
    else:
        d = 0.0
    r_eq = (3 * vol / (4 * np.pi)) ** (1 / 3)
    outside = np.linalg.norm(c - com, axis=1) > r_eq
    opposite = (np.sign(a) == -sign) & ~mask
    cluster_sum = float((a[mask] * v[mask]).sum())
    err = float(np.linalg.norm(com - np.asarray(true_centre))) if true_centre is not None else float("nan")
    return ImageMetrics(
        com=com,
        com_error=err,
        sum_sigma=cluster_sum / grid.voxel_volume,
        volume=vol,
        diameter_equivalent=float((6 * vol / np.pi) ** (1 / 3)),
        extent_xy=float(d + grid.grid.spacing[0]),
        n_cells=int(mask.sum()),
        amplitude_response=float((a * v).sum() / target_volume) if target_volume else float("nan"),
        resolution=float((vol / v.sum()) ** (1 / 3)),
        shape_deformation=float(v[mask][outside].sum() / vol),
        ringing=float(-(a[opposite] * v[opposite]).sum() / cluster_sum) if cluster_sum else float("nan"),
    )


def rms(dv: np.ndarray) -> float:
    """Root-mean-square voltage change δV over the measurements."""
    return float(np.sqrt(np.mean(np.square(dv))))


def sensitivity_total(J_cells: np.ndarray, grid: ChamberGrid) -> float:
    """J_sens = Σ_i ‖J[:, i]‖₂ / V_chamber for the Jacobian on the grid's cells."""
    return float(np.linalg.norm(J_cells, axis=0).sum() / grid.volume.sum())


def metric_fields(metrics: ImageMetrics | None) -> dict[str, Any]:
    """The image metrics a record stores: ``com`` (3,) m, ``sum_sigma``, ``diameter`` m,
    ``extent_xy`` m, ``cluster_cells`` (NaN and 0 for an all-zero image)."""
    if metrics is None:
        return {"com": np.full(3, np.nan), "sum_sigma": np.nan, "diameter": np.nan, "extent_xy": np.nan, "cluster_cells": 0}
    return {"com": metrics.com, "sum_sigma": metrics.sum_sigma, "diameter": metrics.diameter_equivalent,
            "extent_xy": metrics.extent_xy, "cluster_cells": metrics.n_cells}
