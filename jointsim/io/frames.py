"""Measured frames in: voltages from a real instrument (or another simulator), read from CSV,
HDF5 or an EIDORS-style ``.mat`` file, with the stimulation and measurement patterns they were
taken with when the file carries them.

The channel order is jointsim's everywhere (:data:`~jointsim.eit.protocol.CHANNEL_ORDER`):
``voltages[s * n_meas_per_stim + m]`` is measurement m of injection s, injection-major, as
EIDORS's ``meas_pattern`` rows of ``fwd_model.stimulation(s)`` list them. A frame is one row
(CSV, HDF5) or one column (``.mat``, EIDORS's ``data.meas`` / ``vv`` convention).

- **CSV**: one frame per line, its n_meas values comma-separated; a first line that is not
  numbers is a header; ``#`` lines are comments.
- **HDF5**: a dataset ``voltages`` (n, n_meas) (a jointsim palpation or dataset store holds
  one, its patterns in its provenance); patterns, if any, as datasets ``stim_A`` (n_stim, n_el)
  A and ``meas`` (n_stim, n_meas_per_stim, n_el).
- **.mat**: ``data.meas`` or ``vv`` or ``voltages`` (n_meas, n) V; patterns, if any, from
  ``fwd_model.stimulation(s).stim_pattern`` / ``.meas_pattern`` (EIDORS).

Patterns given with the frames are compared with the scene's protocol before anything is
imaged: frames taken otherwise would be read as the wrong channels.
"""

from __future__ import annotations

import csv
import io
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["MeasuredFrames", "read_frames", "check_patterns"]

FORMATS = (".csv", ".h5", ".hdf5", ".mat")


@dataclass(frozen=True)
class MeasuredFrames:
    """``voltages`` (n, n_meas) V, one frame per row; the patterns the file carried (``stim``
    (n_stim, n_el) A and ``meas`` (n_stim, n_meas_per_stim, n_el)) or None; ``source`` the path."""

    voltages: np.ndarray
    stim: np.ndarray | None = None
    meas: np.ndarray | None = None
    source: str = ""

    def __len__(self) -> int:
        return len(self.voltages)


def read_frames(path: str | Path) -> MeasuredFrames:
    """The frames in ``path`` (by its suffix: .csv, .h5/.hdf5, .mat); a ValueError naming the
    file and what is wrong for anything else."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"frames {path}: no such file")
    suffix = path.suffix.lower()
    if suffix not in FORMATS:
        raise ValueError(f"frames {path}: unknown format {suffix!r}; give a {', '.join(FORMATS)} file")
    reader = {".csv": _csv, ".h5": _hdf5, ".hdf5": _hdf5, ".mat": _mat}[suffix]
    try:
        frames = reader(path)
    except (OSError, KeyError, TypeError) as e:
        raise ValueError(f"frames {path}: cannot be read as {suffix} ({type(e).__name__}: {e})") from None
    v = np.atleast_2d(np.asarray(frames.voltages, float))
    if v.size == 0 or not np.isfinite(v).all():
        raise ValueError(f"frames {path}: {'no frames' if v.size == 0 else 'non-finite voltages'}")
    return MeasuredFrames(v, frames.stim, frames.meas, str(path))


def _csv(path: Path) -> MeasuredFrames:
    text = path.read_text(encoding="utf-8")
    rows = [r for r in csv.reader(io.StringIO(text)) if r and not r[0].lstrip().startswith("#")]
    out = []
    for i, r in enumerate(rows):
        try:
            out.append([float(x) for x in r if x.strip()])
        except ValueError:
            if i == 0:
                continue  # a header
            raise ValueError(f"frames {path}: line {i + 1} is not numbers") from None
    if len({len(r) for r in out}) > 1:
        raise ValueError(f"frames {path}: frames of {sorted({len(r) for r in out})} values; each must have n_meas")
    return MeasuredFrames(np.array(out, float))


def _hdf5(path: Path) -> MeasuredFrames:
    import h5py

    from .records import open_records

    with h5py.File(path, "r") as h5:
        plain = "voltages" in h5 and isinstance(h5["voltages"], h5py.Dataset)
        if plain:
            stim = h5["stim_A"][()] if "stim_A" in h5 else None
            meas = h5["meas"][()] if "meas" in h5 else None
            return MeasuredFrames(h5["voltages"][()], stim, meas)
    rec = open_records(path, fields=["voltages"], verify=False)  # a jointsim store
    proto = (rec.provenance.get("params") or {}).get("protocol")
    if isinstance(proto, str):
        proto = json.loads(proto)
    stim = np.asarray(proto["stim_A"], float) if proto else None
    meas = np.asarray(proto["meas"], float) if proto else None
    return MeasuredFrames(np.asarray(rec["voltages"]), stim, meas)


def _mat(path: Path) -> MeasuredFrames:
    from scipy.io import loadmat

    m = loadmat(path, squeeze_me=True, struct_as_record=False)
    v = None
    if "data" in m and hasattr(m["data"], "meas"):
        v = m["data"].meas
    else:
        v = next((m[k] for k in ("vv", "voltages", "meas") if k in m), None)
    if v is None:
        raise KeyError("no data.meas, vv, voltages or meas variable")
    v = np.asarray(v, float)
    v = v[:, None] if v.ndim == 1 else v  # (n_meas,) one frame
    stim = meas = None
    fwd = m.get("fwd_model")
    if fwd is not None and hasattr(fwd, "stimulation"):
        st = np.atleast_1d(fwd.stimulation)
        stim = np.array([np.ravel(s.stim_pattern) for s in st], float)
        meas = np.array([np.atleast_2d(s.meas_pattern) for s in st], float)
    return MeasuredFrames(v.T, stim, meas)


def check_patterns(frames: MeasuredFrames, stim: np.ndarray, meas: np.ndarray, n_meas: int) -> None:
    """Refuse (ValueError) frames whose channel count is not ``n_meas``, or that carry
    patterns other than ``stim`` (n_stim, n_el) and ``meas`` (n_stim, n_meas_per_stim, n_el)
    (the scene's protocol), naming what differs."""
    where = f"frames {frames.source}"
    if frames.voltages.shape[1] != n_meas:
        raise ValueError(f"{where}: {frames.voltages.shape[1]} values per frame; the scene's protocol measures {n_meas} "
                         "(channels in the order voltages[s * n_meas_per_stim + m])")
    for name, got, want in (("stimulation", frames.stim, stim), ("measurement", frames.meas, meas)):
        if got is None:
            continue
        got = np.asarray(got, float)
        if got.shape != want.shape:
            raise ValueError(f"{where}: {name} patterns of shape {got.shape}; the scene's are {want.shape}")
        scale = max(float(np.abs(want).max()), 1e-300)
        if np.abs(got - want).max() > 1e-9 * scale:
            s = int(np.argwhere(np.abs(got - want) > 1e-9 * scale)[0][0])
            raise ValueError(f"{where}: its {name} pattern of injection {s} is not the scene's protocol's "
                             "(set [drive] to the patterns the frames were taken with)")
