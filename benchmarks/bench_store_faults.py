"""The dataset store under faults of the output side: a real file system filled up (while the
records are written, and at the final file), two writers on one output, a damaged record file,
each followed by what a user would do next; what each run ended in, and what was lost.

    python benchmarks/bench_store_faults.py     # ~3 min here; writes results/store_faults.{md,json}

The run: `jointsim dataset --mesh test --n 24 --seed 3 --workers 2`. A full disk is a tmpfs of a
chosen size mounted for the run (root only: without it those cases are reported as not run),
grown afterwards (`mount -o remount,size=…`, as a user frees space) and the same command run
again. "Clear" means exit code 2 and one line on stderr naming the path, no traceback; "same
data" that the store finally read back (every record, verified) has the data_sha256 of an
uninterrupted run.
"""

from __future__ import annotations

import argparse
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _machine import cpu_name, write_pair

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from jointsim.io.records import open_records  # noqa: E402

ARGS = ["dataset", "--mesh", "test", "--n", "24", "--seed", "3", "--workers", "2", "--no-progress"]


def _cmd(out: Path) -> list[str]:
    return [sys.executable, "-m", "jointsim", *ARGS, "--out", str(out)]


def _run(out: Path, env: dict) -> subprocess.CompletedProcess:
    return subprocess.run(_cmd(out), env=env, cwd=ROOT, capture_output=True, text=True)


def _clear(p: subprocess.CompletedProcess) -> bool:
    lines = [x for x in p.stderr.strip().splitlines() if x.strip() and "Warning" not in x and not x.startswith("  ")]
    return p.returncode == 2 and "Traceback" not in p.stderr and len(lines) == 1


def _error(p: subprocess.CompletedProcess) -> str:
    lines = [x for x in p.stderr.strip().splitlines() if x.strip()]
    return lines[-1][:300] if lines else ""


def _sha(path: Path) -> str | None:
    try:
        return open_records(path, fields=[], verify=True).data_sha256
    except Exception:  # noqa: BLE001 - a store that cannot be read back is what the row reports
        return None


def _du(path: Path) -> int:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file())


class Tmpfs:
    """A tmpfs mounted at a new folder, ``size`` bytes; ``grow`` remounts it larger."""

    def __init__(self, size: int):
        self.path = Path(tempfile.mkdtemp(prefix="jointsim-small-fs-"))
        try:
            r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(self.path)], capture_output=True, text=True)
        except OSError as e:  # no mount command
            raise PermissionError(str(e)) from None
        if r.returncode != 0:
            shutil.rmtree(self.path, ignore_errors=True)
            raise PermissionError(r.stderr.strip() or "mount failed")

    def grow(self, size: int) -> None:
        subprocess.run(["mount", "-o", f"remount,size={size}", str(self.path)], check=True)

    def close(self) -> None:
        subprocess.run(["umount", str(self.path)], capture_output=True)
        shutil.rmtree(self.path, ignore_errors=True)


def run() -> dict:
    work = Path(tempfile.mkdtemp(prefix="jointsim-store-faults-"))
    env = {**os.environ, "JOINTSIM_CACHE": str(work / "cache"), "PYTHONPATH": str(ROOT)}
    rows = []
    try:
        ref = work / "ref.h5"
        t = time.perf_counter()
        log = open(work / "ref.log", "w+")  # not a pipe: nobody reads it while the run goes on
        proc = subprocess.Popen(_cmd(ref), env=env, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=log, text=True)
        records_size = chamber_size = 0  # the run's folder at its largest, and its chamber, watched while it runs
        while proc.poll() is None:
            if ref.with_suffix(".partial").exists():
                try:
                    records_size = max(records_size, _du(ref.with_suffix(".partial")))
                    chamber_size = max(chamber_size, (ref.with_suffix(".partial") / "chamber.npz").stat().st_size)
                except FileNotFoundError:  # not written yet, or removed as the run finalised
                    pass
            time.sleep(0.02)
        log.seek(0)
        if proc.returncode != 0:
            raise RuntimeError(log.read()[-1500:])
        log.close()
        wall = time.perf_counter() - t
        reference = _sha(ref)
        final_size = ref.stat().st_size

        # room for half the run's chamber mesh; for it and a third of the records; for all of
        # them and half the final file
        for case, size in (("disk full while the run's chamber mesh is written", chamber_size // 2),
                           ("disk full while the records are written", chamber_size + (records_size - chamber_size) // 3),
                           ("disk full at the final file", records_size + final_size // 2)):
            try:
                fs = Tmpfs(size)
            except PermissionError as e:
                rows.append({"case": case, "ran": False, "why": f"cannot mount a tmpfs here ({e})"})
                continue
            try:
                out = fs.path / "run.h5"
                first = _run(out, env)
                fs.grow(256 * 2**20)
                second = _run(out, env)
                rows.append({"case": case, "ran": True, "fs_bytes": size, "first_rc": first.returncode, "clear": _clear(first),
                             "message": _error(first), "then": "the file system grown, the same command run again",
                             "second_rc": second.returncode, "same_data": _sha(out) == reference})
            finally:
                fs.close()
            print(rows[-1], flush=True)

        out = work / "two.h5"
        a = subprocess.Popen(_cmd(out), env=env, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        deadline = time.time() + 120
        while not out.with_suffix(".partial").exists() and time.time() < deadline and a.poll() is None:
            time.sleep(0.1)
        b = _run(out, env)
        a.communicate()
        rows.append({"case": "a second writer on the same output", "ran": True, "first_rc": b.returncode, "clear": _clear(b),
                     "message": _error(b), "then": "the first run left alone to finish", "second_rc": a.returncode,
                     "same_data": _sha(out) == reference})
        print(rows[-1], flush=True)

        out = work / "damaged.h5"
        half = subprocess.Popen(_cmd(out), env=env, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                start_new_session=True)
        deadline = time.time() + 120
        files: list[Path] = []
        while time.time() < deadline and half.poll() is None:
            files = sorted(out.with_suffix(".partial").rglob("r*.npz")) if out.with_suffix(".partial").exists() else []
            if files:
                break
            time.sleep(0.05)
        os.killpg(half.pid, 9) if half.poll() is None else None
        half.wait()
        if files:
            data = bytearray(files[0].read_bytes())
            for k in range(4):  # four bytes in the middle of the file
                data[len(data) // 2 + k] ^= 0xFF
            files[0].write_bytes(bytes(data))
        first = _run(out, env)
        second = _run(out, env) if first.returncode != 0 else first
        rows.append({"case": "a record file damaged (4 bytes) while the run was stopped", "ran": bool(files),
                     "first_rc": first.returncode, "clear": _clear(first) or first.returncode == 0, "message": _error(first),
                     "then": "the same command run again", "second_rc": second.returncode, "same_data": _sha(out) == reference})
        print(rows[-1], flush=True)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return {"machine": f"{platform.machine()}, {cpu_name()}", "uninterrupted_s": wall, "reference": reference,
            "chamber_bytes": chamber_size, "records_bytes": records_size, "final_bytes": final_size, "rows": rows}


def markdown(r: dict) -> str:
    L = ["# The dataset store under output-side faults", "",
         f"`python benchmarks/bench_store_faults.py` on {r['machine']}.", "",
         __doc__.split("\n\n", 2)[2].strip().replace("\n", " "), "",
         f"The uninterrupted run: {r['uninterrupted_s']:.1f} s, data_sha256 `{(r['reference'] or '')[:16]}…`.", "",
         "| fault | first run: exit code | clear one-line error | its message | then | exit code | data = uninterrupted |",
         "|---|---:|---|---|---|---:|---|"]
    for x in r["rows"]:
        if not x["ran"]:
            L.append(f"| {x['case']} | not run: {x.get('why', '')} | | | | | |")
            continue
        msg = x["message"].replace("|", "\\|")
        L.append(f"| {x['case']} | {x['first_rc']} | {'yes' if x['clear'] else '**no**'} | {msg} | {x['then']} | "
                 f"{x['second_rc']} | {'yes' if x['same_data'] else '**NO**'} |")
    return "\n".join(L) + "\n"


def main() -> None:
    argparse.ArgumentParser(description=__doc__.split("\n\n")[0]).parse_args()
    r = run()
    write_pair(ROOT / "results" / "store_faults", r, markdown(r))
    print(markdown(r))


if __name__ == "__main__":
    main()
