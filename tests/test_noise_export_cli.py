import json
import subprocess
import sys

import numpy as np
import pytest

from jointsim.eit.noise import add_noise, gain_drift, noise_std
from jointsim.io.export import write_mat, write_npz, write_vtu
from jointsim.mesh.electrodes import plane_face_patch
from jointsim.mesh.shapes import box_mesh


def test_noise_has_the_requested_snr_and_is_seeded():
    rng = np.random.default_rng(0)
    v = 0.2 * rng.standard_normal(256)
    frames = add_noise(np.broadcast_to(v, (400, 256)), 60.0, rng=7, standing=v)
    std = (frames - v).std()
    # 102 400 samples: the sample std is within ~0.5 % (3 standard errors) of the true one
    assert std == pytest.approx(np.abs(v).mean() / 1000, rel=0.01)
    snr = 20 * np.log10(np.abs(v).mean() / std)
    assert snr == pytest.approx(60.0, abs=0.1)
    np.testing.assert_array_equal(add_noise(v, 60, rng=3), add_noise(v, 60, rng=3))
    assert not np.array_equal(add_noise(v, 60, rng=3), add_noise(v, 60, rng=4))


def test_noise_rejects_an_undefined_reference():
    with pytest.raises(ValueError, match="standing"):
        noise_std(np.zeros(4), 70)


def test_gain_drift_grows_like_a_random_walk():
    g = gain_drift(n_frames=501, n_meas=2000, drift_per_s=1e-3, frame_rate_hz=50.0, rng=1)
    assert np.all(g[0] == 1.0)
    # after 10 s: std(g − 1) = 1e-3 · √10; 2000 channels give the std to ~1.6 % (1σ)
    assert (g[-1] - 1).std() == pytest.approx(1e-3 * np.sqrt(10), rel=0.06)
    with pytest.raises(ValueError, match="drift_per_s"):
        gain_drift(2, 2, -1.0)


def test_vtu_npz_and_mat_round_trip(tmp_path):
    import meshio
    from scipy.io import loadmat

    m = box_mesh((1.0, 1.0, 1.0), (2, 2, 2))
    sigma = np.linspace(1, 2, m.n_tets)
    write_vtu(tmp_path / "a.vtu", m, {"sigma": sigma}, {"u": np.arange(m.n_nodes, dtype=float)})
    r = meshio.read(tmp_path / "a.vtu")
    np.testing.assert_allclose(r.points, m.nodes)
    np.testing.assert_array_equal(r.cells_dict["tetra"], m.tets)
    np.testing.assert_allclose(r.cell_data["sigma"][0], sigma)
    write_npz(tmp_path / "b.npz", v=np.arange(3.0))
    assert np.load(tmp_path / "b.npz")["v"].tolist() == [0, 1, 2]
    e = [plane_face_patch(m, 2, 1.0), plane_face_patch(m, 2, 0.0)]
    stim = np.array([[1e-3]])
    write_mat(tmp_path / "c.mat", m, sigma, np.array([0.5]), stim, np.ones((1, 1, 1)), e, np.array([1e-3, 2e-3]), 1)
    d = loadmat(tmp_path / "c.mat", squeeze_me=True, struct_as_record=False)
    f = d["fwd_model"]
    assert f.elems.min() == 1 and f.elems.shape == (m.n_tets, 4)  # 1-based, as EIDORS
    assert f.electrode.z_contact == pytest.approx(1e-3)
    assert f.stimulation.stim_pattern == pytest.approx(1e-3)
    # nothing half-written or temporary is left behind
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.vtu", "b.npz", "c.mat"]


def test_vtu_rejects_misshapen_fields(tmp_path):
    m = box_mesh((1.0, 1.0, 1.0), (1, 1, 1))
    with pytest.raises(ValueError, match="sigma"):
        write_vtu(tmp_path / "a.vtu", m, {"sigma": np.ones(m.n_tets + 1)})
    assert not list(tmp_path.iterdir())


def _jointsim(*args, env=None):
    return subprocess.run([sys.executable, "-m", "jointsim", *args], capture_output=True, text=True, env=env)


def test_cli_help_lists_the_subcommands():
    r = _jointsim("--help")
    assert r.returncode == 0
    assert "forward" in r.stdout and "mesh" in r.stdout


def test_cli_help_loads_no_solver():
    """Every subcommand's parser is built without loading the solvers and meshers (Warp, PARDISO,
    scipy, trimesh, MuJoCo: seconds of imports), so `jointsim --help` and a mistyped flag answer
    at once; each command loads them when it runs."""
    heavy = ("warp", "pypardiso", "scipy", "trimesh", "mujoco", "meshio", "h5py", "matplotlib")
    code = ("import sys; from jointsim.cli.main import build_parser; build_parser().format_help(); "
            f"print(' '.join(m for m in {heavy!r} if m in sys.modules))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert r.stdout.split() == []


def test_cli_reports_a_solver_failure_in_one_line(monkeypatch, capsys):
    """A NewtonError raised by a command is one line on stderr and exit status 2, like bad input."""
    from jointsim.cli import main as cli
    from jointsim.cli import mesh
    from jointsim.mechanics.newton import NewtonError

    def fail(args):
        raise NewtonError("no convergence in 50 iterations")

    monkeypatch.setattr(mesh, "run", fail)
    assert cli.main(["mesh"]) == 2
    assert capsys.readouterr().err.strip() == "jointsim mesh: error: no convergence in 50 iterations"


def test_cli_rejects_a_bad_scene_with_the_key(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("[electrodes]\nring_radius_mm = 25.0\n")
    r = _jointsim("forward", str(bad), "--out", str(tmp_path / "out"))
    assert r.returncode == 2
    assert "electrodes.ring_radius_mm = 25: must be in (3, 18.5]" in r.stderr
    assert "Traceback" not in r.stderr
    assert not (tmp_path / "out").exists()


def test_cli_refuses_a_device_warp_lacks_before_any_work(tmp_path, capsys):
    """`--device` of the FEM commands: a name Warp does not have here is one line naming the flag
    and the devices there are, before the membrane is built or anything written."""
    from jointsim.cli import main as cli

    for command in ("indent", "palpate"):
        out = tmp_path / command
        assert cli.main([command, "--device", "gpu", "--out", str(out)]) == 2
        err = capsys.readouterr().err
        assert "--device = 'gpu': not a Warp device on this machine (available: 'cpu'" in err
        assert "Traceback" not in err
        assert not out.exists()


def test_cli_forward_writes_its_outputs(test_chamber, tmp_path):
    import os

    out = tmp_path / "fwd"
    r = _jointsim("forward", "--mesh", "test", "--voxels", "500", "--out", str(out), env=dict(os.environ))
    assert r.returncode == 0, r.stderr
    d = np.load(out / "forward.npz")
    assert d["voltages"].shape == (256,)
    assert d["jacobian_voxels"].shape[0] == 256
    meta = json.loads((out / "forward.json").read_text())
    assert meta["scene"]["electrodes"]["count"] == 16
    assert (out / "chamber.vtu").is_file() and (out / "forward_eidors.mat").is_file()
    # the electrodes are tagged on the chamber's nodes: the 16 ring electrodes and the ground
    import meshio

    tags = meshio.read(out / "chamber.vtu").point_data["electrode"]
    assert set(np.unique(tags).tolist()) == set(range(-1, 17))


def test_solver_failures_reach_the_user_as_one_line(monkeypatch, capsys):
    """A morph that inverts or a Newton solve that fails ends the command with exit code 2 and
    the solver's message, not a traceback."""
    from jointsim.cli import main as cli
    from jointsim.mechanics.newton import NewtonError
    from jointsim.mesh.morph import MeshInversionError

    for err in (MeshInversionError("morphed chamber mesh: 1 inverted elements"), NewtonError("no convergence")):
        def boom(args, err=err):
            raise err

        monkeypatch.setattr(cli.SUBCOMMANDS["mesh"], "run", boom)
        assert cli.main(["mesh"]) == 2
        assert str(err) in capsys.readouterr().err


def test_warp_starts_without_the_cuda_driver_notice():
    """The kernels run on the CPU: a machine without an NVIDIA driver (this one, CI) gets no
    'could not load the CUDA driver' line from Warp's start-up on stderr, and Warp still runs."""
    code = "import jointsim._warp as w; print(w.wp.is_cpu_available(), [d.alias for d in w.wp.get_devices()][0])"
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert r.stdout.split() == ["True", "cpu"]
    assert "CUDA driver" not in r.stderr, r.stderr
