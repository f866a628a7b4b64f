"""What the benchmarks say about the machine they ran on, and how they write their results."""

from __future__ import annotations

import json
import os
import platform
from pathlib import Path


def cpu_name() -> str:
    """The CPU model from /proc/cpuinfo (Linux), else what the platform module knows."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown CPU"


def machine() -> str:
    """This machine in one line: architecture, CPU, cores, Python."""
    return f"{platform.machine()} {cpu_name()}, {os.cpu_count()} cores, Python {platform.python_version()}"


def cpu_counters() -> list[int] | None:
    """The machine's CPU time counters since boot (/proc/stat's "cpu" line: user, nice, system,
    idle, iowait, irq, softirq, steal, …), None where there is no /proc/stat."""
    try:
        return [int(x) for x in Path("/proc/stat").read_text().splitlines()[0].split()[1:]]
    except (OSError, ValueError, IndexError):
        return None


def steal_share(start: list[int] | None, end: list[int] | None) -> float | None:
    """The share of the CPU time between two :func:`cpu_counters` readings that the hypervisor
    gave to other guests (steal). On this shared virtual machine it is why a run is slow: a
    half of it stolen doubles a benchmark's times. None without both readings."""
    if not start or not end or len(start) < 8 or len(end) < 8:
        return None
    d = [b - a for a, b in zip(start, end)]
    return d[7] / sum(d) if sum(d) > 0 else None


def speed_reference(repeats: int = 3) -> float:
    """Seconds (best of ``repeats``) of a fixed workload like the benchmarks' hot path: the
    sparse LDLᵀ factorisation and one solve of a 3-D 7-point Laplacian on a 32³ grid (32 768
    unknowns), with PARDISO where the project has it. The 2 cores of this machine are shared with
    other virtual machines, and its speed varies from day to day by up to ~1.5×: a benchmark
    that records this figure beside its own can be compared with a run of another day by
    the ratio of the two."""
    import time

    import numpy as np
    import scipy.sparse as sp

    import jointsim.linalg as solver

    n = 32
    d1 = sp.diags([-np.ones(n - 1), 2 * np.ones(n), -np.ones(n - 1)], [-1, 0, 1])
    eye = sp.identity(n)
    A = (sp.kron(sp.kron(d1, eye), eye) + sp.kron(sp.kron(eye, d1), eye) + sp.kron(sp.kron(eye, eye), d1)).tocsr()
    b = np.ones(A.shape[0])
    best = np.inf
    # the classic one-level factorisation, as before PARDISO_TWO_LEVEL: the workload stays the same
    two_level, solver.PARDISO_TWO_LEVEL = solver.PARDISO_TWO_LEVEL, False
    try:
        for _ in range(repeats):
            t0 = time.perf_counter()
            with solver.factorize(A, solver.default_backend()) as solve:
                solve(b)
            best = min(best, time.perf_counter() - t0)
    finally:
        solver.PARDISO_TWO_LEVEL = two_level
    return best


def atomic_write(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` through a temporary name: never a half-written result."""
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def write_pair(stem: Path, data: dict, markdown: str) -> None:
    """``stem``.json (``data``) and ``stem``.md (``markdown``), each written atomically."""
    stem.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(stem.with_suffix(".json"), json.dumps(data, indent=2))
    atomic_write(stem.with_suffix(".md"), markdown)


def median_seconds(fn, repeats: int) -> float:
    """The median wall time s of ``repeats`` calls of ``fn()``."""
    import statistics
    import time

    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def run_and_write(doc: str, stem: Path, run, markdown) -> None:
    """A benchmark's main without options (``--help`` shows the first paragraph of its ``doc``):
    ``run()``'s results written to ``stem``.json and, through ``markdown``, ``stem``.md."""
    import argparse

    argparse.ArgumentParser(description=doc.split("\n\n")[0]).parse_args()
    r = run()
    write_pair(stem, r, markdown(r))
