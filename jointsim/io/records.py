"""Reading a finalised store (``NAME.h5``): its fields as arrays, its provenance, its digest
checked. Also where a store's final file is for a path given with or without ``.h5``."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from .schema import Schema, data_digest

__all__ = ["Records", "open_records", "final_path"]


def final_path(path: str | Path) -> Path:
    """The finalised file of the store at ``path`` (``.h5`` added unless it ends in .h5/.hdf5)."""
    path = Path(path)
    return path if path.suffix in (".h5", ".hdf5") else path.with_name(path.name + ".h5")


@dataclass(frozen=True)
class Records:
    """A finalised store: ``fields[name]`` is (N, *shape) in index order; ``provenance`` what
    defines the data (schema, scene_toml, seed, n_records, params, versions); ``run`` what may
    differ between two runs of the same data (times, hosts, sessions' command lines)."""

    fields: dict[str, np.ndarray]
    schema: Schema
    provenance: dict[str, Any]
    run: dict[str, Any]
    data_sha256: str

    def __getitem__(self, name: str) -> np.ndarray:
        return self.fields[name]

    def __len__(self) -> int:
        return int(self.provenance["n_records"])


def open_records(path: str | Path, fields: Sequence[str] | None = None, *, verify: bool = True) -> Records:
    """Read a file written by :meth:`RecordStore.finalize` (``path`` itself where it is a file,
    else the store it finalises to, NAME.h5): the named ``fields`` (all when None)
    as arrays; with ``verify``, recompute ``data_sha256`` from all fields and refuse a mismatch."""
    import h5py

    path = Path(path) if Path(path).is_file() else final_path(path)  # a file named as it is, else NAME.h5
    with h5py.File(path, "r") as h5:
        prov = json.loads(h5["provenance/identity"].asstr()[()])
        run = json.loads(h5["run/info"].asstr()[()])
        schema = Schema.from_json(prov["schema"])
        names = list(schema.names if fields is None else fields)
        for n in names:
            schema[n]  # KeyError naming the schema's fields
        g = h5["records"]
        digest = str(h5.attrs["data_sha256"])
        if verify and data_digest(g, schema, prov["n_records"]) != digest:
            raise ValueError(f"{path}: data does not match its data_sha256; the file is damaged")
        return Records({n: g[n][()] for n in names}, schema, prov, run, digest)
