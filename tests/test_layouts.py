"""Electrode layouts as data (issue 44): scene generators ([[electrodes.ring|grid|disc]]), the
reference electrode or none, and protocols on any layout."""

import math
from dataclasses import replace

import numpy as np
import pytest

from conftest import PAPER_SCENE

from jointsim.eit.forward import ForwardModel
from jointsim.eit.protocol import Protocol, scene_protocol, skip_protocol
from jointsim.geometry import electrode_layout
from jointsim.scene import EDGE_CLEARANCE_MM, SceneError, load_scene, scene_from_dict


def _scene(electrodes: dict, drive: dict | None = None):
    return scene_from_dict({"electrodes": electrodes, **({"drive": drive} if drive else {})})


RING_AND_INNER = {
    "reference": 24,
    "ring": [{"count": 16, "radius_mm": 15.0, "diameter_mm": 2.0}, {"count": 8, "radius_mm": 7.5, "diameter_mm": 2.0, "phase_deg": 22.5}],
    "disc": [{"xy_mm": [0.0, 0.0], "diameter_mm": 4.0}],
}


def test_the_papers_ring_given_as_data_is_the_papers_ring(paper_scene):
    s = _scene({"reference": 16, "ring": [{"count": 16, "radius_mm": 15.0, "diameter_mm": 2.0}],
                "disc": [{"xy_mm": [0.0, 0.0], "diameter_mm": 4.0}]})
    a, b = electrode_layout(s), electrode_layout(paper_scene)
    np.testing.assert_allclose(a.centres, b.centres, rtol=0, atol=1e-15)
    np.testing.assert_array_equal(a.radii, b.radii)
    assert a.ground == b.ground == 16 and s.electrodes.count == 16 and not s.electrodes.is_ring
    assert scene_protocol(s).n_meas == scene_protocol(paper_scene).n_meas == 256


def test_generators_make_their_electrodes_in_order_with_the_reference_last():
    s = _scene({**RING_AND_INNER, "reference": 0})  # a ring electrode as the reference
    lay = electrode_layout(s)
    assert s.electrodes.count == 24 and lay.n_electrodes == 25 and lay.ground == 24
    # electrode 0 of the outer ring (at +x) moved last; the rest keep their order
    np.testing.assert_allclose(lay.centres[-1], [15e-3, 0, 0], atol=1e-15)
    np.testing.assert_allclose(lay.centres[15], [7.5e-3 * math.cos(math.pi / 8), 7.5e-3 * math.sin(math.pi / 8), 0], atol=1e-15)
    np.testing.assert_allclose(lay.centres[23], [0, 0, 0], atol=1e-15)
    assert lay.radii[23] == pytest.approx(2e-3)
    square = _scene({"reference": "none", "grid": [{"pitch_mm": 6.0, "diameter_mm": 2.0, "within_mm": 17.0}]})
    assert len(square.electrodes.discs) == 25 and not square.electrodes.reference
    assert square.drive.measure == "adjacent"  # no reference to measure against
    hexa = _scene({"reference": 0, "grid": [{"pitch_mm": 5.0, "diameter_mm": 1.5, "kind": "hex", "within_mm": 10.0}]})
    xy = np.array(hexa.electrodes.discs)[:, :2]
    # a hexagonal grid: every electrode's nearest neighbours at one pitch, six of them inside
    d = np.hypot(*(xy[:, None] - xy[None]).transpose(2, 0, 1))
    np.fill_diagonal(d, np.inf)
    assert d.min() == pytest.approx(5e-3) and ((np.abs(d - 5e-3) < 1e-9).sum(axis=1).max() == 6)
    assert np.hypot(*xy.T).max() <= 10e-3 + 1e-12


@pytest.mark.parametrize("electrodes, match", [
    ({"reference": 0, "disc": [{"xy_mm": [0, 0], "diameter_mm": 4}, {"xy_mm": [2.5, 0], "diameter_mm": 2}, {"xy_mm": [9, 0]}]},
     r"electrodes.disc\[0\] electrode 0 and electrodes.disc\[1\] electrode 0: overlap"),
    ({"reference": 0, "ring": [{"count": 8, "radius_mm": 19.2, "diameter_mm": 2}]},
     rf"electrodes.ring\[0\] electrode 0: .* reaches 20.2 mm .* end {EDGE_CLEARANCE_MM:g} mm inside the base radius 20 mm"),
    ({"reference": 3, "ring": [{"count": 3, "radius_mm": 10}]}, r"electrodes.reference = 3: the index"),
    ({"ring": [{"count": 3, "radius_mm": 10}]}, r"electrodes.reference = None"),
    ({"reference": 0, "count": 16, "ring": [{"count": 3, "radius_mm": 10}]}, r"electrodes.count: describes the paper's ring"),
    ({"reference": 0, "ring": [{"count": 3, "radius_mm": 10, "colour": "red"}]}, r"unknown key\(s\) in \[electrodes.ring\[0\]\]: colour"),
    ({"reference": 0, "ring": [{"count": 1, "radius_mm": 10}]}, r"make 1 electrodes; a layout has 2 to"),
    ({"reference": 0, "ring": [{"count": 2, "radius_mm": 10}]}, r"\[drive\]: 1 driven electrode: give the protocol as data"),
    ({"reference": 0, "grid": [{"pitch_mm": 1.9, "diameter_mm": 2.0, "within_mm": 5}]}, r"electrodes.grid\[0\] electrode \d+ and .* overlap"),
    ({"reference": 0, "grid": [{"pitch_mm": 1.0, "diameter_mm": 0.5}]}, r"the generators make 1\d\d\d electrodes; a layout has 2 to 129"),
])
def test_a_bad_layout_is_refused_naming_the_electrode(electrodes, match):
    with pytest.raises(SceneError, match=match):
        _scene(electrodes)


def test_the_papers_ring_keeps_clear_of_the_rim_too():
    with pytest.raises(SceneError, match=r"electrodes.ring_radius_mm = 18.95: must be in \(3, 18.5\]"):
        _scene({"ring_radius_mm": 18.95})
    with pytest.raises(SceneError, match=r"drive.measure = 'reference': the layout has no reference"):
        _scene({"reference": "none", "ring": [{"count": 8, "radius_mm": 10}]}, {"measure": "reference", "skip": 2})
    with pytest.raises(SceneError, match=r"drive.skip = 8: must be an integer in \[0, 4\] for 8 driven electrodes"):
        _scene({"reference": 0, "ring": [{"count": 9, "radius_mm": 10}]}, {"skip": 8})
    assert _scene({"reference": 0, "ring": [{"count": 9, "radius_mm": 10}]}).drive.skip == 4  # opposite, by default


def test_a_layout_extends_the_papers_scene_replacing_its_ring(tmp_path):
    (tmp_path / "s.toml").write_text('extends = "paper_sensor"\n[electrodes]\nreference = 8\n[drive]\nskip = 3\n'
                                     '[[electrodes.ring]]\ncount = 8\nradius_mm = 12.0\n[[electrodes.disc]]\nxy_mm = [0.0, 0.0]\n')
    s = load_scene(tmp_path / "s.toml")
    assert s.electrodes.count == 8 and len(s.electrodes.discs) == 9 and s.chamber == load_scene(PAPER_SCENE).chamber
    assert scene_protocol(s).n_meas == 64


def test_a_floating_reference_reads_the_same_whichever_electrode_the_solver_grounds(test_chamber):
    """With no passive reference, injections and differential measurements over all 17 of the
    test chamber's electrodes are exact whichever electrode the solver grounds: the same
    voltages with the centre disc grounded and with ring electrode 5 grounded instead."""
    scene, ch = test_chamber
    n = 17
    full = skip_protocol(n, 3, 1e-4, "adjacent")  # patterns over every electrode
    z = np.full(n, 1e-3)
    sigma = scene.saline.conductivity
    # the chamber's own order: the centre disc last, grounded
    a = ForwardModel(ch.mesh, ch.electrodes, ch.ground, z).solve(sigma).voltages(full.floating())
    # electrode 5 last and grounded: the patterns' columns permuted alike
    order = [i for i in range(n) if i != 5] + [5]
    b_protocol = Protocol(full.stim[:, order], full.meas[:, :, order]).floating()
    b = ForwardModel(ch.mesh, [ch.electrodes[i] for i in order], n - 1, z).solve(sigma).voltages(b_protocol)
    np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-12 * np.abs(a).max())
    with pytest.raises(ValueError, match="sum to zero"):
        skip_protocol(n, 3, 1e-4, "ground").floating()


def test_a_layout_runs_through_the_instrument(test_chamber):
    """16 ring + 8 inner electrodes, meshed and read at rest: 24 lead fields, 576 measurements,
    the inner electrodes as electrodes (current conservation: each injection's currents return
    through the reference)."""
    from jointsim.instrument import Instrument

    paper, _ = test_chamber
    s = replace(_scene(RING_AND_INNER), mesh=paper.mesh, membrane=replace(paper.membrane, rim_vertices=32, layers=1))
    inst = Instrument.build(s, imaging=False)
    try:
        assert inst.readout.n_meas == 576 and inst.readout.forward.n_driven == 24
        r = inst.measure(inst.reference_dome, None)
        assert np.isfinite(r.voltages_clean).all() and not r.dv_clean.any()
        # 8-fold symmetry of the layout: a turn by 45° maps outer electrode k to k + 2 and inner k
        # to k + 1; injection 0 (outer 0 → outer 9) and injection 2 (outer 2 → outer 11) read
        # the same voltages, turned, to the mesh's asymmetry
        V = r.voltages_clean.reshape(24, 24)
        turn = np.r_[(np.arange(16) + 2) % 16, 16 + (np.arange(8) + 1) % 8]
        np.testing.assert_allclose(V[2][turn], V[0], rtol=0, atol=0.02 * np.abs(V[0]).max())
    finally:
        inst.free()


@pytest.mark.parametrize("name", ["paper_sensor", "paper_sensor_stiffness", "ring16_inner8", "grid5x5", "membrane16",
                                  "small_dome8", "elongated_pad"])
def test_every_shipped_scene_loads_and_reads_back_from_its_provenance_text(name):
    import tomllib

    from jointsim.scene import SCENES_DIR, scene_toml, shipped_scenes

    assert name in shipped_scenes()
    s = load_scene(SCENES_DIR / f"{name}.toml")
    assert scene_from_dict(tomllib.loads(scene_toml(SCENES_DIR / f"{name}.toml")), name) == s
    n_driven = s.electrodes.count + (0 if s.electrodes.reference else 1)
    p = scene_protocol(s)
    assert p.n_stim == n_driven and p.n_meas == n_driven * n_driven and p.n_el == s.electrodes.count


def test_a_protocol_given_as_data_is_that_protocol(tmp_path):
    """[drive] stim_ua and meas, EIDORS's patterns: the paper's skip-8 written out is skip-8; an
    opposite-injection, adjacent-measurement protocol on a floating 8-electrode ring is reduced
    exactly; malformed patterns are refused naming the key."""
    p8 = skip_protocol(16, 8, 120e-6)
    written = _scene({}, {"stim_ua": (p8.stim * 1e6).tolist(), "meas": np.eye(16).tolist()})
    got = scene_protocol(written)
    np.testing.assert_allclose(got.stim, p8.stim, rtol=1e-12, atol=0)
    np.testing.assert_array_equal(got.meas, p8.meas)
    ring8 = {"reference": "none", "ring": [{"count": 8, "radius_mm": 12.0}]}
    opp = skip_protocol(8, 3, 1e-4, "adjacent")  # injection i: i against i + 4
    s = _scene(ring8, {"stim_ua": (opp.stim * 1e6).tolist(), "meas": opp.meas[0].tolist()})
    assert scene_protocol(s).n_el == 7 and scene_protocol(s).n_meas == 64
    bad = [({"stim_ua": [[100, 0, 0, 0, 0, 0, 0, 0]], "meas": opp.meas[0].tolist()}, r"drive.stim_ua\[0\]: .* sum to zero"),
           ({"stim_ua": (opp.stim * 1e6).tolist(), "meas": np.eye(8).tolist()}, r"drive.meas: .* sum to zero"),
           ({"stim_ua": [[100, -100]], "meas": [[1, -1]]}, r"drive.stim_ua: must be \(n_stim, 8\)"),
           ({"stim_ua": (opp.stim * 1e6).tolist()}, r"needs both stim_ua"),
           ({"stim_ua": (opp.stim * 1e6).tolist(), "meas": opp.meas[0].tolist(), "skip": 2}, r"drive.skip: give skip and measure, or")]
    for drive, match in bad:
        with pytest.raises(SceneError, match=match):
            _scene(ring8, drive)
    # given in a scene that extends one with skip-N, the patterns replace it
    (tmp_path / "p.toml").write_text('extends = "paper_sensor"\n[drive]\nstim_ua = ' + str((p8.stim * 1e6).tolist())
                                     + '\nmeas = ' + str(np.eye(16).tolist()) + '\n')
    np.testing.assert_allclose(scene_protocol(load_scene(tmp_path / "p.toml")).stim, p8.stim, rtol=1e-12)


@pytest.fixture(scope="module")
def inner8(paper_scene):
    from jointsim.scene import SCENES_DIR

    s = load_scene(SCENES_DIR / "ring16_inner8.toml").with_mesh_preset("test")
    return replace(s, membrane=replace(s.membrane, rim_vertices=32, layers=1),
                   reconstruction=replace(s.reconstruction, cells=1000))


def test_the_jobs_run_on_a_layout_given_as_data(inner8):
    """A dataset group and the protocol study on 16 ring + 8 internal electrodes: 24 electrodes
    moved per draw, 576 measurements per sample, one study row per skip asked for; the internal
    electrodes see the press (their rows of δV are not zero)."""
    from jointsim.dataset.generate import DatasetSetup
    from jointsim.instrument import deployed_chamber
    from jointsim.studies.protocol_study import StudyConfig, run_protocol_study

    setup = DatasetSetup(inner8, deployed_chamber(inner8), seed=1)
    try:
        records, _ = setup.group(0, 2)
    finally:
        setup.free()
    assert records[0]["electrode_jitter"].shape == (24, 2) and records[0]["dv"].shape == (576,)
    assert 0 < records[0]["displaced_volume"] < records[1]["displaced_volume"]
    cfg = StudyConfig(skips=(0, 8), positions=((0.0, 0.0), (5e-3, 0.0)), noise_repeats=2, n_cells=1000, mesh_floor=False)
    result = run_protocol_study(inner8, cfg)
    assert [r["skip"] for r in result.table()] == [0, 8] and result.dv_clean[8].shape == (2, 576)
    inner_rows = result.dv_clean[8].reshape(2, 24, 24)[:, :, 16:]  # every injection, the 8 internal electrodes
    assert np.abs(inner_rows).max() > 0.05 * np.abs(result.dv_clean[8]).max()
    with pytest.raises(ValueError, match=r"skips = \[13\]: each must be in \[0, 12\] for 24 driven electrodes"):
        run_protocol_study(inner8, replace(cfg, skips=(13,)))


def test_stores_record_the_patterns_and_the_channel_order(paper_scene):
    """A palpation's and a dataset's identity hold the stimulation and measurement patterns they
    measured with, and how the voltages are laid out; read back they are the protocol."""
    from jointsim.dataset.generate import dataset_params
    from jointsim.eit.protocol import CHANNEL_ORDER
    from jointsim.palpation import program_params

    grid = load_scene(__import__("jointsim.scene", fromlist=["SCENES_DIR"]).SCENES_DIR / "grid5x5.toml")
    for scene in (paper_scene, grid):
        want = scene_protocol(scene)
        for rec in (program_params(scene)["protocol"], dataset_params(scene, 6, "")["protocol"]):
            got = Protocol(np.array(rec["stim_A"]), np.array(rec["meas"]))
            np.testing.assert_array_equal(got.stim, want.stim)
            np.testing.assert_array_equal(got.meas, want.meas)
            assert rec["channels"] == CHANNEL_ORDER


def test_patterns_read_from_a_file_are_the_inline_ones(tmp_path):
    """[drive] patterns_file: an .npz (stim_ua or stim_A, meas) and an EIDORS-style .mat (as
    jointsim forward writes its fwd_model.stimulation) give the protocol the same patterns
    inline give; a missing file or another kind is one error naming the key."""
    from scipy.io import savemat

    p8 = skip_protocol(16, 9, 120e-6)  # not the paper's skip: the file decides
    np.savez(tmp_path / "p.npz", stim_A=p8.stim, meas=p8.meas)
    # as io.export.write_mat lays out fwd_model.stimulation (one column pattern per injection)
    st = np.zeros(p8.n_stim, dtype=[("stim_pattern", object), ("meas_pattern", object)])
    for k in range(p8.n_stim):
        st[k] = (p8.stim[k][:, None], p8.meas[k])
    savemat(tmp_path / "p.mat", {"fwd_model": {"stimulation": st}})
    for name in ("p.npz", "p.mat"):
        (tmp_path / "s.toml").write_text(f'extends = "paper_sensor"\n[drive]\npatterns_file = "{name}"\n')
        got = scene_protocol(load_scene(tmp_path / "s.toml"))
        np.testing.assert_allclose(got.stim, p8.stim, rtol=1e-12, atol=0)
        np.testing.assert_array_equal(got.meas, p8.meas)
    for text, match in (('patterns_file = "none.npz"', r"drive.patterns_file = 'none.npz': no such file"),
                        ('patterns_file = "s.toml"', r"drive.patterns_file = 's.toml': an .npz")):
        (tmp_path / "bad.toml").write_text(f'extends = "paper_sensor"\n[drive]\n{text}\n')
        with pytest.raises(SceneError, match=match):
            load_scene(tmp_path / "bad.toml")


def test_a_smaller_dome_with_eight_electrodes_reads_a_press():
    """small_dome8 (half the paper's dome, 8 electrodes, skip-4): the instrument builds at the test
    preset, its 64 standing voltages keep the ring's 8-fold symmetry to the mesh's noise
    (injection i measured at electrode k against injection i + 1 at k + 1, within 3 % of the
    largest |V|: the test chamber's one-pitch residual, 1.8 % here, sits on the driven
    electrodes, as on the paper's chamber), and a press reads as a change that grows with depth."""
    from jointsim.instrument import Instrument
    from jointsim.mechanics.geometric import indent_dome
    from jointsim.scene import SCENES_DIR

    s = load_scene(SCENES_DIR / "small_dome8.toml").with_mesh_preset("test")
    s = replace(s, membrane=replace(s.membrane, rim_vertices=32, layers=1))
    inst = Instrument.build(s, imaging=False)
    try:
        v = inst.readout.v_ref.reshape(8, 8)
        assert v.shape == (8, 8) and inst.reference.mesh.nodes[:, 0].max() == pytest.approx(10e-3, rel=1e-6)
        turned = np.roll(np.roll(v, -1, axis=0), -1, axis=1)
        assert np.abs(turned - v).max() < 0.03 * np.abs(v).max()
        dv = [np.linalg.norm(inst.measure(indent_dome(inst.reference_dome, (2e-3, 0.0), d, 4e-3).dome, None, image=False).dv_clean)
              for d in (0.5e-3, 1e-3)]
        assert 0 < dv[0] < dv[1]
    finally:
        inst.free()


def test_the_symmetries_of_a_design_are_found_from_its_layout_and_chamber():
    """jointsim.geometry.symmetries: the paper's ring has the 16 mirrors and the turns by
    360°/k for k | 16 (22.5° moving electrode i to i + 1), the ground kept; the pad only its two
    mirrors and the half turn; the floating grid only the mirror that keeps its last electrode
    (the solver's reference) where it is."""
    from jointsim.geometry import electrode_layout, symmetries
    from jointsim.scene import SCENES_DIR

    paper = load_scene(SCENES_DIR / "paper_sensor.toml")
    sym = symmetries(electrode_layout(paper), paper.chamber)
    assert {k for k in sym if k.startswith("turn")} == {"turn 180 deg", "turn 90 deg", "turn 45 deg", "turn 22.5 deg"}
    assert sum(k.startswith("mirror") for k in sym) == 16
    np.testing.assert_array_equal(sym["turn 22.5 deg"], np.append((np.arange(16) + 1) % 16, 16))
    pad = load_scene(SCENES_DIR / "elongated_pad.toml")
    assert set(symmetries(electrode_layout(pad), pad.chamber)) == {"turn 180 deg", "mirror 0 deg", "mirror 90 deg"}
    grid = load_scene(SCENES_DIR / "grid5x5.toml")
    layout = electrode_layout(grid)
    for P in symmetries(layout, grid.chamber).values():
        assert P[layout.ground] == layout.ground
