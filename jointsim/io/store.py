"""Crash-safe, resumable record store shared by ``jointsim palpate`` and ``jointsim dataset``.

Owns the layout of a run in progress (``NAME.partial/``), its writers, and its consolidation
into one HDF5 file (``NAME.h5``) with full provenance. The record schema and the data digest
are :mod:`.schema`'s, the identity and session records :mod:`.provenance`'s, reading a
finalised file :mod:`.records`' (re-exported here: one import gives a job the whole store). It
neither computes records nor schedules work.

A run in progress::

    NAME.partial/
      meta.json     identity of the run (schema, scene TOML, seed, n_records, params, package
                    versions) and its creation time; written once, atomically
      sessions/     one JSON per open_store(): time, host, pid, command line, versions, git commit
      records/<start // 10000>/r<start>_<step>x<count>.<token>.npz
                    the records start, start + step, …, (count of them), with their optional
                    checkpoints; written under a hidden temporary name, fsync'ed and renamed,
                    so a file exists under its final name only when it is complete

Each record index belongs to the writer that computes it. Several processes, or Dask/Ray
workers on several machines sharing a file system, write one store without locks: no two
files ever share a name, and completion is read from file names alone (``done()`` opens no
record). A process killed at any moment leaves at worst a hidden temporary file, ignored.

``finalize()`` checks that every index 0 … N−1 is present, then writes ``NAME.h5`` under a
temporary name and renames it:

* ``/records/<field>``: (N, *shape) in index order, attributes ``unit`` and ``doc``;
* ``/provenance/identity``: JSON of what defines the data (schema, scene TOML, seed, N, params,
  package versions), ``/provenance/scene_toml`` the scene text; root attributes
  ``data_sha256`` (SHA-256 of the field data alone), ``store_format``, ``schema_name``,
  ``schema_version``, ``n_records``, ``seed`` (−1 for none);
* ``/run/info``: JSON of what legitimately differs between two runs of the same data
  (timestamps, hosts, every session's command line and versions).

Two files hold the same data iff their ``data_sha256`` agree, whatever the completion order,
the number of writers or the interruptions; fields declared ``volatile`` (per-stage wall-clock
timings) are stored but left out of that digest.
"""

from __future__ import annotations

import fcntl
import json
import os
import platform
import re
import secrets
import shutil
import socket
import sys
import tempfile
import zipfile
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Iterator, Mapping, Sequence

import numpy as np
from numpy.typing import ArrayLike

from .export import atomic_path
from .provenance import (
    DEFAULT_PACKAGES, check_versions, comparable, first_difference, git_commit, identity, package_versions, sessions,
    utc_now, warn_if_code_changed,
)
from .records import Records, final_path, open_records
from .schema import NAME_PATTERN, STORE_FORMAT, Field, Schema, data_digest

__all__ = [
    "STORE_FORMAT",
    "DEFAULT_PACKAGES",
    "Field",
    "Schema",
    "RecordStore",
    "Records",
    "open_store",
    "attach",
    "open_records",
    "package_versions",
    "utc_now",
    "exclusive",
    "discard",
    "set_aside",
    "readable_records",
]

_FILE_RE = re.compile(r"^r(\d+)_(\d+)x(\d+)\.[0-9a-f]+\.npz$")
_FANOUT = 10_000  # records per sub-directory: keeps directories small at millions of records
_CHUNK_BYTES = 1 << 20  # HDF5 chunk size along the record axis


def _file_mode() -> int:
    """rw for whom the umask allows: temporary files are created 0600, the store is shared."""
    mask = os.umask(0o022)
    os.umask(mask)
    return 0o666 & ~mask


_FILE_MODE = _file_mode()


# --------------------------------------------------------------------------------------------
# Files of a run in progress


def _partial_path(final: Path) -> Path:
    return final.with_suffix(".partial")


@contextmanager
def exclusive(path: str | Path) -> Iterator[None]:
    """Hold the run at ``path`` for this process while the block runs: a second driver on the
    same output (another ``jointsim`` process, or a second run in this one) is refused at its
    start with a ValueError naming the path and the holder, instead of found out at finalize.
    The lock is ``flock`` on a file beside the store (``.NAME.lock``), which the system releases
    however the holder ends, so a run killed with SIGKILL can be resumed at once. Workers of the
    run (:func:`attach`) take no lock."""
    final = final_path(path)
    lock = final.with_name(f".{final.name}.lock")
    lock.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        holder = os.pread(fd, 200, 0).decode(errors="replace").strip() or "another process"
        os.close(fd)
        raise ValueError(f"{final}: another jointsim run is writing it ({holder}); wait for it to end, "
                         "or give another output") from None
    try:
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"pid {os.getpid()} on {socket.gethostname()}".encode(), 0)
        yield
    finally:
        os.close(fd)  # closing the descriptor releases the lock


def discard(path: str | Path) -> bool:
    """Remove the store at ``path`` (``--overwrite``): its finished file and its run in
    progress, once no other run holds it (:func:`exclusive`; refused otherwise). The partial
    folder is renamed away first, so a kill during the removal never leaves half a store under
    its name. Whether there was anything to remove."""
    final = final_path(path)
    partial = _partial_path(final)
    with exclusive(final):
        found = final.exists() or partial.exists()
        final.unlink(missing_ok=True)
        if partial.exists():
            trash = partial.with_name(f".{partial.name}.removing-{secrets.token_hex(4)}")
            os.replace(partial, trash)
            shutil.rmtree(trash, ignore_errors=True)
    return found


def set_aside(path: Path) -> Path:
    """Rename the file ``path`` to NAME.damaged (NAME.damaged.1, … where taken): kept, no longer
    under its name. The new path."""
    target = path.with_name(path.name + ".damaged")
    k = 0
    while target.exists():
        k += 1
        target = path.with_name(f"{path.name}.damaged.{k}")
    os.replace(path, target)
    return target


def readable_records(path: Path) -> tuple[np.ndarray, dict[str, np.ndarray], str | None]:
    """What can still be trusted of a finished store whose check failed: (``ok`` (n,) bool per
    record, every field (n, ...) with untrusted rows zero, the ``data_sha256`` it recorded or
    None). A record is trusted where every field's chunk holding it decodes *and* carries a
    checksum (gzip's zlib stream, or Fletcher-32): HDF5 then refuses a damaged chunk, which
    localises the damage. Without a checksum a flipped byte reads back as a wrong value, so no
    record is trusted; nor where the file cannot be opened."""
    import h5py

    try:
        with h5py.File(path, "r") as h5:
            expected = str(h5.attrs["data_sha256"])
            g = h5["records"]
            n = int(h5.attrs["n_records"])
            ok = np.ones(n, bool)
            fields = {}
            for name in g:
                ds = g[name]
                out = np.zeros(ds.shape, ds.dtype)
                if not (ds.compression == "gzip" or ds.fletcher32) or ds.chunks is None:
                    return np.zeros(n, bool), {}, expected
                rows = ds.chunks[0]
                for a in range(0, n, rows):
                    try:
                        out[a:a + rows] = ds[a:a + rows]
                    except OSError:
                        ok[a:a + rows] = False
                fields[name] = out
    except (OSError, KeyError, ValueError):
        return np.zeros(0, bool), {}, None
    return ok, fields, expected


def _fsync_dir(d: Path) -> None:
    try:
        fd = os.open(d, os.O_RDONLY)
    except OSError:  # platforms without directory handles
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _write_json_once(target: Path, data: Mapping[str, Any]) -> None:
    """Create ``target`` with ``data`` unless it exists: a reader sees all of it or nothing, and
    of two processes racing, the first one's file stays."""
    fd, tmp = tempfile.mkstemp(dir=target.parent, prefix=f".{target.stem}.", suffix=".json")
    try:
        with os.fdopen(fd, "w") as f:
            json.dump(data, f, indent=1, sort_keys=True)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, _FILE_MODE)
        try:
            os.link(tmp, target)  # fails when the target exists, unlike a rename
        except FileExistsError:
            pass
        except OSError:  # file systems without hard links
            if not target.exists():
                os.replace(tmp, target)
    finally:
        Path(tmp).unlink(missing_ok=True)


@dataclass(frozen=True)
class _Files:
    """The complete record files of a store: file k holds indices start[k] + step[k]·j, j < count[k]."""

    paths: list[Path]
    start: np.ndarray
    step: np.ndarray
    count: np.ndarray

    @classmethod
    def scan(cls, partial: Path) -> "_Files":
        rows: list[tuple[int, str, int, int, Path]] = []
        records = partial / "records"
        if records.is_dir():
            for sub in os.scandir(records):
                if sub.is_dir() and not sub.name.startswith("."):
                    for e in os.scandir(sub.path):
                        if m := _FILE_RE.match(e.name):
                            rows.append((int(m[1]), e.name, int(m[2]), int(m[3]), Path(e.path)))
        rows.sort()  # by start, then name: a deterministic order whatever the directory order
        col = lambda i: np.array([r[i] for r in rows], dtype=np.int64)  # noqa: E731
        return cls([r[4] for r in rows], col(0), col(2), col(3))

    def expand(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(index, file number, position in the file) of every stored record, each (n,)."""
        file = np.repeat(np.arange(len(self.paths)), self.count)
        pos = np.arange(file.size) - np.repeat(np.cumsum(self.count) - self.count, self.count)
        return self.start[file] + self.step[file] * pos, file, pos

    def locate(self, index: int) -> tuple[Path, int]:
        off = index - self.start
        hit = np.flatnonzero((off >= 0) & (off % self.step == 0) & (off // self.step < self.count))
        if not hit.size:
            raise KeyError(f"record {index} is not in the store")
        k = int(hit[0])
        return self.paths[k], int(off[k] // self.step[k])


def _load(path: Path, prefixes: tuple[str, ...] = ("",)) -> dict[str, np.ndarray]:
    """The arrays of one record file whose keys start with one of ``prefixes``."""
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files if k.startswith(prefixes)}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as e:
        raise ValueError(f"{path}: unreadable record file ({e}); delete it and run again to recompute its records") from e


def _preview(a: np.ndarray, k: int = 10) -> str:
    s = ", ".join(str(int(x)) for x in a[:k])
    return s + (f", … ({a.size - k} more)" if a.size > k else "")


# --------------------------------------------------------------------------------------------
# Writer


@dataclass(eq=False)
class RecordStore:
    """A run in progress at ``partial`` that finalises to ``path``; from :func:`open_store`
    (the run's driver) or :func:`attach` (its workers). Picklable: a copy sent to another
    process attaches to the same directory. Use as a context manager, or call :meth:`close`,
    when ``batch`` > 1 (buffered records are written then)."""

    path: Path
    schema: Schema
    identity: dict[str, Any]
    batch: int = 1
    fsync: bool = True
    allow_version_change: bool = False
    _buffer: list[tuple[int, dict[str, np.ndarray], dict[str, np.ndarray] | None]] = field(default_factory=list, repr=False)
    _written: set[int] = field(default_factory=set, repr=False)
    _finalised: bool = field(default=False, repr=False)

    def __post_init__(self) -> None:
        if not isinstance(self.batch, (int, np.integer)) or self.batch < 1:
            raise ValueError(f"batch = {self.batch!r}: an integer ≥ 1 (records per file)")

    @property
    def partial(self) -> Path:
        return _partial_path(self.path)

    @property
    def n_records(self) -> int | None:
        return self.identity["n_records"]

    def __reduce__(self) -> tuple[Any, tuple[Any, ...]]:
        return _reattach, (str(self.path), self.batch, self.fsync, self.allow_version_change)

    def __enter__(self) -> "RecordStore":
        return self

    def __exit__(self, *exc: object) -> None:
        # buffered records are complete and valid even when the caller failed on a later one
        self.close()

    # -- writing ---------------------------------------------------------------------------

    def put(self, index: int, record: Mapping[str, ArrayLike], checkpoint: Mapping[str, ArrayLike] | None = None) -> None:
        """Store record ``index`` (validated against the schema) with an optional checkpoint:
        named arrays returned by :meth:`checkpoint` after a restart, never put in the final
        file. Written at once when ``batch`` is 1, else when ``batch`` records with evenly
        spaced increasing indices have been buffered."""
        if self._finalised:
            raise ValueError(f"{self.path} is finalised; open a new store to write more records")
        i = self._check_index(index)
        arrays = self.schema.validate(record, i)
        ck = _check_checkpoint(checkpoint, i)
        if i in self._written:
            raise ValueError(f"record {i} was already written by this writer")
        if self._buffer and not self._continues(i):
            self.flush()
        self._buffer.append((i, arrays, ck))
        self._written.add(i)
        if len(self._buffer) >= self.batch:
            self.flush()

    def _check_index(self, index: int) -> int:
        if not isinstance(index, (int, np.integer)) or isinstance(index, bool):
            raise TypeError(f"record index must be an integer, got {type(index).__name__}")
        n = self.n_records
        if index < 0 or (n is not None and index >= n):
            raise ValueError(f"record index {index} out of range: 0 ≤ index < {n if n is not None else '∞'}")
        return int(index)

    def _continues(self, i: int) -> bool:
        idx = [b[0] for b in self._buffer]
        return i > idx[-1] if len(idx) == 1 else i - idx[-1] == idx[1] - idx[0]

    def flush(self) -> None:
        """Write the buffered records as one file (temporary name, fsync, rename)."""
        if not self._buffer:
            return
        idx = [b[0] for b in self._buffer]
        start, step, count = idx[0], (idx[1] - idx[0] if len(idx) > 1 else 1), len(idx)
        arrays = {"index": np.array(idx, dtype=np.int64)}
        arrays |= {f"f/{n}": np.stack([b[1][n] for b in self._buffer]) for n in self.schema.names}
        for j, (_, _, ck) in enumerate(self._buffer):
            arrays |= {f"c{j}/{k}": v for k, v in (ck or {}).items()}
        target = self.partial / "records" / f"{start // _FANOUT:08d}" / f"r{start:012d}_{step}x{count}.{secrets.token_hex(8)}.npz"
        try:
            with atomic_path(target) as tmp:
                with open(tmp, "wb") as f:
                    np.savez(f, **arrays)
                    if self.fsync:
                        f.flush()
                        os.fsync(f.fileno())
                os.chmod(tmp, _FILE_MODE)
            if self.fsync:
                _fsync_dir(target.parent)
        except OSError as e:  # a full disk, a quota: say where, and that nothing stored is lost
            raise OSError(e.errno, f"{e.strerror or e} (writing records {start}-{idx[-1]}; the records stored before "
                          "are kept: make room and run again)", str(target.parent)) from None
        self._buffer.clear()

    def close(self) -> None:
        self.flush()

    # -- reading the run in progress -------------------------------------------------------

    def done(self) -> np.ndarray:
        """Sorted indices of the records stored so far by any writer, (n_done,) int64;
        buffered, not yet flushed records are not included."""
        return np.unique(_Files.scan(self.partial).expand()[0])

    def set_aside_unreadable(self) -> list[Path]:
        """Read every stored record file back (all its arrays: the zip's CRC-32 checks each);
        a file that cannot be read is :func:`set_aside` (kept, but no longer a record), so
        that its records count as missing and are computed again. The files set aside."""
        aside = []
        for path in _Files.scan(self.partial).paths:
            try:
                _load(path)
            except ValueError:
                aside.append(set_aside(path))
        return aside

    def missing(self, n_records: int | None = None) -> np.ndarray:
        """Sorted indices in 0 … N−1 not stored yet, (n_missing,) int64."""
        n = self._resolve_n(n_records)
        return np.setdiff1d(np.arange(n, dtype=np.int64), self.done(), assume_unique=True)

    def get(self, index: int) -> dict[str, np.ndarray]:
        """Record ``index`` as stored: field name → array of the declared shape."""
        path, j = _Files.scan(self.partial).locate(self._check_index(index))
        z = _load(path, ("f/",))
        return {n: z[f"f/{n}"][j] for n in self.schema.names}

    def checkpoint(self, index: int) -> dict[str, np.ndarray] | None:
        """The checkpoint saved with record ``index`` (None when it was saved without one);
        KeyError when the record is not stored."""
        path, j = _Files.scan(self.partial).locate(self._check_index(index))
        prefix = f"c{j}/"
        ck = {k[len(prefix):]: v for k, v in _load(path, (prefix,)).items()}
        return ck or None

    def _resolve_n(self, n_records: int | None) -> int:
        n = self.n_records
        if n is not None and n_records is not None and n_records != n:
            raise ValueError(f"n_records = {n_records} differs from the run's n_records = {n}")
        n = n if n is not None else n_records
        if n is None:
            raise ValueError("the number of records is not known: pass n_records")
        if not (isinstance(n, (int, np.integer)) and n >= 1):
            raise ValueError(f"n_records = {n!r}: an integer ≥ 1")
        return int(n)

    # -- finalising ------------------------------------------------------------------------

    def finalize(self, n_records: int | None = None, *, compression: str | None = None, keep_partial: bool = False) -> Path:
        """Consolidate records 0 … N−1 into ``path`` (HDF5, written under a temporary name and
        renamed) and remove the partial directory unless ``keep_partial``. Call it once every
        writer has finished. Refuses missing indices, indices ≥ N, and an index stored twice
        with different data. ``compression`` ("gzip", "lzf") applies to every field."""
        import h5py

        self.flush()
        n = self._resolve_n(n_records)
        files = _Files.scan(self.partial)
        idx, file, pos = files.expand()
        if (beyond := np.unique(idx[idx >= n])).size:
            raise ValueError(
                f"cannot finalise {self.path}: {beyond.size} record(s) have an index ≥ n_records = {n} ({_preview(beyond)})"
            )
        counts = np.bincount(idx, minlength=n)
        if (missing := np.flatnonzero(counts == 0)).size:
            raise ValueError(
                f"cannot finalise {self.path}: {missing.size} of {n} records missing (indices {_preview(missing)}); "
                "run again to compute them"
            )
        self._check_duplicates(files, idx, file, pos, np.flatnonzero(counts > 1))

        _check_space(self.path, sum(n * f.row_bytes for f in self.schema.fields))
        ident = dict(self.identity, n_records=n)
        meta = json.loads((self.partial / "meta.json").read_text())
        run = {"created": meta["created"], "finalised": utc_now(), "finalised_on": socket.gethostname(), "sessions": sessions(self.partial)}
        text = h5py.string_dtype()
        try:
            self._write_final(h5py, text, files, idx, file, pos, n, ident, run, compression)
        except (OSError, RuntimeError) as e:
            # the disk filled (HDF5 says so as a RuntimeError, errno 28) or the folder went away
            # while writing: the temporary file is removed, the partial store is intact
            if isinstance(e, RuntimeError) and "errno 28" not in str(e) and "No space" not in str(e):
                raise
            why = getattr(e, "strerror", None) or str(e)
            raise ValueError(f"cannot finalise {self.path}: {why}; the records are kept in {self.partial}: "
                             "free space (or fix the folder) and run again to finalise") from None
        self._finalised = True
        if not keep_partial:
            # renamed first, so a kill during removal never leaves a half-deleted store under its name
            trash = self.partial.with_name(f".{self.partial.name}.removing-{secrets.token_hex(4)}")
            os.replace(self.partial, trash)
            shutil.rmtree(trash, ignore_errors=True)
        return self.path

    def _write_final(self, h5py, text, files, idx, file, pos, n, ident, run, compression) -> None:
        """Write the final file under a temporary name, fsync it, rename it into place."""
        with atomic_path(self.path) as tmp:
            with h5py.File(tmp, "w", rdcc_nbytes=8 << 20) as h5:
                g = h5.create_group("records")
                cols = {}
                for f in self.schema.fields:
                    rows = int(np.clip(_CHUNK_BYTES // f.row_bytes, 1, n))
                    cols[f.name] = d = g.create_dataset(
                        f.name, shape=(n, *f.shape), dtype=f.np_dtype, chunks=(rows, *f.shape),
                        compression=compression, track_times=False,
                    )
                    d.attrs.update(unit=f.unit, doc=f.doc, volatile=f.volatile)
                _copy_rows(cols, self.schema, files, idx, file, pos, n)
                digest = data_digest(cols, self.schema, n)
                prov = h5.create_group("provenance")
                prov.create_dataset("identity", data=json.dumps(ident, sort_keys=True, indent=1), dtype=text, track_times=False)
                prov.create_dataset("scene_toml", data=ident["scene_toml"], dtype=text, track_times=False)
                h5.create_group("run").create_dataset("info", data=json.dumps(run, sort_keys=True, indent=1), dtype=text)
                h5.attrs.update(
                    data_sha256=digest, store_format=STORE_FORMAT, schema_name=self.schema.name,
                    schema_version=self.schema.version, n_records=n, seed=-1 if ident["seed"] is None else ident["seed"],
                )
            with open(tmp, "rb+") as fh:  # on disk before the rename makes it the final file
                os.fsync(fh.fileno())
            os.chmod(tmp, _FILE_MODE)

    def _check_duplicates(self, files: _Files, idx: np.ndarray, file: np.ndarray, pos: np.ndarray, dups: np.ndarray) -> None:
        """An index written twice (a retried task, a worker killed after it wrote) is harmless
        when both copies agree in every field but the volatile ones (wall-clock timings, which
        two runs of the same work never share); the first copy is kept. The first 1000 such
        indices are compared (each costs two file reads)."""
        for i in dups[:1000]:
            where = np.flatnonzero(idx == i)
            copies = [(files.paths[file[w]], _load(files.paths[file[w]], ("f/",)), pos[w]) for w in where]
            p0, z0, j0 = copies[0]
            for p, z, j in copies[1:]:
                for n in (f.name for f in self.schema.fields if not f.volatile):
                    if not np.array_equal(z0[f"f/{n}"][j0], z[f"f/{n}"][j], equal_nan=z[f"f/{n}"].dtype.kind in "fc"):
                        raise ValueError(
                            f"record {i} was written twice with different data (field {n!r}; files {p0.name}, {p.name}): "
                            "two writers computed the same index differently; delete the wrong file"
                        )


SPACE_MARGIN = 1.1  # free space asked for before finalising: the uncompressed data, plus metadata


def _check_space(path: Path, data_bytes: int) -> None:
    """Refuse to start the final file where the disk cannot hold it (HDF5 does not survive
    ENOSPC cleanly: a full disk mid-write ended in a segfault). Uncompressed bytes are the bound."""
    need = int(SPACE_MARGIN * data_bytes) + (1 << 20)
    free = shutil.disk_usage(path.parent).free
    if free < need:
        raise ValueError(f"cannot finalise {path}: {free / 1e6:.1f} MB free on its disk, {need / 1e6:.1f} MB needed; "
                         f"the records are kept in {_partial_path(path)}: free space and run again to finalise")


def _copy_rows(
    cols: Mapping[str, Any], schema: Schema, files: _Files, idx: np.ndarray, file: np.ndarray, pos: np.ndarray, n: int
) -> None:
    """Write rows 0 … n−1 of every field into ``cols`` (HDF5 datasets) in blocks of contiguous
    rows, gathered from the record files (``idx``, ``file``, ``pos`` from :meth:`_Files.expand`;
    every index present; of duplicates, the first file's copy). A file stays loaded until the
    block that holds its last record has been written."""
    order = np.lexsort((file, idx))
    first = np.r_[True, idx[order][1:] != idx[order][:-1]]
    file_of, pos_of = file[order][first], pos[order][first]  # (n,): where row r is stored
    last = files.start + files.step * (files.count - 1)
    block = int(np.clip((64 << 20) // sum(f.row_bytes for f in schema.fields), 1, n))
    loaded: dict[int, dict[str, np.ndarray]] = {}
    for a in range(0, n, block):
        b = min(n, a + block)
        fk, pk = file_of[a:b], pos_of[a:b]
        o = np.argsort(fk, kind="stable")
        ks, cut = np.unique(fk[o], return_index=True)
        bufs = {f.name: np.empty((b - a, *f.shape), f.np_dtype) for f in schema.fields}
        for k, rows in zip(ks.tolist(), np.split(o, cut[1:])):
            if k not in loaded:
                z = loaded[k] = _load(files.paths[k], ("index", "f/"))  # checkpoints stay behind
                named = files.start[k] + files.step[k] * np.arange(files.count[k])
                if not np.array_equal(z["index"], named):
                    raise ValueError(f"{files.paths[k]}: its contents do not match its name; delete it and run again")
            for name, buf in bufs.items():
                buf[rows] = loaded[k][f"f/{name}"][pk[rows]]
        for name, buf in bufs.items():
            cols[name][a:b] = buf
        loaded = {k: z for k, z in loaded.items() if last[k] >= b}


def _check_checkpoint(checkpoint: Mapping[str, ArrayLike] | None, index: int) -> dict[str, np.ndarray] | None:
    if checkpoint is None:
        return None
    if not isinstance(checkpoint, Mapping):
        raise TypeError(f"record {index}: checkpoint must be a mapping of name to array, got {type(checkpoint).__name__}")
    out = {}
    for k, v in checkpoint.items():
        if not isinstance(k, str) or not NAME_PATTERN.match(k):
            raise ValueError(f"record {index}: checkpoint name {k!r}: letters, digits and '_' only")
        a = np.asarray(v)
        if a.dtype.kind not in "biufc":
            raise ValueError(f"record {index}: checkpoint {k!r} has dtype {a.dtype}; numeric or bool arrays only")
        out[k] = a
    return out


# --------------------------------------------------------------------------------------------
# Opening


def open_store(
    path: str | Path,
    schema: Schema,
    *,
    scene_toml: str,
    seed: int | None,
    n_records: int | None,
    params: Mapping[str, Any] | None = None,
    command: Sequence[str] | None = None,
    batch: int = 1,
    fsync: bool = True,
    allow_version_change: bool = False,
    packages: Iterable[str] = DEFAULT_PACKAGES,
) -> RecordStore:
    """Start the run that finalises to ``path`` (``.h5`` appended when it has no HDF5 suffix),
    or resume it: the partial store must have been created with the same schema, scene (as
    parsed: comments may change), seed, n_records and params (JSON: every run setting that
    shapes the data, e.g. a mesh-preset override), and by default the same package versions.
    Safe to call from several processes at once. Records this call as a session (time, host,
    ``command``, default ``sys.argv``). A FileExistsError when ``path`` already exists."""
    final = final_path(path)
    if final.exists():
        raise FileExistsError(f"{final} already exists (a finished run); remove it or write to another path")
    versions = package_versions(packages)
    ident = identity(schema, scene_toml, seed, n_records, params, versions)
    partial = _partial_path(final)
    (partial / "sessions").mkdir(parents=True, exist_ok=True)
    _write_json_once(partial / "meta.json", {"identity": ident, "created": utc_now()})
    stored = _read_meta(partial)["identity"]
    if diff := first_difference(comparable(stored), comparable(ident)):
        raise ValueError(
            f"{partial} holds a different run ({diff}); resume only the same run (same schema, scene, "
            "seed, n_records, params), or write to another path"
        )
    if not allow_version_change:
        check_versions(stored["versions"], versions, partial)
    commit = git_commit()
    warn_if_code_changed(partial, commit)
    session = {
        "started": utc_now(), "host": socket.gethostname(), "pid": os.getpid(), "platform": platform.platform(),
        "command": list(sys.argv if command is None else command), "versions": versions, "jointsim_git": commit,
    }
    name = f"{session['started'].replace(':', '')}-{os.getpid()}-{secrets.token_hex(4)}.json"  # sorts by time
    with atomic_path(partial / "sessions" / name) as tmp:
        tmp.write_text(json.dumps(session, sort_keys=True, indent=1))
        os.chmod(tmp, _FILE_MODE)
    return RecordStore(final, schema, stored, batch=batch, fsync=fsync, allow_version_change=allow_version_change)


def attach(path: str | Path, *, batch: int = 1, fsync: bool = True, allow_version_change: bool = False) -> RecordStore:
    """A writer on a run already started by :func:`open_store` (e.g. in a Dask or Ray task):
    schema and identity from the store; refuses other package versions unless
    ``allow_version_change``."""
    final = final_path(path)
    partial = _partial_path(final)
    stored = _read_meta(partial)["identity"]
    if not allow_version_change:
        check_versions(stored["versions"], package_versions(stored["versions"].keys() - {"python"}), partial)
    schema = Schema.from_json(stored["schema"])
    return RecordStore(final, schema, stored, batch=batch, fsync=fsync, allow_version_change=allow_version_change)


def _reattach(path: str, batch: int, fsync: bool, allow_version_change: bool) -> RecordStore:
    return attach(path, batch=batch, fsync=fsync, allow_version_change=allow_version_change)


def _read_meta(partial: Path) -> dict[str, Any]:
    meta = partial / "meta.json"
    if not meta.is_file():
        raise FileNotFoundError(f"no run in progress at {partial} (start it with open_store)")
    d = json.loads(meta.read_text())
    if d["identity"].get("store_format") != STORE_FORMAT:
        raise ValueError(f"{partial}: store format {d['identity'].get('store_format')} , this jointsim reads {STORE_FORMAT}")
    return d
