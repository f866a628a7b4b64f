"""The sensor a calibration map was built for, as a fingerprint of named scene values.

Owns which scene values define the sensor for calibration (chamber, electrode geometry, drive
and protocol, chamber-mesh resolution, reconstruction grid, λ method and λ's press, the membrane's nominal
material and reservoir), reading them from a scene or from a record store's provenance, and
comparing two fingerprints with a message that names every value that differs. Values a
dataset randomises around the scene (saline conductivity, contact impedance, noise level) and
numerical resolutions of the mechanics are left out: a map is meant to hold across them.
"""

from __future__ import annotations

import hashlib
import json
import math
import tomllib
from dataclasses import fields, replace
from typing import Any, Mapping

from ..scene import LATER_DEFAULTS, MeshSpec, ReconstructionSpec, Scene, scene_from_dict

__all__ = [
    "SENSOR_KEYS",
    "SceneMismatchError",
    "sensor_fingerprint",
    "provenance_fingerprint",
    "fingerprint_digest",
    "fingerprint_differences",
    "check_fingerprint",
    "scene_from_provenance",
]

# section → the values of it that define the sensor (Scene dataclass attribute names)
SENSOR_KEYS: dict[str, tuple[str, ...]] = {
    "chamber": ("base_radius", "dome_height", "membrane_thickness"),
    "electrodes": ("count", "ring_radius", "diameter", "ground_diameter", "first_angle_deg"),
    "drive": ("current", "skip"),
    "mesh": ("preset", "max_edge", "electrode_refinement", "refinement_zone"),
    "membrane": ("law", "shear_modulus", "yeoh_c", "reservoir_pressure", "chamber"),
    "reconstruction": ("cells", "lambda_method"),
}
# values that define the sensor only where they differ from the default they had before they
# existed, so maps and datasets recorded without them still match the scenes they were built for
# (the representative press λ is chosen on: before [reconstruction], a paper-scene palpation's)
OPTIONAL_KEYS: dict[str, Any] = {
    "mesh.element_order": 1, "membrane.moulding": "cap", "electrodes.discs": [], "electrodes.reference": True,
    "drive.measure": "reference", "drive.stim": None, "drive.meas": None, "reconstruction.lambda_radius": 7.5e-3,
    "reconstruction.lambda_depth": 3e-3, "reconstruction.lambda_xy": [0.0, 0.0],
    # (a user's chamber by its file's SHA-256 and outline, wherever the file lies)
    **{f"{section}.{key}": before for (section, key), before in LATER_DEFAULTS.items() if key != "surface_file"},
}
# sections values were recorded in before they moved (scene.MOVED_KEYS): read there when a
# record has no section of their own
LEGACY_SECTIONS: dict[str, str] = {"reconstruction": "palpation"}
_REL_TOL = 1e-9  # mm → m conversions of the same text agree far better than this


class SceneMismatchError(ValueError):
    """A calibration map applied to a scene it was not built for; the message names the values."""


def _plain(v: Any) -> Any:
    return [_plain(x) for x in v] if isinstance(v, (tuple, list)) else v


def sensor_fingerprint(scene: Scene | Mapping[str, Any]) -> dict[str, Any]:
    """``{"section.key": value}`` of the sensor-defining scene values (SI units), JSON-ready,
    of a :class:`Scene` or of its ``to_dict()`` form (as a dataset's provenance holds it)."""
    d = scene.to_dict() if isinstance(scene, Scene) else dict(scene)
    for new, old in LEGACY_SECTIONS.items():
        if new not in d and old in d:
            d[new] = d[old]
    try:
        fp = {f"{s}.{k}": _plain(d[s][k]) for s, keys in SENSOR_KEYS.items() for k in keys}
    except (KeyError, TypeError) as e:
        raise ValueError(f"the scene record lacks the sensor value {e}: cannot tell which sensor it describes") from None
    for key, default in OPTIONAL_KEYS.items():
        s, k = key.split(".")
        if not _same(v := _plain(d[s].get(k, default)), default):
            fp[key] = v
    return fp


def _legacy(fp: Mapping[str, Any]) -> dict[str, Any]:
    """A stored fingerprint with the keys of moved sections under their new names."""
    out = {}
    for k, v in fp.items():
        s, _, key = k.partition(".")
        for new, old in LEGACY_SECTIONS.items():
            if s == old and key in SENSOR_KEYS[new]:
                k = f"{new}.{key}"
        out[k] = v
    return out


def provenance_fingerprint(provenance: Mapping[str, Any]) -> dict[str, Any]:
    """The sensor fingerprint of a record store: from the effective scene its run recorded
    (``params["scene"]``, as ``jointsim dataset`` writes it), else from its scene TOML and
    recorded overrides (:func:`scene_from_provenance`)."""
    scene = (provenance.get("params") or {}).get("scene")
    if isinstance(scene, Mapping) and all(s in scene or LEGACY_SECTIONS.get(s) in scene for s in SENSOR_KEYS):
        return sensor_fingerprint(scene)
    return sensor_fingerprint(scene_from_provenance(provenance))


def fingerprint_digest(fp: Mapping[str, Any]) -> str:
    """SHA-256 (16 hex digits) of a fingerprint, for file names and reports."""
    return hashlib.sha256(json.dumps(dict(fp), sort_keys=True).encode()).hexdigest()[:16]


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if isinstance(a, (int, float)) and isinstance(b, (int, float)) and not isinstance(a, bool):
        return math.isclose(a, b, rel_tol=_REL_TOL, abs_tol=0.0)
    return a == b


def fingerprint_differences(built: Mapping[str, Any], given: Mapping[str, Any]) -> list[str]:
    """One line per key whose value differs (or is absent on one side), sorted by key."""
    out = []
    built, given = _legacy(built), _legacy(given)
    for k in sorted(set(built) | set(given)):
        a, b = built.get(k, "absent"), given.get(k, "absent")
        if not _same(a, b):
            out.append(f"{k}: {a!r} in the map, {b!r} in the scene")
    return out


def check_fingerprint(built: Mapping[str, Any], given: Mapping[str, Any], what: str = "this calibration map") -> None:
    """Raise :class:`SceneMismatchError` naming every differing value when ``given`` (the scene
    in use) is not the sensor ``built`` (the map's) describes."""
    if diff := fingerprint_differences(built, given):
        preset = built.get("mesh.preset")
        # the commonest case: a quick-look map of `jointsim dataset --mesh test` on the default scene
        hint = (f" (the map was built on the {preset!r} mesh preset: give --mesh {preset})"
                if preset is not None and preset != given.get("mesh.preset") else "")
        raise SceneMismatchError(
            f"{what} was built for another sensor; {len(diff)} value(s) differ: " + "; ".join(diff)
            + f". Build a map from a dataset of this scene (jointsim calibrate), or use the scene the map was built for{hint}."
        )


def scene_from_provenance(provenance: Mapping[str, Any]) -> Scene:
    """The scene a record store was computed for: its scene TOML with the run's recorded
    overrides applied (``params["mesh"]``: the chamber mesh spec, else the mesh spec (and the
    membrane's rim vertices) of the resolved ``params["scene"]``, else ``params["mesh_preset"]``;
    ``params["reconstruction"]``, or before it ``params["palpation"]["cells"]`` /
    ``["lambda_method"]``, as palpation and dataset runs record them)."""
    text = provenance.get("scene_toml")
    if not isinstance(text, str) or not text.strip():
        raise ValueError("the store's provenance has no scene TOML: cannot tell which sensor its data is for")
    scene = scene_from_dict(tomllib.loads(text))
    params = provenance.get("params") or {}
    mesh = params.get("mesh")
    ran = params.get("scene") if isinstance(params.get("scene"), Mapping) else {}
    if not isinstance(mesh, Mapping) and isinstance(ran.get("mesh"), Mapping):
        # the scene as a dataset run resolved it: its fidelity even where the TOML names none
        # and the default has changed since
        mesh = ran["mesh"]
        if isinstance(rim := (ran.get("membrane") or {}).get("rim_vertices"), int):
            scene = replace(scene, membrane=replace(scene.membrane, rim_vertices=rim))
    if isinstance(mesh, Mapping):
        known = {f.name for f in fields(MeshSpec)}
        scene = replace(scene, mesh=replace(scene.mesh, **{k: v for k, v in mesh.items() if k in known}))
    elif isinstance(params.get("mesh_preset"), str):
        scene = scene.with_mesh_preset(params["mesh_preset"])
    rec = params.get("reconstruction")
    if isinstance(rec, Mapping):
        known = {f.name for f in fields(ReconstructionSpec)}
        over = {k: (tuple(v) if isinstance(v, list) else v) for k, v in rec.items() if k in known}
        scene = replace(scene, reconstruction=replace(scene.reconstruction, **over))
    elif isinstance(pal := params.get("palpation"), Mapping):
        over = {k: pal[k] for k in ("cells", "lambda_method") if k in pal}
        scene = replace(scene, reconstruction=replace(scene.reconstruction, **over))
    return scene
