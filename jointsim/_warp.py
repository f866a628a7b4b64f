"""Warp as the package imports it: one place for its process-wide settings, and numpy arrays
seen by CPU kernels without a copy."""

import logging

import numpy as np
import warp as wp

# Warp's start-up banner and per-module load lines are noise on a command line
wp.config.log_level = max(getattr(wp.config, "log_level", logging.WARNING), logging.WARNING)

__all__ = ["wp", "on_host"]


def on_host(a: np.ndarray, dtype=wp.float64) -> wp.array:
    """A Warp CPU array over the memory of ``a`` (C-contiguous, of ``dtype``'s scalar type): a
    kernel's writes land in ``a``, which must outlive the launch."""
    return wp.array(a, dtype=dtype, device="cpu", copy=False)
