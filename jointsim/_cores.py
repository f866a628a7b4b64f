"""The cores this process may run on, and the pool of worker processes the long jobs share: the
default size of worker pools and kernel thread splits, and :func:`run_local`, which runs tasks
on spawned single-threaded processes. Kept apart from the modules that use it so that the
command line can show it without loading them."""

from __future__ import annotations

import concurrent.futures as cf
import ctypes
import multiprocessing
import os
import signal
import sys
from contextlib import contextmanager
from typing import Callable, Iterator, Sequence

__all__ = ["THREAD_VARIABLES", "available_cores", "run_local"]

THREAD_VARIABLES = ("MKL_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMEXPR_NUM_THREADS")


def available_cores() -> int:
    """Cores in this process's CPU affinity (all of the machine's where the platform has none)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # platforms without affinity
        return os.cpu_count() or 1


@contextmanager
def _single_threaded_children() -> Iterator[None]:
    """Processes started inside the block run their numerical libraries on one thread."""
    old = {k: os.environ.get(k) for k in THREAD_VARIABLES}
    os.environ.update({k: "1" for k in THREAD_VARIABLES})
    try:
        yield
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def _die_with(parent: int) -> None:
    """A local worker's initializer: the kernel kills this process when its parent dies (Linux's
    PR_SET_PDEATHSIG), so a driver killed with SIGKILL leaves no worker writing on; where that
    is not available, a worker outlives a killed driver by the task it is computing at most
    (the pool's own management then ends it)."""
    if sys.platform.startswith("linux"):
        try:
            ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # 1: PR_SET_PDEATHSIG
        except (OSError, AttributeError):
            pass
    if os.getppid() != parent:  # the parent died before the line above ran
        os._exit(1)


def run_local(tasks: Sequence[tuple], workers: int, tick: Callable, task: Callable) -> None:
    """``task(*t)`` for each of ``tasks`` on ``workers`` spawned processes (not forked: Warp, MKL
    and MuJoCo hold threads and handles a fork would copy), each running its numerical libraries
    on one thread; ``tick`` is given each result as it comes. A worker that dies ends the run
    with a ChildProcessError saying that what was stored is kept."""
    ctx = multiprocessing.get_context("spawn")
    with _single_threaded_children():
        pool = cf.ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=_die_with, initargs=(os.getpid(),))
        futures: list[cf.Future] = []
        try:
            futures = [pool.submit(task, *t) for t in tasks]
            for f in cf.as_completed(futures):
                tick(f.result())
        except cf.BrokenExecutor:  # a worker process died (BrokenProcessPool)
            for f in futures:
                f.cancel()
            raise ChildProcessError("a worker process died (killed, or out of memory) while computing a press; nothing "
                                    "stored is lost: run the same command again to resume") from None
        except BaseException:
            for f in futures:
                f.cancel()
            raise
        finally:
            pool.shutdown(wait=True, cancel_futures=True)
