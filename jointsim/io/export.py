"""Writing results in formats the field reads: VTU (ParaView, via meshio), ``.npz`` and an
EIDORS-style ``.mat``. Every writer goes to a temporary name first and renames, so an
interrupted run never leaves a half-written file."""

from __future__ import annotations

import os
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Iterator

import numpy as np

if TYPE_CHECKING:  # annotations only: the command line reads this module's neighbours without Warp
    from ..mesh.tetmesh import TetMesh

__all__ = ["atomic_path", "write_vtu", "write_npz", "write_mat", "write_voxels_vtu"]


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path`` (same suffix); rename it onto ``path`` on success."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.", suffix=path.suffix)
    os.close(fd)
    try:
        yield Path(tmp)
        # mkstemp creates the file owner-only; results are ordinary files (the umask decides)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    finally:
        Path(tmp).unlink(missing_ok=True)


def write_vtu(
    path: str | Path,
    mesh: TetMesh,
    cell_data: dict[str, np.ndarray] | None = None,
    point_data: dict[str, np.ndarray] | None = None,
) -> Path:
    """Tetrahedral mesh with per-element (n_tets,) and per-node (n_nodes,) or (n_nodes, k)
    fields; a (n_nodes, k) field is written as k scalars named ``name_0 … name_{k-1}``."""
    import meshio

    pd: dict[str, np.ndarray] = {}
    for name, a in (point_data or {}).items():
        a = np.asarray(a)
        if a.shape[0] != mesh.n_nodes:
            raise ValueError(f"point_data[{name!r}]: expected {mesh.n_nodes} rows, got {a.shape[0]}")
        if a.ndim == 2 and a.shape[1] != 3:
            pd.update({f"{name}_{i}": a[:, i] for i in range(a.shape[1])})
        else:
            pd[name] = a
    cd = {}
    for name, a in (cell_data or {}).items():
        a = np.asarray(a)
        if a.shape[0] != mesh.n_tets:
            raise ValueError(f"cell_data[{name!r}]: expected {mesh.n_tets} rows, got {a.shape[0]}")
        cd[name] = [a]
    m = meshio.Mesh(mesh.nodes, [("tetra", mesh.tets)], point_data=pd, cell_data=cd)
    path = Path(path)
    with atomic_path(path) as tmp:
        m.write(tmp, file_format="vtu")
    return path


def write_npz(path: str | Path, **arrays: np.ndarray) -> Path:
    path = Path(path)
    with atomic_path(path) as tmp:
        np.savez_compressed(tmp, **arrays)
    return path


def write_mat(
    path: str | Path,
    mesh: TetMesh,
    sigma: np.ndarray,
    voltages: np.ndarray,
    stim: np.ndarray,
    meas: np.ndarray,
    electrodes: list,
    contact_impedance: np.ndarray,
    ground: int,
    jacobian: np.ndarray | None = None,
) -> Path:
    """MATLAB file laid out for EIDORS users: ``fwd_model.nodes`` (n, 3), ``fwd_model.elems``
    (m, 4) 1-based, ``fwd_model.electrode(l).nodes`` / ``.z_contact``, ``fwd_model.gnd_node``,
    ``fwd_model.stimulation(s).stim_pattern`` (n_el × 1) and ``.meas_pattern``, the element
    conductivity ``img.elem_data`` and the measurements ``data.meas``. Electrode nodes are
    the nodes of the faces each electrode touches (EIDORS stores node sets)."""
    from scipy.io import savemat

    el = np.zeros(len(electrodes), dtype=[("nodes", object), ("z_contact", float), ("faces", object)])
    for l, e in enumerate(electrodes):
        el[l] = (np.unique(e.faces) + 1.0, float(contact_impedance[l]), e.faces + 1.0)
    ring = [l for l in range(len(electrodes)) if l != ground]
    stim_struct = np.zeros(len(stim), dtype=[("stimulation", object), ("stim_pattern", object), ("meas_pattern", object)])
    for s in range(len(stim)):
        stim_struct[s] = ("Amp", stim[s][:, None], meas[s])
    gnd_nodes = np.unique(electrodes[ground].faces)
    fwd = {
        "type": "fwd_model",
        "nodes": mesh.nodes,
        "elems": mesh.tets + 1.0,
        "electrode": el[ring],
        "ground_electrode": el[[ground]],
        "gnd_node": float(gnd_nodes[0] + 1),
        "stimulation": stim_struct,
    }
    out = {"fwd_model": fwd, "img": {"type": "image", "elem_data": np.asarray(sigma)[:, None]}, "data": {"type": "data", "meas": np.asarray(voltages)[:, None]}}
    if jacobian is not None:
        out["J"] = jacobian
    path = Path(path)
    with atomic_path(path) as tmp:
        savemat(tmp, out, do_compression=True, oned_as="column")
    return path


def write_voxels_vtu(path: str | Path, grid, cell_data: dict[str, np.ndarray]) -> Path:
    """The active cells of a :class:`~jointsim.reconstruction.grid.ChamberGrid` as hexahedra
    with per-cell fields (n_cells,), for ParaView."""
    import meshio

    g = grid.grid
    nx, ny, nz = g.shape
    axes = [g.origin[i] + g.spacing[i] * np.arange(g.shape[i] + 1) for i in range(3)]
    X, Y, Z = np.meshgrid(*axes, indexing="ij")
    points = np.column_stack([X.ravel(), Y.ravel(), Z.ravel()])
    i, j, k = np.unravel_index(grid.active, g.shape)
    node = lambda a, b, c: np.ravel_multi_index((a, b, c), (nx + 1, ny + 1, nz + 1))  # noqa: E731
    hexes = np.column_stack(
        [node(i, j, k), node(i + 1, j, k), node(i + 1, j + 1, k), node(i, j + 1, k),
         node(i, j, k + 1), node(i + 1, j, k + 1), node(i + 1, j + 1, k + 1), node(i, j + 1, k + 1)]
    )
    for name, a in cell_data.items():
        if np.shape(a)[0] != grid.n_cells:
            raise ValueError(f"cell_data[{name!r}]: expected {grid.n_cells} values, got {np.shape(a)[0]}")
    m = meshio.Mesh(points, [("hexahedron", hexes)], cell_data={k: [np.asarray(v)] for k, v in cell_data.items()})
    path = Path(path)
    with atomic_path(path) as tmp:
        m.write(tmp, file_format="vtu")
    return path
