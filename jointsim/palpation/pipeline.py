"""Coupled virtual palpation (paper III.C, Fig. 4): the MuJoCo bench rig presses targets into
the FEM membrane, the chamber mesh follows the membrane, and each 50 Hz frame gives what the
instrument records (256 noisy voltages), the difference image and its metrics.

One frame k of a target's program, in order:

1. **MuJoCo**: the rig advances one frame (1/frame_rate s) with the contact force of frame
   k − 1 held on the target (frame 0: the rig at rest at its start, not stepped);
2. **mechanics**: the membrane is solved with the target centre where the rig put it
   (:meth:`MembraneModel.press`, warm-started from frame k − 1); its contact force is what
   MuJoCo receives during the next frame;
3. **mesh**: the reference chamber mesh is morphed to the membrane's deformed inner surface
   (at the resolution of its P2 nodes), or remeshed when the morph inverts or degrades
   (:meth:`Palpation.deform`);
4. **forward**: the CEM forward model on that chamber gives the 256 clean voltages; noise at
   the scene's SNR (seeded per frame) gives the measured ones;
5. **reconstruction**: δV = V − V_ref (the steady-state reference: the mean of
   ``reference_frames`` noisy frames of the untouched sensor, as the paper subtracts it) is
   imaged by zeroth-order Tikhonov on the fixed voxel grid (one matrix–vector product) and the
   paper's metrics are taken of it.

The reference is the **inflated, untouched** membrane: the reservoir pressure inflates the
dome when the membrane model is built, so the reference chamber is the chamber mesh morphed to
that state (a membrane moulded flat is inflated to the dome's height instead, and the chamber
is meshed on that inflated surface: :func:`deployed_chamber`), and the Jacobian, the voxel
grid and the reconstruction matrix are built on it. A frame at zero indentation therefore
gives the reference mesh bit for bit and δV = 0 exactly on the morph path (its mesh-noise
floor is zero). A remeshed frame (``mesh_path``) takes its change between the remesh and the
same tetrahedra pulled back onto the reference chamber
(:func:`~jointsim.mesh.morph.pull_back`), which cancels the remeshing floor (~40 dB re the
standing voltage at the dataset resolution against the reference mesh; results/mesh_step_benchmark.md).

Resuming: every record is stored with a checkpoint of the rig (MuJoCo's integration state,
frame counter, recent heights) and of the membrane (displacement, warm-start history, target
centre, pressure); a rerun skips stored frames and continues from the last checkpoint of an
unfinished target, bit for bit as if never interrupted.
"""

from __future__ import annotations

import math
import time
from contextlib import contextmanager
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any, Callable, Iterator

import mujoco
import numpy as np
import trimesh

from ..eit.forward import ForwardModel
from ..eit.jacobian import jacobian
from ..eit.noise import gain_drift, noise_std
from ..eit.protocol import Protocol, skip_protocol
from ..geometry import DomeSurface, chamber_surface, electrode_layout
from ..io.store import Field, RecordStore, Schema
from ..mechanics.build import membrane_from_scene
from ..mechanics.dome import MembraneModel, MembraneState, UnreachablePose
from ..mechanics.fem import warp_device
from ..mechanics.geometric import indent_dome
from ..mesh.chamber import ChamberMesh, chamber_mesh, mesh_chamber
from ..mesh.morph import (
    ChamberMorpher,
    DeformedChamber,
    MeshInversionError,
    remeshed,
    untangled_note,
)
from ..mesh.tetmesh import TetMesh
from ..metrics import ImageMetrics, image_metrics, rms
from ..reconstruction.grid import ChamberGrid
from ..reconstruction.tikhonov import SVD, Reconstructor, choose_lambda
from .rig import Controller, Rig, RigFrame, load_rig, press_hold_retract
from ..scene import UNRECORDED_ELEMENT, PalpationSpec, Scene

__all__ = [
    "STAGES",
    "MESH_PATHS",
    "Segment",
    "Frame",
    "Palpation",
    "run_palpation",
    "deployed_chamber",
    "force_profile",
    "program_params",
    "metric_fields",
]

STAGES = ("mujoco", "mechanics", "mesh", "forward", "reconstruction")
MESH_PATHS = ("morph", "remesh")
MIN_CHAMBER_GAP = 0.2e-3  # m: inner surface to base; closer, the chamber cannot be meshed over the electrodes
MIN_QUALITY_RATIO = 0.05  # as deform_chamber's default (results/mesh_step_benchmark.md)
# × membrane thickness: how far the chamber's dome may lie off the membrane's inner surface.
# Measured: the coarsest membrane (16 rim vertices) lies 0.12 mm inside the cap's chamber, the
# 32-rim one 0.05 mm; the cap's chamber under a membrane moulded flat is 1.5 mm off
CHAMBER_FIT = 0.25
LAMBDA_REPEATS = 10  # noisy copies of the representative press pooled for the choice of λ
SCHEMA_VERSION = 1


# ---------------------------------------------------------------------------------------------
# The program: one segment per target
# ---------------------------------------------------------------------------------------------


def force_profile(force: float, ramp_s: float, hold_s: float, frame_rate: float) -> np.ndarray:
    """Force-mode program (n,) N at ``frame_rate`` Hz: a linear ramp from 0 to ``force`` in
    ``ramp_s`` s, a hold of ``hold_s`` s, and a ramp back to 0 (a step when ``ramp_s`` is 0)."""
    if not (math.isfinite(force) and force > 0):
        raise ValueError(f"force = {force!r}: must be > 0 N")
    if not (math.isfinite(ramp_s) and ramp_s >= 0):
        raise ValueError(f"force_ramp_s = {ramp_s!r}: must be >= 0 s")
    if not (math.isfinite(hold_s) and hold_s >= 0):
        raise ValueError(f"hold_s = {hold_s!r}: must be >= 0 s")
    end = 2 * ramp_s + hold_s
    n = int(math.ceil(end * frame_rate - 1e-9)) + 1
    t = np.arange(n) / frame_rate
    if ramp_s == 0:
        return np.where(t <= hold_s + 1e-12, force, 0.0) if hold_s > 0 else np.full(n, force)
    return force * np.interp(t, [0.0, ramp_s, ramp_s + hold_s, end], [0.0, 1.0, 1.0, 0.0])


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
            c = Controller.force(force_profile(spec.force, spec.force_ramp, spec.hold, frame_rate), xy=spec.xy, gap=spec.gap)
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
    command, the force MuJoCo received), the membrane ``state``, the ``chamber`` it gave
    (path taken and quality), the noisy and clean voltages and changes (256,) V, the
    ``image`` (n_cells,) S/m and its noise-normalised version, the ``metrics`` (None when the
    image is all zero), the displaced saline's centroid ``true_centre`` (3,) m, the per-stage
    ``timings`` s, and the ``record`` stored for it."""

    index: int
    segment: Segment
    frame: int
    rig: RigFrame
    state: MembraneState
    chamber: DeformedChamber
    voltages: np.ndarray
    voltages_clean: np.ndarray
    dv: np.ndarray
    dv_clean: np.ndarray
    image: np.ndarray
    image_normalised: np.ndarray
    metrics: ImageMetrics | None
    true_centre: np.ndarray
    timings: dict[str, float]
    record: dict[str, Any]


@contextmanager
def timed(timings: dict[str, float], name: str) -> Iterator[None]:
    t0 = time.perf_counter()
    yield
    timings[name] = timings.get(name, 0.0) + time.perf_counter() - t0


# ---------------------------------------------------------------------------------------------
# The membrane's inner surface at P2 resolution
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _InnerSurface:
    """The membrane's inner surface as the linear sub-triangles of its 6-node faces (the
    surface the FEM's saline volume is integrated over): P2 node indices ``nodes`` (n,),
    ``faces`` (m, 3) into them (normals out of the chamber), ``rim`` (k,) anticlockwise, and the
    reference positions ``X`` (n, 3) with the rim's edge midpoints moved onto the base circle
    (they never move). The chamber follows this surface, so its volume change matches the
    FEM's displaced volume; the vertex-only ``MembraneState.dome`` drops the midside nodes.

    The reference is the moulded surface (the moulded cap; the morph then takes the chamber to
    the reservoir's inflation), or, for a membrane moulded flat, the inflated one: ``u0`` (n, 3)
    is the membrane's displacement included in ``X`` (zero for the cap)."""

    nodes: np.ndarray
    faces: np.ndarray
    rim: np.ndarray
    X: np.ndarray
    u0: np.ndarray

    @classmethod
    def of(cls, model: MembraneModel, base_radius: float, inflated: bool = False) -> "_InnerSurface":
        """The inner surface of ``model``; ``inflated``: its reference is the model's current
        (inflated, untouched) state instead of the moulded one."""
        # reads the model's inner sub-triangles (the pressure term's surface)
        tris = np.asarray(model.inner_tris)
        nodes, local = np.unique(tris, return_inverse=True)
        faces = local.reshape(-1, 3)[:, ::-1]  # the FEM's point into the chamber; a DomeSurface's out
        u0 = model.u[nodes] if inflated else np.zeros((len(nodes), 3))
        X = model.mesh.nodes[nodes] + u0
        # the rim: the surface's nodes the model bonds (by the base plane for a cap, by the rim
        # circle for a flat sheet, whose whole inner surface lies in the base plane)
        rim = np.flatnonzero(model.fixed[nodes, 0])
        rim = rim[np.argsort(np.arctan2(X[rim, 1], X[rim, 0]))]
        X[rim, :2] *= base_radius / np.hypot(X[rim, 0], X[rim, 1])[:, None]
        X[rim, 2] = 0.0
        return cls(nodes, np.ascontiguousarray(faces), rim, X, u0)

    def dome(self, u: np.ndarray | None) -> DomeSurface:
        """The surface displaced by the membrane's ``u`` (n_P2, 3) (None: the reference)."""
        v = self.X.copy() if u is None else self.X + (u[self.nodes] - self.u0)
        if u is not None:
            v[self.rim] = self.X[self.rim]  # bonded: zero displacement, kept bit-exact
        return DomeSurface(v, self.faces, self.rim)


# ---------------------------------------------------------------------------------------------
# The set-up
# ---------------------------------------------------------------------------------------------


def deployed_chamber(scene: Scene, dome: DomeSurface | None = None, **kw) -> ChamberMesh:
    """The chamber mesh of ``scene``'s sensor before any press. Moulded as a cap: the scene's
    dome (:func:`~jointsim.mesh.chamber.chamber_mesh`; the reservoir's inflation is a morph of
    it). Moulded flat: the membrane's inflated inner surface ``dome`` (default: a membrane of
    the scene built and inflated here), since the flat shape holds no chamber to morph from.
    ``kw`` goes to :func:`~jointsim.mesh.chamber.mesh_chamber` (``use_cache``)."""
    if scene.membrane.moulding == "cap":
        return chamber_mesh(scene, **kw)
    if dome is None:
        model = membrane_from_scene(replace(scene, target=replace(scene.target, kind="rigid")))  # the target is not touched
        dome = _InnerSurface.of(model, scene.chamber.base_radius, inflated=True).dome(None)
    return mesh_chamber(chamber_surface(dome), electrode_layout(scene), scene.mesh, **kw)


class Palpation:
    """Everything a palpation run shares, built once from ``scene`` (its [palpation] section
    unless ``spec`` is given): the chamber mesh and its morpher onto the membrane's dome, the
    reference (inflated, untouched) chamber and its voltages, the Jacobian on the voxel grid
    and the Tikhonov reconstruction matrix (λ by cross-validation on a representative press),
    the noisy steady-state reference, and the program's :attr:`segments`.

    Parameters
    ----------
    scene : the sensor; its [mesh] sets the chamber resolution, [membrane] the FEM, [noise]
        the SNR, seed and frame rate, [drive] the current and skip
    spec : the palpation program (default ``scene.palpation``)
    rig_path : MJCF of the bench (default ``scenes/bench_rig.xml``)
    chamber : a ready reference chamber mesh of ``scene`` (default: :func:`deployed_chamber`);
        its dome must lie on the membrane's inner surface (within ``CHAMBER_FIT`` × the
        membrane's thickness), or it is refused
    device : the Warp device of the membrane's element kernel ("cpu", or "cuda:0" where a GPU
        is); the frames agree to round-off

    Attributes used per frame: ``protocol`` (skip-N, all electrodes against ground),
    ``v_ref`` (256,) clean reference voltages, ``v_ref_measured`` (256,) the reference as
    measured (mean of ``reference_frames`` noisy frames), ``noise_std`` V per frame,
    ``grid`` (ChamberGrid), ``reconstructor`` (R (n_cells, 256)), ``cell_noise`` (n_cells,)
    the image's noise std per cell. ``setup_timings`` s per set-up stage.
    """

    def __init__(self, scene: Scene, spec: PalpationSpec | None = None, *, rig_path: str | Path | None = None,
                 chamber: ChamberMesh | None = None, device: str = "cpu"):
        self.scene = scene
        self.device = warp_device(device)
        self.spec = spec = scene.palpation if spec is None else spec
        self.rig_path = rig_path
        self.frame_rate = scene.noise.frame_rate_hz
        self.seed = int(scene.noise.seed)
        self.setup_timings: dict[str, float] = {}
        t = self.setup_timings
        if spec.fdm_contact_impedance and scene.electrodes.contact_impedance_by_freq is None:
            raise ValueError("palpation.fdm_contact_impedance = true: needs electrodes.contact_impedance_by_freq_ohm_m2")
        self.segments = _segments(spec, self.frame_rate)
        self.n_records = self.segments[-1].start + self.segments[-1].n_frames

        flat = scene.membrane.moulding == "flat"
        #: the membrane's inflated displacement where it was moulded flat (each later membrane
        #: starts its inflation there), else None
        self.inflated_u: np.ndarray | None = None
        with timed(t, "membrane"):
            # the membrane is inflated when the model is built (by the reservoir, or to the dome
            # height when moulded flat): the reference is that state
            model = self.membrane(spec.target_radii[0])
            if flat:
                self.inflated_u = model.u[: model.mesh.n_nodes].copy()
            self._surface = _InnerSurface.of(model, scene.chamber.base_radius, inflated=flat)
            self.membrane_dome = self._surface.dome(None)  # the inner surface the morpher maps from
            self.reference_dome = self._surface.dome(model.u)
            self.membrane_nodes = model.mesh.n_nodes
            # the membrane's corner tetrahedra (the P2 mesh without midside nodes), for export
            self.membrane_mesh = TetMesh(model.mesh.nodes, model.mesh.corner_tets)
        with timed(t, "chamber"):
            self.chamber = deployed_chamber(scene, self.membrane_dome) if chamber is None else chamber
            self.morpher = ChamberMorpher(self.chamber, self.membrane_dome)
            gap, allowed = self.morpher.surface_gap, CHAMBER_FIT * scene.chamber.membrane_thickness
            if gap > allowed:
                raise ValueError(f"chamber: its dome lies up to {gap * 1e3:.3g} mm off the membrane's inner surface (allowed "
                                 f"{allowed * 1e3:.3g} mm); mesh it with deployed_chamber(scene) (membrane.moulding = "
                                 f"{scene.membrane.moulding!r})")
            self.reference = self.morpher(self.reference_dome)
            self.reference_volume = float(self.reference.mesh.volumes.sum())
            self._reference_min_shape = self.morpher.reference_quality.min_shape
        n_el = scene.electrodes.count
        self.protocol: Protocol = skip_protocol(n_el, scene.drive.skip, scene.drive.current)
        self.n_meas = self.protocol.n_meas
        with timed(t, "forward"):
            # every morphed frame's model is made like this one: its pattern and analysis carry over
            self._forward = ForwardModel.from_chamber(self.reference, scene).shared()
            fields = self._forward.solve(scene.saline.conductivity)
            self.v_ref = self.voltages(self.reference) if spec.fdm_contact_impedance else fields.voltages(self.protocol)
        with timed(t, "jacobian"):
            self.grid = ChamberGrid.over(self.reference.mesh, spec.cells)
            self.jacobian = jacobian(fields, self.protocol, coarse=self.grid.C)
        self.noise_std = noise_std(self.v_ref, scene.noise.snr_db)
        n_ref = spec.reference_frames
        # the steady state the paper subtracts: the mean of n_ref frames, noise std/√n_ref
        self.v_ref_measured = self.v_ref + self._rng("reference").normal(0.0, self.noise_std / math.sqrt(n_ref), self.n_meas)
        # a frame's δV carries the frame's noise and the reference's
        self.dv_noise_std = self.noise_std * math.sqrt(1.0 + 1.0 / n_ref)
        self.gains = (
            gain_drift(self.n_records, self.n_meas, scene.noise.drift_per_s, self.frame_rate, rng=self._rng("drift"))
            if scene.noise.drift_per_s > 0 else None
        )
        with timed(t, "lambda"):
            self.lambda_press, dv_rep = self._representative_press()
            noisy = dv_rep[None] + self._rng("lambda").normal(0.0, self.dv_noise_std, (LAMBDA_REPEATS, self.n_meas))
            svd = SVD.of(self.jacobian)
            choice = choose_lambda(svd, noisy, spec.lambda_method, seed=self.seed)
            self.reconstructor = Reconstructor(svd.reconstruction_matrix(choice.lam), choice)
            self.cell_noise = self.reconstructor.noise_std(self.dv_noise_std)

    # -- pieces --------------------------------------------------------------------------

    def _rng(self, what: str, index: int = 0) -> np.random.Generator:
        """Independent seeded streams: the reference, the drift, λ's noise, and one per frame."""
        key = {"reference": 0, "drift": 1, "lambda": 2, "frame": 3}[what]
        return np.random.default_rng([self.seed, key, index])

    def membrane(self, radius: float) -> MembraneModel:
        """A fresh membrane (inflated by the reservoir, untouched) for a target of ``radius`` m."""
        return membrane_from_scene(self.scene, target_radius=radius, device=self.device, inflate_from=self.inflated_u)

    def voltages(self, chamber: ChamberMesh) -> np.ndarray:
        """Clean voltages (256,) V of ``chamber`` filled with the scene's saline; with
        ``fdm_contact_impedance`` injection s runs at carrier s mod n_carriers with that
        carrier's contact impedances (ground's unchanged)."""
        model = ForwardModel.from_chamber(chamber, self.scene, like=self._forward)
        sigma = self.scene.saline.conductivity
        if not self.spec.fdm_contact_impedance:
            return model.solve(sigma).voltages(self.protocol)
        e = self.scene.electrodes
        zf = np.asarray(e.contact_impedance_by_freq, float)
        z = np.column_stack([zf, np.full(len(zf), e.ground_contact_impedance)])
        carrier = np.arange(self.protocol.n_stim) % len(zf)
        return model.voltages_by_frequency(sigma, self.protocol, z, carrier)

    def _representative_press(self) -> tuple[dict[str, float], np.ndarray]:
        """A geometric indentation by the middle target at the program's depth (1 mm in force
        mode) at its xy, morphed onto the reference: its clean δV is the data λ is chosen for
        (fixed before any frame, so a resumed run images with the same λ)."""
        spec = self.spec
        radius = float(sorted(spec.target_radii)[len(spec.target_radii) // 2])
        depth = spec.depth if spec.mode != "force" and spec.depth > 0 else 1e-3
        thickness = self.scene.chamber.membrane_thickness
        for d in (depth, depth / 2, depth / 4):
            try:
                ind = indent_dome(self.reference_dome, spec.xy, d, radius, thickness)
                chamber, q = self.morpher.morph(ind.dome)
                if q.min_shape < MIN_QUALITY_RATIO * self._reference_min_shape:
                    continue
            except (MeshInversionError, ValueError):
                continue
            return {"radius": radius, "depth": d, "x": spec.xy[0], "y": spec.xy[1]}, self.voltages(chamber) - self.v_ref
        raise ValueError(f"palpation: no representative press of a {radius * 1e3:g} mm radius target morphs the chamber; "
                         "lower palpation.depth_mm")

    def image(self, dv: np.ndarray, true_centre: np.ndarray | None = None,
              target_volume: float | None = None) -> tuple[np.ndarray, np.ndarray, ImageMetrics | None]:
        """The instrument's image of ``dv`` (256,) V: Δσ (n_cells,) S/m by the reconstruction
        matrix, its noise-normalised version, and their :class:`ImageMetrics` (None when the
        image is all zero; ``true_centre`` (3,) m with NaN and ``target_volume`` 0 count as
        not known)."""
        image = self.reconstructor.image(dv)
        normalised = image / self.cell_noise
        metrics = None
        if np.any(image):
            known = true_centre is not None and not np.isnan(true_centre).any()
            metrics = image_metrics(self.grid, normalised, true_centre if known else None, target_volume or None,
                                    amplitude=image)
        return image, normalised, metrics

    def inner_surface(self, state: MembraneState) -> DomeSurface:
        """The membrane's deformed inner (chamber) surface at the resolution of its P2 nodes."""
        return self._surface.dome(state.u)

    def deform(self, dome: DomeSurface, reference: DomeSurface | None = None) -> DeformedChamber:
        """The chamber whose dome is ``dome`` (from :meth:`inner_surface`), by
        ``spec.mesh_update``: "morph" the reference mesh (raises
        :class:`~jointsim.mesh.morph.MeshInversionError`), "remesh", or "auto": morph, and
        remesh when the morph inverts an element or its smallest shape measure falls below
        ``MIN_QUALITY_RATIO`` × the reference mesh's. A remesh tetrahedralises the morphed
        chamber's boundary (the same geometry, new tetrahedra; cached by its hash, so a rerun
        gets the same mesh) and is pulled back onto the chamber under ``reference`` (default:
        the untouched :attr:`reference_dome`), so that the frame's voltage change is taken on
        one mesh (:meth:`DeformedChamber.change`) without the remeshing noise floor."""
        free = np.ones(len(dome.vertices), bool)
        free[dome.rim] = False
        gap = float(dome.vertices[free, 2].min())
        if gap < MIN_CHAMBER_GAP:
            raise UnreachablePose(
                f"the membrane's inner surface is {gap * 1e3:.2f} mm above the base at its lowest (the chamber collapses "
                f"onto the electrodes; at least {MIN_CHAMBER_GAP * 1e3:g} mm is needed): palpation.depth_mm is too deep for this target"
            )
        mode = self.spec.mesh_update
        why = "mesh_update = 'remesh'"
        if mode != "remesh":
            try:
                chamber, q = self.morpher.morph(dome, MIN_QUALITY_RATIO if mode == "auto" else 0.0)
                if mode == "morph" or q.min_shape >= MIN_QUALITY_RATIO * self._reference_min_shape:
                    return DeformedChamber(chamber, "morph", f"morphed: min shape {q.min_shape:.3g}{untangled_note(chamber)}", q)
                why = f"morph quality {q.min_shape:.3g} below {MIN_QUALITY_RATIO} x reference {self._reference_min_shape:.3g}"
            except MeshInversionError as e:
                if mode == "morph":
                    raise
                why = f"morph failed: {e}"
        mesh = self.chamber.mesh
        faces = mesh.boundary_faces
        surface = trimesh.Trimesh(mesh.nodes + self.morpher.displacement(dome), faces, process=True, validate=False)
        surface.fix_normals()
        chamber = mesh_chamber(surface, self.chamber.layout, self.scene.mesh)
        return remeshed(chamber, dome, self.reference_dome if reference is None else reference, why)

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
        m, c = self.n_meas, self.grid.n_cells
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
                F("true_centre", (3,), "float64", "m", "centroid of the displaced saline (NaN when none)"),
                F("com", (3,), "float64", "m", "CoM of the perturbation cluster (noise-normalised image)"),
                F("com_error", (), "float64", "m", "|com - true_centre|"),
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
        self.morpher.free()
        self._forward.free()


# ---------------------------------------------------------------------------------------------
# The loop
# ---------------------------------------------------------------------------------------------


def program_params(scene: Scene, spec: PalpationSpec | None = None, rig_path: str | Path | None = None) -> dict[str, Any]:
    """The run settings that shape a palpation's data beyond the scene file's text: the
    effective program (after command-line overrides), the mesh and membrane resolution, the
    noise, the rig model and the number of frames. JSON-ready; the store's identity uses it,
    so a run resumes only with the same settings."""
    spec = scene.palpation if spec is None else spec
    d = asdict(spec)
    d["target_radii"] = list(d["target_radii"])
    d["xy"] = list(d["xy"])
    segs = _segments(spec, scene.noise.frame_rate_hz)
    return {
        "palpation": d,
        "mesh": asdict(scene.mesh),
        "membrane": {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(scene.membrane).items()
                     if not (k == "element" and v == UNRECORDED_ELEMENT)},
        "noise": asdict(scene.noise),
        "rig": str(rig_path) if rig_path else "scenes/bench_rig.xml",
        "n_records": segs[-1].start + segs[-1].n_frames,
        "frames_per_target": [sg.n_frames for sg in segs],
    }


_MEMBRANE_KEYS = ("u", "hist_centre", "hist_u", "centre", "pressure", "compliance", "tangent_u", "friction_nodes", "friction_anchors")


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


def _displaced_centroid(reference: ChamberMesh, chamber: ChamberMesh) -> np.ndarray:
    """Centroid (3,) of the saline the frame lost against the reference: (V₀c₀ − V c)/(V₀ − V)."""
    a, b = reference.mesh, chamber.mesh
    va, vb = a.volumes, b.volumes
    lost = va.sum() - vb.sum()
    if lost <= 1e-9 * va.sum():
        return np.full(3, np.nan)
    return (va @ a.centroids - vb @ b.centroids) / lost


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


def metric_fields(metrics: ImageMetrics | None) -> dict[str, Any]:
    """The image metrics a record stores: ``com`` (3,) m, ``sum_sigma``, ``diameter`` m,
    ``extent_xy`` m, ``cluster_cells`` (NaN and 0 for an all-zero image)."""
    if metrics is None:
        return {"com": np.full(3, np.nan), "sum_sigma": np.nan, "diameter": np.nan, "extent_xy": np.nan, "cluster_cells": 0}
    return {"com": metrics.com, "sum_sigma": metrics.sum_sigma, "diameter": metrics.diameter_equivalent,
            "extent_xy": metrics.extent_xy, "cluster_cells": metrics.n_cells}


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
    # a hold leaves the membrane bit for bit where it was (no servo motion, no Newton step): the
    # chamber and its clean voltages are then the last frame's, as a recomputation would give
    # them (both are deterministic in the membrane), and only the noise is drawn anew. At the
    # paper's fidelity that is the mesh and forward stages' ~3 s of each hold frame
    same = last is not None and np.array_equal(last.state.u, st.u)
    with timed(t, "mesh"):
        dc = last.chamber if same else pal.deform(pal.inner_surface(st))
    index = seg.start + k
    with timed(t, "forward"):
        clean = last.voltages_clean.copy() if same else dc.change(pal.voltages, pal.v_ref)
        gain = pal.gains[index] if pal.gains is not None else 1.0
        v = clean * gain + pal._rng("frame", index).normal(0.0, pal.noise_std, pal.n_meas)
    dv, dv_clean = v - pal.v_ref_measured, clean - pal.v_ref
    with timed(t, "reconstruction"):
        centre = _displaced_centroid(pal.reference, dc.chamber)
        image, normalised, metrics = pal.image(dv, centre, st.displaced_volume)
    m = metric_fields(metrics)
    com = m["com"]
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
        "chamber_volume_change": pal.reference_volume - float(dc.chamber.mesh.volumes.sum()),
        "peak_strain": st.peak_strain,
        "penetration": st.penetration,
        "newton_iterations": st.iterations,
        "min_jacobian": st.min_jacobian,
        "mesh_path": MESH_PATHS.index(dc.path),
        "mesh_min_shape": dc.quality.min_shape,
        "voltages": v,
        "voltages_clean": clean,
        "dv": dv,
        "dv_clean": dv_clean,
        "rms_dv": rms(dv),
        "rms_dv_clean": rms(dv_clean),
        "image": image.astype(np.float32),
        "true_centre": centre,
        "com_error": float(np.linalg.norm(com - centre)),
        "com_error_xy": float(np.linalg.norm((com - centre)[:2])),
        **m,
        "timings": np.array([t[s] for s in STAGES]),
    }
    return Frame(index, seg, k, rf, st, dc, v, clean, dv, dv_clean, image, normalised, metrics, centre, t, record)
