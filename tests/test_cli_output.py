"""An output the command line cannot write is refused before any work, in one line naming --out,
the path and why (exit 2): under a file, a file where a folder is wanted and the reverse, a
virtual or device file system."""

import pytest

from jointsim.cli.main import SUBCOMMANDS, main

WRITERS = sorted(name for name, mod in SUBCOMMANDS.items() if getattr(mod, "OUTPUT", None))


def _bad_outputs(tmp_path, kind):
    plain = tmp_path / "plain.txt"
    plain.write_text("not a folder\n")
    cases = {"under a file": plain / "sub", "a virtual file system": "/proc/jointsim-out", "a device": "/dev/null"}
    cases.update({"a file": plain} if kind == "folder" else {"a folder": tmp_path})
    return cases


def test_every_command_that_writes_says_what_its_output_is():
    assert set(WRITERS) == {"calibrate", "dataset", "design-study", "forward", "frames", "indent", "palpate",
                            "protocol-study", "stiffness-study"}


@pytest.mark.parametrize("command", WRITERS)
def test_an_output_that_cannot_be_written_is_refused_in_one_line(command, tmp_path, capsys):
    kind = SUBCOMMANDS[command].OUTPUT
    for why, out in _bad_outputs(tmp_path, kind).items():
        required = {"calibrate": ["missing.h5"], "dataset": ["--n", "3"],
                    "frames": ["--frames", "missing.csv", "--reference", "missing.csv"]}.get(command, [])
        args = [command, *required, "--out", str(out)]
        assert main(args) == 2, why
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith(f"jointsim {command}: error: --out {out}:"), (why, err)
    assert not list(tmp_path.glob(".jointsim-probe-*"))  # the probe leaves nothing behind


def test_frames_reads_measured_frames_and_writes_their_images(tmp_path, capsys):
    """`jointsim frames` end to end on the test mesh: the sensor at rest as the reference, a
    frame with a dent's worth of change in a few channels; one row per frame, the images, the
    summary; a missing file is one line naming it."""
    import numpy as np

    from jointsim.instrument import Instrument
    from jointsim.scene import SCENES_DIR, load_scene

    scene = load_scene(SCENES_DIR / "paper_sensor.toml").with_mesh_preset("test")
    inst = Instrument.build(scene, imaging=False)
    v = inst.readout.v_ref
    inst.free()
    ref, frames = tmp_path / "ref.csv", tmp_path / "frames.csv"
    ref.write_text(",".join(f"{x:.17g}" for x in v) + "\n")
    pressed = v * (1 - 1e-3 * (np.arange(len(v)) % 16 == 3))
    frames.write_text("\n".join(",".join(f"{x:.17g}" for x in row) for row in (v, pressed)) + "\n")
    out = tmp_path / "out"
    assert main(["frames", "--mesh", "test", "--frames", str(frames), "--reference", str(ref), "--out", str(out),
                 "--fit-reference"]) == 0
    import json

    fitted = json.loads((out / "summary.json").read_text())["fitted_sensor"]  # the nominal sensor's own frame
    assert fitted["misfit_before"] < 1e-12 and fitted["conductivity_s_per_m"] == pytest.approx(0.37, rel=1e-9)
    rows = (out / "frames.csv").read_text().splitlines()
    assert rows[0].startswith("frame,com_x,com_y,com_z,sum_sigma,diameter,rms_dv") and len(rows) == 3
    assert (out / "images.vtu").is_file() and (out / "summary.json").is_file()
    capsys.readouterr()
    assert main(["frames", "--mesh", "test", "--frames", str(tmp_path / "none.csv"), "--reference", str(ref),
                 "--out", str(tmp_path / "x")]) == 2
    assert "none.csv: no such file" in capsys.readouterr().err
