"""Electrodes on the membrane: placed on the chamber's dome, carried by the mechanics, their
complete-electrode-model integrals exact on the deformed patch (jointsim.mesh.electrodes)."""

from dataclasses import replace

import numpy as np
import pytest

from jointsim.mesh.electrodes import disc_patches, surface_disc_patch
from jointsim.mesh.shapes import box_mesh
from jointsim.mesh.tetmesh import TetMesh
from jointsim.scene import SCENES_DIR, SceneError, load_scene, scene_from_dict

R_EL = 1.6e-3
CENTRE = np.array([0.7e-3, -0.4e-3])


@pytest.fixture(scope="module")
def box():
    """A 10 × 10 × 4 mm box: its top face stands for a flat membrane."""
    return box_mesh((10e-3, 10e-3, 4e-3), (7, 7, 3), origin=(-5e-3, -5e-3, 0.0))


def assembled(patch, n: int) -> tuple[np.ndarray, np.ndarray]:
    """The patch's ∫φ_i dS (n,) and ∫φ_iφ_j dS (n, n) over the mesh's P1 basis."""
    b = np.zeros(n)
    np.add.at(b, patch.faces, patch.m1)
    M = np.zeros((n, n))
    np.add.at(M, (patch.faces[:, :, None], patch.faces[:, None, :]), patch.m2)
    return b, M


def assert_same_integrals(p, q, n: int) -> None:
    (b1, M1), (b2, M2) = assembled(p, n), assembled(q, n)
    np.testing.assert_allclose(b1, b2, rtol=0, atol=1e-12 * b1.max())
    np.testing.assert_allclose(M1, M2, rtol=0, atol=1e-12 * M1.max())


def test_on_a_flat_face_a_membrane_electrode_is_the_clipped_base_disc(box):
    """On the box's top face the tangent-plane clip is the plane clip of the base's discs: the
    same ∫φ and ∫φφ to round-off (the top mirrored onto z = 0 and clipped there)."""
    top = surface_disc_patch(box, CENTRE, R_EL)
    mirrored = TetMesh(np.column_stack([box.nodes[:, :2], 4e-3 - box.nodes[:, 2]]), box.tets).oriented()
    base = disc_patches(mirrored, np.array([[*CENTRE, 0.0]]), np.array([R_EL]), quadratic=True)[0]
    assert top.total_area == pytest.approx(np.pi * R_EL**2, rel=1e-12)
    assert_same_integrals(top, base, box.n_nodes)


@pytest.mark.parametrize("rigid", [False, True])
def test_a_rigid_motion_leaves_the_patch_as_it_was(box, rigid):
    """Turned and moved as a whole, the membrane carries its electrode unchanged: every face's
    P1 and P2 moments as before, to round-off (stretching and rigid alike)."""
    p = surface_disc_patch(box, CENTRE, R_EL, rigid=rigid)
    t = 0.4
    Q = np.array([[1.0, 0, 0], [0, np.cos(t), -np.sin(t)], [0, np.sin(t), np.cos(t)]])
    q = p.follow(box.nodes @ Q.T + [1e-3, 2e-3, -3e-3])
    for a, b in ((q.m1, p.m1), (q.m2, p.m2), (q.q1, p.q1), (q.q2, p.q2)):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-12 * np.abs(b).max())


def test_a_stretching_electrode_is_the_disc_the_membrane_stretched(box):
    """Scaled by s, a stretching patch is the disc of radius s·r placed on the scaled mesh (the
    same region of each face), area s²πr²; stretched ×2 along x (an affine map: the disc becomes
    an ellipse) its area is 2πr², exactly."""
    p = surface_disc_patch(box, CENTRE, R_EL)
    s = 1.3
    scaled = TetMesh(box.nodes * s, box.tets)
    assert_same_integrals(p.follow(scaled.nodes), surface_disc_patch(scaled, CENTRE * s, R_EL * s), box.n_nodes)
    stretched = p.follow(box.nodes * [2.0, 1.0, 1.0])
    assert stretched.total_area == pytest.approx(2 * np.pi * R_EL**2, rel=1e-12)
    assert stretched.follow(box.nodes).total_area == pytest.approx(np.pi * R_EL**2, rel=1e-12)  # and back


def test_a_rigid_electrode_keeps_its_disc_where_the_membrane_stretches(box):
    """Stretched ×2 along x, a rigid patch is the same disc of radius r at its carried centre
    (placed afresh there on the stretched mesh: the same integrals), area πr²; its faces (the
    CEM pattern) do not change."""
    p = surface_disc_patch(box, CENTRE, R_EL, rigid=True)
    moved = box.nodes * [2.0, 1.0, 1.0]
    q = p.follow(moved)
    assert np.array_equal(q.faces, p.faces) and q.total_area == pytest.approx(np.pi * R_EL**2, rel=1e-12)
    assert_same_integrals(q, surface_disc_patch(TetMesh(moved, box.tets), CENTRE * [2.0, 1.0], R_EL), box.n_nodes)


@pytest.fixture(scope="module")
def membrane16():
    s = load_scene(SCENES_DIR / "membrane16.toml").with_mesh_preset("test")
    return replace(s, membrane=replace(s.membrane, rim_vertices=32, layers=1), reconstruction=replace(s.reconstruction, cells=1000))


def test_the_scene_places_its_electrodes_on_the_dome(membrane16):
    """membrane16's 16 electrodes lie on the chamber's dome (its faces off the base) above the
    paper's ring, each πr²; the central ground on the base; the base triangulated without
    their outlines. At the dome's 16-fold symmetry their voltages at rest agree to the chamber
    mesh's noise (it is not symmetric), and the paper sensor's base ring gives the same
    order of standing voltage."""
    from jointsim.eit.forward import ForwardModel
    from jointsim.eit.protocol import scene_protocol
    from jointsim.mesh.chamber import chamber_mesh

    ch = chamber_mesh(membrane16)
    nodes = ch.mesh.nodes
    for p in ch.electrodes[:16]:
        assert p.carried is not None and p.total_area == pytest.approx(np.pi * 1e-6, rel=1e-12)
        assert nodes[p.faces][..., 2].min() > 3e-3  # on the dome, ~5 mm above the base there
        centre = (p.m1[..., None] * nodes[p.faces]).sum(axis=(0, 1)) / p.total_area
        assert np.hypot(*centre[:2]) == pytest.approx(15e-3, abs=0.1e-3)
    assert ch.electrodes[16].carried is None and np.abs(nodes[ch.electrodes[16].faces][..., 2]).max() == 0
    v = ForwardModel.from_chamber(ch, membrane16).voltages(0.37, scene_protocol(membrane16)).reshape(16, 16)
    # injection i, measurement of electrode i (the driven one) against the ground: by symmetry one value
    driven = v[np.arange(16), np.arange(16)]
    assert np.ptp(driven) / driven.mean() < 0.05


def test_a_remesh_carries_the_membrane_electrodes_over(membrane16):
    """A remeshed frame keeps the morph's dome faces, and the electrodes on them: the patches
    there have the morph's areas to round-off, and the frame's δV is the morph's to the
    remeshing floor of the test preset (measured with the paper sensor's base ring on the same
    press: 31–39 % of ‖δV‖, correlation above 0.9)."""
    from jointsim.instrument import Instrument
    from jointsim.mechanics.geometric import indent_dome
    from jointsim.mesh.morph import deform_chamber

    inst = Instrument.build(membrane16, imaging=False)
    try:
        dome = indent_dome(inst.reference_dome, (8e-3, 0.0), 2e-3, 7.5e-3).dome
        morph = deform_chamber(inst.morpher, dome, membrane16.mesh, "morph")
        remesh = deform_chamber(inst.morpher, dome, membrane16.mesh, "remesh")
        a = [p.total_area for p in inst.readout.model(morph.chamber, True).assembler.electrodes[:16]]
        b = [p.total_area for p in inst.readout.model(remesh.chamber, False).assembler.electrodes[:16]]
        np.testing.assert_allclose(b, a, rtol=1e-12)
        dv_m = inst.readout.change(morph) - inst.readout.v_ref
        dv_r = inst.readout.change(remesh) - inst.readout.v_ref
        assert np.linalg.norm(dv_r - dv_m) < 0.45 * np.linalg.norm(dv_m)
        assert np.corrcoef(dv_r, dv_m)[0, 1] > 0.9
    finally:
        inst.free()


@pytest.mark.parametrize("table, match", [
    ('[[electrodes.membrane]]\ncount = 64\npolar_angle_deg = 20\ndiameter_mm = 2.0',
     r"electrodes.membrane\[0\] electrode \d+ and electrodes.membrane\[0\] electrode \d+: overlap"),
    ('[[electrodes.membrane]]\ncount = 8\npolar_angle_deg = 60\ndiameter_mm = 2.0', r"electrodes.membrane\[0\].polar_angle_deg = 60"),
    ('[[electrodes.ring]]\ncount = 8\n[electrodes]\nmembrane_patch = "rigid"', r"electrodes.membrane_patch = 'rigid': only for electrodes on the membrane"),
    ('[[electrodes.membrane]]\ncount = 8\n[electrodes]\nmembrane_patch = "glued"', r"electrodes.membrane_patch = 'glued'"),
])
def test_bad_membrane_layouts_are_refused_naming_the_key(table, match):
    import tomllib

    data = tomllib.loads(table)
    data.setdefault("electrodes", {}).setdefault("reference", 0)
    data["electrodes"].setdefault("disc", [{"xy_mm": [0.0, 0.0], "diameter_mm": 4.0}])
    with pytest.raises(SceneError, match=match):
        scene_from_dict(data)


def test_the_jobs_run_with_electrodes_on_the_membrane(membrane16):
    """A dataset group (its driven electrodes jittered: those on the membrane moved in their footprint
    and placed on the dome again) and the protocol study run on membrane16; a press moves the
    electrodes on the membrane, so their δV is not zero, and a rigid patch reads the press
    otherwise than a stretching one."""
    from jointsim.dataset.generate import DatasetSetup
    from jointsim.instrument import deployed_chamber
    from jointsim.studies.protocol_study import StudyConfig, run_protocol_study

    setup = DatasetSetup(membrane16, deployed_chamber(membrane16), seed=1)
    try:
        records, _ = setup.group(0, 2)
    finally:
        setup.free()
    assert records[0]["electrode_jitter"].shape == (16, 2) and records[0]["dv"].shape == (256,)
    assert 0 < np.abs(records[0]["dv_clean"]).max() < np.abs(records[1]["dv_clean"]).max()
    cfg = StudyConfig(skips=(8,), positions=((0.0, 0.0),), noise_repeats=2, n_cells=1000, mesh_floor=False)
    stretch = run_protocol_study(membrane16, cfg).dv_clean[8]
    rigid = run_protocol_study(replace(membrane16, electrodes=replace(membrane16.electrodes, membrane_patch="rigid")), cfg).dv_clean[8]
    assert np.abs(stretch).max() > 0 and np.abs(rigid - stretch).max() > 1e-3 * np.abs(stretch).max()


def test_at_zero_deformation_membrane_electrodes_are_static_ones(membrane16):
    """The membrane at rest (the instrument's reference dome): the frame step through the
    electrodes it carries gives the reference voltages bit for bit, and the same as the
    reference chamber read through those patches held still (no carrying) to round-off."""
    from jointsim.eit.forward import ForwardModel
    from jointsim.instrument import Instrument

    inst = Instrument.build(membrane16, imaging=False)
    try:
        ro = inst.readout
        frame = inst.measure(inst.reference_dome, None, image=False)
        np.testing.assert_array_equal(frame.voltages_clean, ro.v_ref)
        still = [replace(p, carried=None) for p in inst.reference.patches(1)]
        v = ForwardModel(inst.reference.mesh, still, inst.reference.ground, ro.forward.z).voltages(ro.conductivity, ro.protocol)
        np.testing.assert_allclose(ro.v_ref, v, rtol=0, atol=1e-10 * np.abs(v).max())
    finally:
        inst.free()
