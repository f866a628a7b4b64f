"""Synthetic datasets (jointsim.dataset, `jointsim dataset`) at coarse settings: the test chamber
mesh, a membrane of 24 rim vertices and one layer, 1000 voxels, 7 samples in presses of 3
depths (the last press cut to one sample), images on. Each run spawns its workers, so the file
takes 1.5-2 min on 2 cores."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from jointsim.dataset import dataset_schema, draw_group, generate_dataset
from jointsim.io.store import open_records
from jointsim.scene import SceneError, load_scene, scene_from_dict, scene_toml

ROOT = Path(__file__).resolve().parents[1]
N, K, SEED = 7, 3, 3
CONTACT_DRIFT = 1e-3  # m: centre of pressure from the point first touched, at <= 1.5 mm deep

SCENE = """
extends = "paper_sensor"
name = "dataset_test"
[mesh]
preset = "test"
[membrane]
reservoir_pressure_pa = 50.0
rim_vertices = 24
layers = 1
[reconstruction]
cells = 1000
lambda_target_diameter_mm = 10.0
lambda_depth_mm = 1.0
[dataset]
radius_mm = [4.0, 10.0]
r_max_mm = 10.0
depth_mm = [0.3, 1.5]
samples_per_press = 3
electrode_jitter_mm = 0.3
snr_db = [50.0, 70.0]
images = true
"""


@pytest.fixture(scope="module")
def scene_file(tmp_path_factory):
    p = tmp_path_factory.mktemp("dataset_scene") / "scene.toml"
    p.write_text(SCENE)
    return p


@pytest.fixture(scope="module")
def scene(scene_file):
    return load_scene(scene_file)


def _generate(scene, scene_file, out, **kw):
    # the scene's text as `jointsim dataset` records it (extends resolved), so the command line's
    # runs and these resume each other
    return generate_dataset(scene, N, out, seed=SEED, scene_toml=scene_toml(scene_file), **kw)


@pytest.fixture(scope="module")
def reference(scene, scene_file, tmp_path_factory):
    """The uninterrupted one-worker run every other run is compared with."""
    run = _generate(scene, scene_file, tmp_path_factory.mktemp("ds_ref") / "ref", workers=1)
    return run, open_records(run.path)


def test_records_follow_the_contract(reference):
    run, rec = reference
    assert len(rec) == N and run.groups_run == 3 and run.samples_resumed == 0
    assert rec.schema.name == "dataset" and rec.schema.version == 3
    shapes = {"xy": (N, 2), "contact_point": (N, 2), "force": (N, 3), "electrode_jitter": (N, 16, 2), "voltages": (N, 256), "dv": (N, 256),
              "reference_clean": (N, 256), "com": (N, 3), "timings": (N, 5)}
    for name, shape in shapes.items():
        assert rec[name].shape == shape, name
    assert rec["group"].dtype == np.int64 and rec["cluster_cells"].dtype == np.int32
    # the image on the nominal voxel grid; its cluster is what the metrics describe
    assert rec["image"].dtype == np.float32 and rec["image"].shape[0] == N and 500 < rec["image"].shape[1] <= 1500
    assert np.isfinite(rec["image"]).all() and (rec["cluster_cells"] > 0).all()
    assert rec.provenance["params"]["scene"]["dataset"]["samples_per_press"] == K


def test_labels_lie_in_the_requested_ranges(scene, reference):
    _, rec = reference
    d = scene.dataset
    assert ((rec["radius"] >= d.radius[0]) & (rec["radius"] <= d.radius[1])).all()
    assert (np.hypot(*rec["contact_point"].T) <= d.r_max).all()
    assert ((rec["depth"] >= d.depth[0]) & (rec["depth"] <= d.depth[1])).all()
    for name, (lo, hi) in (("membrane_scale", d.membrane_scale), ("conductivity", d.conductivity),
                           ("contact_impedance", d.contact_impedance), ("snr_db", d.snr_db)):
        assert ((rec[name] >= lo) & (rec[name] <= hi)).all(), name
    jitter = np.linalg.norm(rec["electrode_jitter"], axis=2)
    assert (jitter <= d.electrode_jitter).all() and jitter.max() > 0.3 * d.electrode_jitter
    assert np.isinf(rec["target_modulus"]).all()  # rigid_fraction = 1
    assert (rec["force"][:, 2] > 0).all() and (rec["displaced_volume"] > 0).all()
    # the contact lies on the line from the target's centre towards the dome's axis (the dome
    # slopes away from it), on the outer surface (10 mm dome + 2 mm membrane at the apex), about
    # the point first touched: the centre of pressure moves with the patch as it grows
    c, p = rec["contact_centre"], rec["contact_point"]
    r_t, r_c = np.hypot(*rec["xy"].T), np.hypot(*c[:, :2].T)
    assert (r_c < r_t).all() and (r_c > 0.3 * r_t).all()
    assert (np.einsum("ij,ij->i", c[:, :2], rec["xy"]) > 0.99 * r_c * r_t).all()
    assert (np.einsum("ij,ij->i", p, rec["xy"]) > 0.99 * np.hypot(*p.T) * r_t).all()
    assert ((c[:, 2] > 3e-3) & (c[:, 2] < 12e-3)).all()
    assert (np.linalg.norm(c[:, :2] - p, axis=1) < CONTACT_DRIFT).all()


def test_groups_are_consistent(reference):
    """Records i of group i // K; a group's draw (target, centre, randomisation, reference) is
    one; its depths are stratified: one in each third of the range, increasing."""
    _, rec = reference
    np.testing.assert_array_equal(rec["group"], np.arange(N) // K)
    per_group = ("radius", "xy", "contact_point", "target_modulus", "membrane_scale", "conductivity", "contact_impedance",
                 "electrode_jitter", "snr_db", "reference_clean")
    for g in np.unique(rec["group"]):
        sel = rec["group"] == g
        for name in per_group:
            assert (rec[name][sel] == rec[name][sel][0]).all(), (g, name)
    assert not np.array_equal(rec["radius"][0], rec["radius"][K])
    np.testing.assert_array_equal(rec["dv_clean"], rec["voltages_clean"] - rec["reference_clean"])
    lo, hi = 0.3e-3, 1.5e-3
    slot = np.floor((rec["depth"] - lo) / (hi - lo) * K)
    np.testing.assert_array_equal(slot, np.arange(N) % K)


def test_dv_and_force_grow_with_depth_within_a_group(reference):
    _, rec = reference
    rms = np.sqrt(np.mean(rec["dv_clean"] ** 2, axis=1))
    for g in range(N // K):
        sel = rec["group"] == g
        assert (np.diff(rec["depth"][sel]) > 0).all()
        assert (np.diff(rms[sel]) > 0).all(), rms[sel]
        assert (np.diff(rec["force"][sel, 2]) > 0).all()
        assert (np.diff(rec["displaced_volume"][sel]) > 0).all()
    # the noisy δV is the clean one plus the frame's and the averaged reference's noise
    noise = rec["dv"] - rec["dv_clean"]
    std = np.mean(np.abs(rec["reference_clean"]), axis=1) / 10 ** (rec["snr_db"] / 20)
    ratio = noise.std(axis=1) / (std * np.sqrt(1 + 1 / 50))
    assert (0.7 < ratio).all() and (ratio < 1.3).all(), ratio


def test_the_image_locates_the_press(reference):
    """The nominal instrument's image puts the CoM of a press on the side of its contact."""
    _, rec = reference
    deepest = np.arange(N) % K == K - 1
    xy, com = rec["xy"][deepest], rec["com"][deepest, :2]
    assert (np.einsum("ij,ij->i", xy, com) > 0).all(), (xy, com)


def test_worker_count_and_an_empty_mesh_cache_do_not_change_the_data(scene, scene_file, reference, tmp_path, monkeypatch):
    """Two workers, each meshing the chamber anew from an empty cache, store the one-worker data."""
    monkeypatch.setenv("JOINTSIM_CACHE", str(tmp_path / "empty_cache"))
    run = _generate(scene, scene_file, tmp_path / "two", workers=2)
    assert list((tmp_path / "empty_cache").glob("chamber-*.npz"))
    assert run.data_sha256 == reference[0].data_sha256


def test_dask_cluster_writes_the_same_data(scene, scene_file, reference, tmp_path):
    """Two Dask worker processes write into one store: nothing lost, same data as one worker."""
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        run = _generate(scene, scene_file, tmp_path / "dask", scheduler=cluster.scheduler_address)
    rec = open_records(run.path)
    np.testing.assert_array_equal(rec["group"], np.arange(N) // K)
    assert run.data_sha256 == reference[0].data_sha256


def _live_processes() -> list[tuple[int, int, int]]:
    """(pid, parent pid, process group) of every live (not zombie) process, read from /proc."""
    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if fields[0] != "Z":
            out.append((int(stat.parent.name), int(fields[1]), int(fields[2])))
    return out


def _group_alive(pgid: int) -> bool:
    """Whether a live process of process group ``pgid`` remains."""
    return any(g == pgid for _, _, g in _live_processes())


def test_resume_after_kill_gives_the_uninterrupted_data(scene, scene_file, reference, tmp_path):
    """`jointsim dataset`'s driver killed with SIGKILL once its first press is stored: its worker
    and the resource tracker die with it (no orphan writes on); run again, no sample is lost or
    corrupt, and the data are the uninterrupted run's."""
    out = tmp_path / "killed"
    cmd = [sys.executable, "-m", "jointsim", "dataset", str(scene_file), "--n", str(N), "--seed", str(SEED),
           "--out", str(out), "--workers", "1", "--no-progress"]
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True)
    records = out.with_suffix(".partial") / "records"
    t0 = time.monotonic()
    try:
        while not list(records.rglob("r*.npz")):
            assert proc.poll() is None, proc.stderr.read().decode()[-2000:]
            assert time.monotonic() - t0 < 120, "no record stored within 2 min"
            time.sleep(0.02)
        os.kill(proc.pid, signal.SIGKILL)  # the driver alone: its worker must die with it (no orphan writing on)
        proc.wait()
        t1 = time.monotonic()
        while _group_alive(proc.pid):
            assert time.monotonic() - t1 < 10, "a worker outlived its killed driver by 10 s"
            time.sleep(0.05)
    finally:
        if _group_alive(proc.pid):
            os.killpg(proc.pid, signal.SIGKILL)  # the process group this test started
        proc.wait()
    assert not out.with_suffix(".h5").exists()
    stored = len(list(records.rglob("r*.npz")))
    assert 1 <= stored < 3
    run = _generate(scene, scene_file, out, workers=2)
    assert run.samples_resumed == stored * K and run.groups_run == 3 - stored
    assert run.data_sha256 == reference[0].data_sha256
    assert not out.with_suffix(".partial").exists()


def _children(pid: int) -> list[int]:
    """The live processes whose parent is ``pid``."""
    return [p for p, parent, _ in _live_processes() if parent == pid]


def _first_record(proc: subprocess.Popen, records: Path) -> None:
    t0 = time.monotonic()
    while not list(records.rglob("r*.npz")):
        assert proc.poll() is None, proc.stderr.read()[-2000:]
        assert time.monotonic() - t0 < 180, "no record stored within 3 min"
        time.sleep(0.02)


def test_a_killed_worker_stops_the_run_in_one_line_and_the_rerun_has_the_data(scene, scene_file, reference, tmp_path):
    """One of `jointsim dataset`'s two local workers killed with SIGKILL once a press is stored:
    the run stops with one line (exit 2) saying to run it again, and the rerun ends with the
    uninterrupted run's data."""
    out = tmp_path / "worker_killed"
    cmd = [sys.executable, "-m", "jointsim", "dataset", str(scene_file), "--n", str(N), "--seed", str(SEED),
           "--out", str(out), "--workers", "2", "--no-progress"]
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        _first_record(proc, out.with_suffix(".partial") / "records")
        workers = [p for p in _children(proc.pid) if "resource_tracker" not in Path(f"/proc/{p}/cmdline").read_bytes().decode(errors="replace")]
        assert workers, "no worker process found"
        os.kill(workers[0], signal.SIGKILL)
        _, err = proc.communicate(timeout=120)
    finally:
        if _group_alive(proc.pid):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    if proc.returncode == 0:  # the worker had finished its last press before it was killed: nothing to resume
        assert open_records(out).data_sha256 == reference[0].data_sha256
        return
    lines = [x for x in err.strip().splitlines() if ": warning: " not in x]
    assert proc.returncode == 2 and len(lines) == 1 and "run the same command again to resume" in lines[0], err
    run = _generate(scene, scene_file, out, workers=2)
    assert run.groups_run >= 1 and run.data_sha256 == reference[0].data_sha256


@pytest.mark.parametrize("victim, seed", [("driver", 11), ("worker", 12)])
def test_a_kill_at_a_random_moment_loses_nothing(scene, scene_file, reference, tmp_path, victim, seed):
    """`jointsim dataset` (two local workers) with its driver or one of its workers killed with
    SIGKILL at a moment drawn uniformly over the uninterrupted run's wall time (from its start,
    the interpreter's start-up included): run again until it finishes, the store is the
    uninterrupted run's, whatever had been stored."""
    out = tmp_path / f"kill_{victim}"
    cmd = [sys.executable, "-m", "jointsim", "dataset", str(scene_file), "--n", str(N), "--seed", str(SEED),
           "--out", str(out), "--workers", "2", "--no-progress"]
    at = np.random.default_rng(seed).uniform(0.05, 0.95) * (reference[0].wall_s + 3.0)  # + the interpreter's start-up
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        time.sleep(at)
        if proc.poll() is None:
            kids = [p for p in _children(proc.pid)
                    if "resource_tracker" not in Path(f"/proc/{p}/cmdline").read_bytes().decode(errors="replace")]
            target = proc.pid if victim == "driver" or not kids else kids[0]
            try:
                os.kill(target, signal.SIGKILL)
            except ProcessLookupError:
                pass
        proc.communicate(timeout=300)
    finally:
        if _group_alive(proc.pid):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    run = _generate(scene, scene_file, out, workers=2)
    assert run.data_sha256 == reference[0].data_sha256
    assert not out.with_suffix(".partial").exists()


def test_a_dask_worker_killed_mid_run_loses_nothing(scene, scene_file, reference, tmp_path):
    """A Dask cluster as a user starts one (a scheduler and two worker processes, each with its
    nanny), one worker's process group killed with SIGKILL once a press is stored: the scheduler
    hands its task to the other, and the run ends with the uninterrupted run's data. The workers'
    own environment names another sparse solver: they compute with the driver's (else the data
    would differ in the last bits where PARDISO is installed)."""
    pytest.importorskip("distributed")
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    env.pop("JOINTSIM_SOLVER", None)
    procs = []

    def start(*args):
        worker_env = {**env, "JOINTSIM_SOLVER": "superlu"} if args[0] == "worker" else env
        procs.append(subprocess.Popen([sys.executable, "-m", "dask", *args], env=worker_env, cwd=tmp_path, stdout=subprocess.DEVNULL,
                                      stderr=subprocess.DEVNULL, start_new_session=True))
        return procs[-1]

    sched = tmp_path / "scheduler.json"
    try:
        start("scheduler", "--scheduler-file", str(sched), "--no-dashboard", "--port", "0")
        t0 = time.monotonic()
        while not sched.exists():
            assert time.monotonic() - t0 < 60, "the scheduler did not start in 60 s"
            time.sleep(0.1)
        workers = [start("worker", "--scheduler-file", str(sched), "--nthreads", "1", "--no-dashboard", "--name", f"w{i}")
                   for i in range(2)]
        import json

        from distributed import Client

        with Client(scheduler_file=str(sched), timeout=60) as c:
            c.wait_for_workers(2, timeout=120)
        address = json.loads(sched.read_text())["address"]
        out = tmp_path / "dask_killed"
        proc = subprocess.Popen([sys.executable, "-m", "jointsim", "dataset", str(scene_file), "--n", str(N), "--seed", str(SEED),
                                 "--out", str(out), "--scheduler", address, "--no-progress"], env=env, cwd=ROOT,
                                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        procs.append(proc)
        _first_record(proc, out.with_suffix(".partial") / "records")
        os.killpg(workers[1].pid, signal.SIGKILL)
        _, err = proc.communicate(timeout=300)
        assert proc.returncode == 0, err[-2000:]
    finally:
        for p in procs:
            if p.poll() is None:
                try:
                    os.killpg(p.pid, signal.SIGKILL)
                except (ProcessLookupError, PermissionError):
                    p.kill()
            p.wait()
    assert open_records(out).data_sha256 == reference[0].data_sha256


class _Stop(Exception):
    pass


@pytest.mark.parametrize("stored", [1, 2])
def test_a_run_stopped_after_any_press_resumes_to_the_uninterrupted_data(scene, scene_file, reference, tmp_path, stored):
    """Stopped after each of its presses in turn (the driver's progress callback raising, as a
    Ctrl-C there would) and run again, the store ends with the uninterrupted run's data: resume
    is per press (a press's samples are stored together), from any of them."""
    out = tmp_path / f"stopped{stored}"
    seen = []

    def stop(n):
        seen.append(n)
        if len(seen) == stored:
            raise _Stop()

    with pytest.raises(_Stop):
        _generate(scene, scene_file, out, workers=1, progress=stop)
    run = _generate(scene, scene_file, out, workers=1)
    assert run.samples_resumed >= stored * K and run.groups_run <= 3 - stored
    assert run.data_sha256 == reference[0].data_sha256


def test_a_finished_file_is_not_recomputed(scene, scene_file, reference):
    run = _generate(scene, scene_file, reference[0].path, workers=1)
    assert run.groups_run == 0 and run.data_sha256 == reference[0].data_sha256
    with pytest.raises(ValueError, match="other settings"):
        generate_dataset(scene, N + 1, reference[0].path, seed=SEED)


def _flip(path: Path, field: str, chunk: int) -> None:
    """Four bytes of chunk ``chunk`` of records/``field`` inverted in place."""
    import h5py

    with h5py.File(path, "r") as h5:
        offset = h5[f"records/{field}"].id.get_chunk_info(chunk).byte_offset
    with open(path, "r+b") as f:
        f.seek(offset + 64)
        b = f.read(4)
        f.seek(offset + 64)
        f.write(bytes(x ^ 0xFF for x in b))


def test_a_damaged_finished_file_is_found_by_a_rerun_and_mended(scene, scene_file, reference, tmp_path):
    """Four bytes flipped in a chunk of a finished store: the rerun that would say "nothing to
    do" reads the file back against its data_sha256, sets it aside (kept, with a warning naming
    it), keeps the presses whose chunks still decode (each gzip chunk carries a checksum) and
    computes the others again: the store ends with the uninterrupted data. Here the file is
    rewritten one record per chunk, so that the damage is one sample's and one press is
    recomputed; in the dataset's own 1 MB chunks it is every press sharing the chunk."""
    import h5py

    path = tmp_path / "damaged.h5"
    with h5py.File(reference[0].path, "r") as src, h5py.File(path, "w") as dst:
        dst.attrs.update(src.attrs)
        for name in ("provenance", "run"):
            src.copy(name, dst)
        g = dst.create_group("records")
        for name, ds in src["records"].items():
            g.create_dataset(name, data=ds[()], chunks=(1, *ds.shape[1:]), compression="gzip").attrs.update(ds.attrs)
    assert open_records(path).data_sha256 == reference[0].data_sha256
    _flip(path, "voltages", 4)  # sample 4: the second press's
    with pytest.warns(UserWarning, match=r"damaged.*set aside as damaged.h5.damaged; 2 of its presses read back whole"):
        run = _generate(scene, scene_file, path, workers=1)
    assert run.groups_run == 1 and run.data_sha256 == reference[0].data_sha256
    assert path.with_name("damaged.h5.damaged").exists()

    _flip(path, "dv", 0)  # the dataset's own chunks: every press shares it
    with pytest.warns(UserWarning, match="0 of its presses read back whole"):
        run = _generate(scene, scene_file, path, workers=1)
    assert run.groups_run == 3 and run.data_sha256 == reference[0].data_sha256
    assert path.with_name("damaged.h5.damaged.1").exists()


def test_kept_presses_that_do_not_give_the_recorded_data_are_all_computed_again(scene, scene_file, reference, tmp_path, monkeypatch):
    """Should the presses kept from a damaged file not make the data_sha256 it recorded (here a
    value read back as if whole but wrong), the mended store is set aside too and every press
    computed again."""
    import shutil

    import jointsim.dataset.runner as runner

    path = tmp_path / "wrong.h5"
    shutil.copy(reference[0].path, path)
    _flip(path, "dv", 0)
    wrong = {k: v.copy() for k, v in open_records(reference[0].path).fields.items()}
    wrong["voltages"][0] += 1e-9
    monkeypatch.setattr(runner, "readable_records", lambda p: (np.ones(N, bool), wrong, reference[0].data_sha256))
    with pytest.warns(UserWarning, match="did not give its recorded data_sha256"):
        run = _generate(scene, scene_file, path, workers=1)
    assert run.groups_run == 3 and run.data_sha256 == reference[0].data_sha256
    assert path.with_name("wrong.h5.damaged").exists() and path.with_name("wrong.h5.damaged.1").exists()


def test_a_scheduler_that_does_not_answer_is_one_error(scene, scene_file, tmp_path, monkeypatch):
    pytest.importorskip("distributed")
    import jointsim.dataset.runner as runner

    monkeypatch.setattr(runner, "SCHEDULER_TIMEOUT_S", 2.0)
    with pytest.raises(ValueError, match=r"scheduler 'tcp://127.0.0.1:9': cannot connect within 2 s"):
        _generate(scene, scene_file, tmp_path / "nowhere", scheduler="tcp://127.0.0.1:9")


def test_force_control_samples_at_the_drawn_forces(scene, scene_file, tmp_path):
    """control = "force": one press, its samples at forces one in each third of force_n, reached
    to the press's tolerance (1e-3), at increasing depths."""
    from dataclasses import replace

    lo, hi = 0.004, 0.02
    fscene = replace(scene, dataset=replace(scene.dataset, control="force", force=(lo, hi)))
    run = generate_dataset(fscene, K, tmp_path / "force", seed=SEED, scene_toml=scene_toml(scene_file), workers=1)
    rec = open_records(run.path)
    fz = rec["force"][:, 2]
    np.testing.assert_array_equal(np.floor((fz - lo) / (hi - lo) * K), np.arange(K))
    want = draw_group(fscene.dataset, SEED, 0, run.rejected_draws).levels
    np.testing.assert_allclose(fz, want, rtol=1.5e-3)
    assert (rec["depth"] > 0).all() and (np.diff(rec["depth"]) > 0).all()
    assert rec.provenance["params"]["scene"]["dataset"]["control"] == "force"


def test_contact_points_cover_the_disc_whatever_is_redrawn():
    """Contact points, not target centres, are drawn uniformly over r <= r_max: over 4000 groups
    the fraction past r = 0.9 r_max is 1 - 0.81 = 0.19 (±0.019 is three standard errors), the
    mean angle's vector is ~0; a redrawn attempt keeps its group's point."""
    from jointsim.scene import DatasetSpec

    spec = DatasetSpec()
    p = np.array([draw_group(spec, 0, g).contact_point for g in range(4000)])
    r = np.hypot(*p.T)
    assert r.max() <= spec.r_max
    assert abs(np.mean(r > 0.9 * spec.r_max) - 0.19) < 0.019
    assert np.linalg.norm(np.mean(p / r[:, None], axis=0)) < 3 / np.sqrt(4000)
    assert draw_group(spec, 0, 7).xy is None
    np.testing.assert_array_equal(draw_group(spec, 0, 7, attempt=3).contact_point, draw_group(spec, 0, 7).contact_point)


def test_draws_are_seeded_per_group():
    from jointsim.scene import DatasetSpec

    spec = DatasetSpec()
    a, b = draw_group(spec, 0, 5), draw_group(spec, 0, 5)
    assert a.radius == b.radius and np.array_equal(a.jitter, b.jitter) and np.array_equal(a.levels, b.levels)
    assert draw_group(spec, 1, 5).radius != a.radius and draw_group(spec, 0, 6).radius != a.radius
    assert draw_group(spec, 0, 5, attempt=1).radius != a.radius


def test_only_draws_the_simulator_cannot_take_are_redrawn():
    """A pose the dome cannot take (UnreachablePose), a Newton failure or an inverted mesh
    rejects the draw and the group draws again; any other error is a fault and stops the run."""
    from types import SimpleNamespace

    from jointsim.dataset.generate import DatasetSetup
    from jointsim.mechanics.dome import UnreachablePose
    from jointsim.mechanics.newton import NewtonError

    spec = load_scene(ROOT / "scenes" / "paper_sensor.toml").dataset
    failures = [UnreachablePose("too deep"), NewtonError("no convergence")]

    def press(draw, k):
        if failures:
            raise failures.pop(0)
        return [{"radius": draw.radius}] * k

    fake = SimpleNamespace(spec=spec, seed=0, n_electrodes=16, press=press, presses=None)
    records, errors = DatasetSetup.group(fake, 3, n_samples=2)
    assert len(records) == 2 and len(errors) == 2
    assert records[0]["radius"] == draw_group(spec, 0, 3, 2, 16).radius  # the third attempt's draw
    assert "UnreachablePose" in errors[0] and "NewtonError" in errors[1]

    def faulty(draw, k):
        raise ValueError("a bug, not a draw")

    with pytest.raises(ValueError, match=r"^a bug, not a draw$"):  # not redrawn MAX_ATTEMPTS times
        DatasetSetup.group(SimpleNamespace(spec=spec, seed=0, n_electrodes=16, press=faulty, presses=None), 3)


def test_schema_has_the_image_only_when_asked():
    assert "image" not in dataset_schema(16, 256, None).names
    s = dataset_schema(16, 256, 1234)
    assert s["image"].shape == (1234,) and s["image"].dtype == "float32" and s["timings"].volatile


@pytest.mark.parametrize(
    "section, match",
    [
        ({"radius_mm": [15.0, 4.0]}, r"dataset\.radius_mm = \[15, 4\]: min must not exceed max"),
        ({"diameter_mm": [-8.0, 30.0]}, r"dataset\.diameter_mm\[0\] = -8: must be in \(0, 200\]"),
        ({"r_max_mm": 25.0}, r"dataset\.r_max_mm = 25: must be in \[0, 17\]"),
        ({"depth_mm": [0.5, 12.0]}, r"dataset\.depth_mm\[1\] = 12: must be in \(0, 9\]"),
        ({"snr_db": [40.0, 300.0]}, r"dataset\.snr_db\[1\] = 300: must be in \[0, 200\]"),
        ({"membrane_scale": [2.0, 0.5]}, r"dataset\.membrane_scale = \[2, 0.5\]: min must not exceed max"),
        ({"conductivity_s_per_m": [0.0, 0.4]}, r"dataset\.conductivity_s_per_m\[0\] = 0: must be in \(0, 100\]"),
        ({"contact_impedance_ohm_m2": "high"}, r"dataset\.contact_impedance_ohm_m2 = 'high': must be \[min, max\]"),
        ({"electrode_jitter_mm": 2.0}, r"dataset\.electrode_jitter_mm = 2: must be in \[0, 0.8\]"),
        ({"samples_per_press": 0}, r"dataset\.samples_per_press = 0: must be an integer in \[1, 1000\]"),
        ({"step_mm": 0.0}, r"dataset\.step_mm = 0: must be in \(0, 5\]"),
        ({"rigid_fraction": 1.5}, r"dataset\.rigid_fraction = 1.5: must be in \[0, 1\]"),
        ({"images": "yes"}, r"dataset\.images = 'yes': must be true or false"),
        ({"control": "torque"}, r"dataset\.control = 'torque': allowed values are 'depth', 'force'"),
        ({"force_n": [0.05, 0.01]}, r"dataset\.force_n = \[0.05, 0.01\]: min must not exceed max"),
        ({"radius_mm": [4, 8], "diameter_mm": [8, 16]}, r"give radius_mm or diameter_mm"),
        ({"sample": 3}, r"unknown key\(s\) in \[dataset\]: sample"),
    ],
)
def test_bad_sampling_ranges_are_rejected(section, match):
    with pytest.raises(SceneError, match=match):
        scene_from_dict({"dataset": section})


def test_the_command_line_rejects_bad_input_with_exit_2(tmp_path, capsys):
    from jointsim.cli.main import main

    bad = tmp_path / "bad.toml"
    bad.write_text('[dataset]\nradius_mm = [15.0, 4.0]\n')
    assert main(["dataset", str(bad), "--n", "3", "--out", str(tmp_path / "x")]) == 2
    assert "dataset.radius_mm" in capsys.readouterr().err
    assert main(["dataset", str(bad.with_name("none.toml")), "--n", "0"]) == 2
    # a seed the store cannot record (a signed 64-bit integer), refused before any work
    assert main(["dataset", "--n", "3", "--seed", str(2**64), "--out", str(tmp_path / "y")]) == 2
    assert "--seed = 18446744073709551616: must be in [0, 2^63 - 1]" in capsys.readouterr().err
    assert not (tmp_path / "y.h5").exists() and not (tmp_path / "y.partial").exists()


def test_an_output_holding_something_else_is_refused_naming_it_and_left_alone(scene, scene_file, reference, tmp_path, capsys):
    """--out on a text file (the store would go beside it, to NAME.h5), a truncated store, a
    store of another kind: each refused in one line naming the file, which is left as it was."""
    import shutil

    from jointsim.cli.main import main
    from jointsim.io.store import Field, Schema, open_store

    text = tmp_path / "notes.txt"
    text.write_text("my notes\n")
    assert main(["dataset", str(scene_file), "--n", str(N), "--out", str(text)]) == 2
    assert f"--out {text}: an existing file that is not an HDF5 store" in capsys.readouterr().err
    assert text.read_text() == "my notes\n" and not text.with_name("notes.txt.h5").exists()

    cut = tmp_path / "cut.h5"
    shutil.copy(reference[0].path, cut)
    with open(cut, "r+b") as f:
        f.truncate(cut.stat().st_size // 2)
    size = cut.stat().st_size
    with pytest.raises(ValueError, match=f"{cut}: exists and is not a readable jointsim store"):
        _generate(scene, scene_file, cut, workers=1)
    assert cut.stat().st_size == size

    other = open_store(tmp_path / "pal", Schema((Field("force", ()),), name="palpation", version=1), scene_toml="", seed=0,
                       n_records=1)
    other.put(0, {"force": 1.0})
    path = other.finalize()
    with pytest.raises(ValueError, match="holds a 'palpation' store, not a dataset"):
        _generate(scene, scene_file, path, workers=1)
    assert open_records(path)["force"][0] == 1.0


def test_a_worker_that_dies_ends_the_run_with_one_clear_error():
    """A local worker killed mid-task (here it exits at once) ends the run with a
    ChildProcessError that says nothing stored is lost and to rerun, not a BrokenProcessPool
    traceback (the command line reports an OSError in one line). Run in its own interpreter, so
    that the pool's dying worker cannot touch the test process."""
    code = "import os\nfrom jointsim._cores import run_local\nrun_local([(3,)], 1, lambda r: None, task=os._exit)\n"
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert r.returncode == 1, r.stderr[-2000:]
    assert "ChildProcessError: a worker process died" in r.stderr and "run the same command again to resume" in r.stderr
