"""Bad input and faults, as a careful user meets them: each run as a command line (`python -m
jointsim ...`, the test mesh) and classed as the independent check classed them — A: a clear
one-line error naming the flag, key or path (exit 2) before any long work; B: an error, but vague
(the name missing) or late (after 20 s); C: a traceback; D: silently run (exit 0). Where a case
touches a store that holds data, the store's bytes are compared before and after: what was lost.

    python benchmarks/bench_bad_inputs.py      # ~3 min here; writes results/bad_inputs.{md,json}

The cases are those the check listed (output faults, stores, silent acceptance, late or
misleading errors); the suite has a test per class and fuzzes scene files and flags
(tests/test_fuzz.py, tests/test_flag_fuzz.py); kills and full disks are results/faults.md and
results/store_faults.md.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _machine import machine, run_and_write

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from jointsim.io.records import open_records  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
LATE_S = 20.0
SMALL = ["--mesh", "test", "--no-progress"]


def _run(argv: list[str], cwd: Path, env: dict | None = None, timeout: float = 600) -> tuple[int, str, float]:
    t = time.perf_counter()
    p = subprocess.run([sys.executable, "-m", "jointsim", *argv], cwd=cwd, capture_output=True, text=True, timeout=timeout,
                       env={**os.environ, "PYTHONPATH": str(ROOT), **(env or {})})
    return p.returncode, p.stderr, time.perf_counter() - t


def _digest(path: Path) -> str | None:
    return hashlib.sha256(path.read_bytes()).hexdigest() if path.is_file() else None


def cases(w: Path) -> list[dict]:
    """(what, argv, the name the error must give, the store to keep intact, extra env)."""
    (w / "a_folder").mkdir()
    (w / "text.txt").write_text("not a store\n")
    (w / "empty.toml").write_text("")
    (w / "no_electrodes.toml").write_text("[chamber]\nbase_radius_mm = 20.0\n")
    (w / "deep.toml").write_text('extends = "paper_sensor"\n[palpation]\ndepth_mm = 11.5\n')
    (w / "suction.toml").write_text('extends = "paper_sensor"\n[membrane]\nreservoir_pressure_pa = -10000.0\nrim_vertices = 32\n')
    (w / "ring.toml").write_text('extends = "paper_sensor"\n[electrodes]\nring_radius_mm = 18.95\n')
    (w / "binary.toml").write_bytes(bytes(range(256)))
    (w / "utf16.toml").write_bytes('extends = "paper_sensor"\n'.encode("utf-16"))
    (w / "carriers.toml").write_text('extends = "paper_sensor"\n[drive]\nfrequencies_hz = []\n')
    small_ds = ["dataset", "--n", "3", "--seed", "1", *SMALL]
    # stores that hold data: a finished dataset, a palpation, and copies damaged two ways
    code, err, _ = _run([*small_ds, "--out", str(w / "done.h5")], w)
    assert code == 0, err[-2000:]
    code, err, _ = _run(["palpate", *SMALL, "--target-diameters-mm", "15", "--depth-mm", "0.5", "--hold-s", "0",
                         "--rim-vertices", "32", "--layers", "1", "--vtu-every", "0", "--out", str(w / "pal")], w)
    assert code == 0, err[-2000:]
    shutil.copy(w / "done.h5", w / "truncated.h5")
    with open(w / "truncated.h5", "r+b") as f:
        f.truncate((w / "done.h5").stat().st_size // 2)
    shutil.copy(w / "done.h5", w / "flipped.h5")
    import h5py

    with h5py.File(w / "flipped.h5", "r") as h5:
        ds = h5["records/voltages"]
        offset = ds.id.get_chunk_info(0).byte_offset if ds.chunks else ds.id.get_offset()
    with open(w / "flipped.h5", "r+b") as f:
        f.seek(offset + 64)
        b = f.read(4)
        f.seek(offset + 64)
        f.write(bytes(x ^ 0xFF for x in b))
    s = str
    return [
        dict(group="output", what="--out under a file", argv=[*small_ds, "--out", s(w / "text.txt" / "x.h5")], names="--out"),
        dict(group="output", what="--out in /proc", argv=[*small_ds, "--out", "/proc/jointsim/x.h5"], names="--out"),
        dict(group="output", what="--out /dev/null", argv=[*small_ds, "--out", "/dev/null"], names="--out"),
        dict(group="output", what="dataset --out an existing folder", argv=[*small_ds, "--out", s(w / "a_folder")], names="--out"),
        dict(group="output", what="palpate --out an existing file", argv=["palpate", *SMALL, "--out", s(w / "text.txt")], names="--out"),
        dict(group="output", what="dataset --out a text file", argv=[*small_ds, "--out", s(w / "text.txt")], names="text.txt",
             keep=w / "text.txt"),
        dict(group="output", what="dataset --out a palpation store", argv=[*small_ds, "--out", s(w / "pal" / "palpation.h5")],
             names="palpation.h5", keep=w / "pal" / "palpation.h5"),
        dict(group="output", what="dataset --out a truncated store", argv=[*small_ds, "--out", s(w / "truncated.h5")],
             names="truncated.h5", keep=w / "truncated.h5"),
        dict(group="store", what="a finished store with 4 bytes flipped in a chunk, run again", argv=[*small_ds, "--out", s(w / "flipped.h5")],
             names=None, ok=True, mended=(w / "flipped.h5", w / "done.h5")),
        dict(group="store", what="a finished store run again (nothing to do)", argv=[*small_ds, "--out", s(w / "done.h5")], names=None,
             keep=w / "done.h5", ok=True),
        dict(group="scene", what="an empty scene file", argv=["palpate", s(w / "empty.toml"), *SMALL], names="empty.toml"),
        dict(group="scene", what="a scene without [electrodes]", argv=["palpate", s(w / "no_electrodes.toml"), *SMALL], names="[electrodes]"),
        dict(group="scene", what="a binary scene file", argv=["palpate", s(w / "binary.toml"), *SMALL], names="binary.toml"),
        dict(group="scene", what="a UTF-16 scene file", argv=["palpate", s(w / "utf16.toml"), *SMALL], names="utf16.toml"),
        dict(group="scene", what="palpation depth 11.5 mm (the dome takes ~10)", argv=["palpate", s(w / "deep.toml"), *SMALL],
             names="palpation.depth_mm"),
        dict(group="scene", what="ring radius 18.95 mm (past the base less the electrode)", argv=["palpate", s(w / "ring.toml"), *SMALL],
             names="electrodes.ring_radius_mm"),
        dict(group="scene", what="an empty FDM carrier list", argv=["forward", s(w / "carriers.toml"), *SMALL[:2]], names="drive.frequencies_hz"),
        dict(group="scene", what="reservoir pressure -10 kPa", argv=["forward", s(w / "suction.toml"), *SMALL[:2], "--out", s(w / "fw")],
             names="membrane.reservoir_pressure_pa"),
        dict(group="flags", what="protocol-study --snr-db -10", argv=["protocol-study", *SMALL, "--snr-db", "-10", "--out", s(w / "ps")],
             names="--snr-db"),
        dict(group="flags", what="--solver cholmod without scikit-sparse", argv=["forward", *SMALL[:2], "--solver", "cholmod"],
             names="--solver"),
        dict(group="flags", what="--solver cudss without a GPU", argv=[*small_ds, "--solver", "cudss", "--out", s(w / "g.h5")],
             names="--solver"),
        dict(group="flags", what="JOINTSIM_SOLVER=magma", argv=[*small_ds, "--out", s(w / "m.h5")], names="JOINTSIM_SOLVER",
             env={"JOINTSIM_SOLVER": "magma"}),
        dict(group="flags", what="a dead --scheduler address", argv=[*small_ds, "--scheduler", "tcp://127.0.0.1:9", "--out", s(w / "d.h5")],
             names="scheduler 'tcp://127.0.0.1:9'"),
        dict(group="flags", what="--seed 2^64", argv=[*small_ds[:3], "--seed", str(2**64), *SMALL, "--out", s(w / "s.h5")], names="--seed"),
        dict(group="flags", what="--n 0", argv=["dataset", "--n", "0", *SMALL, "--out", s(w / "n.h5")], names="--n"),
        dict(group="flags", what="palpate --device cuda:7", argv=["palpate", *SMALL, "--device", "cuda:7", "--out", s(w / "dv")],
             names="--device"),
        dict(group="flags", what="calibrate a text file", argv=["calibrate", s(w / "text.txt"), "--out", s(w / "cal")], names="text.txt"),
        dict(group="flags", what="frames from a missing file", argv=["frames", *SMALL[:2], "--frames", s(w / "none.csv"),
                                                                     "--reference", s(w / "none.csv"), "--out", s(w / "fr")], names="none.csv"),
    ]


def classify(c: dict, code: int, err: str, seconds: float) -> str:
    lines = [x for x in err.strip().splitlines() if ": warning: " not in x]
    if "Traceback" in err:
        return "C"
    if c.get("ok"):
        return "A" if code == 0 else "B"
    if code == 0:
        return "D"
    one = code == 2 and len(lines) == 1 and ": error: " in lines[0]
    named = c["names"] is None or c["names"] in lines[-1]
    return "A" if one and named and seconds <= LATE_S else "B"


def run() -> dict:
    w = Path(tempfile.mkdtemp(prefix="jointsim-bad-inputs-"))
    rows = []
    # a second writer on one store while the first runs: refused by the lock, the first unharmed
    first = subprocess.Popen([sys.executable, "-m", "jointsim", "dataset", "--n", "6", "--seed", "2", *SMALL, "--out", str(w / "two.h5")],
                             cwd=w, env={**os.environ, "PYTHONPATH": str(ROOT)}, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    while not (w / "two.partial").exists() and first.poll() is None:
        time.sleep(0.05)
    code, err, sec = _run(["dataset", "--n", "6", "--seed", "2", *SMALL, "--out", str(w / "two.h5")], w)
    _, ferr = first.communicate()
    c = {"group": "store", "what": "a second writer on a store in progress", "names": "two.h5"}
    rows.append({**c, "rc": code, "seconds": sec, "error": (err.strip().splitlines() or [""])[-1].replace(str(w), "W"),
                 "class": classify(c, code, err, sec),
                 "lost": "nothing (the first run finished)" if first.returncode == 0 else f"the first run failed: {ferr[-300:]}"})
    for c in cases(w):
        keep = c.get("keep")
        before = _digest(keep) if keep else None
        code, err, sec = _run(c["argv"], w, c.get("env"))
        after = _digest(keep) if keep else None
        lost = "n/a" if keep is None else ("nothing (the file unchanged)" if before == after else "THE FILE CHANGED")
        if "mended" in c:  # the damaged file set aside and the store mended: its data against the undamaged original's
            mended, original = c["mended"]
            same = code == 0 and open_records(mended).data_sha256 == open_records(original).data_sha256
            kept = mended.with_name(mended.name + ".damaged").exists()
            lost = (f"nothing (the damaged file kept as {mended.name}.damaged; the store mended to the original data)"
                    if same and kept else "THE DATA DIFFER")
        rows.append({"group": c["group"], "what": c["what"], "names": c["names"], "rc": code, "seconds": sec,
                     "error": (err.strip().splitlines() or [""])[-1].replace(str(w), "W"), "class": classify(c, code, err, sec),
                     "lost": lost})
        print(rows[-1]["class"], c["what"], "|", rows[-1]["error"][:160], flush=True)
    shutil.rmtree(w, ignore_errors=True)
    return {"machine": machine(), "rows": rows}


def markdown(r: dict) -> str:
    tally = {k: sum(x["class"] == k for x in r["rows"]) for k in "ABCD"}
    lines = ["# Bad input and faults: the class each ends in", "", "Command: `python benchmarks/bench_bad_inputs.py`  ",
             f"Machine: {r['machine']}. W: the run's scratch folder.", "", " ".join(__doc__.split("\n\n")[0].split()), "",
             f"**{len(r['rows'])} cases: " + ", ".join(f"{n} {k}" for k, n in tally.items()) + ".**", "",
             "| | case | exit | s | class | what the user reads (last line) | stored data lost |", "|---|---|---:|---:|---|---|---|"]
    for x in r["rows"]:
        err = x["error"].replace("|", "\\|")
        lines.append(f"| {x['group']} | {x['what']} | {x['rc']} | {x['seconds']:.1f} | {x['class']} | {err[:220]} | {x['lost']} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    run_and_write(__doc__, ROOT / "results" / "bad_inputs", run, markdown)


if __name__ == "__main__":
    main()
