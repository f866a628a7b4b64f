"""Reading a ``jointsim dataset`` store for calibration, and splitting it by press.

Owns the fields calibration needs (:data:`REQUIRED`), the checks on a store before any fit
(schema name and version, missing fields, enough press groups), the :class:`Samples` arrays
(SI units, one row per labelled sample) and the held-out split, made **by group** (every
sample of one press on the same side) and deterministic by seed.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from .fingerprint import provenance_fingerprint

__all__ = ["SCHEMA_NAME", "SCHEMA_VERSION", "REQUIRED", "MIN_GROUPS", "Samples", "load_samples", "split_groups",
           "first_per_group", "voltage_features"]

SCHEMA_NAME = "dataset"
SCHEMA_VERSION = 3
SCHEMA_VERSIONS = (1, 2, 3)  # version 1 has no contact_centre: positions are then the target's centre; 3 adds contact_point
REQUIRED = ("group", "radius", "xy", "depth", "target_modulus", "force", "snr_db", "voltages", "dv", "com",
            "sum_sigma", "diameter")
MIN_GROUPS = 5  # 3 to fit, 2 held out, at the least


def voltage_features(voltages: np.ndarray, dv: np.ndarray) -> np.ndarray:
    """δV relative to the measured reference, (n, 256): δV / (V − δV). Dividing by the
    standing voltage takes out the saline conductivity's and the current's scale."""
    ref = np.asarray(voltages, float) - np.asarray(dv, float)
    return np.asarray(dv, float) / np.where(np.abs(ref) > 0, ref, np.nan)


@dataclass(frozen=True)
class Samples:
    """Labelled samples, (n,) or (n, k) arrays in SI units: press ``group``, target ``radius``
    m, centre ``xy`` (n, 2) m, ``depth`` m past first contact, ``modulus`` Pa (+inf rigid),
    contact ``force`` (n, 3) N, ``snr_db``, ``voltages`` and ``dv`` (n, 256) V, reconstructed
    ``com`` (n, 3) m, ``sum_sigma``, image ``diameter`` m, the contact's centre of pressure
    ``contact_xy`` (n, 2) m (NaN from a version-1 store); ``fingerprint`` of the sensor and
    ``source`` (path, data_sha256, n_records, seed). Where the store has them, the noise-free
    ``voltages_clean`` and ``reference_clean`` (n, 256) V and the ``reference_frames`` averaged
    into the measured reference: what fresh noise draws of the same samples need (else None)."""

    group: np.ndarray
    radius: np.ndarray
    xy: np.ndarray
    depth: np.ndarray
    modulus: np.ndarray
    force: np.ndarray
    snr_db: np.ndarray
    voltages: np.ndarray
    dv: np.ndarray
    com: np.ndarray
    sum_sigma: np.ndarray
    diameter: np.ndarray
    contact_xy: np.ndarray
    fingerprint: dict[str, Any] = field(default_factory=dict)
    source: dict[str, Any] = field(default_factory=dict)
    voltages_clean: np.ndarray | None = None
    reference_clean: np.ndarray | None = None
    reference_frames: int = 1

    def __len__(self) -> int:
        return len(self.group)

    @property
    def size(self) -> np.ndarray:
        """True target diameter (n,) m (the paper's 8–30 mm are diameters)."""
        return 2.0 * self.radius

    @property
    def force_mag(self) -> np.ndarray:
        """|force| (n,) N."""
        return np.linalg.norm(self.force, axis=1)

    @property
    def rms_dv(self) -> np.ndarray:
        """RMS of the noisy δV (n,) V."""
        return np.sqrt(np.mean(self.dv**2, axis=1))

    @property
    def contact_known(self) -> bool:
        """Whether every sample has its contact's centre of pressure (a version-2 store)."""
        return bool(len(self.contact_xy) and np.isfinite(self.contact_xy).all())

    @property
    def position(self) -> np.ndarray:
        """True (x, y, depth) (n, 3) m: what the CoM map and the regression estimate. (x, y)
        is where the target presses the sensor, the contact's centre of pressure, when the
        store has it; else the target's centre (off the axis they differ: the dome slopes,
        and the contact lies between the target's centre and the dome's, by an amount that
        grows with the target's radius, which the image does not see directly)."""
        return np.column_stack([self.contact_xy if self.contact_known else self.xy, self.depth])

    def metric(self, name: str) -> np.ndarray:
        """An image or voltage metric (n,) by name: sum_sigma, diameter, rms_dv, force."""
        return {"sum_sigma": self.sum_sigma, "diameter": self.diameter, "rms_dv": self.rms_dv,
                "force": self.force_mag}[name]

    @property
    def press(self) -> np.ndarray:
        """The press θ = (x, y, depth, diameter) (n, 4) m the emulator maps to features: the
        :attr:`position`'s x, y, the depth past first contact, the target's diameter."""
        return np.column_stack([self.position[:, :2], self.depth, self.size])

    @property
    def clean_features(self) -> np.ndarray:
        """:func:`voltage_features` of the noise-free voltages against the noise-free reference (n, 256)."""
        return voltage_features(self.voltages_clean, self.voltages_clean - self.reference_clean)

    @property
    def has_clean(self) -> bool:
        """Whether the noise-free voltages are there (fresh noise can be drawn)."""
        return self.voltages_clean is not None and self.reference_clean is not None

    def subset(self, mask: np.ndarray) -> "Samples":
        """The samples where ``mask`` (n,) bool (or an index array) selects."""
        arrays = {k: getattr(self, k)[mask] for k in REQUIRED_ATTRS}
        clean = {k: None if getattr(self, k) is None else getattr(self, k)[mask] for k in CLEAN}
        return Samples(**arrays, **clean, fingerprint=self.fingerprint, source=self.source,
                       reference_frames=self.reference_frames)


REQUIRED_ATTRS = ("group", "radius", "xy", "depth", "modulus", "force", "snr_db", "voltages", "dv", "com",
                  "sum_sigma", "diameter", "contact_xy")
CLEAN = ("voltages_clean", "reference_clean")  # optional: fresh noise for the direct regression's training


def _check_shapes(fields: Mapping[str, np.ndarray], n: int) -> None:
    want = {"xy": (2,), "force": (3,), "com": (3,)}
    for name, a in fields.items():
        shape = want.get(name, a.shape[1:] if name in ("voltages", "dv") else ())
        if a.shape[0] != n or a.shape[1:] != shape:
            raise ValueError(f"dataset field {name!r} has shape {a.shape}, calibration needs ({n}, {', '.join(map(str, shape))})")
    if fields["voltages"].shape[1:] != fields["dv"].shape[1:] or fields["dv"].ndim != 2:
        raise ValueError(f"dataset fields 'voltages' {fields['voltages'].shape} and 'dv' {fields['dv'].shape} must be (n, n_meas)")


def load_samples(path: str | Path) -> Samples:
    """The calibration fields of the dataset store ``path`` (``NAME.h5`` from ``jointsim
    dataset``), verified against its digest. A ValueError naming the problem for a file that
    is missing or not a record store, a store of another schema, or missing fields."""
    from ..io.records import open_records

    path = Path(path)
    if not path.is_file():
        raise ValueError(f"dataset {path}: no such file (a finished store NAME.h5 from jointsim dataset)")
    try:
        head = open_records(path, fields=[], verify=False)
    except (OSError, KeyError) as e:
        raise ValueError(f"dataset {path}: not a jointsim record store ({e})") from None
    s = head.schema
    if s.name != SCHEMA_NAME or s.version not in SCHEMA_VERSIONS:
        raise ValueError(
            f"dataset {path}: a {s.name!r} store (schema version {s.version}); calibration reads "
            f"{SCHEMA_NAME!r} stores of schema version {' or '.join(map(str, SCHEMA_VERSIONS))} (from jointsim dataset)"
        )
    if missing := [n for n in REQUIRED if n not in s.names]:
        raise ValueError(f"dataset {path}: missing field(s) {missing}; calibration needs {list(REQUIRED)}")
    extra = ["contact_centre"] if "contact_centre" in s.names else []
    clean = list(CLEAN) if all(n in s.names for n in CLEAN) else []
    try:
        rec = open_records(path, fields=list(REQUIRED) + extra + clean)
    except OSError as e:  # pragma: no cover - a damaged file
        raise ValueError(f"dataset {path}: cannot be read ({e})") from None
    f = {k: np.asarray(rec[k]) for k in REQUIRED}
    n = len(f["group"])
    _check_shapes(f, n)
    source = {"path": str(path), "data_sha256": rec.data_sha256, "n_records": n, "seed": rec.provenance.get("seed"),
              "synthetic": bool((rec.provenance.get("params") or {}).get("synthetic", False))}
    return Samples(
        group=f["group"].astype(np.int64), radius=f["radius"].astype(float), xy=f["xy"].astype(float),
        depth=f["depth"].astype(float), modulus=f["target_modulus"].astype(float), force=f["force"].astype(float),
        snr_db=f["snr_db"].astype(float), voltages=f["voltages"].astype(float), dv=f["dv"].astype(float),
        com=f["com"].astype(float), sum_sigma=f["sum_sigma"].astype(float), diameter=f["diameter"].astype(float),
        contact_xy=np.asarray(rec["contact_centre"], float)[:, :2] if extra else np.full((n, 2), np.nan),
        fingerprint=provenance_fingerprint(rec.provenance), source=source,
        **{k: np.asarray(rec[k], float) for k in clean}, reference_frames=_reference_frames(rec.provenance),
    )


def _reference_frames(provenance: Mapping[str, Any]) -> int:
    """Frames averaged into each group's measured reference (the dataset spec's
    ``reference_frames``; jointsim dataset's default when the provenance does not say)."""
    from ..scene import DatasetSpec

    spec = ((provenance.get("params") or {}).get("scene") or {}).get("dataset") or {}
    return int(spec.get("reference_frames", DatasetSpec().reference_frames))


def split_groups(group: np.ndarray, test_fraction: float = 0.2, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Boolean masks (train, test), (n,) each, splitting whole press groups: a group's samples
    are all on one side. The held-out groups are the first ⌈fraction·G⌉ (at least 2) of the
    sorted group ids permuted by ``seed``, so the split depends on the ids alone, not on the
    order of the samples."""
    if not 0 < test_fraction < 1:
        raise ValueError(f"test_fraction = {test_fraction!r}: must be in (0, 1)")
    ids = np.unique(group)
    if len(ids) < MIN_GROUPS:
        raise ValueError(
            f"the dataset has {len(ids)} press group(s); a held-out split needs at least {MIN_GROUPS} "
            "(3 to fit, 2 held out): generate more samples"
        )
    n_test = int(np.clip(np.ceil(test_fraction * len(ids)), 2, len(ids) - 3))
    test_ids = np.random.default_rng(seed).permutation(ids)[:n_test]
    test = np.isin(group, test_ids)
    return ~test, test


def first_per_group(group: np.ndarray, *arrays: np.ndarray) -> tuple[np.ndarray, ...]:
    """The sorted group ids (G,) and, for each array, its value on the group's first sample."""
    ids, first = np.unique(group, return_index=True)
    return (ids, *(np.asarray(a)[first] for a in arrays))
