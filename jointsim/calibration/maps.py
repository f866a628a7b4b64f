"""The calibration map file: a versioned HDF5 file of plain arrays that loads in a new process
without pickle, and applying a loaded map to measured frames.

Owns the file layout (below), the refusal of a file of another format or version and of a
scene the map was not built for (:func:`jointsim.calibration.fingerprint.check_fingerprint`),
and :meth:`CalibrationMap.apply`: per frame, the calibrated position and depth (CoM map), size
(the best inverse size curve), the direct regression's five outputs, and per press the
modulus where the map can estimate it.

Layout (``FORMAT`` = "jointsim-calibration", ``FORMAT_VERSION`` = 2; version 1 maps, whose
CoM spline fitted the position itself with one smoothing, still load)::

    /            attrs: format, format_version, created, size_route, and JSON strings
                 fingerprint (the sensor), source (dataset path, digest, size), settings,
                 evaluation (held-out errors), versions (packages that built it), region
                 (what the training samples span; absent in maps written before it)
    /com         points (p, 3), values (p, 3) in mm (x, y: corrections to the CoM), smoothing
                 (p,); attrs kernel, degree
    /size/<along>__<metric>   levels (L,); x (diameter m), y (metric) (L, K) breakpoints of each
                 level's monotone curve, NaN-padded; count (L,); attrs along, metric, increasing
    /regression  x_mean, components, x_scale, y_mean, y_scale, W<i>, b<i>; attrs kind, layers
    /stiffness   levels, x_mean, x_scale, powers, coef; attrs estimable, reason, intercept
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from ..io.export import atomic_path
from ..io.provenance import package_versions, utc_now
from ..scene import Scene
from .com import ComMap
from .curves import LevelCurves, Monotone
from .data import voltage_features
from .emulator import PARAMETERS, Emulator, fit_frames, fit_presses, sigmas
from .fingerprint import check_fingerprint, sensor_fingerprint
from .regression import OUTPUTS, DirectRegressor
from .stiffness import StiffnessModel

__all__ = ["FORMAT", "FORMAT_VERSION", "CalibrationMap", "save_map", "load_map", "APPLIED", "trained_region",
           "outside_region"]

FORMAT = "jointsim-calibration"
FORMAT_VERSION = 2
READABLE_VERSIONS = (1, 2)
VERSION_PACKAGES = ("jointsim", "numpy", "scipy", "scikit-learn", "h5py")
# the emulator's fields a map may lack (written before them): the fits then go without them
EMULATOR_LATER = ("residual", "shared", "noise_0db", "prior_mean", "prior_sd", "sd_scale")
# what apply() returns per frame (SI): the image route, the direct regression, the modulus, and
# the emulator's fits (NaN from a map without one): per frame, and a press's frames jointly
APPLIED = ("cal_x", "cal_y", "cal_depth", "cal_diameter", *(f"direct_{o}" for o in OUTPUTS), "outside", "modulus",
           *(f"{fit}_{p}" for fit in ("model", "press") for p in PARAMETERS),
           *(f"{fit}_sd_{p}" for fit in ("model", "press") for p in PARAMETERS))
PRESS_MIN_DEPTH = 0.3e-3  # m: a press's frames fitted jointly are those the regression puts this deep or more


@dataclass(frozen=True)
class CalibrationMap:
    """A fitted calibration: the sensor ``fingerprint`` it holds for, the ``com`` map, the
    inverse ``size`` curves keyed ``"<along>/<metric>"`` and the per-frame ``size_route`` among
    them (best held-out), the ``regressor`` (voltages → x, y, depth, diameter, force), the
    ``stiffness`` model, and JSON ``source``, ``settings``, ``evaluation``, ``versions``, and
    the ``region`` its training samples span (:func:`trained_region`; {} for a map written
    before maps recorded it)."""

    fingerprint: dict[str, Any]
    com: ComMap
    size: dict[str, LevelCurves]
    size_route: str
    regressor: DirectRegressor
    stiffness: StiffnessModel
    source: dict[str, Any] = field(default_factory=dict)
    settings: dict[str, Any] = field(default_factory=dict)
    evaluation: dict[str, Any] = field(default_factory=dict)
    versions: dict[str, str] = field(default_factory=dict)
    created: str = ""
    region: dict[str, Any] = field(default_factory=dict)
    emulator: Emulator | None = None  # of the coupled model (model-based estimation); None in maps before it

    def check_scene(self, scene: Scene, what: str = "this calibration map") -> None:
        """Refuse (SceneMismatchError naming the values) a scene of another sensor."""
        check_fingerprint(self.fingerprint, sensor_fingerprint(scene), what)

    def size_of(self, metrics: Mapping[str, np.ndarray], depth: np.ndarray, force_mag: np.ndarray,
                route: str | None = None) -> np.ndarray:
        """Diameter (n,) m by ``route`` (default :attr:`size_route`) from per-frame ``metrics``
        (name → (n,)), the frame's (calibrated) ``depth`` and ``force_mag`` (n,)."""
        lc = self.size[route or self.size_route]
        return lc.predict(metrics[lc.metric], depth if lc.along == "depth" else force_mag)

    def apply(self, frames: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        """Calibrated values (:data:`APPLIED`, each (n,), SI) for frames with ``com`` (n, 3),
        ``voltages`` and ``dv`` (n, 256), ``force`` (n, 3), ``sum_sigma``, ``diameter`` (n,);
        with ``group`` (press ids) and ``depth`` (the stage's indentation, m) also the modulus
        of each press (the same on all its frames; the press-in frames are used, up to its
        deepest), NaN where it cannot be estimated; with ``snr_db`` (one, or (n,)) the emulator's
        fits weigh the noise at that SNR, else at the training SNRs'."""
        com = np.asarray(frames["com"], float)
        n = len(com)
        pos = self.com(com)
        fmag = np.linalg.norm(np.asarray(frames["force"], float), axis=1)
        dv = np.asarray(frames["dv"], float)
        metrics = {"sum_sigma": np.asarray(frames["sum_sigma"], float), "diameter": np.asarray(frames["diameter"], float),
                   "rms_dv": np.sqrt(np.mean(dv**2, axis=1)), "force": fmag}
        out = {"cal_x": pos[:, 0], "cal_y": pos[:, 1], "cal_depth": pos[:, 2],
               "cal_diameter": self.size_of(metrics, pos[:, 2], fmag)}
        features = voltage_features(frames["voltages"], dv)
        direct = self.regressor(features)
        out.update({f"direct_{o}": direct[:, i] for i, o in enumerate(OUTPUTS)})
        out["outside"] = outside_region(self.region, direct[:, :2], direct[:, 2], direct[:, 3])
        out["modulus"] = np.full(n, np.nan)
        if self.stiffness.estimable and "group" in frames and "depth" in frames:
            g, d = np.asarray(frames["group"]), np.asarray(frames["depth"], float)
            press_in = _press_in(g, d)
            ids, E = self.stiffness.predict(g[press_in], d[press_in], fmag[press_in], metrics["sum_sigma"][press_in],
                                            metrics["diameter"][press_in])
            lookup = dict(zip(ids.tolist(), E.tolist()))
            out["modulus"] = np.array([lookup.get(i, np.nan) for i in g.tolist()])
        out.update(self._model_based(features, direct[:, :4], frames.get("group"), frames.get("snr_db")))
        return out

    def _model_based(self, features: np.ndarray, start: np.ndarray, group: np.ndarray | None,
                     snr_db: float | np.ndarray | None) -> dict[str, np.ndarray]:
        """The emulator's fits (:mod:`.emulator`) from the regression's estimates, and their σ:
        each frame's, and with ``group`` each press's frames at least PRESS_MIN_DEPTH deep
        jointly (x, y and the diameter shared), at the frames' ``snr_db`` (None: the training
        SNRs'); NaN without an emulator."""
        n = len(features)
        fits = {"model": (np.full((n, 4), np.nan), np.full((n, 4, 4), np.nan))}
        fits["press"] = fits["model"]
        if self.emulator is not None:
            fits["model"] = fit_frames(self.emulator, features, start, snr_db)
            if group is not None:
                fits["press"] = fit_presses(self.emulator, features, start, np.asarray(group), PRESS_MIN_DEPTH, snr_db)
        out = {}
        for name, (est, cov) in fits.items():
            sd = sigmas(cov)
            out.update({f"{name}_{p}": est[:, j] for j, p in enumerate(PARAMETERS)})
            out.update({f"{name}_sd_{p}": sd[:, j] for j, p in enumerate(PARAMETERS)})
        return out


def trained_region(xy: np.ndarray, depth: np.ndarray, diameter: np.ndarray) -> dict[str, Any]:
    """The region training samples span (JSON-ready, SI): the largest distance from the axis of
    their positions ``xy`` (n, 2) m (where the target presses: the contact's centre of
    pressure), and the ranges of ``depth`` and target ``diameter`` (n,) m."""
    return {"r_max_m": float(np.hypot(*np.asarray(xy, float).T).max()),
            "depth_m": [float(np.min(depth)), float(np.max(depth))],
            "diameter_m": [float(np.min(diameter)), float(np.max(diameter))]}


def outside_region(region: Mapping[str, Any], xy: np.ndarray, depth: np.ndarray, diameter: np.ndarray) -> np.ndarray:
    """Per estimate (n,) str: what lies outside the ``region`` a map was trained on, of
    "position" (``xy`` (n, 2) farther from the axis), "depth", "diameter" (n,), joined by "+";
    "" where all lie inside. A map that recorded no region flags nothing."""
    n = len(depth)
    out = np.full(n, "", dtype=object)
    if not region:
        return out.astype(str)
    lo_d, hi_d = region["depth_m"]
    lo_s, hi_s = region["diameter_m"]
    checks = {"position": np.hypot(*np.asarray(xy, float).T) > region["r_max_m"],
              "depth": (depth < lo_d) | (depth > hi_d), "diameter": (diameter < lo_s) | (diameter > hi_s)}
    for name, bad in checks.items():
        out[bad] = [f"{o}+{name}" if o else name for o in out[bad]]
    return out.astype(str)


def _press_in(group: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """(n,) bool: the frames of each press up to its deepest (the loading branch), in order."""
    keep = np.zeros(len(group), bool)
    for i in np.unique(group):
        idx = np.flatnonzero(group == i)
        keep[idx[: int(np.argmax(depth[idx])) + 1]] = True
    return keep


# -- writing ----------------------------------------------------------------------------------


def _json(d: Any) -> str:
    return json.dumps(d, sort_keys=True, default=float)


def save_map(cmap: CalibrationMap, path: str | Path) -> Path:
    """Write ``cmap`` to ``path`` (HDF5, written under a temporary name and renamed)."""
    import h5py

    path = Path(path)
    with atomic_path(path) as tmp:
        with h5py.File(tmp, "w") as h5:
            h5.attrs.update(
                format=FORMAT, format_version=FORMAT_VERSION, created=cmap.created or utc_now("seconds"), size_route=cmap.size_route,
                fingerprint=_json(cmap.fingerprint), source=_json(cmap.source), settings=_json(cmap.settings),
                evaluation=_json(cmap.evaluation), versions=_json(cmap.versions or package_versions(VERSION_PACKAGES)),
                region=_json(cmap.region),
            )
            c = h5.create_group("com")
            c.create_dataset("points", data=cmap.com.points)
            c.create_dataset("values", data=cmap.com.values)
            c.create_dataset("smoothing", data=np.broadcast_to(cmap.com.smoothing, len(cmap.com.points)))
            c.attrs.update(kernel=cmap.com.kernel, degree=cmap.com.degree)
            s = h5.create_group("size")
            for key, lc in cmap.size.items():
                g = s.create_group(key.replace("/", "__"))
                k = max([len(m.x) for m in lc.curves if m is not None] or [1])
                x = np.full((len(lc.levels), k), np.nan)
                y = np.full_like(x, np.nan)
                count = np.zeros(len(lc.levels), np.int64)
                for i, m in enumerate(lc.curves):
                    if m is not None:
                        count[i] = len(m.x)
                        x[i, : len(m.x)], y[i, : len(m.y)] = m.x, m.y
                g.create_dataset("levels", data=lc.levels)
                g.create_dataset("x", data=x)
                g.create_dataset("y", data=y)
                g.create_dataset("count", data=count)
                g.attrs.update(along=lc.along, metric=lc.metric, increasing=lc.increasing, grid_points=lc.grid_points)
            r, reg = h5.create_group("regression"), cmap.regressor
            for name in ("x_mean", "components", "x_scale", "y_mean", "y_scale"):
                r.create_dataset(name, data=getattr(reg, name))
            for i, (W, b) in enumerate(zip(reg.weights, reg.biases)):
                r.create_dataset(f"W{i}", data=W)
                r.create_dataset(f"b{i}", data=b)
            r.attrs.update(kind=reg.kind, layers=len(reg.weights), outputs=_json(list(OUTPUTS)))
            t, st = h5.create_group("stiffness"), cmap.stiffness
            for name in ("levels", "x_mean", "x_scale", "powers", "coef"):
                t.create_dataset(name, data=getattr(st, name))
            t.attrs.update(estimable=st.estimable, reason=st.reason, intercept=st.intercept)
            if (emu := cmap.emulator) is not None:
                e = h5.create_group("emulator")
                for name in ("t_mean", "t_scale", "x_mean", "components", "x_scale", "covariance", *EMULATOR_LATER):
                    if getattr(emu, name) is not None:
                        e.create_dataset(name, data=getattr(emu, name))
                for i, (W, b) in enumerate(zip(emu.weights, emu.biases)):
                    e.create_dataset(f"W{i}", data=W)
                    e.create_dataset(f"b{i}", data=b)
                e.attrs.update(layers=len(emu.weights), parameters=_json(list(PARAMETERS)), reference_share=emu.reference_share)
    return path


# -- reading ----------------------------------------------------------------------------------


def load_map(path: str | Path) -> CalibrationMap:
    """Read a map written by :func:`save_map`; a ValueError for a file that is not one, or of
    another format version."""
    import h5py

    path = Path(path)
    if not path.is_file():
        raise ValueError(f"calibration map {path}: no such file")
    try:
        h5 = h5py.File(path, "r")
    except OSError as e:
        raise ValueError(f"calibration map {path}: not an HDF5 file ({e})") from None
    with h5:
        a = h5.attrs
        if a.get("format") != FORMAT:
            raise ValueError(f"calibration map {path}: not a jointsim calibration map (format {a.get('format')!r})")
        version = int(a["format_version"])
        if version not in READABLE_VERSIONS:
            raise ValueError(f"calibration map {path}: format version {version}; this jointsim reads "
                             f"versions {list(READABLE_VERSIONS)} (rebuild it with jointsim calibrate)")
        c = h5["com"]
        smoothing = float(c.attrs["smoothing"]) if version == 1 else c["smoothing"][()]
        com = ComMap(c["points"][()], c["values"][()], smoothing, str(c.attrs["kernel"]), int(c.attrs["degree"]),
                     residual=version >= 2)
        size = {}
        for key, g in h5["size"].items():
            x, y, count = g["x"][()], g["y"][()], g["count"][()]
            curves = tuple(Monotone(x[i, :k].copy(), y[i, :k].copy()) if k else None for i, k in enumerate(count))
            size[key.replace("__", "/")] = LevelCurves(str(g.attrs["along"]), str(g.attrs["metric"]), g["levels"][()], curves,
                                                       bool(g.attrs["increasing"]), int(g.attrs["grid_points"]))
        r = h5["regression"]
        n = int(r.attrs["layers"])
        reg = DirectRegressor(str(r.attrs["kind"]), r["x_mean"][()], r["components"][()], r["x_scale"][()],
                              tuple(r[f"W{i}"][()] for i in range(n)), tuple(r[f"b{i}"][()] for i in range(n)),
                              r["y_mean"][()], r["y_scale"][()])
        t = h5["stiffness"]
        st = StiffnessModel(bool(t.attrs["estimable"]), str(t.attrs["reason"]), t["levels"][()], t["x_mean"][()],
                            t["x_scale"][()], t["powers"][()], t["coef"][()], float(t.attrs["intercept"]))
        emu = None
        if "emulator" in h5:
            e = h5["emulator"]
            k = int(e.attrs["layers"])
            emu = Emulator(e["t_mean"][()], e["t_scale"][()], tuple(e[f"W{i}"][()] for i in range(k)),
                           tuple(e[f"b{i}"][()] for i in range(k)), e["x_mean"][()], e["components"][()], e["x_scale"][()],
                           e["covariance"][()], **{n: e[n][()] for n in EMULATOR_LATER if n in e},
                           reference_share=float(e.attrs.get("reference_share", 0.0)))
        return CalibrationMap(
            json.loads(a["fingerprint"]), com, size, str(a["size_route"]), reg, st, json.loads(a["source"]),
            json.loads(a["settings"]), json.loads(a["evaluation"]), json.loads(a["versions"]), str(a["created"]),
            json.loads(a["region"]) if "region" in a else {}, emu,
        )
