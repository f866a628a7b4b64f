"""Applying a calibration map to a palpation run (``jointsim palpate --calibration MAP``).

Owns the per-frame table of calibrated values written beside a palpation's records
(``calibrated.csv``: position, depth and size by the image route, the direct regression's
outputs, the modulus per press) and the per-target summary added to ``summary.json`` under
``"calibration"`` and written to ``calibrated.json``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from ..io.export import atomic_path
from ..io.records import Records
from .fingerprint import fingerprint_digest
from .maps import APPLIED, CalibrationMap
from .report import write_csv

__all__ = ["calibrate_frames", "calibrate_measured", "summarise_calibrated", "write_calibrated", "why_nan"]

PALPATION_FIELDS = ("target", "frame", "target_radius", "position", "depth", "com", "voltages", "dv", "force", "sum_sigma",
                    "diameter")


def calibrate_frames(cmap: CalibrationMap, rec: Records) -> dict[str, np.ndarray]:
    """Per frame (n,) arrays: the palpation's target, frame, true position and depth, and the
    map's :data:`APPLIED` values (SI; modulus per target, from its press-in frames; the
    emulator's fits at the run's SNR)."""
    f = {k: np.asarray(rec[k]) for k in PALPATION_FIELDS}
    snr = rec.provenance.get("params", {}).get("noise", {}).get("snr_db")
    out = cmap.apply({**f, "group": f["target"], "snr_db": snr})
    return {"target": f["target"], "frame": f["frame"], "true_x": f["position"][:, 0], "true_y": f["position"][:, 1],
            "true_depth": f["depth"], "true_diameter": 2 * f["target_radius"],
            "force": np.linalg.norm(f["force"], axis=1), **{k: out[k] for k in APPLIED}}


def calibrate_measured(cmap: CalibrationMap, voltages: np.ndarray, dv: np.ndarray, com: np.ndarray,
                       sum_sigma: np.ndarray, diameter: np.ndarray, snr_db: float | None = None,
                       one_press: bool = False) -> dict[str, np.ndarray]:
    """The map's :data:`APPLIED` values (n,) for measured frames (their ``voltages`` and ``dv``
    (n, n_meas) V, image ``com`` (n, 3) m, ``sum_sigma``, ``diameter`` (n,)), the emulator's
    fits at the instrument's ``snr_db`` (None: the map's training SNRs'); ``one_press``: the
    frames are one press's, fitted jointly too (``press_*``). A measured frame has no force:
    the size route along force and the modulus are NaN there."""
    n = len(voltages)
    frames = {"com": com, "voltages": voltages, "dv": dv, "force": np.full((n, 3), np.nan), "sum_sigma": sum_sigma,
              "diameter": diameter, "snr_db": snr_db}
    if one_press:
        frames["group"] = np.zeros(n, int)
    return cmap.apply(frames)


def why_nan(cmap: CalibrationMap, table: dict[str, np.ndarray], k: int) -> dict[str, str]:
    """Why frame ``k``'s calibrated diameter or modulus is NaN, per quantity (only those NaN)."""
    why = {}
    if not np.isfinite(table["cal_diameter"][k]):
        lc = cmap.size[cmap.size_route]
        at, unit, scale = ((table["cal_depth"][k], "mm", 1e3) if lc.along == "depth" else (table["force"][k], "mN", 1e3))
        lo, hi = lc.levels[0] * scale, lc.levels[-1] * scale
        if not np.isfinite(at) or not lo <= at * scale <= hi:
            why["diameter"] = (f"the frame's {lc.along} ({at * scale:.3g} {unit}) is outside the size curves' levels "
                               f"({lo:.3g}-{hi:.3g} {unit})")
        else:
            why["diameter"] = f"the frame's {lc.metric} is outside what the size curves span at its {lc.along}"
    if not np.isfinite(table["modulus"][k]):
        st = cmap.stiffness
        why["modulus"] = (st.reason if not st.estimable else
                          f"the press does not reach every depth level of the stiffness model "
                          f"({', '.join(f'{v * 1e3:.3g}' for v in st.levels)} mm)")
    return why


def summarise_calibrated(table: dict[str, np.ndarray], cmap: CalibrationMap | None = None) -> list[dict[str, Any]]:
    """One row per target at its deepest frame: true and calibrated values (mm, mN, kPa), and
    (given the map) why any of them is NaN."""
    rows = []
    for t in np.unique(table["target"]):
        sel = np.flatnonzero(table["target"] == t)
        k = sel[np.argmax(table["true_depth"][sel])]
        row = {"target": int(t), "frame": int(table["frame"][k])}
        for name in ("true_x", "true_y", "true_depth", "true_diameter", "cal_x", "cal_y", "cal_depth", "cal_diameter",
                     "direct_x", "direct_y", "direct_depth", "direct_diameter"):
            row[f"{name}_mm"] = float(table[name][k] * 1e3)
        row["force_mN"] = float(table["force"][k] * 1e3)
        row["direct_force_mN"] = float(table["direct_force"][k] * 1e3)
        row["modulus_kPa"] = float(table["modulus"][k] / 1e3)
        row["outside_trained_region"] = str(table["outside"][k])
        if cmap is not None:
            row["why_nan"] = why_nan(cmap, table, k)
        rows.append(row)
    return rows


def write_calibrated(out: str | Path, rec: Records, cmap: CalibrationMap, map_path: str | Path) -> list[Path]:
    """``out/calibrated.csv`` (per frame), ``out/calibrated.json`` (per target) and the
    ``"calibration"`` entry of ``out/summary.json`` (when it exists)."""
    out = Path(out)
    table = calibrate_frames(cmap, rec)
    written = [write_csv(out / "calibrated.csv", table)]
    meta = {"map": str(map_path), "map_created": cmap.created, "sensor_fingerprint": fingerprint_digest(cmap.fingerprint),
            "size_route": cmap.size_route, "regressor": cmap.regressor.kind, "trained_region": cmap.region,
            "frames_outside_trained_region": int(np.count_nonzero(table["outside"])),
            "stiffness": {"estimable": cmap.stiffness.estimable, "reason": cmap.stiffness.reason},
            "held_out_goals": cmap.evaluation.get("goals", []), "targets": summarise_calibrated(table, cmap)}
    with atomic_path(out / "calibrated.json") as tmp:
        tmp.write_text(json.dumps(meta, indent=2, default=float))
    written.append(out / "calibrated.json")
    summary = out / "summary.json"
    if summary.is_file():
        d = json.loads(summary.read_text())
        d["calibration"] = meta
        with atomic_path(summary) as tmp:
            tmp.write_text(json.dumps(d, indent=2, default=float))
    return written
