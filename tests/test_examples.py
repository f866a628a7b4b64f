"""The tutorials (examples/, shown on the documentation site) run as a user runs them: each
script from a fresh folder, in the order the tutorials give (the calibration reads the
dataset's file), and says what it should (about 1 min on 2 cores)."""

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _run(name: str, cwd: Path) -> str:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    r = subprocess.run([sys.executable, str(ROOT / "examples" / name)], cwd=cwd, capture_output=True, text=True,
                       timeout=900, env=env)
    assert r.returncode == 0, f"{name}: {r.stderr[-3000:]}"
    return r.stdout


def test_the_tutorials_run_in_order(tmp_path):
    out = _run("palpation.py", tmp_path)
    assert "12 frames; at the deepest (1.50 mm)" in out and (tmp_path / "out/tutorial/palpation/summary.md").is_file()
    out = _run("dataset.py", tmp_path)
    assert out.startswith("48 samples (8 presses computed now)")
    out = _run("calibration.py", tmp_path)
    assert "applied to 48 frames" in out and (tmp_path / "out/tutorial/calibration/calibration_map.h5").is_file()
