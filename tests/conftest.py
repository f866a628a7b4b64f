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


@pytest.fixture(scope="session", autouse=True)
def _mesh_cache(tmp_path_factory):
    """Meshes go to a per-run cache so a test never reads a stale mesh from another checkout.

    The cache is seeded with the paper chamber at the 'test' preset from tests/data: fTetWild
    is not deterministic, and a fresh mesh each run made the morph tests depend on the mesh
    drawn (one run in a few had a sliver that inverted under a 2 mm press). The seed is found by
    its content hash, so a change to the chamber, electrodes or mesh spec meshes afresh."""
    import shutil

    cache = tmp_path_factory.mktemp("mesh_cache")
    for f in (ROOT / "tests" / "data" / "mesh_cache").glob("chamber-*.npz"):
        shutil.copy(f, cache / f.name)
    mp = pytest.MonkeyPatch()
    mp.setenv("JOINTSIM_CACHE", str(cache))
    yield
    mp.undo()


@pytest.fixture(scope="session")
def paper_scene():
    return load_scene(PAPER_SCENE)


@pytest.fixture(scope="session")
def test_chamber(paper_scene, _mesh_cache):
    """The paper's chamber at the coarse 'test' resolution (~15 k tets, ~25 s to mesh once)."""
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
