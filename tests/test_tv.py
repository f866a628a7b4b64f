"""Total-variation images (jointsim.reconstruction.tv) on a problem with a known answer — a
blocky inclusion seen through a smoothing operator — and in the instrument."""

import numpy as np
import scipy.sparse as sp

from jointsim.reconstruction.tv import TVImager, difference_operator, discrepancy_lambda, tv_objective


def chain(n: int) -> sp.csr_matrix:
    """The graph Laplacian of n cells in a row."""
    main = np.full(n, 2.0)
    main[[0, -1]] = 1.0
    return sp.diags([main, -np.ones(n - 1), -np.ones(n - 1)], [0, 1, -1]).tocsr()


def block_problem(seed: int = 0, noise: float = 0.01):
    """A block of 1 in zeros (60 cells) seen through 40 smooth, overlapping Gaussian sensors,
    noise of ``noise`` × the largest reading: (J, x_true, dv, σ, the smooth image, D)."""
    rng = np.random.default_rng(seed)
    n, m = 60, 40
    c = np.linspace(0, n - 1, m)
    J = np.exp(-0.5 * ((np.arange(n)[None] - c[:, None]) / 3.0) ** 2)
    x_true = np.zeros(n)
    x_true[20:35] = 1.0
    clean = J @ x_true
    sigma = noise * np.abs(clean).max()
    dv = clean + sigma * rng.normal(size=m)
    L = chain(n)
    x0 = np.linalg.solve(J.T @ J + 0.3 * L.toarray() + 1e-6 * np.eye(n), J.T @ dv)
    return J, x_true, dv, sigma, x0, difference_operator(L)


def test_the_difference_operator_squares_to_the_laplacian():
    L = chain(7) + 0.5 * chain(7)
    D = difference_operator(L)
    assert D.shape == (6, 7)
    np.testing.assert_allclose((D.T @ D).toarray(), L.toarray(), atol=1e-15)


def test_every_lagged_diffusivity_step_lowers_the_objective():
    """A majorise–minimise iteration: the TV objective at its λ and β falls step by step."""
    J, _, dv, _, x0, D = block_problem()
    lam, beta, ridge = 0.05, 1e-3, 1e-6
    values = [tv_objective(J, D, x0, dv, lam, beta, ridge)]
    for k in range(1, 6):
        values.append(tv_objective(J, D, TVImager(J, D, lam, beta, ridge, iterations=k).image(dv, x0), dv, lam, beta, ridge))
    assert all(b <= a * (1 + 1e-12) for a, b in zip(values, values[1:])) and values[-1] < 0.9 * values[0]


def test_the_discrepancy_lambda_leaves_the_noise_and_finds_the_block():
    """λ by the discrepancy principle on two noisy frames of the block: their images' mean
    squared residual is n σ² (within 15 %: λ is bracketed to 6 %, and the residual moves
    slower than λ), and the TV image is closer to the block than the smooth one (error down by
    a quarter: 0.67× here; the λ that would be best, ~0.1, gives 0.55×, the principle's known
    lean to smoothing)."""
    J, x_true, dv, sigma, x0, D = block_problem()
    J2, _, dv2, _, x02, _ = block_problem(seed=1)
    tv = discrepancy_lambda(J, D, np.array([dv, dv2]), np.array([x0, x02]), sigma, 1e-6, lam_smooth=0.3)  # x0 is the 0.3-weighted smooth image
    r = [J @ tv.image(d, s) - d for d, s in ((dv, x0), (dv2, x02))]
    assert abs(np.mean([e @ e for e in r]) / (len(dv) * sigma**2) - 1) < 0.15
    assert np.linalg.norm(tv.image(dv, x0) - x_true) < 0.75 * np.linalg.norm(x0 - x_true)


def test_the_instrument_images_with_total_variation(paper_scene):
    """[reconstruction] prior = "tv" at the test preset: a press's TV image is another image of
    the same dent: Σσ of the same sign, its CoM within a voxel of the Laplacian's in the plane
    and within 2.5 voxels in 3-D (a piecewise-constant image's extreme cell means little: its
    flat region's CoM is what it says)."""
    from dataclasses import replace

    from jointsim.instrument import Instrument
    from jointsim.mechanics.geometric import indent_dome

    images = {}
    for prior in ("laplacian", "tv"):
        s = paper_scene.with_mesh_preset("test")
        s = replace(s, membrane=replace(s.membrane, rim_vertices=32, layers=1),
                    reconstruction=replace(s.reconstruction, prior=prior, cells=1000))
        inst = Instrument.build(s)
        try:
            dome = indent_dome(inst.reference_dome, (5e-3, 0.0), 2e-3, 7.5e-3).dome
            r = inst.measure(dome, None)
            images[prior] = (r.image, r.metrics.com, float(np.cbrt(inst.imager.grid.voxel_volume)))
            assert (inst.imager.tv is not None) == (prior == "tv")
        finally:
            inst.free()
    (a, com_a, voxel), (b, com_b, _) = images["laplacian"], images["tv"]
    assert np.all(np.isfinite(b)) and not np.allclose(a, b)
    assert np.sign(a.sum()) == np.sign(b.sum()) == -1
    assert np.linalg.norm((com_a - com_b)[:2]) < voxel and np.linalg.norm(com_a - com_b) < 2.5 * voxel
