"""Figures: matplotlib set up once for writing files (every plot jointsim makes is a PNG)."""

from __future__ import annotations

from typing import Any

__all__ = ["pyplot"]


def pyplot() -> Any:
    """``matplotlib.pyplot`` on the non-interactive Agg backend: figures go to files, and no
    display is needed or touched (a headless machine, a worker process). Imported on first
    use: matplotlib takes a second to load, and most commands draw nothing."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt
