"""Explicit press lists: a dataset of given presses (a calibration rig's raster, a grid, a CSV)
instead of drawn ones.

A :class:`PressList` fixes, per press trajectory (group), the target's diameter and stiffness,
where it presses, given either as the contact point (where it first touches the membrane, its
centre solved as for drawn presses) or as the target's centre (what a rig's stage sets), and
optionally its depths. The sensor's randomisation ([dataset] membrane_scale, conductivity,
contact impedance, electrode jitter, SNR) is still drawn per group from the seed; give those
ranges as single values for a nominal sensor.

CSV (``read_presses``), one header line, comma-separated, ``#`` comments::

    contact_x_mm, contact_y_mm, diameter_mm[, modulus_kpa][, depth_mm]     or
    x_mm, y_mm, diameter_mm[, modulus_kpa][, depth_mm]                    (the target's centre)

``modulus_kpa`` empty or ``inf``: a rigid target. ``force_n`` (with ``depth_mm``): the contact
force a rig read at that depth, N; a dataset ignores it, the membrane's modulus is fitted to it
(:mod:`jointsim.calibration.membrane_fit`, ``jointsim frames --known-presses``). Without ``depth_mm`` each row is one press,
sampled at the centres of ``samples_per_press`` equal slices of [dataset] depth_mm (scaled
into what the dome allows at the point, as drawn presses are). With it, each row is one sample
and consecutive rows of the same press (same place, diameter, modulus) are its depths; every
press must then have as many.
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

__all__ = ["PressList", "read_presses", "press_grid"]

PLACES = {"contact": ("contact_x_mm", "contact_y_mm"), "centre": ("x_mm", "y_mm")}
OPTIONAL = ("modulus_kpa", "depth_mm", "force_n")


@dataclass(frozen=True)
class PressList:
    """Presses (SI): ``place`` "contact" (``xy`` are contact points) or "centre" (the targets'
    centres), ``xy`` (n, 2) m, ``radius`` (n,) m, ``modulus`` (n,) Pa (inf: rigid), ``depths``
    (n, K) m increasing, or None (the spec's depth slices); ``forces`` (n, K) N read at those
    depths, or None."""

    place: str
    xy: np.ndarray
    radius: np.ndarray
    modulus: np.ndarray
    depths: np.ndarray | None = None
    forces: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.place not in PLACES:
            raise ValueError(f"press list place = {self.place!r}: must be one of {sorted(PLACES)}")
        n = len(self.radius)
        if n < 1 or self.xy.shape != (n, 2) or self.modulus.shape != (n,):
            raise ValueError(f"a press list needs n >= 1 presses with xy (n, 2), radius and modulus (n,); got xy "
                             f"{self.xy.shape}, radius {self.radius.shape}, modulus {self.modulus.shape}")
        if not (np.isfinite(self.xy).all() and (self.radius > 0).all() and (self.modulus > 0).all()):
            raise ValueError("a press list's places must be finite, its radii and moduli > 0")
        if self.depths is not None:
            if self.depths.ndim != 2 or len(self.depths) != n or not (np.diff(self.depths, axis=1) > 0).all() \
                    or not (self.depths > 0).all():
                raise ValueError("a press list's depths must be (n, K), > 0 and increasing along each press")
        if self.forces is not None and (self.depths is None or self.forces.shape != self.depths.shape
                                        or not (np.isfinite(self.forces) & (self.forces > 0)).all()):
            raise ValueError("a press list's forces must be one per depth, finite and > 0 N")

    def __len__(self) -> int:
        return len(self.radius)

    @property
    def samples_per_press(self) -> int | None:
        """K when the list gives depths (else the scene's)."""
        return None if self.depths is None else int(self.depths.shape[1])

    def to_record(self) -> dict[str, Any]:
        """JSON-ready (mm, kPa), part of a dataset store's identity."""
        return {"place": self.place, "xy_mm": np.round(self.xy * 1e3, 9).tolist(),
                "diameter_mm": np.round(2e3 * self.radius, 9).tolist(),
                "modulus_kpa": [None if math.isinf(e) else round(e / 1e3, 9) for e in self.modulus.tolist()],
                "depths_mm": None if self.depths is None else np.round(self.depths * 1e3, 9).tolist(),
                # (only where given: lists without forces keep the identity they had)
                **({} if self.forces is None else {"forces_n": self.forces.tolist()})}

    def check_within(self, r_max: float, height: float) -> None:
        """Refuse contact points farther than ``r_max`` m from the axis (the membrane's top) and
        depths past ``height`` m (0.9 × the dome's height, as [dataset] depth_mm)."""
        if self.place == "contact":
            r = np.hypot(*self.xy.T)
            if (bad := np.flatnonzero(r > r_max)).size:
                raise ValueError(f"press {bad[0]}: contact point {np.round(self.xy[bad[0]] * 1e3, 3).tolist()} mm is "
                                 f"{r[bad[0]] * 1e3:.4g} mm from the axis; contact points must be within {r_max * 1e3:.4g} mm")
        if self.depths is not None and self.depths.max() > height:
            raise ValueError(f"press depths up to {self.depths.max() * 1e3:.4g} mm: at most {height * 1e3:.4g} mm "
                             "(0.9 x the dome's height)")


def _number(text: str, where: str, name: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise ValueError(f"{where}: {name} = {text!r} is not a number") from None
    if math.isnan(v):
        raise ValueError(f"{where}: {name} is NaN")
    return v


def read_presses(path: str | Path) -> PressList:
    """The press list in the CSV file ``path`` (see the module's docstring); a ValueError naming
    the file, its line and column for anything else."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise ValueError(f"press list {path}: cannot be read ({type(e).__name__})") from None
    lines = [(i + 1, ln) for i, ln in enumerate(text.splitlines()) if ln.strip() and not ln.lstrip().startswith("#")]
    if not lines:
        raise ValueError(f"press list {path}: empty (a header line, then one line per press)")
    rows = list(csv.reader(io.StringIO("\n".join(ln for _, ln in lines))))
    header = [h.strip() for h in rows[0]]
    place = next((p for p, cols in PLACES.items() if set(cols) <= set(header)), None)
    allowed = {c for cols in PLACES.values() for c in cols} | {"diameter_mm", *OPTIONAL}
    if place is None or "diameter_mm" not in header or set(header) - allowed or len(set(header)) < len(header) \
            or all(set(c) <= set(header) for c in PLACES.values()):
        raise ValueError(f"press list {path}: header {header}; must name contact_x_mm, contact_y_mm (or x_mm, y_mm for "
                         f"the targets' centres) and diameter_mm, optionally {', '.join(OPTIONAL)}")
    col = {h: i for i, h in enumerate(header)}
    x, y, d, e, depth, force = [], [], [], [], [], []
    if "force_n" in col and "depth_mm" not in col:
        raise ValueError(f"press list {path}: force_n is the force read at each depth; give depth_mm with it")
    for (lineno, _), row in zip(lines[1:], rows[1:]):
        where = f"press list {path}, line {lineno}"
        if len(row) != len(header):
            raise ValueError(f"{where}: {len(row)} values for {len(header)} columns")
        get = {h: row[i].strip() for h, i in col.items()}
        cx, cy = PLACES[place]
        x.append(_number(get[cx], where, cx))
        y.append(_number(get[cy], where, cy))
        d.append(_number(get["diameter_mm"], where, "diameter_mm"))
        if d[-1] <= 0:
            raise ValueError(f"{where}: diameter_mm = {d[-1]:g}: must be > 0")
        m = get.get("modulus_kpa", "")
        e.append(math.inf if m in ("", "inf") else _number(m, where, "modulus_kpa"))
        if e[-1] <= 0:
            raise ValueError(f"{where}: modulus_kpa = {e[-1]:g}: must be > 0 (empty or inf for a rigid target)")
        if "depth_mm" in col:
            depth.append(_number(get["depth_mm"], where, "depth_mm"))
            if depth[-1] <= 0:
                raise ValueError(f"{where}: depth_mm = {depth[-1]:g}: must be > 0 (past first contact)")
        if "force_n" in col:
            force.append(_number(get["force_n"], where, "force_n"))
            if not (0 < force[-1] < math.inf):
                raise ValueError(f"{where}: force_n = {force[-1]:g}: must be finite and > 0 N (a press past first contact)")
    if not d:
        raise ValueError(f"press list {path}: a header but no presses")
    keys = np.column_stack([x, y, d, e])
    if not depth:
        return PressList(place, keys[:, :2] * 1e-3, keys[:, 2] * 0.5e-3, keys[:, 3] * 1e3)
    # consecutive rows of one press: a new press wherever a row's place, diameter or modulus changes
    start = np.flatnonzero(np.r_[True, (keys[1:] != keys[:-1]).any(axis=1)])
    counts = np.diff(np.r_[start, len(keys)])
    if len(set(counts.tolist())) > 1:
        raise ValueError(f"press list {path}: presses with {sorted(set(counts.tolist()))} depths; every press must have as "
                         "many (a dataset stores the same number of samples per press)")
    dep = np.asarray(depth).reshape(len(start), counts[0])
    order = np.argsort(dep, axis=1, kind="stable")
    dep = np.take_along_axis(dep, order, axis=1)
    if (np.diff(dep, axis=1) <= 0).any():
        raise ValueError(f"press list {path}: a press repeats a depth")
    forces = np.take_along_axis(np.asarray(force).reshape(dep.shape), order, axis=1) if force else None
    k = keys[start]
    return PressList(place, k[:, :2] * 1e-3, k[:, 2] * 0.5e-3, k[:, 3] * 1e3, dep * 1e-3, forces)


def press_grid(pitch: float, r_max: float, diameters: Sequence[float], depths: Sequence[float] | None = None,
               modulus: float = math.inf, place: str = "contact") -> PressList:
    """A square raster of ``pitch`` m over the disc r ≤ ``r_max`` m (the axis a node), each point
    pressed with every diameter (m) in ``diameters``, at ``depths`` m (or the scene's)."""
    if pitch <= 0 or r_max < 0 or not diameters:
        raise ValueError(f"press grid: pitch {pitch!r} must be > 0, r_max {r_max!r} >= 0, diameters not empty")
    n = int(math.floor(r_max / pitch + 1e-9))  # 15 mm // 5 mm is 2.0 in floating point
    g = np.arange(-n, n + 1) * pitch
    X, Y = np.meshgrid(g, g, indexing="ij")
    pts = np.column_stack([X.ravel(), Y.ravel()])
    pts = pts[np.hypot(*pts.T) <= r_max * (1 + 1e-12)]
    xy = np.repeat(pts, len(diameters), axis=0)
    radius = np.tile(np.asarray(diameters, float) / 2, len(pts))
    dep = None if depths is None else np.tile(np.asarray(depths, float), (len(radius), 1))
    return PressList(place, xy, radius, np.full(len(radius), float(modulus)), dep)
