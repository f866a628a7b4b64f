"""The membrane's modulus from known presses (jointsim.calibration.membrane_fit): the forces a
dataset press records on a membrane of another modulus give that modulus back, and a rig's
CSV of known presses is read, or refused in one line. At the test fidelity with a coarse
membrane (32 rim vertices, one layer)."""

import math
from dataclasses import replace

import numpy as np
import pytest

from jointsim.calibration.membrane_fit import KnownPress, fit_membrane_scale, known_presses, press_forces
from jointsim.dataset.generate import DatasetSetup, GroupDraw
from jointsim.dataset.presses import read_presses

SCALE = 0.7  # the sensor's membrane: 30 % softer than the scene's


@pytest.fixture(scope="module")
def rig_press(test_chamber):
    """A dataset press of a 12 mm sphere at two depths on the membrane × SCALE, as a rig would
    know it (the sphere's centre, the depths past first contact, the forces read)."""
    scene, chamber = test_chamber
    scene = replace(scene, membrane=replace(scene.membrane, rim_vertices=32, layers=1))
    setup = DatasetSetup(scene, chamber, seed=5)
    draw = GroupDraw(0, 0, 6e-3, None, math.inf, SCALE, 0.37, 1e-3, np.zeros((setup.n_electrodes, 2)), 74.2,
                     np.array([1.0e-3, 2.0e-3]), np.array([4e-3, -2e-3]))
    records = setup.press(draw, 2)
    press = KnownPress(6e-3, np.asarray(records[0]["xy"]), np.array([r["depth"] for r in records]),
                       np.array([np.linalg.norm(r["force"]) for r in records]))
    yield scene, setup.instrument, press
    setup.free()


def test_the_forces_of_a_softer_membrane_give_its_modulus_back(rig_press):
    """The fit's press is the dataset's (the same membrane, first contact and steps: the forces
    at the true scale agree to round-off), and from the scene's modulus (×1) the fit lands on
    ×0.7 within 0.05 % (its steps stop below 0.01 %), its σ at a 1 % load cell a few per cent
    of the scale, the misfit nil (the data are noise-free)."""
    scene, inst, press = rig_press
    np.testing.assert_allclose(press_forces(scene, press, SCALE, inst.inflated_u), press.forces, rtol=1e-9)
    fit = fit_membrane_scale(scene, [press], inflate_from=inst.inflated_u)
    assert abs(math.log(fit.scale / SCALE)) < 5e-4
    assert 0.002 < fit.sd_ln < 0.05  # 1 % per reading, two readings, F ∝ s nearly: ~0.7 %
    assert fit.misfit < 0.05 and fit.iterations <= 5
    np.testing.assert_allclose(fit.forces[0], press.forces, rtol=1e-3)


def test_a_rigs_csv_of_known_presses(tmp_path):
    """Rows of one press (same place and diameter) are its depths, sorted with their forces;
    what the fit cannot use is refused naming the file."""
    ok = tmp_path / "rig.csv"
    ok.write_text("x_mm,y_mm,diameter_mm,depth_mm,force_n\n4,-2,12,2.0,0.028\n4,-2,12,1.0,0.015\n-8,3,8,1.5,0.02\n-8,3,8,2.5,0.03\n")
    presses = known_presses(read_presses(ok))
    assert len(presses) == 2
    np.testing.assert_allclose(presses[0].depths, [1e-3, 2e-3])
    np.testing.assert_allclose(presses[0].forces, [0.015, 0.028])  # the forces moved with their depths
    np.testing.assert_allclose(presses[1].xy, [-8e-3, 3e-3])
    assert presses[1].radius == pytest.approx(4e-3)
    cases = {
        "contact_x_mm,contact_y_mm,diameter_mm,depth_mm,force_n\n1,1,12,1,0.01\n": "the target's centre",
        "x_mm,y_mm,diameter_mm,depth_mm\n1,1,12,1\n": "give depth_mm and force_n",
        "x_mm,y_mm,diameter_mm,force_n\n1,1,12,0.01\n": "give depth_mm with it",
        "x_mm,y_mm,diameter_mm,modulus_kpa,depth_mm,force_n\n1,1,12,30,1,0.01\n": "rigid targets only",
        "x_mm,y_mm,diameter_mm,depth_mm,force_n\n1,1,12,1,-0.01\n": r"line 2: force_n = -0.01: must be finite and > 0",
        "x_mm,y_mm,diameter_mm,depth_mm,force_n\n1,1,12,1,abc\n": r"line 2: force_n = 'abc' is not a number",
    }
    for text, match in cases.items():
        bad = tmp_path / "bad.csv"
        bad.write_text(text)
        with pytest.raises(ValueError, match=match):
            known_presses(read_presses(bad))


def test_frames_known_presses_is_refused_in_one_line(tmp_path, capsys):
    """`jointsim frames --known-presses CSV` reads the rig's CSV before any instrument is built:
    a list the fit cannot use (contact points, no forces, a missing file) is one line naming the
    flag or the file (exit 2)."""
    from jointsim.cli.main import main
    from jointsim.eit.protocol import scene_protocol
    from jointsim.scene import SCENES_DIR, load_scene

    n = scene_protocol(load_scene(SCENES_DIR / "paper_sensor.toml")).n_meas
    rows = np.random.default_rng(0).normal(1.0, 1e-3, (3, n))
    frames = tmp_path / "f.csv"
    frames.write_text("\n".join(",".join(f"{v:.9g}" for v in r) for r in rows) + "\n")
    contact, unforced = tmp_path / "contact.csv", tmp_path / "unforced.csv"
    contact.write_text("contact_x_mm,contact_y_mm,diameter_mm,depth_mm,force_n\n1,1,12,1,0.01\n")
    unforced.write_text("x_mm,y_mm,diameter_mm,depth_mm\n1,1,12,1\n")
    for csv, why in ((contact, "--known-presses"), (unforced, "--known-presses"), (tmp_path / "missing.csv", "missing.csv")):
        assert main(["frames", "--frames", str(frames), "--reference", str(frames), "--known-presses", str(csv),
                     "--out", str(tmp_path / "out")]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and why in err[0], err
