"""What a design can measure (jointsim.design): the equilibrium's derivatives against re-solved
differences, the moduli–head identity, a press's Jacobian against the frame step, the bounds
against a Monte-Carlo of an efficient estimator, and the design-study command end to end.
At the test chamber resolution with a coarse membrane (32 rim vertices, one layer)."""

from dataclasses import replace

import numpy as np
import pytest

from jointsim.cli.main import main
from jointsim.design.bounds import Bounds, fisher, median_error, nuisance_prior, press_bounds
from jointsim.design.sensitivity import TARGET, parameter_names, press_sensitivity
from jointsim.instrument import Instrument
from jointsim.mechanics.build import membrane_from_scene
from jointsim.scene import SCENES_DIR, load_scene


@pytest.fixture(scope="module")
def coarse(test_chamber):
    scene, chamber = test_chamber
    scene = replace(scene, membrane=replace(scene.membrane, rim_vertices=32, layers=1))
    inst = Instrument.build(scene, chamber=chamber, imaging=False)
    yield scene, inst
    inst.free()


def _membrane(scene, radius=7.5e-3):
    model = membrane_from_scene(replace(scene, target=replace(scene.target, kind="rigid")), target_radius=radius)
    model.force_rtol = 0.0  # differences of equilibria need them solved to force_tol
    return model


def _press(model, xy, depth, steps=4):
    z0 = model.first_contact_height(xy)
    for s in range(1, steps + 1):
        model.press(np.array([xy[0], xy[1], z0 - depth * s / steps]))


def test_equilibrium_derivative_is_the_limit_of_resolved_differences(coarse):
    """du/dθ = −H⁻¹∂g/∂θ (the implicit function theorem) for the sphere's centre, its radius and
    the saline pressure, against equilibria re-solved at θ ± h. Measured on the 64-rim membrane:
    the differences approach the derivative as h falls (10 % at 100 µm, 0.4 % at 12.5 µm: the
    contact's active set changes within larger steps) and level off at 0.1–0.4 % (the solver's
    tolerance over h); 2 % at 10 µm is the bar."""
    scene, _ = coarse
    model = _membrane(scene)
    _press(model, np.array([3e-3, 2e-3]), 1.5e-3)
    base = model.get_state()
    u, c0, p0 = model.u.copy(), model.contact.centre.copy(), model.pressure.pressure
    dg = np.column_stack([model.contact.parameter_gradients(u), -model.pressure.volume_gradient(u).ravel()])
    du = model.equilibrium_derivative(dg)
    model.set_state(base)
    h = 10e-6
    for j in range(5):
        sides = []
        for sgn in (1, -1):
            if j < 3:
                c = c0.copy()
                c[j] += sgn * h
                model.press(c)
            elif j == 3:
                model.contact.radius = 7.5e-3 + sgn * h
                model.equilibrate()
            else:
                model.equilibrate(p0 + sgn * h * 1e6)  # a pressure step of 10 Pa
            sides.append(model.u.copy())
            model.set_state(base)
            model.contact.radius = 7.5e-3
        fd = (sides[0] - sides[1]) / (2 * h * (1e6 if j == 4 else 1))
        assert np.abs(fd).max() > 0.05 * (1e-6 if j == 4 else 1)  # the parameter moves the membrane
        assert np.linalg.norm(fd - du[..., j]) <= 0.02 * np.linalg.norm(du[..., j]), j


def test_scaled_moduli_act_as_the_head_divided_by_the_scale(coarse):
    """Every modulus (and with it the default contact penalty) × s is the unscaled membrane under
    p/s: the same equilibrium, which is why ∂V/∂ln μ = −∂V/∂ln p (jointsim.design.sensitivity)."""
    scene, _ = coarse
    s = 1.3
    stiff = _membrane(replace(scene, membrane=scene.membrane.scaled(s)))
    soft_head = _membrane(replace(scene, membrane=replace(scene.membrane, reservoir_pressure=scene.membrane.reservoir_pressure / s)))
    for m in (stiff, soft_head):
        _press(m, np.array([2e-3, -1e-3]), 1.0e-3)
    scale = np.abs(stiff.u).max()
    # both solved to their force_tol (the stiffer one's is s× larger): 1e-6 of the displacement
    np.testing.assert_allclose(stiff.u, soft_head.u, atol=1e-6 * scale)
    assert np.abs(stiff.u - _membrane(scene).u).max() > 1e-3 * scale  # while the head alone does move it


def test_a_press_jacobian_matches_the_frame_step(coarse):
    """A press's ∂V/∂depth from press_sensitivity (the tangent, then the morph and the forward
    model along it) against the instrument's clean voltages at depth ± 10 µm, re-solved: the
    columns are assembled with the right signs and units. The reference's columns of the target
    are zero, its head column is not, and ∂V/∂ln μ = −∂V/∂ln p."""
    scene, inst = coarse
    model = _membrane(scene)
    xy, d = np.array([2e-3, 1e-3]), 1.5e-3
    untouched = model.u.copy()
    ps = press_sensitivity(inst, model, xy, np.array([d]))
    assert ps.names == parameter_names(len(inst.reference.layout.radii))
    h = 10e-6
    v = []
    for dd in (d + h, d - h):
        m = _membrane(scene)
        _press(m, xy, dd)
        v.append(inst.measure(inst.dome(m.u), None, image=False).voltages_clean)
    fd = (v[0] - v[1]) / (2 * h)
    col = ps.jacobian[0, :, TARGET.index("depth")]
    assert np.linalg.norm(fd - col) <= 0.02 * np.linalg.norm(col)
    np.testing.assert_allclose(ps.voltages[0], inst.measure(inst.dome(_pressed(scene, xy, d)), None, image=False).voltages_clean,
                               rtol=0, atol=1e-6 * np.abs(ps.voltages).max())
    assert not ps.jacobian_ref[:, :4].any() and np.abs(ps.jacobian_ref[:, 4]).max() > 0
    np.testing.assert_array_equal(ps.jacobian[..., 5], -ps.jacobian[..., 4])
    np.testing.assert_array_equal(model.u, untouched)  # the model is left untouched


def _pressed(scene, xy, d):
    m = _membrane(scene)
    _press(m, xy, d)
    return m.u


def test_the_bound_is_reached_by_least_squares_on_a_linear_model():
    """For a linear Gaussian model the least-squares estimator is efficient: over 4000 noisy
    reference and frame pairs its error covariance is the Cramér–Rao bound (each RMS within 5 %:
    ±2.2 % is one standard error at 4000 draws), with the nuisances known and marginalised over
    a Gaussian prior (the estimator then is the MAP one)."""
    rng = np.random.default_rng(7)
    M, P, R, H, sigma = 60, 7, 5, 3, 0.1
    J_ref = np.column_stack([np.zeros((M, 4)), rng.normal(size=(M, 3))])
    J = rng.normal(size=(M, P))
    prior = np.array([0.0, 0.3, 0.05])  # one known, two with a prior
    F = fisher(J_ref.T @ J_ref, J.T @ J, sigma, reference_frames=R, hold_frames=H)
    b = press_bounds(F, prior, np.eye(2, 4))
    theta = rng.normal(size=P)
    theta[4] = 0.0  # the known nuisance at its known value
    n = 4000
    keep = [0, 1, 2, 3, 5, 6]  # the known nuisance (index 4) is not estimated
    prior_rows = np.zeros((2, len(keep)))
    prior_rows[[0, 1], [4, 5]] = 1 / prior[1:]
    A = np.vstack([np.sqrt(R) / sigma * J_ref[:, keep], np.sqrt(H) / sigma * J[:, keep], prior_rows])  # whitened
    est = np.empty((n, 4))
    for i in range(n):
        y_ref = J_ref @ theta + rng.normal(0, sigma / np.sqrt(R), M)  # the averaged reference
        y = J @ theta + rng.normal(0, sigma / np.sqrt(H), M)  # the averaged frames of the hold
        said = theta[5:] + rng.normal(0, prior[1:])  # what the prior says the nuisances are
        rhs = np.r_[np.sqrt(R) / sigma * y_ref, np.sqrt(H) / sigma * y, said / prior[1:]]
        est[i] = np.linalg.lstsq(A, rhs, rcond=None)[0][:4]
    err = est - theta[:4]
    np.testing.assert_allclose(err.std(axis=0), np.sqrt(np.diag(b.marginal)), rtol=0.05)
    assert np.all(np.diag(b.marginal) >= np.diag(b.known) * (1 - 1e-12))  # not knowing costs
    # the median |error| of the estimator in the plane and in one axis is the bound's
    assert np.median(np.hypot(err[:, 0], err[:, 1])) == pytest.approx(median_error(b.contact_marginal), rel=0.05)
    assert np.median(np.abs(err[:, 2])) == pytest.approx(median_error(b.marginal[2:3, 2:3]), rel=0.05)


def test_a_nuisance_that_mimics_the_target_needs_its_prior():
    """A nuisance whose column equals the radius's: unbounded without a prior, bounded by it with
    one (the radius is then known to about the prior's spread), and the known bound in the limit."""
    rng = np.random.default_rng(3)
    J = rng.normal(size=(30, 4))
    J = np.column_stack([J, J[:, 3]])
    F = J.T @ J / 0.01**2
    free = press_bounds(F, np.array([np.inf]), np.eye(2, 4))
    assert not np.isfinite(free.marginal).all()
    held = press_bounds(F, np.array([1e-3]), np.eye(2, 4))
    assert np.sqrt(held.marginal[3, 3]) == pytest.approx(np.hypot(1e-3, np.sqrt(held.known[3, 3])), rel=0.02)
    tight = press_bounds(F, np.array([1e-9]), np.eye(2, 4))
    np.testing.assert_allclose(tight.marginal, tight.known, rtol=1e-6)
    assert isinstance(tight, Bounds)
    # two nuisances that act only together (the head and the modulus): at any SNR their priors
    # keep the bound finite, even where they are 1e-20 of the data's information
    K = rng.normal(size=(30, 5))
    K = np.column_stack([K, -K[:, 4]])
    for scale in (1.0, 1e20):
        b = press_bounds(scale * K.T @ K, np.array([0.2, 0.4]), np.eye(2, 4))
        assert np.isfinite(b.marginal).all() and np.all(np.diag(b.marginal) >= np.diag(b.known) * (1 - 1e-6))


def test_the_priors_are_the_scene_randomisation(coarse):
    scene, inst = coarse
    names = parameter_names(len(inst.reference.layout.radii))
    prior = nuisance_prior(scene, names)
    d = scene.dataset
    assert prior[names.index("ln_modulus") - 4] == pytest.approx(np.log(d.membrane_scale[1] / d.membrane_scale[0]) / np.sqrt(12))
    assert prior[names.index("x3") - 4] == pytest.approx(d.electrode_jitter / 2)


def test_design_study_command_end_to_end(tmp_path, capsys):
    """Two presses, one depth: the sensitivities stored, the bounds table, the maps and the
    comparison written; run again, the finished store is found, not recomputed; bad input is
    one line naming the flag."""
    out = tmp_path / "ds"
    args = ["design-study", "--mesh", "test", "--diameters-mm", "15", "--depths-mm", "1.5", "--spacing-mm", "4",
            "--r-max-mm", "0", "--contact-levels", "2", "--workers", "1", "--out", str(out)]
    assert main(args) == 0
    for f in ("summary.md", "summary.csv", "paper_sensor/bounds.csv", "paper_sensor/position_bound.png",
              "paper_sensor/sensitivities.h5"):
        assert (out / f).exists(), f
    text = (out / "summary.md").read_text()
    assert "| paper_sensor (all) | 74.2 | 1 | 1 |" in text
    assert "refined about its contact" in text and "paper_sensor 2×" in text
    import argparse

    from jointsim.cli.design_study import add_arguments

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    defaults = parser.parse_args([])
    assert defaults.contact_levels == 3 and defaults.symmetric  # where the size derivative converged
    assert "| paper_sensor (15 mm) | 74.2 | 1 | 1 |" in text and "| paper_sensor (1.5 mm deep) | 74.2 | 1 | 1 |" in text
    rows = (out / "paper_sensor" / "bounds.csv").read_text().splitlines()
    assert len(rows) == 2 and rows[0].startswith("diameter_mm,x_mm")
    capsys.readouterr()
    first = (out / "summary.md").read_text()
    assert main(args) == 0
    # nothing computed the second time: the cost is the run that wrote the store (workers not recorded)
    assert "| 1, –, " in (out / "summary.md").read_text() and "| 1, –, " not in first
    # averaging 4 frames per press: the same store serves, the bounds halve (nuisances known, and
    # the reference already averaged over 50 frames does not bound them)
    before = (out / "paper_sensor" / "bounds.csv").read_text().splitlines()[1].split(",")
    assert main(args + ["--hold-frames", "4"]) == 0
    after = (out / "paper_sensor" / "bounds.csv").read_text().splitlines()[1].split(",")
    assert "| 1, –, " in (out / "summary.md").read_text()  # again nothing computed
    col = rows[0].split(",").index("position_rms_known_mm")
    assert float(after[col]) == pytest.approx(float(before[col]) / 2, rel=2e-5)  # the CSV keeps 6 digits
    assert main(["design-study", "--depths-mm", "2,1", "--out", str(tmp_path / "x")]) == 2
    assert "--depths-mm = '2,1': increasing" in capsys.readouterr().err
    assert main(["design-study", "--contact-levels", "9", "--out", str(tmp_path / "x")]) == 2
    assert "--contact-levels = 9: must be in 0..4" in capsys.readouterr().err
    for extra in ([], ["--target-moduli-kpa", "30", "--contact-levels", "0"]):  # a rigid sphere; no refined zone
        for mesh in ("graded", "layered"):
            assert main(["design-study", f"--{mesh}-target", *extra, "--out", str(tmp_path / "x")]) == 2
            assert f"--{mesh}-target: only with --target-moduli-kpa" in capsys.readouterr().err
    # a pad's membrane is not refined about the contact: read as meshed, and said so
    assert main(["design-study", str(SCENES_DIR / "elongated_pad.toml"), *args[1:-2], "--out", str(tmp_path / "pad")]) == 0
    assert "elongated_pad: read at --contact-levels 0" in capsys.readouterr().out
    assert "elongated_pad 0×" in (tmp_path / "pad" / "summary.md").read_text()


def test_the_calibration_goals_are_read_in_either_csv_form(tmp_path):
    """goals.csv quotes a goal holding a comma now (calibration.report.write_csv); files written
    before did not, and are read too."""
    from jointsim.calibration.report import write_csv
    from jointsim.design.report import estimator_rows

    cols = {"goal": ["CoM xy, r <= 15 mm", "depth", "size (diameter 8-30 mm)"], "route": ["direct (mlp)"] * 3,
            "statistic": ["median"] * 3, "limit": [0.5, 0.5, 1.0], "value": [0.316, 0.045, 4.87], "unit": ["mm"] * 3}
    new = write_csv(tmp_path / "goals.csv", cols)
    assert '"CoM xy, r <= 15 mm"' in new.read_text()
    old = tmp_path / "old.csv"
    old.write_text("goal,route,statistic,limit,value,unit\nCoM xy, r <= 15 mm,direct (mlp),median,0.5,0.316,mm\n"
                   "depth,direct (mlp),median,0.5,0.045,mm\nsize (diameter 8-30 mm),direct (mlp),median,1,4.87,mm\n")
    want = {"direct (mlp)": {"position": 0.316e-3, "depth": 0.045e-3, "diameter": 4.87e-3}}
    for f in (new, old):
        got = estimator_rows(f)
        assert got.keys() == want.keys()
        for q, v in want["direct (mlp)"].items():
            assert got["direct (mlp)"][q] == pytest.approx(v)


def test_a_press_the_mechanics_cannot_take_is_stored_and_said(test_chamber, tmp_path, monkeypatch):
    """A press that raises UnreachablePose is stored as not reached (NaN) and its reason reaches
    the caller (on_missed), not dropped."""
    import jointsim.design.study as study
    from jointsim.io.records import open_records
    from jointsim.mechanics.dome import UnreachablePose

    def refuse(*a, **k):
        raise UnreachablePose("beyond what the dome can take (a test)")

    monkeypatch.setattr(study, "press_mechanics", refuse)
    scene, _ = test_chamber
    missed = []
    h5 = study.run_design(scene, study.Plan(diameters=(15e-3,), depths=(1e-3,), r_max=0.0), tmp_path / "s.h5", workers=1,
                          on_missed=lambda i, why: missed.append((i, why)))
    assert missed == [(0, "UnreachablePose: beyond what the dome can take (a test)")]
    assert open_records(h5)["reached"].tolist() == [0]


def test_an_instrument_reads_through_a_membrane_refined_under_the_press(coarse):
    """Instrument.on_membrane: the same chamber and readout through another membrane of the
    scene. On a membrane meshed as the instrument's own it measures what the instrument does, bit
    for bit (the morpher's closest points are the same); on one refined under the press
    (geometry.refine_near) the untouched sensor's voltages are those of the coarse membrane to
    the inflated surfaces' difference, and the press's δV agrees with the coarse one in shape
    (the refined contact changes its size by the discretisation error, not its pattern).
    Freeing the copy's morpher leaves the shared factor to the original."""
    from jointsim.geometry import chamber_cap, refine_near

    scene, inst = coarse
    rigid = replace(scene, target=replace(scene.target, kind="rigid"))
    xy, d = np.array([2e-3, 1e-3]), 1.5e-3
    same = inst.on_membrane(membrane_from_scene(rigid))
    u = _pressed(scene, xy, d)
    v0 = inst.readout.voltages(inst.morpher(inst.dome(u)), True)
    np.testing.assert_array_equal(same.readout.voltages(same.morpher(same.dome(u)), True), v0)

    dome = refine_near(chamber_cap(scene.chamber, 32), xy, 4e-3, 2)
    fine = membrane_from_scene(rigid, dome=dome)
    fine.force_rtol = 0.0
    on_fine = inst.on_membrane(fine)
    v_ref = on_fine.readout.voltages(on_fine.reference, True)
    v_ref0 = inst.readout.voltages(inst.reference, True)
    assert np.linalg.norm(v_ref - v_ref0) <= 1e-4 * np.linalg.norm(v_ref0)  # measured 1.8e-5
    _press(fine, xy, d)
    dv_fine = on_fine.readout.voltages(on_fine.morpher(on_fine.dome(fine.u)), True) - v_ref
    dv = v0 - v_ref0
    cos = dv @ dv_fine / (np.linalg.norm(dv) * np.linalg.norm(dv_fine))
    # measured: cosine 0.99997, size 0.978 of the coarse δV
    assert cos > 0.999 and 0.9 < np.linalg.norm(dv_fine) / np.linalg.norm(dv) < 1.1
    on_fine.morpher.free()
    same.morpher.free()
    np.testing.assert_array_equal(inst.readout.voltages(inst.morpher(inst.dome(u)), True), v0)


def test_the_grid_is_pressed_once_per_orbit_of_the_sensors_symmetries(paper_scene):
    """press_layout: the paper's ring (skip-8, central ground) keeps its 16 turns and mirrors
    with the protocol, so the 6 mm grid's rings take a multiple of 4 points and only one centre
    per orbit is pressed (4 of 21); every centre is its source's image by an isometry the sensor
    has; a protocol numbered across two rings (ring16_inner8's skip-8 over 16 + 8 electrodes) is
    not kept by the geometry's symmetries, and there every centre is pressed."""
    from jointsim.design.study import Plan, press_layout, press_symmetries

    lay = press_layout(paper_scene, Plan(spacing=6e-3))
    assert len(lay.grid) == 21 and len(lay.computed) == 4
    images = np.einsum("nij,nj->ni", lay.moves, lay.grid[lay.computed[lay.source]])
    np.testing.assert_allclose(images, lay.grid, rtol=0, atol=1e-13)  # m: the turns' rounding, composed
    mats = press_symmetries(paper_scene)
    assert len(mats) == 20  # turns by 180, 90, 45 and 22.5 degrees, 16 mirrors
    for m in lay.moves:  # a composition of the sensor's symmetries: orthogonal, one of the 32
        np.testing.assert_allclose(m @ m.T, np.eye(2), atol=1e-12)
    assert np.bincount(lay.source).tolist() == [1, 8, 4, 8]  # the axis, ring 1, ring 2 in two orbits
    plain = press_layout(paper_scene, Plan(spacing=6e-3, symmetric=False))
    assert len(plain.computed) == len(plain.grid) == 20
    inner = load_scene(SCENES_DIR / "ring16_inner8.toml")
    assert press_symmetries(inner) == [] and len(press_layout(inner, Plan(spacing=6e-3)).computed) == 20


def test_a_press_moved_by_a_symmetry_reads_its_frames_permuted(coarse):
    """A press turned by 90° about the axis, pressed directly, against the press it is an
    image of: its Jacobian is the first's with the channels moved by the ring symmetry and the
    x, y columns turned, to the test chamber's asymmetry (its mesh is not symmetric: measured
    1.7–2.8 % per column, 0.7 % in V), and its bounds, which the study copies, to 1.5 %
    (measured ≤ 0.9 %). Unmoved, the columns differ by more than half."""
    from jointsim.eit.protocol import ring_symmetries

    scene, inst = coarse
    p, a = np.array([5.54e-3, 2.3e-3]), np.pi / 2
    R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    presses, bounds = [], []
    for xy in (p, R @ p):
        ps = press_sensitivity(inst, _membrane(scene), xy, np.array([1e-3, 2e-3]))
        prior = nuisance_prior(scene, ps.names)
        presses.append(ps)
        for k in range(2):
            F = fisher(ps.jacobian_ref.T @ ps.jacobian_ref, ps.jacobian[k].T @ ps.jacobian[k], ps.noise_std, reference_frames=50)
            b = press_bounds(F, prior, ps.contact_jacobian[k])
            bounds.append([b.rms(kind)[q] for kind in ("known", "marginal") for q in ("contact", "depth", "diameter")])
    turn = next(s for s in ring_symmetries(inst.protocol) if s.turn == 4 and not s.mirror)
    J0, J1 = presses[0].jacobian[..., :4], presses[1].jacobian[..., :4]
    moved = turn.sign[:, None] * J0[:, turn.source]
    moved[..., :2] = moved[..., :2] @ R.T
    for c in range(4):
        err = np.linalg.norm(moved[..., c] - J1[..., c]) / np.linalg.norm(J1[..., c])
        assert err < 0.05, (TARGET[c], err)
        assert np.linalg.norm(J0[..., c] - J1[..., c]) > 0.5 * np.linalg.norm(J1[..., c])
    np.testing.assert_allclose(np.array(bounds[2:]), np.array(bounds[:2]), rtol=0.015)


def test_a_symmetric_studys_table_covers_the_whole_grid(coarse, tmp_path):
    """A study of the axis and one ring (8 centres, one orbit) presses twice; its table has a
    row per centre, the ring's rows the bounds of the press they are images of and its contact
    point turned with them; read as an older store without the symmetry, the same file would be
    refused (another study), not misread."""
    from jointsim.design import study

    scene, _ = coarse
    plan = study.Plan(diameters=(15e-3,), depths=(1.5e-3,), spacing=4e-3, r_max=4e-3)
    h5 = study.run_design(scene, plan, tmp_path / "s.h5", workers=1)
    b = study.design_bounds(h5, scene)
    assert len(study.plan_presses(scene, plan)) == 2 and len(b) == 9
    c = b.columns
    ring = slice(1, 9)
    angle = np.arctan2(c["y"][ring], c["x"][ring])
    np.testing.assert_allclose(np.diff(np.unwrap(angle)), np.pi / 4, atol=1e-12)  # 8 centres 45° apart
    # each contact point where its centre's is, turned or mirrored: the same angle off the
    # centre's, its sign flipped by a mirror
    off = np.arctan2(c["contact_y"][ring], c["contact_x"][ring]) - angle
    np.testing.assert_allclose(np.abs(off), abs(off[0]), atol=1e-12)
    np.testing.assert_allclose(c["contact_r"][ring], c["contact_r"][1], rtol=1e-12)
    for name in ("position_rms_marginal", "depth_median_known", "diameter_rms_marginal"):
        assert np.isfinite(c[name]).all()
        np.testing.assert_array_equal(c[name][ring], c[name][1])
    assert c["contact_r"][0] < 1e-4 < c["contact_r"][1]
    with pytest.raises(ValueError, match="other settings"):
        study.run_design(scene, replace(plan, symmetric=False), h5, workers=1)


def test_a_ring_is_solved_once_and_turned_to_each_centre(coarse, tmp_path):
    """ring_mechanics: the axis and a ring of 6 centres, each pressed (no symmetry), cost two
    mechanical solves; a ring centre's stored derivatives are those of its press solved afresh on
    the membrane turned with it (contact_membrane(turn=)): the same equilibria turned, so equal
    to the solver's tolerance (measured 1e-7; bar 1e-5 of each column's largest entry)."""
    from jointsim.design import study
    from jointsim.design.sensitivity import contact_membrane
    from jointsim.io.records import open_records

    scene, inst = coarse
    plan = study.Plan(diameters=(15e-3,), depths=(1.5e-3,), spacing=4e-3, r_max=4e-3, contact_levels=1, symmetric=False)
    assert plan.ring_mechanics and [len(g) for g in study.press_groups(scene, plan)] == [1, 6]
    assert not study.Plan(ray=True, contact_levels=1).ring_mechanics and not study.Plan().ring_mechanics
    rec = open_records(study.run_design(scene, plan, tmp_path / "s.h5", workers=1))
    xy = rec["xy"]
    j = 4  # a ring centre turned from the ring's first, xy[1]
    t = np.arctan2(xy[j, 1], xy[j, 0]) - np.arctan2(xy[1, 1], xy[1, 0])
    m = np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]])
    model = contact_membrane(scene, 7.5e-3, xy[1], 1.5e-3, 1, turn=m)
    ps = press_sensitivity(inst.on_membrane(model), model, xy[j], np.array([1.5e-3]))
    stored = rec["target_jacobian"][j]
    for q in range(4):
        assert np.abs(stored[..., q] - ps.jacobian[..., q]).max() <= 1e-5 * np.abs(ps.jacobian[..., q]).max()
    info = np.einsum("kmp,kmq->kpq", ps.jacobian, ps.jacobian)
    assert np.abs(rec["info"][j] - info).max() <= 1e-5 * np.abs(info).max()
    np.testing.assert_allclose(rec["contact"][j], ps.contact, atol=1e-9)


def test_a_press_read_together_shares_its_position_and_size():
    """press_fisher: K frames that share x, y, R and the nuisances, each with a depth of its own.
    One frame is fisher() itself; where no frame's voltages depend on its depth, the shared
    parameters' information is the frames' sum (the depths drop out); and a depth each costs
    the shared parameters something against one depth for all (the joint bound lies between
    the frames summed with their depths tied and the best single frame)."""
    from jointsim.design.bounds import joint_bounds, press_fisher

    rng = np.random.default_rng(7)
    P, K, M = 7, 3, 40
    J = rng.normal(size=(K, M, P))
    # each frame's depth column close to a multiple of its radius column (as a shallow press's
    # are), the multiple its own: tied, the depths would tell size apart; untied, less
    J[:, :, 2] = J[:, :, 3] * np.array([0.5, 1.0, 2.0])[:, None] + 0.05 * J[:, :, 2]
    J_ref = rng.normal(size=(M, P))
    J_ref[:, :4] = 0.0  # the target does not touch the reference
    infos = np.einsum("kmp,kmq->kpq", J, J)
    info_ref = J_ref.T @ J_ref
    F1 = press_fisher(info_ref, infos[:1], 0.5, reference_frames=10)
    np.testing.assert_allclose(F1, fisher(info_ref, infos[0], 0.5, reference_frames=10), rtol=1e-14)
    prior = np.concatenate([np.full(P - 4, 0.3), np.full(K - 1, np.inf)])
    G = np.eye(2, 4)
    # no depth information anywhere: the shared parameters' information sums
    flat = J.copy()
    flat[:, :, 2] = 0.0
    fi = np.einsum("kmp,kmq->kpq", flat, flat)
    Fj = press_fisher(info_ref, fi, 1.0, reference_frames=10)
    shared = [0, 1, 3]
    summed = fisher(info_ref, fi.sum(axis=0), 1.0, reference_frames=10)
    np.testing.assert_allclose(Fj[np.ix_(shared, shared)], summed[np.ix_(shared, shared)], rtol=1e-12)
    # the bounds: between the depths tied (one depth for all: more information) and one frame alone
    b = joint_bounds(press_fisher(info_ref, infos, 1.0, reference_frames=10), prior, G)
    tied = press_bounds(fisher(info_ref, infos.sum(axis=0), 1.0, reference_frames=10), prior[: P - 4], G)
    for k in range(K):
        one = press_bounds(fisher(info_ref, infos[k], 1.0, reference_frames=10), prior[: P - 4], G)
        for kind in ("known", "marginal"):
            assert b.rms(kind)["diameter"] <= one.rms(kind)["diameter"] * (1 + 1e-12)
    for kind in ("known", "marginal"):
        # strictly: these random frames tell their depths apart, and a depth each is three unknowns
        assert b.rms(kind)["diameter"] > 1.01 * tied.rms(kind)["diameter"]
        assert b.rms(kind)["position"] >= tied.rms(kind)["position"] * (1 - 1e-12)


def test_a_study_of_soft_targets_bounds_their_modulus(tmp_path):
    """design-study --target-moduli-kpa: one soft press (a 32-rim membrane, the test chamber),
    its modulus a fifth target parameter, stored with the press; the tables and the map carry
    the modulus. (Its derivative against re-solved equilibria: tests/test_soft_target.py.) The
    moduli and the head act on a depth-controlled press only as their ratios (every modulus × s
    is the head ÷ s), so ∂V/∂ln E + ∂V/∂ln p + ∂V/∂ln μ = 0: with a prior on the head and the
    membrane's modulus alone, the target's modulus is bounded at any SNR by what those priors
    leave, and the bound levels off as the SNR rises."""
    from jointsim.design.study import design_bounds
    from jointsim.io.records import open_records
    from jointsim.scene import load_scene

    toml = tmp_path / "soft.toml"
    toml.write_text(f'extends = "{SCENES_DIR / "paper_sensor.toml"}"\nname = "soft_dome"\n[membrane]\nrim_vertices = 32\nlayers = 1\n')
    out = tmp_path / "ds"
    assert main(["design-study", str(toml), "--mesh", "test", "--diameters-mm", "15", "--depths-mm", "1.5",
                 "--spacing-mm", "4", "--r-max-mm", "0", "--contact-levels", "0", "--target-moduli-kpa", "200",
                 "--workers", "1", "--out", str(out), "--no-progress"]) == 0
    text = (out / "summary.md").read_text()
    assert "## A soft target's Young's modulus" in text and "| soft_dome (E 200 kPa) | 74.2 | 1 |" in text
    assert "modulus_median_marginal" in (out / "soft_dome" / "bounds.csv").read_text().splitlines()[0]
    assert (out / "soft_dome" / "modulus_bound.png").exists()
    h5 = out / "soft_dome" / "sensitivities.h5"
    rec = open_records(h5)
    J, info = rec["target_jacobian"][0][0], rec["info"][0][0]
    assert rec["target_modulus"][0] == 2e5 and J.shape[-1] == 5
    names = tuple(rec.provenance["params"]["parameters"])
    e, p, mu = (names.index(n) for n in ("ln_target_modulus", "ln_pressure", "ln_modulus"))
    assert info[e, e] == pytest.approx(J[:, 4] @ J[:, 4], rel=1e-12) and info[e, e] > 0
    # the three columns sum to zero: their information matrix is singular along (1, 1, 1). Exactly
    # at equilibrium; the rest state stands within force_tol (1e-6·μt²: on the paper's cap 8.8e-8 N
    # against the head's 1.9e-3 N, 5e-5), which leaves ~5e-5 of a column along (1, 1, 1), ~3e-9 in the information
    one = np.zeros(len(names))
    one[[e, p, mu]] = 1.0
    assert abs(one @ info @ one) <= 1e-8 * info[e, e]
    # so as the SNR rises the bound falls to what the priors leave along that direction,
    # (1/s_p² + 1/s_μ²)^(-1/2), and never below it (on the axis, where E barely moves this
    # press: measured 81 at 74.2 dB, 2.7× the floor at 120 dB, 3 % above it at 140 dB)
    scene = load_scene(toml).with_mesh_preset("test")
    prior = dict(zip(names[5:], nuisance_prior(scene, names)))
    floor = (prior["ln_pressure"] ** -2 + prior["ln_modulus"] ** -2) ** -0.5
    b = [design_bounds(rec, scene, snr_db=snr).columns["modulus_rms_marginal"][0] for snr in (74.2, 140.0)]
    assert b[0] > b[1] >= floor and b[1] <= 1.1 * floor


def test_a_soft_study_meshes_its_spheres_graded_unless_told():
    """Plan.graded_target: a soft sphere read through a refined membrane is meshed graded by
    default; the flag means nothing (False) for rigid spheres or an unrefined membrane; a store
    written before the default changed (no key: layered) reads back as layered, and a layered
    plan stores no key, so such a store keeps its identity."""
    from types import SimpleNamespace

    from jointsim.design.study import Plan, stored_plan

    assert Plan(target_moduli=(3e5,), contact_levels=2).graded_target
    assert not Plan(target_moduli=(3e5,), contact_levels=2, graded_target=False).graded_target
    assert not Plan(contact_levels=2).graded_target and not Plan(target_moduli=(3e5,)).graded_target
    old = {"diameters": [15e-3], "depths": [1e-3], "spacing": 6e-3, "r_max": 12e-3, "contact_levels": 2,
           "target_moduli": [3e5], "ray": True}
    assert not stored_plan(SimpleNamespace(provenance={"params": {"plan": old}})).graded_target
    assert stored_plan(SimpleNamespace(provenance={"params": {"plan": {**old, "graded_target": True}}})).graded_target


def test_a_report_only_run_costs_what_the_store_s_run_did():
    """A design-study run that computes nothing reports the store's own wall time, from its
    creation to its finalisation (ISO times with their offsets)."""
    from jointsim.cli.design_study import store_wall

    run = {"created": "2026-11-28T08:30:00.209+00:00", "finalised": "2026-11-28T09:35:49.775+01:00"}
    assert store_wall(run) == pytest.approx(349.566, abs=1e-6)
