"""Scene files: the sensor's physical setup as typed, validated, SI-unit dataclasses.

A scene is a TOML file whose keys carry their unit (``radius_mm``, ``current_ua``).
``load_scene`` converts everything to SI (m, S/m, A, Ω·m², Hz) and rejects a bad value with a
:class:`SceneError` that names the key and its allowed range, before any solver runs. Files a
scene names are read and checked here too: a protocol's patterns, and a user's chamber surface
(:func:`read_surface`: closed, not self-intersecting, its base on z = 0).
"""

from __future__ import annotations

import hashlib
import json
import math
import re
import numbers
import tomllib
import warnings
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from ._surface import SurfaceError, SurfaceFile, in_polygon, segment_distance, surface_file, top_height

__all__ = [
    "SceneError",
    "Chamber",
    "ElectrodeRing",
    "Saline",
    "Drive",
    "Noise",
    "MeshSpec",
    "preset_mesh",
    "Membrane",
    "Target",
    "ReconstructionSpec",
    "PalpationSpec",
    "DatasetSpec",
    "Scene",
    "load_scene",
    "parameter_table",
    "scene_data",
    "scene_toml",
    "scene_from_dict",
    "MESH_PRESETS",
    "MEMBRANE_RIM_VERTICES",
    "MEMBRANE_LAYERS",
    "MEMBRANE_MAX_LAYERS",
    "MEMBRANE_RIM_RANGE",
    "WEDGE_MIN_RIM_VERTICES",
    "UNRECORDED_ELEMENT",
    "membrane_layers",
    "membrane_rim_vertices",
    "warn_coarse_membrane",
]

MM = 1e-3


class SceneError(ValueError):
    """A scene value outside its allowed range; the message names the key."""


@dataclass(frozen=True)
class Chamber:
    """Saline chamber: a spherical-cap dome over a flat circular base (SI units), or, where
    ``base_radius_y`` is given, an elongated pad: that cap stretched along y to an elliptical
    base of semi-axes ``base_radius`` (x) and ``base_radius_y`` (y), the same height."""

    base_radius: float = 20 * MM
    dome_height: float = 10 * MM
    membrane_thickness: float = 2 * MM
    base_radius_y: float | None = None
    surface_file: str | None = None
    surface_sha256: str | None = None
    surface_unit: float = MM
    outline: tuple[tuple[float, float], ...] = ()

    @property
    def y_scale(self) -> float:
        """The pad's stretch along y (1 for the round dome and a user's surface)."""
        return 1.0 if self.base_radius_y is None else self.base_radius_y / self.base_radius

    @property
    def inradius(self) -> float:
        """The largest disc about the axis inside the base, m."""
        if self.outline:
            return float(segment_distance(np.zeros(2), np.asarray(self.outline)).min())
        return min(self.base_radius, self.base_radius * self.y_scale)

    def inside(self, xy: np.ndarray, inset: float | np.ndarray = 0.0) -> np.ndarray:
        """Whether the points ``xy`` (n, 2) m lie inside the base outline moved ``inset`` m in."""
        xy = np.atleast_2d(np.asarray(xy, float))
        if self.outline:
            poly = np.asarray(self.outline)
            far = np.array([segment_distance(q, poly).min() for q in xy]) >= inset
            return in_polygon(xy, poly) & far
        a, b = self.base_radius - inset, self.base_radius * self.y_scale - inset
        return (xy[:, 0] / a) ** 2 + (xy[:, 1] / b) ** 2 <= 1.0


def read_surface(path: str | Path, unit: float = MM) -> SurfaceFile:
    """A user's chamber surface file, read and checked (:mod:`jointsim._surface`; once per
    version of the file); what is wrong with it as a :class:`SceneError`."""
    try:
        return surface_file(path, unit)
    except SurfaceError as e:
        raise SceneError(str(e)) from None


@dataclass(frozen=True)
class ElectrodeRing:
    """The electrodes on the base (SI units): disc electrodes driven and measured, ``count`` of
    them, and one reference electrode (the paper's central ground), last.

    The paper's layout (``discs`` empty): a ring of ``count`` discs of ``diameter`` at
    ``ring_radius``, electrode 0 at ``first_angle_deg``, anticlockwise, and the central ground
    of ``ground_diameter``. Any other layout is ``discs``: (x, y, radius) of every electrode, the
    reference last, built in a scene by generators ([[electrodes.ring]], [[electrodes.grid]],
    [[electrodes.disc]], and on the membrane [[electrodes.membrane]]); ``reference`` False when
    it is floating (no electrode is a passive reference: the last one is the solver's, and the
    protocol's patterns span every electrode). ``on_membrane`` (one per disc; empty: none): the
    disc lies on the membrane's inner surface where the dome is above (x, y), and moves with it,
    stretching or rigid (``membrane_patch``). ``face_z`` (one per disc; empty: none): where not
    None, the electrode is every face of the chamber's surface on the plane z = face_z
    ([[electrodes.face]]: a user's chamber's end plates).

    ``contact_impedance`` has one value per driven electrode (Ω·m²), ``ground_contact_impedance``
    the reference's; ``contact_impedance_by_freq`` is optional, shape (n_frequencies, count),
    one row per FDM carrier.
    """

    count: int = 16
    ring_radius: float = 15 * MM
    diameter: float = 2 * MM
    ground_diameter: float = 4 * MM
    contact_impedance: tuple[float, ...] = (1e-3,) * 16
    ground_contact_impedance: float = 1e-3
    contact_impedance_by_freq: tuple[tuple[float, ...], ...] | None = None
    first_angle_deg: float = 0.0
    discs: tuple[tuple[float, float, float], ...] = ()
    reference: bool = True
    on_membrane: tuple[bool, ...] = ()
    membrane_patch: str = "stretch"
    face_z: tuple[float | None, ...] = ()

    @property
    def is_ring(self) -> bool:
        """The paper's layout: one ring and a central ground."""
        return not self.discs

    @property
    def n_active(self) -> int:
        """Electrodes that are not a passive reference: the driven ones, and the last one too
        where the reference floats (the protocol's patterns span it; a dataset moves it)."""
        return self.count + (0 if self.reference else 1)

    @property
    def contact_impedances(self) -> np.ndarray:
        """Every electrode's contact impedance (Ω·m²) in the layout's order: the driven ones',
        then the reference's (``ground_contact_impedance``)."""
        return np.append(np.asarray(self.contact_impedance, float), self.ground_contact_impedance)


@dataclass(frozen=True)
class Saline:
    conductivity: float = 0.37


@dataclass(frozen=True)
class Drive:
    """Current injection: amplitude per injection, FDM carriers, and the protocol: skip-N
    injections (injection i drives electrode i against i + N + 1), each frame measuring
    ``measure`` "reference" (every driven electrode against the reference, the paper's) or
    "adjacent" (EIDORS '{ad}': electrode l against l + 1). Or any protocol as data: ``stim``
    (n_stim, n) A into each of the n active electrodes per injection and ``meas`` (n_stim,
    n_meas, n) weights, EIDORS's stim_pattern and meas_pattern (the reference's column left
    out where there is one; every row summing to zero where it floats)."""

    current: float = 120e-6
    frequencies: tuple[float, ...] = tuple(2750.0 + 725.0 * k for k in range(16))
    skip: int = 8
    measure: str = "reference"
    stim: tuple[tuple[float, ...], ...] | None = None
    meas: tuple[tuple[tuple[float, ...], ...], ...] | None = None


@dataclass(frozen=True)
class Membrane:
    """The dome membrane's material (SI): ``law`` "neo-hookean" (``shear_modulus``) or "yeoh"
    (``yeoh_c``), ``bulk_ratio`` κ/μ, prism ``layers`` through the thickness (by default the
    element's, :data:`MEMBRANE_LAYERS`), and the
    reservoir's hydrostatic ``reservoir_pressure`` on the inner surface (Pa); ``chamber``
    "open" (the reservoir takes the displaced saline) or "closed" (the saline volume is held by
    the pressure); ``rim_vertices`` sets the membrane mesh (edge ≈ 2π·base radius / rim_vertices;
    by default the mesh preset's, :data:`MEMBRANE_RIM_VERTICES`);
    ``element``: "wedge15" (one 15-node quadratic prism per surface triangle and layer, its
    dilatation projected per element, jointsim/mechanics/wedge.py; the default) or "p2_tet"
    (each prism as three P2 tetrahedra, jointsim/mechanics/fem.py); ``volumetric``: how the P2
    tetrahedra integrate the volumetric energy, "pointwise" or "mean_dilatation" (wedges:
    "pointwise" only, their volumetric form is their own); ``moulding``: the stress-free shape, "cap" (moulded
    as the dome, inflated by the reservoir pressure) or "flat" (a flat sheet inflated until its
    apex reaches the dome height; the pressure that takes replaces ``reservoir_pressure``)."""

    law: str = "neo-hookean"
    shear_modulus: float = 22e3
    yeoh_c: tuple[float, float, float] = (9.8e3, 0.91e3, -0.16e3)
    bulk_ratio: float = 1000.0
    layers: int = 1
    reservoir_pressure: float = 0.0
    chamber: str = "open"
    rim_vertices: int = 64
    volumetric: str = "pointwise"
    moulding: str = "cap"
    element: str = "wedge15"

    def scaled(self, factor: float) -> "Membrane":
        """The same membrane with its moduli (either law's) multiplied by ``factor``."""
        return replace(self, shear_modulus=self.shear_modulus * factor, yeoh_c=tuple(c * factor for c in self.yeoh_c))


@dataclass(frozen=True)
class Target:
    """The pressing object: a sphere of ``radius`` (m), ``kind`` "rigid" or "soft" (a
    neo-Hookean sphere of ``youngs_modulus`` Pa and ``poisson_ratio``, ignored when rigid),
    with Coulomb ``friction`` coefficient against the membrane (0: frictionless; rigid only)."""

    radius: float = 7.5 * MM
    kind: str = "rigid"
    friction: float = 0.0
    youngs_modulus: float = 1.5e6  # DESIGN.md: Sylgard 184, E ~ 0.6-3 MPa
    poisson_ratio: float = 0.49


@dataclass(frozen=True)
class Noise:
    snr_db: float = 74.2
    seed: int = 0
    drift_per_s: float = 0.0
    frame_rate_hz: float = 50.0


# the scenes shipped with the package (the paper's sensor, its stiffness study, the bench rig);
# a checkout's scenes/ links here
SCENES_DIR = Path(__file__).resolve().parent / "scenes"

MESH_PRESETS: dict[str, dict[str, float]] = {
    # max_edge_mm sets the bulk size; tuned so the default chamber gives the named tet counts
    # (gmsh keeps to the sizes asked; fTetWild, before 2026-11-27, made ~1.5x as many tets from
    # 3.0 / 2.2 / 1.1 / 0.75 mm)
    "test": {"max_edge_mm": 2.6, "electrode_refinement": 4.0},
    "dataset": {"max_edge_mm": 1.9, "electrode_refinement": 6.0},
    # the dataset's fidelity with the forward within 1 % of its converged limit: P2 elements on a
    # coarse mesh graded at the electrodes' rims, the dome's dent sampled finer
    # (results/forward_accuracy.md)
    "dataset_p2": {"max_edge_mm": 2.6, "electrode_refinement": 2.0, "rim_refinement": 10.0, "grading": 0.6,
                   "element_order": 2, "dome_rim_vertices": 144},
    "paper": {"max_edge_mm": 0.97, "electrode_refinement": 10.0},
    # convergence checks only (~1 M tets; minutes per mesh and per solve on 2 cores)
    "fine": {"max_edge_mm": 0.66, "electrode_refinement": 10.0},
}
# a scene's fidelity where its [mesh] section names none: the forward within 1 % of its limit
DEFAULT_MESH_PRESET = "dataset_p2"
GRADING = 0.35  # [mesh] grading: how fast the element size grows away from the electrodes (per unit distance)
# [mesh] rim_refinement: the element size at the electrodes' outlines is max_edge / rim_refinement
# (1: no refinement beyond electrode_refinement's); where the complete electrode model's current
# density peaks, and where a coarse mesh errs most on the current-carrying electrodes
RIM_REFINEMENT_MAX = 100.0
# [mesh] dome_rim_vertices: the chamber's dome surface triangulated with this many rim vertices
# (0: from max_edge, at least geometry.DOME_RIM_VERTICES); the pressed dent is sampled at its
# vertices, so δV converges with it (results/forward_accuracy.md)
SNR_RANGE_DB = (0.0, 200.0)  # [noise] snr_db, [dataset] snr_db and the --snr-db flags: dB re the mean standing |V|
# [mesh] keys of the fTetWild mesher used until 2026-11-27: still read (scenes and stored
# provenance carry them), warned about and ignored
RETIRED_MESH_KEYS = ("epsilon_rel", "stop_energy", "max_opt_iter")
MOULDINGS = ("cap", "flat")  # [membrane] moulding: the membrane's stress-free shape
# [membrane] element: one 15-node quadratic prism per surface triangle and layer, its dilatation
# projected (mechanics/wedge.py; the default), or each prism as three P2 tetrahedra (mechanics/fem.py)
MEMBRANE_ELEMENTS = ("p2_tet", "wedge15")
# the prism layers through the 2 mm thickness each element gets unless [membrane] layers is given:
# wedges 1 (a second changes the force at 3 mm by <= 0.4 %, results/mechanics_benchmark_wedge15.md),
# tetrahedra 2 (one layer of pointwise P2 tetrahedra locks in bending, results/locking_cantilever.md)
MEMBRANE_LAYERS: dict[str, int] = {"p2_tet": 2, "wedge15": 1}
# the element of the records (dataset stores, palpation runs) made before [membrane] element
# existed: they record no element, and a run records it only where it differs from this, so
# that those records still resume and read right
UNRECORDED_ELEMENT = "p2_tet"
MEMBRANE_MAX_LAYERS = 8  # [membrane] layers is in [1, MEMBRANE_MAX_LAYERS]
MEMBRANE_RIM_RANGE = (16, 1024)
# below this a wedge membrane's force is well off the converged one (a contact patch of a few
# triangles): warn_coarse_membrane
WEDGE_MIN_RIM_VERTICES = 48

# the membrane mesh's rim vertices each fidelity gets unless [membrane] rim_vertices is given.
# Wedges, one layer: 92 is within 0.7 % of the 160/2 mesh in force at 1-3 mm (0.4 s per step), 64
# within 2.0 % (0.2 s; results/mechanics_benchmark_wedge15.md). Tetrahedra, two layers: 92 within 2 %,
# 64 2.4-5.8 % stiff (results/mechanics_benchmark.md). 64 at the dataset fidelity and in tests, 92 at
# "paper" and finer; "custom" (a chamber tuned by hand) gets the converged one
MEMBRANE_RIM_VERTICES: dict[str, int] = {"test": 64, "dataset": 64, "dataset_p2": 64, "paper": 92, "fine": 92, "custom": 92}


def membrane_layers(n: int, name: str = "membrane.layers") -> int:
    """``n`` prism layers through the membrane, checked: an integer in [1, MEMBRANE_MAX_LAYERS],
    else a ValueError naming ``name``."""
    if isinstance(n, bool) or not isinstance(n, numbers.Integral) or not 1 <= n <= MEMBRANE_MAX_LAYERS:
        raise SceneError(f"{name} = {n!r}: must be an integer in [1, {MEMBRANE_MAX_LAYERS}]")
    return int(n)


def membrane_rim_vertices(n: int, element: str, name: str = "membrane.rim_vertices") -> int:
    """``n`` rim vertices for the membrane, checked: outside MEMBRANE_RIM_RANGE a ValueError
    naming ``name``, below what the ``element`` needs for its force a warning."""
    lo, hi = MEMBRANE_RIM_RANGE
    if not lo <= n <= hi:
        raise SceneError(f"{name} = {n}: must be in [{lo}, {hi}]")
    warn_coarse_membrane(n, element, name)
    return n


def warn_coarse_membrane(n: int, element: str, name: str = "membrane.rim_vertices") -> None:
    """Warn where one layer of wedges on ``n`` rim vertices is too coarse for its force."""
    if element == "wedge15" and n < WEDGE_MIN_RIM_VERTICES:
        warnings.warn(f"{name} = {n}: wedge membranes coarser than {WEDGE_MIN_RIM_VERTICES} rim vertices are soft (at 32, "
                      "the force at 1 mm is 14 % below the 96-rim mesh's; from 48 on within 2.5 %: tests/test_membrane.py); "
                      "give >= 48 for forces within a few per cent", UserWarning, stacklevel=3)


def preset_mesh(preset: str) -> dict[str, float | int]:
    """The chamber mesh fields (SI) a fidelity ``preset`` sets, its unnamed ones at their plain
    values (no rim refinement, the dome from max_edge, GRADING, P1)."""
    p = MESH_PRESETS[preset]
    return {"max_edge": p["max_edge_mm"] * MM, "electrode_refinement": p["electrode_refinement"],
            "rim_refinement": p.get("rim_refinement", 1.0), "dome_rim_vertices": int(p.get("dome_rim_vertices", 0)),
            "grading": p.get("grading", GRADING), "element_order": int(p.get("element_order", 1))}


_DEFAULT_MESH = preset_mesh(DEFAULT_MESH_PRESET)


@dataclass(frozen=True)
class MeshSpec:
    """Chamber mesh resolution: bulk edge length, refinement factor and zone around electrodes,
    the order of the EIT forward model's elements on it (1: P1; 2: P2, same tetrahedra), and how
    the mesh follows the membrane (``update``: "morph" the reference mesh, "remesh" every
    deformed chamber, or "auto": morph, remesh when the morph inverts or degrades)."""

    preset: str = DEFAULT_MESH_PRESET
    max_edge: float = _DEFAULT_MESH["max_edge"]
    electrode_refinement: float = _DEFAULT_MESH["electrode_refinement"]
    refinement_zone: float = 0.8 * MM
    grading: float = _DEFAULT_MESH["grading"]
    element_order: int = _DEFAULT_MESH["element_order"]
    update: str = "auto"
    rim_refinement: float = _DEFAULT_MESH["rim_refinement"]
    dome_rim_vertices: int = _DEFAULT_MESH["dome_rim_vertices"]


@dataclass(frozen=True)
class Scene:
    name: str = "unnamed"
    chamber: Chamber = field(default_factory=Chamber)
    electrodes: ElectrodeRing = field(default_factory=ElectrodeRing)
    saline: Saline = field(default_factory=Saline)
    drive: Drive = field(default_factory=Drive)
    noise: Noise = field(default_factory=Noise)
    mesh: MeshSpec = field(default_factory=MeshSpec)
    membrane: Membrane = field(default_factory=Membrane)
    target: Target = field(default_factory=Target)
    reconstruction: "ReconstructionSpec" = field(default_factory=lambda: ReconstructionSpec())
    palpation: "PalpationSpec" = field(default_factory=lambda: PalpationSpec())
    dataset: "DatasetSpec" = field(default_factory=lambda: DatasetSpec())

    def with_mesh_preset(self, preset: str) -> "Scene":
        """The scene at fidelity ``preset``: that preset's chamber mesh sizes, element order (P1
        where the preset names none, as a scene's ``[mesh] preset`` parses) and membrane rim
        vertices, replacing what the scene gave for them."""
        if preset not in MESH_PRESETS:
            raise SceneError(f"mesh.preset = {preset!r}: allowed values are {sorted(MESH_PRESETS)}")
        return replace(
            self,
            mesh=replace(self.mesh, preset=preset, **preset_mesh(preset)),
            # a fidelity sets the membrane's mesh with the chamber's (MEMBRANE_RIM_VERTICES)
            membrane=replace(self.membrane, rim_vertices=MEMBRANE_RIM_VERTICES[preset]),
        )

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    def digest(self, *sections: str) -> str:
        """Content hash of the named sections (all when none), for caches and provenance; a
        value added to the scene format later (:data:`LATER_DEFAULTS`) counts only where it
        differs from the behaviour before it, so what was stored before it still matches."""
        d = self.to_dict()
        for (section, key), before in LATER_DEFAULTS.items():
            if d.get(section, {}).get(key) == before:
                d[section] = {k: v for k, v in d[section].items() if k != key}
        if sections:
            d = {k: d[k] for k in sections}
        return hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()[:16]


# scene values added to the format after stores, maps and studies were first written, with the
# behaviour before they existed: identities leave them out at that value
LATER_DEFAULTS: dict[tuple[str, str], Any] = {("reconstruction", "prior"): "tikhonov", ("mesh", "rim_refinement"): 1.0,
                                          ("chamber", "base_radius_y"): None, ("reconstruction", "depth_exponent"): 2.0, ("chamber", "surface_file"): None,
                                          ("chamber", "surface_sha256"): None, ("chamber", "surface_unit"): MM,
                                          ("chamber", "outline"): (), ("electrodes", "face_z"): (),
                                          ("mesh", "dome_rim_vertices"): 0, ("electrodes", "on_membrane"): (),
                                          ("electrodes", "membrane_patch"): "stretch"}


# --------------------------------------------------------------------------------------------
# Parsing and validation


# every key a scene's parse reads, with its default and what is allowed, while
# parameter_table() collects them (None otherwise): the parse is the scene format's one definition
_READS: list[dict[str, Any]] | None = None


def _read(section: str, key: str, kind: str, default: Any, allowed: str) -> None:
    if _READS is not None:
        _READS.append({"section": section, "key": key, "kind": kind, "default": default, "allowed": allowed})


class _Table:
    """Reads one TOML table, checking each key's range and rejecting unknown keys."""

    def __init__(self, data: dict[str, Any], name: str):
        if not isinstance(data, dict):
            raise SceneError(f"[{name}] must be a table, got {type(data).__name__}")
        self.data = dict(data)
        self.name = name
        self.seen: set[str] = set()

    def key(self, k: str) -> str:
        return f"{self.name}.{k}"

    def number(
        self,
        k: str,
        default: float,
        lo: float,
        hi: float,
        *,
        lo_open: bool = False,
        hi_open: bool = False,
    ) -> float:
        self.seen.add(k)
        _read(self.name, k, "number", default, f"{'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}")
        v = self.data.get(k, default)
        return _check_number(self.key(k), v, lo, hi, lo_open, hi_open)

    def integer(self, k: str, default: int, lo: int, hi: int) -> int:
        self.seen.add(k)
        _read(self.name, k, "integer", default, f"[{lo}, {hi}]")
        v = self.data.get(k, default)
        if isinstance(v, bool) or not isinstance(v, int):
            raise SceneError(f"{self.key(k)} = {v!r}: must be an integer in [{lo}, {hi}]")
        if not lo <= v <= hi:
            raise SceneError(f"{self.key(k)} = {v}: must be an integer in [{lo}, {hi}]")
        return v

    def raw(self, k: str, default: Any) -> Any:
        """A value its caller checks (a list, a table, a flag): recorded as such."""
        self.seen.add(k)
        _read(self.name, k, "value", default, "")
        return self.data.get(k, default)

    def choice(self, k: str, default: str, allowed: tuple[str, ...]) -> str:
        """A value that must be one of ``allowed``."""
        self.seen.add(k)
        _read(self.name, k, "choice", default, " | ".join(map(str, allowed)))
        v = self.data.get(k, default)
        if v not in allowed:
            raise SceneError(f"{self.key(k)} = {v!r}: allowed values are {', '.join(map(repr, allowed))}")
        return v

    def finish(self) -> None:
        unknown = sorted(set(self.data) - self.seen)
        if unknown:
            raise SceneError(
                f"unknown key(s) in [{self.name}]: {', '.join(unknown)}; "
                f"known keys are {', '.join(sorted(self.seen))}"
            )


def _check_number(key: str, v: Any, lo: float, hi: float, lo_open: bool, hi_open: bool) -> float:
    rng = f"{'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}"
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise SceneError(f"{key} = {v!r}: must be a number in {rng}")
    v = float(v)
    if not math.isfinite(v):
        raise SceneError(f"{key} = {v}: must be a finite number in {rng}")
    bad_lo = v <= lo if lo_open else v < lo
    bad_hi = v >= hi if hi_open else v > hi
    if bad_lo or bad_hi:
        raise SceneError(f"{key} = {v:g}: must be in {rng}")
    return v


def _number_list(key: str, v: Any, n: int | None, lo: float, hi: float, lo_open: bool) -> tuple[float, ...]:
    if isinstance(v, (int, float)) and not isinstance(v, bool):
        v = [v] * (n or 1)
    if not isinstance(v, list) or (n is not None and len(v) != n):
        want = f"a list of {n} numbers" if n else "a list of numbers"
        raise SceneError(f"{key}: must be a number or {want}, got {v!r}")
    return tuple(_check_number(f"{key}[{i}]", x, lo, hi, lo_open, False) for i, x in enumerate(v))


# --------------------------------------------------------------------------------------------
# [electrodes] layouts as data


LAYOUT_GENERATORS = ("ring", "grid", "disc", "membrane", "face")
MEMBRANE_PATCHES = ("stretch", "rigid")  # [electrodes] membrane_patch: how an electrode on the membrane follows it
RING_KEYS = ("count", "ring_radius_mm", "diameter_mm", "ground_diameter_mm", "first_angle_deg")  # the paper's layout  # [[electrodes.<generator>]] tables, electrodes made in this order
GRID_KINDS = ("square", "hex")
MEASUREMENTS = ("reference", "adjacent")  # [drive] measure
# every disc ends at least this far inside the base's rim: the dome meets the base there, and a
# disc in the corner would leave the saline above it thinner than the mesh can resolve
EDGE_CLEARANCE_MM = 0.5
MIN_ELECTRODE_GAP_MM = 0.1  # edge to edge: the mesher embeds every outline, and they must not touch
MAX_ELECTRODES = 129
MIN_ELECTRODES = 2  # one driven against the reference: a resistance
CAP_KEYS = ("base_radius_mm", "base_radius_y_mm", "dome_height_mm")  # [chamber]: the parametric cap's size
PAD_STRETCH_MAX = 4.0  # [chamber] base_radius_y_mm within this factor of base_radius_mm (the cap's triangles stretch with it)


def _layout(t: "_Table", base_r: float, height: float, base_ry: float,
            chamber: Chamber | None = None) -> tuple[tuple[tuple[float, float, float], ...], bool, tuple[bool, ...], tuple]:
    """The electrodes of [[electrodes.ring]], [[electrodes.grid]], [[electrodes.disc]] and
    [[electrodes.membrane]] (in that order, each in file order) as (x, y, radius) m, the
    reference moved last, whether there is one ([electrodes] reference: an electrode's index in
    that order, or "none"), which lie on the membrane (empty where none does), and the planes of
    the [[electrodes.face]] ones (None for the others; empty where there are none). ``base_ry``:
    the base's semi-axis along y (an elongated pad where it is not ``base_r``: the cap and the
    membrane's electrodes stretched along y with it); ``chamber``: where it is a user's surface,
    the discs are checked against its base's outline."""
    outline = chamber is not None and bool(chamber.outline)
    for k in RING_KEYS:
        if k in t.data:
            raise SceneError(f"electrodes.{k}: describes the paper's ring; with [[electrodes.ring|grid|disc]] tables "
                             "give each generator's own sizes instead")
    discs: list[tuple[float, float, float]] = []
    where: list[str] = []
    on: list[bool] = []
    planes: list[float | None] = []
    sphere = (base_r**2 + height**2) / (2 * height)  # the cap's sphere radius, mm
    rim_angle = math.asin(min(base_r / sphere, 1.0))  # the rim's polar angle, from the apex
    for kind in LAYOUT_GENERATORS:
        tables = t.raw(kind, [])
        if not isinstance(tables, list) or not all(isinstance(g, dict) for g in tables):
            raise SceneError(f"electrodes.{kind}: must be an array of tables ([[electrodes.{kind}]])")
        for i, g in enumerate(tables):
            name = f"electrodes.{kind}[{i}]"
            u = _Table(g, name)
            if kind == "face":
                z = _face_plane(u, name, chamber, height)
                u.finish()
                discs.append((0.0, 0.0, 0.0))
                where.append(f"{name} electrode 0")
                on.append(False)
                planes.append(z * MM)
                continue
            d = u.number("diameter_mm", 2.0, 0.0, base_r, lo_open=True)
            if kind == "ring":
                n = u.integer("count", 16, 1, MAX_ELECTRODES)
                r = u.number("radius_mm", 15.0, 0.0, base_r)
                phase = math.radians(u.number("phase_deg", 0.0, -360.0, 360.0))
                pts = [(r * math.cos(phase + 2 * math.pi * k / n), r * math.sin(phase + 2 * math.pi * k / n)) for k in range(n)]
            elif kind == "membrane" and outline:
                # a user's top has no polar angle: the ring is given by where it lies above the base
                if "polar_angle_deg" in g:
                    raise SceneError(f"{name}.polar_angle_deg: a chamber from chamber.surface_file has no cap; give "
                                     "radius_mm, the ring's radius seen from above")
                n = u.integer("count", 16, 1, MAX_ELECTRODES)
                r = u.number("radius_mm", 0.0, 0.0, base_r)
                phase = math.radians(u.number("phase_deg", 0.0, -360.0, 360.0))
                pts = [(r * math.cos(phase + 2 * math.pi * k / n), r * math.sin(phase + 2 * math.pi * k / n)) for k in range(n)]
            elif kind == "membrane":
                n = u.integer("count", 16, 1, MAX_ELECTRODES)
                # along the surface: the disc ends EDGE_CLEARANCE_MM short of the rim
                top = math.degrees(rim_angle - (d / 2 + EDGE_CLEARANCE_MM) / sphere)
                if top <= 0:
                    raise SceneError(f"{name}.diameter_mm = {d:g}: too large for the dome")
                polar = math.radians(u.number("polar_angle_deg", min(30.0, top), 0.0, top))
                phase = math.radians(u.number("phase_deg", 0.0, -360.0, 360.0))
                rho = sphere * math.sin(polar)
                sy = base_ry / base_r  # on a pad, the cap's points stretched along y with it
                pts = [(rho * math.cos(phase + 2 * math.pi * k / n), sy * rho * math.sin(phase + 2 * math.pi * k / n)) for k in range(n)]
            elif kind == "grid":
                pitch = u.number("pitch_mm", 5.0, 0.0, base_r, lo_open=True)
                shape = u.choice("kind", "square", GRID_KINDS)
                within = u.number("within_mm", base_r - EDGE_CLEARANCE_MM - d / 2, 0.0, base_r)
                m = int(within // pitch) + 1
                dy = pitch * (math.sqrt(3) / 2 if shape == "hex" else 1.0)
                pts = []
                for j in range(-int(within // dy) - 1, int(within // dy) + 2):
                    shift = 0.5 * pitch if shape == "hex" and j % 2 else 0.0
                    pts += [(k * pitch + shift, j * dy) for k in range(-m - 1, m + 2)]
                pts = [(x, y) for x, y in pts if math.hypot(x, y) <= within + 1e-9]
                if not pts:
                    raise SceneError(f"{name}: no grid point within {within:g} mm of the axis")
            else:
                pts = [tuple(_number_list(f"{name}.xy_mm", u.raw("xy_mm", None), 2, -base_r, base_r, False))]
            u.finish()
            discs += [(x, y, d / 2) for x, y in pts]
            where += [f"{name} electrode {k}" for k in range(len(pts))]
            on += [kind == "membrane"] * len(pts)
            planes += [None] * len(pts)
    if not MIN_ELECTRODES <= len(discs) <= MAX_ELECTRODES:
        raise SceneError(f"[electrodes]: the generators make {len(discs)} electrodes; a layout has {MIN_ELECTRODES} to {MAX_ELECTRODES}")
    c, r = np.array([d[:2] for d in discs]), np.array([d[2] for d in discs])
    membrane = np.array(on)
    face = np.array([z is not None for z in planes])
    if face.any():
        zs = [z for z in planes if z is not None]
        if len(set(zs)) < len(zs):
            raise SceneError("[[electrodes.face]]: two face electrodes on one plane")
        if 0.0 in zs and (~face & ~membrane).any():
            raise SceneError("[[electrodes.face]] on z = 0 covers the whole base: no disc can lie there too")
    # on the membrane: the points of the cap (mm), to be apart along it (chords: a little short of arcs)
    round_xy = c * [1.0, base_r / base_ry]  # where on the round cap a point of a pad came from
    lifted = np.column_stack([c, np.sqrt(np.maximum(sphere**2 - (round_xy**2).sum(axis=1), 0.0)) - (sphere - height)])
    if outline and membrane.any():  # on a user's top: its height above each footprint
        lifted[:, 2] = np.where(membrane, top_height(read_surface(chamber.surface_file, chamber.surface_unit), c * MM) / MM, 0.0)
    if outline:
        if (bad := np.flatnonzero(~chamber.inside(c * MM, (r + EDGE_CLEARANCE_MM) * MM) & ~face)).size:
            k = int(bad[0])
            raise SceneError(f"{where[k]}: at ({c[k, 0]:g}, {c[k, 1]:g}) mm it does not end {EDGE_CLEARANCE_MM:g} mm inside the "
                             "base's outline (the rim of chamber.surface_file)")
    elif base_ry == base_r:
        reach = np.where(membrane | face, 0.0, np.hypot(c[:, 0], c[:, 1]) + r)
        if (bad := np.flatnonzero(reach > base_r - EDGE_CLEARANCE_MM + 1e-9)).size:
            k = int(bad[0])
            raise SceneError(f"{where[k]}: at ({c[k, 0]:g}, {c[k, 1]:g}) mm it reaches {reach[k]:.3g} mm from the axis; every disc must "
                             f"end {EDGE_CLEARANCE_MM:g} mm inside the base radius {base_r:g} mm")
    else:  # a pad: every disc's footprint inside the outline moved in by its radius and the clearance
        inset = r + EDGE_CLEARANCE_MM
        q = (c[:, 0] / (base_r - inset)) ** 2 + (c[:, 1] / (base_ry - inset)) ** 2
        if (bad := np.flatnonzero(((q > 1 + 1e-9) | (inset >= min(base_r, base_ry))) & ~face)).size:
            k = int(bad[0])
            raise SceneError(f"{where[k]}: at ({c[k, 0]:g}, {c[k, 1]:g}) mm it does not end {EDGE_CLEARANCE_MM:g} mm inside the "
                             f"base's outline (an ellipse of semi-axes {base_r:g} x {base_ry:g} mm)")
    gaps = _edge_gaps(lifted, r)
    gaps[membrane[:, None] != membrane[None, :]] = np.inf  # the base and the membrane: apart by the chamber
    gaps[face] = gaps[:, face] = np.inf  # a face electrode: alone on its plane (checked above)
    if gaps.min() < MIN_ELECTRODE_GAP_MM:
        a, b = np.unravel_index(int(np.argmin(gaps)), gaps.shape)
        raise SceneError(f"{where[a]} and {where[b]}: {'overlap' if gaps[a, b] < 0 else 'are closer than'} "
                         f"{'' if gaps[a, b] < 0 else f'{MIN_ELECTRODE_GAP_MM:g} mm '}(edge gap {gaps[a, b]:.3g} mm); "
                         "electrodes must be apart")
    ref = t.raw("reference", None)
    if ref == "none":
        reference, k = False, len(discs) - 1
    elif isinstance(ref, int) and not isinstance(ref, bool) and 0 <= ref < len(discs):
        reference, k = True, ref
    else:
        raise SceneError(f"electrodes.reference = {ref!r}: the index of the reference electrode (0 to {len(discs) - 1}, "
                         "numbered in the order the generators make them: rings, grids, discs) or \"none\" for a floating reference")
    order = [i for i in range(len(discs)) if i != k] + [k]
    placed = tuple((discs[i][0] * MM, discs[i][1] * MM, discs[i][2] * MM) for i in order)
    return (placed, reference, tuple(on[i] for i in order) if membrane.any() else (),
            tuple(planes[i] for i in order) if face.any() else ())


def _face_plane(u: "_Table", name: str, chamber: Chamber | None, height: float) -> float:
    """The plane z (mm) of a [[electrodes.face]]: z = 0 (the whole base) on the cap; on a
    user's surface any plane that holds some of its faces."""
    z = u.number("z_mm", 0.0, 0.0, height)
    if chamber is None or not chamber.outline:
        if z != 0.0:
            raise SceneError(f"{name}.z_mm = {z:g}: the cap has faces only on z = 0 (the base); other planes need a "
                             "chamber.surface_file with faces there")
        return z
    sf = read_surface(chamber.surface_file, chamber.surface_unit)
    tol = 1e-9 * float(np.ptp(sf.vertices, axis=0).max())
    if not np.any(np.all(np.abs(sf.vertices[sf.faces][..., 2] - z * MM) <= tol, axis=1)):
        raise SceneError(f"{name}.z_mm = {z:g}: no face of chamber.surface_file lies on that plane")
    return z


PATTERN_KEYS = ("stim_ua", "meas")  # [drive]: a protocol as data, instead of skip and measure


def _patterns(t: "_Table", n: int, reference: bool) -> tuple[tuple | None, tuple | None]:
    """[drive] stim_ua (n_stim, n) µA and meas ((n_meas, n) for every injection, or (n_stim,
    n_meas, n)) over the ``n`` active electrodes, as SI tuples; (None, None) when not given."""
    # read by scene_data before the parse (the file's arrays stand in as stim_ua, meas)
    _read("drive", "patterns_file", "value", None, ".npz (stim_ua or stim_A, meas) or EIDORS .mat, relative to the scene file")
    if not any(k in t.data for k in PATTERN_KEYS):
        return None, None
    if not all(k in t.data for k in PATTERN_KEYS):
        raise SceneError("[drive]: a protocol as data needs both stim_ua (currents per injection) and meas (measurement weights)")
    for k in ("skip", "measure"):
        if k in t.data:
            raise SceneError(f"drive.{k}: give skip and measure, or stim_ua and meas, not both")
    try:
        stim = np.array(t.raw("stim_ua", None), dtype=float) * 1e-6
        meas = np.array(t.raw("meas", None), dtype=float)
    except (TypeError, ValueError):
        raise SceneError("drive.stim_ua, drive.meas: must be rectangular arrays of numbers") from None
    if stim.ndim != 2 or stim.shape[1] != n or not len(stim):
        raise SceneError(f"drive.stim_ua: must be (n_stim, {n}) µA, one row per injection over the {n} active electrodes, "
                         f"got shape {stim.shape}")
    if meas.ndim == 2:
        meas = np.broadcast_to(meas, (len(stim),) + meas.shape)
    if meas.ndim != 3 or meas.shape[0] != len(stim) or meas.shape[2] != n or not meas.shape[1]:
        raise SceneError(f"drive.meas: must be (n_meas, {n}) or ({len(stim)}, n_meas, {n}) weights, got shape {meas.shape}")
    if not (np.isfinite(stim).all() and np.isfinite(meas).all()) or not np.abs(stim).max() > 0:
        raise SceneError("drive.stim_ua, drive.meas: must be finite, with some current")
    if not reference:
        if (bad := np.flatnonzero(np.abs(stim.sum(axis=1)) > 1e-9 * np.abs(stim).max())).size:
            raise SceneError(f"drive.stim_ua[{bad[0]}]: with a floating reference every injection's currents must sum to zero")
        if np.abs(meas.sum(axis=2)).max() > 1e-9 * np.abs(meas).max():
            raise SceneError("drive.meas: with a floating reference every measurement's weights must sum to zero")
    return tuple(map(tuple, stim.tolist())), tuple(tuple(map(tuple, m)) for m in meas.tolist())


def _patterns_from_file(drive: dict[str, Any], scene_path: Path) -> dict[str, Any]:
    """[drive] with ``patterns_file`` (relative to the scene file) read into stim_ua and meas:
    an .npz holding ``stim_ua`` (n_stim, n) µA (or ``stim_A`` in A) and ``meas``, or an
    EIDORS-style .mat (``fwd_model.stimulation(s).stim_pattern`` A, ``.meas_pattern``; what
    ``jointsim forward`` writes). The arrays then stand in the scene as if written inline, and
    are checked as such."""
    drive = dict(drive)
    name = drive.pop("patterns_file")
    if not isinstance(name, str):
        raise SceneError(f"drive.patterns_file = {name!r}: must be the path of an .npz or .mat file")
    f = (scene_path.parent / name).resolve()
    if not f.is_file():
        raise SceneError(f"drive.patterns_file = {name!r}: no such file ({f})")
    for k in PATTERN_KEYS:
        if k in drive:
            raise SceneError(f"drive.{k}: give the patterns inline or in drive.patterns_file, not both")
    try:
        if f.suffix == ".npz":
            with np.load(f) as z:
                stim = z["stim_ua"] if "stim_ua" in z else z["stim_A"] * 1e6
                meas = z["meas"]
        elif f.suffix == ".mat":
            from scipy.io import loadmat

            st = np.atleast_1d(loadmat(f, squeeze_me=True, struct_as_record=False)["fwd_model"].stimulation)
            stim = np.array([np.ravel(x.stim_pattern) for x in st], float) * 1e6
            meas = np.array([np.atleast_2d(x.meas_pattern) for x in st], float)
        else:
            raise SceneError(f"drive.patterns_file = {name!r}: an .npz (stim_ua or stim_A, meas) or an EIDORS .mat file")
    except (KeyError, AttributeError, ValueError, OSError) as e:
        raise SceneError(f"drive.patterns_file = {name!r}: cannot read its patterns ({type(e).__name__}: {e})") from None
    drive["stim_ua"], drive["meas"] = np.asarray(stim, float).tolist(), np.asarray(meas, float).tolist()
    return drive


def _edge_gaps(centres: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """(n, n) edge-to-edge distances between the discs (centres (n, 2 or 3); negative: overlap),
    inf on the diagonal."""
    gaps = np.linalg.norm(centres[:, None] - centres[None], axis=-1) - radii[:, None] - radii[None]
    np.fill_diagonal(gaps, np.inf)
    return gaps


def ring_positions(count: int, radius: float, first_angle_deg: float) -> np.ndarray:
    """(count, 2) centres of the paper's ring: electrode k at first_angle_deg + 360°·k/count,
    anticlockwise, at ``radius`` (any length unit)."""
    ang = np.deg2rad(first_angle_deg) + 2 * np.pi * np.arange(count) / count
    return np.column_stack([radius * np.cos(ang), radius * np.sin(ang)])


def _layout_room(centres: np.ndarray, radii: np.ndarray, base_r: float, on_membrane: tuple[bool, ...] = (),
                 base_ry: float | None = None, outline: tuple = (), face_z: tuple = ()) -> tuple[float, float]:
    """(smallest edge gap between electrodes, least room to the rim beyond EDGE_CLEARANCE_MM), mm,
    in the base plane (a membrane electrode's footprint there: a little less room than it has
    on the dome); a base and a membrane electrode are apart by the chamber. On a pad (``base_ry``
    the semi-axis along y) the room to its elliptical rim is bounded from below by the shorter
    semi-axis × (1 − the point's elliptical radius)."""
    gaps = _edge_gaps(centres, radii)
    if any(on_membrane):
        on = np.asarray(on_membrane)
        gaps[on[:, None] != on[None, :]] = np.inf
    if outline:  # a user's surface (m): the distance to its rim
        poly = np.asarray(outline) / MM
        edge = np.array([segment_distance(q, poly).min() for q in centres]) - EDGE_CLEARANCE_MM - radii
    elif base_ry is None or base_ry == base_r:
        edge = base_r - EDGE_CLEARANCE_MM - (np.hypot(centres[:, 0], centres[:, 1]) + radii)
    else:
        q = np.sqrt((centres[:, 0] / base_r) ** 2 + (centres[:, 1] / base_ry) ** 2)
        edge = min(base_r, base_ry) * (1 - q) - EDGE_CLEARANCE_MM - radii
    if face_z:  # whole faces: no room to measure (a dataset does not move them)
        face = np.array([z is not None for z in face_z])
        gaps[face] = gaps[:, face] = np.inf
        edge = np.where(face, np.inf, edge)
        if face.all():
            return math.inf, math.inf
    return float(gaps.min()), float(edge.min())


def scene_from_dict(data: dict[str, Any], name: str = "unnamed") -> Scene:
    """Build and validate a :class:`Scene` from a parsed TOML mapping (keys with units)."""
    data = _moved_keys(dict(data))
    name = str(data.pop("name", name))
    data.pop("description", None)
    known = {"chamber", "electrodes", "saline", "drive", "noise", "mesh", "membrane", "target", "reconstruction", "palpation",
             "dataset"}
    unknown = sorted(set(data) - known)
    if unknown:
        raise SceneError(f"unknown section(s): {', '.join(unknown)}; known are {', '.join(sorted(known))}")

    t = _Table(data.get("chamber", {}), "chamber")
    t.seen.add("surface_file")
    surface = t.data.get("surface_file")
    _read("chamber", "surface_file", "value", None, "a watertight triangle surface (.stl, .obj, .ply, .off), base on z = 0; "
          "relative to the scene file")
    if surface is not None:
        chamber, base_r, base_ry, height = _user_chamber(t, surface)
    else:
        base_r = t.number("base_radius_mm", 20.0, 1.0, 500.0)
        # an elongated pad: the cap stretched along y to this semi-axis (its membrane's triangles with it)
        base_ry = t.number("base_radius_y_mm", base_r, base_r / PAD_STRETCH_MAX, base_r * PAD_STRETCH_MAX)
        # a spherical cap taller than its base radius would be more than a hemisphere
        height = t.number("dome_height_mm", 10.0, 0.5, min(base_r, base_ry))
        chamber = Chamber(base_r * MM, height * MM, 0.0, None if base_ry == base_r else base_ry * MM)
    thick = t.number("membrane_thickness_mm", 2.0, 0.05, min(height, 50.0), lo_open=False)
    t.finish()
    chamber = replace(chamber, membrane_thickness=thick * MM)
    short = chamber.inradius / MM  # the largest disc about the axis in the base: what contact points or a ring fit in

    t = _Table(data.get("electrodes", {}), "electrodes")
    generated = [k for k in LAYOUT_GENERATORS if k in t.data]
    on_membrane: tuple[bool, ...] = ()
    face_z: tuple = ()
    if generated:
        discs, reference, on_membrane, face_z = _layout(t, base_r, height, base_ry, chamber)
        count = len(discs) - 1
        ring = diam = gdiam = first = 0.0  # the ring's own sizes: not this layout's
    else:
        count = t.integer("count", 16, 3, 64)
        diam = t.number("diameter_mm", 2.0, 0.0, base_r, lo_open=True)
        gdiam = t.number("ground_diameter_mm", 4.0, 0.0, base_r, lo_open=True)
        ring_lo = gdiam / 2 + diam / 2
        ring_hi = short - diam / 2 - EDGE_CLEARANCE_MM
        ring = t.number("ring_radius_mm", 15.0, ring_lo, ring_hi, lo_open=True)
        pitch = 2 * ring * math.sin(math.pi / count)
        if pitch <= diam:
            raise SceneError(
                f"electrodes.diameter_mm = {diam:g}: must be below the ring pitch "
                f"{pitch:.3g} mm (electrodes would overlap)"
            )
        first = t.number("first_angle_deg", 0.0, -360.0, 360.0)
        discs, reference = (), True
    z = _number_list(
        "electrodes.contact_impedance_ohm_m2", t.raw("contact_impedance_ohm_m2", 1e-3), count, 0.0, 1.0, True
    )
    zg = t.number("ground_contact_impedance_ohm_m2", 1e-3, 0.0, 1.0, lo_open=True)
    zf_raw = t.raw("contact_impedance_by_freq_ohm_m2", None)
    patch = t.choice("membrane_patch", "stretch", MEMBRANE_PATCHES)
    if patch != "stretch" and not any(on_membrane):
        raise SceneError(f"electrodes.membrane_patch = {patch!r}: only for electrodes on the membrane ([[electrodes.membrane]])")
    t.finish()
    # room each electrode has: to its nearest neighbour's edge, and to the base's rim (mm)
    centres = (np.array([(d[0], d[1]) for d in discs]) / MM if discs else
               np.vstack([ring_positions(count, ring, first), [0.0, 0.0]]))
    radii = np.array([d[2] for d in discs]) / MM if discs else np.append(np.full(count, diam / 2), gdiam / 2)
    gap, edge = _layout_room(centres, radii, base_r, on_membrane, base_ry, chamber.outline, face_z)

    t = _Table(data.get("saline", {}), "saline")
    sigma = t.number("conductivity_s_per_m", 0.37, 0.0, 100.0, lo_open=True)
    t.finish()

    t = _Table(data.get("drive", {}), "drive")
    current = t.number("current_ua", 120.0, 0.0, 1e5, lo_open=True)
    freqs = _number_list("drive.frequencies_hz", t.raw("frequencies_hz", list(Drive().frequencies)), None, 0.0, 1e7, True)
    if not freqs:
        raise SceneError("drive.frequencies_hz = []: at least one carrier frequency (the paper's FDM drive has 16)")
    # skip-N over the driven electrodes (every electrode where the reference floats)
    n_driven = count + (0 if reference else 1)  # ElectrodeRing.n_active
    skip = t.raw("skip", min(8, n_driven // 2))  # the paper's skip-8, or opposite on fewer electrodes
    if isinstance(skip, bool) or not isinstance(skip, int) or not 0 <= skip <= n_driven // 2:
        raise SceneError(f"drive.skip = {skip!r}: must be an integer in [0, {n_driven // 2}] for {n_driven} driven electrodes")
    stim, meas = _patterns(t, n_driven, reference)
    if stim is None and n_driven < 2:
        raise SceneError(f"[drive]: {n_driven} driven electrode: give the protocol as data (stim_ua, meas), skip-N needs two or more")
    measure = t.choice("measure", "reference" if reference else "adjacent", MEASUREMENTS)
    if measure == "reference" and not reference and stim is None:
        raise SceneError("drive.measure = 'reference': the layout has no reference electrode (electrodes.reference = \"none\"); "
                         "measure \"adjacent\" pairs")
    t.finish()

    zf = None
    if zf_raw is not None:
        if not isinstance(zf_raw, list) or len(zf_raw) != len(freqs):
            raise SceneError(
                "electrodes.contact_impedance_by_freq_ohm_m2: must be a list with one row per "
                f"drive frequency ({len(freqs)} rows)"
            )
        zf = tuple(
            _number_list(f"electrodes.contact_impedance_by_freq_ohm_m2[{i}]", row, count, 0.0, 1.0, True)
            for i, row in enumerate(zf_raw)
        )

    t = _Table(data.get("noise", {}), "noise")
    snr = t.number("snr_db", 74.2, *SNR_RANGE_DB)
    seed = t.integer("seed", 0, 0, 2**63 - 1)
    drift = t.number("drift_per_s", 0.0, 0.0, 1.0)
    rate = t.number("frame_rate_hz", 50.0, 0.0, 1e5, lo_open=True)
    t.finish()

    t = _Table(data.get("mesh", {}), "mesh")
    preset = t.raw("preset", DEFAULT_MESH_PRESET)
    if not isinstance(preset, str) or (preset not in MESH_PRESETS and preset != "custom"):
        raise SceneError(f"mesh.preset = {preset!r}: allowed values are {sorted(MESH_PRESETS) + ['custom']}")
    base = preset if preset in MESH_PRESETS else "dataset"  # "custom": what the scene leaves out, dataset's
    p, d = MESH_PRESETS[base], preset_mesh(base)
    max_edge = t.number("max_edge_mm", p["max_edge_mm"], 0.05, base_r)
    refine = t.number("electrode_refinement", p["electrode_refinement"], 1.0, 50.0)
    zone = t.number("refinement_zone_mm", 0.8, 0.0, base_r)
    grading = t.number("grading", d["grading"], 0.05, 2.0)
    rim = t.number("rim_refinement", d["rim_refinement"], 1.0, RIM_REFINEMENT_MAX)
    dome_rim = t.integer("dome_rim_vertices", d["dome_rim_vertices"], 0, MEMBRANE_RIM_RANGE[1])
    if 0 < dome_rim < MEMBRANE_RIM_RANGE[0]:
        raise SceneError(f"mesh.dome_rim_vertices = {dome_rim}: must be 0 (from max_edge_mm) or in [{MEMBRANE_RIM_RANGE[0]}, {MEMBRANE_RIM_RANGE[1]}]")
    retired = [k for k in RETIRED_MESH_KEYS if k in t.data]
    for k in retired:
        t.raw(k, None)
    if retired:
        warnings.warn(f"mesh.{', mesh.'.join(retired)}: settings of the fTetWild mesher, which jointsim no longer uses "
                      "(the chamber is meshed by gmsh): ignored; remove them from the scene", UserWarning, stacklevel=2)
    element_order = t.integer("element_order", d["element_order"], 1, 2)
    update = t.choice("update", "auto", MESH_UPDATES)
    t.finish()
    if preset != "custom" and any(k in data.get("mesh", {}) for k in ("max_edge_mm", "electrode_refinement", "rim_refinement", "dome_rim_vertices")):
        preset = "custom"

    t = _Table(data.get("membrane", {}), "membrane")
    law = t.choice("law", "neo-hookean", ("neo-hookean", "yeoh"))
    mu = t.number("shear_modulus_kpa", 22.0, 0.0, 1e6, lo_open=True)
    yc = _number_list("membrane.yeoh_c_kpa", t.raw("yeoh_c_kpa", [9.8, 0.91, -0.16]), 3, -1e6, 1e6, False)
    if law == "yeoh" and yc[0] <= 0:
        raise SceneError(f"membrane.yeoh_c_kpa[0] = {yc[0]:g}: must be > 0 (C1 is half the shear modulus)")
    bulk_ratio = t.number("bulk_ratio", 1000.0, 1.0, 1e5)
    p_res = t.number("reservoir_pressure_pa", 0.0, -1e4, 1e5)
    closed = t.choice("chamber", "open", ("open", "closed"))
    rim_vertices = t.integer("rim_vertices", MEMBRANE_RIM_VERTICES[preset], *MEMBRANE_RIM_RANGE)
    volumetric = t.choice("volumetric", "pointwise", ("pointwise", "mean_dilatation"))
    moulding = t.choice("moulding", "cap", MOULDINGS)
    if moulding == "flat" and (chamber.base_radius_y is not None or chamber.outline):
        raise SceneError("membrane.moulding = 'flat': only for a round dome (chamber.base_radius_y_mm makes an elongated pad, "
                         "moulded as its cap)")
    element = t.choice("element", "wedge15", MEMBRANE_ELEMENTS)
    if element == "wedge15" and volumetric != "pointwise":
        raise SceneError(f"membrane.volumetric = {volumetric!r}: only 'pointwise' with membrane.element = 'wedge15' "
                         "(the default; its volumetric form is its own): give element = \"p2_tet\" for the tetrahedra's")
    layers = t.integer("layers", MEMBRANE_LAYERS[element], 1, MEMBRANE_MAX_LAYERS)
    warn_coarse_membrane(rim_vertices, element)
    t.finish()

    target = _target(data.get("target", {}), base_r)

    return Scene(
        name=name,
        chamber=chamber,
        electrodes=ElectrodeRing(count, ring * MM, diam * MM, gdiam * MM, z, zg, zf, first, discs, reference, on_membrane, patch,
                                 face_z),
        saline=Saline(sigma),
        drive=Drive(current * 1e-6, freqs, skip, measure, stim, meas),
        noise=Noise(snr, seed, drift, rate),
        mesh=MeshSpec(preset, max_edge * MM, refine, zone * MM, grading, element_order, update, rim, dome_rim),
        membrane=Membrane(law, mu * 1e3, tuple(c * 1e3 for c in yc), bulk_ratio, layers, p_res, closed, rim_vertices, volumetric, moulding, element),
        target=target,
        reconstruction=_reconstruction(data.get("reconstruction", {}), base_r, height, thick, chamber),
        palpation=_palpation(data.get("palpation", {}), base_r, height, thick, zf is not None, chamber),
        dataset=_dataset(data.get("dataset", {}), short, height, float(np.max(np.hypot(*centres[:-1].T))), gap, edge, zone),
    )


def _user_chamber(t: "_Table", surface: Any) -> tuple[Chamber, float, float, float]:
    """[chamber] from a user's surface file: (the chamber with its outline, its largest rim
    distance from the axis, that again, its height), lengths in mm."""
    if not isinstance(surface, str):
        raise SceneError(f"chamber.surface_file = {surface!r}: must be the path of a surface file")
    for k in CAP_KEYS:
        if k in t.data:
            raise SceneError(f"chamber.{k}: with chamber.surface_file the surface sizes the chamber; give one or the other")
    unit = t.number("surface_unit_mm", 1.0, 1e-6, 1e6, lo_open=True)
    if not Path(surface).is_file():
        raise SceneError(f"chamber.surface_file = {surface!r}: no such file")
    sf = read_surface(surface, unit * MM)
    rim = sf.vertices[sf.rim, :2]
    height = float(sf.vertices[:, 2].max()) / MM
    if not in_polygon(np.zeros((1, 2)), rim)[0]:
        raise SceneError(f"chamber.surface_file = {surface!r}: the axis (x = y = 0) must lie inside the base")
    base_r = float(np.hypot(*rim.T).max()) / MM
    chamber = Chamber(base_r * MM, height * MM, 0.0, None, str(surface), sf.sha256, unit * MM, tuple(map(tuple, rim.tolist())))
    return chamber, base_r, base_r, height


def _outline(chamber: Chamber) -> str:
    """The base's outline in words, mm."""
    if chamber.outline:
        return "the surface file's rim"
    if chamber.base_radius_y is None:
        return f"radius {chamber.base_radius / MM:g} mm about the axis"
    return f"an ellipse of semi-axes {chamber.base_radius / MM:g} x {chamber.base_radius_y / MM:g} mm"


def _sphere_radius(t: "_Table", radius_key: str, diameter_key: str, default: float, base_r: float) -> float:
    """A sphere's radius (mm) given by ``radius_key`` or ``diameter_key`` (one of them) in
    ``t``: a radius in (0, 5 base radii], a diameter in (0, 10]; ``default`` radius otherwise."""
    if radius_key in t.data and diameter_key in t.data:
        raise SceneError(f"[{t.name}]: give {radius_key} or {diameter_key}, not both")
    if diameter_key in t.data:
        return t.number(diameter_key, 2 * default, 0.0, 10 * base_r, lo_open=True) / 2
    return t.number(radius_key, default, 0.0, 5 * base_r, lo_open=True)


def _target(data: dict[str, Any], base_r: float) -> Target:
    t = _Table(data, "target")
    radius = _sphere_radius(t, "radius_mm", "diameter_mm", 7.5, base_r)
    kind = t.choice("kind", "rigid", ("rigid", "soft"))
    friction = t.number("friction", 0.0, 0.0, 2.0)
    # soft targets: Sylgard 184 ~0.6-3 MPa, tumour-like inclusions ~10-100 kPa (DESIGN.md)
    modulus = t.number("youngs_modulus_kpa", 1500.0, 0.0, 1e6, lo_open=True)
    poisson = t.number("poisson_ratio", 0.49, 0.0, 0.5, hi_open=True)
    if kind == "soft" and friction != 0.0:
        raise SceneError(f"target.friction = {friction:g}: must be 0 for a soft target (friction against a soft target is not modelled)")
    t.finish()
    return Target(radius * MM, kind, friction, modulus * 1e3, poisson)


def shipped_scenes() -> list[str]:
    """The names of the scenes shipped with jointsim (``extends = "paper_sensor"`` takes one)."""
    return sorted(p.stem for p in SCENES_DIR.glob("*.toml"))


def scene_data(path: str | Path, _chain: tuple[Path, ...] = ()) -> dict[str, Any]:
    """The parsed TOML mapping of a scene file, with ``extends = "other.toml"`` (a path
    relative to the file, or a shipped scene's name: :func:`shipped_scenes`) resolved: the
    other scene's mapping, each of this file's sections updated key by key over it (so a study
    scene states only what it changes)."""
    path = Path(path)
    if not path.is_file():
        raise SceneError(f"scene file not found: {path}")
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError:
        raise SceneError(f"{path}: not a UTF-8 text file (a scene is TOML text)") from None
    except tomllib.TOMLDecodeError as e:
        raise SceneError(f"{path}: not valid TOML: {e}") from None
    base = data.pop("extends", None)
    data = _moved_keys(data)
    drive = data.get("drive")
    if isinstance(drive, dict) and "patterns_file" in drive:
        data["drive"] = _patterns_from_file(drive, path)
    chamber = data.get("chamber")
    if isinstance(chamber, dict) and isinstance(chamber.get("surface_file"), str):
        data["chamber"] = {**chamber, "surface_file": str((path.parent / chamber["surface_file"]).resolve())}
    if base is None:
        return data
    if not isinstance(base, str):
        raise SceneError(f"{path}: extends = {base!r}: must be the path of another scene file or a shipped scene's name")
    if base in shipped_scenes():
        base_path = SCENES_DIR / f"{base}.toml"
    else:
        base_path = (path.parent / base).resolve()
    if base_path in _chain or base_path == path.resolve():
        raise SceneError(f"{path}: extends = {base!r}: scenes extend each other in a cycle")
    merged = scene_data(base_path, _chain + (path.resolve(),))
    merged.pop("description", None)
    for key, value in data.items():
        if isinstance(value, dict) and isinstance(merged.get(key), dict):
            # a size given by radius here replaces the base's by diameter, and the other way round
            drop = {b for pair in SIZE_ALIASES for a, b in (pair, pair[::-1]) if a in value}
            if key == "electrodes" and any(g in value for g in LAYOUT_GENERATORS):
                drop |= set(RING_KEYS)  # a layout given as data replaces the other scene's ring
            if key == "drive" and any(k in value for k in PATTERN_KEYS):
                drop |= {"skip", "measure"}  # and a protocol as data the other's skip-N
            if key == "chamber" and "surface_file" in value:
                drop |= set(CAP_KEYS)  # a user's surface sizes the chamber itself
            merged[key] = {**{k: v for k, v in merged[key].items() if k not in drop}, **value}
        else:
            merged[key] = value
    return merged


def scene_toml(path: str | Path) -> str:
    """A scene file's text with ``extends`` resolved (the file itself when it extends
    nothing): self-contained, for the provenance of what a run computed."""
    path = Path(path)
    data = scene_data(path)  # checks the file (and what it extends) first
    text = path.read_text()
    if "extends" not in tomllib.loads(text):
        return text
    return f"# {path.name} with its extends resolved\n" + _toml(data)


def _toml(data: dict[str, Any]) -> str:
    """TOML text of a scene mapping (top-level scalars, then one table per section, its arrays
    of tables, such as [[electrodes.ring]], after its keys)."""
    def value(v: Any) -> str:
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, (int, float)):
            return repr(v)
        if isinstance(v, str):
            return json.dumps(v)  # a JSON string is a TOML basic string
        if isinstance(v, list):
            return "[" + ", ".join(value(x) for x in v) + "]"
        raise SceneError(f"scene value {v!r}: not representable in a scene file")

    def tables(v: Any) -> bool:
        return isinstance(v, list) and bool(v) and all(isinstance(x, dict) for x in v)

    lines = [f"{k} = {value(v)}" for k, v in data.items() if not isinstance(v, dict)]
    for k, v in data.items():
        if isinstance(v, dict):
            lines += ["", f"[{k}]"] + [f"{kk} = {value(vv)}" for kk, vv in v.items() if not tables(vv)]
            for kk, vv in v.items():
                if tables(vv):
                    for t in vv:
                        lines += ["", f"[[{k}.{kk}]]"] + [f"{a} = {value(b)}" for a, b in t.items()]
    return "\n".join(lines) + "\n"


# the sections a scene file must describe, itself or through what it extends: the sensor
SENSOR_SECTIONS = ("chamber", "electrodes")


def parameter_table(paths: Sequence[str | Path] | None = None) -> list[dict[str, Any]]:
    """Every key the parse of the scenes at ``paths`` (default: the shipped ones) reads, once
    each in the order first read: section, key, kind (number, integer, choice, value), its
    default and what is allowed. Generated from the parse itself, so the scene reference
    (the documentation's) cannot drift from the code. A key only some scenes reach (an
    electrode generator's, a soft target's) is there when one of them does."""
    global _READS
    if paths is None:  # the paper's sensor first: its reads set the order
        paths = sorted(SCENES_DIR.glob("*.toml"), key=lambda p: (p.stem != "paper_sensor", p.stem))
    rows: dict[tuple[str, str], dict[str, Any]] = {}
    _READS = []
    try:
        for p in paths:
            load_scene(p)
            for r in _READS:
                section = re.sub(r"\[\d+\]$", "", r["section"])  # one row per generator key, not per table
                rows.setdefault((section, r["key"]), {**r, "section": section})
            _READS.clear()
    finally:
        _READS = None
    return list(rows.values())


def load_scene(path: str | Path) -> Scene:
    """Read and validate a TOML scene file (``extends`` resolved: :func:`scene_data`). It must
    describe the sensor (``SENSOR_SECTIONS``), itself or through a scene it extends; the other
    sections default to the paper's values (see ``scenes/paper_sensor.toml``)."""
    path = Path(path)
    data = scene_data(path)
    scene = scene_from_dict(data, name=path.stem)
    missing = [f"[{k}]" for k in SENSOR_SECTIONS if k not in data]
    if missing:
        raise SceneError(f"{path}: no {' or '.join(missing)} section: the file does not describe a sensor; give "
                         f"{' and '.join(missing)}, or start it with extends = \"paper_sensor\" (shipped: {', '.join(shipped_scenes())})")
    return scene


# --------------------------------------------------------------------------------------------
# [palpation]: the virtual palpation experiment (jointsim.palpation, `jointsim palpate`)

PALPATION_MODES = ("position", "force", "compliant")
MESH_UPDATES = ("auto", "morph", "remesh")
LAMBDA_METHODS = ("kfold", "loo", "gcv", "lcurve")
IMAGE_PRIORS = ("tikhonov", "noser", "laplacian", "depth", "tv")  # as jointsim.reconstruction.tikhonov.PRIORS (tested)


# --------------------------------------------------------------------------------------------
# [reconstruction]: the instrument's image (jointsim.instrument)


@dataclass(frozen=True)
class ReconstructionSpec:
    """The instrument's reconstruction (SI): Tikhonov images on ``cells`` voxels of the
    reference chamber with the ``prior`` (zeroth order "tikhonov", the paper's; "noser";
    "laplacian"; "depth", cells near the base weighted up by ((z + z₀)/H)^−``depth_exponent``;
    "tv", total variation from the Laplacian's image, its own λ by the discrepancy principle:
    jointsim.reconstruction.tikhonov.PRIORS), λ chosen once by ``lambda_method`` cross-validation on the noisy
    δV of a representative press: a geometric indentation of the untouched sensor by a sphere
    of ``lambda_radius`` m, ``lambda_depth`` m past first contact, at ``lambda_xy`` (m). Every
    job on the sensor (palpation, datasets, ``forward``) images with it, as a real instrument
    calibrated once would."""

    cells: int = 7000
    lambda_method: str = "kfold"
    lambda_radius: float = 7.5 * MM
    lambda_depth: float = 3 * MM
    lambda_xy: tuple[float, float] = (0.0, 0.0)
    prior: str = "tikhonov"
    depth_exponent: float = 2.0


def _reconstruction(data: dict[str, Any], base_r: float, height: float, thick: float, chamber: Chamber = Chamber()) -> ReconstructionSpec:
    """Parse [reconstruction] (units in the key names); the sensor's lengths in mm."""
    t = _Table(data, "reconstruction")
    cells = t.integer("cells", 7000, 100, 200_000)
    lam = t.choice("lambda_method", "kfold", LAMBDA_METHODS)
    prior = t.choice("prior", "tikhonov", IMAGE_PRIORS)
    exponent = t.number("depth_exponent", 2.0, 0.0, 8.0)  # the "depth" prior's (results/image_priors.md)
    if exponent != 2.0 and prior != "depth":
        raise SceneError(f"reconstruction.depth_exponent = {exponent:g}: only for prior = \"depth\"")
    radius = _sphere_radius(t, "lambda_target_radius_mm", "lambda_target_diameter_mm", 7.5, base_r)
    depth = t.number("lambda_depth_mm", min(3.0, height / 2), 0.0, height + thick, lo_open=True)
    xy = _number_list("reconstruction.lambda_xy_mm", t.raw("lambda_xy_mm", [0.0, 0.0]), 2, -base_r, base_r, True)
    if not chamber.inside(np.array(xy) * MM, 1e-12)[0]:
        raise SceneError(f"reconstruction.lambda_xy_mm = {list(xy)}: must lie within the base ({_outline(chamber)})")
    t.finish()
    return ReconstructionSpec(cells, lam, radius * MM, depth * MM, (xy[0] * MM, xy[1] * MM), prior, exponent)


# keys that moved to another section: (old section, key) -> (new section, key). Scenes written
# before still load (with a warning); given in both places they must agree
MOVED_KEYS: dict[tuple[str, str], tuple[str, str]] = {
    ("palpation", "cells"): ("reconstruction", "cells"),
    ("palpation", "lambda_method"): ("reconstruction", "lambda_method"),
    ("palpation", "mesh_update"): ("mesh", "update"),
}


# keys that give one size two ways (a section takes one of each pair)
SIZE_ALIASES = (("radius_mm", "diameter_mm"), ("target_radii_mm", "target_diameters_mm"),
                ("lambda_target_radius_mm", "lambda_target_diameter_mm"))


def _moved_keys(data: dict[str, Any]) -> dict[str, Any]:
    """``data`` with the keys of :data:`MOVED_KEYS` at their new place (a warning names them)."""
    moved = []
    for (s0, k0), (s1, k1) in MOVED_KEYS.items():
        old = data.get(s0)
        if not isinstance(old, dict) or k0 not in old:
            continue
        new = data.get(s1, {})
        if not isinstance(new, dict):
            continue  # the new section's parser names the error
        if k1 in new and new[k1] != old[k0]:
            raise SceneError(f"{s0}.{k0} = {old[k0]!r} and {s1}.{k1} = {new[k1]!r}: the key moved to {s1}.{k1}; give it there only")
        data[s0] = {k: v for k, v in old.items() if k != k0}
        data[s1] = {**new, k1: old[k0]}
        moved.append(f"{s0}.{k0} -> {s1}.{k1}")
    if moved:
        warnings.warn(f"scene keys moved: {', '.join(moved)} (read from the old place; write them at the new)", UserWarning, stacklevel=3)
    return data


@dataclass(frozen=True)
class PalpationSpec:
    """The palpation program (SI): targets of ``target_radii`` (m) pressed one after the other
    at ``xy`` (m) by the bench rig in ``mode`` "position" (the stage goes from ``gap`` above
    first contact to ``depth`` past it at ``speed`` m/s, holds ``hold`` s, retracts), "force"
    (the press force ramps to ``force`` N in ``force_ramp`` s, holds ``hold`` s, ramps back)
    or "compliant" (the position program through the probe spring ``probe_stiffness`` N/m,
    ``probe_damping`` N s/m; None keeps the rig's). The reference ("steady state") is the mean
    of ``reference_frames`` noisy frames of the untouched sensor; ``fdm_contact_impedance``
    runs each injection at its own FDM carrier with that carrier's contact impedances. The image
    is the instrument's ([reconstruction]); the chamber mesh follows the membrane by
    ``[mesh] update``."""

    mode: str = "position"
    target_radii: tuple[float, ...] = (4 * MM, 7.5 * MM, 15 * MM)
    depth: float = 3 * MM
    speed: float = 25 * MM
    hold: float = 0.5
    gap: float = 0.0
    xy: tuple[float, float] = (0.0, 0.0)
    force: float = 0.05
    force_ramp: float = 0.2
    probe_stiffness: float | None = None
    probe_damping: float | None = None
    reference_frames: int = 50
    fdm_contact_impedance: bool = False


def _palpation(data: dict[str, Any], base_r: float, height: float, thick: float, has_zf: bool, chamber: Chamber = Chamber()) -> PalpationSpec:
    """Parse [palpation] (mm, s, N in the key names); ``base_r``, ``height``, ``thick`` in mm;
    ``has_zf``: the scene gives per-carrier contact impedances."""
    t = _Table(data, "palpation")
    mode = t.choice("mode", "position", PALPATION_MODES)
    has_r, has_d = "target_radii_mm" in data, "target_diameters_mm" in data
    if has_r and has_d:
        raise SceneError("[palpation]: give target_radii_mm or target_diameters_mm, not both")
    if has_r:
        radii = _number_list("palpation.target_radii_mm", t.raw("target_radii_mm", None), None, 0.0, 5 * base_r, True)
    else:
        diam = _number_list("palpation.target_diameters_mm", t.raw("target_diameters_mm", [8.0, 15.0, 30.0]), None, 0.0, 10 * base_r, True)
        radii = tuple(d / 2 for d in diam)
    if not radii:
        raise SceneError("palpation.target_diameters_mm: must list at least one target")
    # past first contact at the apex, the sphere's lowest point reaches the base's membrane
    # thickness (what the mechanics can take: MembraneModel.press) after the dome's height
    depth = t.number("depth_mm", 3.0, 0.0, height)
    if mode != "force" and depth == 0:
        raise SceneError(f"palpation.depth_mm = 0: must be in (0, {height:g}] in {mode} mode")
    speed = t.number("speed_mm_per_s", 25.0, 0.0, 1000.0, lo_open=True)
    hold = t.number("hold_s", 0.5, 0.0, 60.0)
    gap = t.number("gap_mm", 0.0, 0.0, 50.0)
    xy = _number_list("palpation.xy_mm", t.raw("xy_mm", [0.0, 0.0]), 2, -base_r, base_r, True)
    if not chamber.inside(np.array(xy) * MM, 1e-12)[0]:
        raise SceneError(f"palpation.xy_mm = {list(xy)}: must lie within the base ({_outline(chamber)})")
    force = t.number("force_n", 0.05, 0.0, 10.0, lo_open=True)
    ramp = t.number("force_ramp_s", 0.2, 0.0, 60.0)
    k = t.raw("probe_stiffness_n_per_m", None)
    c = t.raw("probe_damping_ns_per_m", None)
    k = None if k is None else _check_number("palpation.probe_stiffness_n_per_m", k, 0.0, 1e6, True, False)
    c = None if c is None else _check_number("palpation.probe_damping_ns_per_m", c, 0.0, 1e4, True, False)
    n_ref = t.integer("reference_frames", 50, 1, 100_000)
    fdm = t.raw("fdm_contact_impedance", False)
    if not isinstance(fdm, bool):
        raise SceneError(f"palpation.fdm_contact_impedance = {fdm!r}: must be true or false")
    if fdm and not has_zf:
        raise SceneError("palpation.fdm_contact_impedance = true: needs electrodes.contact_impedance_by_freq_ohm_m2 (one row per carrier)")
    t.finish()
    return PalpationSpec(
        mode, tuple(r * MM for r in radii), depth * MM, speed * MM, hold, gap * MM, (xy[0] * MM, xy[1] * MM),
        force, ramp, k, c, n_ref, fdm,
    )


# --------------------------------------------------------------------------------------------
# [dataset]: synthetic labelled samples (jointsim.dataset, `jointsim dataset`)


DATASET_CONTROLS = ("depth", "force")
# mm: contact points are drawn at least this far inside the base's rim: the smooth outer surface
# about a point is fitted to the nodes within 3 mm of it (mechanics.touch.FIT_RADIUS)
DATASET_RIM_MM = 3.0


@dataclass(frozen=True)
class DatasetSpec:
    """What ``jointsim dataset`` samples (SI). Each press trajectory ("group") draws a target
    sphere ``radius`` (m, uniform in the range), a contact point (where it first touches the
    membrane, the target's centre solved from it) uniform over the disc of radius ``r_max`` (m)
    about the axis, and the domain randomisation: ``membrane_scale``
    (multiplier of the membrane moduli, log-uniform), saline ``conductivity`` (S/m, uniform),
    ``contact_impedance`` (Ω·m², log-uniform, every electrode), an in-plane offset of each
    ring electrode uniform over a disc of radius ``electrode_jitter`` (m), ``snr_db``
    (uniform), and the target: rigid with probability ``rigid_fraction``, else soft with
    Young's modulus ``target_modulus`` (Pa, log-uniform). The target is pressed in steps of at
    most ``step`` (m) and ``samples_per_press`` samples are taken at depths past first contact
    stratified over ``depth`` (m): one in each of as many equal slices of the range (of the
    part of it the dome allows at that point, where the sphere would otherwise come within a
    membrane thickness of the base). The
    steady-state reference is the mean of ``reference_frames`` noisy frames; ``images`` stores
    each reconstructed image. ``control`` "force" takes the samples at contact forces (N, along
    z) stratified over ``force`` instead, the target lowered until each is reached; the depth
    reached is the label then."""

    radius: tuple[float, float] = (4 * MM, 15 * MM)
    r_max: float = 15 * MM
    depth: tuple[float, float] = (0.5 * MM, 3 * MM)
    samples_per_press: int = 6
    step: float = 0.5 * MM
    membrane_scale: tuple[float, float] = (0.5, 2.0)
    conductivity: tuple[float, float] = (0.35, 0.39)
    contact_impedance: tuple[float, float] = (5e-4, 2e-3)
    electrode_jitter: float = 0.1 * MM
    snr_db: tuple[float, float] = (40.0, 80.0)
    rigid_fraction: float = 1.0
    target_modulus: tuple[float, float] = (10e3, 3e6)
    reference_frames: int = 50
    images: bool = False
    control: str = "depth"
    force: tuple[float, float] = (5e-3, 50e-3)


def _range(t: _Table, k: str, default: tuple[float, float], lo: float, hi: float, *, lo_open: bool = False) -> tuple[float, float]:
    """A [min, max] pair (or one number: min = max) within [lo, hi], min ≤ max."""
    v = t.raw(k, list(default))
    key = t.key(k)
    rng = f"{'(' if lo_open else '['}{lo:g}, {hi:g}]"
    if isinstance(v, (int, float)) and not isinstance(v, bool):
        v = [v, v]
    if not isinstance(v, list) or len(v) != 2:
        raise SceneError(f"{key} = {v!r}: must be [min, max] with both in {rng}")
    a, b = (_check_number(f"{key}[{i}]", x, lo, hi, lo_open, False) for i, x in enumerate(v))
    if a > b:
        raise SceneError(f"{key} = [{a:g}, {b:g}]: min must not exceed max (both in {rng})")
    return a, b


def _dataset(data: dict[str, Any], base_r: float, height: float, ring: float, gap: float, edge: float, zone: float) -> DatasetSpec:
    """Parse [dataset] (units in the key names); lengths of the sensor in mm: ``ring`` the
    outermost driven electrode's distance from the axis, ``gap`` the smallest edge-to-edge
    distance between electrodes, ``edge`` the least room between an electrode and the rim
    (beyond the clearance every layout keeps)."""
    t = _Table(data, "dataset")
    d = DatasetSpec()
    has_r, has_d = "radius_mm" in data, "diameter_mm" in data
    if has_r and has_d:
        raise SceneError("[dataset]: give radius_mm or diameter_mm, not both")
    if has_d:
        radius = tuple(x / 2 for x in _range(t, "diameter_mm", (8.0, 30.0), 0.0, 10 * base_r, lo_open=True))
    else:
        radius = _range(t, "radius_mm", (4.0, 15.0), 0.0, 5 * base_r, lo_open=True)
    # contact points stay DATASET_RIM_MM inside the rim, where the dome's top meets its clamp
    r_max = t.number("r_max_mm", min(15.0, ring), 0.0, base_r - DATASET_RIM_MM)
    # the membrane's inner surface reaches the base (and the electrodes) at about the dome height
    depth = _range(t, "depth_mm", (0.5, 3.0), 0.0, 0.9 * height, lo_open=True)
    k = t.integer("samples_per_press", d.samples_per_press, 1, 1000)
    step = t.number("step_mm", 0.5, 0.0, 5.0, lo_open=True)
    scale = _range(t, "membrane_scale", d.membrane_scale, 0.05, 20.0)
    sigma = _range(t, "conductivity_s_per_m", d.conductivity, 0.0, 100.0, lo_open=True)
    z = _range(t, "contact_impedance_ohm_m2", d.contact_impedance, 0.0, 1.0, lo_open=True)
    # a jittered disc stays inside the refined zone of the mesh, clear of its neighbours and
    # inside the base (the layout keeps every disc EDGE_CLEARANCE_MM inside the rim)
    jit_hi = max(0.0, min(zone, gap / 2, edge))
    jitter = t.number("electrode_jitter_mm", min(0.1, jit_hi), 0.0, jit_hi)
    snr = _range(t, "snr_db", d.snr_db, *SNR_RANGE_DB)
    rigid = t.number("rigid_fraction", 1.0, 0.0, 1.0)
    modulus = _range(t, "target_modulus_kpa", (10.0, 3000.0), 0.0, 1e8, lo_open=True)
    n_ref = t.integer("reference_frames", 50, 1, 100_000)
    images = t.raw("images", False)
    if not isinstance(images, bool):
        raise SceneError(f"dataset.images = {images!r}: must be true or false")
    control = t.choice("control", "depth", DATASET_CONTROLS)
    force = _range(t, "force_n", d.force, 0.0, 100.0, lo_open=True)
    t.finish()
    return DatasetSpec(
        (radius[0] * MM, radius[1] * MM), r_max * MM, (depth[0] * MM, depth[1] * MM), k, step * MM, scale, sigma, z,
        jitter * MM, snr, rigid, (modulus[0] * 1e3, modulus[1] * 1e3), n_ref, images, control, force,
    )
