"""The sensor at rest, as ``jointsim forward`` writes it: the instrument built and the untouched
sensor read as one frame by its frame step, with everything an EIT user takes elsewhere.

Writes into a folder: ``forward.npz`` (standing voltages clean and one noisy frame, the
protocol, the transfer impedances, the Jacobian and the reconstruction matrix on the voxel
grid), ``chamber.vtu`` (conductivity and each injection's potential, for ParaView),
``forward_eidors.mat`` (an EIDORS-style model and data) and ``forward.json`` (provenance).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from .. import __version__
from ..eit.protocol import Protocol
from ..instrument import Instrument, Reading, stream
from ..io.export import atomic_path, write_mat, write_npz, write_vtu
from ..mesh.electrodes import electrode_tags
from ..scene import Scene
from ..timing import timed

__all__ = ["read_at_rest", "write_at_rest"]


def read_at_rest(scene: Scene, protocol: Protocol, *, imaging: bool = True, cells: int | None = None,
                 backend: str = "auto") -> tuple[Instrument, Reading]:
    """The instrument of ``scene`` reading ``protocol`` (per-carrier contact impedances where the
    scene gives them), and one frame of the untouched sensor (noise seeded by [noise] seed)."""
    inst = Instrument.build(scene, protocol=protocol, fdm=scene.electrodes.contact_impedance_by_freq is not None,
                            imaging=imaging, cells=cells, backend=backend)
    return inst, inst.measure(inst.reference_dome, stream(scene.noise.seed, "frame"), image=False)


def write_at_rest(out: str | Path, inst: Instrument, reading: Reading, timings: dict[str, float] | None = None) -> dict[str, Any]:
    """Write ``reading`` of ``inst`` into ``out`` (module docstring); returns forward.json's content."""
    out = Path(out)
    t = {} if timings is None else timings
    ch, ro, scene = inst.reference, inst.readout, inst.scene
    protocol = ro.protocol
    fields = ro.fields(ch, True)
    arrays = dict(voltages=reading.voltages_clean, voltages_noisy=reading.voltages, stim=protocol.stim, meas=protocol.meas,
                  transfer=fields.transfer)
    if inst.imager is not None:
        grid = inst.imager.grid
        arrays.update(
            jacobian_voxels=inst.imager.jacobian,
            reconstruction_matrix=inst.imager.reconstructor.R,
            voxel_active=grid.active,
            voxel_volume=grid.volume,
            voxel_origin=grid.grid.origin,
            voxel_spacing=grid.grid.spacing,
            voxel_shape=np.array(grid.grid.shape),
        )
    sigma = np.full(ch.mesh.n_tets, ro.conductivity)
    with timed(t, "write outputs"):
        write_npz(out / "forward.npz", **arrays)
        write_vtu(out / "chamber.vtu", ch.mesh, {"sigma": sigma},
                  {"potential_inj": fields.potentials(protocol), "electrode": electrode_tags(ch.mesh.n_nodes, ch.electrodes)})
        write_mat(out / "forward_eidors.mat", ch.mesh, sigma, reading.voltages_clean, protocol.stim, protocol.meas,
                  ch.electrodes, ro.forward.z, ch.ground)
        meta = {
            "jointsim": __version__,
            "scene": scene.to_dict(),
            "protocol": {"n_el": protocol.n_el, "n_stim": protocol.n_stim, "n_meas": protocol.n_meas},
            "mesh_key": inst.chamber.key,
            "quality": ch.quality().__dict__,
            "lambda": None if inst.imager is None else inst.imager.reconstructor.lam,
            "lambda_press": inst.lambda_press,
            "timings_s": {**inst.setup_timings, **t},
        }
        with atomic_path(out / "forward.json") as tmp:
            tmp.write_text(json.dumps(meta, indent=2, default=float))
    return meta
