"""Tikhonov difference imaging, λ selection, and the image metrics on hand-built grids."""

import numpy as np
import pytest

from jointsim.mesh.shapes import box_mesh
from jointsim.metrics import image_metrics, largest_cluster, rms
from jointsim.reconstruction.grid import ChamberGrid, VoxelGrid
from jointsim.reconstruction.tikhonov import SVD, Reconstructor, choose_lambda, lambda_grid, tikhonov_solve


def _ill_posed(n_meas=80, n_cells=200, seed=0):
    rng = np.random.default_rng(seed)
    U, _ = np.linalg.qr(rng.standard_normal((n_meas, n_meas)))
    V, _ = np.linalg.qr(rng.standard_normal((n_cells, n_meas)))
    s = np.logspace(0, -5, n_meas)  # singular values decaying like an EIT Jacobian's
    J = (U * s) @ V.T
    x_true = V @ (rng.standard_normal(n_meas) * s**0.7)  # a truth the data can partly see
    return J, x_true, rng


def test_tikhonov_matches_the_normal_equations():
    J, x_true, rng = _ill_posed()
    dv = J @ x_true + 1e-4 * rng.standard_normal(J.shape[0])
    for lam in (1e-4, 1e-2, 1.0):
        x = tikhonov_solve(J, dv, lam)
        ref = np.linalg.solve(J.T @ J + lam**2 * np.eye(J.shape[1]), J.T @ dv)
        np.testing.assert_allclose(x, ref, rtol=1e-6, atol=1e-9 * np.abs(ref).max())


def test_leave_one_out_from_the_svd_equals_refitting():
    J, x_true, rng = _ill_posed(30, 50)
    dv = J @ x_true + 1e-3 * rng.standard_normal(30)
    grid = np.array([1e-3, 1e-2, 1e-1])
    score = choose_lambda(SVD.of(J), dv, "loo", grid=grid).score
    for lam, sc in zip(grid, score):
        brute = 0.0
        for i in range(30):
            keep = np.arange(30) != i
            x = np.linalg.solve(J[keep].T @ J[keep] + lam**2 * np.eye(50), J[keep].T @ dv[keep])
            brute += (dv[i] - J[i] @ x) ** 2
        assert sc == pytest.approx(brute, rel=1e-6)


def test_kfold_from_the_svd_equals_refitting():
    J, x_true, rng = _ill_posed(30, 50)
    dv = J @ x_true + 1e-3 * rng.standard_normal(30)
    lam = 3e-3
    sc = choose_lambda(SVD.of(J), dv, "kfold", grid=np.array([lam, 1.0]), k=5, seed=4).score[0]
    folds = np.array_split(np.random.default_rng(4).permutation(30), 5)
    brute = 0.0
    for f in folds:
        keep = np.setdiff1d(np.arange(30), f)
        x = np.linalg.solve(J[keep].T @ J[keep] + lam**2 * np.eye(50), J[keep].T @ dv[keep])
        brute += ((dv[f] - J[f] @ x) ** 2).sum()
    assert sc == pytest.approx(brute, rel=1e-6)


@pytest.mark.parametrize("method", ["kfold", "loo", "gcv"])
def test_cross_validation_picks_a_lambda_near_the_noise_optimal_one(method):
    J, x_true, rng = _ill_posed(120, 300, seed=2)
    clean = J @ x_true
    frames = clean + 1e-3 * np.abs(clean).mean() * rng.standard_normal((20, len(clean)))
    svd = SVD.of(J)
    grid = lambda_grid(svd, 500)
    choice = choose_lambda(svd, frames, method, grid=grid)
    # the noise-optimal λ minimises the image error against the truth
    err = np.array([np.linalg.norm(frames @ svd.reconstruction_matrix(l).T - x_true) for l in grid])
    lam_opt = grid[err.argmin()]
    got = np.linalg.norm(frames @ svd.reconstruction_matrix(choice.lam).T - x_true)
    # CV minimises the prediction error, not the image error; the two optima differ by a small
    # factor (measured 1.7-1.8 here, costing 21-27 % in image error)
    assert abs(np.log10(choice.lam / lam_opt)) < np.log10(3.0)
    assert got <= 1.5 * err.min()
    assert len(choice.grid) >= 500


def test_lcurve_corner_is_inside_the_grid():
    J, x_true, rng = _ill_posed()
    dv = J @ x_true + 1e-4 * rng.standard_normal(J.shape[0])
    svd = SVD.of(J)
    c = choose_lambda(svd, dv, "lcurve")
    assert c.grid[5] < c.lam < c.grid[-5]


def test_bad_lambda_inputs():
    J, x_true, _ = _ill_posed(20, 30)
    svd = SVD.of(J)
    with pytest.raises(ValueError, match="grid"):
        choose_lambda(svd, J @ x_true, grid=np.array([1e-3, 0.0, 1.0]))
    with pytest.raises(ValueError, match="all-zero"):
        choose_lambda(svd, np.zeros(20))
    with pytest.raises(ValueError, match="method"):
        choose_lambda(svd, J @ x_true, method="magic")


def test_reconstructor_frame_is_a_matvec_and_noise_normalisation():
    J, x_true, rng = _ill_posed()
    dv = J @ x_true
    rec = Reconstructor.build(J, dv + 1e-4 * rng.standard_normal(len(dv)))
    frames = np.stack([dv, 2 * dv])
    np.testing.assert_allclose(rec.image(frames), np.stack([rec.R @ dv, 2 * rec.R @ dv]))
    # the noise std of the image matches Monte Carlo
    noise = 1e-3 * rng.standard_normal((4000, len(dv)))
    mc = rec.image(noise).std(axis=0)
    np.testing.assert_allclose(mc, rec.noise_std(1e-3), rtol=0.1)


def _cube_grid(n=8):
    """An n³ grid of 1 mm voxels over a box meshed with 6 tets per voxel."""
    mesh = box_mesh((n * 1e-3,) * 3, (n, n, n))
    return ChamberGrid.over(mesh, grid=VoxelGrid(np.zeros(3), np.full(3, 1e-3), (n, n, n)))


def _img(grid, cells):
    x = np.zeros(grid.grid.n_cells)
    for (i, j, k), val in cells.items():
        x[np.ravel_multi_index((i, j, k), grid.grid.shape)] = val
    return x[grid.active]


def test_chamber_grid_shares_each_element_among_the_cells_of_its_children():
    # C[k, c] = (children of element k whose centroid lies in cell c) / 64, from the children's
    # barycentres directly; elements here straddle voxels (1 mm cells, 0.7 mm voxels, offset)
    from jointsim.reconstruction.grid import _child_barycentres

    mesh = box_mesh((3e-3,) * 3, (3, 3, 3))
    rng = np.random.default_rng(2)
    inner = np.all((mesh.nodes > 1e-9) & (mesh.nodes < 3e-3 - 1e-9), axis=1)
    mesh = type(mesh)(mesh.nodes + inner[:, None] * rng.uniform(-2e-4, 2e-4, mesh.nodes.shape), mesh.tets)
    vg = VoxelGrid(np.full(3, -0.2e-3), np.full(3, 0.7e-3), (5, 6, 7))  # unequal: the flat index order counts
    g = ChamberGrid.over(mesh, grid=vg)
    bary = _child_barycentres(2)
    cells = vg.cell_of(np.einsum("sa,kai->ksi", bary, mesh.nodes[mesh.tets]).reshape(-1, 3)).reshape(mesh.n_tets, -1)
    expected = np.zeros((mesh.n_tets, vg.n_cells))
    np.add.at(expected, (np.repeat(np.arange(mesh.n_tets), len(bary)), cells.ravel()), 1.0 / len(bary))
    np.testing.assert_array_equal(g.active, np.flatnonzero(expected.any(axis=0)))
    np.testing.assert_allclose(g.C.toarray(), expected[:, g.active], rtol=0, atol=1e-15)
    assert g.volume.sum() == pytest.approx(27e-9, rel=1e-12)


def test_cube_grid_has_full_cells():
    g = _cube_grid()
    assert g.n_cells == 512
    np.testing.assert_allclose(g.volume_fraction, 1.0)


def test_the_larger_of_two_blobs_wins():
    g = _cube_grid()
    small = {(1, 1, 1): -1.0, (1, 1, 2): -0.9}
    big = {(5, 5, 5): -0.95, (5, 5, 6): -0.8, (5, 6, 5): -0.8, (6, 5, 5): -0.85}
    x = _img(g, small | big)
    mask = largest_cluster(g, x)
    assert mask.sum() == 4
    m = image_metrics(g, x)
    assert m.com[0] > 5e-3 and m.n_cells == 4


def test_diagonal_neighbours_are_not_connected():
    g = _cube_grid()
    x = _img(g, {(2, 2, 2): 1.0, (3, 3, 2): 0.95, (4, 4, 4): 0.9})
    assert largest_cluster(g, x).sum() == 1  # three separate cells; ties go to the largest |x|
    assert largest_cluster(g, x)[np.argmax(x)]


def test_threshold_edges():
    g = _cube_grid()
    x = _img(g, {(3, 3, 3): -1.0, (3, 3, 4): -0.75, (3, 3, 5): -0.7499})
    assert largest_cluster(g, x, 0.75).sum() == 2  # exactly 75 % is in
    assert largest_cluster(g, x, 1.0).sum() == 1
    # cells of the opposite sign never join, however large
    y = _img(g, {(3, 3, 3): -1.0, (3, 3, 4): 0.9})
    assert largest_cluster(g, y).sum() == 1
    with pytest.raises(ValueError, match="threshold"):
        largest_cluster(g, x, 0.0)


def test_com_of_a_symmetric_blob_is_its_centre():
    g = _cube_grid()
    cells = {(4, 4, 4): -1.0}
    for d in [(1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1)]:
        cells[(4 + d[0], 4 + d[1], 4 + d[2])] = -0.8
    x = _img(g, cells)
    centre = np.array([4.5e-3] * 3)
    m = image_metrics(g, x, true_centre=centre, target_volume=7e-9)
    np.testing.assert_allclose(m.com, centre, atol=1e-12)
    assert m.com_error == pytest.approx(0.0, abs=1e-12)
    assert m.n_cells == 7
    assert m.sum_sigma == pytest.approx(-1.0 - 6 * 0.8)
    assert m.diameter_equivalent == pytest.approx((6 * 7e-9 / np.pi) ** (1 / 3))
    assert m.extent_xy == pytest.approx(3e-3)
    assert m.ringing == 0.0


def test_all_zero_image_is_rejected():
    g = _cube_grid()
    with pytest.raises(ValueError, match="all zero"):
        image_metrics(g, np.zeros(g.n_cells))
    with pytest.raises(ValueError, match="expected 512"):
        largest_cluster(g, np.ones(5))


def test_rms():
    assert rms(np.array([3.0, -4.0])) == pytest.approx(np.sqrt(12.5))


def test_a_prior_gives_the_minimiser_of_its_objective():
    """SVD.generalized: R δv = argmin ‖Jx − δv‖² + λ²xᵀPx, checked against the normal
    equations (JᵀJ + λ²P) x = Jᵀδv solved densely, for NOSER and a smoothness Laplacian on a
    small grid; the identity prior reproduces zeroth-order Tikhonov."""
    import scipy.sparse as sp

    from jointsim.reconstruction.tikhonov import SVD, prior_matrix

    rng = np.random.default_rng(0)
    J = rng.normal(size=(30, 80)) * np.linspace(1, 0.01, 80)  # sensitivity decaying across the cells
    dv = rng.normal(size=30)
    path = sp.diags([np.ones(79), np.ones(79)], [-1, 1])
    L = (sp.diags(np.asarray(path.sum(axis=1)).ravel()) - path).tocsr()
    lam = 0.3
    for name in ("noser", "laplacian"):
        P = prior_matrix(name, J, L).toarray()
        x = np.linalg.solve(J.T @ J + lam**2 * P, J.T @ dv)
        np.testing.assert_allclose(SVD.generalized(J, sp.csr_matrix(P)).reconstruction_matrix(lam) @ dv, x,
                                   rtol=1e-8, atol=1e-10 * np.abs(x).max())
    np.testing.assert_allclose(SVD.generalized(J, sp.identity(80)).reconstruction_matrix(lam),
                               SVD.of(J).reconstruction_matrix(lam), rtol=1e-8, atol=1e-12)
    assert prior_matrix("tikhonov", J) is None


def test_the_scene_offers_the_reconstructions_priors():
    from jointsim.reconstruction.tikhonov import DEPTH_EXPONENT, PRIORS
    from jointsim.scene import IMAGE_PRIORS, ReconstructionSpec

    assert IMAGE_PRIORS == PRIORS
    assert ReconstructionSpec().depth_exponent == DEPTH_EXPONENT


def test_the_depth_prior_weighs_cells_by_their_height_and_lifts_the_image(paper_scene):
    """prior "depth": P = diag(((z + z₀)/H)^−q), 1 at the highest cell and growing towards the
    base; q = 0 is Tikhonov's image to round-off. On a press's noise-free δV (test preset, the
    same λ for both) the depth prior's image has its CoM higher than Tikhonov's: the cells near
    the base electrodes cost more."""
    from dataclasses import replace

    import scipy.sparse as sp

    from jointsim.instrument import Instrument
    from jointsim.mechanics.geometric import indent_dome
    from jointsim.reconstruction.tikhonov import SVD, prior_matrix

    z = np.array([0.0, 1e-3, 4e-3, 9e-3])
    P = prior_matrix("depth", np.ones((2, 4)), heights=z, exponent=2.0, half_voxel=0.5e-3)
    np.testing.assert_allclose(P.diagonal(), ((z + 0.5e-3) / 9.5e-3) ** -2.0, rtol=1e-14)
    assert P.diagonal()[-1] == 1.0 and np.all(np.diff(P.diagonal()) < 0)
    s = paper_scene.with_mesh_preset("test")
    s = replace(s, membrane=replace(s.membrane, rim_vertices=32, layers=1), reconstruction=replace(s.reconstruction, cells=1000))
    inst = Instrument.build(s)
    try:
        J, grid = inst.imager.jacobian, inst.imager.grid
        dv = inst.measure(indent_dome(inst.reference_dome, (5e-3, 0.0), 2e-3, 7.5e-3).dome, None, image=False).dv_clean
        lam = inst.imager.reconstructor.lam
        z = grid.centroid[:, 2]
        flat = SVD.generalized(J, prior_matrix("depth", J, heights=z, exponent=0.0)).reconstruction_matrix(lam) @ dv
        np.testing.assert_allclose(flat, SVD.of(J).reconstruction_matrix(lam) @ dv, rtol=0, atol=1e-8 * np.abs(flat).max())
        deep = SVD.generalized(J, prior_matrix("depth", J, heights=z, exponent=2.0, half_voxel=1e-4)).reconstruction_matrix(lam) @ dv
        height = lambda x: (np.abs(x) * z).sum() / np.abs(x).sum()  # noqa: E731
        assert height(deep) > height(flat) + 0.5e-3
    finally:
        inst.free()
    assert isinstance(P, sp.csr_matrix)


def test_the_voxel_laplacian_is_a_graph_laplacian(test_chamber):
    """Rows sum to zero, the diagonal counts face neighbours (≤ 6), constants are its null space."""
    from jointsim.reconstruction.grid import ChamberGrid

    _, ch = test_chamber
    g = ChamberGrid.over(ch.mesh, 1000)
    L = g.laplacian()
    assert abs(L.sum(axis=1)).max() < 1e-12 and 0 < L.diagonal().max() <= 6
    assert (abs(L - L.T)).max() == 0
