"""Warp as the package imports it: one place for its process-wide settings and start-up, and
numpy arrays seen by CPU kernels without a copy."""

import logging
import os
import sys
import tempfile

import numpy as np
import warp as wp

# Warp's start-up banner and per-module load lines are noise on a command line
wp.config.log_level = max(getattr(wp.config, "log_level", logging.WARNING), logging.WARNING)

__all__ = ["wp", "on_host"]

# printed by Warp's native library on every machine without an NVIDIA driver, which is where
# jointsim mostly runs (its kernels run on the CPU); asking for a CUDA device there still gets
# a clear error (mechanics.fem.warp_device)
_NO_DRIVER = "Could not find or load the NVIDIA CUDA driver"


def _init() -> None:
    """``wp.init()`` with its native stderr read back and passed on without the no-driver line."""
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError):  # no usable fd 2 (an embedded interpreter): let it print
        wp.init()
        return
    with tempfile.TemporaryFile() as tmp:
        os.dup2(tmp.fileno(), 2)
        try:
            wp.init()
        finally:  # passed on even when the start-up fails: its own words say why
            os.dup2(saved, 2)
            os.close(saved)
            tmp.seek(0)
            text = tmp.read().decode(errors="replace")
            sys.stderr.write("".join(line for line in text.splitlines(keepends=True) if _NO_DRIVER not in line))


_init()


def on_host(a: np.ndarray, dtype=wp.float64) -> wp.array:
    """A Warp CPU array over the memory of ``a`` (C-contiguous, of ``dtype``'s scalar type): a
    kernel's writes land in ``a``, which must outlive the launch."""
    return wp.array(a, dtype=dtype, device="cpu", copy=False)
