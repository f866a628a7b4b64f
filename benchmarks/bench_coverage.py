"""Coverage: what a calibration map reads over the sensor, by how far from the axis a press is.

    python benchmarks/bench_coverage.py DATASET.h5 MAP.h5 [MAP.h5 ...] --out results/calibration/coverage.md

For each map, on the held-out presses of ``DATASET`` (its split by seed 0, as ``jointsim
calibrate`` makes it: presses no map built from that dataset trained on; a map built from
another dataset never saw any of it): the direct regression's in-plane position error by the
true position's distance from the axis (the contact's centre of pressure), median and P95, all
SNRs and in the 74 ± 4 dB band; and the region each map says it was trained on. A map trained
on presses that never reached the ring errs there, and says so only if it records its region.
"""

from __future__ import annotations

import argparse
import platform
import sys
from pathlib import Path

import numpy as np

from _machine import cpu_name, write_pair

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from jointsim.calibration import load_map, load_samples  # noqa: E402
from jointsim.calibration.data import split_groups, voltage_features  # noqa: E402

BINS_MM = (0, 3, 6, 9, 12, 13.5, 15, 99)
BAND_DB = (70.2, 78.2)


def errors(cmap, s) -> np.ndarray:
    pred = cmap.regressor(voltage_features(s.voltages, s.dv))[:, :2]
    return np.linalg.norm(pred - s.position[:, :2], axis=1)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset", type=Path)
    ap.add_argument("maps", type=Path, nargs="+")
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "coverage.md")
    args = ap.parse_args()
    samples = load_samples(args.dataset)
    _, test = split_groups(samples.group, 0.2, seed=0)
    s = samples.subset(test)
    r = np.hypot(*s.position[:, :2].T) * 1e3
    band = (s.snr_db >= BAND_DB[0]) & (s.snr_db <= BAND_DB[1])
    result = {"dataset": str(args.dataset), "data_sha256": samples.source["data_sha256"], "held_out_samples": int(len(s)),
              "held_out_presses": int(len(np.unique(s.group))), "machine": f"{platform.machine()}, {cpu_name()}", "maps": []}
    for path in args.maps:
        cmap = load_map(path)
        e = errors(cmap, s) * 1e3
        rows = []
        for lo, hi in zip(BINS_MM[:-1], BINS_MM[1:]):
            sel = (r >= lo) & (r < hi)
            sb = sel & band
            rows.append({"from_mm": lo, "to_mm": hi, "n": int(sel.sum()),
                         "median_mm": float(np.median(e[sel])) if sel.any() else None,
                         "p95_mm": float(np.percentile(e[sel], 95)) if sel.any() else None,
                         "n_band": int(sb.sum()), "median_band_mm": float(np.median(e[sb])) if sb.any() else None,
                         "p95_band_mm": float(np.percentile(e[sb], 95)) if sb.any() else None})
        result["maps"].append({"map": str(path), "trained_on": cmap.source.get("data_sha256", "")[:16],
                               "region": cmap.region, "by_radius": rows})

    def f(v):
        return "–" if v is None else f"{v:.2f}"

    L = ["# Position by distance from the axis", "",
         f"Held-out presses of `{args.dataset.name}` (data_sha256 `{result['data_sha256'][:16]}…`; split by seed 0 as "
         f"`jointsim calibrate` makes it: {result['held_out_presses']} presses, {result['held_out_samples']} samples), "
         "the direct regression's in-plane error against the contact's centre of pressure, mm. "
         f"Made by `python benchmarks/bench_coverage.py {args.dataset.name} {' '.join(p.name for p in args.maps)}` on "
         f"{result['machine']}.", ""]
    for m in result["maps"]:
        reg = m["region"]
        where = (f"trained within r ≤ {reg['r_max_m'] * 1e3:.3g} mm" if reg else "records no trained region")
        L += [f"## `{m['map']}` (its dataset `{m['trained_on']}…`; {where})", "",
              "| r (mm) | n | median | P95 | n at 74 ± 4 dB | median | P95 |", "|---|---|---|---|---|---|---|"]
        for row in m["by_radius"]:
            span = f"{row['from_mm']:g}–{row['to_mm']:g}" if row["to_mm"] < 99 else f"{row['from_mm']:g}+"
            L.append(f"| {span} | {row['n']} | {f(row['median_mm'])} | {f(row['p95_mm'])} | {row['n_band']} | "
                     f"{f(row['median_band_mm'])} | {f(row['p95_band_mm'])} |")
        L.append("")
    write_pair(args.out.with_suffix(""), result, "\n".join(L) + "\n")
    print("\n".join(L))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
