"""The instrument: the sensor's measurement chain, built once, and the one frame step.

An :class:`Instrument` owns everything between the membrane and a frame's numbers: the chamber
mesh and the one policy by which it follows the membrane (:func:`~jointsim.mesh.morph.deform_chamber`:
morph the reference mesh, remesh when the morph degrades), the electrodes' readout (forward
model, protocol, the reference voltages, the noise), and the image (Jacobian on the voxel grid,
Tikhonov with λ chosen once, the paper's metrics). It is ready when built
(:meth:`Instrument.build`), and :meth:`Instrument.measure` is the frame step every job uses:

    deformed inner surface  →  chamber (morph or remesh)  →  clean voltages
        →  measured voltages (gain, noise)  →  δV against the measured reference  →  image, metrics

Palpation (:mod:`jointsim.palpation`), datasets (:mod:`jointsim.dataset`), the protocol study
and ``jointsim forward`` all call it. The mechanics hand it the membrane's deformed inner surface
(:class:`~jointsim.mechanics.inner_surface.InnerSurface`); nothing here steps the mechanics.

The reference is the **inflated, untouched** membrane: the reservoir pressure inflates the dome
when the membrane model is built, so the reference chamber is the chamber mesh morphed to that
state (a membrane moulded flat is inflated to the dome's height instead, and the chamber is meshed
on that inflated surface: :func:`deployed_chamber`); the Jacobian, the voxel grid and the
reconstruction matrix are built on it. Zero indentation therefore gives the reference mesh bit
for bit and δV = 0 exactly on the morph path. A remeshed frame takes its change between the
remesh and the same tetrahedra pulled back onto the reference chamber, which cancels the
remeshing floor (results/mesh_step_benchmark.md).

A :class:`Readout` is the electrodes' side alone, so a dataset can read a randomised sensor
(moved electrodes, another saline, contact impedance and SNR) through the same chamber and image
it with the nominal instrument's reconstruction, as a real instrument calibrated once would.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from .eit.forward import ForwardModel, LeadFields
from .eit.jacobian import jacobian
from .eit.noise import noise_std
from .eit.protocol import Protocol, scene_protocol
from .geometry import DomeSurface, chamber_surface, electrode_layout
from .mechanics.build import membrane_from_scene
from .mechanics.dome import MembraneModel
from .mechanics.geometric import indent_dome
from .mechanics.inner_surface import InnerSurface
from .mesh.chamber import ChamberMesh, chamber_mesh, mesh_chamber
from .mesh.electrodes import ElectrodePatch, disc_patches, layout_patches
from .mesh.morph import MIN_QUALITY_RATIO, ChamberMorpher, DeformedChamber, MeshInversionError, deform_chamber
from .metrics import ImageMetrics, image_metrics
from .reconstruction.grid import ChamberGrid
from .reconstruction.tikhonov import DEPTH_EXPONENT, LAPLACIAN_RIDGE, SVD, Reconstructor, choose_lambda, prior_matrix
from .reconstruction.tv import TVImager, difference_operator, discrepancy_lambda
from .scene import Scene
from .timing import timed

__all__ = ["STAGES", "Instrument", "Readout", "Imager", "Reading", "deployed_chamber", "dent_centroid"]

STAGES = ("mesh", "forward", "reconstruction")  # a frame step's stages, timed in Reading.timings
# × membrane thickness: how far the chamber's dome may lie off the membrane's inner surface.
# Measured: the coarsest membrane (16 rim vertices) lies 0.12 mm inside the cap's chamber, the
# 32-rim one 0.05 mm; the cap's chamber under a membrane moulded flat is 1.5 mm off
CHAMBER_FIT = 0.25
LAMBDA_REPEATS = 10  # noisy copies of the representative press pooled for the choice of λ
# independent seeded streams of the instrument (np.random.default_rng([seed, stream, index]))
STREAMS = {"reference": 0, "drift": 1, "lambda": 2, "frame": 3}


def stream(seed: int, what: str, index: int = 0) -> np.random.Generator:
    """The instrument's noise stream ``what`` (:data:`STREAMS`) for ``seed``, frame ``index``."""
    return np.random.default_rng([int(seed), STREAMS[what], index])


# ---------------------------------------------------------------------------------------------
# The electrodes' side
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Readout:
    """What turns a chamber into voltages: the forward model made on a reference chamber
    (``forward``: its electrode patches, ground, contact impedances, element order; its solver
    analysis shared by the morphs of that chamber), the ``protocol``, the saline's
    ``conductivity`` S/m, the noise level ``snr_db`` (re the mean standing |V|), and the
    reference readings of the untouched ``reference`` chamber: clean ``v_ref`` (n_meas,) V, the
    noise ``noise_std`` V of one frame, and ``v_ref_measured``, the steady state as measured
    (the mean of ``reference_frames`` noisy frames).

    ``centres`` (n_el, 3) m: the electrode discs the patches were clipped from when they are
    not the chamber's own (a dataset's moved electrodes), re-clipped on a remesh; None: the
    chamber's own patches. ``z_by_freq`` (n_carriers, n_el), ``carrier`` (n_stim,): with FDM
    contact impedances, injection s runs at carrier ``carrier[s]``."""

    forward: ForwardModel
    reference: ChamberMesh
    patches: tuple[ElectrodePatch, ...]
    protocol: Protocol
    conductivity: float
    snr_db: float
    reference_frames: int
    v_ref: np.ndarray
    noise_std: float
    v_ref_measured: np.ndarray
    centres: np.ndarray | None = None
    radii: np.ndarray | None = None
    z_by_freq: np.ndarray | None = None
    carrier: np.ndarray | None = None
    # the lead fields of the last chamber solved, shared with the readouts made from this one
    # by :meth:`with_protocol` (one solve serves every protocol of a frame)
    _last: list = field(default_factory=list, repr=False)

    @classmethod
    def on(cls, reference: ChamberMesh, scene: Scene, protocol: Protocol, *, rng: np.random.Generator | None,
           reference_frames: int, conductivity: float | None = None, contact_impedance: float | np.ndarray | None = None,
           offsets: np.ndarray | None = None, snr_db: float | None = None, fdm: bool = False,
           backend: str = "auto", reach: float = 0.0, like: ForwardModel | None = None) -> "Readout":
        """The readout of ``scene``'s electrodes on the chamber ``reference`` (the untouched
        sensor), with the scene's saline, contact impedances and SNR unless given
        (``contact_impedance``: one value for every electrode, the ground included, or one per
        electrode in the layout's order (a fitted sensor: :mod:`~jointsim.eit.fit`);
        ``offsets`` (k, 2) m: the first k electrodes moved in the base plane, the driven ones and
        a floating reference; a passive reference stays). The measured
        reference is drawn from ``rng`` (None: noise-free). ``fdm``: per-carrier contact
        impedances ([electrodes] contact_impedance_by_freq_ohm_m2). ``reach`` m: the moved base
        discs keep every face they could cover moved up to it from the layout's places
        (:func:`~jointsim.mesh.electrodes.disc_patches`), so that readouts with other offsets
        within it have one CEM pattern; ``like``: an earlier readout's forward model of a
        chamber of this topology, whose pattern and solver analysis this one keeps where its
        patches have that model's faces (:meth:`~jointsim.eit.forward.ForwardModel.on`)."""
        e = scene.electrodes
        order = scene.mesh.element_order
        centres = radii = None
        if offsets is not None:
            layout = reference.layout
            centres = layout.centres.copy()
            centres[: len(offsets), :2] += offsets
            radii = layout.radii
            # (electrodes on the membrane placed where the reference dome is now: at rest there)
            around = layout.centres if reach > 0 else None
            patches = [p.follow(reference.mesh.nodes)
                       for p in layout_patches(reference.mesh, replace(layout, centres=centres), quadratic=order == 2,
                                               around=around, reach=reach)]
        else:
            patches = reference.patches(order)
        if contact_impedance is None:
            z = e.contact_impedances
        else:
            z = np.broadcast_to(np.asarray(contact_impedance, float), (len(patches),)).copy()
        forward = ForwardModel.like_or_new(like, reference.mesh, patches, reference.ground, z, backend, order).shared()
        z_by_freq = carrier = None
        if fdm:
            if e.contact_impedance_by_freq is None:
                raise ValueError("fdm contact impedances: the scene needs electrodes.contact_impedance_by_freq_ohm_m2")
            zf = np.asarray(e.contact_impedance_by_freq, float)
            z_by_freq = np.column_stack([zf, np.full(len(zf), e.ground_contact_impedance)])
            carrier = np.arange(protocol.n_stim) % len(zf)
        sigma = scene.saline.conductivity if conductivity is None else float(conductivity)
        snr = scene.noise.snr_db if snr_db is None else float(snr_db)
        readout = cls(forward, reference, tuple(patches), protocol, sigma, snr, reference_frames, np.empty(0), math.nan,
                      np.empty(0), centres, radii, z_by_freq, carrier)
        return readout._referenced(rng)

    def with_protocol(self, protocol: Protocol, rng: np.random.Generator | None = None) -> "Readout":
        """This readout measuring by ``protocol`` (its reference readings anew, the measured
        one drawn from ``rng``; None: noise-free). The two share their solves."""
        carrier = None if self.z_by_freq is None else np.arange(protocol.n_stim) % len(self.z_by_freq)
        return replace(self, protocol=protocol, carrier=carrier)._referenced(rng)

    def _referenced(self, rng: np.random.Generator | None) -> "Readout":
        """This readout with its reference readings taken (the measured one drawn from ``rng``)."""
        v_ref = self.voltages(self.reference, same_topology=True)
        std = noise_std(v_ref, self.snr_db)
        measured = v_ref if rng is None else v_ref + rng.normal(0.0, std / math.sqrt(self.reference_frames), v_ref.shape)
        return replace(self, v_ref=v_ref, noise_std=std, v_ref_measured=measured)

    @property
    def n_meas(self) -> int:
        return self.protocol.n_meas

    @property
    def dv_noise_std(self) -> float:
        """Noise std of one frame's δV: the frame's noise and the measured reference's."""
        return self.noise_std * math.sqrt(1.0 + 1.0 / self.reference_frames)

    def model(self, chamber: ChamberMesh, same_topology: bool) -> ForwardModel:
        """The forward model of ``chamber``: a morph of the reference (``same_topology``) keeps
        its patches (those on the membrane followed to its nodes), pattern and solver analysis;
        a remesh gets its electrodes clipped anew (those on the membrane carried over)."""
        if same_topology:
            patches = [p.follow(chamber.mesh.nodes) for p in self.patches]
        else:
            patches = self._patches_of(chamber)
        return self.forward.on(chamber.mesh, patches)

    def fields(self, chamber: ChamberMesh, same_topology: bool) -> LeadFields:
        """Lead fields of ``chamber`` filled with this readout's saline (the last chamber's
        are kept: asked again, by this readout or one :meth:`with_protocol` made, they are
        not solved again)."""
        if self._last and self._last[0] is chamber.mesh:
            return self._last[1]
        fields = self.model(chamber, same_topology).solve(self.conductivity)
        self._last[:] = [chamber.mesh, fields]
        return fields

    def voltages(self, chamber: ChamberMesh, same_topology: bool) -> np.ndarray:
        """Clean voltages (n_meas,) V of ``chamber``."""
        if self.z_by_freq is None:
            return self.fields(chamber, same_topology).voltages(self.protocol)
        model = self.model(chamber, same_topology)
        return model.voltages_by_frequency(self.conductivity, self.protocol, self.z_by_freq, self.carrier)

    def change(self, dc: DeformedChamber) -> np.ndarray:
        """Clean voltages of a deformed chamber, its change taken on one mesh (a remesh against
        its pull-back: :meth:`~jointsim.mesh.morph.DeformedChamber.change`)."""
        same = dc.path == "morph"
        return dc.change(lambda c: self.voltages(c, same), self.v_ref)

    def free(self) -> None:
        self._last.clear()
        self.forward.free()

    def _patches_of(self, chamber: ChamberMesh) -> list[ElectrodePatch]:
        order = self.forward.order
        if self.centres is None:
            return chamber.carry(list(self.patches), order)
        clip = chamber.layout.clipped
        base = disc_patches(chamber.mesh, self.centres[clip], self.radii[clip], quadratic=order == 2)
        own = replace(chamber, electrodes=[base.pop(0) if c else p for c, p in zip(clip, chamber.electrodes)])
        return own.carry(list(self.patches), order)


# ---------------------------------------------------------------------------------------------
# The image
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Imager:
    """The instrument's reconstruction: the voxel ``grid``, the ``jacobian`` (n_meas, n_cells)
    of the reference chamber, the Tikhonov ``reconstructor`` (λ chosen once), and each cell's
    image noise std ``cell_noise`` (n_cells,) under the frame's δV noise; ``tv`` the total
    variation imager that refines the reconstructor's image (prior "tv"), else None."""

    grid: ChamberGrid
    jacobian: np.ndarray
    reconstructor: Reconstructor
    cell_noise: np.ndarray
    tv: TVImager | None = None

    @classmethod
    def choose(cls, grid: ChamberGrid, J: np.ndarray, dv_for_lambda: np.ndarray, method: str, dv_noise_std: float,
               seed: int, prior: str = "tikhonov", depth_exponent: float = DEPTH_EXPONENT) -> "Imager":
        """λ by ``method`` cross-validation on the noisy frames ``dv_for_lambda`` (k, n_meas),
        for the image ``prior`` (:data:`~jointsim.reconstruction.tikhonov.PRIORS`; "depth" with
        ``depth_exponent``; "tv": the Laplacian's image refined by total variation, its λ by
        the discrepancy principle on the same frames, :mod:`~jointsim.reconstruction.tv`; the
        cell noise stays the Laplacian's, a normalisation of the image)."""
        L = grid.laplacian() if prior in ("laplacian", "tv") else None
        P = prior_matrix(prior, J, L, grid.centroid[:, 2], depth_exponent, 0.5 * float(np.cbrt(grid.voxel_volume)))
        svd = SVD.of(J) if P is None else SVD.generalized(J, P)
        choice = choose_lambda(svd, dv_for_lambda, method, seed=seed)
        rec = Reconstructor(svd.reconstruction_matrix(choice.lam), choice)
        tv = None
        if prior == "tv":
            lam2 = choice.lam**2
            starts = np.array([rec.image(d) for d in np.atleast_2d(dv_for_lambda)])
            tv = discrepancy_lambda(J, difference_operator(L), dv_for_lambda, starts, dv_noise_std,
                                    lam2 * LAPLACIAN_RIDGE * float(L.diagonal().mean()), lam2)
        return cls(grid, J, rec, rec.noise_std(dv_noise_std), tv)

    def image(self, dv: np.ndarray, true_centre: np.ndarray | None = None,
              target_volume: float | None = None) -> tuple[np.ndarray, np.ndarray, ImageMetrics | None]:
        """The image of ``dv`` (n_meas,) V: Δσ (n_cells,) S/m, its noise-normalised version, and
        their :class:`ImageMetrics` (None when the image is all zero; ``true_centre`` (3,) m with
        NaN and ``target_volume`` 0 count as not known)."""
        image = self.reconstructor.image(dv)
        if self.tv is not None:
            image = self.tv.image(dv, image)
        normalised = image / self.cell_noise
        metrics = None
        if np.any(image):
            known = true_centre is not None and not np.isnan(true_centre).any()
            metrics = image_metrics(self.grid, normalised, true_centre if known else None, target_volume or None,
                                    amplitude=image)
        return image, normalised, metrics


# ---------------------------------------------------------------------------------------------
# One frame
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Reading:
    """What the frame step gives: the deformed inner surface ``dome`` it was given, the
    ``chamber`` (path taken, quality), the clean and measured voltages (n_meas,) V and their
    changes against the reference, the ``image`` (n_cells,) S/m, its noise-normalised version
    and ``metrics`` (None without an image or when it is all zero), the dent's centroid
    ``true_centre`` (3,) m (:func:`dent_centroid`; NaN when not asked for or none), and the stages' wall
    ``timings`` s (:data:`STAGES`)."""

    dome: DomeSurface
    chamber: DeformedChamber
    voltages_clean: np.ndarray
    voltages: np.ndarray
    dv_clean: np.ndarray
    dv: np.ndarray
    image: np.ndarray | None
    image_normalised: np.ndarray | None
    metrics: ImageMetrics | None
    true_centre: np.ndarray
    timings: dict[str, float] = field(default_factory=dict)


def dent_centroid(reference: DomeSurface, dome: DomeSurface) -> np.ndarray:
    """Centroid (3,) m of the dent: the saline displaced where the membrane's inner surface
    moved *in* from ``reference`` to ``dome`` (the same triangles); NaN where it moved in
    nowhere. Each triangle sweeps ΔV = −d̄·S̄ (d̄ its vertices' mean move, S̄ its outward area
    vector averaged over the two states), centred half-way along the move; the centroid is
    over the triangles with ΔV > 0. The bulges a press raises about the dent are left out: the
    centroid of the *net* saline lost, (V₀c₀ − V c)/(V₀ − V), divides by a small difference and
    fell outside the chamber for off-axis presses (x = 21 mm for a press at 12 mm, past the
    20 mm base)."""
    a, b = reference.vertices, dome.vertices
    f = reference.faces

    def area_vectors(x: np.ndarray) -> np.ndarray:
        return 0.5 * np.cross(x[f[:, 1]] - x[f[:, 0]], x[f[:, 2]] - x[f[:, 0]])

    Sa = area_vectors(a)
    ca, cb = a[f].mean(axis=1), b[f].mean(axis=1)
    volume = np.einsum("ij,ij->", Sa, ca) / 3  # the enclosed volume, signed by the faces' orientation
    S = 0.5 * (Sa + area_vectors(b)) * np.sign(volume)  # outward
    swept = -np.einsum("ij,ij->i", cb - ca, S)
    w = np.where(swept > 0, swept, 0.0)
    if w.sum() <= 1e-12 * abs(volume):
        return np.full(3, np.nan)
    return w @ (0.5 * (ca + cb)) / w.sum()


# ---------------------------------------------------------------------------------------------
# The instrument
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
        model = _resting_membrane(scene)
        dome = InnerSurface.of(model, scene.chamber, inflated=True).dome(None)
    return mesh_chamber(chamber_surface(dome), electrode_layout(scene), scene.mesh, **kw)


def _misfit(morpher: ChamberMorpher, scene: Scene) -> str:
    """Why the chamber under ``morpher`` does not fit its reference membrane surface (its dome
    lies further off it than ``CHAMBER_FIT`` × the membrane thickness), or "" where it fits."""
    gap, allowed = morpher.surface_gap, CHAMBER_FIT * scene.chamber.membrane_thickness
    if gap <= allowed:
        return ""
    return f"its dome lies up to {gap * 1e3:.3g} mm off the membrane's inner surface (allowed {allowed * 1e3:.3g} mm)"


def _resting_membrane(scene: Scene, device: str = "cpu") -> MembraneModel:
    """The membrane of ``scene`` inflated and untouched (its target made rigid: it is not touched)."""
    return membrane_from_scene(replace(scene, target=replace(scene.target, kind="rigid")), device=device)


@dataclass(frozen=True, eq=False)
class Instrument:
    """The sensor of ``scene`` as an instrument, ready to measure (build it with :meth:`build`).

    ``surface`` maps the membrane's displacement to its inner surface (None for an instrument
    built on a geometric dome; ``inflated_u``: the membrane's displacement at rest, inflated to
    the dome (moulded flat) or by the reservoir head (a cap), which later membranes of the
    scene start from; None on a geometric dome); ``chamber`` is the chamber as meshed, ``morpher`` prepared on the membrane's reference
    surface, ``reference_dome`` the inflated untouched inner surface and ``reference`` the
    chamber under it; ``readout`` the nominal electrodes; ``imager`` the reconstruction (None
    when built without); ``lambda_press`` the representative press λ was chosen on;
    ``setup_timings`` s per set-up stage."""

    scene: Scene
    surface: InnerSurface | None
    inflated_u: np.ndarray | None
    chamber: ChamberMesh
    morpher: ChamberMorpher
    reference_dome: DomeSurface
    reference: ChamberMesh
    readout: Readout
    imager: Imager | None
    lambda_press: dict[str, float] | None
    setup_timings: dict[str, float]

    @classmethod
    def build(cls, scene: Scene, *, membrane: MembraneModel | None = None, dome: DomeSurface | None = None,
              chamber: ChamberMesh | None = None,
              protocol: Protocol | None = None, reference_frames: int = 50, fdm: bool = False, imaging: bool = True,
              cells: int | None = None, backend: str = "auto", device: str = "cpu") -> "Instrument":
        """The instrument of ``scene``: the chamber ([mesh]), the readout ([electrodes],
        [drive] skip-N unless ``protocol``, [noise]), the image ([reconstruction]; ``cells``
        overrides its voxels; none when not ``imaging``).

        ``membrane``: the scene's membrane, inflated and untouched (default: built here with a
        rigid target); ``dome``: instead of a membrane, a surface to deform geometrically (the
        moulded cap: no inflation, no membrane; the protocol study's); ``chamber``: a ready chamber mesh of the scene (default
        :func:`deployed_chamber`), refused when its dome lies off the membrane's inner surface
        by more than ``CHAMBER_FIT`` × the membrane thickness; ``reference_frames``: frames
        averaged into the measured reference; ``fdm``: per-carrier contact impedances;
        ``backend``: the forward model's sparse solver; ``device``: Warp device of a membrane
        built here. The noise streams are seeded by [noise] seed."""
        t: dict[str, float] = {}
        seed = int(scene.noise.seed)
        flat = scene.membrane.moulding == "flat"
        surface, inflated_u = None, None
        if dome is not None:
            membrane_dome = reference_dome = dome
        else:
            with timed(t, "membrane"):
                model = _resting_membrane(scene, device) if membrane is None else membrane
                inflated_u = model.u[: model.mesh.n_nodes].copy()
                surface = InnerSurface.of(model, scene.chamber, inflated=flat)
                membrane_dome = surface.dome(None)  # the inner surface the morpher maps from
                reference_dome = surface.dome(model.u)
        with timed(t, "chamber"):
            chamber = deployed_chamber(scene, membrane_dome) if chamber is None else chamber
            morpher = ChamberMorpher(chamber, membrane_dome)
            misfit = _misfit(morpher, scene)
            if misfit:
                morpher.free()
                raise ValueError(f"chamber: {misfit}; mesh it with deployed_chamber(scene) (membrane.moulding = "
                                 f"{scene.membrane.moulding!r})")
            reference = morpher(reference_dome)
        if protocol is None:
            protocol = scene_protocol(scene)
        with timed(t, "forward"):
            readout = Readout.on(reference, scene, protocol, rng=stream(seed, "reference"),
                                 reference_frames=reference_frames, fdm=fdm, backend=backend)
        inst = cls(scene, surface, inflated_u, chamber, morpher, reference_dome, reference, readout, None, None, t)
        if not imaging:
            return inst
        spec = scene.reconstruction
        with timed(t, "jacobian"):
            grid = ChamberGrid.over(reference.mesh, spec.cells if cells is None else cells)
            # the nominal contact impedances' fields (an FDM readout's carriers differ only at the electrodes)
            J = jacobian(readout.fields(reference, True), protocol, coarse=grid.C)
        with timed(t, "lambda"):
            press, dv = inst._representative_press()
            noisy = dv[None] + stream(seed, "lambda").normal(0.0, readout.dv_noise_std, (LAMBDA_REPEATS, readout.n_meas))
            imager = Imager.choose(grid, J, noisy, spec.lambda_method, readout.dv_noise_std, seed, spec.prior, spec.depth_exponent)
        return replace(inst, imager=imager, lambda_press=press)

    # -- the frame step ---------------------------------------------------------------------

    def on_membrane(self, model: MembraneModel) -> "Instrument":
        """This instrument read through another membrane of its scene, ``model`` (inflated and
        untouched; meshed otherwise, e.g. refined under a press: :func:`~jointsim.geometry.refine_near`):
        its inner surface, the morpher remapped onto it (the chamber, its factor and the readout
        are shared: :meth:`free` the original, not this) and the reference chamber under it.
        Only for a membrane moulded as a cap: the chamber of one moulded flat is its membrane's."""
        if self.surface is None or self.scene.membrane.moulding != "cap":
            raise ValueError("on_membrane: only for an instrument of a membrane moulded as a cap")
        return self.on_surface(InnerSurface.of(model, self.scene.chamber), model.u)

    def on_surface(self, surface: InnerSurface, u: np.ndarray) -> "Instrument":
        """This instrument read through a membrane of its scene given by its inner ``surface``
        and its inflated, untouched displacement ``u`` (:meth:`on_membrane`; a surface turned
        about the axis: :meth:`~jointsim.mechanics.inner_surface.InnerSurface.turned`)."""
        if self.surface is None or self.scene.membrane.moulding != "cap":
            raise ValueError("on_surface: only for an instrument of a membrane moulded as a cap")
        morpher = self.morpher.remapped(surface.dome(None))
        misfit = _misfit(morpher, self.scene)
        if misfit:
            raise ValueError(f"on_membrane: {misfit}")
        reference_dome = surface.dome(u)
        return replace(self, surface=surface, morpher=morpher, reference_dome=reference_dome, reference=morpher(reference_dome))

    def dome(self, u: np.ndarray | None) -> DomeSurface:
        """The membrane's inner surface under its displacement ``u`` (n_P2, 3) (None: moulded)."""
        if self.surface is None:
            raise ValueError("this instrument was built on a geometric dome: it has no membrane to map a displacement from")
        return self.surface.dome(u)

    def deform(self, dome: DomeSurface, reference: DomeSurface | None = None) -> DeformedChamber:
        """The chamber under ``dome`` by [mesh] update (:func:`~jointsim.mesh.morph.deform_chamber`),
        a remesh pulled back onto ``reference`` (default: :attr:`reference_dome`). Raises
        :class:`~jointsim.mesh.morph.ChamberCollapse` when the dome nears the base."""
        return deform_chamber(self.morpher, dome, self.scene.mesh, self.scene.mesh.update,
                              reference=self.reference_dome if reference is None else reference)

    def measure(self, dome: DomeSurface, rng: np.random.Generator | None, *, readout: Readout | None = None,
                last: Reading | None = None, gain: float | np.ndarray = 1.0, reference: DomeSurface | None = None,
                image: bool = True, truth_volume: float | None = None) -> Reading:
        """One frame: the chamber under the membrane's deformed inner ``dome``, its clean
        voltages through ``readout`` (default: the nominal one), the measured ones (× ``gain``,
        plus the noise drawn from ``rng``; None: noise-free), δV against the readout's
        measured reference, and the instrument's image of it with its metrics (``image``).

        ``last``: the previous frame's reading; where ``dome`` is bit for bit its dome (a hold)
        its chamber and clean voltages are reused, as a recomputation would give them, and only
        the noise is drawn anew. ``reference``: the untouched dome a remesh is pulled back onto
        (default the instrument's; a dataset's randomised membrane has its own).
        ``truth_volume``: the displaced volume m³ from the mechanics; given, the dent's centroid
        (:func:`dent_centroid`) is computed and the metrics are taken against both."""
        ro = self.readout if readout is None else readout
        t = {s: 0.0 for s in STAGES}
        same = last is not None and np.array_equal(last.dome.vertices, dome.vertices)
        with timed(t, "mesh"):
            dc = last.chamber if same else self.deform(dome, reference)
        with timed(t, "forward"):
            clean = last.voltages_clean.copy() if same else ro.change(dc)
            v = clean * gain + rng.normal(0.0, ro.noise_std, ro.n_meas) if rng is not None else clean * gain
        dv, dv_clean = v - ro.v_ref_measured, clean - ro.v_ref
        img = normalised = metrics = None
        centre = np.full(3, np.nan)
        with timed(t, "reconstruction"):
            if truth_volume is not None:
                centre = dent_centroid(self.reference_dome if reference is None else reference, dome)
            if image and self.imager is not None:
                img, normalised, metrics = self.imager.image(dv, centre, truth_volume)
        return Reading(dome, dc, clean, v, dv_clean, dv, img, normalised, metrics, centre, t)

    # -- pieces -----------------------------------------------------------------------------

    @property
    def protocol(self) -> Protocol:
        return self.readout.protocol

    @property
    def grid(self) -> ChamberGrid:
        return self.imager.grid

    @property
    def reference_volume(self) -> float:
        return float(self.reference.mesh.volumes.sum())

    def _representative_press(self) -> tuple[dict[str, float], np.ndarray]:
        """The press λ is chosen for ([reconstruction] lambda_*): a geometric indentation of the
        reference dome, morphed; its clean δV. Halved up to twice where the morph cannot take it."""
        spec = self.scene.reconstruction
        thickness = self.scene.chamber.membrane_thickness
        ro = self.readout
        for d in (spec.lambda_depth, spec.lambda_depth / 2, spec.lambda_depth / 4):
            try:
                ind = indent_dome(self.reference_dome, spec.lambda_xy, d, spec.lambda_radius, thickness)
                chamber, q = self.morpher.morph(ind.dome)
                if q.min_shape < MIN_QUALITY_RATIO * self.morpher.reference_quality.min_shape:
                    continue
            except (MeshInversionError, ValueError):
                continue
            press = {"radius": spec.lambda_radius, "depth": d, "x": spec.lambda_xy[0], "y": spec.lambda_xy[1]}
            return press, ro.voltages(chamber, True) - ro.v_ref
        raise ValueError(f"reconstruction: no representative press of a {spec.lambda_radius * 1e3:g} mm radius target "
                         f"{spec.lambda_depth * 1e3:g} mm deep morphs the chamber; lower reconstruction.lambda_depth_mm")

    def free(self) -> None:
        """Release the factorisations (the morpher's and the readout's shared solver)."""
        self.morpher.free()
        self.readout.free()
