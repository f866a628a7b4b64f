"""Labelled samples of one press trajectory ("group"): the draw, the press, the records.

A group is one draw of target (radius, contact point, stiffness) and domain randomisation
(membrane moduli, saline conductivity, contact impedance, electrode positions, SNR). The
contact point, where the target first touches the membrane, is drawn uniformly over the disc
r ≤ ``[dataset] r_max_mm``, and the target's centre is solved from it on the membrane inflated
under that draw (:func:`~jointsim.mechanics.touch.centre_touching`: off the axis the centre lies
outside the point, by R sin θ on a surface tilted by θ), so the samples cover the disc their
labels claim; drawing the *centre* over the disc left contacts past ~11 mm untrained. The
target comes down there and is pressed in quasi-static steps of at most ``[dataset] step_mm``
(each warm-started from the last) through ``samples_per_press`` depths stratified over
``[dataset] depth_mm``, up to what the dome allows at that point (the sphere's lowest point
stays a membrane thickness above the base: a large sphere touching near the ring reaches
less deep, :func:`~jointsim.mechanics.touch.depth_reach`); at each of them the
sample is taken: membrane state, morphed chamber, clean and noisy voltages, δV against the
noisy steady-state reference, the instrument's image and its metrics. The marginal cost of a
sample is therefore one or two mechanics steps, not a whole press. With ``control = "force"``
the samples are at contact forces stratified over ``force_n``: the target is lowered by secant
steps on its depth until each force is reached (a few mechanics steps per sample), and the
depth reached is the label.

The instrument
    Each sample is the instrument's frame step (:meth:`~jointsim.instrument.Instrument.measure`).
    Voltages come from the randomised sensor (a :class:`~jointsim.instrument.Readout` of the
    group's electrodes, saline, contact impedance and SNR), images from the **nominal** one: δV
    is imaged with the reconstruction built on the nominal scene (Jacobian of the nominal
    inflated chamber, λ by cross-validation as its [reconstruction] says), as a real instrument
    calibrated once would do, not with one rebuilt for each draw.

Electrode jitter: the electrodes are re-clipped, not the mesh moved
    Electrode patches are exact clippings of the base triangles against the electrode discs
    (:func:`~jointsim.mesh.electrodes.disc_patches`), wherever the discs are. A group's
    jittered electrodes are therefore clipped once on the reference chamber's base, and the
    morph never moves a base node, so the same patches are exact for every frame of the group
    and for its reference: the tagging holds exactly with no remesh and no warp of the mesh,
    and δV within a group carries no mesh noise. A warp of the base nodes (an RBF field
    carrying each electrode patch) would do the same with more machinery and a distorted
    base; what it keeps that re-clipping does not is the mesh refinement centred on the
    moved electrode. The jitter is bounded by the scene (``[dataset] electrode_jitter_mm``
    ≤ ``[mesh] refinement_zone_mm``), so a jittered disc stays inside its refined zone. On a
    remesh fallback the patches are clipped on the new mesh.

Determinism
    Everything a group draws comes from ``SeedSequence(seed, spawn_key=(group, attempt, stream))``:
    the same seed gives the same group whatever worker computes it and in whatever order. The
    contact point is the group's, drawn once (attempt 0) and kept by every redraw, so what is
    rejected never thins the disc's edge. A
    draw the mechanics or the chamber mesh cannot take (a sphere that would reach the base,
    a chamber that collapses onto the electrodes: ``UnreachablePose``; a Newton failure; an
    inverted morph) is rejected as a whole and the group draws again (attempt + 1),
    deterministically; so the dataset samples the draws the simulator can take. Any other
    error stops the run.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from ..eit.forward import ForwardModel
from ..eit.protocol import scene_protocol
from ..instrument import Instrument, Readout
from ..io.schema import Field, Schema
from ..linalg import preferred_backend
from ..mechanics.build import membrane_from_scene
from ..mechanics.dome import MembraneModel, UnreachablePose
from ..mechanics.newton import NewtonError
from ..mechanics.touch import centre_touching, depth_reach, point_touched, press_through
from ..mesh.chamber import ChamberMesh
from ..mesh.morph import MeshInversionError
from ..metrics import metric_fields
from ..scene import LATER_DEFAULTS, UNRECORDED_ELEMENT, DatasetSpec, Scene
from ..timing import timed
from .presses import PressList

__all__ = ["SCHEMA_NAME", "SCHEMA_VERSION", "STAGES", "GroupDraw", "DatasetSetup", "draw_group", "listed_draw", "dataset_schema",
           "dataset_params", "group_indices", "n_groups"]

SCHEMA_NAME = "dataset"
SCHEMA_VERSION = 3  # 2: contact_centre; 3: contact points drawn over the disc, contact_point
STAGES = ("group_setup", "mechanics", "mesh", "forward", "reconstruction")
MAX_ATTEMPTS = 16  # draws of one group before its failure is reported
REACH_MARGIN = 1e-6  # m kept from the dome's depth limit at a contact point


@dataclass(frozen=True)
class GroupDraw:
    """One press trajectory's draw (SI): target ``radius`` m, centre ``xy`` (2,) m (None:
    solved on the group's membrane from ``contact_point``, where it first touches, (2,) m),
    ``modulus`` Pa (inf: rigid), ``membrane_scale``, ``conductivity`` S/m,
    ``contact_impedance`` Ω·m², ``jitter`` (n_el, 2) m, ``snr_db``, and the samples'
    ``levels`` (K,), increasing: depths m past first contact (over the spec's range; scaled
    into what the dome allows where it allows less), or contact forces N when the spec's
    ``control`` is "force"."""

    group: int
    attempt: int
    radius: float
    xy: np.ndarray | None
    modulus: float
    membrane_scale: float
    conductivity: float
    contact_impedance: float
    jitter: np.ndarray
    snr_db: float
    levels: np.ndarray
    contact_point: np.ndarray | None = None
    fixed_levels: bool = False  # the levels are a press list's own depths: never scaled


def _rng(seed: int, group: int, attempt: int, stream: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(group, attempt, stream)))


def _log_uniform(rng: np.random.Generator, lo_hi: tuple[float, float]) -> float:
    lo, hi = lo_hi
    return float(math.exp(rng.uniform(math.log(lo), math.log(hi)))) if hi > lo else float(lo)


def draw_group(spec: DatasetSpec, seed: int, group: int, attempt: int = 0, n_electrodes: int = 16) -> GroupDraw:
    """The draw of ``group`` (its ``attempt``-th): uniform radius, the contact point uniform
    over the disc r ≤ r_max (the group's: the same for every attempt), log-uniform moduli
    scale, contact impedance and target modulus, uniform conductivity and SNR, each electrode
    moved uniformly within a disc of radius ``electrode_jitter``, K depths (or forces) one per
    equal slice of their range. The target's centre is left to the press (``xy`` None)."""
    rng = _rng(seed, group, attempt, 0)
    radius = float(rng.uniform(*spec.radius))
    at = _rng(seed, group, 0, 2).uniform(size=2)
    r, phi = spec.r_max * math.sqrt(at[0]), 2 * math.pi * at[1]
    rigid = rng.uniform() < spec.rigid_fraction
    modulus = _log_uniform(rng, spec.target_modulus)
    scale = _log_uniform(rng, spec.membrane_scale)
    sigma = float(rng.uniform(*spec.conductivity))
    z = _log_uniform(rng, spec.contact_impedance)
    jr = spec.electrode_jitter * np.sqrt(rng.uniform(size=n_electrodes))
    ja = 2 * np.pi * rng.uniform(size=n_electrodes)
    snr = float(rng.uniform(*spec.snr_db))
    k = spec.samples_per_press
    lo, hi = spec.force if spec.control == "force" else spec.depth
    levels = lo + (hi - lo) * (np.arange(k) + rng.uniform(size=k)) / k
    return GroupDraw(
        group, attempt, radius, None, math.inf if rigid else modulus, scale, sigma, z,
        np.column_stack([jr * np.cos(ja), jr * np.sin(ja)]), snr, levels, np.array([r * math.cos(phi), r * math.sin(phi)]),
    )


def listed_draw(draw: GroupDraw, presses: PressList, spec: DatasetSpec) -> GroupDraw:
    """``draw`` (its sensor randomisation) pressing the press list's press ``draw.group``: its
    place, radius and modulus, and its depths (else the centres of the spec's K depth slices)."""
    g = draw.group
    k = spec.samples_per_press
    lo, hi = spec.force if spec.control == "force" else spec.depth
    levels = presses.depths[g] if presses.depths is not None else lo + (hi - lo) * (np.arange(k) + 0.5) / k
    xy = presses.xy[g].copy()
    return replace(draw, radius=float(presses.radius[g]), modulus=float(presses.modulus[g]), levels=levels,
                   xy=xy if presses.place == "centre" else None, contact_point=xy if presses.place == "contact" else None,
                   fixed_levels=presses.depths is not None)


def _where(draw: GroupDraw) -> str:
    """Where ``draw`` presses, in words (mm)."""
    if draw.contact_point is not None:
        return f"touching at {np.round(draw.contact_point * 1e3, 2).tolist()} mm"
    return f"centred at {np.round(draw.xy * 1e3, 2).tolist()} mm"


def n_groups(n_samples: int, samples_per_press: int) -> int:
    return -(-n_samples // samples_per_press)


def group_indices(group: int, n_samples: int, samples_per_press: int) -> range:
    """Record indices of ``group``: K consecutive ones (the last group may be cut short by N)."""
    a = group * samples_per_press
    return range(a, min(n_samples, a + samples_per_press))


def dataset_schema(n_electrodes: int, n_meas: int, n_cells: int | None) -> Schema:
    """One record per labelled sample; ``image`` only when ``n_cells`` is given."""
    F = Field
    m = n_meas
    fields = [
        F("group", (), "int64", "", "press trajectory (group) id: samples of one group share the draw; split by group"),
        F("radius", (), "float64", "m", "target sphere radius"),
        F("xy", (2,), "float64", "m", "target centre in the base plane"),
        F("contact_point", (2,), "float64", "m", "where the target first touches the untouched membrane's (smooth) outer "
          "surface, in the base plane: drawn uniformly over the disc r <= r_max, the target centre solved from it"),
        F("depth", (), "float64", "m", "indentation past first contact (target centre below its first-contact height)"),
        F("target_modulus", (), "float64", "Pa", "target Young's modulus (inf: rigid)"),
        F("force", (3,), "float64", "N", "FEM contact force of the membrane on the target"),
        F("contact_centre", (3,), "float64", "m", "FEM centre of pressure of the contact on the membrane's outer surface "
          "(off the axis it lies between the target's centre and the dome's, not below the target's centre)"),
        F("contact_area", (), "float64", "m^2", "FEM contact area"),
        F("displaced_volume", (), "float64", "m^3", "saline displaced to the reservoir (from the inflated state)"),
        F("peak_strain", (), "float64", "", "largest principal Green-Lagrange strain in the membrane"),
        F("membrane_scale", (), "float64", "", "multiplier of the membrane moduli (randomisation, per group)"),
        F("conductivity", (), "float64", "S/m", "saline conductivity (randomisation, per group)"),
        F("contact_impedance", (), "float64", "ohm m^2", "contact impedance of every electrode (randomisation, per group)"),
        F("electrode_jitter", (n_electrodes, 2), "float64", "m", "in-plane offset of each ring electrode (per group)"),
        F("snr_db", (), "float64", "dB", "noise level re the mean standing |V| (per group)"),
        F("voltages_clean", (m,), "float64", "V", "noise-free voltages"),
        F("reference_clean", (m,), "float64", "V", "noise-free voltages of the untouched inflated sensor, same randomisation"),
        F("voltages", (m,), "float64", "V", "measured voltages: clean plus noise at snr_db"),
        F("dv", (m,), "float64", "V", "voltages minus the measured steady-state reference (mean of reference_frames noisy frames)"),
        F("dv_clean", (m,), "float64", "V", "voltages_clean minus reference_clean"),
        F("com", (3,), "float64", "m", "CoM of the perturbation cluster of the nominal instrument's image"),
        F("sum_sigma", (), "float64", "S/m voxel", "total conductivity change in the cluster"),
        F("diameter", (), "float64", "m", "equivalent diameter of the cluster"),
        F("extent_xy", (), "float64", "m", "in-plane extent of the cluster"),
        F("cluster_cells", (), "int32", "", "voxels in the cluster"),
    ]
    if n_cells is not None:
        fields.append(F("image", (n_cells,), "float32", "S/m", "conductivity change on the nominal voxel grid"))
    fields.append(F("timings", (len(STAGES),), "float64", "s", "wall time per stage: " + ", ".join(STAGES)
                    + " (the group's set-up shared among its samples)", volatile=True))
    return Schema(tuple(fields), name=SCHEMA_NAME, version=SCHEMA_VERSION)


# scene values added after stores were first written, with the behaviour before they existed:
# recorded only where they differ from it, so a store written before still resumes
LATER_KEYS: dict[tuple[str, str], object] = {("membrane", "moulding"): "cap", ("membrane", "element"): UNRECORDED_ELEMENT,
                                             ("mesh", "update"): "auto", ("electrodes", "discs"): (),
                                             ("electrodes", "reference"): True, ("drive", "measure"): "reference",
                                             ("drive", "stim"): None, ("drive", "meas"): None, **LATER_DEFAULTS}


def dataset_params(scene: Scene, n_samples: int, chamber_sha256: str, presses: PressList | None = None) -> dict[str, Any]:
    """What shapes the data beyond the scene file's text: the effective scene (after
    command-line overrides: sampling spec, mesh, membrane, noise, reconstruction settings; not
    the palpation program, which a dataset does not use), N, the stimulation and measurement
    patterns with the voltages' channel order, the press list when one is given, the sparse
    solver when one is chosen (``--solver``: its bits differ at round-off), and the chamber mesh used (a
    resumed run continues on the mesh it started with, whatever mesher version the machine
    has). JSON-ready; the store's identity."""
    d = scene.to_dict()
    d.pop("name", None)
    d.pop("palpation", None)
    for (section, key), before in LATER_KEYS.items():
        if d[section].get(key) == before:
            del d[section][key]
    params = {"scene": d, "n_samples": int(n_samples), "chamber_sha256": chamber_sha256,
              "protocol": scene_protocol(scene).to_record()}
    if presses is not None:  # recorded only when given: a store of drawn presses keeps its identity
        params["presses"] = presses.to_record()
    if (solver := preferred_backend()) != "auto":  # another solver gives other bits: resume only with it
        params["solver"] = solver
    return params


class DatasetSetup:
    """What every group shares, built once per worker: the nominal
    :class:`~jointsim.instrument.Instrument` of ``scene`` on ``chamber`` (morpher, protocol,
    voxel grid, reconstruction matrix) and the record schema."""

    def __init__(self, scene: Scene, chamber: ChamberMesh, seed: int, presses: PressList | None = None):
        self.scene = scene
        self.spec = scene.dataset
        self.seed = int(seed)
        self.presses = presses
        self.instrument = Instrument.build(scene, chamber=chamber, reference_frames=self.spec.reference_frames)
        self.n_electrodes = scene.electrodes.n_active  # the electrodes a draw moves
        inst = self.instrument
        self.schema = dataset_schema(self.n_electrodes, inst.readout.n_meas, inst.grid.n_cells if self.spec.images else None)
        # the groups' forward model: their electrodes, jittered within the spec's bound, keep
        # the faces they could cover, so every group's CEM system has one pattern and the
        # solver's ordering and symbolic analysis are done once per worker, not per group
        # (with the rest state's warm start, a group's set-up at dataset_p2 went from ~1.0 to
        # ~0.55 s: docs/datasets.md)
        self._forward: ForwardModel | None = None

    def free(self) -> None:
        if self._forward is not None:
            self._forward.free()
        self.instrument.free()

    # -- one group -----------------------------------------------------------------------

    def group(self, group: int, n_samples: int | None = None) -> tuple[list[dict[str, Any]], list[str]]:
        """The records of ``group`` (its first ``n_samples``, default K) in depth order, and
        why each draw rejected before the one they come from failed."""
        k = self.spec.samples_per_press if n_samples is None else n_samples
        errors = []
        for attempt in range(MAX_ATTEMPTS):
            draw = draw_group(self.spec, self.seed, group, attempt, self.n_electrodes)
            if self.presses is not None:
                draw = listed_draw(draw, self.presses, self.spec)
            try:
                return self.press(draw, k), errors
            # only what a draw can cause: any other error (a bug, a bad setting) stops the run
            # rather than being redrawn around, as an int8 overflow once was
            except (UnreachablePose, NewtonError, MeshInversionError) as e:
                errors.append(f"group {group} attempt {attempt} (radius {draw.radius * 1e3:.2f} mm, {_where(draw)}, "
                              f"target modulus {draw.modulus:.3g} Pa, membrane x{draw.membrane_scale:.2f}): {type(e).__name__}: {e}")
        raise ValueError(f"group {group}: no draw in {MAX_ATTEMPTS} could be pressed ({'; '.join(errors[-3:])}); "
                           "narrow [dataset] depth_mm, radius_mm or r_max_mm")

    def press(self, draw: GroupDraw, n_samples: int) -> list[dict[str, Any]]:
        """Press ``draw``'s target through its first ``n_samples`` depths; one record each."""
        inst = self.instrument
        t: dict[str, float] = {}
        with timed(t, "group_setup"):
            model = self._membrane(draw)
            draw, levels, contact_z = self._placed(draw, model)
            ref_dome = inst.dome(model.u)
            ref_chamber = inst.deform(ref_dome).chamber
            rng = _rng(self.seed, draw.group, draw.attempt, 1)
            # the group's sensor: its electrodes, saline, contact impedance and noise; its
            # morphed chambers, and every other group's, share one pattern and PARDISO analysis
            readout = Readout.on(ref_chamber, self.scene, inst.protocol, rng=rng, reference_frames=self.spec.reference_frames,
                                 conductivity=draw.conductivity, contact_impedance=draw.contact_impedance,
                                 offsets=draw.jitter, snr_db=draw.snr_db, reach=self.spec.electrode_jitter, like=self._forward)
            if self._forward is not None and not readout.forward.assembler.same_pattern(self._forward.assembler):
                self._forward.free()
            self._forward = readout.forward
        share = t["group_setup"] / n_samples
        records = []
        descent = press_through(model, draw.xy, contact_z, levels[:n_samples], self.spec.step)
        for level in levels[:n_samples]:
            t = {s: 0.0 for s in STAGES}
            t["group_setup"] = share
            with timed(t, "mechanics"):
                if self.spec.control == "force":
                    st = model.press_to_force(draw.xy, level)
                    d = contact_z - float(model.contact.centre[2])
                else:
                    # steps of at most spec.step, equal, ending on the sample's depth
                    d, st = next(descent)
            r = inst.measure(inst.dome(st.u), rng, readout=readout, reference=ref_dome)
            t.update(r.timings)
            rec = {
                "group": draw.group, "radius": draw.radius, "xy": draw.xy, "contact_point": draw.contact_point, "depth": d, "target_modulus": draw.modulus,
                "force": st.force, "contact_centre": st.contact_centre, "contact_area": st.contact_area, "displaced_volume": st.displaced_volume,
                "peak_strain": st.peak_strain, "membrane_scale": draw.membrane_scale, "conductivity": draw.conductivity,
                "contact_impedance": draw.contact_impedance, "electrode_jitter": draw.jitter, "snr_db": draw.snr_db,
                "voltages_clean": r.voltages_clean, "reference_clean": readout.v_ref, "voltages": r.voltages, "dv": r.dv,
                "dv_clean": r.dv_clean, **metric_fields(r.metrics),
            }
            if self.spec.images:
                rec["image"] = r.image.astype(np.float32)
            rec["timings"] = np.array([t[s] for s in STAGES])
            records.append(rec)
        return records

    def _placed(self, draw: GroupDraw, model: MembraneModel) -> tuple[GroupDraw, np.ndarray, float]:
        """``draw`` with both its target centre and its contact point on ``model`` (the group's
        untouched membrane), the other solved from the one given; its levels, the depths
        scaled into what the dome allows there (:func:`~jointsim.mechanics.touch.depth_reach`)
        where it allows less than the spec's range; and the height m at which the target
        touches there. UnreachablePose where the dome allows less than the range's start."""
        if draw.xy is None:
            draw = replace(draw, xy=centre_touching(model, draw.contact_point)[:2])
        elif draw.contact_point is None:
            draw = replace(draw, contact_point=point_touched(model, draw.xy))
        levels = draw.levels
        contact_z = model.first_contact_height(draw.xy)
        if self.spec.control == "depth":
            lo, hi = self.spec.depth
            # a hair short of the limit: press() refuses the lowest point below it by round-off
            reach = depth_reach(model, contact_z) - REACH_MARGIN
            if draw.fixed_levels and reach < levels[-1]:  # a listed depth is the user's: not scaled, not redrawn
                raise ValueError(f"press {draw.group} ({_where(draw)}, {2 * draw.radius * 1e3:.3g} mm): depth "
                                 f"{levels[-1] * 1e3:.4g} mm is past what the dome allows there ({max(reach, 0) * 1e3:.3g} mm)")
            if reach < levels[0]:
                raise UnreachablePose(f"a {2 * draw.radius * 1e3:.3g} mm target touching at "
                                      f"{np.round(draw.contact_point * 1e3, 2).tolist()} mm reaches {max(reach, 0) * 1e3:.3g} mm "
                                      f"deep, less than the first depth {levels[0] * 1e3:.3g} mm")
            if reach < hi:  # (then hi > lo: reach ≥ levels[0] ≥ lo)
                levels = lo + (levels - lo) * (reach - lo) / (hi - lo)
        return draw, levels, contact_z

    def _membrane(self, draw: GroupDraw) -> MembraneModel:
        """The membrane of ``draw`` (moduli scaled, inflated by the reservoir, untouched) with
        its target: rigid, or a neo-Hookean sphere of ``draw.modulus`` and the scene's Poisson
        ratio solved together with the membrane."""
        scaled = replace(self.scene, membrane=self.scene.membrane.scaled(draw.membrane_scale),
                         target=replace(self.scene.target, kind="rigid"))
        soft = math.isfinite(draw.modulus)
        return membrane_from_scene(scaled, target_radius=draw.radius, target_modulus=draw.modulus if soft else None,
                                   inflate_from=self.instrument.inflated_u)
