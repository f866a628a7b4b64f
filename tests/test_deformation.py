"""The geometric indentation of the dome and the fixed-topology (morphed) chamber mesh."""

import numpy as np
import pytest

from jointsim.geometry import DomeSurface, chamber_surface, spherical_cap
from jointsim.mechanics.geometric import indent_dome
from jointsim.mesh.morph import MeshInversionError, dome_nodes, morph_chamber


@pytest.fixture(scope="module")
def dome():
    return spherical_cap(0.02, 0.01, 96)


def test_on_axis_indentation_moves_the_apex_by_the_depth(dome):
    ind = indent_dome(dome, (0.0, 0.0), 2e-3, 7.5e-3, thickness=2e-3)
    apex = np.argmax(dome.vertices[:, 2])
    assert ind.dome.vertices[apex, 2] == pytest.approx(dome.vertices[apex, 2] - 2e-3, abs=1e-12)
    # nothing penetrates the target inflated by the membrane thickness
    d = np.linalg.norm(ind.dome.vertices - ind.centre, axis=1)
    assert d.min() >= 9.5e-3 * (1 - 1e-9)
    # the bonded rim does not move
    np.testing.assert_array_equal(ind.dome.vertices[dome.rim], dome.vertices[dome.rim])
    # the dent is centred on the axis
    np.testing.assert_allclose(ind.centroid[:2], 0.0, atol=1e-9)
    assert chamber_surface(ind.dome).is_watertight


def test_displaced_volume_grows_with_depth_and_size(dome):
    v = [indent_dome(dome, (0.004, 0.002), d, 5e-3).volume for d in (0.5e-3, 1e-3, 2e-3)]
    assert 0 < v[0] < v[1] < v[2]
    big = indent_dome(dome, (0.004, 0.002), 1e-3, 12e-3).volume
    assert big > v[1]
    # the displaced volume matches the chamber surfaces' volume difference
    ind = indent_dome(dome, (0.004, 0.002), 1e-3, 5e-3)
    dvol = chamber_surface(dome).volume - chamber_surface(ind.dome).volume
    assert ind.volume == pytest.approx(dvol, rel=1e-9)


def test_bad_indentations_are_rejected(dome):
    with pytest.raises(ValueError, match="misses the dome"):
        indent_dome(dome, (0.05, 0.0), 1e-3, 5e-3)
    with pytest.raises(ValueError, match="depth"):
        indent_dome(dome, (0.0, 0.0), 0.0, 5e-3)
    with pytest.raises(ValueError, match="depth"):
        indent_dome(dome, (0.0, 0.0), 9.5e-3, 5e-3)
    with pytest.raises(ValueError, match="radius"):
        indent_dome(dome, (0.0, 0.0), 1e-3, -5e-3)


def test_morphed_chamber_keeps_topology_base_and_electrodes(test_chamber, dome):
    scene, ch = test_chamber
    ind = indent_dome(dome, (0.003, -0.002), 1.5e-3, 7.5e-3)
    m = morph_chamber(ch, dome, ind.dome)
    np.testing.assert_array_equal(m.mesh.tets, ch.mesh.tets)
    base = np.abs(ch.mesh.nodes[:, 2]) < 1e-12
    np.testing.assert_array_equal(m.mesh.nodes[base], ch.mesh.nodes[base])
    assert m.electrodes is ch.electrodes
    # the mesh's volume change is the displaced saline volume (the dome is followed to
    # within fTetWild's envelope, ~1e-3 of the displaced volume here)
    dvol = ch.mesh.volumes.sum() - m.mesh.volumes.sum()
    assert dvol == pytest.approx(ind.volume, rel=0.01)
    # the dome nodes at the contact moved by about the depth
    top = dome_nodes(ch.mesh)
    assert np.abs(m.mesh.nodes[top] - ch.mesh.nodes[top]).max() == pytest.approx(1.5e-3, rel=0.05)


def test_morph_refuses_to_invert(test_chamber, dome):
    scene, ch = test_chamber
    v = dome.vertices.copy()
    v[:, 2] *= -0.5  # fold the dome through the base
    v[dome.rim, 2] = 0.0
    with pytest.raises(MeshInversionError, match="remesh"):
        morph_chamber(ch, dome, DomeSurface(v, dome.faces, dome.rim))
