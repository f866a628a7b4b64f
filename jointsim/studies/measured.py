"""Measured frames through the instrument (``jointsim frames``): frames from a real sensor, or
from another simulator, imaged as the scene's instrument images its own.

δV is each frame minus the mean of the reference frames (the untouched sensor, as the paper's
steady-state reference), checked first against the scene's protocol
(:func:`~jointsim.io.frames.check_patterns`); the image is the scene's reconstruction (its
Jacobian on the nominal inflated chamber, λ by its [reconstruction] rule) with the paper's
metrics. A calibration map is applied to the result by the caller
(:func:`jointsim.calibration.apply.calibrate_measured`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..eit.protocol import scene_protocol
from ..instrument import Instrument
from ..io.frames import MeasuredFrames, check_patterns
from ..metrics import metric_fields
from ..scene import Scene

__all__ = ["MeasuredImages", "check_frames", "image_frames", "reference_snr_db"]


@dataclass(frozen=True)
class MeasuredImages:
    """Per frame (n rows): ``voltages`` and ``dv`` (n, n_meas) V, the ``images`` (n, n_cells)
    S/m on the scene's voxel grid, and their metrics ``com`` (n, 3) m, ``sum_sigma``,
    ``diameter`` m, ``extent_xy`` m, ``cluster_cells`` (n,) (NaN and 0 for an all-zero
    image); ``reference`` (n_meas,) V the mean reference frame."""

    voltages: np.ndarray
    dv: np.ndarray
    reference: np.ndarray
    images: np.ndarray
    com: np.ndarray
    sum_sigma: np.ndarray
    diameter: np.ndarray
    extent_xy: np.ndarray
    cluster_cells: np.ndarray


def check_frames(scene: Scene, *frames: MeasuredFrames) -> None:
    """Refuse (ValueError naming the file) frames that do not match ``scene``'s protocol: what
    a caller checks before it builds the instrument."""
    proto = scene_protocol(scene)
    for f in frames:
        check_patterns(f, proto.stim, proto.meas, proto.n_meas)


def reference_snr_db(reference: np.ndarray) -> float | None:
    """The instrument's SNR in the paper's convention, 20 log10(mean |V̄| / σ), from the scatter
    of the untouched sensor's frames ``reference`` (r, n_meas) V about their mean V̄ (σ² the
    channels' mean unbiased variance); None from fewer than two frames, or frames that scatter
    by round-off only (past 200 dB: copies of one frame)."""
    if len(reference) < 2:
        return None
    level = float(np.mean(np.abs(reference.mean(axis=0))))
    sd = float(np.sqrt(np.mean(np.var(reference, axis=0, ddof=1))))
    return 20.0 * float(np.log10(level / sd)) if sd > 1e-10 * level else None


def image_frames(scene: Scene, frames: MeasuredFrames, reference: MeasuredFrames,
                 instrument: Instrument | None = None, progress: Callable[[int], None] | None = None) -> MeasuredImages:
    """Image ``frames`` against the mean of ``reference``'s with ``scene``'s instrument
    (built here unless given; ``progress(1)`` after each frame); a ValueError naming the file
    when either does not match the scene's protocol."""
    check_frames(scene, frames, reference)
    inst = Instrument.build(scene) if instrument is None else instrument
    try:
        v_ref = reference.voltages.mean(axis=0)
        dv = frames.voltages - v_ref
        images, fields = [], []
        for d in dv:
            image, _, metrics = inst.imager.image(d)
            images.append(image)
            fields.append(metric_fields(metrics))
            if progress is not None:
                progress(1)
    finally:
        if instrument is None:
            inst.free()
    col = {k: np.array([f[k] for f in fields]) for k in fields[0]}
    return MeasuredImages(frames.voltages, dv, v_ref, np.array(images), col["com"], col["sum_sigma"], col["diameter"],
                          col["extent_xy"], col["cluster_cells"])
