"""Coupled virtual palpation: the MuJoCo bench rig, the FEM membrane, the chamber mesh, the EIT
forward model and the difference image, frame by frame (paper III.C, Fig. 4).

``Palpation(scene)`` is built once; ``run_palpation(pal, store)`` yields the frames and stores
them resumably; :mod:`jointsim.palpation.report` writes the VTU series, the Fig. 4 plots and the
summary. See :mod:`jointsim.palpation.pipeline` for the frame's stages."""

from .pipeline import MESH_PATHS, STAGES, Frame, Palpation, Segment, force_profile, program_params, run_palpation

__all__ = ["Palpation", "run_palpation", "Frame", "Segment", "STAGES", "MESH_PATHS", "force_profile", "program_params"]
