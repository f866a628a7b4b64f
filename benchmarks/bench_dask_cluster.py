"""A dataset on a Dask cluster of separate processes, started as a user starts one: samples per
hour with 1, 2 and 4 workers, the efficiency, the same data whatever the count, and a worker
killed in the middle of a run.

    python benchmarks/bench_dask_cluster.py      # ~5 min here; writes results/dask_cluster.{md,json}

Each configuration: `dask scheduler --scheduler-file F` and N × `dask worker --scheduler-file F
--nthreads 1` (each worker its own process under its nanny, one numerical thread), then
`jointsim dataset --scheduler ADDRESS` timed from its start to its end (connecting, the
workers' set-up on their first group, every group, the store's finalisation). The chamber is
meshed before the first run, so no run pays for it. The kill: with 2 workers, once the first
group is stored, one worker's process group (nanny and worker: a machine lost) is killed with
SIGKILL; the scheduler gives its groups to the other, and the store must end with the data of
the 1-worker run (data_sha256 over every field but the timings).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _machine import machine, run_and_write

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
WORKERS = (1, 2, 4)
SAMPLES = 72  # 12 presses of 6
ARGS = ["--mesh", "dataset", "--seed", "0", "--no-progress"]


def _env(cache: Path) -> dict:
    threads = {v: "1" for v in ("MKL_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS")}
    return {**os.environ, **threads, "JOINTSIM_CACHE": str(cache), "PYTHONPATH": str(ROOT)}


class Cluster:
    """A scheduler and ``n`` workers, each in a process group of its own."""

    def __init__(self, n: int, folder: Path, env: dict):
        self.file = folder / f"scheduler-{n}.json"
        self.env = env
        self.scheduler = self._start(["scheduler", "--scheduler-file", str(self.file), "--no-dashboard", "--port", "0"])
        deadline = time.time() + 60
        while not self.file.exists():
            if time.time() > deadline:
                raise RuntimeError("the scheduler did not start in 60 s")
            time.sleep(0.2)
        self.workers = [self._start(["worker", "--scheduler-file", str(self.file), "--nthreads", "1", "--no-dashboard",
                                     "--name", f"w{i}"]) for i in range(n)]
        from distributed import Client

        with Client(scheduler_file=str(self.file), timeout=60) as c:
            c.wait_for_workers(n, timeout=120)
        self.address = json.loads(self.file.read_text())["address"]

    def _start(self, args: list[str]) -> subprocess.Popen:
        return subprocess.Popen([sys.executable, "-m", "dask", *args], env=self.env, cwd=ROOT, stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL, start_new_session=True)

    def kill_worker(self, i: int) -> None:
        os.killpg(self.workers[i].pid, signal.SIGKILL)

    def close(self) -> None:
        for p in self.workers + [self.scheduler]:
            try:
                os.killpg(p.pid, signal.SIGTERM)
            except ProcessLookupError:
                pass
        for p in self.workers + [self.scheduler]:
            try:
                p.wait(timeout=30)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)


def _dataset(address: str, out: Path, env: dict) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "jointsim", "dataset", "--n", str(SAMPLES), *ARGS, "--scheduler", address,
                             "--out", str(out)], env=env, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _finished(proc: subprocess.Popen, what: str) -> None:
    _, err = proc.communicate()
    if proc.returncode != 0:
        raise RuntimeError(f"{what} failed (rc {proc.returncode}): {err[-1500:]}")


def run() -> dict:
    from jointsim.io.records import open_records

    folder = Path(tempfile.mkdtemp(prefix="jointsim-bench-dask-"))
    env = _env(folder / "mesh-cache")
    subprocess.run([sys.executable, "-m", "jointsim", "mesh", "--mesh", "dataset"], env=env, cwd=ROOT, check=True,
                   capture_output=True)
    rows = []
    for n in WORKERS:
        cluster = Cluster(n, folder, env)
        try:
            out = folder / f"w{n}.h5"
            t = time.perf_counter()
            _finished(_dataset(cluster.address, out, env), f"{n} workers")
            wall = time.perf_counter() - t
        finally:
            cluster.close()
        sha = open_records(out, fields=[], verify=True).data_sha256
        rows.append({"workers": n, "samples": SAMPLES, "wall_s": wall, "samples_per_hour": 3600 * SAMPLES / wall,
                     "data_sha256": sha})
        print(rows[-1], flush=True)
    base = rows[0]["samples_per_hour"]
    for r in rows:
        r["efficiency"] = r["samples_per_hour"] / (r["workers"] * base)
        r["same_data"] = r["data_sha256"] == rows[0]["data_sha256"]

    cluster = Cluster(2, folder, env)
    try:
        out = folder / "killed.h5"
        proc = _dataset(cluster.address, out, env)
        partial = out.with_suffix(".partial") / "records"
        t = time.perf_counter()
        while not (partial.exists() and any(partial.rglob("r*.npz"))):
            if proc.poll() is not None or time.perf_counter() - t > 300:
                raise RuntimeError("the run ended or stalled before its first group was stored")
            time.sleep(0.1)
        stored = len(list(partial.rglob("r*.npz")))
        cluster.kill_worker(1)
        killed_at = time.perf_counter() - t
        _finished(proc, "the run with a killed worker")
        wall = time.perf_counter() - t
    finally:
        cluster.close()
    sha = open_records(out, fields=[], verify=True).data_sha256
    kill = {"workers": 2, "killed_after_s": killed_at, "groups_stored_before": stored, "wall_s": wall, "data_sha256": sha,
            "same_data": sha == rows[0]["data_sha256"]}
    print(kill, flush=True)
    return {"machine": machine(), "cores": os.cpu_count(), "samples": SAMPLES, "args": ARGS, "rows": rows, "kill": kill}


def markdown(r: dict) -> str:
    lines = ["# A dataset on a Dask cluster of separate processes", "",
             "Command: `python benchmarks/bench_dask_cluster.py`  ", f"Machine: {r['machine']}.", "",
             __doc__.split("\n\n", 2)[2].strip().replace("\n", " "), "",
             f"`jointsim dataset --n {r['samples']} {' '.join(r['args'])} --scheduler ADDRESS`:", "",
             "| workers | wall s | samples/h | efficiency | data_sha256 | same data as 1 worker |", "|---:|---:|---:|---:|---|---|"]
    for x in r["rows"]:
        lines.append(f"| {x['workers']} | {x['wall_s']:.1f} | {x['samples_per_hour']:.0f} | {100 * x['efficiency']:.0f} % | "
                     f"`{x['data_sha256'][:16]}…` | {'yes' if x['same_data'] else 'NO'} |")
    k = r["kill"]
    lines += ["", f"A worker killed (SIGKILL of its nanny and process) {k['killed_after_s']:.1f} s into a 2-worker run, "
              f"{k['groups_stored_before']} group(s) stored by then: the run finished in {k['wall_s']:.1f} s on the other "
              f"worker, data_sha256 `{k['data_sha256'][:16]}…`: {'the 1-worker run' + chr(39) + 's data' if k['same_data'] else 'NOT the 1-worker data'}.",
              "", f"This machine has {r['cores']} cores: past {r['cores']} workers the processes share them, so the "
              "4-worker row measures the scheduler's overhead under oversubscription, not scaling."]
    return "\n".join(lines) + "\n"


def main() -> None:
    run_and_write(__doc__, ROOT / "results" / "dask_cluster", run, markdown)


if __name__ == "__main__":
    main()
