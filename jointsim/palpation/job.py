"""A palpation job, as ``jointsim palpate`` runs it: a scene's program into an output folder.

Owns the folder's life: the store (``OUT/palpation.h5``, resumed when a run with the same
settings was interrupted; a finished one is only reported again), the VTU series, the set-up
record, the Fig. 4 report. One call does it all; the command line parses and prints.
"""

from __future__ import annotations

import json
import shlex
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from ..io.records import Records, open_records
from ..io.store import exclusive, open_store, set_aside
from ..scene import Scene
from .pipeline import Frame, Palpation, program_params, run_palpation
from .report import VtuSeries, write_pvd, write_report, write_setup

__all__ = ["PalpationJob", "palpate"]


@dataclass(frozen=True)
class PalpationJob:
    """What :func:`palpate` did: the finished ``records``, the report files ``written``, and
    whether the frames were ``computed`` now (False: the folder held the finished run)."""

    records: Records
    written: list[Path]
    computed: bool


def palpate(scene: Scene, out: str | Path, *, scene_text: str, command: str, device: str = "cpu",
            vtu_every: int = 1, say: Callable[[str], None] = print, progress: Callable[[int, Frame], None] | None = None,
            ) -> PalpationJob:
    """Run ``scene``'s palpation program into ``out``: its frames stored resumably in
    ``out/palpation.h5`` (``scene_text``, the scene file's text, and ``command``, the command
    line as text, in its provenance), the VTU series every ``vtu_every`` frames of each target
    (0: none), the set-up record and the report. A folder holding the finished run with other settings is
    refused (ValueError); with the same settings its report is rewritten. ``say`` gets the
    progress lines (set-up, resume); ``progress(n, frame)`` each frame done (n frames skipped:
    frame None)."""
    if vtu_every < 0:
        raise ValueError(f"vtu_every = {vtu_every}: must be >= 0")
    out = Path(out)
    h5 = out / "palpation.h5"
    spec = scene.palpation
    params = program_params(scene, spec)
    computed = False
    with exclusive(h5):  # a second palpate on this folder is refused now, not at finalize
        if h5.exists():
            try:  # read back whole against its data_sha256: a damaged file is found here
                rec = open_records(h5)
            except (ValueError, OSError) as e:
                # a time series resumes from its checkpoints, which the finished file does not
                # keep: the damaged file is set aside (kept) and the run computed again
                aside = set_aside(h5)
                warnings.warn(f"{h5}: cannot be read back whole ({e}); set aside as {aside.name}, the run is computed again",
                              UserWarning, stacklevel=2)
        if h5.exists():
            if rec.provenance["params"] != json.loads(json.dumps(params)):
                raise ValueError(f"{h5} holds a finished run with other settings; remove it, give --overwrite, or use another --out")
            say(f"  {h5} is complete ({len(rec)} frames): reports rewritten from it")
        else:
            pal = Palpation(scene, spec, device=device)
            inst = pal.instrument
            say("  set-up: " + ", ".join(f"{k} {v:.1f} s" for k, v in pal.setup_timings.items())
                + f"; chamber {inst.reference.mesh.n_tets:,} tets, membrane {pal.membrane_nodes:,} nodes ({scene.membrane.element}), "
                f"{inst.grid.n_cells:,} voxels, lambda {inst.imager.reconstructor.lam:.3g}")
            store = open_store(h5, pal.schema(), scene_toml=scene_text, seed=scene.noise.seed, n_records=pal.n_records,
                               params=params, command=shlex.split(command))
            if done := len(store.done()):
                say(f"  resuming: {done} of {pal.n_records} frames already stored")
            write_setup(out, pal)
            export = VtuSeries(out, pal, vtu_every) if vtu_every else None
            last: list[Frame | None] = [None]

            def tick(n: int) -> None:
                if progress is not None:
                    progress(n, last[0])

            try:
                for f in run_palpation(pal, store, export=export, progress=tick):
                    last[0] = f
                store.finalize(compression="gzip")
            finally:
                pal.free()
            rec, computed = open_records(h5), True
    written = write_pvd(out, scene.noise.frame_rate_hz) + write_report(out, rec, command)
    return PalpationJob(rec, written, computed)
