"""The record schema of a store: named fields with a fixed shape, dtype, unit and doc, and the
digest that identifies a store's data.

Owns what a record is (:class:`Field`, :class:`Schema`, validation of one record against it)
and ``data_sha256`` (:func:`data_digest`): the SHA-256 of the non-volatile fields in schema
order, so that two files hold the same data iff their digests agree.
"""

from __future__ import annotations

import hashlib
import re
from dataclasses import asdict, dataclass
from typing import Any, Mapping

import numpy as np
from numpy.typing import ArrayLike

__all__ = ["STORE_FORMAT", "NAME_PATTERN", "Field", "Schema", "data_digest"]

STORE_FORMAT = 1  # the layout of stores and finalised files; part of every identity and digest
NAME_PATTERN = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")  # field and checkpoint names
HASH_BLOCK_BYTES = 16 << 20  # rows hashed at a time


@dataclass(frozen=True)
class Field:
    """One named array per record: ``shape`` excludes the record axis, ``()`` is a scalar.
    A ``volatile`` field (wall-clock timings) may differ between two runs of the same data and
    is left out of ``data_sha256``."""

    name: str
    shape: tuple[int, ...] = ()
    dtype: str = "float64"
    unit: str = ""
    doc: str = ""
    volatile: bool = False

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not NAME_PATTERN.match(self.name):
            raise ValueError(f"field name {self.name!r}: letters, digits and '_' only, not starting with a digit")
        shape = (self.shape,) if isinstance(self.shape, (int, np.integer)) else tuple(self.shape)
        if not all(isinstance(s, (int, np.integer)) and s >= 1 for s in shape):
            raise ValueError(f"field {self.name!r}: shape {self.shape!r} must be a tuple of integers ≥ 1")
        try:
            dt = np.dtype(self.dtype)
        except TypeError as e:
            raise ValueError(f"field {self.name!r}: dtype {self.dtype!r} is not a NumPy dtype ({e})") from None
        if dt.kind not in "biufc":
            raise ValueError(f"field {self.name!r}: dtype {dt} is not numeric or bool (allowed kinds: b, i, u, f, c)")
        object.__setattr__(self, "shape", tuple(int(s) for s in shape))
        object.__setattr__(self, "dtype", dt.name)
        object.__setattr__(self, "volatile", bool(self.volatile))

    @property
    def np_dtype(self) -> np.dtype:
        return np.dtype(self.dtype)

    @property
    def row_bytes(self) -> int:
        return self.np_dtype.itemsize * int(np.prod(self.shape, dtype=np.int64))


@dataclass(frozen=True)
class Schema:
    """The fields every record carries, in order; ``name`` and ``version`` identify the layout
    for readers (bump ``version`` when a command changes what it writes)."""

    fields: tuple[Field, ...]
    name: str = "records"
    version: int = 1

    def __post_init__(self) -> None:
        fields = tuple(self.fields)
        if not fields or not all(isinstance(f, Field) for f in fields):
            raise ValueError("a schema needs one or more Field objects")
        names = [f.name for f in fields]
        if dup := sorted({n for n in names if names.count(n) > 1}):
            raise ValueError(f"schema {self.name!r}: duplicate field name(s) {dup}")
        if not isinstance(self.version, (int, np.integer)) or self.version < 1:
            raise ValueError(f"schema {self.name!r}: version {self.version!r} must be an integer ≥ 1")
        object.__setattr__(self, "fields", fields)
        object.__setattr__(self, "version", int(self.version))

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(f.name for f in self.fields)

    def __getitem__(self, name: str) -> Field:
        for f in self.fields:
            if f.name == name:
                return f
        raise KeyError(f"no field {name!r} in schema {self.name!r} (fields: {', '.join(self.names)})")

    def to_json(self) -> dict[str, Any]:
        return {"name": self.name, "version": self.version, "fields": [asdict(f) for f in self.fields]}

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> "Schema":
        return cls(tuple(Field(**f) for f in d["fields"]), name=d["name"], version=d["version"])

    def validate(self, record: Mapping[str, ArrayLike], index: int | None = None) -> dict[str, np.ndarray]:
        """The record's arrays cast to the declared dtypes; a ValueError naming the field for a
        missing or extra field, a wrong shape, or a dtype that does not convert (same kind)."""
        where = "record" if index is None else f"record {index}"
        if not isinstance(record, Mapping):
            raise TypeError(f"{where}: expected a mapping of field name to array, got {type(record).__name__}")
        if missing := [n for n in self.names if n not in record]:
            raise ValueError(f"{where}: missing field(s) {missing}; schema {self.name!r} declares {list(self.names)}")
        if extra := sorted(set(record) - set(self.names), key=str):
            raise ValueError(f"{where}: field(s) {extra} not in schema {self.name!r}, which declares {list(self.names)}")
        out = {}
        for f in self.fields:
            a = np.asarray(record[f.name])
            if a.shape != f.shape:
                raise ValueError(f"{where}: field {f.name!r} has shape {a.shape}, the schema declares {f.shape}")
            if not np.can_cast(a.dtype, f.np_dtype, casting="same_kind"):
                raise ValueError(
                    f"{where}: field {f.name!r} has dtype {a.dtype}, which does not convert to the declared {f.dtype}"
                )
            out[f.name] = a.astype(f.np_dtype, copy=False)
        return out


def data_digest(columns: Mapping[str, Any], schema: Schema, n: int) -> str:
    """SHA-256 of the non-volatile fields in schema order, little-endian, rows 0 … n−1;
    ``columns`` maps a field name to anything sliceable along rows (HDF5 dataset, array)."""
    h = hashlib.sha256(f"jointsim-store-{STORE_FORMAT} n={n}\n".encode())
    for f in (f for f in schema.fields if not f.volatile):
        le = f.np_dtype.newbyteorder("<")
        h.update(f"{f.name} {le.str} {f.shape}\n".encode())
        rows = max(1, HASH_BLOCK_BYTES // f.row_bytes)
        for a in range(0, n, rows):
            h.update(np.ascontiguousarray(columns[f.name][a : a + rows], dtype=le).data)
    return h.hexdigest()
