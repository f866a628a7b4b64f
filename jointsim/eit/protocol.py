"""Injection and measurement protocols as plain arrays with EIDORS meaning.

``stim[s]`` is EIDORS's ``stimulation(s).stim_pattern``: the current (A) into each electrode
for injection s (positive into the saline). ``meas[s]`` is ``stimulation(s).meas_pattern``:
each row weights the electrode voltages into one measurement. Voltages are referenced to the
grounded electrode, so "electrode l against ground" is the unit row e_l.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Protocol", "skip_protocol", "skip_pairs"]


@dataclass(frozen=True, eq=False)
class Protocol:
    """``stim`` (n_stim, n_el) currents in A; ``meas`` (n_stim, n_meas, n_el) weights.

    ``n_el`` counts the driven/measured electrodes (the ring), not the ground."""

    stim: np.ndarray
    meas: np.ndarray

    def __post_init__(self) -> None:
        stim = np.atleast_2d(np.asarray(self.stim, dtype=float))
        meas = np.asarray(self.meas, dtype=float)
        if meas.ndim == 2:  # one measurement pattern shared by all injections
            meas = np.broadcast_to(meas, (len(stim),) + meas.shape)
        if meas.ndim != 3 or meas.shape[0] != stim.shape[0] or meas.shape[2] != stim.shape[1]:
            raise ValueError(
                f"meas: expected shape (n_stim={stim.shape[0]}, n_meas, n_el={stim.shape[1]}), got {meas.shape}"
            )
        if not (np.isfinite(stim).all() and np.isfinite(meas).all()):
            raise ValueError("stim and meas must be finite")
        object.__setattr__(self, "stim", stim)
        object.__setattr__(self, "meas", np.ascontiguousarray(meas))

    @property
    def n_el(self) -> int:
        return self.stim.shape[1]

    @property
    def n_stim(self) -> int:
        return self.stim.shape[0]

    @property
    def n_meas(self) -> int:
        """Total number of measurements (all injections)."""
        return self.meas.shape[0] * self.meas.shape[1]

    def measure(self, electrode_voltages: np.ndarray) -> np.ndarray:
        """Measurements from electrode voltages (n_stim, n_el) → (n_meas,), injection-major."""
        return np.einsum("sme,se->sm", self.meas, electrode_voltages).ravel()


def skip_pairs(n_el: int, skip: int) -> np.ndarray:
    """(n_el, 2) source/sink electrodes: injection i drives i (+) against i + skip + 1 (−)."""
    if not 0 <= skip <= n_el - 2:
        raise ValueError(f"skip = {skip}: must be in [0, {n_el - 2}] for {n_el} electrodes")
    i = np.arange(n_el)
    return np.column_stack([i, (i + skip + 1) % n_el])


def skip_protocol(n_el: int = 16, skip: int = 8, current: float = 120e-6, measure: str = "ground") -> Protocol:
    """Skip-N injections (skip-0 adjacent; skip-7 opposite on 16 electrodes).

    measure = "ground": every electrode against the ground (the paper's 16 × n_el frame,
    injecting electrodes included); "adjacent": EIDORS '{ad}' differential pairs l − (l+1)."""
    if current <= 0:
        raise ValueError(f"current = {current}: must be > 0 A")
    pairs = skip_pairs(n_el, skip)
    stim = np.zeros((n_el, n_el))
    stim[np.arange(n_el), pairs[:, 0]] = current
    stim[np.arange(n_el), pairs[:, 1]] = -current
    if measure == "ground":
        m = np.eye(n_el)
    elif measure == "adjacent":
        m = np.eye(n_el) - np.roll(np.eye(n_el), 1, axis=1)
    else:
        raise ValueError(f"measure = {measure!r}: allowed values are 'ground', 'adjacent'")
    return Protocol(stim, m)
