"""jointsim: coupled mechanics–EIT simulation of a saline-filled soft tactile sensor.

Pipeline stages, one subpackage each: ``scene`` (TOML setup) → ``geometry`` (dome, electrodes)
→ ``mesh`` (chamber tetrahedra, electrode patches) → ``eit`` (CEM forward, protocols, noise,
Jacobian) → ``reconstruction`` (voxel grid) → ``io`` (VTU, npz, mat)."""

__version__ = "0.1.0"
