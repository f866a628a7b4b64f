"""Kill the long jobs at random moments and resume them: nothing computed is lost, and the data
are the uninterrupted run's.

    python benchmarks/bench_faults.py [--kills 6] [--seed 0]   # writes results/faults.{md,json}

For `jointsim dataset` (60 samples of 10 presses, 2 workers, the test mesh) and `jointsim
palpate` (the paper's three targets pressed 1.5 mm, the test mesh, a 32-vertex membrane): one
uninterrupted run, then ``--kills`` runs each killed with SIGKILL (the whole process group:
driver and workers at once) at a moment drawn uniformly over the uninterrupted run's wall time,
then run again with the same command until it finishes. Per kill: when, what had been stored,
what the resume recomputed, and whether the finished data's SHA-256 is the uninterrupted one's.
"""

from __future__ import annotations

import argparse
import os
import platform
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from _machine import cpu_name, write_pair

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from jointsim.io.records import open_records  # noqa: E402

JOBS = {
    "dataset": (["dataset", "--mesh", "test", "--n", "60", "--seed", "5", "--workers", "2", "--no-progress"], "run.h5",
                "run.h5"),
    "palpate": (["palpate", "--mesh", "test", "--target-diameters-mm", "8,15,30", "--depth-mm", "1.5", "--hold-s", "0.1",
                 "--rim-vertices", "32", "--layers", "1", "--vtu-every", "0", "--no-progress"], "run", "run/palpation.h5"),
}


def _cmd(job: str, out: Path) -> list[str]:
    args, name, _ = JOBS[job]
    return [sys.executable, "-m", "jointsim", *args, "--out", str(out / name)]


def _stored(job: str, out: Path) -> int:
    """Records stored in the run in progress (files of whole groups or frames)."""
    partial = (out / JOBS[job][2]).with_suffix(".partial")
    return len(list((partial / "records").rglob("r*.npz"))) if partial.exists() else 0


def _run(cmd: list[str], env: dict) -> float:
    t0 = time.perf_counter()
    r = subprocess.run(cmd, env=env, cwd=ROOT, capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed: {r.stderr[-1500:]}")
    return time.perf_counter() - t0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--kills", type=int, default=6)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=ROOT / "results" / "faults")
    args = ap.parse_args()
    rng = np.random.default_rng(args.seed)
    work = Path(tempfile.mkdtemp(prefix="jointsim-faults-"))
    env = {**os.environ, "JOINTSIM_CACHE": str(work / "cache"),
           "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    rows, reference = [], {}
    try:
        for job in JOBS:
            ref = work / f"{job}-ref"
            wall = _run(_cmd(job, ref), env)
            reference[job] = {"wall_s": wall, "data_sha256": open_records(ref / JOBS[job][2], fields=[], verify=False).data_sha256}
            for k in range(args.kills):
                out = work / f"{job}-{k}"
                at = float(rng.uniform(0.05, 0.95) * wall)
                proc = subprocess.Popen(_cmd(job, out), env=env, cwd=ROOT, stdout=subprocess.DEVNULL,
                                        stderr=subprocess.DEVNULL, start_new_session=True)
                time.sleep(at)
                finished = proc.poll() is not None
                if not finished:
                    os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
                stored = _stored(job, out)
                resumed = _run(_cmd(job, out), env)
                rec = open_records(out / JOBS[job][2], fields=[], verify=True)
                rows.append({"job": job, "kill_at_s": at, "finished_before_kill": finished, "records_stored": stored,
                             "resume_s": resumed, "same_data": rec.data_sha256 == reference[job]["data_sha256"]})
                print(rows[-1], flush=True)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    result = {"machine": f"{platform.machine()}, {cpu_name()}", "kills": args.kills, "seed": args.seed,
              "reference": reference, "rows": rows}
    L = ["# Killed at random moments, resumed", "",
         f"`python benchmarks/bench_faults.py --kills {args.kills} --seed {args.seed}` on {result['machine']}. Each run "
         "killed with SIGKILL (driver and workers at once) at a moment drawn uniformly over 5–95 % of the uninterrupted "
         "run's wall time, then run again with the same command.", "",
         "| job | uninterrupted (s) | killed at (s) | records stored at the kill | resume (s) | data = uninterrupted |",
         "|---|---|---|---|---|---|"]
    for r in rows:
        ref = reference[r["job"]]
        L.append(f"| {r['job']} | {ref['wall_s']:.1f} | {r['kill_at_s']:.1f}{' (had finished)' if r['finished_before_kill'] else ''} "
                 f"| {r['records_stored']} | {r['resume_s']:.1f} | {'yes' if r['same_data'] else '**NO**'} |")
    n_same = sum(r["same_data"] for r in rows)
    L += ["", f"{n_same} of {len(rows)} resumed runs gave the uninterrupted run's data (data_sha256, every record "
          "read back against it)."]
    write_pair(args.out, result, "\n".join(L) + "\n")
    print("\n".join(L))
    return 0 if n_same == len(rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
