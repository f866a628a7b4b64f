"""Property-based fuzz of scene files (issue 48): whatever a scene mapping holds, loading it
gives a Scene or a SceneError naming a key — never another exception (a traceback)."""

import math

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from jointsim.scene import MESH_PRESETS, SceneError, scene_from_dict

# the keys each section knows (and a few it does not), values of every TOML kind around them
SECTIONS = {
    "chamber": ["base_radius_mm", "dome_height_mm", "membrane_thickness_mm"],
    "electrodes": ["count", "ring_radius_mm", "diameter_mm", "ground_diameter_mm", "contact_impedance_ohm_m2",
                   "ground_contact_impedance_ohm_m2", "contact_impedance_by_freq_ohm_m2", "first_angle_deg", "reference",
                   "ring", "grid", "disc"],
    "saline": ["conductivity_s_per_m"],
    "drive": ["current_ua", "frequencies_hz", "skip", "measure", "stim_ua", "meas"],
    "noise": ["snr_db", "seed", "drift_per_s", "frame_rate_hz"],
    "mesh": ["preset", "max_edge_mm", "electrode_refinement", "refinement_zone_mm", "grading", "element_order", "update",
             "rim_refinement", "dome_rim_vertices"],
    "membrane": ["law", "shear_modulus_kpa", "yeoh_c_kpa", "bulk_ratio", "reservoir_pressure_pa", "chamber", "rim_vertices",
                 "volumetric", "moulding", "element", "layers"],
    "target": ["diameter_mm", "radius_mm", "kind", "friction", "youngs_modulus_kpa", "poisson_ratio"],
    "reconstruction": ["cells", "lambda_method", "lambda_target_diameter_mm", "lambda_depth_mm", "lambda_xy_mm"],
    "palpation": ["mode", "target_diameters_mm", "depth_mm", "speed_mm_per_s", "hold_s", "xy_mm", "force_n", "cells"],
    "dataset": ["radius_mm", "r_max_mm", "depth_mm", "samples_per_press", "membrane_scale", "snr_db", "electrode_jitter_mm",
                "images", "control", "force_n"],
}
scalars = st.one_of(
    st.integers(-10**20, 10**20), st.floats(allow_nan=True, allow_infinity=True), st.booleans(),
    st.sampled_from(["", "none", "auto", "cap", "flat", "yeoh", "ring", "adjacent", *MESH_PRESETS]),
    st.floats(-1e3, 1e3), st.integers(-5, 40),
)
values = st.recursive(scalars, lambda inner: st.one_of(st.lists(inner, max_size=5),
                                                         st.dictionaries(st.sampled_from(["count", "radius_mm", "xy_mm", "x"]), inner, max_size=3)),
                      max_leaves=12)
tables = st.lists(st.dictionaries(st.sampled_from(["count", "radius_mm", "diameter_mm", "phase_deg", "pitch_mm", "kind",
                                                   "within_mm", "xy_mm"]), values, max_size=4), max_size=3)


@st.composite
def scenes(draw):
    data = {}
    for section in draw(st.lists(st.sampled_from(sorted(SECTIONS) + ["optics"]), max_size=4, unique=True)):
        keys = SECTIONS.get(section, ["x"]) + ["unknown_key"]
        body = {}
        for k in draw(st.lists(st.sampled_from(keys), max_size=4, unique=True)):
            body[k] = draw(tables) if k in ("ring", "grid", "disc") else draw(values)
        data[section] = draw(st.one_of(st.just(body), values)) if section == "optics" else body
    return data


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(scenes())
def test_any_scene_mapping_loads_or_is_refused_with_a_scene_error(data):
    try:
        s = scene_from_dict(data)
    except SceneError as e:
        assert str(e) and "\n" not in str(e).strip()
        return
    # what loads is a usable scene: finite sizes, a consistent electrode count
    assert math.isfinite(s.chamber.base_radius) and s.electrodes.count >= 2
