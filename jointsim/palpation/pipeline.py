"""Coupled virtual palpation (paper III.C, Fig. 4): the MuJoCo bench rig presses targets into
the FEM membrane, the chamber mesh follows the membrane, and each 50 Hz frame gives what the
instrument records (256 noisy voltages), the difference image and its metrics.

One frame k of a target's program, in order:

1. **MuJoCo**: the rig advances one frame (1/frame_rate s) with the contact force of frame
   k − 1 held on the target (frame 0: the rig at rest at its start, not stepped);
2. **mechanics**: the membrane is solved with the target centre where the rig put it
   (:meth:`MembraneModel.press`, warm-started from frame k − 1); its contact force is what
   MuJoCo receives during the next frame;
3–5. **the instrument's frame step** (:meth:`jointsim.instrument.Instrument.measure`): the
   chamber follows the membrane's deformed inner surface (morph, or remesh when the morph
   degrades), the CEM forward model gives the clean voltages, noise at the scene's SNR (seeded
   per frame) the measured ones, δV against the measured steady-state reference (the mean of
   ``reference_frames`` noisy frames of the untouched sensor, as the paper subtracts it) is
   imaged by zeroth-order Tikhonov on the fixed voxel grid and the paper's metrics are taken.

The reference is the inflated, untouched membrane (see :mod:`jointsim.instrument`): a frame at
zero indentation gives the reference mesh bit for bit and δV = 0 exactly on the morph path.

Resuming: every record is stored with a checkpoint of the rig (MuJoCo's integration state,
frame counter, recent heights) and of the membrane (displacement, warm-start history, target
centre, pressure); a rerun skips stored frames and continues from the last checkpoint of an
unfinished target, bit for bit as if never interrupted.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Callable, Iterator

import mujoco
import numpy as np

from ..eit.noise import gain_drift
from ..eit.protocol import scene_protocol
from ..instrument import STAGES as FRAME_STAGES
from ..instrument import Instrument, Reading, stream
from ..io.schema import Field, Schema
from ..io.store import RecordStore
from ..linalg import preferred_backend
from ..mechanics.build import membrane_from_scene
from ..mechanics.dome import MembraneModel, MembraneState
from ..mechanics.fem import warp_device
from ..mesh.chamber import ChamberMesh
from ..mesh.tetmesh import TetMesh
from ..metrics import metric_fields, rms
from ..scene import LATER_DEFAULTS, UNRECORDED_ELEMENT, PalpationSpec, Scene
from ..timing import timed
from .rig import Controller, Rig, RigFrame, load_rig, press_hold_retract

__all__ = [
    "STAGES",
    "MESH_PATHS",
    "Segment",
    "Frame",
    "Palpation",
    "run_palpation",
    "force_profile",
    "program_params",
]

STAGES = ("mujoco", "mechanics") + FRAME_STAGES
MESH_PATHS = ("morph", "remesh")
# s of the stage lifting the target after a force-mode press: the rig lags the command by a few
# frames (measured: 12 mN still on a 15 mm target when a 30 mN command reached 0), so the record
# ends only once the target has let go
RELEASE_S = 0.2
SCHEMA_VERSION = 2  # 2: true_centre is the dent's centroid (was the net displaced saline's)


# ---------------------------------------------------------------------------------------------
# The program: one segment per target
# ---------------------------------------------------------------------------------------------


def force_profile(force: float, ramp_s: float, hold_s: float, frame_rate: float, release_s: float = 0.0) -> np.ndarray:
    """Force-mode program (n,) N at ``frame_rate`` Hz: a linear ramp from 0 to ``force`` in
    ``ramp_s`` s, a hold of ``hold_s`` s, a ramp back to 0 (a step when ``ramp_s`` is 0), then
    ``release_s`` s of the stage lifting the target away with ``force`` (−``force``): with no
    force at all the membrane alone pushes the target out, and the damped rig lets go only
    exponentially (1.8 mN still on after 0.3 s, measured)."""
    if not (math.isfinite(force) and force > 0):
        raise ValueError(f"force = {force!r}: must be > 0 N")
    if not (math.isfinite(ramp_s) and ramp_s >= 0):
        raise ValueError(f"force_ramp_s = {ramp_s!r}: must be >= 0 s")
    if not (math.isfinite(hold_s) and hold_s >= 0):
        raise ValueError(f"hold_s = {hold_s!r}: must be >= 0 s")
    if not (math.isfinite(release_s) and release_s >= 0):
        raise ValueError(f"release_s = {release_s!r}: must be >= 0 s")
    end = 2 * ramp_s + hold_s
    n = int(math.ceil((end + release_s) * frame_rate - 1e-9)) + 1
    t = np.arange(n) / frame_rate
    if ramp_s == 0:
        f = np.where(t <= hold_s + 1e-12, force, 0.0) if hold_s > 0 or release_s > 0 else np.full(n, force)
    else:
        f = force * np.interp(t, [0.0, ramp_s, ramp_s + hold_s, end], [0.0, 1.0, 1.0, 0.0])
    return np.where(t > end + 1e-12, -force, f)


@dataclass(frozen=True)
class Segment:
    """One target's program: target number ``target``, sphere ``radius`` m, ``n_frames``
    frames stored as records ``start`` … ``start + n_frames − 1``, driven by ``controller``
    (its trajectory's depths are measured from first contact; the rig is placed when the
    segment runs, from the membrane's first-contact height)."""

    target: int
    radius: float
    start: int
    n_frames: int
    controller: Controller

    @property
    def indices(self) -> range:
        return range(self.start, self.start + self.n_frames)


def _segments(spec: PalpationSpec, frame_rate: float) -> tuple[Segment, ...]:
    out, start = [], 0
    for i, r in enumerate(spec.target_radii):
        if spec.mode == "force":
            c = Controller.force(force_profile(spec.force, spec.force_ramp, spec.hold, frame_rate, RELEASE_S),
                                 xy=spec.xy, gap=spec.gap)
            n = len(c.press_force)
        else:
            tr = press_hold_retract(spec.depth, spec.speed, spec.hold, frame_rate, spec.xy, spec.gap)
            c = Controller.position(tr) if spec.mode == "position" else Controller.compliant(tr, spec.probe_stiffness, spec.probe_damping)
            n = len(tr)
        out.append(Segment(i, float(r), start, n, c))
        start += n
    return tuple(out)


# ---------------------------------------------------------------------------------------------
# A frame
# ---------------------------------------------------------------------------------------------


@dataclass(eq=False)
class Frame:
    """One frame as computed: its global ``index``, ``segment``, the ``rig`` frame (pose,
    command, the force MuJoCo received), the membrane ``state``, the instrument's ``reading``
    (chamber, voltages, δV, image, metrics, the dent's centroid), the per-stage
    ``timings`` s, and the ``record`` stored for it."""

    index: int
    segment: Segment
    frame: int
    rig: RigFrame
    state: MembraneState
    reading: Reading
    timings: dict[str, float]
    record: dict[str, Any]

    # the reading's parts by the names the reports use
    chamber = property(lambda self: self.reading.chamber)
    voltages = property(lambda self: self.reading.voltages)
    voltages_clean = property(lambda self: self.reading.voltages_clean)
    dv = property(lambda self: self.reading.dv)
    dv_clean = property(lambda self: self.reading.dv_clean)
    image = property(lambda self: self.reading.image)
    image_normalised = property(lambda self: self.reading.image_normalised)
    metrics = property(lambda self: self.reading.metrics)
    true_centre = property(lambda self: self.reading.true_centre)


# ---------------------------------------------------------------------------------------------
# The set-up
# ---------------------------------------------------------------------------------------------


class Palpation:
    """A palpation run's set-up, built once from ``scene`` (its [palpation] section unless
    ``spec`` is given): the program's :attr:`segments`, the bench rig, and the
    :class:`~jointsim.instrument.Instrument` (chamber, readout, image) that measures each frame.

    Parameters
    ----------
    scene : the sensor; its [mesh] sets the chamber resolution, [membrane] the FEM, [noise]
        the SNR, seed and frame rate, [drive] the current and skip, [reconstruction] the image
    spec : the palpation program (default ``scene.palpation``)
    rig_path : MJCF of the bench (default ``scenes/bench_rig.xml``)
    chamber : a ready reference chamber mesh of ``scene`` (default:
        :func:`~jointsim.instrument.deployed_chamber`); its dome must lie on the membrane's inner
        surface, or it is refused
    device : the Warp device of the membrane's element kernel ("cpu", or "cuda:0" where a GPU
        is); the frames agree to round-off

    ``instrument``: the measurement chain; ``gains`` (n_records, n_meas) the gain drift or
    None; ``setup_timings`` s per set-up stage.
    """

    def __init__(self, scene: Scene, spec: PalpationSpec | None = None, *, rig_path: str | Path | None = None,
                 chamber: ChamberMesh | None = None, device: str = "cpu"):
        self.scene = scene
        self.device = warp_device(device)
        self.spec = spec = scene.palpation if spec is None else spec
        self.rig_path = rig_path
        self.frame_rate = scene.noise.frame_rate_hz
        self.seed = int(scene.noise.seed)
        if spec.fdm_contact_impedance and scene.electrodes.contact_impedance_by_freq is None:
            raise ValueError("palpation.fdm_contact_impedance = true: needs electrodes.contact_impedance_by_freq_ohm_m2")
        self.segments = _segments(spec, self.frame_rate)
        self.n_records = self.segments[-1].start + self.segments[-1].n_frames
        t: dict[str, float] = {}
        with timed(t, "membrane"):
            # the membrane is inflated when the model is built (by the reservoir, or to the dome
            # height when moulded flat): the instrument's reference is that state
            model = membrane_from_scene(scene, target_radius=spec.target_radii[0], device=self.device)
            self.membrane_nodes = model.mesh.n_nodes
            # the membrane's corner tetrahedra (the P2 mesh without midside nodes), for export
            self.membrane_mesh = TetMesh(model.mesh.nodes, model.mesh.corner_tets)
        self.instrument = Instrument.build(scene, membrane=model, chamber=chamber, reference_frames=spec.reference_frames,
                                           fdm=spec.fdm_contact_impedance)
        self.setup_timings = {**t, **self.instrument.setup_timings}
        self.setup_timings["membrane"] += t["membrane"]
        n_meas = self.instrument.readout.n_meas
        self.gains = (
            gain_drift(self.n_records, n_meas, scene.noise.drift_per_s, self.frame_rate, rng=stream(self.seed, "drift"))
            if scene.noise.drift_per_s > 0 else None
        )

    def membrane(self, radius: float) -> MembraneModel:
        """A fresh membrane (inflated by the reservoir, untouched) for a target of ``radius`` m."""
        return membrane_from_scene(self.scene, target_radius=radius, device=self.device, inflate_from=self.instrument.inflated_u)

    def rig(self, segment: Segment, contact_z: float) -> Rig:
        """The bench for ``segment``, its program offset from the membrane's first contact
        ``contact_z`` (target-centre height). The position servo sags under the stage's
        weight by M·g/kp; that static offset is compensated (the stage is placed by its
        encoder), so frame 0 of a zero-gap program touches the membrane without pressing."""
        c = segment.controller
        rig = load_rig(self.rig_path, segment.radius, c, self.frame_rate, contact_z)
        if c.mode == "force":
            return rig
        sag = rig.moving_mass * rig.gravity / rig.servo_gains[0]
        z = contact_z + sag
        for _ in range(16):  # (contact + sag) − sag may round below contact: never press at rest
            rig = load_rig(self.rig_path, segment.radius, c, self.frame_rate, z)
            if rig.current.position[2] >= contact_z:
                break
            z = float(np.nextafter(z, np.inf))
        return rig

    # -- the record --------------------------------------------------------------------

    def schema(self) -> Schema:
        """The fields of one frame's record."""
        m, c = self.instrument.readout.n_meas, self.instrument.grid.n_cells
        F = Field
        return Schema(
            (
                F("target", (), "int32", "", "target number (order of palpation.target_*)"),
                F("target_radius", (), "float64", "m", "target sphere radius"),
                F("frame", (), "int32", "", "frame number within the target's program"),
                F("time", (), "float64", "s", "time since the start of the target's program"),
                F("command_depth", (), "float64", "m", "commanded stage depth past first contact (NaN in force mode)"),
                F("command_force", (), "float64", "N", "commanded press force (NaN outside force mode)"),
                F("position", (3,), "float64", "m", "target centre (world; sensor base z = 0)"),
                F("velocity", (3,), "float64", "m/s", "target centre velocity"),
                F("depth", (), "float64", "m", "indentation: first-contact height minus the target centre height"),
                F("force", (3,), "float64", "N", "FEM contact force of the membrane on the target (fed to MuJoCo for the next frame)"),
                F("applied_force", (3,), "float64", "N", "external force on the target as MuJoCo received it over the previous frame"),
                F("contact_area", (), "float64", "m^2", "FEM contact area"),
                F("displaced_volume", (), "float64", "m^3", "saline displaced to the reservoir (FEM, from the inflated state)"),
                F("chamber_volume_change", (), "float64", "m^3", "reference chamber mesh volume minus this frame's"),
                F("peak_strain", (), "float64", "", "largest principal Green-Lagrange strain in the membrane"),
                F("penetration", (), "float64", "m", "largest target penetration of the membrane"),
                F("newton_iterations", (), "int32", "", "Newton iterations of the mechanics step"),
                F("min_jacobian", (), "float64", "", "smallest det F in the membrane"),
                F("mesh_path", (), "int8", "", "0: reference mesh morphed (no mesh noise); 1: remeshed (change taken between the remesh and its pull-back to the reference)"),
                F("mesh_min_shape", (), "float64", "", "smallest tet shape measure of the chamber mesh"),
                F("voltages", (m,), "float64", "V", "measured voltages: clean, drift gain, noise at the scene SNR"),
                F("voltages_clean", (m,), "float64", "V", "noise-free voltages"),
                F("dv", (m,), "float64", "V", "measured voltages minus the measured steady-state reference"),
                F("dv_clean", (m,), "float64", "V", "noise-free voltage change"),
                F("rms_dv", (), "float64", "V", "RMS of dv"),
                F("rms_dv_clean", (), "float64", "V", "RMS of dv_clean"),
                F("image", (c,), "float32", "S/m", "reconstructed conductivity change on the voxel grid"),
                F("true_centre", (3,), "float64", "m", "centroid of the dent: the saline displaced where the membrane's "
                  "inner surface moved in, the bulges about it left out (NaN when none)"),
                F("com", (3,), "float64", "m", "CoM of the perturbation cluster (noise-normalised image)"),
                F("com_error", (), "float64", "m", "|com - true_centre|: the image's CoM from the dent's centroid, in 3-D"),
                F("com_error_xy", (), "float64", "m", "in-plane part of com_error"),
                F("sum_sigma", (), "float64", "S/m voxel", "total change in the cluster"),
                F("diameter", (), "float64", "m", "equivalent diameter of the cluster (sphere of its volume)"),
                F("extent_xy", (), "float64", "m", "in-plane extent of the cluster"),
                F("cluster_cells", (), "int32", "", "cells in the cluster"),
                F("timings", (len(STAGES),), "float64", "s", "wall time per stage: " + ", ".join(STAGES), volatile=True),
            ),
            name="palpation",
            version=SCHEMA_VERSION,
        )

    def params(self) -> dict[str, Any]:
        """What shapes the data beyond the scene file (see :func:`program_params`)."""
        return program_params(self.scene, self.spec, self.rig_path)

    def free(self) -> None:
        self.instrument.free()


# ---------------------------------------------------------------------------------------------
# The loop
# ---------------------------------------------------------------------------------------------


def program_params(scene: Scene, spec: PalpationSpec | None = None, rig_path: str | Path | None = None) -> dict[str, Any]:
    """The run settings that shape a palpation's data beyond the scene file's text: the
    effective program (after command-line overrides), the mesh and membrane resolution, the
    noise, the rig model, the stimulation and measurement patterns with the voltages' channel
    order, the number of frames, and the sparse solver where one is chosen (JOINTSIM_SOLVER,
    ``--solver``). JSON-ready; the store's identity uses it,
    so a run resumes only with the same settings."""
    spec = scene.palpation if spec is None else spec
    d = asdict(spec)
    d["target_radii"] = list(d["target_radii"])
    d["xy"] = list(d["xy"])
    segs = _segments(spec, scene.noise.frame_rate_hz)
    params = {
        "palpation": d,
        "mesh": asdict(scene.mesh),
        # values added to the format later recorded only where they change what was done before
        "reconstruction": {k: v for k, v in asdict(scene.reconstruction).items()
                           if LATER_DEFAULTS.get(("reconstruction", k), object()) != v},
        "membrane": {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(scene.membrane).items()
                     if not (k == "element" and v == UNRECORDED_ELEMENT)},
        "noise": asdict(scene.noise),
        "rig": str(rig_path) if rig_path else "scenes/bench_rig.xml",
        "protocol": scene_protocol(scene).to_record(),
        "n_records": segs[-1].start + segs[-1].n_frames,
        "frames_per_target": [sg.n_frames for sg in segs],
    }
    if (solver := preferred_backend()) != "auto":  # chosen (--solver): its bits differ at round-off; resume only with it
        params["solver"] = solver
    return params


_MEMBRANE_KEYS = ("u", "hist_centre", "hist_u", "centre", "pressure", "compliance", "tangent_u", "friction_nodes", "friction_anchors",
                  "newton_shift", "tangent_context")


def _checkpoint(model: MembraneModel, rig: Rig, force: np.ndarray) -> dict[str, np.ndarray]:
    """What continuing after this frame needs: the rig (MuJoCo's full integration state, its
    frame counter and recent heights), the membrane (:meth:`MembraneModel.get_state`) and the
    force to hold over the next frame."""
    state = np.empty(mujoco.mj_stateSize(rig.model, mujoco.mjtState.mjSTATE_INTEGRATION))
    mujoco.mj_getState(rig.model, rig.data, state, mujoco.mjtState.mjSTATE_INTEGRATION)
    membrane = model.get_state()
    if set(membrane) != set(_MEMBRANE_KEYS):  # the checkpoint's layout is fixed: say so if it changes
        raise RuntimeError(f"MembraneModel.get_state gave {sorted(membrane)}, palpation checkpoints hold {sorted(_MEMBRANE_KEYS)}")
    return {
        "mj_state": state,
        "rig_index": np.int64(rig.index),
        "rig_recent": np.array(rig._recent, float),
        **membrane,
        "force": np.asarray(force, float),
    }


def _restore(model: MembraneModel, rig: Rig, ck: dict[str, np.ndarray]) -> np.ndarray:
    """Put ``model`` and ``rig`` back in the state :func:`_checkpoint` saved; return the force."""
    mujoco.mj_setState(rig.model, rig.data, ck["mj_state"], mujoco.mjtState.mjSTATE_INTEGRATION)
    mujoco.mj_forward(rig.model, rig.data)
    rig.index = int(ck["rig_index"])
    rig._recent.clear()
    rig._recent.extend(float(z) for z in ck["rig_recent"])
    model.set_state({k: ck[k] for k in _MEMBRANE_KEYS if k in ck})  # a checkpoint of an older version lacks some
    return ck["force"].copy()


def run_palpation(
    pal: Palpation,
    store: RecordStore | None = None,
    *,
    export: Callable[[Frame], None] | None = None,
    progress: Callable[[int], None] | None = None,
) -> Iterator[Frame]:
    """Run the program of ``pal``, yielding each computed :class:`Frame` in order.

    With a ``store`` (from :func:`jointsim.io.store.open_store` with ``pal.schema()`` and
    ``n_records = pal.n_records``), each frame is stored with its checkpoint as soon as it is
    computed, and frames already stored are skipped: an unfinished target continues from its
    last stored frame's checkpoint (bit for bit the frames an uninterrupted run gives), a
    finished one is not rebuilt. ``export(frame)`` runs before the frame is stored (so a
    stored frame's exports exist); ``progress(n)`` is told of frames done or skipped.

    Errors from the mechanics (an indentation the dome cannot take, a Newton failure) are
    raised with the target and frame named; every frame before them is kept in the store."""
    tick = progress or (lambda n: None)
    done = set(store.done().tolist()) if store is not None else set()
    for seg in pal.segments:
        k0 = 0
        while k0 < seg.n_frames and seg.start + k0 in done:
            k0 += 1
        if k0 == seg.n_frames:
            tick(seg.n_frames)
            continue
        tick(k0)
        model = pal.membrane(seg.radius)
        contact_z = model.first_contact_height(seg.controller.start_xy)
        rig = pal.rig(seg, contact_z)
        force = np.zeros(3)
        if k0 > 0:
            force = _restore(model, rig, store.checkpoint(seg.start + k0 - 1))
        last = None
        for k in range(k0, seg.n_frames):
            try:
                frame = _frame(pal, seg, k, model, rig, force, contact_z, last)
            except (ValueError, RuntimeError) as e:
                raise _in_context(e, f"target {seg.target} (radius {seg.radius * 1e3:g} mm), frame {k}") from e
            force = frame.state.force
            last = frame
            if export is not None:
                export(frame)
            if store is not None:
                store.put(frame.index, frame.record, checkpoint=_checkpoint(model, rig, force))
            yield frame
            tick(1)


def _in_context(e: Exception, where: str) -> Exception:
    """``e`` of the same type with ``where`` in front of its message (or ``e`` with a note)."""
    try:
        return type(e)(f"{where}: {e}")
    except Exception:
        e.add_note(where)
        return e


def _frame(pal: Palpation, seg: Segment, k: int, model: MembraneModel, rig: Rig, force: np.ndarray, contact_z: float,
           last: Frame | None = None) -> Frame:
    t: dict[str, float] = {s: 0.0 for s in STAGES}
    with timed(t, "mujoco"):
        rf = rig.current if k == 0 else rig.frame(force)
    with timed(t, "mechanics"):
        st = model.press(rf.position)
    index = seg.start + k
    inst = pal.instrument
    # a hold leaves the membrane bit for bit where it was: the frame step then reuses the last
    # chamber and clean voltages (at the paper's fidelity ~3 s of each hold frame) and draws
    # only the noise anew
    r = inst.measure(inst.dome(st.u), stream(pal.seed, "frame", index), last=last.reading if last is not None else None,
                     gain=pal.gains[index] if pal.gains is not None else 1.0, truth_volume=st.displaced_volume)
    t.update(r.timings)
    m = metric_fields(r.metrics)
    com, centre = m["com"], r.true_centre
    record = {
        "target": seg.target,
        "target_radius": seg.radius,
        "frame": k,
        "time": k / pal.frame_rate,
        "command_depth": rig.controller.trajectory.depth[k] if rig.controller.trajectory is not None else np.nan,
        "command_force": rf.command_force,
        "position": rf.position,
        "velocity": rf.velocity,
        "depth": contact_z - rf.position[2],
        "force": st.force,
        "applied_force": rf.applied_force,
        "contact_area": st.contact_area,
        "displaced_volume": st.displaced_volume,
        "chamber_volume_change": inst.reference_volume - float(r.chamber.chamber.mesh.volumes.sum()),
        "peak_strain": st.peak_strain,
        "penetration": st.penetration,
        "newton_iterations": st.iterations,
        "min_jacobian": st.min_jacobian,
        "mesh_path": MESH_PATHS.index(r.chamber.path),
        "mesh_min_shape": r.chamber.quality.min_shape,
        "voltages": r.voltages,
        "voltages_clean": r.voltages_clean,
        "dv": r.dv,
        "dv_clean": r.dv_clean,
        "rms_dv": rms(r.dv),
        "rms_dv_clean": rms(r.dv_clean),
        "image": r.image.astype(np.float32),
        "true_centre": centre,
        "com_error": float(np.linalg.norm(com - centre)),
        "com_error_xy": float(np.linalg.norm((com - centre)[:2])),
        **m,
        "timings": np.array([t[s] for s in STAGES]),
    }
    return Frame(index, seg, k, rf, st, r, t, record)
