import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from jointsim.geometry import DomeSurface, chamber_surface, electrode_layout, isotropic_cap, spherical_cap
from jointsim.mesh.electrodes import ElectrodePatch, _clip_moments, disc_patches
from jointsim.mesh.shapes import box_mesh
from jointsim.mesh.tetmesh import TetMesh, mesh_quality


def test_spherical_cap_chamber_is_watertight_with_the_cap_volume():
    a, h = 0.02, 0.01
    surf = chamber_surface(spherical_cap(a, h, n_rim=192))
    assert surf.is_watertight
    exact = np.pi * h * (3 * a * a + h * h) / 6
    # inscribed facets: the relative volume deficit is O((π/n)²) ≈ 2.7e-4 for 192 facets
    assert surf.volume == pytest.approx(exact, rel=1e-3)
    assert surf.volume < exact


def test_dome_rim_off_the_base_circle_is_rejected():
    d = spherical_cap(0.02, 0.01, n_rim=32)
    v = d.vertices.copy()
    v[d.rim[0], 2] = 1e-3
    with pytest.raises(ValueError, match="rim"):
        chamber_surface(DomeSurface(v, d.faces, d.rim))


def test_electrode_layout_follows_the_ring(paper_scene):
    lay = electrode_layout(paper_scene)
    assert lay.n_electrodes == 17 and lay.ground == 16
    r = np.hypot(*lay.centres[:16, :2].T)
    np.testing.assert_allclose(r, 15e-3)
    ang = np.degrees(np.arctan2(lay.centres[:16, 1], lay.centres[:16, 0])) % 360
    np.testing.assert_allclose(ang, 22.5 * np.arange(16), atol=1e-9)
    assert lay.radii[16] == pytest.approx(2e-3)


def test_unit_tet_gradients_and_volume():
    m = TetMesh(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]]), np.array([[0, 1, 2, 3]]))
    assert m.volumes[0] == pytest.approx(1 / 6)
    np.testing.assert_allclose(m.gradients[0], [[-1, -1, -1], [1, 0, 0], [0, 1, 0], [0, 0, 1]], atol=1e-14)


def test_element_geometry_of_affine_images_of_the_unit_tet():
    """Each tetrahedron x = A ξ + x0 of the unit one: volume det A / 6, ∇λ = A⁻ᵀ ∇_ξ λ (rows:
    ∇_ξ λ · A⁻¹) and centroid A (¼, ¼, ¼) + x0, against numpy, to round-off of
    well-conditioned maps."""
    rng = np.random.default_rng(1)
    A = np.eye(3) + 0.4 * rng.standard_normal((200, 3, 3))
    A[np.linalg.det(A) < 0, :, 0] *= -1  # positively oriented
    unit = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]])
    x0 = rng.standard_normal((200, 1, 3))
    nodes = (np.einsum("kij,aj->kai", A, unit) + x0).reshape(-1, 3)
    m = TetMesh(nodes, np.arange(800).reshape(200, 4))
    np.testing.assert_allclose(m.signed_volumes, np.linalg.det(A) / 6, rtol=1e-12)
    g_unit = np.array([[-1, -1, -1], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]])
    expected = np.einsum("aj,kji->kai", g_unit, np.linalg.inv(A))
    np.testing.assert_allclose(m.gradients, expected, rtol=1e-10, atol=1e-12 * np.abs(expected).max())
    np.testing.assert_allclose(m.centroids, A.sum(axis=2) / 4 + x0[:, 0], rtol=0, atol=1e-14 * np.abs(nodes).max())


def test_a_flat_element_has_no_gradients():
    m = TetMesh(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0.0]]), np.array([[0, 1, 2, 3]]))
    assert m.signed_volumes[0] == 0.0
    with pytest.raises(ValueError, match="zero volume"):
        m.gradients


def test_box_mesh_quality_and_boundary():
    m = box_mesh((2.0, 3.0, 4.0), (2, 3, 4))  # unit cubes, 6 Kuhn tets each
    q = mesh_quality(m)
    assert q.n_inverted == 0
    assert q.volume == pytest.approx(24.0)
    assert q.min_dihedral_deg == pytest.approx(45.0) and q.max_dihedral_deg == pytest.approx(90.0)
    f = m.boundary_faces
    p = m.nodes[f]
    area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1).sum()
    assert area == pytest.approx(2 * (6 + 8 + 12))


def test_inverted_element_is_reported():
    m = TetMesh(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]]), np.array([[0, 2, 1, 3]]))
    assert mesh_quality(m).n_inverted == 1
    assert mesh_quality(m.oriented()).n_inverted == 0


def _cross2(u, v):
    return u[0] * v[1] - u[1] * v[0]


def _unit_poly():
    n = 256
    ang = 2 * np.pi * (np.arange(n) + 0.5) / n
    return np.sqrt(2 * np.pi / (n * np.sin(2 * np.pi / n))) * np.column_stack([np.cos(ang), np.sin(ang)])


def test_clipped_moments_of_a_triangle_inside_the_disc_are_the_whole_triangle_moments():
    tri = np.array([[[0.1, -0.2], [0.4, 0.1], [-0.3, 0.3]]])
    area, m1, m2 = _clip_moments(tri, _unit_poly())
    full = ElectrodePatch.from_faces(np.c_[tri[0], np.zeros(3)], [[0, 1, 2]])
    np.testing.assert_allclose(area, full.area, rtol=1e-12)
    np.testing.assert_allclose(m1, full.m1, rtol=1e-12)
    np.testing.assert_allclose(m2, full.m2, rtol=1e-12)


def test_p2_moments_of_a_whole_triangle_are_the_p2_mass_matrix():
    # closed forms: ∫ vertex functions = 0, ∫ edge functions = A/3, M = A/180 · [[6, −1, −1, 0, −4, 0], …]
    tri = np.array([[[0.1, -0.2], [0.4, 0.1], [-0.3, 0.3]]])
    area, _, _, q1, q2 = _clip_moments(tri, _unit_poly(), quadratic=True)
    V, E = 6 * np.eye(3) - (1 - np.eye(3)), 16 * (np.ones((3, 3)) + np.eye(3))
    VE = np.array([[0, -4, 0], [0, 0, -4], [-4, 0, 0]])  # vertex a against the edge opposite it
    np.testing.assert_allclose(q2[0], area[0] / 180 * np.block([[V, VE], [VE.T, E]]), atol=1e-14 * area[0])
    np.testing.assert_allclose(q1[0], area[0] * np.r_[0, 0, 0, 1, 1, 1] / 3, atol=1e-14 * area[0])
    full = ElectrodePatch.from_faces(np.c_[tri[0], np.zeros(3)], [[0, 1, 2]])
    np.testing.assert_allclose(full.q2[0], q2[0], atol=1e-14 * area[0])


def test_quarter_disc_first_moment():
    # ∫ x dA over the quarter of the unit disc in the triangle (0,0),(2,0),(0,2) is 1/3; λ1 = x/2
    area, m1, _ = _clip_moments(np.array([[[0, 0], [2, 0], [0, 2.0]]]), _unit_poly())
    assert area[0] == pytest.approx(np.pi / 4, rel=1e-12)
    assert m1[0, 1] == pytest.approx(1 / 6, rel=1e-4)  # the polygon is a 256-gon, not the disc


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(-2, 2), min_size=6, max_size=6))
def test_clipped_moments_are_consistent(coords):
    tri = np.array(coords).reshape(1, 3, 2)
    if abs(_cross2(tri[0, 1] - tri[0, 0], tri[0, 2] - tri[0, 0])) < 1e-3:
        return
    area, m1, m2, q1, q2 = _clip_moments(tri, _unit_poly(), quadratic=True)
    tri_area = 0.5 * abs(_cross2(tri[0, 1] - tri[0, 0], tri[0, 2] - tri[0, 0]))
    # the P2 basis sums to one as well, and its moments carry the P1 ones (λ_a = φ_a + ½ Σ edges at a)
    assert q1[0].sum() == pytest.approx(area[0], abs=1e-12)
    np.testing.assert_allclose(q2[0].sum(axis=1), q1[0], atol=1e-12)
    to_p1 = np.hstack([np.eye(3), 0.5 * np.array([[1, 0, 1], [1, 1, 0], [0, 1, 1]])])  # λ = to_p1 @ φ
    np.testing.assert_allclose(to_p1 @ q1[0], m1[0], atol=1e-12)
    np.testing.assert_allclose(to_p1 @ q2[0] @ to_p1.T, m2[0], atol=1e-12)
    assert -1e-12 <= area[0] <= min(tri_area, np.pi) + 1e-12
    # the barycentrics sum to one: Σ_a m1_a = area and Σ_ab m2_ab = area
    assert m1[0].sum() == pytest.approx(area[0], abs=1e-12)
    assert m2[0].sum() == pytest.approx(area[0], abs=1e-12)
    assert np.allclose(m2[0], m2[0].T)


def test_disc_patches_cover_exactly_the_disc_on_any_mesh():
    centres = np.array([[0.3, 0.1, 0.0], [-0.45, -0.2, 0.0]])
    radii = np.array([0.21, 0.13])
    for n in (3, 7, 12):
        m = box_mesh((2.0, 2.0, 0.5), (n, n, 2), origin=(-1.0, -1.0, 0.0))
        patches = disc_patches(m, centres, radii)
        for p, r in zip(patches, radii):
            assert p.total_area == pytest.approx(np.pi * r * r, rel=1e-12)


def test_discs_moved_within_their_reach_keep_one_set_of_faces_and_their_exact_moments():
    """A dataset's jittered electrodes: moved up to ``reach`` from their places they keep the
    same faces (one CEM pattern), with the same moments as clipped alone (the faces they miss
    at zero); moved further, refused."""
    m = box_mesh((2.0, 2.0, 0.5), (9, 9, 2), origin=(-1.0, -1.0, 0.0))
    home = np.array([[0.3, 0.1, 0.0], [-0.45, -0.2, 0.0]])
    radii = np.array([0.21, 0.13])
    reach = 0.05
    moved = home + np.array([[0.03, -0.04, 0.0], [-0.05, 0.0, 0.0]])
    kept = [disc_patches(m, c, radii, quadratic=True, around=home, reach=reach) for c in (home, moved)]
    for a, b in zip(*kept):
        np.testing.assert_array_equal(a.faces, b.faces)
    for patch, alone, r in zip(kept[1], disc_patches(m, moved, radii, quadratic=True), radii):
        assert patch.total_area == pytest.approx(np.pi * r * r, rel=1e-12)
        key = {tuple(f): i for i, f in enumerate(patch.faces.tolist())}
        at = np.array([key[tuple(f)] for f in alone.faces.tolist()])  # every covered face is kept
        np.testing.assert_allclose(patch.q2[at], alone.q2, rtol=0, atol=1e-15 * r * r)
        missed = np.setdiff1d(np.arange(len(patch.faces)), at)
        assert len(missed) > 0 and np.abs(patch.area[missed]).max() < 1e-14 * r * r
    with pytest.raises(ValueError, match="electrode 1: moved 60 mm from its place, more than the reach 50 mm"):  # (mm: ×1e3 of the box's units)
        disc_patches(m, home + np.array([[0.0, 0.0, 0.0], [0.06, 0.0, 0.0]]), radii, around=home, reach=reach)


def test_disc_off_the_base_is_rejected():
    m = box_mesh((1.0, 1.0, 0.5), (4, 4, 2))
    with pytest.raises(ValueError, match="electrode 0"):
        disc_patches(m, np.array([[1.0, 0.5, 0.0]]), np.array([0.2]))


def test_chamber_mesh_is_valid_and_electrodes_exact(test_chamber):
    scene, ch = test_chamber
    q = ch.quality()
    assert q.n_inverted == 0
    assert q.min_dihedral_deg > 5.0
    a, h = scene.chamber.base_radius, scene.chamber.dome_height
    assert q.volume == pytest.approx(np.pi * h * (3 * a * a + h * h) / 6, rel=5e-3)
    for e, r in zip(ch.electrodes, ch.layout.radii):
        assert e.total_area == pytest.approx(np.pi * r * r, rel=1e-12)


# SHA-256 of the paper chamber's test-preset mesh (nodes then tets, as stored): the same on
# every machine, thread count and run. Computed on the 2-core AMD EPYC (gmsh 4.15.2); a change
# here means the published meshes, and every number made on them, would change: bump
# chamber._MESHER_VERSION and say why.
TEST_MESH_SHA256 = "fa5d8b2993710f43"


def _mesh_digest(mesh) -> str:
    import hashlib

    return hashlib.sha256(mesh.nodes.tobytes() + mesh.tets.tobytes()).hexdigest()[:16]


def test_the_chamber_mesh_is_the_same_everywhere(test_chamber, tmp_path):
    """Meshing the test preset again, in a new process with an empty mesh cache, gives the mesh
    bit for bit, and it is the one pinned above (so on another machine too)."""
    import os
    import subprocess
    import sys

    scene, ch = test_chamber
    code = ("import hashlib, sys\n"
            "from jointsim.scene import load_scene\n"
            "from jointsim.mesh.chamber import chamber_mesh\n"
            "m = chamber_mesh(load_scene(sys.argv[1]).with_mesh_preset('test')).mesh\n"
            "print(hashlib.sha256(m.nodes.tobytes() + m.tets.tobytes()).hexdigest()[:16])")
    from jointsim.scene import SCENES_DIR

    r = subprocess.run([sys.executable, "-c", code, str(SCENES_DIR / "paper_sensor.toml")], capture_output=True, text=True,
                       env=dict(os.environ, JOINTSIM_CACHE=str(tmp_path)))
    assert r.returncode == 0, r.stderr[-2000:]
    assert list(tmp_path.glob("chamber-*.npz"))  # it meshed (and cached) anew
    assert r.stdout.strip() == _mesh_digest(ch.mesh) == TEST_MESH_SHA256


def test_the_electrode_outlines_are_mesh_edges(test_chamber):
    """Each electrode's circle is embedded in the base: boundary nodes lie on it all round (at
    least one every 45 deg), so the clipped electrode integrals see whole triangles."""
    _, ch = test_chamber
    m = ch.mesh
    f = m.boundary_faces
    base = np.unique(f[np.all(m.nodes[f][..., 2] == 0.0, axis=1)])
    for c, r in zip(ch.layout.centres, ch.layout.radii):
        d = m.nodes[base, :2] - c[:2]
        on = np.abs(np.hypot(*d.T) - r) <= 1e-9 * r
        angles = np.sort(np.arctan2(d[on, 1], d[on, 0]))
        gaps = np.diff(np.concatenate([angles, [angles[0] + 2 * np.pi]]))
        assert on.sum() >= 8 and gaps.max() <= np.pi / 4 + 1e-9


def test_chamber_mesh_is_cached(test_chamber):
    from jointsim.mesh.chamber import cache_dir, chamber_mesh

    scene, ch = test_chamber
    assert (cache_dir() / f"chamber-{ch.key}.npz").is_file()
    again = chamber_mesh(scene)
    assert again.key == ch.key
    np.testing.assert_array_equal(again.mesh.tets, ch.mesh.tets)


def test_uniform_refinement_keeps_volume_and_conformity():
    from jointsim.mesh.tetmesh import refine_uniform

    m = box_mesh((1.0, 1.0, 1.0), (2, 2, 2))
    r = refine_uniform(m)
    assert r.n_tets == 8 * m.n_tets
    assert mesh_quality(r).n_inverted == 0
    assert r.volumes.sum() == pytest.approx(1.0)
    # conforming: the boundary of the refined mesh is 4x the faces of the coarse boundary
    assert len(r.boundary_faces) == 4 * len(m.boundary_faces)
    np.testing.assert_allclose(np.sort(r.volumes)[-1], np.sort(m.volumes)[-1] / 8)


@pytest.mark.parametrize("r", [5.5455e-3, 5.5565e-3, 7.5e-3])
def test_hemispherical_caps_are_built_whatever_the_rounding(r):
    # h = a gives a / R = 1 in exact arithmetic; for these radii it rounds to 1 + 1 ulp and the
    # rim angle was NaN (the soft target's hemisphere mesh then failed for ~5 % of radii)
    for build in (isotropic_cap, spherical_cap):
        cap = build(r, r, 32)
        v = np.asarray(cap.vertices)
        assert np.isfinite(v).all()
        np.testing.assert_allclose(np.linalg.norm(v - [0, 0, 0], axis=1), r, rtol=1e-9)
        assert v[:, 2].min() == pytest.approx(0.0, abs=1e-12) and v[:, 2].max() == pytest.approx(r)


@pytest.mark.parametrize("about, levels", [((6e-3, 3e-3), 1), ((6e-3, 3e-3), 3), ((19e-3, 0.0), 2), ((0.0, 0.0), 2)])
def test_a_cap_refined_near_a_point_stays_the_cap(about, levels):
    """refine_near splits the faces about a point (four within the finest radius, closed by
    bisected ones): the surface is still a watertight, consistently wound cap welded to the
    base, every new vertex on the cap's sphere (or on the rim circle), the old vertices and
    their indices kept, the faces near the point ``2^levels`` times smaller, none far from it
    touched, and no angle below half the coarse mesh's smallest (one bisection of a face)."""
    from jointsim.geometry import refine_near

    a, h = 20e-3, 12e-3
    cap = isotropic_cap(a, h, 64)
    fine = refine_near(cap, np.array(about), 4e-3, levels)
    v, f = np.asarray(fine.vertices), np.asarray(fine.faces)
    np.testing.assert_array_equal(v[: len(cap.vertices)], cap.vertices)
    surf = chamber_surface(fine)
    assert surf.is_watertight and surf.is_winding_consistent and surf.volume > 0
    R = (a * a + h * h) / (2 * h)
    off = np.abs(np.linalg.norm(v - [0, 0, h - R], axis=1) - R)
    assert off.max() < 1e-12
    rim = np.asarray(fine.rim)
    np.testing.assert_allclose(np.hypot(v[rim, 0], v[rim, 1]), a, rtol=1e-12)
    assert not v[rim, 2].any()
    turn = np.unwrap(np.arctan2(v[rim, 1], v[rim, 0]))
    assert np.all(np.diff(turn) > 0) and turn[-1] - turn[0] < 2 * np.pi  # anticlockwise, once round
    # the faces within the finest radius are 4^levels times smaller; far ones are the coarse ones
    def areas(v, f):
        return 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)

    def dist(v, f):
        return np.hypot(*(v[f].mean(axis=1)[:, :2] - about).T)

    c_area, f_area = areas(cap.vertices, cap.faces), areas(v, f)
    c_dist, f_dist = dist(cap.vertices, cap.faces), dist(v, f)
    assert np.median(f_area[f_dist < 2e-3]) == pytest.approx(np.median(c_area[c_dist < 2e-3]) / 4**levels, rel=0.35)
    far_coarse = {tuple(sorted(t)) for t in np.asarray(cap.faces)[c_dist > 12e-3].tolist()}
    assert far_coarse <= {tuple(sorted(t)) for t in f.tolist()}

    def min_angle(v, f):
        p = v[f]
        ang = [np.arccos(np.einsum("ij,ij->i", p[:, (k + 1) % 3] - p[:, k], p[:, (k + 2) % 3] - p[:, k])
                         / np.linalg.norm(p[:, (k + 1) % 3] - p[:, k], axis=1) / np.linalg.norm(p[:, (k + 2) % 3] - p[:, k], axis=1))
               for k in range(3)]
        return np.degrees(np.min(ang))

    assert min_angle(v, f) >= 0.45 * min_angle(np.asarray(cap.vertices), np.asarray(cap.faces))
