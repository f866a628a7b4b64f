"""The protocol-optimisation study of the paper (sections III.A / IV.A, Fig. 2 G–H).

For each skip-N injection protocol (N = 0…n/2: 0…8 on the paper's 16 electrodes, all measured
against ground, or as the scene's [drive] measure says) and a
representative indentation at several contact positions: the RMS voltage change δV, the total
sensitivity J_sens in the chamber, the difference image (zeroth-order Tikhonov, λ by k-fold
cross-validation), the perturbation's CoM error against the true centre of the displaced
saline, and its total change Σσ. Beside them: the mesh-noise floor (the voltage change produced
by meshing alone: the chamber meshed with a sub-µm jitter, or turned by one electrode pitch)
against the instrument noise.

The indentation is geometric (jointsim.mechanics.geometric) and reaches the EIT through the
same interface the FEM mechanics use (a deformed DomeSurface): an
:class:`~jointsim.instrument.Instrument` built on the moulded cap deforms the chamber by its one
policy (the reference mesh morphed, so δV contains no remeshing noise) and one
:class:`~jointsim.instrument.Readout` per skip reads it (one solve per position serves all
skips). The images are the study's own: λ per skip, chosen on every position's noisy δV
together, since the study compares the protocols at their best.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import trimesh

from ..eit.forward import ForwardModel
from ..eit.jacobian import jacobian
from ..eit.protocol import scene_protocol
from ..geometry import dome_from_scene, electrode_layout
from ..instrument import Instrument
from ..mechanics.geometric import indent_dome
from ..mesh.chamber import ChamberMesh, chamber_mesh, mesh_chamber, reference_surface
from ..metrics import ImageMetrics, image_metrics, rms, sensitivity_total
from ..reconstruction.grid import ChamberGrid
from ..reconstruction.tikhonov import SVD, LambdaChoice, choose_lambda
from ..scene import Scene

__all__ = ["StudyConfig", "StudyResult", "run_protocol_study", "mesh_noise_floor", "mirror_pair_differences"]


@dataclass(frozen=True)
class StudyConfig:
    skips: tuple[int, ...] | None = None  # default: 0 … n/2 for the layout's n driven electrodes
    # contact positions (x, y) in m: the centre and points along and between electrode axes
    positions: tuple[tuple[float, float], ...] = ((0.0, 0.0), (5e-3, 0.0), (0.0, 8e-3), (-7e-3, -7e-3), (10e-3, 4e-3))
    target_radius: float = 7.5e-3  # a 15 mm diameter target, the paper's middle size
    depth: float = 2.0e-3
    snr_db: float = 74.2
    seed: int = 0
    n_cells: int = 7000
    threshold: float = 0.75
    lambda_method: str = "kfold"
    noise_repeats: int = 10  # noisy frames per position pooled for the choice of λ
    mesh_floor: bool = True

    def __post_init__(self) -> None:
        if self.skips is not None and (not self.skips or any(isinstance(s, bool) or not isinstance(s, int) or s < 0 for s in self.skips)):
            raise ValueError(f"skips = {self.skips}: integers >= 0, at least one (each at most n/2 of the layout's n driven electrodes)")
        if self.target_radius <= 0:
            raise ValueError(f"target_radius = {self.target_radius}: must be > 0 m")
        if self.depth <= 0:
            raise ValueError(f"depth = {self.depth}: must be > 0 m")
        if not self.positions:
            raise ValueError("positions: at least one contact position is needed")
        if self.noise_repeats < 1:
            raise ValueError(f"noise_repeats = {self.noise_repeats}: must be >= 1")


@dataclass
class StudyResult:
    config: StudyConfig
    scene: Scene
    grid: ChamberGrid
    true_centres: np.ndarray  # (P, 3)
    displaced_volume: np.ndarray  # (P,)
    v_ref: dict[int, np.ndarray]  # skip -> (256,)
    dv: dict[int, np.ndarray]  # skip -> (P, 256) noisy
    dv_clean: dict[int, np.ndarray]
    j_sens: dict[int, float]
    lambdas: dict[int, LambdaChoice]
    images: dict[int, np.ndarray]  # skip -> (P, n_cells), Δσ in S/m
    metrics: dict[int, list[ImageMetrics]]  # of the noise-normalised images (localisation)
    metrics_raw: dict[int, list[ImageMetrics]]  # of the Δσ images (Σσ in S/m·voxel)
    noise_std: dict[int, float]
    floor: dict[str, dict[int, float]] = field(default_factory=dict)  # kind -> skip -> dB re mean |V|
    # skip -> (n_cells,) ‖∂V/∂σ_i‖₂ / V_i, V S⁻¹ m⁻²: the measurements' sensitivity density (paper Fig. 2B/C)
    sensitivity: dict[int, np.ndarray] = field(default_factory=dict)
    mirror_pairs: dict[str, float] = field(default_factory=dict)  # "6~8" -> relative difference

    def table(self) -> list[dict]:
        """One row per skip: means over the positions."""
        rows = []
        for s in self.config.skips:
            m = self.metrics[s]
            raw = self.metrics_raw[s]
            xy = [float(np.linalg.norm(x.com[:2] - c[:2])) for x, c in zip(m, self.true_centres)]
            dz = [float(x.com[2] - c[2]) for x, c in zip(m, self.true_centres)]
            rows.append(
                {
                    "skip": s,
                    "rms_dV_uV": 1e6 * float(np.mean([rms(d) for d in self.dv_clean[s]])),
                    "snr_dV_dB": 20 * np.log10(np.mean([rms(d) for d in self.dv_clean[s]]) / self.noise_std[s]),
                    "J_sens": self.j_sens[s],
                    "com_error_mm_mean": 1e3 * float(np.mean([x.com_error for x in m])),
                    "com_error_mm_max": 1e3 * float(np.max([x.com_error for x in m])),
                    "com_error_xy_mm_mean": 1e3 * float(np.mean(xy)),
                    "com_dz_mm_mean": 1e3 * float(np.mean(dz)),
                    "com_error_raw_mm_mean": 1e3 * float(np.mean([x.com_error for x in raw])),
                    "sum_sigma": float(np.mean([x.sum_sigma for x in m])),
                    "diameter_eq_mm": 1e3 * float(np.mean([x.diameter_equivalent for x in m])),
                    "lambda": self.lambdas[s].lam,
                    **{f"floor_{k}_dB": v.get(s, float("nan")) for k, v in self.floor.items()},
                    **{
                        f"floor_{k}_uV": 1e6 * float(np.abs(self.v_ref[s]).mean()) * 10 ** (-v.get(s, np.nan) / 20)
                        for k, v in self.floor.items()
                    },
                }
            )
        return rows


def _fields(chamber: ChamberMesh, scene: Scene, like: ForwardModel | None = None):
    return ForwardModel.from_chamber(chamber, scene, like=like).solve(scene.saline.conductivity)


def run_protocol_study(scene: Scene, config: StudyConfig = StudyConfig(), progress=None) -> StudyResult:
    """Run the study; ``progress(n)`` (optional) is called as steps complete (a tqdm update)."""
    if scene.membrane.moulding != "cap":
        # the study indents the moulded cap geometrically; a flat moulding's deployed dome is
        # the FEM's inflated shape, which it does not compute
        raise ValueError(f"membrane.moulding = {scene.membrane.moulding!r}: the protocol study takes the moulded cap only (\"cap\")")
    tick = progress or (lambda n=1: None)
    n_el = scene.electrodes.count
    n = scene.electrodes.n_active
    if config.skips is None:
        config = replace(config, skips=tuple(range(n // 2 + 1)))
    if max(config.skips) > n // 2:
        raise ValueError(f"skips = {list(config.skips)}: each must be in [0, {n // 2}] for {n} driven electrodes")
    dome = dome_from_scene(scene)
    scene = replace(scene, noise=replace(scene.noise, snr_db=config.snr_db))
    inst = Instrument.build(scene, dome=dome, chamber=chamber_mesh(scene), imaging=False)
    ch = inst.chamber
    tick()
    grid = ChamberGrid.over(ch.mesh, config.n_cells)
    # one readout per skip; they share their solves (the reference's, then each position's)
    readouts = {s: inst.readout.with_protocol(scene_protocol(scene, s)) for s in config.skips}
    protocols = {s: r.protocol for s, r in readouts.items()}
    v_ref = {s: r.v_ref for s, r in readouts.items()}
    f0 = inst.readout.fields(inst.reference, True)
    J = {s: jacobian(f0, p, coarse=grid.C) for s, p in protocols.items()}
    tick()

    P = len(config.positions)
    v_def = {s: np.empty((P, readouts[s].n_meas)) for s in config.skips}
    centres, volumes = np.empty((P, 3)), np.empty(P)
    for i, xy in enumerate(config.positions):
        ind = indent_dome(dome, xy, config.depth, config.target_radius, scene.chamber.membrane_thickness)
        dc = inst.deform(ind.dome)
        for s, r in readouts.items():
            v_def[s][i] = r.change(dc)
        centres[i], volumes[i] = ind.centroid, ind.volume
        tick()
    inst.free()

    rng = np.random.default_rng(config.seed)
    dv, dv_clean, lambdas, images, metrics, metrics_raw, j_sens, std = {}, {}, {}, {}, {}, {}, {}, {}
    for s in config.skips:
        std[s] = readouts[s].noise_std
        dv_clean[s] = v_def[s] - v_ref[s]
        # the paper subtracts a steady-state reference averaged over many frames: only the
        # deformed frame carries noise. Several noisy repeats per position steady the choice
        # of λ (one frame's CV curve is flat and its minimum wanders by a decade); the first
        # repeat is the frame that is imaged.
        noisy = dv_clean[s][None] + rng.normal(0.0, std[s], size=(config.noise_repeats,) + dv_clean[s].shape)
        dv[s] = noisy[0]
        svd = SVD.of(J[s])
        lambdas[s] = choose_lambda(svd, noisy.reshape(-1, noisy.shape[-1]), config.lambda_method, seed=config.seed)
        R = svd.reconstruction_matrix(lambdas[s].lam)
        images[s] = dv[s] @ R.T
        # 0th-order Tikhonov images peak where the sensitivity is largest, at the electrodes;
        # dividing by each cell's noise std (white noise through R) removes that bias, as the
        # noise-based correction of the paper's reconstruction software does
        normalised = images[s] / np.sqrt((R**2).sum(axis=1))
        metrics[s] = [
            image_metrics(grid, normalised[i], centres[i], volumes[i], config.threshold, amplitude=images[s][i])
            for i in range(P)
        ]
        metrics_raw[s] = [image_metrics(grid, images[s][i], centres[i], volumes[i], config.threshold) for i in range(P)]
        j_sens[s] = sensitivity_total(J[s], grid)
        tick()
    result = StudyResult(
        config, scene, grid, centres, volumes, v_ref, dv, dv_clean, j_sens, lambdas, images, metrics, metrics_raw, std
    )
    result.sensitivity = {s: np.linalg.norm(J[s], axis=0) / grid.volume for s in config.skips}
    ring = scene.electrodes.is_ring and scene.drive.measure == "reference"
    result.mirror_pairs = mirror_pair_differences(v_def, n_el) if ring else {}
    if config.mesh_floor:
        result.floor = mesh_noise_floor(scene, f0, protocols)
        tick()
    return result


def mirror_pair_differences(v: dict[int, np.ndarray], n_el: int) -> dict[str, float]:
    """skip-N and skip-(n_el − 2 − N) drive the same electrode pairs with reversed polarity:
    injection i of skip-N is injection i + N + 1 of the other, negated. For each such pair in
    ``v`` (skip → (…, n_el·n_el) voltages), the largest difference after that permutation,
    relative to the largest voltage (0 up to round-off means identical information)."""
    out = {}
    for a in sorted(v):
        b = n_el - 2 - a
        if a < b and b in v:
            va = v[a].reshape(-1, n_el, n_el)
            vb = -np.roll(v[b].reshape(-1, n_el, n_el), -(a + 1), axis=1)
            out[f"{a}~{b}"] = float(np.abs(va - vb).max() / np.abs(va).max())
    return out


def jitter_surface(surface: trimesh.Trimesh, amplitude: float) -> trimesh.Trimesh:
    """``surface`` with its vertices above the base moved by up to ``amplitude`` (m) along z,
    by a fixed low-discrepancy sequence (the same everywhere): the same chamber, another mesh."""
    v = np.array(surface.vertices)
    free = v[:, 2] > 0
    v[free, 2] += amplitude * (2 * np.mod(np.arange(free.sum()) * 0.6180339887498949, 1.0) - 1)
    return trimesh.Trimesh(v, surface.faces, process=False)


def jittered_chamber(scene: Scene, amplitude: float) -> ChamberMesh:
    """The chamber of ``scene`` meshed with its dome's vertices jittered (:func:`jitter_surface`)."""
    surface = jitter_surface(reference_surface(scene), amplitude)
    return mesh_chamber(surface, electrode_layout(scene), scene.mesh, use_cache=False)


def mesh_noise_floor(scene: Scene, fields, protocols: dict) -> dict[str, dict[int, float]]:
    """Voltage change produced by meshing alone, in dB re the mean standing |V| (the SNR
    convention), per skip: ``jitter`` meshes the chamber with its dome's vertices moved by at
    most 1 µm (the mesher is deterministic, so meshing the same chamber again gives the same
    mesh; a jitter far below the physical scale gives another); ``rotate`` meshes the chamber
    with the electrode ring rotated by one pitch (360°/n, a symmetry of the dome's
    triangulation) and permutes the electrodes back (the paper's ring only). The morphed (fixed-topology) path has no
    such floor: no deformation gives the reference mesh itself."""
    n_el = scene.electrodes.count
    ring = scene.electrodes.is_ring and scene.drive.measure == "reference"
    out: dict[str, dict[int, float]] = {"jitter": {}, **({"rotate": {}} if ring else {})}
    again = _fields(jittered_chamber(scene, 1e-6), scene)
    for s, p in protocols.items():
        v = fields.voltages(p)
        out["jitter"][s] = float(20 * np.log10(np.abs(v).mean() / rms(again.voltages(p) - v)))
    if not ring:  # the turn by one pitch is a symmetry of the paper's ring only
        return out
    pitch = 360.0 / n_el
    rot_scene = replace(scene, electrodes=replace(scene.electrodes, first_angle_deg=scene.electrodes.first_angle_deg + pitch))
    rotated = _fields(chamber_mesh(rot_scene), rot_scene)
    for s, p in protocols.items():
        v = fields.voltages(p)
        ref = np.abs(v).mean()
        # electrode l of the rotated ring sits where electrode l + 1 was: the same physical
        # frame is injection i, electrode j of the original ↔ injection i − 1, electrode j − 1
        vr = rotated.voltages(p).reshape(n_el, n_el)
        vr = np.roll(np.roll(vr, 1, axis=0), 1, axis=1).ravel()
        out["rotate"][s] = float(20 * np.log10(ref / rms(vr - v)))
    return out
