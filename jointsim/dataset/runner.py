"""Running a dataset: the store, the shared chamber mesh, and the workers (local processes or
a Dask distributed cluster) that take whole groups.

Layout and crash safety
    The run writes to ``OUT.partial/`` (see :mod:`jointsim.io.store`) and finalises to
    ``OUT.h5``. Before anything else the chamber mesh is written there once
    (``OUT.partial/chamber.npz``, first writer wins) and every worker, this run's or a resumed
    one's, on this machine or another, uses that file: the mesher is deterministic, but another
    gmsh version may mesh otherwise, and a mesh made afresh would then give other data. Its
    SHA-256 is part of the store's identity.

    A group's K records are stored together, as one file, when the group is done: a record
    file exists complete or not at all, so a kill at any moment loses at most the groups in
    flight (seconds to a minute of work per worker) and never leaves a partial group. The
    alternative, each sample stored with a checkpoint of the membrane to continue a group
    mid-press, would save at most K − 1 steps per worker on a crash, at the price of a
    checkpoint per sample (the full displacement history) and of rejected draws that would
    have to unwind stored samples; whole groups keep both simple.

Workers
    Local workers are spawned processes (not forked: Warp, MKL and MuJoCo hold threads and
    handles a fork would copy), each building the set-up (:class:`DatasetSetup`) once and
    then taking groups. Every worker runs its numerical libraries on one thread (MKL, OpenMP,
    OpenBLAS): MKL's reproducible mode gives the same bits only for the same thread count,
    so the data do not depend on the number of workers; and on a machine of C cores, C
    single-threaded workers use it better than fewer threaded ones. The default is one worker
    per core available to this process.

    With a Dask scheduler address the same groups are submitted to an existing cluster; each
    Dask worker process builds the set-up once (cached per process) and writes its groups
    straight into the shared store, which must be on a file system every worker sees. Start
    workers with one thread each (``dask worker ADDRESS --nthreads 1``); Dask's nanny already
    runs them with one MKL/OpenMP thread. Tasks in one process run one at a time.
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
import threading
import time
import warnings
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from .._cores import THREAD_VARIABLES, available_cores, run_local
from ..geometry import electrode_layout
from ..io.records import open_records
from ..io.store import RecordStore, attach, exclusive, open_store, readable_records, set_aside
from ..linalg import SOLVER_VARIABLE, preferred_backend
from ..mesh.chamber import ChamberMesh
from ..mesh.electrodes import layout_patches
from ..mesh.tetmesh import TetMesh
from ..instrument import deployed_chamber
from ..scene import Scene
from .generate import DatasetSetup, dataset_params, dataset_schema, group_indices
from .presses import PressList

__all__ = ["DatasetRun", "generate_dataset", "default_workers", "THREAD_VARIABLES"]

MAX_SEED = 2**63 - 1  # as [noise] seed: the store records it as a signed 64-bit integer
CHAMBER_FILE = "chamber.npz"
SCHEDULER_TIMEOUT_S = 15.0


@dataclass(frozen=True)
class DatasetRun:
    """What :func:`generate_dataset` did: the finished ``path``, its ``n_samples`` and
    ``data_sha256``, the groups computed now (``groups_run``; 0 when the file was complete),
    the samples found already stored, the draws rejected and redrawn (and why), and the wall time s."""

    path: Path
    n_samples: int
    data_sha256: str
    groups_run: int
    samples_resumed: int
    rejected_draws: int
    wall_s: float
    rejections: tuple[str, ...] = ()


def default_workers() -> int:
    """One worker per core available to this process."""
    return available_cores()


def _paths(out: str | Path) -> tuple[Path, Path]:
    """(final file, partial directory) as :func:`~jointsim.io.store.open_store` names them."""
    out = Path(out)
    final = out if out.suffix in (".h5", ".hdf5") else out.with_name(out.name + ".h5")
    return final, final.with_suffix(".partial")


# --------------------------------------------------------------------------------------------
# The chamber mesh every worker shares


def _save_chamber_once(partial: Path, chamber: ChamberMesh) -> None:
    """Write ``partial/chamber.npz`` unless it exists (complete or absent; first writer wins)."""
    target = partial / CHAMBER_FILE
    if target.exists():
        return
    partial.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=partial, prefix=".chamber.", suffix=".npz")
    try:
        with os.fdopen(fd, "wb") as f:
            np.savez(f, nodes=chamber.mesh.nodes, tets=chamber.mesh.tets)
            f.flush()
            os.fsync(f.fileno())
        try:
            os.link(tmp, target)  # fails if it exists, unlike a rename
        except FileExistsError:
            pass
    except OSError as e:  # a full disk: say where
        raise OSError(e.errno, f"{e.strerror or e} (writing the run's chamber mesh; make room and run again)", str(target)) from None
    finally:
        Path(tmp).unlink(missing_ok=True)


def _load_chamber(partial: Path, scene: Scene) -> tuple[ChamberMesh, str]:
    """The run's chamber mesh (electrodes tagged for ``scene``) and the SHA-256 of its arrays."""
    with np.load(partial / CHAMBER_FILE) as z:
        nodes, tets = z["nodes"], z["tets"]
    h = hashlib.sha256()
    for a in (nodes, tets):
        h.update(str(a.dtype).encode() + str(a.shape).encode())
        h.update(np.ascontiguousarray(a).data)
    sha = h.hexdigest()
    mesh = TetMesh(nodes, tets)
    layout = electrode_layout(scene)
    return ChamberMesh(mesh, layout_patches(mesh, layout), layout, f"dataset-{sha[:20]}"), sha


# --------------------------------------------------------------------------------------------
# Worker side (a spawned process or a Dask worker)

_WORKER: dict[str, Any] = {}
_WORKER_LOCK = threading.Lock()


def _worker(path: str, scene: Scene, seed: int, presses: PressList | None) -> tuple[DatasetSetup, RecordStore]:
    """This process's set-up and store writer for the run at ``path``, built on first use."""
    key = (path, seed, scene.digest(), None if presses is None else json.dumps(presses.to_record()), preferred_backend())
    if _WORKER.get("key") != key:
        if "setup" in _WORKER:
            _WORKER.pop("setup").free()
        final, partial = _paths(path)
        chamber, _ = _load_chamber(partial, scene)
        setup = DatasetSetup(scene, chamber, seed, presses)
        _WORKER.update(key=key, setup=setup)
    # a fresh writer per group: a retried or resubmitted group may write its indices again
    return _WORKER["setup"], attach(_paths(path)[0], batch=scene.dataset.samples_per_press)


def _run_group(path: str, scene: Scene, seed: int, group: int, n_samples: int,
               presses: PressList | None = None, solver: str = "auto") -> tuple[int, int, list[str], float]:
    """Compute and store ``group`` (one record file) with the driver's sparse ``solver`` (a Dask
    worker does not inherit the driver's environment); returns (group, samples, why draws were
    rejected, s)."""
    with _WORKER_LOCK:  # one group at a time per process: the set-up is not thread-safe
        os.environ[SOLVER_VARIABLE] = solver
        t0 = time.perf_counter()
        setup, store = _worker(path, scene, seed, presses)
        records, rejected = setup.group(group)
        idx = group_indices(group, n_samples, setup.spec.samples_per_press)
        for i, rec in zip(idx, records):
            store.put(i, rec)
        store.flush()
        return group, len(idx), rejected, time.perf_counter() - t0


def _run_dask(tasks: Sequence[tuple], scheduler: Any, tick: Callable[[tuple], None]) -> None:
    from distributed import Client, as_completed

    if isinstance(scheduler, Client):
        client = scheduler
    else:
        try:
            client = Client(scheduler, timeout=SCHEDULER_TIMEOUT_S)
        except (OSError, TimeoutError, ValueError) as e:
            raise ValueError(f"scheduler {scheduler!r}: cannot connect within {SCHEDULER_TIMEOUT_S:g} s ({type(e).__name__}: "
                             f"{e}); start it (dask scheduler) or check the address, e.g. tcp://host:8786") from None
    try:
        futures = [client.submit(_run_group, *t, pure=False, key=f"jointsim-dataset-group-{t[3]}-{os.urandom(4).hex()}")
                   for t in tasks]
        try:
            for f in as_completed(futures):
                tick(f.result())
        except BaseException:
            client.cancel(futures)
            raise
    finally:
        if client is not scheduler:
            client.close()


# --------------------------------------------------------------------------------------------
# The driver


def _with_presses(scene: Scene, presses: PressList, n_samples: int) -> Scene:
    """``scene`` with the press list's samples per press; refuses a list the scene cannot take
    or an ``n_samples`` other than the list's."""
    from ..scene import DATASET_RIM_MM

    spec = scene.dataset
    if presses.depths is not None and spec.control == "force":
        raise ValueError("a press list with depth_mm: the scene's [dataset] control is \"force\" (its samples are at "
                         "forces); give the list without depths or set control = \"depth\"")
    presses.check_within(scene.chamber.base_radius - DATASET_RIM_MM * 1e-3, 0.9 * scene.chamber.dome_height)
    k = presses.samples_per_press or spec.samples_per_press
    if n_samples != len(presses) * k:
        raise ValueError(f"n_samples = {n_samples}: the press list has {len(presses)} presses x {k} depths = "
                         f"{len(presses) * k} samples")
    return replace(scene, dataset=replace(spec, samples_per_press=k))


def generate_dataset(
    scene: Scene,
    n_samples: int,
    out: str | Path,
    *,
    seed: int | None = None,
    workers: int | None = None,
    scheduler: Any = None,
    scene_toml: str | None = None,
    command: Sequence[str] | None = None,
    progress: Callable[[int], None] | None = None,
    on_start: Callable[[int, int], None] | None = None,
    presses: PressList | None = None,
) -> DatasetRun:
    """Generate (or resume, or find finished) the dataset of ``n_samples`` labelled samples
    of ``scene`` (its [dataset] section) at ``out`` (``.h5`` appended without an HDF5 suffix).

    Parameters
    ----------
    seed : the dataset's seed (default: the scene's [noise] seed); the same seed gives the same
        data (``data_sha256``) whatever the workers, their number and interruptions
    workers : local worker processes (default :func:`default_workers`); ignored with ``scheduler``
    scheduler : a Dask distributed scheduler address (or a ``distributed.Client``): the groups
        run on that cluster, whose workers must see ``out``'s folder
    scene_toml : the scene file's text, kept in the file's provenance (default: a TOML-free
        placeholder, the effective scene is in the params anyway)
    command : the command line recorded with the session (default ``sys.argv``)
    progress : told the number of samples of each group as it is stored
    on_start : told (samples already stored, samples to compute) before the work starts
    presses : a :class:`~jointsim.dataset.presses.PressList`: these presses, one group each, instead
        of drawn ones (``n_samples`` must then be its length × its samples per press, the
        list's own depths' count or the scene's); the sensor's randomisation is still drawn
    """
    t0 = time.perf_counter()
    if not isinstance(n_samples, (int, np.integer)) or isinstance(n_samples, bool) or n_samples < 1:
        raise ValueError(f"n_samples = {n_samples!r}: must be an integer >= 1")
    seed = scene.noise.seed if seed is None else seed
    if not isinstance(seed, (int, np.integer)) or isinstance(seed, bool) or not 0 <= seed <= MAX_SEED:
        raise ValueError(f"seed = {seed!r}: must be an integer in [0, 2^63 - 1]")
    if presses is not None:
        scene = _with_presses(scene, presses, n_samples)
    workers = default_workers() if workers is None else workers
    if not isinstance(workers, (int, np.integer)) or workers < 1:
        raise ValueError(f"workers = {workers!r}: must be an integer >= 1")
    final, partial = _paths(out)
    salvage, kept, aside = None, [], None
    with exclusive(final):  # a second driver on this output is refused now, not at finalize
        if final.exists():
            try:
                rec = open_records(final, fields=[], verify=False)
            except (OSError, KeyError, ValueError) as e:  # not HDF5, truncated, or HDF5 of another kind
                raise ValueError(f"{final}: exists and is not a readable jointsim store ({e}); move it away, or write to "
                                 "another path") from None
            prov = rec.provenance
            if prov["schema"]["name"] != "dataset":
                raise ValueError(f"{final} holds a {prov['schema']['name']!r} store, not a dataset; write to another path")
            same = prov["n_records"] == n_samples and prov["seed"] == seed
            if same:
                want = dataset_params(scene, n_samples, prov["params"].get("chamber_sha256", ""), presses)
                same = json.loads(json.dumps(want)) == prov["params"]
            if not same:
                raise ValueError(f"{final} holds a finished run with other settings; remove it (--overwrite), or write to another path")
            # a rerun reads the whole file back against its digest: damage (a flipped chunk) is
            # found here, not by the user's analysis later; the file is set aside (kept) and the
            # presses it can no longer vouch for are computed again
            try:
                open_records(final, fields=[], verify=True)
                return DatasetRun(final, n_samples, rec.data_sha256, 0, n_samples, 0, time.perf_counter() - t0)
            except (ValueError, OSError) as e:  # a digest mismatch, or a chunk HDF5 cannot decode
                what = str(e) if isinstance(e, ValueError) else f"{final}: damaged ({e})"
                aside = set_aside(final)
                salvage = readable_records(aside)
                kept = _whole_groups(salvage[0], scene.dataset.samples_per_press)
                warnings.warn(f"{what}: set aside as {aside.name}; {len(kept)} of its presses read back whole and are kept, "
                              "the others are computed again", UserWarning, stacklevel=2)

        k = scene.dataset.samples_per_press
        if not (partial / CHAMBER_FILE).exists():
            _save_chamber_once(partial, deployed_chamber(scene))
        chamber, sha = _load_chamber(partial, scene)
        n_cells = None
        if scene.dataset.images:  # the image's length is the nominal voxel grid's
            setup = DatasetSetup(scene, chamber, seed)
            n_cells = setup.instrument.grid.n_cells
            setup.free()
        from ..eit.protocol import scene_protocol

        n_meas = scene_protocol(scene).n_meas
        schema = dataset_schema(scene.electrodes.n_active, n_meas, n_cells)
        store = open_store(final, schema, scene_toml=scene_toml if scene_toml is not None else f'name = "{scene.name}"\n',
                           seed=int(seed), n_records=int(n_samples), params=dataset_params(scene, n_samples, sha, presses),
                           command=command)
        if kept:  # the presses of a damaged finished file that read back whole
            _put_groups(final, kept, salvage[1], k, n_samples)
        # a record file damaged since it was written (a flipped byte, a truncated copy) is found
        # here, set aside and its group computed again: the run still ends with the whole data
        if damaged := store.set_aside_unreadable():
            warnings.warn(f"{len(damaged)} stored record file(s) could not be read back: set aside as {damaged[0]}"
                          f"{' and others' if len(damaged) > 1 else ''}; their samples are computed again", UserWarning, stacklevel=2)
        missing = store.missing()
        todo = np.unique(missing // k)
        if on_start is not None:
            on_start(n_samples - len(missing), len(missing))
        rejected: list[str] = []

        def tick(result: tuple[int, int, list[str], float]) -> None:
            rejected.extend(result[2])
            if progress is not None:
                progress(result[1])

        tasks = [(str(final), scene, int(seed), int(g), int(n_samples), presses, preferred_backend()) for g in todo]
        if tasks:
            if scheduler is not None:
                _run_dask(tasks, scheduler, tick)
            else:
                run_local(tasks, min(workers, len(tasks)), tick, _run_group)
        store.finalize(compression="gzip")
        rec = open_records(final, fields=[], verify=False)
    if kept and rec.data_sha256 != salvage[2]:
        # the kept presses and the recomputed ones do not make the data the damaged file
        # recorded: trust none of it, set this one aside too and compute every press again
        again = set_aside(final)
        warnings.warn(f"{final}: the presses kept from {aside.name} did not give its recorded data_sha256; set aside as "
                      f"{again.name}, every press computed again", UserWarning, stacklevel=2)
        return generate_dataset(scene, n_samples, out, seed=seed, workers=workers, scheduler=scheduler, scene_toml=scene_toml,
                                command=command, progress=progress, on_start=on_start, presses=presses)
    return DatasetRun(final, n_samples, rec.data_sha256, len(tasks), n_samples - len(missing), len(rejected),
                      time.perf_counter() - t0, tuple(rejected))


def _whole_groups(ok: np.ndarray, k: int) -> list[int]:
    """The groups (presses of ``k`` samples, the last perhaps fewer) whose every record is ``ok``."""
    if not len(ok):
        return []
    groups = np.arange(len(ok)) // k
    return [int(g) for g in np.unique(groups) if ok[groups == g].all()]


def _put_groups(final: Path, groups: list[int], fields: dict[str, np.ndarray], k: int, n_samples: int) -> None:
    """Store ``groups``' records from ``fields`` (a damaged file's rows that read back), one
    record file per group as a worker writes it."""
    writer = attach(final, batch=k)
    for g in groups:
        for i in group_indices(g, n_samples, k):
            writer.put(int(i), {name: a[i] for name, a in fields.items()})
        writer.flush()

