"""The calibration report: CSV tables, PNG figures and a Markdown summary of a built
calibration, every file written under a temporary name and renamed.

Owns what goes in the output folder (besides the map file, :mod:`.maps`): the held-out
per-sample tables, the size curves at fixed depth and at fixed force, the CoM error maps over
the sensing area (r ≤ 15 mm), the direct-regression-versus-image-route table, stiffness, and
the goals with whether each is met. Matplotlib is imported here only.
"""

from __future__ import annotations

import csv
import io

import json
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from ..io.export import atomic_path
from ..io.figures import pyplot
from .build import SENSING_RADIUS, Calibration
from .regression import OUTPUTS

__all__ = ["write_report", "write_csv", "error_grid"]

CELL = 2e-3  # m: the error map's bin size


def _training_text(t: dict | None) -> str:
    """One sentence on what the direct regression was trained on."""
    if not t:
        return ""
    if not t["noise_copies"]:
        return f"Trained on the {t['samples']} stored (noisy) training samples."
    lo, hi = t["snr_db"]
    moved = (f", each moved about the ring by one of its {t['symmetries']} symmetries" if t.get("symmetries") else "")
    return (f"Trained on the {t['samples']} stored training samples and {t['noise_copies']} fresh noise draws of each "
            f"(SNR uniform {lo:.0f}–{hi:.0f} dB, as the dataset draws it{moved}): {t['rows']} rows.")


def _span_mm(lo: float, hi: float | None) -> str:
    """A bin of lengths in m as "a-b" mm ("a+" when open above: ``hi`` None)."""
    return f"{lo * 1e3:.0f}-{hi * 1e3:.0f}" if hi is not None else f"{lo * 1e3:.0f}+"


def _binned_tables(reg: Mapping[str, Any]) -> list[str]:
    """Where the direct regression's position, size and force errors come from (held-out, by bin)."""
    L = []
    rows = [r for r in reg.get("position_by_radius", []) if r["n"]]
    if rows:
        L += ["", "In-plane position error by the true position's distance from the axis (all held-out samples, all SNRs):", "",
              "| r (mm) | n | median (mm) | P95 (mm) |", "|---|---|---|---|"]
        L += [f"| {_span_mm(r['from'], r['to'])} | {r['n']} | {_fmt(r['median'] * 1e3)} | {_fmt(r['p95'] * 1e3)} |" for r in rows]
    rows = [r for r in reg.get("by_size", []) if r["n"]]
    if rows:
        L += ["", "By true diameter (all held-out samples): a predicted median that stays near the training mean "
              "across the bins means the voltages do not tell the size.", "",
              "| true diameter (mm) | n | predicted median (mm) | median error (mm) |", "|---|---|---|---|"]
        L += [f"| {r['from'] * 1e3:.0f}-{r['to'] * 1e3:.0f} | {r['n']} | {_fmt(r['predicted_median'] * 1e3)} | "
              f"{_fmt(r['error_median'] * 1e3)} |" for r in rows]
    rows = [r for r in reg.get("force_by_depth", []) if r["n"]]
    if rows:
        L += ["", "|F| by true depth (all held-out samples):", "",
              "| depth (mm) | n | true median (mN) | predicted median (mN) | median error (mN) | median relative error |",
              "|---|---|---|---|---|---|"]
        L += [f"| {r['from'] * 1e3:.0f}-{r['to'] * 1e3:.0f} | {r['n']} | {_fmt(r['truth_median'] * 1e3)} | "
              f"{_fmt(r['predicted_median'] * 1e3)} | {_fmt(r['error_median'] * 1e3)} | {r['relative_median']:.0%} |"
              for r in rows]
    return L


def write_csv(path: Path, columns: Mapping[str, Sequence[Any]]) -> Path:
    """Columns of equal length as CSV (header = the names), floats with 6 significant digits."""
    names = list(columns)
    cols = [np.asarray(columns[n]) for n in names]
    n = len(cols[0]) if cols else 0

    def fmt(v: Any) -> str:
        return f"{v:.6g}" if isinstance(v, (float, np.floating)) else str(v)

    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")  # quotes a field with a comma ("CoM xy, r <= 15 mm")
    w.writerow(names)
    w.writerows([fmt(c[i]) for c in cols] for i in range(n))
    with atomic_path(path) as tmp:
        tmp.write_text(buf.getvalue())
    return path


def error_grid(x: np.ndarray, y: np.ndarray, err: np.ndarray, radius: float = SENSING_RADIUS,
               cell: float = CELL) -> dict[str, np.ndarray]:
    """Median |err| and count per square cell of side ``cell`` whose centre is within
    ``radius``: columns x, y (cell centres, m), n, median (same unit as ``err``)."""
    edges = np.arange(-radius, radius + cell / 2, cell)
    cx = (edges[:-1] + edges[1:]) / 2
    ok = np.isfinite(err)
    ix, iy = np.digitize(x[ok], edges) - 1, np.digitize(y[ok], edges) - 1
    e = np.abs(err[ok])
    rows = {"x": [], "y": [], "n": [], "median": []}
    for i, xc in enumerate(cx):
        for j, yc in enumerate(cx):
            if np.hypot(xc, yc) > radius:
                continue
            sel = (ix == i) & (iy == j)
            rows["x"].append(xc)
            rows["y"].append(yc)
            rows["n"].append(int(sel.sum()))
            rows["median"].append(float(np.median(e[sel])) if sel.any() else float("nan"))
    return {k: np.asarray(v) for k, v in rows.items()}


def _save(fig, path: Path) -> Path:
    import matplotlib.pyplot as plt

    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=120, bbox_inches="tight", format="png")
    plt.close(fig)
    return path


def _size_figure(out: Path, cal: Calibration, along: str) -> Path:
    plt = pyplot()

    curves = {k: lc for k, lc in cal.map.size.items() if lc.along == along}
    t = cal.tables["size_at_levels"]
    fig, axes = plt.subplots(1, len(curves), figsize=(4.2 * len(curves), 3.6), squeeze=False)
    cmap = plt.get_cmap("viridis")
    unit = {"sum_sigma": ("Σσ, total conductivity change (S/m·voxel)", 1.0), "diameter": ("image diameter (mm)", 1e3),
            "rms_dv": ("RMS δV (µV)", 1e6), "force": ("|F| (mN)", 1e3)}
    words = {"sum_sigma": "Σσ", "diameter": "image diameter", "rms_dv": "RMS δV", "force": "|F|"}
    for ax, (key, lc) in zip(axes[0], curves.items()):
        label, s = unit[lc.metric]
        for i, (lv, c) in enumerate(zip(lc.levels, lc.curves)):
            col = cmap(i / max(1, len(lc.levels) - 1))
            name = f"{lv * 1e3:.2g} mm" if along == "depth" else f"{lv * 1e3:.3g} mN"
            if c is not None:
                ax.plot(c.x * 1e3, c.y * s, "-", color=col, lw=1.2, label=name)
            sel = (t["along"] == along) & (t["metric"] == lc.metric) & np.isclose(t["level"], lv)
            ax.plot(t["size"][sel] * 1e3, t["value"][sel] * s, "o", ms=3, color=col, mfc="none")
        ax.set_xlabel("true target diameter (mm)")
        ax.set_ylabel(label)
        ax.set_title(f"{words[lc.metric]} at fixed {along}" + (" (route used)" if key == cal.map.size_route else ""), fontsize=9)
        ax.legend(fontsize=6, title=f"{along}", title_fontsize=6)
    fig.suptitle("size curves: lines fitted on training presses (isotonic), circles held-out presses", fontsize=9)
    return _save(fig, out / f"size_curves_{along}.png")


def _com_figure(out: Path, grids: dict[str, dict[str, np.ndarray]]) -> Path:
    plt = pyplot()

    fig, axes = plt.subplots(1, 2, figsize=(9, 4))
    for ax, (name, g) in zip(axes, grids.items()):
        xs = np.unique(g["x"])
        img = np.full((len(xs), len(xs)), np.nan)
        ix, iy = np.searchsorted(xs, g["x"]), np.searchsorted(xs, g["y"])
        img[iy, ix] = g["median"] * 1e3
        h = CELL * 1e3 / 2
        im = ax.imshow(img, origin="lower", extent=(xs[0] * 1e3 - h, xs[-1] * 1e3 + h, xs[0] * 1e3 - h, xs[-1] * 1e3 + h),
                       cmap="magma")
        ax.add_patch(plt.Circle((0, 0), SENSING_RADIUS * 1e3, fill=False, ls="--", color="0.5"))
        ax.set_title(f"held-out median |{name} error| (mm) per {CELL * 1e3:g} mm cell", fontsize=9)
        ax.set_xlabel("x (mm)")
        ax.set_ylabel("y (mm)")
        fig.colorbar(im, ax=ax, shrink=0.8, label=f"median |{name} error| (mm)")
    return _save(fig, out / "com_error_map.png")


def _coverage_figure(out: Path, t: Mapping[str, np.ndarray]) -> Path:
    """What the dataset covers: every sample's contact centre coloured by depth, with the
    electrode ring's radius; RMS δV against depth coloured by the target's diameter."""
    plt = pyplot()

    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4.2), gridspec_kw={"wspace": 0.45})
    sc = a.scatter(t["x"] * 1e3, t["y"] * 1e3, c=t["depth"] * 1e3, s=4, cmap="viridis")
    a.add_patch(plt.Circle((0, 0), SENSING_RADIUS * 1e3, fill=False, ls="--", color="0.5"))
    a.set_aspect("equal")
    a.set_xlabel("x (mm)")
    a.set_ylabel("y (mm)")
    a.set_title(f"{len(t['x'])} samples: contact centres (dashed: r = {SENSING_RADIUS * 1e3:g} mm)", fontsize=9)
    fig.colorbar(sc, ax=a, shrink=0.8, label="depth past first contact (mm)")
    sc = b.scatter(t["depth"] * 1e3, t["rms_dv"] * 1e6, c=t["diameter"] * 1e3, s=4, cmap="plasma")
    b.set_yscale("log")
    b.set_xlabel("depth past first contact (mm)")
    b.set_ylabel("RMS δV, noisy (µV)")
    b.set_title("signal against depth", fontsize=9)
    fig.colorbar(sc, ax=b, shrink=0.8, label="target diameter (mm)")
    return _save(fig, out / "dataset_coverage.png")


def _position_figure(out: Path, reg: Mapping[str, np.ndarray], kind: str) -> Path:
    """The direct regression's held-out in-plane error against the true position's distance
    from the axis: every sample, and the median per 1.5 mm."""
    plt = pyplot()

    r = np.hypot(reg["true_x"], reg["true_y"]) * 1e3
    e = np.hypot(reg[f"{kind}_x"] - reg["true_x"], reg[f"{kind}_y"] - reg["true_y"]) * 1e3
    fig, ax = plt.subplots(figsize=(5.5, 4))
    ax.semilogy(r, e, ".", ms=3, alpha=0.5, color="tab:blue", label="held-out samples")
    edges = np.arange(0, max(16.5, r.max() + 1.5), 1.5)
    mid, med = [], []
    for lo, hi in zip(edges[:-1], edges[1:]):
        sel = (r >= lo) & (r < hi)
        if sel.any():
            mid.append((lo + hi) / 2)
            med.append(np.median(e[sel]))
    ax.plot(mid, med, "k-o", ms=3, label="median per 1.5 mm")
    ax.axvline(SENSING_RADIUS * 1e3, color="0.5", ls="--", lw=0.8)
    ax.set_xlabel("contact centre's distance from the axis (mm)")
    ax.set_ylabel(f"|position error| ({kind}, mm)")
    ax.set_title("held-out position error over the sensor (all SNRs)", fontsize=9)
    ax.legend(fontsize=7)
    return _save(fig, out / "position_by_radius.png")


def _stiffness_figure(out: Path, t: Mapping[str, np.ndarray]) -> Path:
    plt = pyplot()

    fig, ax = plt.subplots(figsize=(4, 4))
    ax.loglog(t["true_modulus"] / 1e3, t["predicted_modulus"] / 1e3, "o", mfc="none")
    lim = [min(t["true_modulus"].min(), t["predicted_modulus"].min()) / 1e3, max(t["true_modulus"].max(), t["predicted_modulus"].max()) / 1e3]
    ax.plot(lim, lim, "k--", lw=0.8)
    ax.set_xlabel("true modulus (kPa)")
    ax.set_ylabel("estimated modulus (kPa)")
    ax.set_title("stiffness, held-out presses", fontsize=9)
    return _save(fig, out / "stiffness.png")


def _region_text(r: Mapping[str, Any]) -> list[str]:
    """The region the map was trained on, and the held-out estimates flagged outside it."""
    return [f"Trained on presses within r ≤ {r['r_max_m'] * 1e3:.3g} mm of the axis (centre of pressure), "
            f"{r['depth_m'][0] * 1e3:.3g}–{r['depth_m'][1] * 1e3:.3g} mm deep, targets of "
            f"{r['diameter_m'][0] * 1e3:.3g}–{r['diameter_m'][1] * 1e3:.3g} mm diameter. Applied to frames, "
            "an estimate outside this region is flagged (`outside` in calibrated.csv); "
            f"{r['test_estimates_outside']} of {r['test_samples']} held-out samples' direct estimates were.", ""]


def _fmt(v: Any, digits: int = 3) -> str:
    return "—" if v is None or (isinstance(v, float) and not np.isfinite(v)) else f"{v:.{digits}g}"


def _model_based_table(mb: Mapping[str, Any] | None) -> list[str]:
    """The emulator's section: its fits' errors, and how often their σ covers the truth."""
    if not mb:
        return []
    L = ["", "## Model-based estimation (an emulator of the coupled model)", "",
         f"The emulator explains {mb['emulator_r2']:.0%} of the held-out presses' feature variance (R², whitened). Fitted from "
         "the direct regression's estimates at each frame's SNR: each frame alone, and a press's frames at least "
         f"{mb['press_min_depth_m'] * 1e3:g} mm deep jointly (x, y and the diameter shared). Errors in mm over all held-out "
         "samples; the share of estimates within 1σ and 2σ of the truth in the goal band, by the σ each fit reports "
         "(68 % and 95 % when the σ is right; `model_sd_*`, `press_sd_*` where the map is applied).", "",
         "| fit | xy median / P95 (r ≤ 15 mm) | depth median / P95 | diameter median / P95 | within 1σ (x, y, depth, diameter) "
         "| within 2σ |", "|---|---|---|---|---|---|"]
    for name in ("per frame", "press"):
        r = mb[name]
        cov = r.get("coverage")
        within = [" / ".join(f"{c[k]:.0%}" for c in cov.values()) if cov else "–" for k in ("within_1sd", "within_2sd")]
        L.append(f"| {name} | {_fmt(r['xy_r15']['median'])} / {_fmt(r['xy_r15']['p95'])} | {_fmt(r['depth']['median'])} / "
                 f"{_fmt(r['depth']['p95'])} | {_fmt(r['size']['median'])} / {_fmt(r['size']['p95'])} | {within[0]} | {within[1]} |")
    return L


def _markdown(cal: Calibration, command: str, files: list[str]) -> str:
    ev, m = cal.evaluation, cal.map
    sp, com = ev["split"], ev["com"]
    src = m.source
    L = [
        "# Calibration report", "",
        *(["**SYNTHETIC dataset** (jointsim.calibration.synthetic: measurements are known functions of the labels, "
            "no physics simulated): these numbers say nothing about the sensor.", ""] if src.get("synthetic") else []),
        f"Command: `{command}`", "",
        f"Dataset: `{src.get('path')}`, {src.get('n_records')} samples (data_sha256 `{str(src.get('data_sha256'))[:16]}…`); "
        f"{sp['train_presses']} presses ({sp['train_samples']} samples) fitted, {sp['test_presses']} presses "
        f"({sp['test_samples']} samples) held out by press (split seed {sp['seed']}, overlap {sp['overlapping_presses']}). "
        "Every error below is on the held-out presses only.", "",
        f"Goal figures use {ev['goal_band']}.", "",
        *([f"**Warning:** {w}." for w in ev.get("warnings", [])] + [""] if ev.get("warnings") else []),
        *(_region_text(ev["region"]) if "region" in ev else []),
        "## Goals (at 74 dB)", "",
        "| goal | route | statistic | limit | held-out value | verdict |", "|---|---|---|---|---|---|",
    ]
    for g in ev["goals"]:
        unit = g["unit"] or "(fraction)"
        L.append(f"| {g['goal']} | {g.get('route', 'image')} | {g['statistic']} | {g['limit']:g} {unit} | {_fmt(g['value'])} {g['unit']} | "
                 f"{g.get('verdict', 'met' if g['met'] else 'not met')}{(' — ' + g['note']) if g['note'] else ''} |")
    L += ["", "## CoM map (thin-plate spline, reconstructed CoM → x, y, depth)", "",
          "In x and y the spline fits the correction to the reconstructed CoM; each training point's smoothing is "
          "scaled by its noise power.",
          f"Smoothing {com['smoothing']:g} at the median SNR (grouped 3-fold CV on the training presses: mean 3-D error, weighted by inverse noise), "
          f"{com['fitted_points']} points; "
          f"{com['test_without_com']} held-out samples had no reconstructed CoM. Position (x, y): {com['position']}.", "",
          "| error (mm) | n | median | P95 |", "|---|---|---|---|"]
    for name, key in (("xy, all", "xy_all"), ("xy, r ≤ 15 mm", "xy_r15"), ("xy, r ≤ 15 mm, goal SNR band", "xy_r15_goal_band"),
                      ("depth, all", "depth_all"), ("depth, goal SNR band", "depth_goal_band"),
                      ("uncalibrated CoM xy, r ≤ 15 mm", "raw_xy_r15")):
        e = com[key]
        L.append(f"| {name} | {e['n']} | {_fmt(e['median'])} | {_fmt(e['p95'])} |")
    L += ["", "Error map: `com_error_map.png`, `com_error_map.csv` (median per 2 mm cell over r ≤ 15 mm).", "",
          "## Size curves (target diameter)", "",
          f"Levels: depth {', '.join(f'{d * 1e3:.3g}' for d in ev['size_levels']['depth_m'])} mm; force "
          f"{', '.join(f'{f * 1e3:.3g}' for f in ev['size_levels']['force_n'])} mN. Per frame, each route blends the "
          "curves of the two levels around the frame's calibrated depth (CoM map) or |force| and inverts the blend.", "",
          "| route | frames covered | median (mm) | P95 (mm) | median, 8–30 mm, goal band |", "|---|---|---|---|---|"]
    for k, r in ev["size_per_frame"].items():
        L.append(f"| {k}{' (used)' if k == ev['size_route'] else ''} | {r['covered']:.0%} | {_fmt(r['all']['median'])} | "
                 f"{_fmt(r['all']['p95'])} | {_fmt(r['range_goal_band']['median'])} |")
    L += ["", "At each level alone (held-out presses read at that depth or force): `size_errors.csv`; curves: "
          "`size_curves_depth.png`, `size_curves_force.png`, `size_at_levels.csv`.", "",
          f"## Direct regression (256 δV/V → x, y, depth, diameter, |F|; {ev['regression']['kind']}) vs the image route", "",
          "Errors in mm (force in mN); x, y over r ≤ 15 mm, diameter over 8–30 mm. The image route is the CoM map "
          "and the size curve; it has no force estimate. " + _training_text(ev["regression"].get("training")), "",
          "| output | image route median / P95 | " + " | ".join(f"{k} median / P95" for k in ev["regression"]["comparison"]["x"]
                                                        if k in ("mlp", "ridge")) + " |",
          "|---|---|" + "---|" * len([k for k in ev["regression"]["comparison"]["x"] if k in ("mlp", "ridge")])]
    for o, c in ev["regression"]["comparison"].items():
        kinds = [k for k in c if k in ("mlp", "ridge")]
        L.append(f"| {o} | {_fmt(c['image']['median'])} / {_fmt(c['image']['p95'])} | "
                 + " | ".join(f"{_fmt(c[k]['median'])} / {_fmt(c[k]['p95'])}" for k in kinds) + " |")
    L += _binned_tables(ev["regression"])
    L += _model_based_table(ev.get("model_based"))
    st = ev["stiffness"]
    L += ["", "## Stiffness", ""]
    if st["estimable"]:
        r = st["relative"]
        L.append(f"{st['reason']}. Held-out relative modulus error: median {_fmt(r['median'])}, P95 {_fmt(r['p95'])} "
                 f"({r['n']} presses). `stiffness.png`, `stiffness.csv`.")
        rows = [b for b in st.get("by_decade", []) if b["n"]]
        if rows:
            L += ["", "| true modulus (kPa) | presses | median | P95 |", "|---|---|---|---|"]
            L += [f"| {b['from_pa'] / 1e3:g}-{b['to_pa'] / 1e3:g} | {b['n']} | {_fmt(b['median'])} | {_fmt(b['p95'])} |"
                  for b in rows]
    else:
        L.append(f"**Not estimable**: {st['reason']}. The map predicts no modulus (NaN).")
    fs = st.get("force_sensitivity", {})
    if fs.get("by_decade"):
        L += ["", f"What the force tells of the modulus (all soft presses, labels known): |F| at {fs['depth_m'] * 1e3:.2g} mm "
              "against a target of the same radius (fit of log |F| on log R), per decade of E:", "",
              "| true modulus (kPa) | presses | mean | spread (SD) |", "|---|---|---|---|"]
        L += [f"| {b['from_pa'] / 1e3:g}-{b['to_pa'] / 1e3:g} | {b['n']} | {b['mean_percent']:+.1f} % | {b['sd_percent']:.1f} % |"
              for b in fs["by_decade"]]
    L += ["", "## Files", "", *[f"- `{f}`" for f in files], ""]
    return "\n".join(L)


def write_report(out: str | Path, cal: Calibration, command: str) -> list[Path]:
    """Write the tables, figures, ``evaluation.json`` and ``report.md`` of ``cal`` into ``out``."""
    out = Path(out)
    t = cal.tables
    written = [write_csv(out / "size_at_levels.csv", {k: v for k, v in t["size_at_levels"].items()})]
    rows = cal.evaluation["size_at_levels"]
    written.append(write_csv(out / "size_errors.csv", {k: [r[k] for r in rows] for k in
                                                       ("route", "along", "metric", "level", "n", "median_mm", "p95_mm")}))
    written.append(write_csv(out / "com_heldout.csv", t["com"]))
    c = t["com"]
    grids = {"xy": error_grid(c["x"], c["y"], c["error_xy"]), "depth": error_grid(c["x"], c["y"], c["error_depth"])}
    written.append(write_csv(out / "com_error_map.csv", {"x": grids["xy"]["x"], "y": grids["xy"]["y"], "n": grids["xy"]["n"],
                                                         "median_xy_error": grids["xy"]["median"],
                                                         "median_depth_error": grids["depth"]["median"]}))
    written.append(write_csv(out / "regression_heldout.csv", t["regression"]))
    comp = cal.evaluation["regression"]["comparison"]
    kinds = [k for k in comp["x"] if k in ("image", "mlp", "ridge")]
    written.append(write_csv(out / "regression_comparison.csv", {
        "output": list(OUTPUTS), **{f"{k}_{s}": [comp[o][k][s] for o in OUTPUTS] for k in kinds for s in ("n", "median", "p95")}}))
    g = cal.evaluation["goals"]
    written.append(write_csv(out / "goals.csv", {k: [r.get(k, "image" if k == "route" else None) for r in g] for k in ("goal", "route", "statistic", "limit", "value", "unit", "met", "verdict")}))
    written += [_size_figure(out, cal, "depth"), _size_figure(out, cal, "force"), _com_figure(out, grids)]
    if "samples" in t:
        written.append(_coverage_figure(out, t["samples"]))
    written.append(_position_figure(out, t["regression"], cal.evaluation["regression"]["kind"]))
    if "stiffness" in t:
        written.append(write_csv(out / "stiffness.csv", t["stiffness"]))
        written.append(_stiffness_figure(out, t["stiffness"]))
    with atomic_path(out / "evaluation.json") as tmp:
        tmp.write_text(json.dumps(cal.evaluation, indent=1, default=float))
    written.append(out / "evaluation.json")
    names = sorted({p.name for p in written} | {"calibration_map.h5", "report.md"})
    with atomic_path(out / "report.md") as tmp:
        tmp.write_text(_markdown(cal, command, names))
    written.append(out / "report.md")
    return written
