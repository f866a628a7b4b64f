"""Mechanics against closed forms: uniaxial stretch of one cube (neo-Hookean, Yeoh), the
pressurised thick neo-Hookean sphere; derivative checks of the Warp element kernel."""

import os

import numpy as np
import pytest
import warp as wp
from conftest import (
    cantilever_tip_ratio,
    check_element_derivatives,
    inflate_octant,
    press_block,
    uniaxial_nominal_stress,
    wedge_grid,
)

from jointsim.mechanics.fem import ElasticTerm, ElementKernel, P2Mesh
from jointsim.mechanics.materials import Material
from jointsim.mechanics.newton import (
    NewtonError,
    NewtonSystem,
    NodalForce,
    minimize_energy,
)
from jointsim.mechanics.pressure import PressureTerm, linear_subtriangles
from jointsim.mesh.shapes import box_mesh


@pytest.mark.parametrize("volumetric", ["mean_dilatation", "pointwise"])
def test_element_gradient_and_hessian_match_finite_differences(volumetric):
    m = P2Mesh.from_linear(box_mesh((1.0, 1.0, 1.0), (2, 2, 2)))
    k = ElementKernel(m, Material.yeoh(9.8e3, 0.91e3, -0.16e3), volumetric=volumetric)
    rng = np.random.default_rng(0)
    u = 0.01 * rng.standard_normal((m.n_nodes, 3))
    check_element_derivatives(k, m, u, rng.standard_normal(u.shape))
    assert k(np.zeros_like(u), False).energy.sum() == 0.0


@pytest.mark.parametrize("volumetric", ["mean_dilatation", "pointwise"])
def test_the_kernel_split_over_threads_equals_one_launch(monkeypatch, volumetric):
    """The element kernel launched in uneven chunks from several threads gives every element the
    same energy, gradient and Hessian as one launch; the assembled Hessians differ only by the
    order of the additions (to 1e-14 of the largest entry)."""
    import jointsim.mechanics.fem as fem

    m = P2Mesh.from_linear(box_mesh((1.0, 1.0, 1.0), (3, 3, 3)))  # 162 tets
    k = ElementKernel(m, Material.yeoh(9.8e3, 0.91e3, -0.16e3), volumetric=volumetric)
    u = 0.02 * np.random.default_rng(4).standard_normal((m.n_nodes, 3))
    monkeypatch.setattr(fem, "KERNEL_THREADS", 1)
    one = k(u, True, elements=True)
    monkeypatch.setattr(fem, "KERNEL_THREADS", 3)
    monkeypatch.setattr(fem, "MIN_CHUNK", 50)  # 162 // 50 = 3 chunks of 54
    split = k(u, True, elements=True)
    np.testing.assert_array_equal(split.energy, one.energy)
    np.testing.assert_array_equal(split.grad, one.grad)
    np.testing.assert_array_equal(split.element_hessians, one.element_hessians)
    assert abs(split.hessian - one.hessian).max() <= 1e-14 * abs(one.hessian).max()


@pytest.mark.parametrize("threads", [1, 3])
def test_the_hessian_assembled_into_a_newton_system_equals_its_gather(monkeypatch, threads):
    """The kernel adding straight into a Newton system's free upper triangle gives the values
    the system gathers from the Hessian on the mesh's pattern, bit for bit (the same additions
    in the same order), on the mesh's own pattern and on a wider one; and the system refuses
    values made for another system."""
    import scipy.sparse as sp

    import jointsim.mechanics.fem as fem
    from jointsim.mechanics.newton import SystemValues

    monkeypatch.setattr(fem, "KERNEL_THREADS", threads)
    monkeypatch.setattr(fem, "MIN_CHUNK", 50)
    m = P2Mesh.from_linear(box_mesh((1.0, 1.0, 1.0), (3, 3, 3)))
    term = ElasticTerm(m, Material.neo_hookean(1.0))
    rng = np.random.default_rng(5)
    u = 0.02 * rng.standard_normal((m.n_nodes, 3))
    free = rng.random(3 * m.n_nodes) > 0.2
    indptr, indices, _ = m.sparsity
    n = 3 * m.n_nodes
    wider = sp.csr_matrix((np.ones(len(indices)), indices, indptr), shape=(n, n)) + sp.eye(n, k=n // 2) + sp.eye(n, k=-n // 2)
    wider.sort_indices()
    for pattern in ((indptr, indices), (wider.indptr, wider.indices)):
        system = NewtonSystem(*pattern, free)
        E, g, H, ok = term.evaluate_into(u, system)
        assert isinstance(H, SystemValues) and ok
        np.testing.assert_array_equal(system.data([H]), system.data([term.evaluate(u, True)[2]]))
        E0, g0 = term.evaluate(u, False)[:2]
        assert E == E0
        np.testing.assert_array_equal(g, g0)
    with pytest.raises(ValueError, match="another Newton system"):
        NewtonSystem(indptr, indices, free).data([H])


def test_a_newton_systems_values_are_the_free_upper_triangle_of_the_summed_hessians():
    """NewtonSystem.data of several terms (the elastic values, a matrix on the mesh's pattern, and
    a sparse term with duplicate entries, entries below the diagonal and on fixed components, as
    a contact or pressure term gives) is the free upper triangle of their dense sum."""
    import scipy.sparse as sp

    m = P2Mesh.from_linear(box_mesh((1.0, 1.0, 1.0), (2, 2, 2)))
    term = ElasticTerm(m, Material.neo_hookean(1.0))
    rng = np.random.default_rng(8)
    u = 0.02 * rng.standard_normal((m.n_nodes, 3))
    n = 3 * m.n_nodes
    free = rng.random(n) > 0.2
    indptr, indices, _ = m.sparsity
    system = NewtonSystem(indptr, indices, free)
    values = term.evaluate_into(u, system)[2]
    H = term.evaluate(u, True)[2]
    # a symmetric term on a few nodal 3 × 3 blocks (on the mesh's pattern), each entry given twice
    nodes = rng.choice(m.n_nodes, 6, replace=False)
    r = (3 * nodes[:, None, None] + np.arange(3)[None, :, None] + 0 * np.arange(3)).ravel()
    c = (3 * nodes[:, None, None] + 0 * np.arange(3)[:, None] + np.arange(3)).ravel()
    w = rng.standard_normal(len(r))
    block = sp.coo_matrix((np.concatenate([w, w]), (np.concatenate([r, c]), np.concatenate([c, r]))), shape=(n, n))
    once = block.tocsr()
    # each row's entries stored twice over: a CSR matrix that is not in canonical form
    twice = sp.csr_matrix((np.repeat(once.data, 2), np.repeat(once.indices, 2), 2 * once.indptr), shape=(n, n))
    assert not twice.has_canonical_format
    dense = 2 * H.toarray() + 2 * block.toarray()
    expected = sp.triu(sp.csr_matrix(dense[free][:, free]), format="csr")
    got = sp.csr_matrix((system.data([values, H, twice]), system.projected.indices, system.projected.indptr), shape=expected.shape)
    assert abs(got - expected).max() <= 1e-13 * np.abs(dense).max()


def test_the_reported_peak_strain_is_the_largest_principal_green_strain():
    """The peak strain a membrane state reports: under a homogeneous deformation every element's
    F is exact, so a uniaxial stretch λ with lateral contraction gives (λ² − 1)/2, and a large
    rigid rotation of it the same (Green–Lagrange strain is frame-invariant); undeformed, 0."""
    from scipy.spatial.transform import Rotation


    m = P2Mesh.from_linear(box_mesh((2.0, 1.0, 0.5), (3, 2, 2)))
    lam = 1.3
    F = np.diag([lam, lam**-0.5, lam**-0.5])
    u = m.nodes @ F.T - m.nodes
    assert m.peak_green_strain(u) == pytest.approx(0.5 * (lam**2 - 1), rel=1e-12)
    R = Rotation.from_rotvec([0.4, -1.1, 0.7]).as_matrix()
    assert m.peak_green_strain(m.nodes @ (R @ F).T - m.nodes) == pytest.approx(0.5 * (lam**2 - 1), rel=1e-12)
    assert abs(m.peak_green_strain(np.zeros_like(m.nodes))) <= 1e-15


@pytest.mark.skipif(not hasattr(os, "fork"), reason="needs fork")
def test_a_forked_child_runs_the_split_kernel(monkeypatch):
    """A child forked after the kernel threads exist gets threads of its own: the parent's pool
    has none in the child, and a chunk submitted to it would never run (a hang, caught here by a
    60 s wait on the child's answer)."""
    import select

    import jointsim.mechanics.fem as fem

    monkeypatch.setattr(fem, "KERNEL_THREADS", 2)
    monkeypatch.setattr(fem, "MIN_CHUNK", 50)
    m = P2Mesh.from_linear(box_mesh((1.0, 1.0, 1.0), (3, 3, 3)))
    k = ElementKernel(m, Material.neo_hookean(1.0))
    u = 0.01 * np.random.default_rng(5).standard_normal((m.n_nodes, 3))
    expected = k(u, False).energy.sum()  # the parent's pool now exists
    read, write = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: answer, then leave without running pytest's teardown
        try:
            os.write(write, repr(float(k(u, False).energy.sum())).encode())
        finally:
            os._exit(0)
    os.close(write)
    ready, _, _ = select.select([read], [], [], 60.0)
    if not ready:
        os.kill(pid, 9)
    os.waitpid(pid, 0)
    answer = os.read(read, 100).decode() if ready else ""
    os.close(read)
    assert ready, "the forked child's kernel call did not return within 60 s"
    assert float(answer) == expected


def test_a_device_warp_does_not_have_is_refused_by_name():
    """The element kernel's device is checked where it is given: a name Warp does not know, or a
    CUDA device on a machine without one, is a ValueError that names the parameter and the
    devices there are, not Warp's driver error from the first launch."""
    from jointsim.mechanics.fem import warp_device

    m = P2Mesh.from_linear(box_mesh((1.0, 1.0, 1.0), (1, 1, 1)))
    with pytest.raises(ValueError, match=r"device = 'gpu': not a Warp device on this machine \(available: 'cpu'"):
        ElementKernel(m, Material.neo_hookean(1.0), device="gpu")
    with pytest.raises(ValueError, match="--device = 7"):
        warp_device(7, "--device")
    missing = "cuda:0" if not wp.is_cuda_available() else f"cuda:{wp.get_cuda_device_count()}"
    with pytest.raises(ValueError, match=f"device = '{missing}'"):
        ElasticTerm(m, Material.neo_hookean(1.0), device=missing)
    assert warp_device("cpu") == "cpu"


@pytest.mark.skipif(not wp.is_cuda_available(), reason="no CUDA device on this machine")
@pytest.mark.parametrize("element", ["p2_tet mean_dilatation", "p2_tet pointwise", "wedge15"])
def test_the_kernel_on_cuda_equals_the_cpu(element):
    """Where a GPU is: the element kernel on Warp's CUDA device gives the CPU's energies,
    gradients and Hessians (the Hessian into a Newton system too), to round-off (another
    compiler's contractions, atomic additions in another order); P2 tetrahedra by either
    volumetric form and the default 15-node wedges."""
    import scipy.sparse as sp

    mat = Material.yeoh(9.8e3, 0.91e3, -0.16e3)
    if element == "wedge15":
        from jointsim.mechanics.wedge import WedgeElasticTerm

        m = wedge_grid(*[np.linspace(0.0, 1.0, 4)] * 3)
        cpu, gpu = (WedgeElasticTerm(m, mat, device=d) for d in ("cpu", "cuda"))
    else:
        m = P2Mesh.from_linear(box_mesh((1.0, 1.0, 1.0), (3, 3, 3)))
        cpu, gpu = (ElasticTerm(m, mat, volumetric=element.split()[1], device=d) for d in ("cpu", "cuda"))
    # 0.005 of the box: smallest det F 0.74 (at 0.02 a P2 element inverted, det F -0.07, and
    # NaN energies would have passed the comparisons below as equal)
    u = 0.005 * np.random.default_rng(6).standard_normal((m.n_nodes, 3))
    a, b = cpu.kernel(u, True, elements=True), gpu.kernel(u, True, elements=True)
    assert a.min_det.min() > 0.5 and np.isfinite(a.grad).all()
    scale = np.abs(a.element_hessians).max()
    np.testing.assert_allclose(b.energy, a.energy, rtol=1e-12, atol=1e-14 * np.abs(a.energy).max())
    np.testing.assert_allclose(b.grad, a.grad, rtol=0, atol=1e-12 * np.abs(a.grad).max())
    np.testing.assert_allclose(b.element_hessians, a.element_hessians, rtol=0, atol=1e-12 * scale)
    assert abs(sp.csr_matrix(b.hessian) - a.hessian).max() <= 1e-12 * scale
    indptr, indices, _ = m.sparsity
    system = NewtonSystem(indptr, indices, np.ones(3 * m.n_nodes, bool))
    np.testing.assert_allclose(system.data([gpu.evaluate_into(u, system)[2]]), system.data([cpu.evaluate_into(u, system)[2]]), rtol=0, atol=1e-12 * scale)


def test_cholesky_first_reaches_the_equilibrium_ldlt_reaches(monkeypatch):
    """The pressurised dome pressed 1 mm (two 0.5 mm steps): Newton with Cholesky-first
    factorisations ends where the LDLᵀ-only Newton does, to the force tolerance's 1e-3 of the
    contact force (both stop at their own iterate below it)."""
    import jointsim.mechanics.newton as newton
    from jointsim.geometry import isotropic_cap
    from jointsim.mechanics.dome import MembraneModel

    if newton.large_backend() != "pardiso":
        pytest.skip("Cholesky-first needs PARDISO")
    forces = {}
    for cholesky in (True, False):
        monkeypatch.setattr(newton, "CHOLESKY_FIRST", cholesky)
        model = MembraneModel(isotropic_cap(0.02, 0.01, 48), 2e-3, layers=1, pressure=50.0, target_radius=7.5e-3)
        assert model.system.projected.backend == "pardiso"
        top = model.first_contact_height((0.0, 0.0))
        forces[cholesky] = [model.press(np.array([0.0, 0.0, top - d])).force[2] for d in (0.5e-3, 1e-3)]
    np.testing.assert_allclose(forces[True], forces[False], rtol=2e-3)


@pytest.mark.parametrize(
    "material", [Material.neo_hookean(22e3), Material.yeoh(9.8e3, 0.91e3, -0.16e3)], ids=["neo-Hookean", "Yeoh"]
)
def test_uniaxial_nominal_stress(material):
    lam, L = np.array([1.1, 1.5, 2.0]), 1e-2
    m = P2Mesh.from_linear(box_mesh((L, L, L), (1, 1, 1)))
    P = uniaxial_nominal_stress(m, ElasticTerm(m, material), L, lam)
    # the closed form is incompressible; κ = 1000 μ leaves an O(μ/κ) compressibility (~0.1 %)
    np.testing.assert_allclose(P, material.uniaxial_nominal_stress(lam), rtol=5e-3)
    if material.c2 == 0:
        np.testing.assert_allclose(P, material.mu * (lam - lam**-2), rtol=5e-3)


@pytest.mark.parametrize("volumetric", ["pointwise", "mean_dilatation"])
def test_pressurised_thick_sphere(volumetric):
    """An octant of the shell A ≤ r ≤ B under cavity pressure, on its symmetry planes, against
    the exact inflation (conftest.inflate_octant)."""
    from jointsim.mesh.shapes import shell_octant, spherical_midsides

    A, B, mu = 5e-3, 10e-3, 22e3
    # 1200 curved (isoparametric) P2 tets: 10² triangles per sphere, 4 layers through the wall
    m = P2Mesh.from_linear(shell_octant(A, B, 10, 4), spherical_midsides)
    pressures = np.array([4e3, 8e3, 12e3])
    exact, _, _ = inflate_octant(m, ElasticTerm(m, Material.neo_hookean(mu), volumetric=volumetric), A, B, mu, pressures)
    # measured 0.3-0.9 % high pointwise, 0.8-1.1 % low by mean dilatation (its element-wise
    # constant pressure against a pressure falling through the wall); both fall under
    # refinement (the full shell in 5 k unstructured tets: 0.8-1.5 % and 0.07-0.13 %)
    np.testing.assert_allclose(pressures, exact, rtol=0.02)


def test_a_nearly_incompressible_cantilever_bends_without_locking():
    """A 20 × 2 × 2 mm cantilever, κ = 1000 μ, two P2 elements through the thickness, under a
    small tip load, against Timoshenko's δ = PL³/3EI + PL/(κₛGA) with E = 3μ, G = μ. Measured:
    mean dilatation 1.015 of it, the pointwise penalty 0.874 (locked); both converge to ~0.98,
    the clamped 3-D limit, under refinement: results/locking_cantilever.md
    (benchmarks/bench_locking.py)."""
    L, t, mu, P = 20e-3, 2e-3, 22e3, 1e-5
    m = P2Mesh.from_linear(box_mesh((L, t, t), (10, 2, 2)))
    deflection = {v: cantilever_tip_ratio(m, ElasticTerm(m, Material.neo_hookean(mu), volumetric=v), L, t, mu, P)
                  for v in ("mean_dilatation", "pointwise")}
    assert deflection["mean_dilatation"] == pytest.approx(1.0, abs=0.03)
    assert deflection["pointwise"] < 0.9


def test_bad_materials_are_rejected():
    with pytest.raises(ValueError, match="mu"):
        Material.neo_hookean(-1.0)
    with pytest.raises(ValueError, match="c1"):
        Material(c1=0.0, bulk=1.0)
    with pytest.raises(ValueError, match="bulk"):
        Material(c1=1.0, bulk=0.0)
    with pytest.raises(ValueError, match="stretches up to 2"):
        Material.yeoh(1.0, 0.0, -5.0)


def test_newton_refuses_an_inverted_start():
    m = P2Mesh.from_linear(box_mesh((1.0, 1.0, 1.0), (1, 1, 1)))
    term = ElasticTerm(m, Material.neo_hookean(1.0))
    u = np.zeros_like(m.nodes)
    u[:, 2] = -2.0 * m.nodes[:, 2]  # mirror every element through z = 0
    with pytest.raises(NewtonError, match="inverted"):
        minimize_energy([term], u, np.zeros_like(u, bool))


class _Spring:
    """E = ½ k·|u|² on every component: Newton's first step lands on the minimum exactly."""

    def evaluate(self, u, hessian):
        import scipy.sparse as sp

        x = u.ravel()
        return 0.5 * float(x @ x), x.copy(), (sp.identity(x.size, format="csr") if hessian else None), True


def test_newton_counts_convergence_on_its_last_allowed_iteration():
    u0 = np.ones((2, 3))
    fixed = np.zeros_like(u0, bool)
    res = minimize_energy([_Spring(), NodalForce(np.full((2, 3), 0.5))], u0, fixed, max_iter=1)
    assert res.iterations == 1 and res.residual <= 1e-12
    np.testing.assert_allclose(res.u, 0.5, rtol=1e-12)
    with pytest.raises(NewtonError, match="no convergence in 0 iterations"):
        minimize_energy([_Spring()], u0, fixed, max_iter=0)


def test_chord_steps_reach_the_same_equilibrium_with_fewer_factorisations(monkeypatch):
    """A compressible neo-Hookean block (κ = 2μ), its top sheared by 0.75 of its height, solved
    from rest to a gradient of 1e-10 of the initial one, with chord steps (the last factor
    re-used while it keeps reducing the gradient) and with a fresh Hessian every iteration. Both
    stop on the same gradient test, and the block's Hessian is well conditioned, so the two
    equilibria agree to ~1e-10 (measured 9e-12); the chord steps replace factorisations
    (measured 10 against 12). 6 084 free unknowns: PARDISO, whose Cholesky marks a factor
    positive definite (SuperLU, below 5 000, gives Newton no such factor to re-use)."""
    import jointsim.linalg as solver
    import jointsim.mechanics.newton as newton

    if "pardiso" not in solver.available_backends():
        pytest.skip("PARDISO (pypardiso) not installed: no positive definite factor to re-use")
    m = P2Mesh.from_linear(box_mesh((1.0, 1.0, 1.0), (6, 6, 6)))
    X = m.nodes
    fixed = np.zeros_like(X, bool)
    fixed[np.isclose(X[:, 2], 0)] = True
    top = np.isclose(X[:, 2], 1.0)
    f = np.zeros_like(X)
    f[top, 0] = 0.3 / top.sum()
    terms = [ElasticTerm(m, Material.neo_hookean(1.0, bulk_ratio=2.0)), NodalForce(f)]
    factor = solver.PatternSolver.factor
    runs = {}
    for chord in (True, False):
        monkeypatch.setattr(newton, "CHORD_STEPS", chord)
        calls = []
        monkeypatch.setattr(solver.PatternSolver, "factor", lambda self, data: (calls.append(1), factor(self, data))[1])
        system = NewtonSystem(*m.sparsity[:2], ~fixed.ravel())
        assert system.projected.backend == "pardiso"
        runs[chord] = (minimize_energy(terms, np.zeros_like(X), fixed, rtol=1e-10, system=system), len(calls))
    (with_chords, n_with), (without, n_without) = runs[True], runs[False]
    assert with_chords.chord_steps >= 1 and without.chord_steps == 0
    assert n_with < n_without
    assert np.abs(with_chords.u - without.u).max() <= 1e-8 * np.abs(without.u).max()
    assert with_chords.u[top, 0].mean() == pytest.approx(0.748, rel=1e-3)  # large shear: nonlinear


def test_rigid_sphere_into_a_thick_block_follows_hertz():
    from jointsim.mesh.shapes import graded_axis, grid_mesh

    R, W, h0, d, mu = 10e-3, 55e-3, 0.25e-3, 0.2e-3, 22e3
    E = 3 * mu  # ν = 0.5
    # a quarter of a block 11 × 11 × 5.5 cm (39 contact radii √(Rd): the rigid base and far sides
    # stiffen it by ~1 %, measured against a 16 × 16 × 8 cm block), cells growing from 0.25 mm at
    # the contact by 1.4× per cell
    ax = graded_axis(W, h0, 1.4)
    m = P2Mesh.from_linear(grid_mesh(ax, ax, -ax[::-1]))
    F, penetration, a = press_block(m, ElasticTerm(m, Material.neo_hookean(mu)), R, W, h0, d, E)
    hertz = 16 / 9 * E * np.sqrt(R) * d**1.5
    # d/R = 0.02: measured +2.4 % (+1.5 % on the 16 cm block; small-strain theory, finite block,
    # 7 cells across the contact)
    assert F == pytest.approx(hertz, rel=0.05)
    assert penetration < 0.01 * d
    assert a == pytest.approx(np.sqrt(R * d), rel=0.15)


def test_friction_term_gradient_and_hessian_match_finite_differences():
    from jointsim.mechanics.contact import SphereContact, SphereFriction

    rng = np.random.default_rng(1)
    X = rng.uniform(-1e-3, 1e-3, (6, 3))
    X[:, 2] = 0.0
    c = SphereContact(X, np.arange(6), np.full(6, 1e-7), 5e-3, stiffness=1e9)
    c.centre = np.array([0.0, 0.0, 5e-3 - 1e-5])  # every node 10 µm inside
    fr = SphereFriction(c, 0.4, slip=1e-6)
    fr.lag(np.zeros_like(X), c.centre)
    c.centre = c.centre + np.array([3e-6, 0.0, 0.0])  # some nodes stick, some slip
    u = rng.normal(0, 1e-6, X.shape)
    E, g, H, _ = fr.evaluate(u, True)
    h = 1e-10
    for i in rng.choice(u.size, 6, replace=False):
        du = np.zeros(u.size)
        du[i] = h
        Ep, gp = fr.evaluate(u + du.reshape(u.shape), False)[:2]
        Em, gm = fr.evaluate(u - du.reshape(u.shape), False)[:2]
        assert g[i] == pytest.approx((Ep - Em) / (2 * h), rel=1e-5, abs=1e-12 * np.abs(g).max())
        np.testing.assert_allclose(H.toarray()[:, i], (gp - gm) / (2 * h), rtol=1e-4, atol=1e-6 * np.abs(H).max())


def test_pressure_term_gradient_and_hessian_match_differences():
    import trimesh

    rng = np.random.default_rng(3)
    s = trimesh.creation.icosphere(subdivisions=1, radius=1e-2)
    X = s.vertices + rng.normal(0, 5e-4, s.vertices.shape)  # not a sphere: no symmetry to hide in
    term = PressureTerm(X, s.faces, pressure=2e3)
    u = rng.normal(0, 1e-3, X.shape)
    E, g, H, _ = term.evaluate(u, True)
    assert -E / term.pressure == pytest.approx(trimesh.Trimesh(X + u, s.faces, process=False).volume, rel=1e-12)
    # V is cubic in the positions, so the gradient is quadratic and its central difference is
    # exact (to round-off) for any step; the energy's has an O(h²) error, small at this h
    h = 1e-4
    Hd = H.toarray()
    for i in range(u.size):
        du = np.zeros(u.size)
        du[i] = h
        Ep, gp = term.evaluate(u + du.reshape(u.shape), False)[:2]
        Em, gm = term.evaluate(u - du.reshape(u.shape), False)[:2]
        assert g[i] == pytest.approx((Ep - Em) / (2 * h), rel=1e-5, abs=1e-9 * np.abs(g).max())
        np.testing.assert_allclose(Hd[:, i], (gp - gm) / (2 * h), rtol=1e-9, atol=1e-9 * np.abs(Hd).max())
    np.testing.assert_array_equal(Hd, Hd.T)


def test_a_sliding_sphere_feels_coulomb_friction():
    """A rigid sphere pressed into a block and dragged sideways well past the stick limit: the
    tangential force is μ times the normal force (gross sliding; the normal forces are re-lagged
    twice per step, as in the membrane model)."""
    from jointsim.mechanics.contact import SphereContact, SphereFriction, nodal_areas
    from jointsim.mesh.shapes import grid_mesh

    R, d, mu, cof = 10e-3, 0.3e-3, 22e3, 0.3
    xs = np.linspace(-8e-3, 8e-3, 17)
    ys = np.linspace(0.0, 8e-3, 9)  # half block: y = 0 is a symmetry plane of x-sliding
    zs = np.linspace(-6e-3, 0.0, 5)
    m = P2Mesh.from_linear(grid_mesh(xs, ys, zs))
    bf = m.boundary_faces
    top = bf[np.all(np.isclose(m.nodes[bf[:, :3], 2], 0.0), axis=1)]
    nodes, w = nodal_areas(m.nodes, linear_subtriangles(top))
    contact = SphereContact(m.nodes, nodes, w, R, stiffness=100 * 3 * mu / 1e-3)
    friction = SphereFriction(contact, cof, slip=1e-6)
    X = m.nodes
    fixed = np.zeros_like(X, bool)
    fixed[np.isclose(X[:, 1], 0), 1] = True
    fixed[np.isclose(X[:, 2], zs[0]), :] = True
    terms = [ElasticTerm(m, Material.neo_hookean(mu)), contact, friction]
    u = np.zeros_like(X)
    c = np.array([0.0, 0.0, R - d])
    contact.centre = c
    system = NewtonSystem(*m.sparsity[:2], ~fixed.ravel())
    u = minimize_energy(terms[:2], u, fixed, system=system).u
    for step in range(4):  # drag 0.2 mm per step
        start, c = c.copy(), c + np.array([0.2e-3, 0.0, 0.0])
        u_start = u
        friction.lag(u_start, start)
        contact.centre = c
        for _ in range(3):
            u = minimize_energy(terms, u, fixed, rtol=1e-10, system=system).u
            friction.lag(u_start, start, u_normal=u)
    Fn = contact.force(u)
    Ft = friction.force(u)
    # the block drags the sphere back (−x) with μ·N; the sphere's normal force is mostly z
    assert Ft[0] < 0
    assert abs(Ft[0]) == pytest.approx(cof * Fn[2], rel=0.03)


def test_contact_hessian_exact_capped_and_gauss_newton():
    """The exact contact Hessian matches finite differences of the gradient; the projected
    (Gauss–Newton) one drops the sphere's curvature term k·w·pen/r·(I − n nᵀ), i.e. differs by
    exactly that and is PSD; with ``curvature_cap`` the term uses min(pen, cap)."""
    from jointsim.mechanics.contact import SphereContact

    rng = np.random.default_rng(3)
    X = rng.uniform(-1e-3, 1e-3, (8, 3))
    X[:, 2] = 0.0
    c = SphereContact(X, np.arange(8), np.full(8, 1e-7), 5e-3, stiffness=1e9)
    c.centre = np.array([0.0, 0.0, 5e-3 - 1e-4])  # penetrations −100 … +100 µm
    u = rng.normal(0, 1e-6, X.shape)
    _, g, H_exact, _ = c.evaluate(u, True, exact=True)
    h = 1e-10
    for i in range(u.size):
        du = np.zeros(u.size)
        du[i] = h
        gp = c.evaluate(u + du.reshape(u.shape), False)[1]
        gm = c.evaluate(u - du.reshape(u.shape), False)[1]
        np.testing.assert_allclose(H_exact.toarray()[:, i], (gp - gm) / (2 * h), rtol=1e-5, atol=1e-7 * np.abs(H_exact).max())
    np.testing.assert_array_equal(c.evaluate(u, True)[2].toarray(), H_exact.toarray())  # cap ∞ by default
    H_gn = c.projected_hessian(u).toarray()
    cap = 3e-5  # among the nodes' penetrations
    c.curvature_cap = cap
    H_cap = c.evaluate(u, True)[2].toarray()
    d = X + u - c.centre
    r = np.linalg.norm(d, axis=1)
    pen = c.radius - r
    n = d / r[:, None]
    for k in np.flatnonzero(pen > 0):
        block = slice(3 * k, 3 * k + 3)
        curvature = c.stiffness * c.weights[k] * pen[k] / r[k] * (np.eye(3) - np.outer(n[k], n[k]))
        np.testing.assert_allclose(H_gn[block, block] - H_exact.toarray()[block, block], curvature, rtol=1e-9, atol=1e-12 * np.abs(H_gn).max())
        capped = curvature * min(pen[k], cap) / pen[k]
        np.testing.assert_allclose(H_gn[block, block] - H_cap[block, block], capped, rtol=1e-9, atol=1e-12 * np.abs(H_gn).max())
    assert (pen > cap).any() and ((pen > 0) & (pen < cap)).any()  # both branches of the cap exercised
    assert np.linalg.eigvalsh(H_gn).min() >= -1e-9 * np.abs(H_gn).max()  # Gauss–Newton: PSD
