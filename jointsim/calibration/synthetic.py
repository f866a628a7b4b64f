"""Synthetic dataset stores with a known answer, for testing and demonstrating calibration.

Owns :func:`write_synthetic_dataset`, written in :data:`DATASET_SCHEMA` (the ``jointsim
dataset`` store contract, schema "dataset" v1): presses of spheres at increasing depths whose
"measurements" are known smooth functions of the labels — the CoM a smooth warp of (x, y, depth), Σσ and the image diameter monotone in size at each depth, the 256
voltage changes Gaussian bumps around each measurement's sensitive spot, the force a Hertz
law of the target and membrane moduli in series — plus noise at each press's SNR. No physics
is simulated: a calibration fitted on it must recover these functions, and that is all such
a store can show.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..dataset.generate import dataset_schema
from ..io.store import open_store

__all__ = ["DATASET_SCHEMA", "synthetic_com", "write_synthetic_dataset", "MEMBRANE_MODULUS"]

N_MEAS = 256
N_ELECTRODES = 16
MEMBRANE_MODULUS = 66e3  # Pa: 3 μ of the scene's Ecoflex
MM = 1e-3


# the store contract is the dataset generator's own schema (16 electrodes, 256 measurements, no images)
DATASET_SCHEMA = dataset_schema(N_ELECTRODES, N_MEAS, None)


def synthetic_com(position: np.ndarray) -> np.ndarray:
    """The known warp (n, 3) m of true (x, y, depth) (n, 3) m to the 'reconstructed' CoM:
    in-plane shrink growing with radius, height rising with depth and falling off-axis."""
    x, y, d = np.asarray(position, float).T
    r2 = (x**2 + y**2) / (15 * MM) ** 2
    k = 0.85 + 0.08 * r2
    return np.column_stack([k * x, k * y, 3 * MM + 0.6 * d - 1.0 * MM * r2])


def _sensitive_spots() -> tuple[np.ndarray, np.ndarray]:
    """(256, 2) m centres and (256,) V standing voltages of the fixed synthetic sensor."""
    rng = np.random.default_rng(12345)
    th = rng.uniform(0, 2 * np.pi, N_MEAS)
    rho = 15 * MM * np.sqrt(rng.uniform(0, 1, N_MEAS))
    ref = 0.2 * (1 + 0.3 * np.cos(th * 3)) + 0.02 * rng.standard_normal(N_MEAS)
    return np.column_stack([rho * np.cos(th), rho * np.sin(th)]), ref


def write_synthetic_dataset(
    path: str | Path, scene_toml: str, *, n_groups: int = 60, seed: int = 0, depths_mm: tuple[float, ...] = (0.5, 1, 1.5, 2, 2.5, 3, 3.5, 4),
    soft_fraction: float = 0.0, snr_db: tuple[float, float] = (70.0, 78.0), com_noise: float = 0.05 * MM,
    params: dict | None = None,
) -> Path:
    """Write ``n_groups`` presses × ``len(depths_mm)`` samples to ``path`` (a finalised store).
    Targets: diameters 8–30 mm, centres over r ≤ 17 mm; a ``soft_fraction`` of them soft
    (E log-uniform 20 kPa – 2 MPa), the rest rigid; SNR uniform in ``snr_db``."""
    rng = np.random.default_rng(seed)
    depth = np.asarray(depths_mm, float) * MM
    K = len(depth)
    n = n_groups * K
    spots, ref = _sensitive_spots()
    R = rng.uniform(4, 15, n_groups) * MM
    rr = 17 * MM * np.sqrt(rng.uniform(0, 1, n_groups))
    th = rng.uniform(0, 2 * np.pi, n_groups)
    xy = np.column_stack([rr * np.cos(th), rr * np.sin(th)])
    soft = rng.uniform(0, 1, n_groups) < soft_fraction
    E = np.where(soft, 10 ** rng.uniform(np.log10(20e3), np.log10(2e6), n_groups), np.inf)
    snr = rng.uniform(*snr_db, n_groups)
    g = np.repeat(np.arange(n_groups), K)
    d = np.tile(depth, n_groups)
    Rg, xyg, Eg, snrg = R[g], xy[g], E[g], snr[g]
    e_eff = 1.0 / (1.0 / MEMBRANE_MODULUS + 1.0 / Eg)
    fz = (4.0 / 3.0) * e_eff * np.sqrt(Rg) * d**1.5
    D = 2 * Rg
    # the softer the target, the less it indents the membrane: the image sees less change
    share = e_eff / MEMBRANE_MODULUS
    com = synthetic_com(np.column_stack([xyg, d])) + rng.normal(0, com_noise, (n, 3))
    sum_sigma = -30 * (D / (10 * MM)) ** 1.5 * (d / MM) * share * (1 + 0.01 * rng.standard_normal(n))
    diam_img = 4 * MM + 0.5 * D * (d / (d + MM)) * share**0.5 + 0.05 * MM * rng.standard_normal(n)
    bump = np.exp(-((xyg[:, None, :] - spots[None]) ** 2).sum(-1) / (2 * (8 * MM) ** 2))
    dv_clean = -1e-3 * ref[None] * (D / (10 * MM))[:, None] * ((d / MM) ** 1.2 * share)[:, None] * bump
    sd = np.abs(ref).mean() / 10 ** (snrg / 20)
    noise = rng.standard_normal((n, N_MEAS)) * sd[:, None]
    ref_noise = rng.standard_normal((n, N_MEAS)) * (sd / np.sqrt(50))[:, None]
    v = ref[None] + dv_clean + noise
    store = open_store(path, DATASET_SCHEMA, scene_toml=scene_toml, seed=seed, n_records=n,
                       params={"synthetic": True, **(params or {})}, batch=n, fsync=False)
    for i in range(n):
        store.put(i, {
            "group": g[i], "radius": Rg[i], "xy": xyg[i], "contact_point": xyg[i], "depth": d[i], "target_modulus": Eg[i],
            "force": np.array([0.0, 0.0, fz[i]]), "contact_centre": np.array([*xyg[i], 0.0]), "contact_area": np.pi * Rg[i] * d[i], "displaced_volume": np.pi * Rg[i] * d[i] ** 2,
            "peak_strain": 0.1 * d[i] / MM, "membrane_scale": 1.0, "conductivity": 0.37, "contact_impedance": 1e-3,
            "electrode_jitter": np.zeros((N_ELECTRODES, 2)), "snr_db": snrg[i], "voltages_clean": ref + dv_clean[i],
            "reference_clean": ref, "voltages": v[i], "dv": v[i] - (ref + ref_noise[i]), "dv_clean": dv_clean[i],
            "com": com[i], "sum_sigma": sum_sigma[i], "diameter": diam_img[i], "extent_xy": diam_img[i],
            "cluster_cells": 10, "timings": np.zeros(5),
        })
    return store.finalize()
