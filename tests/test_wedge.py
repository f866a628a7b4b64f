"""The 15-node wedge membrane element (jointsim/mechanics/wedge.py): its shape functions, its
Warp kernel's derivatives, uniaxial stretch against the closed form, bending without locking,
and the membrane built of it."""

import numpy as np
import pytest
from conftest import (
    cantilever_tip_ratio,
    check_element_derivatives,
    inflate_octant,
    press_block,
    uniaxial_nominal_stress,
    wedge_grid,
)

from jointsim.mechanics.materials import Material
from jointsim.mechanics.wedge import (
    WEDGE_POINTS,
    WEDGE_WEIGHTS,
    WedgeElasticTerm,
    WedgeKernel,
    WedgeMesh,
    wedge_shape,
)

# the reference prism's nodes in the module's order (ξ, η, ζ)
_REF = np.array([[0, 0, -1], [1, 0, -1], [0, 1, -1], [0, 0, 1], [1, 0, 1], [0, 1, 1],
                 [0.5, 0, -1], [0.5, 0.5, -1], [0, 0.5, -1], [0.5, 0, 1], [0.5, 0.5, 1], [0, 0.5, 1],
                 [0, 0, 0], [1, 0, 0], [0, 1, 0]], float)


def _block(size=(1e-2, 1e-2, 1e-2), cells=(1, 1), layers=1):
    """A box of wedges: a rectangle split into 2 triangles per cell, extruded in z."""
    nx, ny = cells
    return wedge_grid(np.linspace(0, size[0], nx + 1), np.linspace(0, size[1], ny + 1), np.linspace(0, size[2], layers + 1))


def test_shape_functions_interpolate_and_differentiate():
    N, dN = wedge_shape(_REF)
    np.testing.assert_allclose(N, np.eye(15), atol=1e-14)  # each is 1 at its node, 0 at the others
    rng = np.random.default_rng(0)
    p = np.column_stack([rng.uniform(0, 0.5, 20), rng.uniform(0, 0.5, 20), rng.uniform(-1, 1, 20)])
    N, dN = wedge_shape(p)
    np.testing.assert_allclose(N.sum(axis=1), 1.0, atol=1e-14)
    # quadratics are reproduced: Σ N_a f(x_a) = f(x) for f = ξ², ξζ, ζ² (serendipity: no ξ²ζ²)
    for f in (lambda q: q[:, 0] ** 2, lambda q: q[:, 0] * q[:, 2], lambda q: q[:, 2] ** 2, lambda q: q[:, 1] * q[:, 0]):
        np.testing.assert_allclose(N @ f(_REF), f(p), atol=1e-13)
    h = 1e-6
    for k in range(3):
        e = np.zeros(3)
        e[k] = h
        fd = (wedge_shape(p + e)[0] - wedge_shape(p - e)[0]) / (2 * h)
        np.testing.assert_allclose(dN[:, :, k], fd, atol=1e-8)
    assert WEDGE_WEIGHTS.sum() == pytest.approx(1.0, rel=1e-14)  # the reference prism's volume
    # the rule integrates ζ⁴ and ξ² exactly
    assert (WEDGE_WEIGHTS * WEDGE_POINTS[:, 2] ** 4).sum() == pytest.approx(0.5 * 2 / 5, rel=1e-12)
    assert (WEDGE_WEIGHTS * WEDGE_POINTS[:, 0] ** 2).sum() == pytest.approx(2 / 12, rel=1e-12)


def test_a_box_of_wedges_has_its_volume_and_outward_faces():
    m = _block((2e-2, 1e-2, 5e-3), (3, 2), layers=2)
    assert (m.jacobians * WEDGE_WEIGHTS).sum() == pytest.approx(2e-2 * 1e-2 * 5e-3, rel=1e-12)
    p = m.nodes[m.boundary_faces[:, :3]]
    normal = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    z = p[:, 0, 2]
    assert np.all(normal[z == 0, 2] < 0) and np.all(normal[z > 0, 2] > 0)
    assert len(m.boundary_faces) == 2 * 12


@pytest.mark.parametrize("material", [Material.neo_hookean(22e3), Material.yeoh(9.8e3, 0.91e3, -0.16e3)], ids=["neo-Hookean", "Yeoh"])
def test_element_gradient_and_hessian_match_finite_differences(material):
    m = _block((1.0, 1.0, 0.5), (2, 2), layers=2)
    k = WedgeKernel(m, material)
    rng = np.random.default_rng(0)
    u = 0.01 * rng.standard_normal((m.n_nodes, 3))
    s = check_element_derivatives(k, m, u, rng.standard_normal(u.shape))
    # undeformed and rigidly translated: no energy (the projected dilatation is 1 to round-off)
    for rigid in (np.zeros_like(u), np.tile([0.3, -0.2, 0.1], (m.n_nodes, 1))):
        assert abs(k(rigid, False).energy.sum()) <= 1e-12 * abs(s.energy.sum())


@pytest.mark.parametrize("material", [Material.neo_hookean(22e3), Material.yeoh(9.8e3, 0.91e3, -0.16e3)], ids=["neo-Hookean", "Yeoh"])
def test_uniaxial_nominal_stress(material):
    """A cube of two wedges stretched along x (symmetry planes at 0, lateral faces free): the
    deformation is homogeneous, so the elements are exact and the reaction per reference area
    is the closed-form nominal stress, up to the O(μ/κ) compressibility of κ = 1000 μ (~0.1 %)."""
    L, lam = 1e-2, np.array([1.1, 1.5, 2.0])
    m = _block((L, L, L))
    P = uniaxial_nominal_stress(m, WedgeElasticTerm(m, material), L, lam)
    np.testing.assert_allclose(P, material.uniaxial_nominal_stress(lam), rtol=5e-3)


def test_a_nearly_incompressible_cantilever_bends_without_locking():
    """tests/test_mechanics.py's cantilever (20 × 2 × 2 mm, κ = 1000 μ, a small tip load) on ONE
    wedge layer through the thickness, against Timoshenko's δ = PL³/3EI + PL/(κₛGA) (E = 3μ,
    G = μ). The clamped 3-D solution is ~0.98 of it (results/locking_cantilever.md: P2 tetrahedra
    converge there under refinement); the wedges give 0.970 here and 0.972 at 40 × 4 cells and
    4 layers (a scratch refinement), where pointwise P2 tetrahedra on two layers lock at 0.874
    (tests/test_mechanics.py). Within 2 % of the 3-D limit: locking would be ≥ 10 %."""
    L, t, mu, P = 20e-3, 2e-3, 22e3, 1e-5
    m = _block((L, t, t), (10, 1), layers=1)
    assert cantilever_tip_ratio(m, WedgeElasticTerm(m, Material.neo_hookean(mu)), L, t, mu, P) == pytest.approx(0.98, abs=0.02)


def _paper_membrane(rim: int, layers: int = 1, **membrane):
    from dataclasses import replace
    from pathlib import Path

    from jointsim.geometry import isotropic_cap
    from jointsim.mechanics.build import membrane_from_scene
    from jointsim.scene import load_scene

    scene = load_scene(Path(__file__).resolve().parents[1] / "scenes" / "paper_sensor.toml")
    scene = replace(scene, membrane=replace(scene.membrane, layers=layers, element="wedge15", **membrane))
    c = scene.chamber
    return membrane_from_scene(scene, 7.5e-3, dome=isotropic_cap(c.base_radius, c.dome_height, rim))


def test_the_wedge_membrane_presses_the_paper_dome_and_converges():
    """The paper's press (15 mm sphere on the axis) on one wedge layer: the force points along
    the axis (the cap's 16-fold symmetry), the penetration is below 1 % of the indentation, no
    element inverts, and the force at 1 mm agrees between 48 and 64 rim vertices within 2 %
    (results/mechanics_benchmark_wedge15.md: both within 2 % of the finest wedge mesh)."""
    forces = {}
    for rim in (48, 64):
        model = _paper_membrane(rim)
        top = model.first_contact_height((0.0, 0.0))
        st = model.press(np.array([0.0, 0.0, top - 1e-3]))
        assert abs(st.force[:2]).max() <= 1e-3 * st.force[2]
        assert st.penetration < 0.01 * 1e-3
        assert st.min_jacobian > 0.5 and 0 < st.peak_strain < 0.2
        assert st.displaced_volume > 0
        forces[rim] = st.force[2]
    assert forces[48] == pytest.approx(forces[64], rel=0.02)
    # the corner tetrahedra written for ParaView fill the membrane (chords: a little less)
    from jointsim.mesh.tetmesh import TetMesh

    m = model.mesh
    tets = TetMesh(m.nodes, m.corner_tets)
    p = m.nodes[tets.tets]
    vol = np.abs(np.einsum("ti,ti->t", p[:, 1] - p[:, 0], np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]))).sum() / 6
    assert vol == pytest.approx((m.jacobians * WEDGE_WEIGHTS).sum(), rel=0.01)


def test_the_scene_defaults_to_one_wedge_layer_and_refuses_another_volumetric_form():
    """Wedges are the default element, one layer unless given; the tetrahedra keep their two
    (one layer of them locks in bending); a volumetric form other than pointwise with wedges,
    an unknown element and a layer count outside [1, 8] are refused by name."""
    import tomllib
    from pathlib import Path

    from jointsim.geometry import isotropic_cap
    from jointsim.mechanics.dome import MembraneModel
    from jointsim.scene import SceneError, scene_from_dict

    d = tomllib.loads((Path(__file__).resolve().parents[1] / "scenes" / "paper_sensor.toml").read_text())
    d["membrane"].pop("layers", None)
    d["membrane"].pop("element", None)
    m = scene_from_dict(d).membrane
    assert (m.element, m.layers) == ("wedge15", 1)
    assert (scene_from_dict({}).membrane.element, scene_from_dict({}).membrane.layers) == ("wedge15", 1)
    d["membrane"]["element"] = "p2_tet"
    assert scene_from_dict(d).membrane.layers == 2
    d["membrane"]["element"] = "wedge15"
    d["membrane"]["volumetric"] = "mean_dilatation"
    with pytest.raises(SceneError, match="volumetric.*p2_tet"):
        scene_from_dict(d)
    d["membrane"]["volumetric"], d["membrane"]["element"] = "pointwise", "hex27"
    with pytest.raises(SceneError, match="element"):
        scene_from_dict(d)

    cap = isotropic_cap(0.02, 0.01, 32)
    assert isinstance(MembraneModel(cap, 2e-3).mesh, WedgeMesh)
    assert MembraneModel(cap, 2e-3).mesh.n_nodes < MembraneModel(cap, 2e-3, element="p2_tet").mesh.n_nodes
    with pytest.raises(ValueError, match="volumetric"):
        MembraneModel(cap, 2e-3, layers=1, volumetric="mean_dilatation")
    with pytest.raises(ValueError, match="element"):
        MembraneModel(cap, 2e-3, layers=1, element="hex27")
    with pytest.raises(ValueError, match=r"layers = 0.*\[1, 8\]"):
        MembraneModel(cap, 2e-3, layers=0)


def test_pressurised_thick_sphere():
    """tests/test_mechanics.py's octant of the shell A ≤ r ≤ B under cavity pressure (symmetry
    planes, the same 10² triangles per sphere), as curved wedges in two radial layers, against
    the exact inflation p = 2μ[(1/λb + 1/(4λb⁴)) − (1/λa + 1/(4λa⁴))] (≤ 2 %, the issue's
    bound). Measured: -0.7 to -0.8 % at 4-12 kPa (λa up to 1.25); the P2 tetrahedra on four
    layers are +0.3-0.9 % (pointwise), -0.8-1.1 % (mean dilatation)."""
    from jointsim.mesh.shapes import octant_triangles, spherical_midsides

    A, B, mu, layers = 5e-3, 10e-3, 22e3, 2
    direction, tri = octant_triangles(10)
    corners = (np.linspace(A, B, layers + 1)[:, None, None] * direction).reshape(-1, 3)
    m = WedgeMesh.extrude(corners, tri, layers, spherical_midsides)
    pressures = np.array([4e3, 8e3, 12e3])
    exact, la, cavity_faces = inflate_octant(m, WedgeElasticTerm(m, Material.neo_hookean(mu)), A, B, mu, pressures)
    assert cavity_faces == len(tri)
    assert la > 1.2
    np.testing.assert_allclose(pressures / exact - 1, 0.0, atol=0.02)


def test_rigid_sphere_into_a_thick_block_follows_hertz():
    """tests/test_mechanics.py's Hertz case on wedges: a quarter of an 11 × 11 × 5.5 cm nearly
    incompressible block graded from 0.25 mm cells at the contact, a rigid 10 mm sphere pressed
    0.2 mm (d/R = 0.02) against F = (16/9)·E·√R·d^1.5 (≤ 5 %: small-strain theory, a finite
    block), the contact radius against √(Rd) (≤ 15 %: ~7 cells across it), penetration below
    1 % of the depth. Measured: force +0.6 % (the tetrahedra on the same grid +2.4 %), contact
    radius +5.4 %, penetration 0.2 %."""
    from jointsim.mesh.shapes import graded_axis

    R, W, h0, d, mu = 10e-3, 55e-3, 0.25e-3, 0.2e-3, 22e3
    E = 3 * mu  # ν = 0.5
    ax = graded_axis(W, h0, 1.4)
    m = wedge_grid(ax, ax, -ax[::-1])
    F, penetration, a = press_block(m, WedgeElasticTerm(m, Material.neo_hookean(mu)), R, W, h0, d, E)
    assert F == pytest.approx(16 / 9 * E * np.sqrt(R) * d**1.5, rel=0.05)
    assert penetration < 0.01 * d
    assert a == pytest.approx(np.sqrt(R * d), rel=0.15)
