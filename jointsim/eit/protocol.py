"""Injection and measurement protocols as plain arrays with EIDORS meaning.

``stim[s]`` is EIDORS's ``stimulation(s).stim_pattern``: the current (A) into each electrode
for injection s (positive into the saline). ``meas[s]`` is ``stimulation(s).meas_pattern``:
each row weights the electrode voltages into one measurement. Voltages are referenced to the
grounded electrode, so "electrode l against ground" is the unit row e_l.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..scene import Scene

__all__ = ["Protocol", "RingSymmetry", "ring_symmetries", "invariant", "skip_protocol", "skip_pairs", "scene_protocol", "CHANNEL_ORDER"]

# how a frame's voltages are laid out, as stores record it beside the patterns
CHANNEL_ORDER = "voltages[s * n_meas_per_stim + m] = measurement m of injection s (injection-major; EIDORS meas_pattern rows)"


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

    def to_record(self) -> dict:
        """The patterns as a store records them (JSON-ready): ``stim_A`` (n_stim, n_el),
        ``meas`` (n_stim, n_meas_per_stim, n_el), the electrodes they span (the driven ones,
        in the layout's order; the reference's column is left out) and the channel order."""
        return {"stim_A": self.stim.tolist(), "meas": self.meas.tolist(), "electrodes": "driven, in the layout's order",
                "channels": CHANNEL_ORDER}

    def floating(self) -> "Protocol":
        """This protocol's patterns, which span every electrode of a layout with no passive
        reference, on the driven electrodes of the forward model, whose reference (potential 0,
        taking the rest of each injection's current) is the last electrode: its column
        dropped. Exact when every injection's currents and every measurement's weights sum to
        zero (then neither depends on which electrode the solver grounds); else a ValueError."""
        scale = max(np.abs(self.stim).max(), 1e-300)
        if np.abs(self.stim.sum(axis=1)).max() > 1e-12 * scale:
            raise ValueError("a floating reference: every injection's currents must sum to zero")
        if np.abs(self.meas.sum(axis=2)).max() > 1e-12 * max(np.abs(self.meas).max(), 1e-300):
            raise ValueError("a floating reference: every measurement's weights must sum to zero (differential)")
        return Protocol(self.stim[:, :-1], self.meas[:, :, :-1])


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


def scene_protocol(scene: Scene, skip: int | None = None) -> Protocol:
    """The protocol of ``scene``'s [drive] on its [electrodes]: its patterns given as data, or
    skip-N (``skip`` overriding its N, and any patterns) over the driven electrodes against the
    reference, or adjacent pairs; where the reference floats, patterns over every electrode
    reduced by :meth:`Protocol.floating`."""
    e, d = scene.electrodes, scene.drive
    if d.stim is not None and skip is None:  # a protocol given as data
        p = Protocol(np.array(d.stim), np.array(d.meas))
        return p if e.reference else p.floating()
    skip = d.skip if skip is None else skip
    if e.reference:
        return skip_protocol(e.count, skip, d.current, "ground" if d.measure == "reference" else "adjacent")
    return skip_protocol(e.count + 1, skip, d.current, "adjacent").floating()


@dataclass(frozen=True, eq=False)
class RingSymmetry:
    """A symmetry of the electrode ring that maps a protocol onto itself: the press turned by
    ``turn`` electrode pitches anticlockwise about the ring's centre, after a mirror in the line
    through electrode 0 when ``mirror``. The frame of the moved press is
    ``sign * frame[source]`` (:meth:`frames`), its position ``matrix @ xy`` (:meth:`positions`);
    exact for an axisymmetric chamber, up to the mesh's asymmetry for a real one."""

    turn: int
    mirror: bool
    source: np.ndarray  # (n_meas,) measurement of the original frame each one reads
    sign: np.ndarray  # (n_meas,) ±1: a reversed injection or measurement pair
    matrix: np.ndarray  # (2, 2) the move of a point in the base plane

    def frames(self, v: np.ndarray) -> np.ndarray:
        """Frames (..., n_meas) of the presses moved by this symmetry."""
        return self.sign * np.asarray(v)[..., self.source]

    def positions(self, xy: np.ndarray) -> np.ndarray:
        """Points (..., 2) moved by this symmetry."""
        return np.asarray(xy) @ self.matrix.T


def _match(patterns: np.ndarray, target: np.ndarray) -> tuple[int, float] | None:
    """Index and sign (±1) of the row of ``patterns`` equal to ± ``target``, or None."""
    for sgn in (1.0, -1.0):
        hit = np.flatnonzero(np.all(np.abs(patterns - sgn * target) <= 1e-12 * np.abs(target).max(), axis=1))
        if len(hit):
            return int(hit[0]), sgn
    return None


def ring_symmetries(protocol: Protocol, first_angle_deg: float = 0.0) -> list[RingSymmetry]:
    """The symmetries of a ring of ``protocol.n_el`` equally spaced electrodes (electrode k at
    ``first_angle_deg`` + 360°·k/n, anticlockwise) under which ``protocol`` is invariant, the
    identity first: all 2n of the dihedral group for a skip protocol.

    Moving the press by a symmetry g moves its potentials with it, so the moved frame's
    injection s' equals the original injection whose currents are those of s' read through g
    (electrode e takes the current of electrode g(e)), and its measurement the original one
    with weights read the same way; a pair that comes back reversed flips the sign."""
    n = protocol.n_el
    e = np.arange(n)
    out = []
    for mirror in (False, True):
        for turn in range(n):
            read = _read_through(protocol, ((-e if mirror else e) + turn) % n)
            if read is None:
                continue
            a = 2 * np.pi * turn / n
            rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
            if mirror:
                b = 2 * np.deg2rad(first_angle_deg)
                rot = rot @ np.array([[np.cos(b), np.sin(b)], [np.sin(b), -np.cos(b)]])
            out.append(RingSymmetry(turn, mirror, *read, rot))
    return out


def invariant(protocol: Protocol, image: np.ndarray) -> bool:
    """Whether the electrode map ``image`` (electrode e to ``image[e]``, a permutation of the
    protocol's electrodes) maps ``protocol``'s injections and measurements onto themselves,
    each up to its sign: then a frame moved by it is a permutation of a frame's channels, with
    signs."""
    return _read_through(protocol, np.asarray(image, int)) is not None


def _read_through(protocol: Protocol, image: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """(source, sign) (n_meas,) of the frame moved by the electrode map ``image`` (electrode e
    moves to ``image[e]``), or None where the protocol has no injection or measurement that
    the map's reading of one matches."""
    per_stim = protocol.meas.shape[1]
    source, sign = np.empty(protocol.n_meas, int), np.empty(protocol.n_meas)
    for s1 in range(protocol.n_stim):
        hit = _match(protocol.stim, protocol.stim[s1][image])
        if hit is None:
            return None
        s0, ts = hit
        for m1 in range(per_stim):
            mh = _match(protocol.meas[s0], protocol.meas[s1, m1][image])
            if mh is None:
                return None
            source[s1 * per_stim + m1], sign[s1 * per_stim + m1] = s0 * per_stim + mh[0], ts * mh[1]
    return source, sign
