"""jointsim: coupled mechanics–EIT simulation of a saline-filled soft tactile sensor.

Pipeline stages, one subpackage each: ``scene`` (TOML setup) → ``geometry`` (dome, electrodes)
→ ``mesh`` (chamber tetrahedra, electrode patches) → ``eit`` (CEM forward, protocols, noise,
Jacobian) → ``reconstruction`` (voxel grid) → ``io`` (VTU, npz, mat)."""

import os as _os

# MKL (PARDISO) picks code paths per call unless told otherwise, and its threaded factorisation
# then differs run to run at round-off level (~1e-15); a resumed run must continue bit for bit
_os.environ.setdefault("MKL_CBWR", "AUTO")

__version__ = "0.1.0"
