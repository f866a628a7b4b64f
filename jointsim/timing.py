"""Wall-clock timing of named stages: the one timer of the package (a frame's stages, a run's
set-up, the command line's progress lines all add into a ``{stage: seconds}`` dict with it)."""

from __future__ import annotations

import time
from contextlib import contextmanager
from typing import Iterator

__all__ = ["timed"]


@contextmanager
def timed(timings: dict[str, float], name: str) -> Iterator[None]:
    """Add the wall time of the ``with`` block to ``timings[name]`` (s), also when it raises,
    so a stage entered twice in a frame (a remesh's two solves) is counted once in total."""
    t0 = time.perf_counter()
    try:
        yield
    finally:
        timings[name] = timings.get(name, 0.0) + time.perf_counter() - t0
