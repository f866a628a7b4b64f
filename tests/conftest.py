import os

import numpy as np
import pytest

from jointsim.scene import load_scene
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PAPER_SCENE = ROOT / "scenes" / "paper_sensor.toml"


def check_element_derivatives(kernel, mesh, u: np.ndarray, d: np.ndarray, eps: float = 1e-6):
    """An element kernel's (fem.ElementKernel, wedge.WedgeKernel) gradient against a central
    difference of its energy along ``d``, its Hessian against one of its gradient (the
    difference's truncation and round-off at eps = 1e-6 are ~1e-9 relative), the in-kernel
    assembly against the per-element matrices assembled, and symmetry. Returns the state at u."""
    from jointsim.mechanics.fem import assemble_gradient, assemble_hessian

    s = kernel(u)
    g = assemble_gradient(mesh, s.grad)
    dE = (kernel(u + eps * d, False).energy.sum() - kernel(u - eps * d, False).energy.sum()) / (2 * eps)
    assert g @ d.ravel() == pytest.approx(dE, rel=1e-6)
    dg = (assemble_gradient(mesh, kernel(u + eps * d, False).grad) - assemble_gradient(mesh, kernel(u - eps * d, False).grad)) / (2 * eps)
    assert np.abs(s.hessian @ d.ravel() - dg).max() <= 1e-7 * np.abs(dg).max()
    H = s.hessian.toarray()
    tol = 1e-12 * np.abs(H).max()
    np.testing.assert_allclose(assemble_hessian(mesh, kernel(u, True, elements=True).element_hessians).toarray(), H, rtol=0, atol=tol)
    np.testing.assert_allclose(H, H.T, rtol=0, atol=tol)
    return s


def pytest_configure(config):
    """Each xdist worker runs its numerical libraries on one thread. The suite runs two workers
    on a 2-core machine; with each BLAS pool as wide as the machine, their spinning threads
    fought for the cores and some tests ran 5-16x slower than alone. The variables reach the
    subprocesses the tests start; threadpoolctl limits the libraries already loaded."""
    if not os.environ.get("PYTEST_XDIST_WORKER"):
        return
    from jointsim._cores import THREAD_VARIABLES
    from threadpoolctl import threadpool_limits

    for name in THREAD_VARIABLES:
        os.environ.setdefault(name, "1")
    threadpool_limits(1)


@pytest.fixture(scope="session", autouse=True)
def _mesh_cache(tmp_path_factory):
    """Meshes go to a per-run cache, empty at the start, so a test never reads a mesh from
    another checkout or an earlier run (the mesher is deterministic: it would be the same)."""
    cache = tmp_path_factory.mktemp("mesh_cache")
    mp = pytest.MonkeyPatch()
    mp.setenv("JOINTSIM_CACHE", str(cache))
    yield
    mp.undo()


@pytest.fixture(scope="session")
def paper_scene():
    return load_scene(PAPER_SCENE)


@pytest.fixture(scope="session")
def test_chamber(paper_scene, _mesh_cache):
    """The paper's chamber at the coarse 'test' resolution (~19 k tets, ~1 s to mesh)."""
    from jointsim.mesh.chamber import chamber_mesh

    scene = paper_scene.with_mesh_preset("test")
    return scene, chamber_mesh(scene)


@pytest.fixture(scope="session")
def chamber_fields(test_chamber):
    from jointsim.eit.forward import ForwardModel

    scene, ch = test_chamber
    model = ForwardModel.from_chamber(ch, scene)
    sigma = np.full(ch.mesh.n_tets, scene.saline.conductivity)
    return scene, ch, model, model.solve(sigma)


def wedge_grid(xs, ys, zs):
    """15-node wedges on a tensor grid: the (xs, ys) rectangle's cells split into 2 triangles
    each, extruded through the levels zs (bottom first)."""
    from jointsim.mechanics.wedge import WedgeMesh

    x, y = np.meshgrid(xs, ys, indexing="ij")
    v = np.column_stack([x.ravel(), y.ravel()])
    idx = np.arange(len(xs) * len(ys)).reshape(len(xs), len(ys))
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = np.vstack([np.column_stack([a, b, c]), np.column_stack([a, c, d])])
    corners = np.vstack([np.column_stack([v, np.full(len(v), zl)]) for zl in zs])
    return WedgeMesh.extrude(corners, faces, len(zs) - 1)


# The closed-form load cases both membrane elements are checked against (tests/test_mechanics.py
# on P2 tetrahedra, tests/test_wedge.py on wedges): each takes a mesh and its elastic term and
# returns what the test compares with the closed form.


def uniaxial_nominal_stress(mesh, term, L: float, stretches) -> np.ndarray:
    """The cube [0, L]³ stretched along x (symmetry planes at 0, lateral faces free), loaded in
    order to each stretch: the reaction per reference area at each."""
    from jointsim.mechanics.newton import step_to

    X = mesh.nodes
    fixed = np.zeros_like(X, bool)
    for ax in range(3):
        fixed[np.isclose(X[:, ax], 0), ax] = True  # symmetry planes: lateral faces free
    right = np.isclose(X[:, 0], L)
    fixed[right, 0] = True
    u = np.zeros_like(X)
    out = []
    for lam in stretches:
        target = u.copy()
        target[right, 0] = (lam - 1) * L
        res = step_to([term], u, fixed, target)
        u = res.u
        out.append(res.gradient.reshape(-1, 3)[right, 0].sum() / L**2)  # reaction / A₀
    return np.array(out)


def cantilever_tip_ratio(mesh, term, L: float, t: float, mu: float, P: float) -> float:
    """The beam [0, L] × [0, t]² clamped at x = 0 under a tip load P along z spread over the tip
    nodes: the tip's mean deflection over Timoshenko's δ = PL³/3EI + PL/(κₛGA) (E = 3μ, G = μ)."""
    from jointsim.mechanics.newton import NodalForce, minimize_energy

    X = mesh.nodes
    fixed = np.zeros_like(X, bool)
    fixed[np.isclose(X[:, 0], 0)] = True
    tip = np.isclose(X[:, 0], L)
    f = np.zeros_like(X)
    f[tip, 2] = P / tip.sum()
    timoshenko = P * L**3 / (3 * 3 * mu * t**4 / 12) + P * L / (5 / 6 * mu * t * t)
    # atol: the gradient's round-off floor is ~1e-13 N (κ·L² ~ 1e4 N·m⁻¹·m²·1e-16)
    u = minimize_energy([term, NodalForce(f)], np.zeros_like(X), fixed, rtol=0.0, atol=1e-10).u
    return float(u[tip, 2].mean() / timoshenko)


def inflate_octant(mesh, term, A: float, B: float, mu: float, pressures) -> tuple[np.ndarray, float, int]:
    """The octant of the shell A ≤ r ≤ B about the origin under cavity pressure, on its symmetry
    planes (each plane's nodes free in the plane only), loaded in order to each pressure: the
    exact neo-Hookean pressure p = 2μ[(1/λb + 1/(4λb⁴)) − (1/λa + 1/(4λa⁴))] at each inflation
    reached, the last λa, and the number of cavity faces. The cavity volume is that of the cone
    from the origin to the loaded octant of its surface: the symmetry faces pass through the
    origin and add nothing to ∮ x·n."""
    from jointsim.mechanics.newton import minimize_energy
    from jointsim.mechanics.pressure import PressureTerm, linear_subtriangles

    X, bf = mesh.nodes, mesh.boundary_faces
    on_plane = np.any(np.all(np.abs(X[bf[:, :3]]) < 1e-9 * B, axis=1), axis=1)
    cavity = bf[~on_plane & (np.linalg.norm(X[bf[:, :3]].mean(axis=1), axis=1) < (A + B) / 2)]
    # the cavity's faces point into it (out of the solid): sign −1 for the cavity volume
    pressure = PressureTerm(X, linear_subtriangles(cavity), sign=-1.0)
    fixed = np.abs(X) < 1e-9 * B  # u_x = 0 on x = 0, and so on
    u = np.zeros_like(X)
    V0 = pressure.volume(u)
    assert V0 == pytest.approx(np.pi / 6 * A**3, rel=5e-3)  # the octant of the cavity
    exact = []
    for p in pressures:
        pressure.pressure = p
        u = minimize_energy([term, pressure], u, fixed).u
        la = (pressure.volume(u) / V0) ** (1 / 3)
        lb = (1 + (la**3 - 1) * (A / B) ** 3) ** (1 / 3)
        exact.append(2 * mu * ((1 / lb + 1 / (4 * lb**4)) - (1 / la + 1 / (4 * la**4))))
    return np.array(exact), la, len(cavity)


def press_block(mesh, term, R: float, W: float, h0: float, d: float, E: float) -> tuple[float, float, float]:
    """A quarter of the block [0, W]² × [−W, 0] (symmetry planes x = 0, y = 0, the base fixed),
    its top pressed by a rigid frictionless sphere of radius R to depth d (penalty 100·E/h0, h0
    the top cells' size): the whole block's contact force, the largest penetration and the
    contact radius."""
    from jointsim.mechanics.contact import SphereContact, nodal_areas
    from jointsim.mechanics.newton import NewtonSystem, minimize_energy
    from jointsim.mechanics.pressure import linear_subtriangles

    X, bf = mesh.nodes, mesh.boundary_faces
    top = bf[np.all(np.isclose(X[bf[:, :3], 2], 0.0), axis=1)]
    nodes, w = nodal_areas(X, linear_subtriangles(top))
    contact = SphereContact(X, nodes, w, R, stiffness=100 * E / h0)
    contact.centre = np.array([0.0, 0.0, R - d])
    fixed = np.zeros_like(X, bool)
    fixed[np.isclose(X[:, 0], 0), 0] = True  # symmetry planes
    fixed[np.isclose(X[:, 1], 0), 1] = True
    fixed[np.isclose(X[:, 2], -W), :] = True  # the base
    system = NewtonSystem(*mesh.sparsity[:2], ~fixed.ravel())  # the analysis once, not per iteration
    res = minimize_energy([term, contact], np.zeros_like(X), fixed, system=system)
    a = np.sqrt(4 * contact.contact_area(res.u) / np.pi)  # a quarter of the contact disc
    return 4 * contact.force(res.u)[2], contact.penetration(res.u), a
