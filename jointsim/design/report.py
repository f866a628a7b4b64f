"""The design study's outputs: per design its bounds table (CSV) and maps (PNG), and the table
that sets the designs side by side against the goals (Markdown, CSV)."""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..geometry import electrode_layout
from ..scene import Scene
from ..io.records import Records
from .study import DesignBounds, design_bounds

__all__ = ["GOALS", "MODULUS_GOAL", "goals_of", "BANDS", "Summary", "summarise", "required_snr", "write_design", "write_comparison", "estimator_rows",
           "by_contact_radius"]

# the calibration goals at 74.2 dB (jointsim.calibration.build.GOALS), median |error| in m;
# a soft target's modulus: its relative error (the bound on ln E), 20 %
GOALS = {"position": 0.5e-3, "depth": 0.5e-3, "diameter": 1.0e-3}
MODULUS_GOAL = 0.2
QUANTITIES = ("position", "depth", "diameter")


def goals_of(b: "DesignBounds") -> dict[str, float]:
    """The goals a study is held to: :data:`GOALS`, and :data:`MODULUS_GOAL` where its targets are soft."""
    return {**GOALS, "modulus": MODULUS_GOAL} if "modulus" in b.quantities else dict(GOALS)


@dataclass(frozen=True)
class Summary:
    """One design at one SNR: per quantity and bound kind, the median over the reached presses
    and depths of the efficient estimator's median error, and the 95th percentile of the RMS
    bound, m (the modulus's: of ln E, a relative error, for soft targets); ``reached`` of
    ``presses`` (press × depth) the mechanics could take."""

    design: str
    snr_db: float
    median: dict[str, float]
    p95: dict[str, float]
    reached: int
    presses: int


def summarise(name: str, b: DesignBounds, diameter: float | None = None, depth: float | None = None,
              modulus: float | None = None) -> Summary:
    """The :class:`Summary` of ``b`` (over one ``diameter`` m, one ``depth`` m, or one soft
    target's ``modulus`` Pa, only, where given)."""
    c = b.columns
    within = np.ones(len(b), bool)
    if diameter is not None:
        within &= np.isclose(c["diameter"], diameter)
    if depth is not None:
        within &= np.isclose(c["depth"], depth)
    if modulus is not None:
        within &= np.isclose(c["target_modulus"], modulus)
    sel = within & np.isfinite(c["position_rms_marginal"])
    total = int(within.sum())
    med, p95 = {}, {}
    for kind in ("known", "marginal"):
        for q in b.quantities:
            m, r = c[f"{q}_median_{kind}"][sel], c[f"{q}_rms_{kind}"][sel]
            med[f"{q}_{kind}"] = float(np.median(m)) if m.size else math.nan
            p95[f"{q}_{kind}"] = float(np.percentile(r, 95)) if r.size else math.nan
    return Summary(name, b.snr_db, med, p95, int(sel.sum()), total)


# dB: the highest SNR the required-SNR search tries. Above ~180 dB the data's information swamps
# the priors by ~1e16 where only a prior separates two parameters (the head and the moduli act on
# a depth-controlled press only as ratios), and the bounds' Cholesky fails
SNR_CEILING = 160.0


def required_snr(study: Path | Records, scene: Scene, goals: dict[str, float], kind: str = "marginal",
                 lo: float = 0.0, hi: float = SNR_CEILING, resolution: float = 0.1, **frames: int) -> dict[str, float]:
    """For each quantity of ``goals`` (m), the lowest SNR dB (to ``resolution``, within [``lo``,
    ``hi``]) at which the efficient estimator's median error (median over the presses) is
    within its goal, by bisection (the bounds fall as the SNR rises); ``lo`` where it is met
    there already, inf where not even at ``hi``. The quantities share the bounds of the SNRs
    they both visit. ``frames``: reference_frames, hold_frames (:func:`design_bounds`)."""
    medians: dict[float, dict[str, float]] = {}

    def met(quantity: str, snr: float) -> bool:
        if snr not in medians:
            medians[snr] = summarise("", design_bounds(study, scene, snr_db=snr, **frames)).median
        return medians[snr][f"{quantity}_{kind}"] <= goals[quantity]

    out = {}
    for q in goals:
        a, b = lo, hi
        if met(q, a):
            out[q] = a
            continue
        if not met(q, b):
            out[q] = math.inf
            continue
        while b - a > resolution:
            mid = 0.5 * (a + b)
            a, b = (a, mid) if met(q, mid) else (mid, b)
        out[q] = b
    return out


def _unit(key: str) -> tuple[str, float]:
    """A bounds column's unit suffix and scale: mm for lengths, kPa for a target's modulus, and
    the bounds on ln E as they are (a relative error)."""
    if key == "target_modulus":
        return "_kpa", 1e-3
    if key.startswith("modulus_"):
        return "", 1.0
    return "_mm", 1e3


def _write_csv(path: Path, columns: dict[str, np.ndarray]) -> Path:
    keys = list(columns)
    units = [_unit(k) for k in keys]
    with path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow([k + u for k, (u, _) in zip(keys, units)])
        for row in zip(*(columns[k] for k in keys)):
            w.writerow([f"{v * x:.6g}" for v, (_, x) in zip(row, units)])
    return path


def _map_figure(path: Path, scene: Scene, b: DesignBounds, column: str, title: str, scale: float = 1e3,
                unit: str = "mm") -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm
    from matplotlib.patches import Circle

    c = b.columns
    # panels: depth × size, or × modulus for soft targets
    across = "target_modulus" if "target_modulus" in c else "diameter"
    panels = np.unique(c[across])
    depths = np.unique(c["depth"])
    layout = electrode_layout(scene)
    vals = c[column][np.isfinite(c[column])] * scale
    norm = LogNorm(vmin=max(vals.min(), 1e-4), vmax=max(vals.max(), 1e-3)) if vals.size else None
    fig, axes = plt.subplots(len(depths), len(panels), figsize=(3.4 * len(panels) + 1.2, 3.3 * len(depths)),
                             squeeze=False, layout="constrained")
    sc = None
    base = scene.chamber.base_radius * 1e3
    for row, depth in zip(axes, depths):
        for ax, d in zip(row, panels):
            sel = np.isclose(c[across], d) & np.isclose(c["depth"], depth)
            ok = sel & np.isfinite(c[column])
            ax.add_patch(Circle((0, 0), base, fill=False, color="0.6"))
            for (x, y, _), r in zip(layout.centres, layout.radii):
                ax.add_patch(Circle((x * 1e3, y * 1e3), r * 1e3, fill=False, color="0.3", zorder=1))
            sc = ax.scatter(c["contact_x"][ok] * 1e3, c["contact_y"][ok] * 1e3, c=c[column][ok] * scale, norm=norm,
                            cmap="viridis", s=18, zorder=2)
            miss = sel & ~np.isfinite(c[column])
            ax.plot(c["x"][miss] * 1e3, c["y"][miss] * 1e3, "x", color="r", ms=4, label="not reached (target centre)")
            ax.set_aspect("equal")
            ax.set_xlim(-base * 1.05, base * 1.05)
            ax.set_ylim(-base * 1.05, base * 1.05)
            ax.set_xlabel("contact x (mm)", fontsize=8)
            ax.set_ylabel("contact y (mm)", fontsize=8)
            ax.tick_params(labelsize=7)
            what = f"E {d * 1e-3:g} kPa" if across == "target_modulus" else f"{d * 1e3:g} mm sphere"
            ax.set_title(f"{what}, {depth * 1e3:g} mm deep", fontsize=9)
            if miss.any():
                ax.legend(loc="lower left", fontsize=6)
    if sc is not None:
        fig.colorbar(sc, ax=axes.ravel().tolist(), label=unit, shrink=0.6)
    fig.suptitle(f"{scene.name}\n{title} at {b.snr_db:g} dB", fontsize=10)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def write_design(out: Path, scene: Scene, path: Path | Records, snrs: tuple[float, ...] = (),
                 **frames: int) -> tuple[list[Path], list[tuple[Summary, str]], DesignBounds]:
    """Write ``out``/bounds.csv and the maps of the study at ``path`` (or its records already
    read); its summaries with what each covers (all presses, each diameter, each depth, at the
    scene's SNR; all at each of ``snrs``), and its bounds at the scene's SNR. ``frames``:
    reference_frames, hold_frames (:func:`~.study.design_bounds`)."""
    out.mkdir(parents=True, exist_ok=True)
    b = design_bounds(path, scene, **frames)
    written = [_write_csv(out / "bounds.csv", b.columns)]
    written.append(_map_figure(out / "position_bound.png", scene, b, "position_median_marginal",
                               "contact position: an efficient estimator's median error"))
    written.append(_map_figure(out / "diameter_bound.png", scene, b, "diameter_median_marginal",
                               "diameter: an efficient estimator's median error"))
    summaries = [(summarise(scene.name, b), "all")]
    summaries += [(summarise(scene.name, b, diameter=d), f"{d * 1e3:g} mm") for d in np.unique(b.columns["diameter"])]
    summaries += [(summarise(scene.name, b, depth=d), f"{d * 1e3:g} mm deep") for d in np.unique(b.columns["depth"])]
    if "target_modulus" in b.columns:
        written.append(_map_figure(out / "modulus_bound.png", scene, b, "modulus_median_marginal",
                                   "soft target's Young's modulus: an efficient estimator's median relative error",
                                   scale=100.0, unit="%"))
        summaries += [(summarise(scene.name, b, modulus=e), f"E {e * 1e-3:g} kPa") for e in np.unique(b.columns["target_modulus"])]
    for snr in snrs:
        if not math.isclose(snr, scene.noise.snr_db):
            summaries.append((summarise(scene.name, design_bounds(path, scene, snr_db=snr, **frames)), "all"))
    return written, summaries, b


def _mm(v: float) -> str:
    return "inf" if not math.isfinite(v) else f"{v * 1e3:.3g}"


def _pct(v: float) -> str:
    return "inf" if not math.isfinite(v) else f"{v * 1e2:.3g}"


def estimator_rows(goals_csv: Path) -> dict[str, dict[str, float]]:
    """The medians a calibration's routes reached (its ``goals.csv``): {route: {quantity: m}}.
    Files written before the goal names were quoted ("CoM xy, r <= 15 mm" unquoted) are read
    too: a row's surplus fields belong to its goal."""
    rows = list(csv.reader(Path(goals_csv).read_text().splitlines()))
    header = rows[0]
    out: dict[str, dict[str, float]] = {}
    for fields in rows[1:]:
        extra = len(fields) - len(header)
        if extra > 0:
            fields = [",".join(fields[: extra + 1])] + fields[extra + 1:]
        r = dict(zip(header, fields))
        goal = r.get("goal", "")
        q = "position" if goal.startswith("CoM") else "diameter" if goal.startswith("size") else goal
        if r.get("statistic") == "median" and q in QUANTITIES and r.get("value") not in (None, "", "nan"):
            out.setdefault(r["route"], {})[q] = float(r["value"]) * 1e-3
    return out


BANDS = (0.0, 5e-3, 10e-3, 15e-3, 20e-3)  # m: contact radius bands of the "where" table


def by_contact_radius(b: DesignBounds, column: str = "position_median_marginal") -> list[float]:
    """The median of ``column`` over the presses whose contact point lies in each band of
    :data:`BANDS` (NaN for an empty band): where over the surface a design loses accuracy."""
    c = b.columns
    out = []
    for lo, hi in zip(BANDS[:-1], BANDS[1:]):
        v = c[column][(c["contact_r"] >= lo) & (c["contact_r"] < hi) & np.isfinite(c[column])]
        out.append(float(np.median(v)) if v.size else math.nan)
    return out


def _over_all(rows: list[tuple[Summary, str]], design: str) -> Summary:
    """``design``'s summary over all its presses at its own SNR (the first such row)."""
    return next(s for s, what in rows if s.design == design and what == "all")


def write_comparison(out: Path, rows: list[tuple[Summary, str]], needed: dict[str, dict[str, float]], command: str,
                     timings: dict[str, tuple[np.ndarray, float, int, int, str]] | None = None,
                     estimators: tuple[str, Path] | None = None,
                     where: dict[str, DesignBounds] | None = None, refined: dict[str, int] | None = None,
                     joint: dict[str, Summary] | None = None,
                     joint_moduli: dict[str, list[tuple[str, Summary]]] | None = None,
                     pressed: dict[str, tuple[int, int, int]] | None = None) -> list[Path]:
    """``out``/summary.md and summary.csv: the designs side by side (``rows``: a summary and
    what it covers), the SNR each needs to meet each goal (``needed``[design][quantity]), what
    each design cost (``timings``[design]: the stored press times s, and this run's wall s,
    presses computed and workers, or the store's own run's with workers None; and the store's
    data digest), and a calibration's estimators beside the first design's
    bound (``estimators``: the design's name and the calibration's goals.csv); ``refined``[design]:
    how many times its membrane was refined about each press's contact; ``joint``[design]: the
    summary of its presses' frames read together (:func:`~.study.press_joint_bounds`), which a
    calibration's per-press route is set beside; ``joint_moduli``[design]: the same per soft
    target's modulus (what, summary); ``pressed``[design]: the presses computed, and those of
    the grid they stand for by the design's symmetries (:func:`~.study.press_layout`), and the
    mechanical solves they took (:func:`~.study.press_groups`)."""
    lines = ["# Design study: what each design can measure", "", f"Command: `{command}`", "",
             "Cramér–Rao bounds through the coupled model (jointsim.design): an unbiased estimator's error cannot be "
             "smaller. *median*: over the presses (target centres × depths) of an efficient estimator's median |error|; "
             "*P95*: the 95th percentile of the RMS bound. *known*: the sensor's nuisances known exactly; *marginal*: "
             "marginalised over the scene's [dataset] randomisation as a prior. Position is the contact point's, "
             "size the sphere's diameter. All in mm.", ""]
    if refined:
        lines += ["Each press read through a membrane refined about its contact (jointsim.design.sensitivity.contact_membrane; "
                  "0: the scene's membrane as meshed, whose size bounds are optimistic): "
                  + ", ".join(f"{d} {n}×" for d, n in refined.items()) + ".", ""]
    if pressed and any(n < total for n, total, _ in pressed.values()):
        lines += ["Presses computed, of the grid's: one per set of centres the design's symmetries (its chamber, "
                  "electrodes and protocol) map onto each other, the others given its bounds "
                  "(jointsim.design.study.press_layout): " + ", ".join(f"{d} {n} of {t}" for d, (n, t, _) in pressed.items()) + ".", ""]
    if pressed and any(m < n for n, _, m in pressed.values()):
        lines += ["Mechanical solves, of the presses computed: one per target and ring of the grid, turned about the axis "
                  "to the ring's other centres, each measured on its own (jointsim.design.study.press_groups): "
                  + ", ".join(f"{d} {m} of {n}" for d, (n, _, m) in pressed.items()) + ".", ""]
    lines += ["| design | SNR dB | presses | reached | position median (known / marg.) | position P95 marg. | depth median (known / marg.) "
              "| depth P95 marg. | diameter median (known / marg.) | diameter P95 marg. |",
              "|---|---|---|---|---|---|---|---|---|---|"]
    csv_rows = []
    for s, what in rows:
        lines.append(f"| {s.design} ({what}) | {s.snr_db:g} | {s.presses} | {s.reached} | "
                     f"{_mm(s.median['position_known'])} / {_mm(s.median['position_marginal'])} | {_mm(s.p95['position_marginal'])} | "
                     f"{_mm(s.median['depth_known'])} / {_mm(s.median['depth_marginal'])} | {_mm(s.p95['depth_marginal'])} | "
                     f"{_mm(s.median['diameter_known'])} / {_mm(s.median['diameter_marginal'])} | {_mm(s.p95['diameter_marginal'])} |")
        csv_rows.append({"design": s.design, "covers": what, "snr_db": s.snr_db, "presses": s.presses, "reached": s.reached,
                         **{f"median_{k}_mm": v * 1e3 for k, v in s.median.items()},
                         **{f"p95_{k}_mm": v * 1e3 for k, v in s.p95.items()}})
    soft = [(s, what) for s, what in rows if "modulus_marginal" in s.median]
    if soft:
        lines += ["", "## A soft target's Young's modulus", "",
                  "The relative error of E an efficient estimator allows (the bound on ln E), with the target's position, "
                  "depth and size unknown too; median over the presses × depths of the median error, and the P95 of the "
                  "RMS bound, %.", "",
                  "| design | SNR dB | presses | modulus median (known / marg.) | modulus P95 marg. |", "|---|---|---|---|---|"]
        for s, what in soft:
            lines.append(f"| {s.design} ({what}) | {s.snr_db:g} | {s.presses} | {_pct(s.median['modulus_known'])} / "
                         f"{_pct(s.median['modulus_marginal'])} | {_pct(s.p95['modulus_marginal'])} |")
    quantities = QUANTITIES + (("modulus",) if any("modulus" in req for req in needed.values()) else ())
    lines += ["", "## The SNR each design needs for the goals (an efficient estimator, nuisances marginalised)", "",
              "Goals (jointsim calibrate's, medians): " + ", ".join(f"{q} {g * 1e3:g} mm" for q, g in GOALS.items())
              + (f", a soft target's modulus {MODULUS_GOAL:.0%}" if len(quantities) > len(QUANTITIES) else "") + ".", "",
              "| design | " + " | ".join(quantities) + " |", "|---|" + "---|" * len(quantities)]
    for design, req in needed.items():
        lines.append(f"| {design} | " + " | ".join("–" if q not in req else f"not below {SNR_CEILING:g} dB" if not math.isfinite(req[q])
                                                    else f"{req[q]:.1f} dB" for q in quantities) + " |")
    if where:
        bands = [f"{lo * 1e3:g}–{hi * 1e3:g} mm" for lo, hi in zip(BANDS[:-1], BANDS[1:])]
        lines += ["", "## Where over the surface (contact point's distance from the axis)", "",
                  "Median over presses, depths and sizes of an efficient estimator's median error, nuisances "
                  "marginalised, at each design's SNR; position / diameter, mm.", "",
                  "| design | " + " | ".join(bands) + " |", "|---|" + "---|" * len(bands)]
        for design, b in where.items():
            pos, dia = by_contact_radius(b), by_contact_radius(b, "diameter_median_marginal")
            lines.append(f"| {design} | " + " | ".join("–" if math.isnan(p) else f"{_mm(p)} / {_mm(d)}"
                                                      for p, d in zip(pos, dia)) + " |")
    if joint:
        lines += ["", "## A press's frames read together", "",
                  "The frames of a press's depths fitted as one (its position and size shared, a depth each), nuisances "
                  "marginalised, at each design's SNR: the efficient estimator's median error over the presses, against "
                  "one frame's (over the presses × depths). Position is the contact point's at the deepest depth; mm.", "",
                  "| design | position: one frame / the press | depth: one frame / the press's deepest | "
                  "diameter: one frame / the press |", "|---|---|---|---|"]
        for design, j in joint.items():
            one = _over_all(rows, design)
            lines.append(f"| {design} | " + " | ".join(f"{_mm(one.median[f'{q}_marginal'])} / {_mm(j.median[f'{q}_marginal'])}"
                                                      for q in QUANTITIES) + " |")
        soft_joint = [(d, what, j) for d, js in (joint_moduli or {}).items() for what, j in js]
        if soft_joint:
            lines += ["", "A soft target's modulus (its relative error, %), one frame / the press (its modulus shared by "
                      "the frames), nuisances known and marginalised:", "",
                      "| design | one frame: known / marg. | the press: known / marg. |", "|---|---|---|"]
            for d, what, j in soft_joint:
                one = next(s for s, w in rows if s.design == d and w == what)
                lines.append(f"| {d} ({what}) | {_pct(one.median['modulus_known'])} / {_pct(one.median['modulus_marginal'])} | "
                             f"{_pct(j.median['modulus_known'])} / {_pct(j.median['modulus_marginal'])} |")
    if estimators is not None:
        design, goals = estimators
        base = _over_all(rows, design)
        lines += ["", f"## The calibration's estimators beside the bound ({design})", "",
                  f"Held-out medians from `{goals}` (presses drawn over the dataset's ranges, its SNR band about "
                  "74 dB, the sensor randomised) against an efficient estimator's median with the nuisances "
                  "marginalised over the same randomisation (this study's presses; a route fitting a press's frames "
                  "together against the press's bound). A ratio near 1: the estimator "
                  "reads what the sensor holds; far above: the estimator, not the sensor, limits it.", "",
                  "| route | " + " | ".join(f"{q}: estimator / bound (ratio)" for q in QUANTITIES) + " |",
                  "|---|" + "---|" * len(QUANTITIES)]
        for route, vals in estimator_rows(goals).items():
            cells = []
            # a route that reads a press's frames together is held to the press's bound
            against = joint[design] if joint and design in joint and "(press)" in route else base
            for q in QUANTITIES:
                b = against.median[f"{q}_marginal"]
                v = vals.get(q)
                cells.append("–" if v is None else f"{_mm(v)} / {_mm(b)} ({v / b:.3g}×)")
            lines.append(f"| {route} | " + " | ".join(cells) + " |")
    if timings:
        lines += ["", "## Cost", "",
                  "Press times are stored with each press (one worker, single-threaded, derivatives of every depth); "
                  "the wall time is this command's, which computed only what was not stored; where it computed none, the "
                  "run's that wrote the store (from its creation to its finalisation; its workers not recorded: –).", "",
                  "| design | presses | mean s per press | sum s | computed, workers, wall s | sensitivities.h5 data SHA-256 |",
                  "|---|---|---|---|---|---|"]
        for design, (stored, wall, n, w, sha) in timings.items():
            lines.append(f"| {design} | {len(stored)} | {np.mean(stored):.1f} | {np.sum(stored):.0f} | {n}, {w or '–'}, {wall:.0f} "
                         f"| `{sha[:16]}…` |")
    out.mkdir(parents=True, exist_ok=True)
    md = out / "summary.md"
    md.write_text("\n".join(lines) + "\n")
    path = out / "summary.csv"
    with path.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(csv_rows[0]))
        w.writeheader()
        for r in csv_rows:
            w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})
    return [md, path]
