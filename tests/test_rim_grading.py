"""The chamber mesh graded at the electrodes' outlines ([mesh] rim_refinement), the chamber's
dome resolution ([mesh] dome_rim_vertices) and the dataset_p2 preset that uses them."""

from dataclasses import replace

import numpy as np
import pytest

from jointsim.eit.forward import ForwardModel
from jointsim.eit.protocol import skip_protocol
from jointsim.mesh.chamber import chamber_mesh, reference_surface
from jointsim.scene import MM, SceneError, scene_from_dict


def _graded(scene, rim: float, order: int = 2):
    # a coarse bulk (3.5 mm) with no disc refinement: only the rim term refines
    return replace(scene, mesh=replace(scene.mesh, preset="custom", max_edge=3.5 * MM, electrode_refinement=1.0,
                                       rim_refinement=rim, grading=0.7, element_order=order))


def _rim_edges(chamber) -> np.ndarray:
    """Lengths (m) of the base's mesh edges that lie on an electrode's outline."""
    m, lay = chamber.mesh, chamber.layout
    f = m.boundary_faces
    base = f[np.all(np.abs(m.nodes[f][..., 2]) < 1e-12, axis=1)]
    e = np.unique(np.sort(base[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2), axis=1), axis=0)
    a, b = m.nodes[e[:, 0]], m.nodes[e[:, 1]]
    on = np.zeros(len(e), bool)
    for c, r in zip(lay.centres, lay.radii):
        on |= (np.abs(np.hypot(*(a[:, :2] - c[:2]).T) - r) < 1e-9) & (np.abs(np.hypot(*(b[:, :2] - c[:2]).T) - r) < 1e-9)
    return np.linalg.norm(a[on] - b[on], axis=1)


def test_rim_refinement_sizes_the_outlines_and_leaves_the_unrefined_mesh_as_it_was(paper_scene, _mesh_cache):
    off = chamber_mesh(_graded(paper_scene, 1.0))
    on = chamber_mesh(_graded(paper_scene, 10.0))
    # gmsh keeps to the field: the outline is split into chords of at most h_max / rim_refinement
    # (+ 1 % for the chord of a circle against the field's value at its ends)
    assert _rim_edges(on).max() <= 1.01 * 3.5 * MM / 10
    assert _rim_edges(off).max() > 1.0 * MM
    # off, the key is left out of the mesh's identity: the same mesh as a spec without the term
    assert chamber_mesh(replace(paper_scene, mesh=replace(_graded(paper_scene, 1.0).mesh, rim_refinement=1.0))).key == off.key


def test_the_current_carrying_electrodes_converge_as_the_rims_are_refined(paper_scene, _mesh_cache):
    # the complete electrode model's current density peaks at an electrode's outline: on a 3.5 mm
    # bulk P2 mesh the skip-8 voltages (dominated by the two driven electrodes) approach those at
    # 16x rim refinement monotonically; the rest of the voltages hardly depend on the rims
    p = skip_protocol(16, 8, 120e-6)
    carrying = (np.abs(p.stim) > 0).ravel()
    v = {}
    for rim in (1.0, 4.0, 8.0, 16.0):
        s = _graded(paper_scene, rim)
        v[rim] = ForwardModel.from_chamber(chamber_mesh(s), s).solve(s.saline.conductivity).voltages(p)
    err = {r: np.linalg.norm(v[r] - v[16.0]) / np.linalg.norm(v[16.0]) for r in (1.0, 4.0, 8.0)}
    assert err[1.0] > err[4.0] > err[8.0]
    assert err[8.0] < 0.3 * err[1.0]  # measured 0.18
    other = np.linalg.norm((v[1.0] - v[16.0])[~carrying]) / np.linalg.norm(v[16.0][~carrying])
    assert other < 0.1 * err[1.0]  # measured 0.04: the error sits on the driven electrodes


def test_dataset_p2_preset_and_the_new_mesh_keys():
    s = scene_from_dict({"mesh": {"preset": "dataset_p2"}})
    assert (s.mesh.element_order, s.mesh.rim_refinement, s.mesh.dome_rim_vertices) == (2, 10.0, 144)
    assert s.mesh.max_edge == pytest.approx(2.6 * MM) and s.mesh.grading == pytest.approx(0.6)
    # another preset resets the sizes and the element order, P1 where it names none (as it parses)
    t = s.with_mesh_preset("test")
    assert (t.mesh.rim_refinement, t.mesh.dome_rim_vertices, t.mesh.grading, t.mesh.element_order) == (1.0, 0, 0.35, 1)
    assert t.mesh == scene_from_dict({"mesh": {"preset": "test"}}).mesh
    # a scene that names no fidelity gets dataset_p2's
    assert scene_from_dict({}).mesh == s.mesh
    assert s.with_mesh_preset("dataset_p2").mesh == s.mesh
    # sizes given by hand make the mesh a custom one
    assert scene_from_dict({"mesh": {"rim_refinement": 5.0}}).mesh.preset == "custom"
    with pytest.raises(SceneError, match=r"mesh.rim_refinement = 0.5: .*\[1, 100\]"):
        scene_from_dict({"mesh": {"rim_refinement": 0.5}})
    with pytest.raises(SceneError, match="mesh.dome_rim_vertices = 8: must be 0"):
        scene_from_dict({"mesh": {"dome_rim_vertices": 8}})


def test_dome_rim_vertices_sets_the_chamber_dome(paper_scene):
    def rim_vertices(scene) -> int:
        v = reference_surface(scene).vertices
        return int(np.sum((np.abs(v[:, 2]) < 1e-12) & (np.hypot(v[:, 0], v[:, 1]) > 0.99 * scene.chamber.base_radius)))

    assert rim_vertices(replace(paper_scene, mesh=replace(paper_scene.mesh, dome_rim_vertices=144))) == 144
    assert rim_vertices(paper_scene) == 144  # dataset_p2's
    assert rim_vertices(paper_scene.with_mesh_preset("dataset")) == 96  # 0: from max_edge, at least geometry.DOME_RIM_VERTICES
