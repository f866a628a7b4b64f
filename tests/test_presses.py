"""Explicit press lists (jointsim.dataset.presses, `jointsim dataset --presses`): the CSV's
forms and its refusals, the grid, and a dataset of listed presses on the test chamber (a
membrane of 24 rim vertices, one layer; ~30 s)."""

import math
from pathlib import Path

import numpy as np
import pytest

from jointsim.cli.main import main
from jointsim.dataset import generate_dataset, press_grid, read_presses
from jointsim.io.store import open_records
from jointsim.scene import load_scene, scene_toml

SCENE = """
extends = "paper_sensor"
name = "presses_test"
[mesh]
preset = "test"
[membrane]
rim_vertices = 24
layers = 1
[reconstruction]
cells = 1000
lambda_target_diameter_mm = 10.0
lambda_depth_mm = 1.0
[dataset]
samples_per_press = 2
"""


def _csv(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "presses.csv"
    p.write_text(text)
    return p


def test_a_csv_of_presses_one_row_each(tmp_path):
    p = read_presses(_csv(tmp_path, "# a rig's raster\ncontact_x_mm,contact_y_mm,diameter_mm,modulus_kpa\n"
                                    "0,0,15,\n12.5,-3,8,200\n"))
    assert p.place == "contact" and len(p) == 2 and p.depths is None and p.samples_per_press is None
    np.testing.assert_allclose(p.xy, [[0, 0], [12.5e-3, -3e-3]])
    np.testing.assert_allclose(p.radius, [7.5e-3, 4e-3])
    assert math.isinf(p.modulus[0]) and p.modulus[1] == pytest.approx(200e3)


def test_a_csv_of_samples_groups_consecutive_rows_into_presses(tmp_path):
    """Rows of one place, diameter and modulus in a row are one press; its depths sorted."""
    p = read_presses(_csv(tmp_path, "x_mm,y_mm,diameter_mm,depth_mm\n0,0,15,2\n0,0,15,1\n5,0,15,1\n5,0,15,2\n"))
    assert p.place == "centre" and len(p) == 2 and p.samples_per_press == 2
    np.testing.assert_allclose(p.depths, [[1e-3, 2e-3], [1e-3, 2e-3]])


@pytest.mark.parametrize("text, match", [
    ("a,b\n1,2\n", r"header \['a', 'b'\]; must name contact_x_mm"),
    ("contact_x_mm,contact_y_mm,x_mm,y_mm,diameter_mm\n0,0,0,0,8\n", "must name"),
    ("contact_x_mm,contact_y_mm,diameter_mm\n0,zero,8\n", r"line 2: contact_y_mm = 'zero' is not a number"),
    ("contact_x_mm,contact_y_mm,diameter_mm\n0,0\n", r"line 2: 2 values for 3 columns"),
    ("contact_x_mm,contact_y_mm,diameter_mm\n0,0,-8\n", r"diameter_mm = -8: must be > 0"),
    ("contact_x_mm,contact_y_mm,diameter_mm,depth_mm\n0,0,8,1\n0,0,8,2\n5,0,8,1\n", r"presses with \[1, 2\] depths"),
    ("contact_x_mm,contact_y_mm,diameter_mm,depth_mm\n0,0,8,1\n0,0,8,1\n", "repeats a depth"),
    ("contact_x_mm,contact_y_mm,diameter_mm\n", "a header but no presses"),
])
def test_a_bad_csv_is_refused_naming_the_line(tmp_path, text, match):
    with pytest.raises(ValueError, match=match):
        read_presses(_csv(tmp_path, text))


def test_the_grid_covers_the_disc_at_its_pitch():
    g = press_grid(5e-3, 15e-3, [8e-3, 30e-3], depths=[1e-3, 2e-3])
    pts = np.unique(g.xy, axis=0)
    # the square raster of pitch 5 mm within 15 mm of the axis: 29 nodes, the axis and (15, 0) among them
    assert len(pts) == 29 and len(g) == 58 and g.samples_per_press == 2
    assert {(0.0, 0.0), (15e-3, 0.0)} <= {tuple(np.round(q, 12)) for q in pts}
    np.testing.assert_allclose(np.sort(np.unique(g.radius)), [4e-3, 15e-3])


@pytest.fixture(scope="module")
def listed(tmp_path_factory):
    d = tmp_path_factory.mktemp("presses")
    scene_file = d / "scene.toml"
    scene_file.write_text(SCENE)
    csv = d / "presses.csv"
    csv.write_text("contact_x_mm,contact_y_mm,diameter_mm,depth_mm\n0,0,15,0.5\n0,0,15,1.0\n14,0,8,0.4\n14,0,8,0.8\n")
    scene = load_scene(scene_file)
    run = generate_dataset(scene, 4, d / "listed", seed=1, scene_toml=scene_toml(scene_file), workers=1,
                           presses=read_presses(csv))
    return scene_file, csv, d, run, open_records(run.path)


def test_a_dataset_presses_the_listed_presses(listed):
    """Each group is the listed press: touching at its point (to the surface fit's few µm), its
    diameter, at its depths; the list is part of the store's identity."""
    _, _, _, run, rec = listed
    assert run.n_samples == 4 and run.rejected_draws == 0
    np.testing.assert_allclose(rec["contact_point"], [[0, 0], [0, 0], [14e-3, 0], [14e-3, 0]], atol=1e-12)
    np.testing.assert_allclose(2 * rec["radius"], [15e-3, 15e-3, 8e-3, 8e-3])
    np.testing.assert_allclose(rec["depth"], [0.5e-3, 1e-3, 0.4e-3, 0.8e-3], atol=1e-12)
    assert rec["xy"][2, 0] > 14e-3  # the centre outside the point: the dome slopes away
    assert rec.provenance["params"]["presses"]["depths_mm"] == [[0.5, 1.0], [0.4, 0.8]]


def test_the_command_line_takes_a_press_list_and_refuses_a_wrong_n(listed, tmp_path, capsys):
    scene_file, csv, d, run, _ = listed
    # the same list and seed: the finished store is found, not recomputed
    assert main(["dataset", str(scene_file), "--presses", str(csv), "--seed", "1", "--out", str(run.path),
                 "--workers", "1", "--no-progress"]) == 0
    assert "nothing to do" in capsys.readouterr().out
    assert main(["dataset", str(scene_file), "--presses", str(csv), "--n", "5", "--out", str(tmp_path / "x")]) == 2
    assert "--n = 5: the press list" in capsys.readouterr().err
    bad = _csv(tmp_path, "contact_x_mm,contact_y_mm,diameter_mm\n18,0,8\n")
    assert main(["dataset", str(scene_file), "--presses", str(bad), "--out", str(tmp_path / "y")]) == 2
    assert "contact points must be within 17 mm" in capsys.readouterr().err
    assert not (tmp_path / "x.h5").exists() and not (tmp_path / "y.h5").exists()


def test_overwrite_discards_a_store_of_other_settings(listed, tmp_path, capsys):
    """A finished store of other settings is refused naming --overwrite; with it, the store and
    any run in progress are removed and the run starts afresh."""
    scene_file, csv, _, run, _ = listed
    out = tmp_path / "again.h5"
    out.write_bytes(run.path.read_bytes())
    (tmp_path / "again.partial").mkdir()  # a leftover run in progress goes too
    args = ["dataset", str(scene_file), "--presses", str(csv), "--out", str(out), "--workers", "1", "--no-progress"]
    assert main(args + ["--seed", "2"]) == 2
    assert "other settings; remove it (--overwrite)" in capsys.readouterr().err
    assert main(args + ["--seed", "2", "--overwrite"]) == 0
    assert f"--overwrite: removed {out}" in capsys.readouterr().out
    assert open_records(out).provenance["seed"] == 2 and not (tmp_path / "again.partial").exists()
