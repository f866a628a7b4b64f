"""Synthetic labelled datasets (`jointsim dataset`): press trajectories drawn over target size,
position, depth and stiffness with domain randomisation, each sample's voltages (clean and
noisy), labels, force, displaced volume and image metrics, stored resumably in one HDF5 file.

``generate_dataset(scene, n, out)`` runs it (local worker processes, or a Dask cluster);
:mod:`jointsim.dataset.generate` holds the draw and the press of one group, and the schema;
:mod:`jointsim.dataset.presses` the explicit press lists (a grid, a CSV) a run may take instead
of drawn presses."""

from .generate import (
    SCHEMA_NAME, SCHEMA_VERSION, STAGES, DatasetSetup, GroupDraw, dataset_params, dataset_schema, draw_group,
    group_indices, n_groups,
)
from .presses import PressList, press_grid, read_presses
from .runner import DatasetRun, default_workers, generate_dataset

__all__ = [
    "generate_dataset", "DatasetRun", "default_workers", "DatasetSetup", "GroupDraw", "draw_group", "dataset_schema",
    "dataset_params", "group_indices", "n_groups", "SCHEMA_NAME", "SCHEMA_VERSION", "STAGES",
    "PressList", "press_grid", "read_presses",
]
