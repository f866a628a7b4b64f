"""The cores this process may run on: the default size of worker pools and kernel thread splits.
Kept apart from the modules that use it so that the command line can show it without loading them."""

from __future__ import annotations

import os


def available_cores() -> int:
    """Cores in this process's CPU affinity (all of the machine's where the platform has none)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # platforms without affinity
        return os.cpu_count() or 1
