"""The prepared chamber morpher, its quality check and the automatic fallback to a remesh."""

from dataclasses import replace

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

import jointsim.mesh.morph as morph
from jointsim.eit.fem import element_stiffness
from jointsim.eit.forward import ForwardModel
from jointsim.eit.protocol import skip_protocol
from jointsim.geometry import DomeSurface, chamber_surface, dome_from_scene
from jointsim.mechanics.geometric import indent_dome
from jointsim.mesh.electrodes import disc_patches
from jointsim.mesh.morph import (
    ChamberMorpher,
    MeshInversionError,
    deform_chamber,
    dome_nodes,
    element_quality,
    morph_chamber,
)
from jointsim.mesh.kernels import tet_quality
from jointsim.mesh.tetmesh import TetMesh, mesh_quality
from jointsim.mechanics.surface_contact import closest_points


def _reference_morph(chamber, dome, deformed):
    """The one-off algorithm written out step by step (closest points, assembly, a fresh
    factorisation, one solve): the nodes the prepared morpher must reproduce."""
    mesh = chamber.mesh
    disp = deformed.vertices - dome.vertices
    top = dome_nodes(mesh)
    tri, bary, _ = morph.closest_on_surface(dome.vertices, dome.faces, mesh.nodes[top])  # tested on its own below
    u = np.zeros_like(mesh.nodes)
    u[top] = np.einsum("na,nai->ni", bary, disp[dome.faces[tri]])
    fixed = np.zeros(mesh.n_nodes, bool)
    fixed[np.unique(mesh.boundary_faces)] = True
    k = element_stiffness(mesh)
    rows, cols = np.repeat(mesh.tets, 4, axis=1).ravel(), np.tile(mesh.tets, (1, 4)).ravel()
    K = sp.csr_matrix((k.ravel(), (rows, cols)), shape=(mesh.n_nodes,) * 2)
    u[~fixed] = spla.spsolve(K[~fixed][:, ~fixed].tocsc(), -(K[~fixed][:, fixed] @ u[fixed]))
    return mesh.nodes + u


@pytest.fixture(scope="module")
def morpher(test_chamber):
    scene, ch = test_chamber
    with ChamberMorpher(ch, dome_from_scene(scene)) as m:
        yield m


def _press(scene, xy, depth):
    return indent_dome(dome_from_scene(scene), xy, depth, 7.5e-3, scene.chamber.membrane_thickness).dome


def _fold(dome):
    """A huge non-physical deformation that stays above the base: the dome turned upside down
    into a bowl (z -> c - z/2, its lowest point 0.5 mm over the base, the rim left in place).
    The dome's elements are mirrored, so the morph inverts them."""
    v = dome.vertices.copy()
    c = 0.5 * v[:, 2].max() + 0.5e-3
    v[:, 2] = c - 0.5 * v[:, 2]
    v[dome.rim, 2] = 0.0
    return DomeSurface(v, dome.faces, dome.rim)


def test_each_dome_node_takes_the_displacement_of_its_closest_point(test_chamber, morpher):
    """The morph moves a dome node with the displacement of its closest point on the reference
    dome. That point, rebuilt from the stored triangle and barycentric coordinates, must be as
    close to the node as the closest of all the dome's triangles (brute force), whatever the
    length unit (trimesh's tolerances are absolute: in metres the apex's small triangles were
    skipped and nodes took the displacement of points up to 1.3 mm away)."""
    scene, ch = test_chamber
    dome = morpher.dome
    nodes = ch.mesh.nodes[morpher.top]
    rebuilt = np.einsum("na,nai->ni", morpher._bary, dome.vertices[morpher._corners])
    got = np.linalg.norm(rebuilt - nodes, axis=1)
    a, b, c = (dome.vertices[dome.faces[:, i]] for i in range(3))
    best = np.array([np.linalg.norm(closest_points(np.broadcast_to(p, a.shape), a, b, c)[1] - p, axis=1).min() for p in nodes])
    # to 0.1 µm: trimesh's point for a node a few µm off the surface is up to ~15 nm farther
    # than the exhaustive search's; the scale bug put points up to 1.3 mm away
    assert np.all(got <= best + 1e-7)
    tri_mm, bary_mm, dist_mm = morph.closest_on_surface(1e3 * dome.vertices, dome.faces, 1e3 * nodes)
    np.testing.assert_allclose(np.einsum("na,nai->ni", bary_mm, dome.vertices[dome.faces[tri_mm]]), rebuilt, rtol=0, atol=1e-12)
    np.testing.assert_allclose(1e-3 * dist_mm, got, rtol=0, atol=1e-12)


@pytest.mark.parametrize("xy, depth", [((0.0, 0.0), 1.5e-3), ((0.008, -0.004), 2.5e-3)])
def test_prepared_morpher_matches_the_one_off_morph(test_chamber, morpher, xy, depth):
    scene, ch = test_chamber
    deformed = _press(scene, xy, depth)
    m = morpher(deformed)
    np.testing.assert_array_equal(m.mesh.tets, ch.mesh.tets)
    np.testing.assert_allclose(m.mesh.nodes, _reference_morph(ch, morpher.dome, deformed), rtol=0, atol=1e-12)
    # the one-off wrapper is the same computation
    np.testing.assert_array_equal(morph_chamber(ch, morpher.dome, deformed).mesh.nodes, m.mesh.nodes)
    # the policy, when the morph passes, is the morph
    r = deform_chamber(morpher, deformed, scene.mesh)
    assert r.path == "morph" and r.reason.startswith("morphed")
    np.testing.assert_array_equal(r.chamber.mesh.nodes, m.mesh.nodes)


def test_zero_deformation_is_the_reference_mesh_and_has_no_mesh_noise(chamber_fields, morpher):
    scene, ch, model, f0 = chamber_fields
    m = morpher(morpher.dome)
    np.testing.assert_array_equal(m.mesh.nodes, ch.mesh.nodes)
    p = skip_protocol(16, 8, scene.drive.current)
    v = ForwardModel.from_chamber(m, scene).solve(scene.saline.conductivity).voltages(p)
    np.testing.assert_array_equal(v, f0.voltages(p))


def test_morph_keeps_the_electrode_patches_exact(test_chamber, morpher):
    scene, ch = test_chamber
    m = morpher(_press(scene, (0.012, 0.003), 2e-3))
    assert m.electrodes is ch.electrodes
    # the base does not move, so clipping the electrodes on the morphed mesh gives the same
    # patches, integrals included
    for a, b in zip(disc_patches(m.mesh, ch.layout.centres, ch.layout.radii), ch.electrodes):
        for f in ("faces", "area", "m1", "m2"):
            np.testing.assert_array_equal(getattr(a, f), getattr(b, f))
        np.testing.assert_array_equal(m.mesh.nodes[b.faces], ch.mesh.nodes[b.faces])
    assert m.key.startswith(ch.key) and m.key != ch.key


def test_element_quality_agrees_with_mesh_quality(test_chamber, morpher):
    scene, ch = test_chamber
    for mesh in (ch.mesh, morpher(_press(scene, (0.0, 0.0), 2.5e-3)).mesh):
        fast, full = element_quality(mesh.nodes, mesh.tets), mesh_quality(mesh)
        assert fast.n_inverted == full.n_inverted == 0
        assert fast.min_dihedral_deg == pytest.approx(full.min_dihedral_deg, abs=1e-9)
        assert fast.max_dihedral_deg == pytest.approx(full.max_dihedral_deg, abs=1e-9)
        # the kernel's η against the numpy formula (the untangling's), and its 6V against the volumes
        vol6, _, _, eta = tet_quality(mesh.nodes, mesh.tets)
        np.testing.assert_allclose(eta, morph.shape_measure(mesh.nodes, mesh.tets), rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(vol6, 6 * mesh.signed_volumes, rtol=1e-12)
    # η: 1 for the regular tetrahedron, negative once inverted, 0 when flat
    reg = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], float)
    tet = TetMesh(reg, [[0, 1, 2, 3]]).oriented().tets
    q = element_quality(reg, tet)
    assert q.min_shape == pytest.approx(1.0, abs=1e-12) and q.n_inverted == 0
    assert q.min_dihedral_deg == pytest.approx(np.degrees(np.arccos(1 / 3)), abs=1e-9)
    flipped = element_quality(reg, tet[:, [0, 1, 3, 2]])
    assert flipped.n_inverted == 1 and flipped.min_shape == pytest.approx(-1.0, abs=1e-12)
    flat = reg.copy()
    flat[:, 2] = 0.0
    assert element_quality(flat, tet).min_shape == 0.0


def test_an_inverting_deformation_remeshes_in_auto_and_raises_in_morph(test_chamber, morpher):
    scene, ch = test_chamber
    fold = _fold(morpher.dome)
    with pytest.raises(MeshInversionError, match="remesh"):
        deform_chamber(morpher, fold, scene.mesh, mode="morph")
    r = deform_chamber(morpher, fold, scene.mesh)  # the one real remesh of these tests
    assert r.path == "remesh" and "inverted" in r.reason
    assert r.quality.n_inverted == 0
    # mirrored back, every element would invert: no pull-back, the reason says the floor applies
    assert r.pulled_back is None and "remeshing floor" in r.reason
    # the remesh fills the morphed boundary, whose dome nodes lie on the fold's triangles
    assert r.chamber.mesh.volumes.sum() == pytest.approx(chamber_surface(fold).volume, rel=5e-3)
    # electrodes are clipped exactly on the new base: the same areas as on the reference mesh
    np.testing.assert_allclose(
        [e.total_area for e in r.chamber.electrodes], [e.total_area for e in ch.electrodes], rtol=1e-12
    )


def test_pull_back_undoes_an_affine_squash_exactly(test_chamber, morpher):
    """A chamber mesh squashed by z → 0.8 z (the base plane stays: an affine deformation of the
    chamber) is pulled back onto the reference dome exactly: barycentric coordinates are affine
    invariant and the P1 harmonic extension reproduces affine maps. Zero deformation gives the
    nodes back bit for bit, so the remesh path's change is exactly zero there."""
    scene, ch = test_chamber
    dome = morpher.dome
    # the test mesh's dome nodes sit up to ~5 µm off the dome (chords); put them on it, where the
    # closest-point map is exact
    nodes = ch.mesh.nodes.copy()
    nodes[morpher.top] = np.einsum("na,nai->ni", morpher._bary, dome.vertices[morpher._corners])
    on = replace(ch, mesh=TetMesh(nodes, ch.mesh.tets))
    assert element_quality(nodes, ch.mesh.tets).n_inverted == 0
    same = morph.pull_back(on, dome, dome)
    assert same.dropped == 0 and same.reference is same.deformed is on
    A = np.diag([1.0, 1.0, 0.8])
    squashed = replace(on, mesh=TetMesh(nodes @ A, ch.mesh.tets))
    pb = morph.pull_back(squashed, DomeSurface(dome.vertices @ A, dome.faces, dome.rim), dome)
    assert pb.dropped == 0 and pb.deformed is squashed
    np.testing.assert_array_equal(pb.reference.mesh.tets, ch.mesh.tets)
    np.testing.assert_allclose(pb.reference.mesh.nodes, nodes, rtol=0, atol=1e-12)  # m; round-off of ~1e-2 m
    # the electrodes are the remesh's own: the base does not move
    assert pb.reference.electrodes is squashed.electrodes


def test_the_remesh_fallback_gives_the_same_mesh_every_time(test_chamber, morpher):
    """The remesh of a pressed chamber, meshed twice without the cache, is the same bit for bit
    (the mesher is deterministic), and so is its pull-back onto the reference chamber."""
    scene, _ = test_chamber
    deformed = _press(scene, (3e-3, 0.0), 2e-3)
    a, b = (deform_chamber(morpher, deformed, scene.mesh, "remesh", use_cache=False) for _ in range(2))
    assert a.path == b.path == "remesh" and a.chamber is not b.chamber
    np.testing.assert_array_equal(a.chamber.mesh.nodes, b.chamber.mesh.nodes)
    np.testing.assert_array_equal(a.chamber.mesh.tets, b.chamber.mesh.tets)
    assert (a.pulled_back is None) == (b.pulled_back is None)
    if a.pulled_back is not None:
        np.testing.assert_array_equal(a.pulled_back.reference.mesh.nodes, b.pulled_back.reference.mesh.nodes)


def test_a_remeshed_press_gives_the_morphs_voltage_change(test_chamber, morpher):
    """The same 2 mm press through both paths. Taken against the reference mesh, the remesh's
    δV carries the remeshing floor (~35 % of this δV at the dataset resolution); taken on the
    remesh and its pull-back it is the same change up to the two discretisations' difference
    (1.3 % at the dataset resolution, 1.0 % at the paper's: results/mesh_step_benchmark*.md),
    so 5 % at this coarse test resolution."""
    scene, ch = test_chamber
    deformed = _press(scene, (0.0, 0.0), 2e-3)
    protocol = skip_protocol(scene.electrodes.count, scene.drive.skip, scene.drive.current)
    volts = lambda c: ForwardModel.from_chamber(c, scene).solve(scene.saline.conductivity).voltages(protocol)  # noqa: E731
    v_ref = volts(ch)
    dv_morph = volts(morpher(deformed)) - v_ref
    r = deform_chamber(morpher, deformed, scene.mesh, "remesh")
    assert r.pulled_back is not None and "pulled back" in r.reason
    dv_remesh = r.change(volts, v_ref) - v_ref
    rms = lambda x: float(np.sqrt(np.mean(x**2)))  # noqa: E731
    assert rms(dv_remesh - dv_morph) <= 0.05 * rms(dv_morph)


def test_untangle_moves_interior_nodes_until_no_element_is_below_the_floor(test_chamber):
    """Interior nodes pushed through a neighbour (inverting a few dozen elements, as a
    harmonic pull-back can near a dent's rim) are moved until every element's shape measure
    is above the floor. Only interior nodes move, and only near the tangle: a node moves in a
    sweep only when an element of its star is still low, so within ``rounds`` (4) rings of
    the tangled elements."""
    _, ch = test_chamber
    mesh = ch.mesh
    interior = np.ones(mesh.n_nodes, bool)
    interior[np.unique(mesh.boundary_faces)] = False
    nodes = mesh.nodes.copy()
    picked = np.random.default_rng(3).choice(np.flatnonzero(interior), 5, replace=False)
    for i in picked:  # onto the far side of one of its neighbours
        t = mesh.tets[(mesh.tets == i).any(axis=1)][0]
        other = t[t != i][0]
        nodes[i] = nodes[other] + 0.5 * (nodes[other] - nodes[i])
    tangled = morph.shape_measure(nodes, mesh.tets)
    assert (tangled < 0).sum() >= 5
    floor = 0.1 * morph.shape_measure(mesh.nodes, mesh.tets).min()
    out = morph.untangle(nodes, mesh.tets, interior, floor)
    assert morph.shape_measure(out, mesh.tets).min() >= floor
    moved = np.any(out != nodes, axis=1)
    assert interior[moved].all() and moved[picked].all()
    near = np.zeros(mesh.n_nodes, bool)
    near[mesh.tets[tangled < floor]] = True
    for _ in range(4):
        near[mesh.tets[near[mesh.tets].any(axis=1)]] = True
    assert near[moved].all()
    np.testing.assert_array_equal(morph.untangle(nodes, mesh.tets, interior, -1.0), nodes)  # none below: unchanged


def test_dropping_elements_renumbers_nodes_and_electrodes(test_chamber, morpher):
    """Elements dropped from a chamber (pull_back's surface slivers) take the nodes only they
    used with them; the electrodes are renumbered onto the remaining nodes and keep their
    areas, and the mesh still solves."""
    scene, ch = test_chamber
    mesh = ch.mesh
    # every element around the dome's highest node: that node is left without elements
    apex = morpher.top[np.argmax(mesh.nodes[morpher.top, 2])]
    lone = (mesh.tets == apex).any(axis=1)
    out = morph._without(ch, mesh.nodes, ~lone, "test")
    orphans = np.setdiff1d(np.arange(mesh.n_nodes), mesh.tets[~lone])
    assert out.mesh.n_tets == mesh.n_tets - lone.sum() and out.mesh.n_nodes == mesh.n_nodes - len(orphans)
    assert np.array_equal(np.unique(out.mesh.tets), np.arange(out.mesh.n_nodes))
    for a, b in zip(out.electrodes, ch.electrodes):
        np.testing.assert_array_equal(out.mesh.nodes[a.faces], mesh.nodes[b.faces])
    protocol = skip_protocol(scene.electrodes.count, scene.drive.skip, scene.drive.current)
    v = ForwardModel.from_chamber(out, scene).solve(scene.saline.conductivity).voltages(protocol)
    assert np.all(np.isfinite(v))


def test_auto_untangles_then_remeshes_when_the_quality_drops_below_the_threshold(test_chamber, morpher, monkeypatch):
    scene, ch = test_chamber
    calls = []
    monkeypatch.setattr(morph, "_remesh", lambda morpher, deformed, spec, use_cache: calls.append(deformed) or ch)
    deformed = _press(scene, (0.0, 0.0), 2.5e-3)
    _, q = morpher.morph(deformed)
    ratio = q.min_shape / morpher.reference_quality.min_shape
    assert 0 < ratio < 1
    plain = morpher(deformed)
    # just below the threshold: the interior nodes of the worst elements are untangled first,
    # and the morph passes (only interior nodes moved, the reason says so)
    rescued = deform_chamber(morpher, deformed, scene.mesh, min_quality_ratio=min(1.0, 1.01 * ratio))
    assert rescued.path == "morph" and "untangled" in rescued.reason and not calls
    assert rescued.quality.min_shape >= 1.01 * q.min_shape
    moved = np.any(rescued.chamber.mesh.nodes != plain.mesh.nodes, axis=1)
    assert moved.any() and morpher._free[moved].all()
    # where untangling cannot lift them (here: made to do nothing), the morph falls back on quality
    with monkeypatch.context() as m:
        m.setattr(morph, "untangle", lambda nodes, *a, **k: nodes)
        below = deform_chamber(morpher, deformed, scene.mesh, min_quality_ratio=min(1.0, 1.01 * ratio))
    assert below.path == "remesh" and "quality" in below.reason and len(calls) == 1
    above = deform_chamber(morpher, deformed, scene.mesh, min_quality_ratio=0.99 * ratio)
    assert above.path == "morph" and above.quality == q and "untangled" not in above.reason
    np.testing.assert_array_equal(above.chamber.mesh.nodes, plain.mesh.nodes)  # a passing morph is untouched
    # "morph" never falls back on quality; "remesh" always remeshes
    assert deform_chamber(morpher, deformed, scene.mesh, "morph", min_quality_ratio=1.0).path == "morph"
    r = deform_chamber(morpher, deformed, scene.mesh, "remesh")
    assert r.path == "remesh" and "mode = 'remesh'" in r.reason and len(calls) == 2


def test_bad_arguments_name_the_parameter(test_chamber, morpher):
    scene, ch = test_chamber
    dome = morpher.dome
    with pytest.raises(ValueError, match="mode"):
        deform_chamber(morpher, dome, scene.mesh, mode="smooth")
    for bad in (-0.1, 1.5, float("nan")):
        with pytest.raises(ValueError, match="min_quality_ratio"):
            deform_chamber(morpher, dome, scene.mesh, min_quality_ratio=bad)
    with pytest.raises(ValueError, match="min_dihedral_deg"):
        ChamberMorpher(ch, dome, min_dihedral_deg=75.0)
    coarse = dome_from_scene(scene, n_rim=32)
    with pytest.raises(ValueError, match="same vertices and faces"):
        morpher(coarse)


def test_a_freed_morpher_refuses_to_solve(test_chamber):
    scene, ch = test_chamber
    m = ChamberMorpher(ch, dome_from_scene(scene))
    m.free()
    with pytest.raises(RuntimeError, match="freed"):
        m(_press(scene, (0.0, 0.0), 1e-3))
