import json

import numpy as np
import pytest

from conftest import PAPER_SCENE, ROOT

from jointsim.scene import MEMBRANE_RIM_VERTICES, SCENES_DIR, SceneError, load_scene, scene_from_dict


def test_paper_scene_holds_the_papers_values(paper_scene):
    s = paper_scene
    assert s.electrodes.count == 16
    assert s.electrodes.ring_radius == pytest.approx(15e-3)
    assert s.chamber.membrane_thickness == pytest.approx(2e-3)
    assert s.drive.current == pytest.approx(120e-6)
    assert len(s.drive.frequencies) == 16
    assert s.drive.frequencies[0] == 2750 and s.drive.frequencies[-1] == 13625
    assert all(b - a == pytest.approx(725) for a, b in zip(s.drive.frequencies, s.drive.frequencies[1:]))
    assert s.drive.skip == 8
    assert s.noise.snr_db == pytest.approx(74.2)


@pytest.mark.parametrize(
    "data, key",
    [
        ({"chamber": {"base_radius_mm": -1}}, "chamber.base_radius_mm"),
        ({"chamber": {"dome_height_mm": 30}}, "chamber.dome_height_mm"),
        ({"electrodes": {"ring_radius_mm": 25}}, "electrodes.ring_radius_mm"),
        ({"electrodes": {"count": 2}}, "electrodes.count"),
        ({"electrodes": {"diameter_mm": 8}}, "electrodes.diameter_mm"),
        ({"electrodes": {"contact_impedance_ohm_m2": [1e-3] * 15}}, "electrodes.contact_impedance_ohm_m2"),
        ({"electrodes": {"contact_impedance_ohm_m2": -1e-3}}, "electrodes.contact_impedance_ohm_m2"),
        ({"saline": {"conductivity_s_per_m": 0}}, "saline.conductivity_s_per_m"),
        ({"saline": {"conductivity_s_per_m": "salty"}}, "saline.conductivity_s_per_m"),
        ({"drive": {"current_ua": float("nan")}}, "drive.current_ua"),
        ({"drive": {"skip": 9}}, "drive.skip"),
        ({"noise": {"snr_db": -3}}, "noise.snr_db"),
        ({"mesh": {"preset": "huge"}}, "mesh.preset"),
        ({"mesh": {"element_order": 3}}, "mesh.element_order"),
        ({"saline": {"conductivity": 0.4}}, "conductivity_s_per_m"),  # unit missing from the key
        ({"optics": {}}, "optics"),
        ({"membrane": {"law": "mooney"}}, "membrane.law"),
        ({"membrane": {"shear_modulus_kpa": 0}}, "membrane.shear_modulus_kpa"),
        ({"membrane": {"layers": 0}}, "membrane.layers"),
        ({"membrane": {"law": "yeoh", "yeoh_c_kpa": [-1, 0, 0]}}, r"membrane.yeoh_c_kpa\[0\]"),
        ({"mesh": {"update": "sometimes"}}, "mesh.update"),
        ({"reconstruction": {"cells": 10}}, "reconstruction.cells"),
        ({"reconstruction": {"lambda_method": "guess"}}, "reconstruction.lambda_method"),
        ({"reconstruction": {"lambda_depth_mm": 0}}, "reconstruction.lambda_depth_mm"),
        ({"reconstruction": {"lambda_target_radius_mm": -2}}, "reconstruction.lambda_target_radius_mm"),
        ({"reconstruction": {"lambda_xy_mm": [19.5, 5.0]}}, "reconstruction.lambda_xy_mm"),
        ({"reconstruction": {"lambda_target_radius_mm": 5, "lambda_target_diameter_mm": 10}}, r"\[reconstruction\]"),
    ],
)
def test_bad_values_are_rejected_naming_the_key(data, key):
    with pytest.raises(SceneError, match=key if "\\[" in key else key.replace(".", r"\.")):
        scene_from_dict(data)


def test_error_states_the_allowed_range():
    # the ring's discs end at least EDGE_CLEARANCE_MM (0.5) inside the 20 mm base: 20 - 1 - 0.5
    with pytest.raises(SceneError, match=r"must be in \(3, 18.5\]"):
        scene_from_dict({"electrodes": {"ring_radius_mm": 25}})


def test_units_are_converted_to_si():
    s = scene_from_dict({"chamber": {"base_radius_mm": 25, "dome_height_mm": 12}, "drive": {"current_ua": 50}})
    assert s.chamber.base_radius == pytest.approx(0.025)
    assert s.drive.current == pytest.approx(50e-6)


def test_missing_file_and_bad_toml(tmp_path):
    with pytest.raises(SceneError, match="not found"):
        load_scene(tmp_path / "nope.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[chamber\n")
    with pytest.raises(SceneError, match="not valid TOML"):
        load_scene(bad)


def test_digest_changes_with_content(paper_scene):
    assert paper_scene.digest() != paper_scene.with_mesh_preset("paper").digest()
    assert paper_scene.digest("chamber") == paper_scene.with_mesh_preset("paper").digest("chamber")


def test_the_membrane_mesh_follows_the_fidelity_unless_given(paper_scene):
    assert paper_scene.mesh.preset == "dataset_p2" and paper_scene.membrane.rim_vertices == MEMBRANE_RIM_VERTICES["dataset_p2"]
    assert paper_scene.with_mesh_preset("paper").membrane.rim_vertices == MEMBRANE_RIM_VERTICES["paper"]
    assert scene_from_dict({"mesh": {"preset": "paper"}}).membrane.rim_vertices == MEMBRANE_RIM_VERTICES["paper"]
    assert scene_from_dict({"mesh": {"max_edge_mm": 1.5}}).membrane.rim_vertices == MEMBRANE_RIM_VERTICES["custom"]
    given = scene_from_dict({"mesh": {"preset": "paper"}, "membrane": {"rim_vertices": 40}})
    assert given.membrane.rim_vertices == 40


def test_the_converged_fidelities_get_the_mesh_the_benchmark_shows_within_2_percent():
    # the paper's (and finer) fidelity must get the coarsest two-layer membrane whose force is
    # within 2 % of the finest mesh's at every depth in results/mechanics_benchmark.json; the
    # dataset's is a coarser one, by choice, whose error is what README states (2.4-5.8 %)
    rows = json.loads((ROOT / "results" / "mechanics_benchmark.json").read_text())["rows"]
    two = sorted((r for r in rows if r["layers"] == 2 and r["apex_mm"] == 0 and r["volumetric"] == "pointwise"), key=lambda r: r["n_rim"])
    force = {r["n_rim"]: np.array([s["force_mN"] for s in r["steps"] if s["depth_mm"] in (1.0, 2.0, 3.0)]) for r in two}
    ref = force[two[-1]["n_rim"]]
    err = {n: np.abs(f / ref - 1).max() for n, f in force.items()}
    converged = min(n for n, e in err.items() if e <= 0.02 and all(err[m] <= 0.02 for m in err if m > n))
    assert MEMBRANE_RIM_VERTICES["paper"] == MEMBRANE_RIM_VERTICES["fine"] == MEMBRANE_RIM_VERTICES["custom"] == converged
    assert 0.02 < err[MEMBRANE_RIM_VERTICES["dataset"]] < 0.06


def test_a_scene_extends_another_section_by_section(tmp_path, paper_scene):
    import tomllib
    from dataclasses import replace

    from jointsim.scene import scene_toml

    study = ROOT / "scenes" / "paper_sensor_stiffness.toml"
    s = load_scene(study)
    assert s.name == "paper_sensor_stiffness"
    assert s.dataset.rigid_fraction == 0.0
    # every other value is the paper scene's, [dataset] included, at the fidelity the study pins
    assert s.mesh == paper_scene.with_mesh_preset("dataset").mesh
    assert replace(s, name=paper_scene.name, dataset=replace(s.dataset, rigid_fraction=1.0), mesh=paper_scene.mesh) == paper_scene
    # the provenance text is self-contained and reads back as the same scene
    text = scene_toml(study)
    assert "extends" not in tomllib.loads(text)
    assert scene_from_dict(tomllib.loads(text)) == s
    assert scene_toml(PAPER_SCENE) == PAPER_SCENE.read_text()


def test_extends_errors_name_the_problem(tmp_path):
    a, b = tmp_path / "a.toml", tmp_path / "b.toml"
    a.write_text('extends = "b.toml"\n')
    b.write_text('extends = "a.toml"\n')
    with pytest.raises(SceneError, match="cycle"):
        load_scene(a)
    a.write_text('extends = "missing.toml"\n')
    with pytest.raises(SceneError, match="not found"):
        load_scene(a)
    a.write_text("extends = 3\n")
    with pytest.raises(SceneError, match="extends = 3"):
        load_scene(a)
    a.write_text('extends = "b.toml"\n[chamber]\nbase_radius_mm = -1\n')
    b.write_text("")
    with pytest.raises(SceneError, match="chamber.base_radius_mm"):
        load_scene(a)


def test_a_wedge_membrane_too_coarse_for_its_force_is_warned_of():
    """One layer of wedges below 48 rim vertices is soft (32: 14 % at 1 mm, the convergence test
    in test_membrane): a scene asking for it is loaded, with a warning that names the parameter
    and the rim count from which forces are within a few per cent; 48 and the tetrahedra are not."""
    import warnings

    with pytest.warns(UserWarning, match=r"membrane.rim_vertices = 32: .*give >= 48"):
        assert scene_from_dict({"membrane": {"rim_vertices": 32}}).membrane.rim_vertices == 32
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        scene_from_dict({"membrane": {"rim_vertices": 48}})
        scene_from_dict({"membrane": {"rim_vertices": 32, "element": "p2_tet"}})


def test_a_scene_file_must_describe_the_sensor_or_extend_one(tmp_path):
    """An empty file, or one without [electrodes], is refused naming what is missing and how to
    take the paper's sensor; ``extends`` takes a shipped scene by name from any folder."""
    empty, partial, named = tmp_path / "empty.toml", tmp_path / "partial.toml", tmp_path / "named.toml"
    empty.write_text("")
    partial.write_text("[chamber]\nbase_radius_mm = 20.0\n")
    named.write_text('extends = "paper_sensor"\n[noise]\nsnr_db = 60.0\n')
    with pytest.raises(SceneError, match=r"empty\.toml: no \[chamber\] or \[electrodes\] section.*extends = \"paper_sensor\""):
        load_scene(empty)
    with pytest.raises(SceneError, match=r"partial\.toml: no \[electrodes\] section"):
        load_scene(partial)
    scene = load_scene(named)
    assert scene.noise.snr_db == 60.0 and scene.electrodes == load_scene(SCENES_DIR / "paper_sensor.toml").electrodes


def test_a_scene_file_that_is_not_utf8_text_is_refused_naming_it(tmp_path):
    f = tmp_path / "utf16.toml"
    f.write_text('extends = "paper_sensor"\n', encoding="utf-16")
    with pytest.raises(SceneError, match=r"utf16\.toml: not a UTF-8 text file"):
        load_scene(f)


def test_keys_that_moved_section_are_read_from_the_old_place_with_a_warning(tmp_path):
    """[palpation] cells, lambda_method and mesh_update, from before [reconstruction] and
    [mesh] update held them, still load (warned of) into their new place; given in both places
    with different values they are refused naming both."""
    old = {"palpation": {"cells": 2000, "lambda_method": "gcv", "mesh_update": "remesh", "depth_mm": 2.0}}
    with pytest.warns(UserWarning, match=r"palpation.cells -> reconstruction.cells.*palpation.mesh_update -> mesh.update"):
        s = scene_from_dict(old)
    assert (s.reconstruction.cells, s.reconstruction.lambda_method, s.mesh.update) == (2000, "gcv", "remesh")
    assert s.palpation.depth == pytest.approx(2e-3)
    with pytest.raises(SceneError, match=r"palpation.cells = 2000 and reconstruction.cells = 3000"):
        scene_from_dict({"palpation": {"cells": 2000}, "reconstruction": {"cells": 3000}})
    # an old key in a scene that extends one written with the new key: the extending file wins
    (tmp_path / "old.toml").write_text('extends = "paper_sensor"\n[palpation]\nmesh_update = "morph"\n')
    with pytest.warns(UserWarning, match="mesh.update"):
        assert load_scene(tmp_path / "old.toml").mesh.update == "morph"


def test_a_size_given_by_radius_replaces_the_extended_scenes_diameter(tmp_path):
    """The paper scene gives λ's press by diameter; a scene extending it may give a radius."""
    (tmp_path / "r.toml").write_text('extends = "paper_sensor"\n[reconstruction]\nlambda_target_radius_mm = 4.0\n'
                                     '[palpation]\ntarget_radii_mm = [3.0]\n')
    s = load_scene(tmp_path / "r.toml")
    assert s.reconstruction.lambda_radius == pytest.approx(4e-3) and s.palpation.target_radii == pytest.approx((3e-3,))


def test_the_papers_reconstruction_is_the_one_every_job_images_with(paper_scene):
    r = paper_scene.reconstruction
    assert (r.cells, r.lambda_method) == (7000, "kfold")  # paper II.C: 7 k hexahedra, λ by cross-validation
    assert (r.lambda_radius, r.lambda_depth, *r.lambda_xy) == pytest.approx((7.5e-3, 3e-3, 0.0, 0.0))


def test_the_parameter_table_holds_every_key_the_shipped_scenes_use():
    """The documentation's scene reference is generated from parameter_table (the parse's own
    reads): every key a shipped scene file writes is in it, with what is allowed for numbers."""
    import tomllib

    from jointsim.scene import SCENES_DIR, parameter_table

    rows = {(r["section"], r["key"]): r for r in parameter_table()}
    for path in SCENES_DIR.glob("*.toml"):
        data = tomllib.loads(path.read_text())
        for section, table in data.items():
            if not isinstance(table, dict):
                continue
            for key, value in table.items():
                if isinstance(value, list) and value and isinstance(value[0], dict):  # [[electrodes.ring]]
                    keys = [(f"{section}.{key}", k) for item in value for k in item]
                else:
                    keys = [(section, key)]
                for k in keys:
                    assert k in rows, (path.name, k)
    assert rows[("chamber", "base_radius_mm")]["allowed"] == "[1, 500]"
    assert rows[("membrane", "element")]["kind"] == "choice"
