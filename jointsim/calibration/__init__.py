"""Calibration maps from labelled datasets: size curves and their inverse
(:mod:`.curves`), the CoM map (:mod:`.com`), the direct voltage regression (:mod:`.regression`),
stiffness (:mod:`.stiffness`), the versioned map file and its application (:mod:`.maps`), the
sensor fingerprint a map holds for (:mod:`.fingerprint`), reading a dataset store
(:mod:`.data`), the fit and held-out evaluation (:mod:`.build`) and its report (:mod:`.report`)."""

from .build import Calibration, Settings, calibrate
from .data import Samples, load_samples, split_groups
from .fingerprint import SceneMismatchError, check_fingerprint, scene_from_provenance, sensor_fingerprint
from .maps import CalibrationMap, load_map, save_map

__all__ = [
    "Calibration", "Settings", "calibrate", "Samples", "load_samples", "split_groups", "SceneMismatchError",
    "check_fingerprint", "scene_from_provenance", "sensor_fingerprint", "CalibrationMap", "load_map", "save_map",
]
