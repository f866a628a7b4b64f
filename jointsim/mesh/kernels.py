"""Per-tetrahedron geometry as Warp kernels on the CPU: signed volumes, barycentric
gradients and centroids (:func:`tet_geometry`), and the quality measures of a morphed chamber
(:func:`tet_quality`). These run once per frame over the whole chamber (323 k tetrahedra at
the paper's fidelity), where numpy's batched 3×3 inverse and determinant and its per-element
quality were most of the frame's mesh and forward stages: with the kernels those went from
0.61 s and 1.64 s to 0.13 s and 0.49 s (results/palpation_benchmark.md, at e6af84c and cb38c7f).

Both kernels work from the three edge vectors a, b, c out of vertex 0: 6V = a·(b × c), and the
gradients of λ_1..3 are the columns of the inverse edge matrix, (b × c, c × a, a × b) / 6V, so
no element needs a factorisation. Inputs and outputs are plain numpy arrays (the kernels alias
them on the CPU, no copy)."""

from __future__ import annotations

import numpy as np

from .._warp import on_host, wp

__all__ = ["tet_geometry", "tet_quality", "p1_stiffness"]

wp.set_module_options({"enable_backward": False})


@wp.func
def _edges(x: wp.array(dtype=wp.vec3d), tets: wp.array2d(dtype=wp.int64), k: int):
    p0 = x[tets[k, 0]]
    return x[tets[k, 1]] - p0, x[tets[k, 2]] - p0, x[tets[k, 3]] - p0


@wp.kernel
def _geometry(x: wp.array(dtype=wp.vec3d), tets: wp.array2d(dtype=wp.int64),
              volume: wp.array(dtype=wp.float64), grad: wp.array2d(dtype=wp.vec3d), centroid: wp.array(dtype=wp.vec3d)):
    k = wp.tid()
    a, b, c = _edges(x, tets, k)
    centroid[k] = x[tets[k, 0]] + (a + b + c) * wp.float64(0.25)
    # area normals of the faces opposite vertices 1, 2, 3, each ∝ ∇λ of that vertex
    n1 = wp.cross(b, c)
    n2 = wp.cross(c, a)
    n3 = wp.cross(a, b)
    vol6 = wp.dot(a, n1)
    volume[k] = vol6 / wp.float64(6.0)
    s = wp.float64(0.0)  # a flat element has no gradients: zeros, for the caller to refuse
    if vol6 != wp.float64(0.0):
        s = wp.float64(1.0) / vol6
    grad[k, 1] = n1 * s
    grad[k, 2] = n2 * s
    grad[k, 3] = n3 * s
    grad[k, 0] = -(n1 + n2 + n3) * s  # the barycentrics sum to one


@wp.func
def _cos_between(n: wp.vec3d, m: wp.vec3d) -> wp.float64:
    # the dihedral angle's cosine from the two faces' outward normals; a collapsed face: 0°
    nn = wp.dot(n, n) * wp.dot(m, m)
    if nn > wp.float64(0.0):
        return -wp.dot(n, m) / wp.sqrt(nn)
    return wp.float64(1.0)


@wp.kernel
def _quality(x: wp.array(dtype=wp.vec3d), tets: wp.array2d(dtype=wp.int64), vol6: wp.array(dtype=wp.float64),
             cos_min: wp.array(dtype=wp.float64), cos_max: wp.array(dtype=wp.float64), eta: wp.array(dtype=wp.float64)):
    k = wp.tid()
    a, b, c = _edges(x, tets, k)
    d = b - a  # edge 12
    e = c - a  # edge 13
    f = c - b  # edge 23
    # outward (for positive orientation) area normals of the faces opposite vertices 0..3
    n0 = wp.cross(d, e)
    n1 = wp.cross(c, b)
    n2 = wp.cross(a, c)
    n3 = wp.cross(b, a)
    v6 = wp.dot(a, wp.cross(b, c))
    vol6[k] = v6
    # faces i and j meet on the edge joining the other two vertices: six pairs, six angles
    c01 = _cos_between(n0, n1)
    c02 = _cos_between(n0, n2)
    c03 = _cos_between(n0, n3)
    c12 = _cos_between(n1, n2)
    c13 = _cos_between(n1, n3)
    c23 = _cos_between(n2, n3)
    cos_min[k] = wp.min(wp.min(wp.min(c01, c02), wp.min(c03, c12)), wp.min(c13, c23))
    cos_max[k] = wp.max(wp.max(wp.max(c01, c02), wp.max(c03, c12)), wp.max(c13, c23))
    # η = 6√2·V / l_rms³: 1 for the regular tetrahedron, 0 for a flat (or collapsed) one
    l2 = (wp.dot(a, a) + wp.dot(b, b) + wp.dot(c, c) + wp.dot(d, d) + wp.dot(e, e) + wp.dot(f, f)) / wp.float64(6.0)
    if l2 > wp.float64(0.0):
        eta[k] = wp.sqrt(wp.float64(2.0)) * v6 / (l2 * wp.sqrt(l2))
    else:
        eta[k] = wp.float64(0.0)


def _inputs(nodes: np.ndarray, tets: np.ndarray) -> tuple[wp.array, wp.array]:
    x = np.ascontiguousarray(nodes, dtype=np.float64)
    t = np.ascontiguousarray(tets, dtype=np.int64)
    if x.ndim != 2 or x.shape[1] != 3 or t.ndim != 2 or t.shape[1] != 4:
        raise ValueError(f"nodes (n, 3) and tets (m, 4): got {x.shape} and {t.shape}")
    return on_host(x, wp.vec3d), on_host(t, wp.int64)


def tet_geometry(nodes: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Signed volumes (m,), the gradients ∇λ_a of the four barycentric coordinates (m, 4, 3)
    and the centroids (m, 3) of the tetrahedra ``tets`` (m, 4) on ``nodes`` (n, 3). A flat
    element (zero volume) has no gradients: its rows are zeros, not infinities."""
    x, t = _inputs(nodes, tets)
    m = t.shape[0]
    volume, grad, centroid = np.empty(m), np.empty((m, 4, 3)), np.empty((m, 3))
    wp.launch(_geometry, m, inputs=[x, t, on_host(volume), on_host(grad, wp.vec3d), on_host(centroid, wp.vec3d)], device="cpu")
    return volume, grad, centroid


def tet_quality(nodes: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per element of ``tets`` (m, 4) on ``nodes`` (n, 3): 6V (signed), the smallest and largest
    cosine of its six dihedral angles, and its shape measure η = 6√2·V / l_rms³; each (m,)."""
    x, t = _inputs(nodes, tets)
    m = t.shape[0]
    vol6, cos_min, cos_max, eta = (np.empty(m) for _ in range(4))
    wp.launch(_quality, m, inputs=[x, t, *map(on_host, (vol6, cos_min, cos_max, eta))], device="cpu")
    return vol6, cos_min, cos_max, eta


@wp.kernel
def _p1_stiffness(grad: wp.array2d(dtype=wp.vec3d), volume: wp.array(dtype=wp.float64), K: wp.array3d(dtype=wp.float64)):
    # ∫_k ∇λ_a·∇λ_b = |V_k| ∇λ_a·∇λ_b: the gradients are constant on the element
    k = wp.tid()
    v = wp.abs(volume[k])
    for a in range(4):
        for b in range(4):
            K[k, a, b] = v * wp.dot(grad[k, a], grad[k, b])


def p1_stiffness(gradients: np.ndarray, signed_volumes: np.ndarray) -> np.ndarray:
    """The P1 Laplacian's local matrices ∫_k ∇λ_a·∇λ_b = |V_k| ∇λ_a·∇λ_b (n_tets, 4, 4), from
    the barycentric gradients (n_tets, 4, 3) and signed volumes (n_tets,) of
    :func:`tet_geometry`: the EIT's unit-conductivity stiffness and the morph's Laplacian. A
    kernel: a morphed frame assembles afresh, and at the paper's 323 k tetrahedra numpy's
    batched product was a visible part of the forward stage."""
    K = np.empty((len(signed_volumes), 4, 4))
    wp.launch(_p1_stiffness, len(signed_volumes), inputs=[on_host(gradients, wp.vec3d), on_host(signed_volumes), on_host(K)], device="cpu")
    return K
