"""The instrument (jointsim.instrument): the measurement chain built once and the one frame step
every job measures through. At the test chamber resolution with a coarse membrane (32 rim
vertices, one layer of wedges)."""

from dataclasses import replace

import numpy as np
import pytest

from jointsim.eit.forward import ForwardModel
from jointsim.eit.protocol import skip_protocol
from jointsim.instrument import Instrument, Readout, stream
from jointsim.mechanics.geometric import indent_dome


@pytest.fixture(scope="module")
def inst(test_chamber):
    scene, chamber = test_chamber
    scene = replace(scene, membrane=replace(scene.membrane, rim_vertices=32, layers=1),
                    reconstruction=replace(scene.reconstruction, cells=1000))
    i = Instrument.build(scene, chamber=chamber)
    yield i
    i.free()


def _dent(inst, xy=(3e-3, 1e-3), depth=1.5e-3):
    return indent_dome(inst.reference_dome, xy, depth, 7.5e-3, inst.scene.chamber.membrane_thickness).dome


def test_the_untouched_sensor_reads_its_reference_exactly(inst):
    """At rest the frame step morphs the reference mesh onto itself (bit for bit), so the clean
    change is exactly zero and the measured one is the noise of the frame and of the averaged
    reference alone."""
    r = inst.measure(inst.reference_dome, None)
    assert r.chamber.path == "morph"
    np.testing.assert_array_equal(r.chamber.chamber.mesh.nodes, inst.reference.mesh.nodes)
    np.testing.assert_array_equal(r.voltages_clean, inst.readout.v_ref)
    assert not r.dv_clean.any()
    noisy = np.array([inst.measure(inst.reference_dome, stream(0, "frame", k), last=r).dv for k in range(200)])
    assert noisy.std() == pytest.approx(inst.readout.dv_noise_std, rel=0.05)  # 51,200 draws: ±0.3 % (1 sd)


def test_a_frame_is_the_forward_model_of_the_deformed_chamber(inst):
    """The frame step's clean voltages are the CEM forward model solved afresh on the chamber it
    deformed, and its image is the reconstruction matrix applied to its δV."""
    dome = _dent(inst)
    r = inst.measure(dome, stream(0, "frame", 1))
    ro = inst.readout
    fresh = ForwardModel(r.chamber.chamber.mesh, list(ro.patches), inst.reference.ground, ro.forward.z)
    v = fresh.solve(ro.conductivity).voltages(ro.protocol)
    np.testing.assert_allclose(r.voltages_clean, v, rtol=1e-9, atol=1e-12 * np.abs(v).max())
    np.testing.assert_array_equal(r.dv, r.voltages - ro.v_ref_measured)
    np.testing.assert_allclose(r.image, inst.imager.reconstructor.R @ r.dv, rtol=1e-12, atol=0)
    assert r.metrics is not None and np.isnan(r.true_centre).all()  # no truth asked for


def test_a_hold_reuses_the_chamber_and_draws_only_the_noise(inst):
    dome = _dent(inst)
    a = inst.measure(dome, stream(0, "frame", 1))
    b = inst.measure(dome, stream(0, "frame", 2), last=a)
    assert b.chamber is a.chamber
    np.testing.assert_array_equal(b.voltages_clean, a.voltages_clean)
    assert not np.array_equal(b.voltages, a.voltages)


def test_readouts_of_several_protocols_share_one_solve(inst, monkeypatch):
    """The protocol study reads every skip-N of a frame: one factorisation serves them all, and
    each protocol's voltages are its own."""
    n = inst.scene.electrodes.count
    readouts = [inst.readout.with_protocol(skip_protocol(n, s, inst.scene.drive.current)) for s in (0, 4, 8)]
    dc = inst.deform(_dent(inst))
    solves = []
    real = ForwardModel.solve
    monkeypatch.setattr(ForwardModel, "solve", lambda self, *a, **k: solves.append(1) or real(self, *a, **k))
    volts = [r.change(dc) for r in readouts]
    assert len(solves) == 1
    fields = inst.readout.fields(dc.chamber, True)
    for r, v in zip(readouts, volts):
        np.testing.assert_array_equal(v, fields.voltages(r.protocol))
    assert not np.allclose(volts[0], volts[2])


def test_a_randomised_readout_with_nothing_randomised_is_the_nominal_one(inst):
    """A dataset's readout clips its (moved) electrode discs itself; moved by zero, with the
    scene's contact impedance and saline, it reads what the instrument reads."""
    e = inst.scene.electrodes
    assert len(set(e.contact_impedance) | {e.ground_contact_impedance}) == 1
    ro = Readout.on(inst.reference, inst.scene, inst.protocol, rng=None, reference_frames=50,
                    contact_impedance=e.ground_contact_impedance, offsets=np.zeros((e.count, 2)))
    try:
        np.testing.assert_allclose(ro.v_ref, inst.readout.v_ref, rtol=1e-12, atol=1e-15)
        dc = inst.deform(_dent(inst))
        np.testing.assert_allclose(ro.change(dc), inst.readout.change(dc), rtol=1e-12, atol=1e-15)
        # an electrode moved by 0.1 mm changes the reading
        moved = Readout.on(inst.reference, inst.scene, inst.protocol, rng=None, reference_frames=50,
                           offsets=np.vstack([[1e-4, 0.0], np.zeros((e.count - 1, 2))]))
        assert np.abs(moved.v_ref - ro.v_ref).max() > 1e-4 * np.abs(ro.v_ref).max()
        moved.free()
    finally:
        ro.free()


def test_lambda_is_chosen_on_the_scenes_representative_press(inst):
    r = inst.scene.reconstruction
    assert inst.lambda_press == pytest.approx({"radius": r.lambda_radius, "depth": r.lambda_depth, "x": 0.0, "y": 0.0})
    assert inst.imager.grid.n_cells == pytest.approx(1000, rel=0.1)


@pytest.mark.parametrize("xy", [(0.0, 0.0), (6e-3, 0.0), (-8.5e-3, 8.5e-3)])
def test_the_dents_centroid_is_the_displaced_saline_where_nothing_bulges(inst, xy):
    """A geometric indentation moves the surface in only (the rest follows a Laplacian, the rim
    fixed): there the dent's centroid is the exact centroid of the saline lost (the cones'
    moments, jointsim.mechanics.geometric.displaced_volume), to 50 µm (measured ≤ 11 µm: the
    swept prisms' first-order volume against the exact cones)."""
    from jointsim.instrument import dent_centroid
    from jointsim.mechanics.geometric import displaced_volume

    ind = indent_dome(inst.reference_dome, xy, 1.5e-3, 7.5e-3, inst.scene.chamber.membrane_thickness)
    np.testing.assert_allclose(dent_centroid(inst.reference_dome, ind.dome), displaced_volume(inst.reference_dome, ind.dome)[1],
                               atol=50e-6)
    assert np.isnan(dent_centroid(inst.reference_dome, inst.reference_dome)).all()


def test_the_dents_centroid_of_an_off_axis_press_lies_under_the_contact(inst):
    """A 15 mm sphere pressed 3 mm at 12 mm off the axis raises bulges about its dent; the net
    saline lost then has its centroid 15 mm out (measured; outside the dent), the dent's centroid
    lies inside the chamber under the contact: in-plane within 1 mm of the centre of pressure
    (measured 0.46 mm), below it."""
    from jointsim.instrument import dent_centroid
    from jointsim.mechanics.build import membrane_from_scene

    scene = inst.scene
    m = membrane_from_scene(replace(scene, target=replace(scene.target, kind="rigid")), target_radius=7.5e-3)
    z0 = m.first_contact_height(np.array([12e-3, 0.0]))
    for s in range(1, 7):
        st = m.press(np.array([12e-3, 0.0, z0 - 0.5e-3 * s]))
    c = dent_centroid(inst.reference_dome, inst.dome(m.u))
    assert np.hypot(*c[:2]) < scene.chamber.base_radius and 0 < c[2] < st.contact_centre[2]
    assert np.linalg.norm(c[:2] - st.contact_centre[:2]) < 1e-3
