"""What the stiffness calibration lacks: the target's size, or the membrane's modulus?

    python benchmarks/bench_stiffness_size.py STORE [STORE ...]   # writes results/calibration/stiffness_size.{md,json}

For each soft-target dataset store (``jointsim dataset`` on a stiffness scene), the stiffness
model exactly as ``jointsim calibrate`` fits it (a ridge on degree-2 polynomial features of
log |F|, the image diameter and log |Σσ| at three depth levels; the same press split, seed 0,
20 % held out), and the same model with the image diameter replaced by the target's true
diameter: the modulus error an estimator would reach if it read the size perfectly. Run on the
stiffness scene's store (membrane ×0.5–2) and on the one whose membrane is known to 1 %, it
separates the two nuisances.
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

from jointsim.calibration.curves import default_levels  # noqa: E402
from jointsim.calibration.data import load_samples, split_groups  # noqa: E402
from jointsim.calibration.stiffness import decades, fit_stiffness, press_moduli, stiffness_levels  # noqa: E402
from jointsim.io.records import open_records  # noqa: E402


def errors(train, test, levels: np.ndarray, size: str) -> dict:
    """Held-out relative modulus errors of the stiffness model with the image's diameter
    (``size`` "image") or the target's own (``size`` "true") as its size feature."""
    def diameter(s):
        return s.diameter if size == "image" else 2 * s.radius

    model = fit_stiffness(train.group, train.depth, train.force_mag, train.sum_sigma, diameter(train), train.modulus, levels)
    ids, E = model.predict(test.group, test.depth, test.force_mag, test.sum_sigma, diameter(test))
    Et = press_moduli(test.group, test.modulus, ids)
    rel = np.abs(E / Et - 1)
    return {"presses": len(ids), "median": float(np.median(rel)), "p95": float(np.percentile(rel, 95)),
            "by_decade": [{"from_kpa": lo / 1e3, "presses": int(m.sum()), "median": float(np.median(rel[m]))} for lo, m in decades(Et)]}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("stores", type=Path, nargs="+")
    ap.add_argument("--out", type=Path, default=ROOT / "results" / "calibration" / "stiffness_size")
    a = ap.parse_args()
    rows = []
    for path in a.stores:
        s = load_samples(path)
        train_m, test_m = split_groups(s.group, 0.2, 0)
        train, test = s.subset(train_m), s.subset(test_m)
        soft = np.isfinite(train.modulus)
        soft_test = test.subset(np.isfinite(test.modulus))
        levels = stiffness_levels(default_levels("depth", train.group, train.depth))  # as jointsim calibrate's
        scale = np.asarray(open_records(path, fields=["membrane_scale"])["membrane_scale"])
        rows.append({"store": path.name, "data_sha256": s.source["data_sha256"],
                     "soft_train_samples": int(soft.sum()), "levels_mm": (levels * 1e3).round(3).tolist(),
                     "membrane_scale_range": [float(np.min(scale)), float(np.max(scale))],
                     "image_size": errors(train, soft_test, levels, "image"),
                     "true_size": errors(train, soft_test, levels, "true")})
        print(rows[-1], flush=True)
    L = ["# The stiffness calibration: what the size and the membrane each cost", "",
         f"`python benchmarks/bench_stiffness_size.py {' '.join(p.name for p in a.stores)}` on {platform.machine()}, {cpu_name()}. "
         "The stiffness model as `jointsim calibrate` fits it (ridge on degree-2 polynomial features of log |F|, the image "
         "diameter and log |Σσ| at three depths; split seed 0, 20 % of the presses held out), with the image's diameter "
         "and with the target's true diameter in its place. Relative modulus error on the held-out soft presses.", "",
         "| store | membrane ×, drawn | size feature | presses | median | P95 | median by decade (10–100 kPa / 0.1–1 MPa / 1–10 MPa) |",
         "|---|---|---|---|---|---|---|"]
    for r in rows:
        ms = r["membrane_scale_range"]
        for key, name in (("image_size", "the image's diameter"), ("true_size", "the true diameter")):
            e = r[key]
            dec = " / ".join(f"{d['median']:.2f} ({d['presses']})" for d in e["by_decade"])
            L.append(f"| `{r['store']}` (`{r['data_sha256'][:16]}…`) | {ms[0]:.2f}–{ms[1]:.2f} | {name} | {e['presses']} | "
                     f"{e['median']:.2f} | {e['p95']:.2f} | {dec} |")
    write_pair(a.out, {"machine": f"{platform.machine()}, {cpu_name()}", "rows": rows}, "\n".join(L) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
