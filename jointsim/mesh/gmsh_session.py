"""gmsh as every mesher of this package runs it: one fresh model at a time (gmsh is one global
state per process), one thread (so a mesh does not depend on the machine's core count), no
configuration file read, no signal handler installed, sizes from a closed-form field alone, and
gmsh's node and element arrays turned into plain numbered ones."""

from __future__ import annotations

import contextlib
import threading
from typing import Iterator

import numpy as np

__all__ = ["gmsh_session", "compact", "size_field"]

# Frontal-Delaunay 2-D, Delaunay 3-D, then gmsh's and Netgen's optimisers (on the default
# chamber at the three presets: smallest dihedral angle 12.6-14.8 deg, largest 149.1-149.2 deg;
# fTetWild's 14.7-17.2 / 142.0-151.5: results/mesher.md)
OPTIONS = {
    "General.Terminal": 0,
    "General.NumThreads": 1,
    "Mesh.MeshSizeExtendFromBoundary": 0,
    "Mesh.MeshSizeFromPoints": 0,
    "Mesh.MeshSizeFromCurvature": 0,
    "Mesh.Algorithm": 6,
    "Mesh.Algorithm3D": 1,
    "Mesh.Optimize": 1,
    "Mesh.OptimizeNetgen": 1,
}
_LOCK = threading.Lock()


@contextlib.contextmanager
def gmsh_session(name: str) -> Iterator:
    """The gmsh module with a fresh model ``name`` and :data:`OPTIONS` set, finalised on exit."""
    try:
        import gmsh
    except OSError as e:  # its wheel links the system's OpenGL and X11 client libraries
        raise RuntimeError(f"gmsh, the mesher, cannot load ({e}); on Debian or Ubuntu install its system "
                           "libraries: apt-get install libglu1-mesa libxcursor1 libxft2 libxinerama1") from None

    with _LOCK:
        gmsh.initialize(readConfigFiles=False, interruptible=False)
        try:
            for k, value in OPTIONS.items():
                gmsh.option.setNumber(k, value)
            gmsh.model.add(name)
            yield gmsh
        finally:
            gmsh.finalize()


def size_field(gmsh, expression: str) -> None:
    """The mesh sizes of the current model: the MathEval ``expression`` in x, y, z alone."""
    field = gmsh.model.mesh.field.add("MathEval")
    gmsh.model.mesh.field.setString(field, "F", expression)
    gmsh.model.mesh.field.setAsBackgroundMesh(field)


def compact(tags: np.ndarray, xyz: np.ndarray, elements: np.ndarray, width: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """gmsh's nodes (tags (n,), coordinates flat (3n,)) and elements (flat node tags, ``width``
    per element) as arrays numbered from 0 over the nodes the elements use, in gmsh's node
    order: (nodes (k, 3), elements (m, width), and, indexed by a node tag, its new index (−1 for
    a node no element uses; only meaningful for tags gmsh returned))."""
    position = np.zeros(int(tags.max()) + 1, np.int64)
    position[tags.astype(np.int64)] = np.arange(len(tags))
    elements = position[elements.astype(np.int64).reshape(-1, width)]
    used = np.unique(elements)
    renumber = np.full(len(tags), -1)
    renumber[used] = np.arange(len(used))
    return xyz.reshape(-1, 3)[used], renumber[elements], renumber[position]
