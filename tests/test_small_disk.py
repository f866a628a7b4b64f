"""A dataset run on a real file system that fills up (a tmpfs mounted for the test, so root
only; skipped elsewhere): the run stops with one line naming the path, keeps what it stored, and
the same command, once there is room, ends with the data of a run that never lacked it."""

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from jointsim.io.records import open_records

ROOT = Path(__file__).resolve().parents[1]
ARGS = ["dataset", "--mesh", "test", "--n", "12", "--seed", "4", "--workers", "1", "--no-progress"]


def _run(out: Path, env: dict) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "jointsim", *ARGS, "--out", str(out)], env=env, cwd=ROOT,
                          capture_output=True, text=True, timeout=600)


@pytest.fixture
def small_fs(tmp_path):
    """A folder on a tmpfs of 64 kB (less than the run's chamber mesh), and a function to grow it."""
    if not hasattr(os, "geteuid") or os.geteuid() != 0 or shutil.which("mount") is None:
        pytest.skip("mounting a small file system needs root and mount(8)")
    where = tmp_path / "small"
    where.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(where)], capture_output=True).returncode:
        pytest.skip("this machine refuses to mount a tmpfs")
    yield where, lambda size: subprocess.run(["mount", "-o", f"remount,size={size}", str(where)], check=True)
    subprocess.run(["umount", str(where)], capture_output=True)


def test_a_full_file_system_stops_the_run_clearly_and_it_finishes_once_there_is_room(tmp_path, small_fs):
    where, grow = small_fs
    env = {**os.environ, "JOINTSIM_CACHE": str(tmp_path / "cache"), "PYTHONPATH": str(ROOT)}
    reference = _run(tmp_path / "ref.h5", env)
    assert reference.returncode == 0, reference.stderr[-2000:]
    out = where / "run.h5"
    full = _run(out, env)
    assert full.returncode == 2 and "Traceback" not in full.stderr
    line = [x for x in full.stderr.splitlines() if "error:" in x]
    assert len(line) == 1 and "No space left on device" in line[0] and str(where) in line[0]
    grow("64m")
    again = _run(out, env)
    assert again.returncode == 0, again.stderr[-2000:]
    assert open_records(out, fields=[], verify=True).data_sha256 == open_records(tmp_path / "ref.h5", fields=[]).data_sha256
