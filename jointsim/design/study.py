"""The design study: for each sensor design (a scene), the Cramér–Rao bounds of a target's
position, depth and size over a grid of presses, and the tables that compare designs.

A design's presses are spheres of the plan's diameters coming down at the target centres of a
polar grid out to ``r_max`` (default: the outermost electrode's centre), each pressed through
the plan's depths past first contact. Each press's derivatives (:mod:`.sensitivity`) are
reduced to its information matrices (JᵀJ per depth and of the reference, at unit noise) and
stored, one record per press, in a resumable store (:mod:`jointsim.io.store`), so the bounds
at any SNR, frame count or prior are recomputed from the file without the simulator. A press
the mechanics cannot take (a large sphere far out) is stored as not ``reached``.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Callable

import numpy as np

from .._cores import available_cores, run_local
from ..geometry import electrode_layout
from ..instrument import Instrument
from ..io.records import Records, open_records
from ..io.schema import Field, Schema
from ..io.store import attach, exclusive, open_store
from ..mechanics.build import membrane_from_scene
from ..mechanics.dome import UnreachablePose
from ..mechanics.newton import NewtonError
from ..mechanics.soft_target import GENERIC_TURN
from ..mesh.morph import MeshInversionError
from ..scene import Scene
from .bounds import Bounds, fisher, joint_bounds, median_error, nuisance_prior, press_bounds, press_fisher
from .sensitivity import (ELECTRODE_STEP, contact_membrane, electrode_moves, head_moves, parameter_names, press_electrical,
                          press_mechanics, TARGET_MODULUS, target_names, unrefinable)

__all__ = ["Plan", "press_grid", "press_symmetries", "PressLayout", "press_layout", "orbits", "plan_presses", "press_groups", "design_schema", "run_design", "DesignBounds", "design_bounds",
           "press_joint_bounds"]

SCHEMA_NAME, SCHEMA_VERSION = "design_sensitivity", 1
MAX_CONTACT_LEVELS = 4  # each level has about 4x the faces in the zone: 4 is ~16x a 64-rim pitch


@dataclass(frozen=True)
class Plan:
    """The presses of a design study: sphere ``diameters`` m, ``depths`` m past first contact,
    target centres on a polar grid of ``spacing`` m out to ``r_max`` m (None: the outermost
    electrode's centre); the noise model: ``reference_frames`` averaged into the reference,
    ``hold_frames`` into a press's frame; ``contact_levels``: each press read through a
    membrane that many times finer about its contact (:func:`~.sensitivity.contact_membrane`;
    0: the scene's membrane as meshed); ``target_moduli`` Pa: soft (neo-Hookean) spheres of
    each of these Young's moduli, whose modulus is then a target parameter too (none: rigid
    spheres); ``ray``: the target centres along the +x axis, ``spacing`` apart, instead of
    the polar grid (a survey of costly presses, the soft ones); ``symmetric``: each ring of the
    grid has a multiple of the design's order of symmetry of points, and only one press of each
    set the sensor's symmetries map onto each other is computed (:func:`press_layout`; False:
    every centre of the plain grid is pressed); ``ring_mechanics``: the presses of one target on
    one ring of the grid share one mechanical solve, at the ring's first centre, turned about
    the axis to each (:meth:`~.sensitivity.PressMechanics.turned`: a round cap's mechanics know
    no direction, so each is read through the refined membrane turned with it), and only the
    measurement is computed per centre (only with ``contact_levels``; False: each centre's
    membrane refined about it and solved); ``graded_target``: each soft sphere meshed graded,
    its cells uniform over the refined contact zone
    (:func:`~jointsim.mechanics.soft_target.graded_hemisphere_mesh`; it applies only with
    ``target_moduli`` and ``contact_levels`` and is False otherwise; False: in layers, whose
    cells grow 3-4x from its lowest point to the contact's edge, coarser there than the refined
    membrane, which made the soft study's size and modulus bounds optimistic)."""

    diameters: tuple[float, ...] = (8e-3, 15e-3, 30e-3)
    depths: tuple[float, ...] = (1e-3, 2e-3, 3e-3)
    spacing: float = 6e-3
    r_max: float | None = None
    reference_frames: int = 50
    hold_frames: int = 1
    contact_levels: int = 0
    target_moduli: tuple[float, ...] = ()
    ray: bool = False
    symmetric: bool = True
    ring_mechanics: bool = True
    graded_target: bool = True

    def __post_init__(self) -> None:
        if not self.diameters or any(not d > 0 for d in self.diameters):
            raise ValueError(f"diameters = {self.diameters}: one or more, each > 0 m")
        if not self.depths or any(not d > 0 for d in self.depths) or list(self.depths) != sorted(set(self.depths)):
            raise ValueError(f"depths = {self.depths}: one or more, increasing, each > 0 m")
        if not self.spacing > 0:
            raise ValueError(f"spacing = {self.spacing}: must be > 0 m")
        if self.reference_frames < 1 or self.hold_frames < 1:
            raise ValueError("reference_frames, hold_frames: must be >= 1")
        if not 0 <= self.contact_levels <= MAX_CONTACT_LEVELS:
            raise ValueError(f"contact_levels = {self.contact_levels}: must be in 0..{MAX_CONTACT_LEVELS}")
        if any(not (math.isfinite(e) and e > 0) for e in self.target_moduli):
            raise ValueError(f"target_moduli = {self.target_moduli}: each > 0 Pa")
        if not (self.target_moduli and self.contact_levels):  # no soft sphere, or none read at its contact
            object.__setattr__(self, "graded_target", False)
        if self.ray:  # one centre per ring: no two are images of each other
            object.__setattr__(self, "symmetric", False)
        if self.ray or not self.contact_levels:  # one centre per ring; the scene's own membrane is not turned
            object.__setattr__(self, "ring_mechanics", False)

    def outer_radius(self, scene: Scene) -> float:
        if self.r_max is not None:
            return self.r_max
        return float(np.hypot(*electrode_layout(scene).centres[:, :2].T).max())


def press_grid(r_max: float, spacing: float, ray: bool = False, order: int = 1) -> np.ndarray:
    """Target centres (n, 2) m: the axis and rings i·``spacing`` ≤ ``r_max``, each with the
    multiple of ``order`` nearest 2π r / ``spacing`` points (about ``spacing`` apart; at least
    6, or ``order``), alternate rings turned by half a pitch; or with ``ray`` one point per
    ring, on the +x axis. A ring of k·``order`` points at a pitch offset of 0 or ½ is mapped onto
    itself by the turns by 360°/``order`` and the mirrors in lines at multiples of
    180°/``order`` (from the x axis)."""
    rings = int(math.floor(r_max / spacing + 1e-9))
    if ray:
        r = spacing * np.arange(rings + 1)
        return np.column_stack([r, np.zeros_like(r)])
    pts = [np.zeros((1, 2))]
    for i in range(1, rings + 1):
        r = i * spacing
        n = order * max(math.ceil(6 / order), round(2 * math.pi * r / (spacing * order)))
        a = 2 * math.pi * (np.arange(n) + 0.5 * (i % 2)) / n
        pts.append(r * np.column_stack([np.cos(a), np.sin(a)]))
    return np.vstack(pts)


def press_symmetries(scene: Scene) -> list[np.ndarray]:
    """The 2 × 2 matrices of the isometries of ``scene``'s ideal sensor (its chamber's outline
    and electrodes: :func:`~jointsim.geometry.isometries`) that map its protocol onto itself,
    each injection and measurement up to its sign. A press moved by one reads the same channels,
    permuted and signed, with the electrodes' nuisances permuted, whose priors are the same for
    every electrode (:func:`~.bounds.nuisance_prior`): its bounds on position (RMS and median of
    the contact point's error, which turn with it), depth, size and modulus are those of the
    press it came from. A real chamber's mesh is not symmetric: pressed directly, a moved press
    differs by the mesh's asymmetry (tests/test_design.py measures it)."""
    from ..eit.protocol import Protocol, invariant, scene_protocol
    from ..geometry import isometries

    floating = not scene.electrodes.reference
    protocol = scene_protocol(scene)
    if floating:  # the patterns over every electrode: the solver's reference's column put back
        protocol = Protocol(np.column_stack([protocol.stim, -protocol.stim.sum(axis=1)]),
                            np.concatenate([protocol.meas, -protocol.meas.sum(axis=2, keepdims=True)], axis=2))
    out = []
    for m, P in isometries(electrode_layout(scene), scene.chamber, keep_reference=not floating).values():
        if invariant(protocol, P if floating else P[: protocol.n_el]):  # a kept reference is last
            out.append(m)
    return out


@dataclass(frozen=True)
class PressLayout:
    """Where a study presses: the target centres ``grid`` (n, 2) m, those ``computed`` (m,)
    (indices into ``grid``), and for each centre j the computed press it is an image of,
    ``source[j]`` (an index into ``computed``), and the isometry ``moves[j]`` (2, 2) with
    grid[j] = moves[j] @ grid[computed[source[j]]]."""

    grid: np.ndarray
    computed: np.ndarray
    source: np.ndarray
    moves: np.ndarray


def press_layout(scene: Scene, plan: Plan) -> PressLayout:
    """The :class:`PressLayout` of ``plan`` on ``scene``: the polar grid (:func:`press_grid`),
    with ``plan.symmetric`` of the largest order ≤ 6 (a ring's fewest points, so the rings stay
    about ``spacing`` apart) that divides the design's (its finest turn among
    :func:`press_symmetries`), reduced to one centre per orbit of those symmetries."""
    mats = press_symmetries(scene) if plan.symmetric else []
    turns = [abs(math.atan2(m[1, 0], m[0, 0])) for m in mats if np.linalg.det(m) > 0]
    k = max((round(2 * math.pi / t) for t in turns if t > 1e-9), default=1)
    order = max(q for q in range(1, 7) if k % q == 0)
    r_max = plan.outer_radius(scene)
    return orbits(press_grid(r_max, plan.spacing, plan.ray, order), mats, 1e-9 * max(r_max, plan.spacing))


def orbits(points: np.ndarray, moves: list[np.ndarray], tol: float) -> PressLayout:
    """``points`` (n, 2) split into the orbits of the group the matrices ``moves`` generate,
    as far as they map points onto points (within ``tol``): each orbit's first point computed,
    the others its images (:class:`PressLayout`)."""
    n = len(points)
    source, move = np.full(n, -1), np.zeros((n, 2, 2))
    computed: list[int] = []
    for j in range(n):
        if source[j] >= 0:
            continue
        source[j], move[j] = len(computed), np.eye(2)
        computed.append(j)
        todo = [j]
        while todo:  # every image of the orbit's points under each generator
            a = todo.pop()
            for m in moves:
                d = np.linalg.norm(points - m @ points[a], axis=1)
                k = int(np.argmin(d))
                if d[k] <= tol and source[k] < 0:
                    source[k], move[k] = source[j], m @ move[a]
                    todo.append(k)
    return PressLayout(np.asarray(points, float), np.asarray(computed, int), source, move)


def plan_presses(scene: Scene, plan: Plan) -> list[tuple[float, np.ndarray, float | None]]:
    """The study's presses in record order: (diameter m, centre xy (2,) m, the soft target's
    Young's modulus Pa or None for a rigid one), modulus-major, then diameter-major, then the
    computed centres of :func:`press_layout`."""
    lay = press_layout(scene, plan)
    xy = lay.grid[lay.computed]
    return [(float(d), p, e) for e in (plan.target_moduli or (None,)) for d in plan.diameters for p in xy]


def press_groups(scene: Scene, plan: Plan) -> list[list[int]]:
    """The study's presses (:func:`plan_presses` indices) in groups that share one mechanical
    solve: with ``plan.ring_mechanics`` one target's presses on one ring of the grid (the
    first of each group is solved, the others turned from it), else one press each."""
    presses = plan_presses(scene, plan)
    if not plan.ring_mechanics:
        return [[i] for i in range(len(presses))]
    tol = 1e-9 * max(plan.outer_radius(scene), plan.spacing)
    groups: dict[tuple, list[int]] = {}
    for i, (d, xy, e) in enumerate(presses):
        groups.setdefault((e, d, round(float(np.hypot(*xy)) / tol)), []).append(i)
    return list(groups.values())


def _turn(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The rotation (2, 2) about the axis that takes the in-plane point ``a`` to ``b`` (as far
    from the axis)."""
    t = math.atan2(b[1], b[0]) - math.atan2(a[1], a[0])
    return np.array([[math.cos(t), -math.sin(t)], [math.sin(t), math.cos(t)]])


def design_schema(n_meas: int, n_params: int, n_depths: int, soft: bool = False) -> Schema:
    K, P = n_depths, n_params
    t = len(target_names(soft))
    extra = (Field("target_modulus", (), "float64", "Pa", "the soft sphere's Young's modulus"),) if soft else ()
    return Schema(extra + (
        Field("diameter", (), "float64", "m", "the sphere's diameter"),
        Field("xy", (2,), "float64", "m", "the target's centre in the plane"),
        Field("reached", (), "int8", "", "1: pressed through every depth; 0: the mechanics could not take it (the rest NaN)"),
        Field("depths", (K,), "float64", "m", "past first contact"),
        Field("contact", (K, 3), "float64", "m", "the contact's centre of pressure"),
        Field("contact_jacobian", (K, 2, t), "float64", "m/m", "d(contact xy)/d(the target's parameters)"),
        Field("force", (K,), "float64", "N", "normal contact force"),
        Field("noise_std", (), "float64", "V", "one frame's noise per channel (the scene's SNR)"),
        Field("voltages", (K, n_meas), "float64", "V", "the press's clean voltages"),
        Field("target_jacobian", (K, n_meas, t), "float64", "V/m", "dV/d(the target's parameters: x, y, depth, radius[, ln E])"),
        Field("info", (K, P, P), "float64", "V²/unit²", "JᵀJ of each depth's frame (Fisher information × σ²)"),
        Field("info_ref", (P, P), "float64", "V²/unit²", "JᵀJ of the reference frame"),
        Field("seconds", (), "float64", "s", "wall time of the press", volatile=True),
    ), name=SCHEMA_NAME, version=SCHEMA_VERSION)


def _nan_record(schema: Schema, diameter: float, xy: np.ndarray, seconds: float, modulus: float | None) -> dict[str, Any]:
    rec = {f.name: np.full(f.shape, np.nan) for f in schema.fields}
    rec.update(diameter=diameter, xy=xy, reached=0, seconds=seconds)
    if modulus is not None:
        rec["target_modulus"] = modulus
    return rec


# --------------------------------------------------------------------------------------------
# Worker side

_WORKER: dict[str, Any] = {}
_LOCK = threading.Lock()


def _setup(scene: Scene) -> tuple[Instrument, list]:
    key = scene.digest()
    if _WORKER.get("key") != key:
        if "inst" in _WORKER:
            _WORKER.pop("inst").free()
        inst = Instrument.build(scene, imaging=False)
        _WORKER.clear()
        _WORKER.update(key=key, inst=inst, moves=electrode_moves(inst, ELECTRODE_STEP), models={})
    return _WORKER["inst"], _WORKER["moves"]


def _model(scene: Scene, inst: Instrument, radius: float, modulus: float | None):
    models = _WORKER["models"]
    if (radius, modulus) not in models:
        models.clear()  # one target at a time: the presses come modulus- then diameter-major
        rigid = replace(scene, target=replace(scene.target, kind="rigid"))
        models[radius, modulus] = membrane_from_scene(rigid, target_radius=radius, inflate_from=inst.inflated_u,
                                                      target_modulus=modulus, target_turn=GENERIC_TURN)
    return models[radius, modulus]


def _record(ps, xy: np.ndarray, diameter: float, modulus: float | None, seconds: float) -> dict[str, Any]:
    J = ps.jacobian
    rec = {"diameter": diameter, "xy": xy, "reached": 1, "depths": ps.depths, "contact": ps.contact,
           "contact_jacobian": ps.contact_jacobian, "force": ps.force, "noise_std": ps.noise_std,
           "voltages": ps.voltages, "target_jacobian": J[:, :, : len(target_names(ps.names))],
           "info": np.einsum("kmp,kmq->kpq", J, J), "info_ref": ps.jacobian_ref.T @ ps.jacobian_ref, "seconds": seconds}
    if modulus is not None:
        rec["target_modulus"] = modulus
    return rec


def _run_group(path: str, scene: Scene, plan: Plan, indices: list[int], centres: np.ndarray, todo: list[int],
               diameter: float, modulus: float | None) -> list[tuple[int, bool, str]]:
    """Compute and store the presses ``todo`` of a group (:func:`press_groups`: ``indices``
    with their ``centres`` (n, 2) m): the mechanics solved once, at the group's first centre
    (whether or not it is still to do, so that a resumed study computes what an uninterrupted
    one would), and each press measured; [(index, reached, why not)]."""
    with _LOCK:
        t0 = time.perf_counter()
        inst, moves = _setup(scene)
        store = attach(path)
        depths = np.asarray(plan.depths)
        out = []
        try:
            if plan.contact_levels:  # a membrane of its own; the chamber, morph factor and readout shared
                model = contact_membrane(scene, diameter / 2, centres[0], max(plan.depths), plan.contact_levels, modulus,
                                         graded_target=plan.graded_target)
                on = inst.on_membrane(model)
            else:
                model, on = _model(scene, inst, diameter / 2, modulus), inst
            mech = press_mechanics(model, centres[0], depths, head=head_moves(scene))
            shared = (time.perf_counter() - t0) / len(todo)  # the solve's time, spread over the presses computed
            surface = on.surface
            for i in todo:
                t1 = time.perf_counter()
                xy = centres[indices.index(i)]
                if i == indices[0]:
                    ps = press_electrical(on, mech, moves=moves)
                else:  # the first centre's press turned to this one, read through its membrane turned
                    m = _turn(centres[0], xy)
                    turned = mech.turned(m)
                    ps = press_electrical(inst.on_surface(surface.turned(m), turned.u_ref), turned, moves=moves)
                store.put(i, _record(ps, xy, diameter, modulus, shared + time.perf_counter() - t1))
                out.append((i, True, ""))
        except (UnreachablePose, NewtonError, MeshInversionError) as e:
            why = f"{type(e).__name__}: {e}"
            # the model may stand anywhere after a failed press: start the next one afresh
            _WORKER["models"].clear()
            seconds = (time.perf_counter() - t0) / len(todo)
            done = {j for j, _, _ in out}
            for i in todo:
                if i not in done:
                    store.put(i, _nan_record(store.schema, diameter, centres[indices.index(i)], seconds, modulus))
                    out.append((i, False, why))
        store.flush()
        return out


# --------------------------------------------------------------------------------------------
# The driver


def run_design(scene: Scene, plan: Plan, out: str | Path, *, workers: int | None = None, scene_toml: str | None = None,
               progress: Callable[[int], None] | None = None, on_start: Callable[[int, int], None] | None = None,
               on_missed: Callable[[int, str], None] | None = None) -> Path:
    """Compute (or resume, or find finished) the sensitivities of ``scene`` over ``plan``'s
    presses into ``out`` (.h5); the file's path. ``workers``: local processes (default: one per
    core); ``on_missed(index, why)`` told of each press the mechanics could not take (stored
    as not reached)."""
    presses = plan_presses(scene, plan)
    n = len(presses)
    if plan.contact_levels and unrefinable(scene):
        raise ValueError(unrefinable(scene))  # in one line, before any work
    inst_meas = _n_meas(scene)
    soft = bool(plan.target_moduli)
    names = parameter_names(len(electrode_layout(scene).radii), soft)
    schema = design_schema(inst_meas, len(names), len(plan.depths), soft)
    # a study without refinement, soft targets or symmetry keeps the identity it had before they existed
    params = {"plan": {k: list(v) if isinstance(v, tuple) else v for k, v in plan.__dict__.items()
                       if k in _SHAPE and not (k in _LATER and not v)},
              "parameters": list(names), "scene_digest": scene.digest()}
    final = Path(out)
    final = final if final.suffix in (".h5", ".hdf5") else final.with_suffix(".h5")
    with exclusive(final):
        if final.exists():
            rec = open_records(final, fields=["reached"], verify=True)
            stored = dict(rec.provenance["params"])
            # a store written when the frame counts were part of its plan is the same study
            stored["plan"] = {k: v for k, v in stored.get("plan", {}).items() if k in _SHAPE}
            if stored != params or len(rec) != n:
                raise ValueError(f"{final} holds a design study with other settings; remove it (--overwrite), or write to another path")
            return final
        store = open_store(final, schema, scene_toml=scene_toml or f'name = "{scene.name}"\n', seed=None, n_records=n,
                           params=params)
        missing = store.missing()
        if on_start is not None:
            on_start(n - len(missing), len(missing))
        todo = set(int(i) for i in missing)
        tasks = []
        for g in press_groups(scene, plan):
            if todo.intersection(g):
                d, _, e = presses[g[0]]
                tasks.append((str(final), scene, plan, g, np.array([presses[i][1] for i in g]),
                              [i for i in g if i in todo], d, e))
        tasks.sort(key=lambda t: -len(t[5]))  # the longest first: the workers end together
        if tasks:
            w = min(available_cores() if workers is None else workers, len(tasks))
            def tick(results: list[tuple[int, bool, str]]) -> None:
                for index, reached, why in results:
                    if progress is not None:
                        progress(1)
                    if not reached and on_missed is not None:
                        on_missed(index, why)

            if w == 1:
                for t in tasks:
                    tick(_run_group(*t))
            else:
                run_local(tasks, w, tick, _run_group)
        store.finalize(compression="gzip")
    return final


# what shapes the stored derivatives (not the frame counts, which the bounds take from the file);
# the later keys are stored only where set
_SHAPE = ("diameters", "depths", "spacing", "r_max", "contact_levels", "target_moduli", "ray", "symmetric", "ring_mechanics",
          "graded_target")
_LATER = ("contact_levels", "target_moduli", "ray", "symmetric", "ring_mechanics", "graded_target")


def stored_plan(rec: Records) -> Plan:
    """The :class:`Plan` a finished study was computed with (its frame counts the defaults)."""
    p = {k: tuple(v) if isinstance(v, list) else v for k, v in rec.provenance["params"]["plan"].items() if k in _SHAPE}
    return Plan(**{"symmetric": False, "ring_mechanics": False, "graded_target": False, **p})


def _rows(rec: Records, scene: Scene) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """(record, target centre (2,) m, isometry (2, 2) from the record's press) of each press of
    the study's grid, in record order with each record's images in its place: a symmetric
    study's table covers the whole grid."""
    lay = press_layout(scene, stored_plan(rec))
    m = len(lay.computed)
    if len(rec) % m:
        raise ValueError(f"{len(rec)} records do not fill the study's {m} computed centres per target")
    return [(base + int(lay.source[j]), lay.grid[j], lay.moves[j]) for base in range(0, len(rec), m)
            for j in range(len(lay.grid))]


def _n_meas(scene: Scene) -> int:
    from ..eit.protocol import scene_protocol

    return scene_protocol(scene).n_meas


# --------------------------------------------------------------------------------------------
# Bounds from a finished study


@dataclass(frozen=True)
class DesignBounds:
    """The bounds of every press and depth of a study, as a table: one row per (press, depth)
    with ``diameter``, ``x``, ``y`` (the target's centre), ``contact_x``, ``contact_y``,
    ``contact_r``, ``depth`` (m) and, per bound kind (known, marginal), the RMS and the
    efficient estimator's median error m of ``position`` (the contact point), ``depth``,
    ``diameter``; NaN where the press was not reached. A study of soft targets adds their
    ``target_modulus`` (Pa) and the bounds on ``modulus``: those of ln E, the relative error
    of E to first order."""

    columns: dict[str, np.ndarray]
    snr_db: float

    def __len__(self) -> int:
        return len(self.columns["depth"])

    @property
    def quantities(self) -> tuple[str, ...]:
        """What the table bounds: position, depth, diameter, and a soft target's modulus."""
        return _quantities(self.columns)


def design_bounds(study: str | Path | Records, scene: Scene, *, snr_db: float | None = None, reference_frames: int = 50,
                  hold_frames: int = 1) -> DesignBounds:
    """The :class:`DesignBounds` of the finished study (its path, or its records already read:
    bounds at several SNRs then read the file once) for ``scene``'s nuisance priors, at
    ``snr_db`` (default the scene's: the stored noise is rescaled), with the reference averaged
    over ``reference_frames`` and a press over ``hold_frames`` frames."""
    rec = study if isinstance(study, Records) else open_records(study)
    prov = rec.provenance["params"]
    names = tuple(prov["parameters"])
    plan = prov["plan"]
    R, H = int(reference_frames), int(hold_frames)
    snr = scene.noise.snr_db if snr_db is None else float(snr_db)
    scale = 10 ** ((scene.noise.snr_db - snr) / 20)
    prior = nuisance_prior(scene, names)
    cols = _columns(target_names(names))
    bounds: dict[tuple[int, int], Bounds | None] = {}  # a record's, for each of its images
    for i, xy, move in _rows(rec, scene):
        for k in range(len(plan["depths"])):
            _press_row(cols, rec, i, k, plan["depths"][k], xy, move)
            if (i, k) not in bounds:
                bounds[i, k] = None
                if rec["reached"][i]:
                    sigma = rec["noise_std"][i] * scale
                    F = fisher(rec["info_ref"][i], rec["info"][i][k], sigma, reference_frames=R, hold_frames=H)
                    bounds[i, k] = press_bounds(F, prior, rec["contact_jacobian"][i][k])
            for kind in ("known", "marginal"):
                _bound_columns(cols, bounds[i, k], kind)
    return DesignBounds({k: np.asarray(v, float) for k, v in cols.items()}, snr)


def press_joint_bounds(study: str | Path | Records, scene: Scene, *, snr_db: float | None = None, reference_frames: int = 50,
                       hold_frames: int = 1) -> DesignBounds:
    """The bounds of each press's frames read together (:func:`~.bounds.press_fisher`: the
    target's position and size shared by the frames of every depth, a depth each), as a
    :class:`DesignBounds` with one row per press: its position is the contact point's at the
    deepest depth, its depth that depth's; NaN where the press was not reached."""
    rec = study if isinstance(study, Records) else open_records(study)
    prov = rec.provenance["params"]
    names = tuple(prov["parameters"])
    depths = prov["plan"]["depths"]
    snr = scene.noise.snr_db if snr_db is None else float(snr_db)
    scale = 10 ** ((scene.noise.snr_db - snr) / 20)
    prior = np.concatenate([nuisance_prior(scene, names), np.full(len(depths) - 1, np.inf)])
    cols = _columns(target_names(names))
    bounds: dict[int, Bounds | None] = {}
    for i, xy, move in _rows(rec, scene):
        _press_row(cols, rec, i, len(depths) - 1, depths[-1], xy, move)
        if i not in bounds:
            bounds[i] = None
            if rec["reached"][i]:
                F = press_fisher(rec["info_ref"][i], rec["info"][i], rec["noise_std"][i] * scale,
                                 reference_frames=int(reference_frames), hold_frames=int(hold_frames))
                bounds[i] = joint_bounds(F, prior, rec["contact_jacobian"][i][-1])
        for kind in ("known", "marginal"):
            _bound_columns(cols, bounds[i], kind)
    return DesignBounds({k: np.asarray(v, float) for k, v in cols.items()}, snr)


def _quantities(cols: dict[str, list]) -> tuple[str, ...]:
    return ("position", "depth", "diameter") + (("modulus",) if "target_modulus" in cols else ())


def _columns(target: tuple[str, ...]) -> dict[str, list]:
    """A :class:`DesignBounds` table's columns, empty, for the ``target``'s parameters."""
    names = ["diameter", "x", "y", "contact_x", "contact_y", "contact_r", "depth"]
    names += ["target_modulus"] if TARGET_MODULUS in target else []
    names += [f"{q}_{stat}_{kind}" for kind in ("known", "marginal") for q in _quantities(dict.fromkeys(names))
              for stat in ("rms", "median")]
    return {n: [] for n in names}


def _press_row(cols: dict[str, list], rec: Records, i: int, k: int, depth: float, xy: np.ndarray,
               move: np.ndarray) -> None:
    """Record ``i``'s size and, moved by ``move`` to the target centre ``xy``, its contact point
    at its depth ``k`` (``depth`` m) into ``cols``."""
    c = move @ rec["contact"][i][k][:2]
    for name, v in (("diameter", rec["diameter"][i]), ("x", xy[0]), ("y", xy[1]), ("contact_x", c[0]),
                    ("contact_y", c[1]), ("contact_r", math.hypot(c[0], c[1])), ("depth", depth)):
        cols[name].append(v)
    if "target_modulus" in cols:
        cols["target_modulus"].append(rec["target_modulus"][i])


def _bound_columns(cols: dict[str, list], b: Bounds | None, kind: str) -> None:
    if b is None:
        for q in _quantities(cols):
            cols[f"{q}_rms_{kind}"].append(math.nan)
            cols[f"{q}_median_{kind}"].append(math.nan)
        return
    C, Cc = getattr(b, kind), getattr(b, f"contact_{kind}")
    rms = b.rms(kind)
    cols[f"position_rms_{kind}"].append(rms["contact"])
    cols[f"position_median_{kind}"].append(median_error(Cc))
    cols[f"depth_rms_{kind}"].append(rms["depth"])
    cols[f"depth_median_{kind}"].append(median_error(C[2:3, 2:3]))
    cols[f"diameter_rms_{kind}"].append(rms["diameter"])
    cols[f"diameter_median_{kind}"].append(2 * median_error(C[3:4, 3:4]))
    if "target_modulus" in cols:
        cols[f"modulus_rms_{kind}"].append(rms["modulus"])
        cols[f"modulus_median_{kind}"].append(median_error(C[4:5, 4:5]))
