"""Validation of the membrane mechanics: the paper's dome (a 2 mm thick spherical cap, base
radius 20 mm, height 10 mm to the inner apex, base clamped) under a small downward load spread
uniformly over the outer surface within 3 mm of the axis, linear elastic, μ 22 kPa, κ = 10 μ and
1000 μ. The 3-D P2 membrane of jointsim (both volumetric forms, several meshes) against an
independent axisymmetric reference written here: Taylor–Hood P2–P1 on curved 6-node triangles in
the (r, z) half-plane, plain numpy/scipy, itself checked against Lamé's thick hollow sphere.

    python benchmarks/bench_dome_apex_load.py                      # writes results/dome_apex_load.{md,json}
    python benchmarks/bench_dome_apex_load.py --levels 4 8 16 32   # a finer reference (nt = 32 adds ~15 s)
    python benchmarks/bench_dome_apex_load.py --report             # rewrites the .md from the .json
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
import scipy.sparse as sp
from scipy.optimize import brentq
from scipy.sparse.linalg import spsolve

from _machine import machine, speed_reference, write_pair

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "results" / "dome_apex_load"

# the problem, SI units: the sphere about (0, 0, ZC) between radii RI and RO, the part above z = 0
ZC, RI, RO = -0.015, 0.025, 0.027
RPATCH, FTOT, MU = 3e-3, 1e-3, 22e3  # patch: horizontal radius on the outer surface; total load N; shear modulus Pa
KAPPAS = (10, 1000)  # κ / μ
LEVELS = (4, 8, 16)  # reference elements through the thickness (the arc is meshed in proportion)
MESHES_3D = [(64, 1), (64, 2), (96, 2), (64, 3)]  # (rim vertices, prism layers)
FORMS_3D = ("pointwise", "mean_dilatation", "wedge15")  # the last: 15-node wedges, their own projected form
F3D = 1e-4  # the 3-D load, N: small enough that the finite-strain model responds linearly
VERIFY_TOL = 1e-3

# ============================================================================ axisymmetric reference
# Small-strain elasticity in (r, z), u = (u_r, u_z), strain e = [e_rr, e_zz, e_θθ = u_r / r, γ_rz],
# dV = 2π r dA. Every node of the 6-node triangles is placed by an exact map of the cap, so the
# curved surfaces are represented to the elements' order. 'mixed': Taylor–Hood P2 displacement /
# continuous P1 pressure, W = ∫ μ dev e : dev e + p tr e − p² / 2κ, which does not lock as κ → ∞.
# 'disp': plain P2 with the full isotropic D, a cross-check of the mixed form at κ = 10 μ, where
# plain P2 does not lock either.


def tri_quad(n: int = 5) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(ξ, η, w): a collapsed (Duffy) n × n Gauss rule on the reference triangle, the collapsed side
    on vertex 1 (ξ = 1, η = 0). Its points are all interior (r > 0 on elements touching the axis),
    and its Jacobian, which vanishes at vertex 1, cancels the 1/r of the hoop strain there."""
    g, w = np.polynomial.legendre.leggauss(n)
    g, w = 0.5 * (g + 1), 0.5 * w
    a, b = np.meshgrid(g, g, indexing="ij")
    wa, wb = np.meshgrid(w, w, indexing="ij")
    return a.ravel(), (b * (1 - a)).ravel(), (wa * wb * (1 - a)).ravel()


def p2_shape(xi: np.ndarray, eta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Shape functions (q, 6) and their ξ, η derivatives: vertices 0–2, then midsides 01, 12, 20."""
    l1, l2, l3 = 1 - xi - eta, xi, eta
    n = np.stack([l1 * (2 * l1 - 1), l2 * (2 * l2 - 1), l3 * (2 * l3 - 1), 4 * l1 * l2, 4 * l2 * l3, 4 * l3 * l1], -1)
    z = 0 * l1
    dxi = np.stack([1 - 4 * l1, 4 * l2 - 1, z, 4 * (l1 - l2), 4 * l3, -4 * l3], -1)
    deta = np.stack([1 - 4 * l1, z, 4 * l3 - 1, -4 * l2, 4 * l2, 4 * (l1 - l3)], -1)
    return n, dxi, deta


def structured_mesh(s: np.ndarray, t: np.ndarray, mapping) -> dict:
    """P2 triangles on the grid s × t of a map (s, t) → (r, z), two per cell, with every node
    (corners, edge midpoints, the cell centre on the shared diagonal) placed by the map. Node
    (i, j) of the twice-refined grid is i·len(tf) + j."""
    refine = lambda c: np.insert(c, np.arange(1, len(c)), 0.5 * (c[:-1] + c[1:]))
    sf, tf = refine(np.asarray(s, float)), refine(np.asarray(t, float))
    r, z = mapping(*np.meshgrid(sf, tf, indexing="ij"))
    X = np.column_stack([r.ravel(), z.ravel()])
    i, j = (a.ravel() for a in np.meshgrid(2 * np.arange(len(s) - 1), 2 * np.arange(len(t) - 1), indexing="ij"))
    nd = lambda di, dj: (i + di) * len(tf) + j + dj
    T6 = np.vstack([np.column_stack([nd(0, 0), nd(2, 0), nd(2, 2), nd(1, 0), nd(2, 1), nd(1, 1)]),
                    np.column_stack([nd(0, 0), nd(2, 2), nd(0, 2), nd(1, 1), nd(1, 2), nd(0, 1)])])
    # a triangle touching the axis at one vertex: renumber it so that vertex is local vertex 1,
    # where the quadrature collapses (tri_quad); rotating the corners by k moves old vertex p to p + k
    on_axis = np.abs(X[T6[:, :3], 0]) < 1e-12 * np.abs(X[:, 0]).max()
    k = np.where(on_axis.sum(1) == 1, (1 - np.argmax(on_axis, 1)) % 3, 0)
    c = (np.arange(3) - k[:, None]) % 3
    T6 = np.take_along_axis(T6, np.hstack([c, 3 + c]), 1)
    # the pressure lives on the vertices (P1): number them 0 … nv − 1
    vmap = -np.ones(len(X), int)
    corners = np.unique(T6[:, :3])
    vmap[corners] = np.arange(len(corners))
    return {"X": X, "T6": T6, "vmap": vmap, "nv": len(corners), "nsf": len(sf), "ntf": len(tf)}


def element_geometry(mesh: dict) -> dict:
    """Strain–displacement matrices B (e, q, 4, 12), dof order [u_r0, u_z0, u_r1, …], volume
    weights dV = 2π r |J| w (e, q) and the P1 pressure shape functions (q, 3)."""
    xi, eta, w = tri_quad()
    n, dxi, deta = p2_shape(xi, eta)
    Xe = mesh["X"][mesh["T6"]]
    r = n @ Xe[:, :, 0].T  # (q, e)
    j11, j12 = dxi @ Xe[:, :, 0].T, dxi @ Xe[:, :, 1].T  # ∂(r, z)/∂ξ
    j21, j22 = deta @ Xe[:, :, 0].T, deta @ Xe[:, :, 1].T  # ∂(r, z)/∂η
    det = j11 * j22 - j12 * j21
    assert np.all(np.sign(det) == np.sign(det[:1])), "an element is inverted at a quadrature point"
    assert r.min() > 0, "a quadrature point on the axis"
    r, det, j11, j12, j21, j22 = (a.T[:, :, None] for a in (r, det, j11, j12, j21, j22))  # (e, q, 1)
    dnr = (j22 * dxi - j12 * deta) / det
    dnz = (j11 * deta - j21 * dxi) / det
    B = np.zeros(dnr.shape[:2] + (4, 12))
    B[:, :, 0, 0::2] = dnr
    B[:, :, 1, 1::2] = dnz
    B[:, :, 2, 0::2] = n / r
    B[:, :, 3, 0::2] = dnz
    B[:, :, 3, 1::2] = dnr
    return {"B": B, "dV": 2 * np.pi * (r * np.abs(det))[:, :, 0] * w, "Np": np.stack([1 - xi - eta, xi, eta], -1)}


def assemble(mesh: dict, geo: dict, mu: float, kappa: float, form: str) -> sp.csr_matrix:
    """The stiffness matrix: displacements (2 per node) then, for 'mixed', the vertex pressures."""
    T6, nu = mesh["T6"], 2 * len(mesh["X"])
    dofs = np.stack([2 * T6, 2 * T6 + 1], -1).reshape(len(T6), 12)
    m = np.array([1.0, 1, 1, 0])  # tr e = m · e
    D = 2 * mu * (np.diag([1, 1, 1, 0.5]) - np.outer(m, m) / 3)  # the deviatoric part (engineering γ_rz)
    if form == "disp":
        D = D + kappa * np.outer(m, m)
    B, dV = geo["B"], geo["dV"]
    Ke = np.einsum("eqia,ij,eqjb,eq->eab", B, D, B, dV, optimize=True)
    rows, cols, vals = [np.repeat(dofs, 12, 1)], [np.tile(dofs, 12)], [Ke]
    n = nu
    if form == "mixed":
        Np = geo["Np"]
        G = np.einsum("qk,eqa,eq->eka", Np, np.einsum("i,eqia->eqa", m, B), dV)  # ∫ N_p div u
        M = np.einsum("qk,ql,eq->ekl", Np, Np, dV)  # ∫ N_p N_p
        p = nu + mesh["vmap"][T6[:, :3]]
        # G at (p_k, dof_a) and, mirrored, at (dof_a, p_k); −M/κ at (p_k, p_l)
        rows += [np.repeat(p, 12, 1), np.tile(dofs, 3), np.repeat(p, 3, 1)]
        cols += [np.tile(dofs, 3), np.repeat(p, 12, 1), np.tile(p, 3)]
        vals += [G, G, -M / kappa]
        n = nu + mesh["nv"]
    ravel = lambda a: np.concatenate([x.ravel() for x in a])
    return sp.csr_matrix((ravel(vals), (ravel(rows), ravel(cols))), shape=(n, n))


def edge_forces(X: np.ndarray, edges: np.ndarray, traction, n: int) -> tuple[np.ndarray, float]:
    """Consistent nodal forces (n,) of a traction on quadratic boundary edges (m, 3) [end, middle,
    end], and their surface area. traction(x (m, q, 2), normal (m, q, 2)) → (m, q, 2); the normal
    is the edge tangent turned by −90°."""
    g, w = np.polynomial.legendre.leggauss(6)
    N = np.stack([0.5 * g * (g - 1), 1 - g**2, 0.5 * g * (g + 1)], -1)
    dN = np.stack([g - 0.5, -2 * g, g + 0.5], -1)
    x, dx = np.einsum("qa,mac->mqc", N, X[edges]), np.einsum("qa,mac->mqc", dN, X[edges])
    jac = np.linalg.norm(dx, axis=-1)
    normal = np.stack([dx[..., 1], -dx[..., 0]], -1) / jac[..., None]
    dA = 2 * np.pi * x[..., 0] * jac * w
    fe = np.einsum("qa,mqc->mac", N, traction(x, normal) * dA[..., None])
    f = np.zeros(n)
    np.add.at(f, 2 * edges, fe[..., 0])
    np.add.at(f, 2 * edges + 1, fe[..., 1])
    return f, float(dA.sum())


def solve(K: sp.csr_matrix, f: np.ndarray, fixed: np.ndarray) -> tuple[np.ndarray, float]:
    """K u = f with u = 0 on ``fixed``; (u, relative residual)."""
    free = np.setdiff1d(np.arange(len(f)), fixed)
    Kf = K[free][:, free]
    # the entries span many decades (r → 0 at the axis, displacement against pressure rows):
    # scale rows and columns by 1/√max|row| before the LU, and refine once
    d = 1 / np.sqrt(abs(Kf).max(axis=1).toarray().ravel())
    Ks = (sp.diags(d) @ Kf @ sp.diags(d)).tocsc()
    x = d * spsolve(Ks, d * f[free], permc_spec="COLAMD")
    x += d * spsolve(Ks, d * (f[free] - Kf @ x), permc_spec="COLAMD")
    u = np.zeros(len(f))
    u[free] = x
    return u, float(np.linalg.norm(f[free] - Kf @ x) / np.linalg.norm(f[free]))


def lame_check(a: float, b: float, k: float, form: str, nt: int, ns: int) -> dict:
    """Hollow sphere (radii a < b), unit internal pressure, the same elements on the section
    θ ∈ [0, π] (nt through the wall, ns along it): max over the nodes of |u_ρ − Lamé's| over
    max |Lamé's|, and the same of the tangential displacement (exactly 0)."""
    mu, kappa, p = MU, k * MU, 1.0
    E, nu = 9 * kappa * mu / (3 * kappa + mu), (3 * kappa - 2 * mu) / (2 * (3 * kappa + mu))
    mesh = structured_mesh(np.linspace(0, np.pi, ns + 1), np.linspace(a, b, nt + 1), lambda th, rho: (rho * np.sin(th), rho * np.cos(th)))
    X, ntf = mesh["X"], mesh["ntf"]
    X[np.abs(X[:, 0]) < 1e-14 * b, 0] = 0.0  # sin π ≠ 0 in floating point
    K = assemble(mesh, element_geometry(mesh), mu, kappa, form)
    edges = (2 * np.arange(ns)[:, None] + np.arange(3)) * ntf  # the inner surface, j = 0
    # the pressure pushes the wall away from the centre: along ± the edge normal, whichever points outward
    away = lambda x, nrm: p * np.sign((x * nrm).sum(-1, keepdims=True)) * nrm
    f, _ = edge_forces(X, edges, away, K.shape[0])
    axis = np.flatnonzero(X[:, 0] == 0)
    equator = (mesh["nsf"] // 2) * ntf  # inner equator: its u_z pinned against rigid translation
    u, relres = solve(K, f, np.concatenate([2 * axis, [2 * equator + 1]]))
    U, R = u[: 2 * len(X)].reshape(-1, 2), np.linalg.norm(X, axis=1)
    exact = p * a**3 / (E * (b**3 - a**3)) * ((1 - 2 * nu) * R + (1 + nu) * b**3 / (2 * R**2))
    radial, tangential = (U * X).sum(1) / R, (U[:, 0] * X[:, 1] - U[:, 1] * X[:, 0]) / R
    return {"a": a, "b": b, "k": k, "form": form, "nt": nt, "ns": ns, "ndof": K.shape[0], "relres": relres,
            "max_rel_err_radial": float(np.abs(radial - exact).max() / np.abs(exact).max()),
            "max_tangential_rel": float(np.abs(tangential).max() / np.abs(exact).max())}


def cap_mesh(nt: int, rpatch: float = RPATCH) -> dict:
    """The cap, s ∈ [0, 1] the polar angle as a fraction of the angle where the sphere of radius ρ
    meets z = 0 (so s = 1 is the base plane at every depth), ρ ∈ [RI, RO]. 1.5 nt elements along
    the arc over the patch (whose edge on the outer surface is exactly a grid line), then 5 nt
    growing geometrically to the base (the response is concentrated under the load)."""
    th_max = lambda rho: np.arccos(-ZC / rho)
    s_p = np.arcsin(rpatch / RO) / th_max(RO)
    n1, n2 = int(round(1.5 * nt)), 5 * nt
    h0 = s_p / n1
    if n2 * h0 >= 1 - s_p:  # uniform is already no finer than the patch
        s2 = np.linspace(s_p, 1, n2 + 1)
    else:  # growth q with h0 (1 + q + … + q^(n2 − 1)) = 1 − s_p
        q = brentq(lambda q: h0 * (q**n2 - 1) / (q - 1) - (1 - s_p), 1 + 1e-12, 2.0, xtol=1e-15)
        s2 = s_p + np.concatenate([[0], np.cumsum(h0 * q ** np.arange(n2))])
        s2[-1] = 1.0
    s = np.concatenate([np.linspace(0, s_p, n1 + 1), s2[1:]])

    def mapping(s, rho):
        th = s * th_max(rho)
        return rho * np.sin(th), ZC + rho * np.cos(th)

    mesh = structured_mesh(s, np.linspace(RI, RO, nt + 1), mapping)
    ntf, nsf = mesh["ntf"], mesh["nsf"]
    mesh["X"][:ntf, 0] = 0.0  # exactly on the axis
    mesh["X"][(nsf - 1) * ntf :, 1] = 0.0  # exactly on the base plane
    mesh["n_patch"], mesh["n_arc"] = n1, len(s) - 1
    return mesh


def patch_load(mesh: dict, n: int) -> tuple[np.ndarray, float]:
    """(f, patch area): FTOT downward, uniform per unit area over the patch of the outer surface,
    as consistent nodal forces in a vector of n dofs."""
    ntf = mesh["ntf"]
    edges = 2 * np.arange(mesh["n_patch"])[:, None] * ntf + np.arange(3)[None] * ntf + ntf - 1  # outer surface (j = ntf − 1)
    _, area = edge_forces(mesh["X"], edges, lambda x, nrm: 0 * x, n)  # the discrete patch's area
    f, _ = edge_forces(mesh["X"], edges, lambda x, nrm: np.stack([0 * x[..., 0], np.full(x.shape[:2], -FTOT / area)], -1), n)
    return f, area


def rms_radius(r: np.ndarray, fz: np.ndarray) -> float:
    """√2 × the load-weighted rms horizontal radius: the radius itself for a uniform flat disc, a
    size of the loaded patch that can be compared between the reference and the 3-D nodal loads."""
    return float(np.sqrt(2 * (fz * r**2).sum() / fz.sum()))


def cap_reference(nt: int, k: float, form: str, rpatch: float = RPATCH) -> dict:
    """The cap under FTOT downward, uniform over the patch of horizontal radius ``rpatch`` on the
    outer surface, base clamped."""
    t0 = time.perf_counter()
    mesh = cap_mesh(nt, rpatch)
    X, ntf, nsf = mesh["X"], mesh["ntf"], mesh["nsf"]
    K = assemble(mesh, element_geometry(mesh), MU, k * MU, form)
    f, area = patch_load(mesh, K.shape[0])
    axis, base = np.arange(ntf), (nsf - 1) * ntf + np.arange(ntf)
    u, relres = solve(K, f, np.concatenate([2 * axis, 2 * base, 2 * base + 1]))
    uz = u[1 : 2 * len(X) : 2]
    mean = -float(f @ u) / FTOT  # f · u = −FTOT × (1/A) ∫ u_z dA over the patch
    return {"k": k, "form": form, "nt": nt, "patch_radius": rpatch, "n_arc": mesh["n_arc"], "n_elem": len(mesh["T6"]), "ndof": K.shape[0],
            "uz_outer_apex": float(uz[ntf - 1]), "uz_inner_apex": float(uz[0]), "mean_patch_uz": mean,
            "stiffness_N_per_m": FTOT / -mean, "patch_area_mesh": area,
            "patch_area_exact": 2 * np.pi * RO**2 * (1 - np.cos(np.arcsin(rpatch / RO))),
            "load_rms_radius": rms_radius(X[:, 0], f[1 : 2 * len(X) : 2]), "relres": relres, "wall_s": time.perf_counter() - t0}


def patch_for_rms_radius(target: float, nt: int) -> float:
    """The reference's patch radius whose load has the rms radius ``target`` (rms_radius)."""
    def excess(rp):
        mesh = cap_mesh(nt, rp)
        f, _ = patch_load(mesh, 2 * len(mesh["X"]))
        return rms_radius(mesh["X"][:, 0], f[1::2]) - target
    return brentq(excess, 0.3 * target, 3 * target, xtol=1e-9)


def aitken(a: float, b: float, c: float) -> float:
    """The limit of a geometrically converging sequence a, b, c (Aitken's Δ²)."""
    return c - (c - b) ** 2 / ((c - b) - (b - a))


# ============================================================================ the 3-D membrane


def dome_3d(n_rim: int, layers: int, form: str, k: float, load: float = F3D) -> dict:
    """The package's membrane on the paper's dome under ``load`` N spread over the patch as nodal
    forces in proportion to the outer-surface nodes' areas; displacements scaled to FTOT."""
    from jointsim.geometry import isotropic_cap
    from jointsim.mechanics.dome import MembraneModel
    from jointsim.mechanics.materials import Material
    from jointsim.mechanics.newton import NodalForce, minimize_energy

    # the package's own membrane (mesh, bonded rim, outer-surface nodes and their areas), unpressurised
    wedge = form == "wedge15"
    model = MembraneModel(isotropic_cap(0.02, 0.01, n_rim), RO - RI, Material.neo_hookean(MU, bulk_ratio=k), layers,
                          volumetric="pointwise" if wedge else form, element="wedge15" if wedge else "p2_tet")
    mesh, X, n, fixed, elastic = model.mesh, model.mesh.nodes, model.n_surface, model.fixed, model.elastic
    nodes, w = model.contact.nodes, model.contact.weights
    r = np.hypot(X[nodes, 0], X[nodes, 1])
    patch = r <= RPATCH + 1e-12
    f = np.zeros_like(X)
    f[nodes[patch], 2] = -load * w[patch] / w[patch].sum()
    t0 = time.perf_counter()
    # atol 1e-4 × the largest nodal force (1.6e-10 … 1e-9 N): at κ = 1000 μ the gradient can stall at
    # ~5e-11 N (96/2, mean dilatation: the line search then fails below it); where a tighter solve
    # converges, it moves the stiffness by < 1e-6
    res = minimize_energy([elastic, NodalForce(f)], np.zeros_like(X), fixed, rtol=0.0, atol=1e-4 * np.abs(f).max())
    wall = time.perf_counter() - t0
    u = res.u * (FTOT / load)
    mean = float((f * u).sum()) / -load  # the load-weighted mean u_z over the patch
    return {"n_rim": n_rim, "layers": layers, "form": form, "k": k, "load_N": load, "p2_nodes": mesh.n_nodes, "tets": mesh.n_elements,
            "patch_nodes": int(patch.sum()), "outermost_loaded_mm": 1e3 * r[patch].max(), "nearest_unloaded_mm": 1e3 * r[~patch].min(),
            "load_rms_radius": rms_radius(r[patch], f[nodes[patch], 2]), "mean_patch_uz": mean, "uz_outer_apex": float(u[np.argmax(X[:, 2]), 2]),
            "uz_inner_apex": float(u[np.argmax(X[:n, 2]), 2]), "stiffness_N_per_m": FTOT / -mean,
            "newton_iterations": res.iterations, "residual_N": float(res.residual), "solve_s": wall}


# ============================================================================ driver and report


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--levels", type=int, nargs="+", default=list(LEVELS), help="reference elements through the thickness")
    ap.add_argument("--report", action="store_true", help="rewrite the .md from the .json")
    args = ap.parse_args()
    if args.report:
        write(json.loads(OUT.with_suffix(".json").read_text()))
        return 0
    t0 = time.perf_counter()
    load0, speed0 = os.getloadavg()[0], speed_reference()
    out = {"problem": {"sphere_centre_z": ZC, "inner_radius": RI, "outer_radius": RO, "patch_radius": RPATCH, "total_load_N": FTOT, "mu_Pa": MU}}

    # verification: Lamé's thick sphere (b = 2a) at two meshes, to see the error fall, and one
    # as thin as the dome (b − a = 2 mm)
    cases = [(10, "disp"), (10, "mixed"), (1000, "mixed")]
    out["verification"] = [lame_check(a, b, k, form, nt, ns) for a, b, grids in ((RI, 2 * RI, ((8, 64), (16, 128))), (RI, RO, ((4, 160),)))
                           for k, form in cases for nt, ns in grids]
    for v in out["verification"]:
        print(f"Lamé a {v['a']} b {v['b']} κ/μ {v['k']} {v['form']} {v['nt']}×{v['ns']}: error {v['max_rel_err_radial']:.2e}", flush=True)

    out["reference"] = [cap_reference(nt, k, form) for k, form in [(k, "mixed") for k in KAPPAS] + [(10, "disp")] for nt in args.levels]
    for r in out["reference"]:
        print(f"reference κ/μ {r['k']} {r['form']} nt {r['nt']}: {r['stiffness_N_per_m']:.4f} N/m ({r['wall_s']:.1f} s)", flush=True)

    out["dome_3d"] = []
    for n_rim, layers in MESHES_3D:
        for form in FORMS_3D:
            for k in KAPPAS:
                out["dome_3d"].append(dome_3d(n_rim, layers, form, k))
                r = out["dome_3d"][-1]
                print(f"3-D {n_rim}/{layers} {form} κ/μ {k}: {r['stiffness_N_per_m']:.3f} N/m ({r['solve_s']:.1f} s)", flush=True)
    # against the finest reference level of the same κ. The nodal loads do not cover the 3 mm patch
    # exactly (they stop at the last node inside it) and the stiffness depends strongly on the
    # patch's size, so also against the reference for a uniform patch of the same rms radius as the
    # mesh's load: a rough correction for that
    nt = max(args.levels)
    finest = {k: next(r for r in out["reference"] if (r["k"], r["form"], r["nt"]) == (k, "mixed", nt)) for k in KAPPAS}
    matched = {}
    for r in out["dome_3d"]:
        key = (round(r["load_rms_radius"], 9), r["k"])
        if key not in matched:
            matched[key] = cap_reference(nt, r["k"], "mixed", patch_for_rms_radius(r["load_rms_radius"], nt))
        r["ref_same_rms_radius"] = {q: matched[key][q] for q in ("patch_radius", "load_rms_radius", "stiffness_N_per_m", "uz_outer_apex")}
        r["stiffness_ratio"] = r["stiffness_N_per_m"] / finest[r["k"]]["stiffness_N_per_m"]
        r["apex_ratio"] = r["uz_outer_apex"] / finest[r["k"]]["uz_outer_apex"]
        r["stiffness_ratio_same_rms_radius"] = r["stiffness_N_per_m"] / matched[key]["stiffness_N_per_m"]
    # linearity: the same mesh at twice the load, per unit load
    base = next(r for r in out["dome_3d"] if (r["n_rim"], r["layers"], r["form"], r["k"]) == (64, 2, "mean_dilatation", 1000))
    double = dome_3d(64, 2, "mean_dilatation", 1000, 2 * F3D)
    out["linearity"] = {"case": [64, 2, "mean_dilatation", 1000], "loads_N": [F3D, 2 * F3D],
                        "stiffness_rel_change": double["stiffness_N_per_m"] / base["stiffness_N_per_m"] - 1}

    command = "python benchmarks/bench_dome_apex_load.py" + ("" if tuple(args.levels) == LEVELS else " --levels " + " ".join(map(str, args.levels)))
    out["meta"] = {"command": command,
                   "date": time.strftime("%Y-%m-%d"),
                   "machine": machine(),
                   "load_average_start_end": [load0, os.getloadavg()[0]],
                   "speed_reference_s_start_end": [speed0, speed_reference()], "wall_s": time.perf_counter() - t0}
    write(out)
    return 0


def write(out: dict) -> None:
    """results/dome_apex_load.{json,md} from the measured ``out``."""
    meta, ver, refs, rows = out["meta"], out["verification"], out["reference"], out["dome_3d"]
    nt = max(r["nt"] for r in refs)
    finest = {k: next(r for r in refs if (r["k"], r["form"], r["nt"]) == (k, "mixed", nt)) for k in KAPPAS}
    um = lambda x: f"{1e6 * x:.3f}"
    case = lambda v: (v["a"], v["b"], v["k"], v["form"])
    worst = max(v["max_rel_err_radial"] for v in ver if v["nt"] == max(w["nt"] for w in ver if case(w) == case(v)))
    load, speed = meta["load_average_start_end"], meta["speed_reference_s_start_end"]
    lines = ["# The dome under an apex load: 3-D membrane against an axisymmetric reference", "",
             f"Command: `{meta['command']}` ({meta['wall_s']:.0f} s; {meta['machine']}; run {meta['date']}).  ",
             f"1-min load average {load[0]:.1f} at the start, {load[1]:.1f} at the end (on 2 cores a load above 1 inflates the times; "
             "the displacements do not depend on it). Reference workload (`benchmarks/_machine.py` speed_reference, a fixed sparse "
             f"factorisation): {speed[0]:.3f} s at the start, {speed[1]:.3f} s at the end; to compare times with a run of another "
             "day, scale by the ratio of this figure.", "",
             "The paper's dome: the part above the base plane z = 0 of a spherical shell about (0, 0, −15 mm), inner radius 25 mm, "
             "outer 27 mm (inner surface: base radius 20 mm, height 10 mm). The base face is clamped; a total load of 1 mN acts "
             "downward, uniform per unit area over the outer surface within 3 mm of the axis (horizontal radius). Linear "
             "elastic, μ = 22 kPa, κ = 10 μ (ν = 0.452) and 1000 μ (ν = 0.4995). Displacements are u_z per mN in µm "
             "(negative: down); stiffness = 1 mN / −(mean u_z over the patch, weighted by the load).", "",
             "## Reference (axisymmetric, this script)", "",
             "Small-strain elasticity in the (r, z) half-plane on curved 6-node triangles (every node on the exact surfaces), "
             "Taylor–Hood P2 displacement / continuous P1 pressure ('mixed', locking-free), and plain P2 ('disp') at κ = 10 μ as "
             "a cross-check. Structured mesh: nt elements through the 2 mm wall, 1.5 nt along the arc over the patch, 5 nt "
             "growing geometrically from the patch to the base. Consistent nodal forces of the uniform traction.", "",
             "Verification, Lamé's hollow sphere under unit internal pressure (the same elements on the θ ∈ [0, π] section; max "
             f"over the nodes of |u_ρ − exact| / max |exact|): at the finest mesh of each case at most {worst:.1e}, "
             + ("below" if worst < VERIFY_TOL else "**above**") + f" the {VERIFY_TOL:g} required. The observed order is near "
             "3, that of P2 displacements.", "",
             "| a, b mm | κ/μ | form | elements (wall × arc) | error | observed order |", "|---|---|---|---|---|---|"]
    for i, v in enumerate(ver):
        prev = ver[i - 1] if i and case(ver[i - 1]) == case(v) else None
        order = f"{np.log2(prev['max_rel_err_radial'] / v['max_rel_err_radial']):.1f}" if prev else ""
        lines.append(f"| {1e3 * v['a']:g}, {1e3 * v['b']:g} | {v['k']} | {v['form']} | {v['nt']} × {v['ns']} | {v['max_rel_err_radial']:.1e} | {order} |")
    lines += ["", "The cap, over nt ('change': against the previous level; 'Aitken': the Δ² limit of the last three levels, an "
              "estimate of the finest level's error).", "",
              "| κ/μ | form | nt | dofs | outer apex u_z | inner apex u_z | mean patch u_z | stiffness N/m | change |", "|---|---|---|---|---|---|---|---|---|"]
    for k, form in [(k, "mixed") for k in KAPPAS] + [(10, "disp")]:
        rs = sorted((r for r in refs if (r["k"], r["form"]) == (k, form)), key=lambda r: r["nt"])
        for i, r in enumerate(rs):
            ch = f"{100 * (r['stiffness_N_per_m'] / rs[i - 1]['stiffness_N_per_m'] - 1):+.3f} %" if i else ""
            lines.append(f"| {k} | {form} | {r['nt']} | {r['ndof']:,} | {um(r['uz_outer_apex'])} | {um(r['uz_inner_apex'])} | "
                         f"{um(r['mean_patch_uz'])} | {r['stiffness_N_per_m']:.4f} | {ch} |")
        if len(rs) >= 3:
            lim = aitken(*(r["stiffness_N_per_m"] for r in rs[-3:]))
            lines.append(f"| {k} | {form} | Aitken | | | | | {lim:.4f} | nt = {rs[-1]['nt']}: {100 * (rs[-1]['stiffness_N_per_m'] / lim - 1):+.3f} % |")
    rms = {n: next(r["load_rms_radius"] for r in rows if r["n_rim"] == n) for n in sorted({r["n_rim"] for r in rows})}
    lines += ["", "## The 3-D membrane against it", "",
              "The package's dome: `isotropic_cap(0.02, 0.01, rim)`, `membrane_mesh` (prism layers along the radii from the "
              "sphere's centre; at the rim in the base plane, out to where each layer's sphere meets it, so the shell is the "
              "reference's: concentric spheres cut by the base plane), P2 with midside nodes on the spheres "
              "(`on_spheres`), base nodes clamped. The load: 0.1 mN on the outer-surface nodes with horizontal radius ≤ 3 mm, in "
              "proportion to their areas (`nodal_areas` of the outer faces' linear subtriangles); the neo-Hookean model solved "
              "by `minimize_energy` (finite strain, but linear at this load: twice the load changes the stiffness by "
              f"{100 * out['linearity']['stiffness_rel_change']:+.2f} % on 64/2, mean dilatation, κ = 1000 μ), scaled to 1 mN. "
              f"'/ ref': against the reference's finest level (nt = {nt}) of the same κ.", "",
              "The nodal loads stop at the last node inside 3 mm: "
              + "; ".join(f"{n} rim: loaded nodes out to {next(r['outermost_loaded_mm'] for r in rows if r['n_rim'] == n):.2f} mm, the next "
                          f"at {next(r['nearest_unloaded_mm'] for r in rows if r['n_rim'] == n):.2f} mm" for n in rms)
              + ". As a size of the loaded patch, √2 × the load-weighted rms radius (the radius of a uniform disc): "
              + ", ".join(f"{1e3 * v:.2f} mm ({n} rim)" for n, v in rms.items())
              + f", {1e3 * finest[KAPPAS[0]]['load_rms_radius']:.2f} mm in the reference. The stiffness is sensitive to it "
              + "(reference, κ = " + f"{KAPPAS[-1]} μ: " + ", ".join(
                  f"{next(r['ref_same_rms_radius']['stiffness_N_per_m'] for r in rows if r['n_rim'] == n and r['k'] == KAPPAS[-1]):.2f} N/m at {1e3 * v:.2f} mm"
                  for n, v in rms.items()) + f", {finest[KAPPAS[-1]]['stiffness_N_per_m']:.2f} at 3 mm), so the last ratio is against the "
              "reference for a uniform patch of the mesh's rms radius: a rough correction, as the nodal loads are not uniform in shape.",
              "", "Solve: wall time of `minimize_energy` (the first includes loading Warp's kernels).", "",
              "| rim | layers | P2 nodes | volumetric | κ/μ | mean patch u_z | outer apex u_z | stiffness N/m | stiffness / ref | apex u_z / ref | "
              "stiffness / ref of same rms radius | Newton its | solve s |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['n_rim']} | {r['layers']} | {r['p2_nodes']:,} | {r['form'].replace('_', ' ')} | {r['k']} | {um(r['mean_patch_uz'])} | "
                     f"{um(r['uz_outer_apex'])} | {r['stiffness_N_per_m']:.3f} | {r['stiffness_ratio']:.3f} | {r['apex_ratio']:.3f} | "
                     f"{r['stiffness_ratio_same_rms_radius']:.3f} | {r['newton_iterations']} | {r['solve_s']:.1f} |")
    lines += ["", "## Findings", "", findings(out, finest)]
    write_pair(OUT, out, "\n".join(lines) + "\n")
    print("\n".join(lines))


def findings(out: dict, finest: dict) -> str:
    """The plain reading of the tables, with this run's numbers filled in."""
    rows = out["dome_3d"]
    disp = next(r for r in out["reference"] if (r["k"], r["form"], r["nt"]) == (10, "disp", finest[10]["nt"]))
    # the range of quantity q over the rows of the given layers, volumetric form and κ (None: all)
    def span(q, layers, form, k=None):
        v = [r[q] for r in rows if r["layers"] in layers and r["form"] == form and k in (None, r["k"])]
        return f"{min(v):.3f}–{max(v):.3f}"

    k0, k1 = KAPPAS[0], KAPPAS[-1]
    return (f"The reference's two formulations agree at κ = {k0} μ ({finest[k0]['stiffness_N_per_m']:.3f} mixed, "
            f"{disp['stiffness_N_per_m']:.3f} N/m displacement-only at nt = {disp['nt']}); its stiffness is "
            f"{finest[k0]['stiffness_N_per_m']:.2f} N/m at κ = {k0} μ and {finest[k1]['stiffness_N_per_m']:.2f} N/m at {k1} μ. "
            f"Against it, the 3-D membrane with two or three layers gives {span('stiffness_ratio', (2, 3), 'pointwise')} "
            f"of its stiffness with the pointwise volumetric form and {span('stiffness_ratio', (2, 3), 'mean_dilatation')} "
            "with mean dilatation; much of the difference between the 64- and 96-rim meshes is the load's, not the "
            "membrane's: the 64-rim meshes load a smaller patch (above). "
            f"Against the reference of the same rms patch radius, pointwise with two or three layers is at "
            f"{span('stiffness_ratio_same_rms_radius', (2, 3), 'pointwise', k0)} at κ = {k0} μ and "
            f"{span('stiffness_ratio_same_rms_radius', (2, 3), 'pointwise', k1)} at {k1} μ, mean dilatation at "
            f"{span('stiffness_ratio_same_rms_radius', (2, 3), 'mean_dilatation')}, alike at both κ, and with one layer at "
            f"{span('stiffness_ratio_same_rms_radius', (1,), 'mean_dilatation')}. "
            + (f"The 15-node wedges (membrane element = \"wedge15\", the dilatation projected per element onto linear "
               f"polynomials) are at {span('stiffness_ratio_same_rms_radius', (1, 2, 3), 'wedge15', k0)} at κ = {k0} μ and "
               f"{span('stiffness_ratio_same_rms_radius', (1, 2, 3), 'wedge15', k1)} at {k1} μ, one layer included: no locking. "
               if any(r["form"] == "wedge15" for r in rows) else "")
            + 
            "The two share the geometry (until 2026-11-21 the 3-D rim grew by 2 mm in the base plane, thinning the wall "
            "to 1.6 mm normal to the surface at the bond; the full shell stiffened the 3-D membrane by 0.7–0.8 %), so the "
            "remaining differences are the elements' and the nodal loads' shape.")


if __name__ == "__main__":
    sys.exit(main())
