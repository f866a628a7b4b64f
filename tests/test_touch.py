"""Where a sphere coming down touches the membrane (jointsim.mechanics.touch): the smooth
surface's fit on an exact sphere, and on the paper's inflated dome (32 rim vertices, one layer)
the centre that touches at a point against the faceted first contact, its inverse, and the
depth the dome allows there against the press's own refusal."""

from dataclasses import replace

import numpy as np
import pytest

from jointsim.mechanics.build import membrane_from_scene
from jointsim.mechanics.dome import UnreachablePose
from jointsim.mechanics.touch import centre_touching, depth_reach, outer_points, point_touched, surface_fit


def test_the_cubic_fits_a_spheres_height_and_slope():
    """A sphere of radius 25 mm sampled like a membrane's surface (1 mm apart, 3 mm about the
    point, 7 mm off the axis): the analytic slope −x/√(ρ² − r²) to 0.1 %, the height to 1 µm."""
    rho = 25e-3
    g = np.arange(-3, 3.01, 1.0) * 1e-3
    at = np.array([6e-3, -4e-3])
    X, Y = np.meshgrid(at[0] + g, at[1] + g)
    Z = np.sqrt(rho**2 - X**2 - Y**2)
    height, slope = surface_fit(np.column_stack([X.ravel(), Y.ravel(), Z.ravel()]), at)
    exact = -at / np.sqrt(rho**2 - at @ at)
    np.testing.assert_allclose(slope, exact, rtol=1e-3)
    assert height == pytest.approx(np.sqrt(rho**2 - at @ at), abs=1e-6)


@pytest.fixture(scope="module")
def dome(paper_scene):
    scene = paper_scene.with_mesh_preset("test")
    scene = replace(scene, membrane=replace(scene.membrane, rim_vertices=32, layers=1),
                    target=replace(scene.target, kind="rigid"))
    return membrane_from_scene(scene, target_radius=7.5e-3)


@pytest.mark.parametrize("point_mm", [(0.0, 0.0), (6.0, -4.0), (-10.0, 3.0), (0.0, 15.0)])
def test_the_centre_solved_from_a_point_touches_there(dome, point_mm):
    """The 15 mm sphere centred where centre_touching says, coming down, first touches the
    faceted surface at a node within one node spacing (~2 mm at 32 rim vertices) of the point,
    outside it off the axis (the dome slopes away), and point_touched gives the point back to
    10 µm (0.5 % of the spacing: the nodes fitted change as the point moves, so the inverse
    finds a fixed point a few µm from it; measured ≤ 3 µm)."""
    p = np.array(point_mm) * 1e-3
    c = centre_touching(dome, p)
    node = dome.first_contact(c[:2])[1]
    spacing = 2 * np.pi * 20e-3 / 32
    assert np.linalg.norm(outer_points(dome)[node, :2] - p) < spacing
    assert np.hypot(*c[:2]) >= np.hypot(*p) - 1e-6
    np.testing.assert_allclose(point_touched(dome, c[:2]), p, atol=1e-5)


def test_the_depth_allowed_is_the_press_limit(dome):
    """At the ring (15 mm) a 15 mm sphere may press depth_reach past its touch and not 0.2 mm
    more: press refuses a sphere whose lowest point comes within a thickness of the base."""
    c = centre_touching(dome, np.array([15e-3, 0.0]))
    z0 = dome.first_contact_height(c[:2])
    reach = depth_reach(dome, z0)
    assert 2e-3 < reach < 6e-3
    with pytest.raises(UnreachablePose, match="beyond what the dome can take"):
        dome.press(np.array([c[0], c[1], z0 - reach - 0.2e-3]))


def test_a_point_off_the_membrane_is_refused(dome):
    with pytest.raises(ValueError, match=r"contact point \[25\.0, 0\.0\] mm is not on the membrane's top"):
        centre_touching(dome, np.array([25e-3, 0.0]))
