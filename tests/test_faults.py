"""Bad input found before any work, one line, exit 2 (issue 48): the solver a machine lacks, a
drive with no carrier, a suction the membrane cannot hold."""

from dataclasses import replace

import pytest

from jointsim.cli.main import main
from jointsim.linalg import available_backends
from jointsim.scene import SceneError, scene_from_dict


@pytest.mark.parametrize("solver, why", [("cholmod", "not installed here"), ("magic", "not a solver jointsim knows")])
def test_forward_refuses_a_solver_it_cannot_use_before_any_work(solver, why, tmp_path, capsys):
    if solver in available_backends():
        pytest.skip(f"{solver} is installed here")
    out = tmp_path / "f"
    assert main(["forward", "--mesh", "test", "--solver", solver, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert f"--solver = '{solver}': {why}; available here: auto, superlu" in err and "Traceback" not in err
    assert not out.exists()


def test_a_drive_without_carriers_is_refused_naming_the_key():
    with pytest.raises(SceneError, match=r"drive.frequencies_hz = \[\]: at least one carrier"):
        scene_from_dict({"drive": {"frequencies_hz": []}})
    with pytest.raises(SceneError, match="contact_impedance_by_freq_ohm_m2: must be a list with one row per"):
        scene_from_dict({"electrodes": {"contact_impedance_by_freq_ohm_m2": []}})


def test_a_suction_the_membrane_cannot_hold_names_the_reservoir_pressure(paper_scene):
    from jointsim.mechanics.build import membrane_from_scene
    from jointsim.mechanics.newton import NewtonError

    s = paper_scene.with_mesh_preset("test")
    s = replace(s, membrane=replace(s.membrane, reservoir_pressure=-1e4, rim_vertices=32))
    with pytest.raises(NewtonError, match=r"no equilibrium at rest under membrane.reservoir_pressure_pa = -10000 "
                                          r"\(a suction this strong collapses the dome\)"):
        membrane_from_scene(s)


def test_an_unknown_flag_gets_the_subcommands_usage_and_version_is_there(capsys):
    with pytest.raises(SystemExit) as e:
        main(["palpate", "--dome-rim", "32"])
    err = capsys.readouterr().err
    assert e.value.code == 2 and err.startswith("usage: jointsim palpate") and "jointsim palpate: error: unrecognized arguments: --dome-rim (--dome-rim is now --rim-vertices)" in err
    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0 and capsys.readouterr().out.strip() == f"jointsim {__import__('jointsim').__version__}"


def test_the_studies_write_under_out_by_default():
    """Run from the checkout, a study must not overwrite the committed results/."""
    from jointsim.cli.main import build_parser

    p = build_parser()
    for command in ("protocol-study", "indent", "stiffness-study", "palpate", "forward"):
        out = p.parse_args([command]).out
        assert out.parts[0] == "out", (command, out)


def test_every_command_with_a_progress_bar_takes_the_progress_flag():
    # one convention: the bar shows on a terminal unless --no-progress, and --progress forces it
    from jointsim.cli.common import progress_off
    from jointsim.cli.main import build_parser

    p = build_parser()
    needs = {"design-study": ["a.toml"], "frames": ["--frames", "f.csv", "--reference", "r.csv"], "calibrate": ["d.h5"]}
    for command in ("calibrate", "dataset", "palpate", "design-study", "frames", "indent", "protocol-study", "stiffness-study"):
        base = [command, *needs.get(command, [])]
        assert progress_off(p.parse_args(base)) is None, command
        assert progress_off(p.parse_args([*base, "--no-progress"])) is True, command
        assert progress_off(p.parse_args([*base, "--progress"])) is False, command


def test_indent_refuses_a_contact_off_the_base_naming_the_flags(tmp_path, capsys):
    out = tmp_path / "i"
    assert main(["indent", "--x-mm", "25", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "--x-mm, --y-mm = 25, 0: the contact must lie within the base radius 20 mm of the axis" in err
    assert not out.exists()
