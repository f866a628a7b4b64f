import numpy as np
import pytest

from jointsim.scene import load_scene
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PAPER_SCENE = ROOT / "scenes" / "paper_sensor.toml"


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
