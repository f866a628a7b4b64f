"""Building a calibration from a dataset: the split, every fit, and the held-out evaluation.

Owns the order of the work (split by press → size curves → CoM map → direct regression →
stiffness), the choice of the per-frame size route (the inverse curve with the least
held-out median error), and the evaluation of every part on the held-out presses alone:
median and 95th-percentile errors, over all noise levels and in the band around the goal
SNR, and the goals with whether each is met, not met or undetermined. The figures and files are
:mod:`jointsim.calibration.report`'s.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..eit.protocol import RingSymmetry, ring_symmetries, skip_protocol
from ..io.provenance import package_versions, utc_now
from .com import fit_com_map
from .curves import ALONG, LevelCurves, default_levels, fit_level_curves, value_at
from .data import Samples, split_groups, voltage_features
from .emulator import Emulator, coverage, fit_emulator, fit_frames, fit_presses, held_out_presses, recalibrated
from .maps import PRESS_MIN_DEPTH, VERSION_PACKAGES, CalibrationMap, outside_region, trained_region
from .regression import KINDS, OUTPUTS, copy_groups, fit_regressor, moved_by_symmetry, noisy_features, regression_targets
from .stiffness import decades, fit_stiffness, force_sensitivity, press_moduli, stiffness_levels

__all__ = ["Settings", "Calibration", "calibrate", "err_stats", "worse_than_uncalibrated", "METRICS", "GOALS"]

METRICS = {"depth": ("sum_sigma", "diameter", "rms_dv", "force"), "force": ("sum_sigma", "diameter", "rms_dv")}
SENSING_RADIUS = 15e-3  # m: the CoM goal holds for contacts within the electrode ring
MIN_JUDGED = {"modulus": 5}  # held-out presses for the modulus, samples for the rest (default 20) below which
# a goal is not called met
SIZE_RANGE = (8e-3, 30e-3)  # m: target diameters the size goal covers
# the goals at 74 dB: (name, quantity, statistic, limit in mm, or as a fraction for the modulus)
GOALS = (
    ("CoM xy, r <= 15 mm", "com_xy", "median", 0.5),
    ("CoM xy, r <= 15 mm", "com_xy", "p95", 1.0),
    ("depth", "depth", "median", 0.5),
    ("size (diameter 8-30 mm)", "size", "median", 1.0),
    ("modulus (relative)", "modulus", "median", 0.20),
)


@dataclass(frozen=True)
class Settings:
    """What shapes a calibration besides the data: the held-out fraction and split ``seed``,
    the depth (m) and force (N) levels of the size curves (None: chosen from the data), the
    direct regressor's kind, the goal SNR and the band around it (dB), the cap on the
    CoM map's fitted points, and ``noise_copies``: fresh noise draws of each training sample
    added to the direct regression's training set (over the training samples' SNR range; 0:
    the stored noisy samples only; ignored for a store without clean voltages), each moved
    about the ring by one of the sensor's symmetries when ``symmetry`` (a simulated store's
    only: a synthetic one's voltages are not a chamber's). Off by default: on the paper
    scene's 1500 samples (4 splits) it evens out the force and size tails (P95 27-33 vs
    31-36 mN, 10-11 vs 12-15 mm) but widens the x, y tail (1.7-2.6 vs 1.4-2.2 mm), the
    chamber mesh's own asymmetry (0.5-1.8 % of δV/V at the dataset preset) being what a
    moved copy gets wrong. ``emulator``: fit the model-based estimator (an emulator of the
    coupled model, where the store has clean voltages); off, the map has none and the
    calibration is quicker."""

    test_fraction: float = 0.2
    seed: int = 0
    depth_levels: tuple[float, ...] | None = None
    force_levels: tuple[float, ...] | None = None
    regressor: str = "mlp"
    goal_snr_db: float = 74.2
    snr_band_db: float = 4.0
    max_com_points: int = 3000
    noise_copies: int = 30
    symmetry: bool = False
    emulator: bool = True

    def __post_init__(self) -> None:
        if self.regressor not in KINDS:
            raise ValueError(f"regressor = {self.regressor!r}: one of {KINDS}")
        for name in ("depth_levels", "force_levels"):
            v = getattr(self, name)
            if v is not None and (len(v) == 0 or any(not (np.isfinite(x) and x > 0) for x in v)):
                raise ValueError(f"{name} = {v!r}: positive numbers, at least one")
        if not (self.snr_band_db > 0 and self.max_com_points >= 50):
            raise ValueError("snr_band_db must be > 0 dB and max_com_points >= 50")
        if not (isinstance(self.noise_copies, int) and 0 <= self.noise_copies <= 1000):
            raise ValueError(f"noise_copies = {self.noise_copies!r}: an integer in [0, 1000]")


def err_stats(e: np.ndarray, scale: float = 1e3) -> dict[str, float]:
    """n, median and 95th percentile of |e| (finite entries), times ``scale`` (m → mm)."""
    e = np.abs(np.asarray(e, float))
    e = e[np.isfinite(e)]
    if not len(e):
        return {"n": 0, "median": float("nan"), "p95": float("nan")}
    return {"n": int(len(e)), "median": float(np.median(e) * scale), "p95": float(np.percentile(e, 95) * scale)}


def worse_than_uncalibrated(com: dict) -> list[str]:
    """Warnings where the CoM map makes the held-out in-plane position worse than the raw image
    CoM it corrects (median or P95, within the electrode ring): the map then should not be used
    for position."""
    cal, raw = com.get("xy_r15", {}), com.get("raw_xy_r15", {})
    out = []
    for stat in ("median", "p95"):
        a, b = cal.get(stat, float("nan")), raw.get(stat, float("nan"))
        if np.isfinite(a) and np.isfinite(b) and a > b:
            out.append(f"the CoM map makes the in-plane position worse than the uncalibrated image CoM on held-out presses "
                       f"({stat} {a:.3g} mm against {b:.3g} mm within r <= 15 mm): use the raw CoM, or the direct regression, for position")
    return out


@dataclass
class Calibration:
    """A built calibration: the ``map``, the ``evaluation`` (JSON-ready, also stored in the
    map) and the held-out per-sample ``tables`` (name → dict of (n,) arrays) the report draws."""

    map: CalibrationMap
    evaluation: dict[str, Any]
    tables: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)


SIZE_BINS = (8e-3, 12e-3, 16e-3, 20e-3, 25e-3, 30e-3 + 1e-9)  # m, true diameter
DEPTH_BINS = (0.0, 1e-3, 2e-3, 3e-3 + 1e-9)  # m, true depth
RADIUS_BINS = (0.0, 3e-3, 6e-3, 9e-3, 12e-3, 15e-3, np.inf)  # m, the true position's distance from the axis


def _position_by_radius(xy_true: np.ndarray, xy_pred: np.ndarray) -> list[dict[str, Any]]:
    """Held-out in-plane errors per bin of the true position's distance from the axis: n,
    median and P95 (m). Where over the sensor the position is read, and where it was not trained."""
    r = np.hypot(*xy_true.T)
    e = np.linalg.norm(xy_pred - xy_true, axis=1)
    rows = []
    for lo, hi in zip(RADIUS_BINS[:-1], RADIUS_BINS[1:]):
        sel = (r >= lo) & (r < hi) & np.isfinite(e)
        rows.append({"from": float(lo), "to": float(hi) if np.isfinite(hi) else None, "n": int(sel.sum()),
                     **({"median": float(np.median(e[sel])), "p95": float(np.percentile(e[sel], 95))} if sel.any() else {})})
    return rows


def _binned(by: np.ndarray, pred: np.ndarray, edges: Sequence[float], truth: np.ndarray | None = None) -> list[dict[str, Any]]:
    """Held-out predictions per bin of ``by`` (SI): n, the medians of the truth (``by`` itself
    unless ``truth`` is given) and of the prediction, the median |error| and |error| / truth.
    Where one output's error comes from: a prediction that stays put across the bins of its
    own truth is the training mean (the voltages do not tell it), one that follows the truth
    with a wide spread is noise."""
    truth = by if truth is None else truth
    rows = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        sel = (by >= lo) & (by < hi) & np.isfinite(pred)
        e = np.abs(pred[sel] - truth[sel])
        rows.append({"from": float(lo), "to": float(min(hi, edges[-1] - 1e-9)), "n": int(sel.sum()),
                     **({"truth_median": float(np.median(truth[sel])), "predicted_median": float(np.median(pred[sel])),
                         "error_median": float(np.median(e)), "relative_median": float(np.median(e / np.abs(truth[sel])))}
                        if sel.any() else {})})
    return rows


def _ring_symmetries(samples: Samples, n_meas: int) -> list[RingSymmetry]:
    """The electrode ring's symmetries under the store's drive protocol (from its sensor
    fingerprint); none for a synthetic store, a layout other than the paper's ring, or one
    whose frames are not that protocol's."""
    if samples.source.get("synthetic"):
        return []
    fp = samples.fingerprint
    if fp.get("electrodes.discs") or fp.get("drive.stim") or fp.get("drive.measure", "reference") != "reference":
        return []  # a layout given as data, or other measurements: the ring's symmetries are not known to hold
    try:
        protocol = skip_protocol(int(fp["electrodes.count"]), int(fp["drive.skip"]), float(fp["drive.current"]))
    except (KeyError, TypeError, ValueError):
        return []
    return ring_symmetries(protocol, float(fp["electrodes.first_angle_deg"])) if protocol.n_meas == n_meas else []


def _goal_band(test: Samples, s: Settings) -> tuple[np.ndarray, str]:
    band = np.abs(test.snr_db - s.goal_snr_db) <= s.snr_band_db
    if band.sum() >= 20:
        return band, f"held-out samples with SNR {s.goal_snr_db:g} ± {s.snr_band_db:g} dB ({int(band.sum())})"
    return np.ones(len(test), bool), (f"all held-out samples ({len(test)}): fewer than 20 within "
                                      f"{s.goal_snr_db:g} ± {s.snr_band_db:g} dB")


def _size_curves(train: Samples, levels: dict[str, np.ndarray]) -> dict[str, LevelCurves]:
    coord = {"depth": train.depth, "force": train.force_mag}
    return {f"{a}/{m}": fit_level_curves(a, m, levels[a], train.group, coord[a], train.metric(m), train.size)
            for a in ALONG for m in METRICS[a]}


def _size_at_levels(curves: dict[str, LevelCurves], test: Samples) -> tuple[list[dict[str, Any]], dict[str, np.ndarray]]:
    """Held-out presses read at each level and inverted there: one row per (route, level)."""
    coord = {"depth": test.depth, "force": test.force_mag}
    rows, tab = [], {k: [] for k in ("along", "metric", "level", "group", "size", "value", "predicted")}
    ids, sizes = np.unique(test.group, return_index=True)
    size_of = dict(zip(ids.tolist(), test.size[sizes].tolist()))
    for key, lc in curves.items():
        for k, (lv, curve) in enumerate(zip(lc.levels, lc.curves)):
            g, v = value_at(test.group, coord[lc.along], test.metric(lc.metric), float(lv))
            s = np.array([size_of[i] for i in g.tolist()])
            p = lc.inverse_at_level(k, v) if curve is not None else np.full(len(v), np.nan)
            rows.append({"route": key, "along": lc.along, "metric": lc.metric, "level": float(lv),
                         **{f"{k}_mm": x for k, x in err_stats(p - s).items() if k != "n"}, "n": int(np.isfinite(p - s).sum())})
            for k, x in (("group", g), ("size", s), ("value", v), ("predicted", p)):
                tab[k].append(x)
            tab["along"].append(np.full(len(g), lc.along))
            tab["metric"].append(np.full(len(g), lc.metric))
            tab["level"].append(np.full(len(g), float(lv)))
    return rows, {k: np.concatenate(v) if v else np.zeros(0) for k, v in tab.items()}


RECALIBRATION_COPIES = 2  # fresh noise draws of each held-out training sample the emulator's σ is recalibrated on


def _model_based(train: Samples, test: Samples, regressor, start: np.ndarray, inside: np.ndarray, band: np.ndarray,
                 seed: int, goal_snr_db: float) -> tuple[Emulator, dict[str, Any], dict[str, dict[str, Any]]]:
    """The emulator trained on the training presses' noise-free features (its noise from draws at
    the training samples' SNRs; its σ recalibrated on the training presses it held out, at
    ``goal_snr_db``, from ``regressor``'s estimates), and its held-out fits at each frame's SNR from the regression's
    estimates ``start``: per frame, and each press's frames at least PRESS_MIN_DEPTH deep
    jointly; with their errors and how often their σ covers them in the goal band. (the
    emulator, the evaluation, the goals' rows by route)."""
    rng = np.random.default_rng([seed, 11])
    clean = train.clean_features
    noise = noisy_features(train.voltages_clean, train.reference_clean, train.snr_db, train.reference_frames, 1, rng) - clean
    emu = fit_emulator(clean, train.press, train.group, noise, train.snr_db, train.reference_frames, seed=seed)
    # its σ recalibrated on the training presses it held out and measured nothing on, their frames
    # drawn afresh at the instrument's SNR (the factor grows with the SNR: there the emulator's own
    # error dominates), each fit from the regression's estimate
    out = held_out_presses(train.group, seed=seed)[1]
    copies = RECALIBRATION_COPIES
    own = noisy_features(train.voltages_clean[out], train.reference_clean[out], (goal_snr_db, goal_snr_db),
                         train.reference_frames, copies, rng)
    emu = recalibrated(emu, own, regressor(own)[:, :4], np.tile(train.press[out], (copies, 1)),
                       copy_groups(train.group[out], copies), goal_snr_db, PRESS_MIN_DEPTH)
    Z, T = emu.whiten(test.clean_features), test.press
    r2 = 1.0 - float(((Z - emu(T)) ** 2).sum() / ((Z - Z.mean(axis=0)) ** 2).sum())
    features = voltage_features(test.voltages, test.dv)
    frame = fit_frames(emu, features, start, test.snr_db)
    press = fit_presses(emu, features, start, test.group, PRESS_MIN_DEPTH, test.snr_db)
    ev, goal = {"emulator_r2": r2, "press_min_depth_m": PRESS_MIN_DEPTH}, {}
    in_range = (test.size >= SIZE_RANGE[0] - 1e-12) & (test.size <= SIZE_RANGE[1] + 1e-12)
    for name, (P, cov) in (("per frame", frame), ("press", press)):
        e = P - T
        exy = np.hypot(e[:, 0], e[:, 1])
        ev[name] = {"xy_r15": err_stats(exy[inside]), "depth": err_stats(e[:, 2]), "size": err_stats(e[:, 3][in_range]),
                    "coverage": coverage(P[band], cov[band], T[band])}
        goal[f"emulator ({name})"] = {"com_xy": err_stats(exy[inside & band]), "depth": err_stats(e[band, 2]),
                                      "size": err_stats(e[in_range & band, 3])}
    return emu, ev, goal


def calibrate(samples: Samples, settings: Settings = Settings(), progress=print) -> Calibration:
    """Fit every part of the calibration on the training presses of ``samples`` and evaluate it
    on the held-out ones. ``progress(str)`` is told of each stage."""
    s = settings
    train_m, test_m = split_groups(samples.group, s.test_fraction, s.seed)
    train, test = samples.subset(train_m), samples.subset(test_m)
    overlap = np.intersect1d(train.group, test.group)
    assert overlap.size == 0  # split_groups guarantees it; the report states it
    ev: dict[str, Any] = {"split": {
        "seed": s.seed, "test_fraction": s.test_fraction, "train_presses": int(len(np.unique(train.group))),
        "test_presses": int(len(np.unique(test.group))), "train_samples": len(train), "test_samples": len(test),
        "overlapping_presses": int(overlap.size)}}
    tables: dict[str, dict[str, np.ndarray]] = {}
    band, band_text = _goal_band(test, s)
    ev["goal_band"] = band_text

    # size curves
    progress(f"size curves ({len(train)} training samples of {ev['split']['train_presses']} presses)")
    levels = {"depth": np.asarray(s.depth_levels, float) if s.depth_levels else default_levels("depth", train.group, train.depth),
              "force": np.asarray(s.force_levels, float) if s.force_levels else default_levels("force", train.group, train.force_mag)}
    curves = _size_curves(train, levels)
    rows, tables["size_at_levels"] = _size_at_levels(curves, test)
    ev["size_levels"] = {"depth_m": levels["depth"].tolist(), "force_n": levels["force"].tolist()}
    ev["size_at_levels"] = rows

    # CoM map
    progress("CoM map (thin-plate spline, smoothing by grouped CV)")
    com_map, cv = fit_com_map(train.com, train.position, train.group, train.snr_db, seed=s.seed,
                              max_points=s.max_com_points)
    pred = com_map(test.com)
    err = pred - test.position
    exy = np.hypot(err[:, 0], err[:, 1])
    r = np.hypot(test.position[:, 0], test.position[:, 1])
    inside = r <= SENSING_RADIUS
    ev["com"] = {
        "smoothing": min(cv, key=cv.get), "cv_mean_error_mm": {f"{k:g}": v for k, v in cv.items()},
        "fitted_points": int(len(com_map.points)), "test_without_com": int((~np.isfinite(test.com).all(axis=1)).sum()),
        "xy_all": err_stats(exy), "xy_r15": err_stats(exy[inside]), "xy_r15_goal_band": err_stats(exy[inside & band]),
        "depth_all": err_stats(err[:, 2]), "depth_goal_band": err_stats(err[:, 2][band]),
        "raw_xy_r15": err_stats(np.hypot(*(test.com[:, :2] - test.position[:, :2]).T)[inside]),
        "position": ("the contact's centre of pressure (the FEM's, in the dataset)" if test.contact_known
                     else "the target's centre (the dataset has no contact centre: schema version 1)"),
    }
    # every sample's place, depth, size and signal: what the dataset covers (the report's figure)
    tables["samples"] = {"x": samples.position[:, 0], "y": samples.position[:, 1], "depth": samples.depth,
                         "diameter": samples.size, "rms_dv": samples.rms_dv, "held_out": test_m}
    tables["com"] = {"group": test.group, "x": test.position[:, 0], "y": test.position[:, 1], "depth": test.depth,
                     "target_x": test.xy[:, 0], "target_y": test.xy[:, 1],
                     "snr_db": test.snr_db, "com_x": test.com[:, 0], "com_y": test.com[:, 1], "com_z": test.com[:, 2],
                     "cal_x": pred[:, 0], "cal_y": pred[:, 1], "cal_depth": pred[:, 2], "error_xy": exy,
                     "error_depth": err[:, 2]}

    # per-frame size routes, conditioned on the calibrated depth (image route) or the force
    metrics = {m: test.metric(m) for m in METRICS["depth"]}
    in_range = (test.size >= SIZE_RANGE[0] - 1e-12) & (test.size <= SIZE_RANGE[1] + 1e-12)
    frame_rows = {}
    for key, lc in curves.items():
        p = lc.predict(metrics[lc.metric], pred[:, 2] if lc.along == "depth" else test.force_mag)
        frame_rows[key] = {"all": err_stats(p - test.size), "range_goal_band": err_stats((p - test.size)[in_range & band]),
                           "covered": float(np.isfinite(p).mean())}
    usable = {k: v for k, v in frame_rows.items() if v["covered"] >= 0.2 and np.isfinite(v["all"]["median"])}
    route = min(usable or frame_rows, key=lambda k: (usable or frame_rows)[k]["all"]["median"])
    ev["size_per_frame"] = frame_rows
    ev["size_route"] = route
    size_pred = curves[route].predict(metrics[curves[route].metric],
                                      pred[:, 2] if curves[route].along == "depth" else test.force_mag)

    # direct regression (and the ridge baseline beside the chosen kind)
    progress(f"direct regression ({s.regressor}; ridge baseline)")
    Xtr, Xte = voltage_features(train.voltages, train.dv), voltage_features(test.voltages, test.dv)
    Ttr = regression_targets(train.position, train.size, train.force_mag)
    Tte = regression_targets(test.position, test.size, test.force_mag)
    Gtr = train.group
    copies = s.noise_copies if train.has_clean else 0
    snr_range = (float(train.snr_db.min()), float(train.snr_db.max()))
    if copies:
        rng = np.random.default_rng([s.seed, 7])
        Xtr = np.vstack([Xtr, noisy_features(train.voltages_clean, train.reference_clean, snr_range,
                                             train.reference_frames, copies, rng)])
        Ttr, Gtr = np.tile(Ttr, (copies + 1, 1)), np.tile(Gtr, copies + 1)
    symmetries = _ring_symmetries(train, Xtr.shape[1]) if s.symmetry and copies else []
    if symmetries:
        fresh = slice(len(train), None)  # the noise copies; the stored samples stay where they were pressed
        Xtr[fresh], Ttr[fresh] = moved_by_symmetry(Xtr[fresh], Ttr[fresh], symmetries, rng)
    regs = {k: fit_regressor(Xtr, Ttr, Gtr, kind=k, seed=s.seed) for k in dict.fromkeys((s.regressor, "ridge"))}
    direct = {k: reg(Xte) for k, reg in regs.items()}
    image = np.column_stack([pred, size_pred, np.full(len(test), np.nan)])
    comparison = {}
    for i, o in enumerate(OUTPUTS):
        scale = 1e3  # m → mm; N → mN
        sel = inside if o in ("x", "y") else (in_range if o == "diameter" else np.ones(len(test), bool))
        comparison[o] = {"image": err_stats((image[:, i] - Tte[:, i])[sel], scale),
                         **{k: err_stats((d[:, i] - Tte[:, i])[sel], scale) for k, d in direct.items()}}
        comparison[o]["image_goal_band"] = err_stats((image[:, i] - Tte[:, i])[sel & band], scale)
        comparison[o][f"{s.regressor}_goal_band"] = err_stats((direct[s.regressor][:, i] - Tte[:, i])[sel & band], scale)
    d = direct[s.regressor] - Tte
    direct_goal = {"com_xy": err_stats(np.hypot(d[:, 0], d[:, 1])[inside & band]), "depth": err_stats(d[band, 2]),
                   "size": err_stats(d[in_range & band, 3])}
    ev["regression"] = {"kind": s.regressor, "comparison": comparison,
                        "by_size": _binned(Tte[:, 3], direct[s.regressor][:, 3], SIZE_BINS),
                        "position_by_radius": _position_by_radius(Tte[:, :2], direct[s.regressor][:, :2]),
                        "force_by_depth": _binned(test.depth, direct[s.regressor][:, 4], DEPTH_BINS, truth=Tte[:, 4]),
                        "training": {"samples": len(train), "noise_copies": copies, "rows": int(len(Xtr)),
                                     "symmetries": len(symmetries),
                                     "snr_db": list(snr_range) if copies else None},
                        "note": "x, y over r <= 15 mm; diameter over 8-30 mm; errors in mm (force in mN)"}
    tables["regression"] = {"group": test.group, **{f"true_{o}": Tte[:, i] for i, o in enumerate(OUTPUTS)},
                            **{f"image_{o}": image[:, i] for i, o in enumerate(OUTPUTS)},
                            **{f"{k}_{o}": d[:, i] for k, d in direct.items() for i, o in enumerate(OUTPUTS)}}

    # model-based estimation: an emulator of the coupled model, fitted per frame and per press
    emulator, model_goal = None, {}
    if s.emulator and train.has_clean and len(train) >= 50:
        progress("emulator of the coupled model (model-based estimation)")
        emulator, ev["model_based"], model_goal = _model_based(train, test, regs[s.regressor], direct[s.regressor][:, :4], inside,
                                                               band, s.seed, s.goal_snr_db)

    # stiffness
    progress("stiffness")
    st_levels = stiffness_levels(levels["depth"])
    stiff = fit_stiffness(train.group, train.depth, train.force_mag, train.sum_sigma, train.diameter, train.modulus,
                          st_levels)
    ev["stiffness"] = {"estimable": stiff.estimable, "reason": stiff.reason, "depth_levels_m": st_levels.tolist()}
    # a diagnostic of the data, not an evaluation: all presses, labels included
    # (at a shallow level: the deeper the press, the more even a soft target's contact stiffens)
    shallow = float(levels["depth"][min(1, len(levels["depth"]) - 1)])
    ev["stiffness"]["force_sensitivity"] = {
        "depth_m": shallow,
        "by_decade": force_sensitivity(samples.group, samples.depth, samples.force_mag, samples.radius, samples.modulus,
                                       shallow)}
    if stiff.estimable:
        soft = np.isfinite(test.modulus)
        t = test.subset(soft)
        ids, E = stiff.predict(t.group, t.depth, t.force_mag, t.sum_sigma, t.diameter)
        Et = press_moduli(t.group, t.modulus, ids)
        ev["stiffness"]["relative"] = err_stats(E / Et - 1, 1.0)
        # how far the modulus can be told depends on how the target compares with the membrane
        # (a target much stiffer than it presses like a rigid one): the error per decade of E
        ev["stiffness"]["by_decade"] = [{"from_pa": lo, "to_pa": 10 * lo, **err_stats((E / Et - 1)[m], 1.0)}
                                        for lo, m in decades(Et)]
        tables["stiffness"] = {"group": ids, "true_modulus": Et, "predicted_modulus": E}

    # goals, by each route that estimates the quantity: the image route (CoM map, size curve),
    # the direct regression, and the stiffness model
    routes = {"image": {"com_xy": ev["com"]["xy_r15_goal_band"], "depth": ev["com"]["depth_goal_band"],
                        "size": frame_rows[route]["range_goal_band"]},
              f"direct ({s.regressor})": direct_goal, **model_goal,
              "stiffness model": {"modulus": ev["stiffness"].get("relative")}}
    goals = []
    for name, q, stat, limit in GOALS:
        for via, value in routes.items():
            if q not in value:
                continue
            n = value[q]["n"] if value[q] is not None else 0
            v = value[q][stat] if n else float("nan")
            note = "" if np.isfinite(v) else ("not estimable: " + stiff.reason if q == "modulus" and not stiff.estimable
                                              else "no held-out samples")
            need = MIN_JUDGED.get(q, 20)
            if np.isfinite(v) and n < need:
                note = f"only {n} held-out {'presses' if q == 'modulus' else 'samples'} (< {need}): too few to judge"
            met = bool(np.isfinite(v) and v <= limit and n >= need)
            # too few held-out samples, or no value: neither met nor not met
            verdict = "met" if met else ("undetermined" if not np.isfinite(v) or n < need else "not met")
            goals.append({"goal": name, "route": via, "statistic": stat, "limit": limit, "value": v, "n": int(n),
                          "unit": "" if q == "modulus" else "mm", "met": met, "verdict": verdict, "note": note})
    ev["goals"] = goals
    ev["warnings"] = worse_than_uncalibrated(ev["com"])
    region = trained_region(train.position[:, :2], train.depth, train.size)
    # held-out estimates outside what was trained are flagged, as apply() flags frames
    flags = outside_region(region, direct[s.regressor][:, :2], direct[s.regressor][:, 2], direct[s.regressor][:, 3])
    ev["region"] = {**region, "test_estimates_outside": int(np.count_nonzero(flags)), "test_samples": len(flags)}

    cmap = CalibrationMap(
        fingerprint=samples.fingerprint, com=com_map, size=curves, size_route=route, regressor=regs[s.regressor],
        stiffness=stiff, source=samples.source,
        settings={"test_fraction": s.test_fraction, "seed": s.seed, "regressor": s.regressor,
                  "goal_snr_db": s.goal_snr_db, "snr_band_db": s.snr_band_db, "max_com_points": s.max_com_points,
                  "noise_copies": s.noise_copies, "symmetry": s.symmetry},
        evaluation=ev, versions=package_versions(VERSION_PACKAGES), created=utc_now("seconds"),
        region=region, emulator=emulator,
    )
    return Calibration(cmap, ev, tables)
