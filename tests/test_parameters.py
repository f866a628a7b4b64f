"""The electrical parameter sensitivities (jointsim.eit.parameters) against re-solved central
differences on the box with disc electrodes of test_eit."""

import numpy as np
import pytest

from jointsim.eit.forward import ForwardModel
from jointsim.eit.parameters import (conductivity_sensitivity, contact_impedance_sensitivity,
                                     electrode_position_sensitivity, moved_discs, transfer_voltages)
from jointsim.eit.protocol import Protocol
from jointsim.mesh.electrodes import disc_patches
from jointsim.mesh.shapes import box_mesh

CENTRES = np.vstack([np.column_stack([6e-3 * np.cos(a), 6e-3 * np.sin(a), 0.0 * a]) for a in [np.pi / 2 * np.arange(4)]]
                    + [[[0.0, 0.0, 0.0]]])
RADII = np.array([2.5e-3] * 4 + [2e-3])
PROTOCOL = Protocol(np.eye(4) - np.roll(np.eye(4), 2, axis=1), np.eye(4) - np.roll(np.eye(4), 1, axis=1))


def _model(mesh, order, centres=CENTRES, z=None):
    z = np.array([1e-3, 2e-3, 0.5e-3, 1.5e-3, 1e-3]) if z is None else z
    return ForwardModel(mesh, disc_patches(mesh, centres, RADII, quadratic=order == 2), ground=4, contact_impedance=z,
                        order=order)


@pytest.fixture(scope="module", params=[1, 2], ids=["P1", "P2"])
def box(request):
    mesh = box_mesh((0.02, 0.02, 0.006), (10, 10, 3), origin=(-0.01, -0.01, 0.0))
    model = _model(mesh, request.param)
    return mesh, request.param, model, model.solve(0.37)


def test_transfer_voltages_are_the_protocol_of_the_transfer_matrix(box):
    _, _, _, f = box
    np.testing.assert_allclose(transfer_voltages(f.transfer, PROTOCOL), f.voltages(PROTOCOL), rtol=1e-12)


def test_contact_impedance_and_conductivity_sensitivities_match_resolved_differences(box):
    mesh, order, model, f = box
    dz = contact_impedance_sensitivity(f, PROTOCOL)
    scale = np.abs(f.voltages(PROTOCOL)).max()
    h = 1e-4
    for l in range(5):
        zp, zm = model.z.copy(), model.z.copy()
        zp[l] *= np.exp(h)
        zm[l] *= np.exp(-h)
        fd = (model.solve(0.37, zp).voltages(PROTOCOL) - model.solve(0.37, zm).voltages(PROTOCOL)) / (2 * h)
        # exact derivative against O(h²) = 1e-8 relative differences: agree to 1e-6 of the voltages
        np.testing.assert_allclose(dz[l], fd, atol=1e-6 * scale)
        assert np.abs(fd).max() > 1e-4 * scale  # each electrode's impedance is seen
    fd = (model.voltages(0.37 * np.exp(h), PROTOCOL) - model.voltages(0.37 * np.exp(-h), PROTOCOL)) / (2 * h)
    np.testing.assert_allclose(conductivity_sensitivity(f, PROTOCOL, dz), fd, atol=1e-6 * scale)


def test_electrode_position_sensitivity_matches_resolved_moved_discs(box):
    mesh, order, model, f = box
    dc = electrode_position_sensitivity(f, PROTOCOL, moved_discs(mesh, CENTRES, RADII, 1e-5, order == 2), 1e-5)
    scale = np.abs(dc).max()
    h = 2e-5
    for l, a in [(0, 0), (0, 1), (2, 1), (4, 0)]:
        cp, cm = CENTRES.copy(), CENTRES.copy()
        cp[l, a] += h
        cm[l, a] -= h
        fd = (_model(mesh, order, cp).voltages(0.37, PROTOCOL) - _model(mesh, order, cm).voltages(0.37, PROTOCOL)) / (2 * h)
        # a moved disc re-clips the faces it covers, so the moments are piecewise smooth in the
        # centre: both sides are differences over 10-20 µm; 1 % of the largest column is the bar
        np.testing.assert_allclose(dc[l, a], fd, atol=0.01 * scale)
    # by symmetry a ground at the centre moved along x changes what electrode 0 (on +x) sees
    assert np.abs(dc[4, 0]).max() > 0.01 * scale


def test_the_position_sensitivity_of_electrodes_on_the_membrane_follows_it():
    """Electrodes on the box's top (standing for the membrane), the box then stretched (the
    membrane deformed): ∂V/∂(x, y) of each electrode's footprint, from patches moved on the
    undeformed box and carried to the stretched one, against re-solved central differences of
    the same carried electrodes, within 1 % of the largest column (as for the base's discs)."""
    from jointsim.mesh.electrodes import place_discs
    from jointsim.mesh.tetmesh import TetMesh

    mesh = box_mesh((0.02, 0.02, 0.006), (10, 10, 3), origin=(-0.01, -0.01, 0.0))
    on = np.array([True] * 4 + [False])
    stretched = mesh.nodes * [1.2, 0.9, 1.1]  # an affine deformation: exact for the stretching patches
    deformed = TetMesh(stretched, mesh.tets)
    z = np.array([1e-3, 2e-3, 0.5e-3, 1.5e-3, 1e-3])

    def model(centres):
        patches = [p.follow(stretched) for p in place_discs(mesh, centres, RADII, on)]
        return ForwardModel(deformed, patches, ground=4, contact_impedance=z)

    f = model(CENTRES).solve(0.37)
    dc = electrode_position_sensitivity(f, PROTOCOL, moved_discs(mesh, CENTRES, RADII, 1e-5, False, on), 1e-5)
    scale = np.abs(dc).max()
    h = 2e-5
    for l, a in [(0, 0), (1, 1), (2, 0), (3, 1)]:
        cp, cm = CENTRES.copy(), CENTRES.copy()
        cp[l, a] += h
        cm[l, a] -= h
        fd = (model(cp).voltages(0.37, PROTOCOL) - model(cm).voltages(0.37, PROTOCOL)) / (2 * h)
        np.testing.assert_allclose(dc[l, a], fd, atol=0.01 * scale)
        assert np.abs(fd).max() > 0.05 * scale
