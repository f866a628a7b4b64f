"""The record store: schema checks, round trip through HDF5, resume after SIGKILL, concurrent
writers, refusal of incomplete or foreign runs."""

import json
import os
import pickle
import signal
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

from jointsim.io.store import Field, Schema, attach, open_records, open_store

ROOT = Path(__file__).resolve().parents[1]
SCENE = "# test scene\n[chamber]\nheight_mm = 10.0\n"

# A palpation-like frame: the writer script below declares the same fields.
SCHEMA = Schema(
    (
        Field("voltages", (256,), unit="V"),
        Field("clean", (256,), unit="V"),
        Field("pose", (3,), unit="m"),
        Field("force", (3,), unit="N"),
        Field("volume", unit="m^3"),
        Field("image", (7000,), "float32"),
        Field("frame", (), "int64"),
        Field("timings", (2,), unit="s", volatile=True),
    ),
    name="palpate",
    version=1,
)

# Writes records with a time-series state carried by checkpoints ("series": record i depends
# on record i-1, resumed from the checkpoint of the last stored frame) or independent ones
# ("independent": worker w of k writes the indices i ≡ w mod k that are missing).
WRITER = r'''
import sys, time
from pathlib import Path
import numpy as np
from jointsim.io.store import Field, Schema, open_store

SCENE = "# test scene\n[chamber]\nheight_mm = 10.0\n"
SCHEMA = Schema((
    Field("voltages", (256,), unit="V"), Field("clean", (256,), unit="V"), Field("pose", (3,), unit="m"),
    Field("force", (3,), unit="N"), Field("volume", unit="m^3"), Field("image", (7000,), "float32"),
    Field("frame", (), "int64"), Field("timings", (2,), unit="s", volatile=True),
), name="palpate", version=1)

path, mode = sys.argv[1], sys.argv[2]
n, batch, worker, n_workers = (int(a) for a in sys.argv[3:7])
delay = float(sys.argv[7])
store = open_store(path, SCHEMA, scene_toml=SCENE, seed=7, n_records=n, params={"mode": mode}, batch=batch)
if n_workers > 1:  # barrier: every worker has opened the store before any writes
    Path(f"{path}.ready{worker}").touch()
    while not all(Path(f"{path}.ready{w}").exists() for w in range(n_workers)):
        time.sleep(0.005)
missing = store.missing()
if mode == "series":
    k = int(missing[0]) if missing.size else n
    state = store.checkpoint(k - 1)["state"] if k else np.zeros(4)
    todo = range(k, n)
else:
    todo = [int(i) for i in missing if i % n_workers == worker]
with store:
    for i in todo:
        t0 = time.perf_counter()
        rng = np.random.default_rng([7, i])
        if mode == "series":
            state = 0.9 * state + rng.standard_normal(4)
            x = state
        else:
            x = rng.standard_normal(4)
        clean = np.cos(x.sum() + 0.1 * np.arange(256))
        rec = {
            "voltages": clean + 1e-3 * rng.standard_normal(256), "clean": clean, "pose": x[:3],
            "force": x[1:] ** 2, "volume": x[3], "image": rng.standard_normal(7000).astype(np.float32),
            "frame": i, "timings": [time.perf_counter() - t0, time.time() % 1],
        }
        store.put(i, rec, checkpoint={"state": state} if mode == "series" else None)
        print(i, flush=True)
        time.sleep(delay)
'''


def _record(i: int, x: float = 1.0) -> dict:
    return {
        "voltages": np.full(256, x * i), "clean": np.full(256, -x * i), "pose": [i, 2 * i, 3 * i],
        "force": np.ones(3) * x, "volume": 0.5 * i, "image": np.arange(7000, dtype=np.float32) * i,
        "frame": i, "timings": [0.1 * x, 0.2],
    }


def _open(path, schema=SCHEMA, scene=SCENE, seed=7, n=6, **kw):
    return open_store(path, schema, scene_toml=scene, seed=seed, n_records=n, **kw)


def _writer(tmp_path: Path, store: Path, mode: str, n: int, batch: int = 1, worker: int = 0, n_workers: int = 1,
            delay: float = 0.0) -> subprocess.Popen:
    script = tmp_path / "writer.py"
    script.write_text(WRITER)
    env = dict(os.environ, PYTHONPATH=f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}")
    args = [sys.executable, str(script), str(store), mode, str(n), str(batch), str(worker), str(n_workers), str(delay)]
    return subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)


def _finish(p: subprocess.Popen) -> None:
    out, err = p.communicate(timeout=60)
    assert p.returncode == 0, err


def _kill_after(p: subprocess.Popen, lines: int) -> None:
    """SIGKILL the writer once it has reported ``lines`` more records."""
    for _ in range(lines):
        assert p.stdout.readline(), p.stderr.read()
    os.kill(p.pid, signal.SIGKILL)
    p.communicate(timeout=60)
    assert p.returncode == -signal.SIGKILL


# --------------------------------------------------------------------------------------------


def test_round_trip_orders_by_index_and_keeps_provenance(tmp_path):
    store = _open(tmp_path / "run", command=["jointsim", "palpate", "scene.toml"])
    for i in [4, 1, 5, 0, 3, 2]:
        store.put(i, _record(i), checkpoint={"state": np.arange(3.0) + i} if i % 2 else None)
    np.testing.assert_array_equal(store.done(), np.arange(6))
    np.testing.assert_array_equal(store.checkpoint(3)["state"], [3.0, 4.0, 5.0])
    assert store.checkpoint(2) is None
    np.testing.assert_array_equal(store.get(5)["pose"], [5, 10, 15])
    path = store.finalize()

    assert path == tmp_path / "run.h5" and not (tmp_path / "run.partial").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.h5"]  # no temporary left behind
    r = open_records(path)
    assert len(r) == 6 and r["image"].dtype == np.float32 and r["frame"].dtype == np.int64
    np.testing.assert_array_equal(r["frame"], np.arange(6))
    np.testing.assert_array_equal(r["pose"], np.arange(6)[:, None] * [1, 2, 3])
    np.testing.assert_array_equal(r["voltages"][:, 17], np.arange(6.0))
    assert r.provenance["scene_toml"] == SCENE and r.provenance["seed"] == 7
    assert r.provenance["schema"]["name"] == "palpate" and r.provenance["schema"]["version"] == 1
    assert r.provenance["versions"]["numpy"] == np.__version__ and "scipy" in r.provenance["versions"]
    assert r.run["sessions"][0]["command"] == ["jointsim", "palpate", "scene.toml"]
    with h5py.File(path) as h5:
        assert h5["records/voltages"].attrs["unit"] == "V" and h5.attrs["schema_version"] == 1

    # the same data written in another order, with other timings: the same digest
    other = _open(tmp_path / "rev")
    for i in range(5, -1, -1):
        other.put(i, dict(_record(i), timings=[9.0, 9.0]))
    r2 = open_records(other.finalize())
    assert r2.data_sha256 == r.data_sha256 and r2.provenance == r.provenance
    assert not np.array_equal(r2["timings"], r["timings"])
    # and a change in one value of a data field changes it
    third = _open(tmp_path / "changed")
    for i in range(6):
        third.put(i, dict(_record(i), volume=0.5 * i + (i == 3) * 1e-12))
    assert open_records(third.finalize()).data_sha256 != r.data_sha256


@pytest.mark.parametrize(
    "change, message",
    [
        (lambda r: r.pop("force"), r"missing field\(s\) \['force'\]"),
        (lambda r: r.update(stiffness=1.0), r"field\(s\) \['stiffness'\] not in schema"),
        (lambda r: r.update(voltages=np.zeros(255)), r"field 'voltages' has shape \(255,\), the schema declares \(256,\)"),
        (lambda r: r.update(volume=[1.0]), r"field 'volume' has shape \(1,\)"),
        (lambda r: r.update(frame=2.5), r"field 'frame' has dtype float64, which does not convert to the declared int64"),
        (lambda r: r.update(pose=np.ones(3, complex)), r"field 'pose' has dtype complex128"),
    ],
)
def test_schema_violations_are_rejected_naming_the_field(tmp_path, change, message):
    store = _open(tmp_path / "run")
    rec = _record(2)
    change(rec)
    with pytest.raises(ValueError, match="record 2: " + message):
        store.put(2, rec)
    assert store.done().size == 0


def test_bad_schemas_indices_and_checkpoints_are_rejected(tmp_path):
    with pytest.raises(ValueError, match="field name '2x'"):
        Field("2x")
    with pytest.raises(ValueError, match="field 'a': shape"):
        Field("a", (0,))
    with pytest.raises(ValueError, match="field 'a': dtype <U3 is not numeric"):
        Field("a", dtype="U3")
    with pytest.raises(ValueError, match=r"duplicate field name\(s\) \['a'\]"):
        Schema((Field("a"), Field("a")))
    store = _open(tmp_path / "run")
    with pytest.raises(ValueError, match="record index 6 out of range: 0 ≤ index < 6"):
        store.put(6, _record(6))
    with pytest.raises(ValueError, match="checkpoint 'state' has dtype object"):
        store.put(1, _record(1), checkpoint={"state": np.array([None])})
    store.put(1, _record(1))
    with pytest.raises(ValueError, match="record 1 was already written"):
        store.put(1, _record(1))
    with pytest.raises(KeyError, match="record 2 is not in the store"):
        store.checkpoint(2)


def test_finalize_refuses_missing_records_and_says_how_many(tmp_path):
    store = _open(tmp_path / "run", n=10)
    for i in [0, 1, 2, 4, 5, 7, 9]:
        store.put(i, _record(i))
    np.testing.assert_array_equal(store.missing(), [3, 6, 8])
    with pytest.raises(ValueError, match=r"3 of 10 records missing \(indices 3, 6, 8\)"):
        store.finalize()
    assert not (tmp_path / "run.h5").exists() and store.done().size == 7
    for i in [3, 6, 8]:
        store.put(i, _record(i))
    assert open_records(store.finalize())["frame"].tolist() == list(range(10))


def test_a_full_disk_at_finalise_is_an_error_that_keeps_the_records(tmp_path, monkeypatch):
    """Too little free space for the final file: refused before HDF5 writes a byte (a disk that
    filled mid-write ended in a segfault); a write that fails anyway (ENOSPC) is the same clear
    error, no temporary file is left, and the records finalise once there is room."""
    import shutil
    from collections import namedtuple

    import jointsim.io.store as store_module

    store = _open(tmp_path / "run", n=3)
    for i in range(3):
        store.put(i, _record(i))
    real = shutil.disk_usage
    Usage = namedtuple("Usage", "total used free")
    monkeypatch.setattr(store_module.shutil, "disk_usage", lambda p: Usage(10**9, 10**9 - 4096, 4096))
    with pytest.raises(ValueError, match=r"cannot finalise .*run.h5: 0.0 MB free on its disk, \d+\.\d MB needed; "
                                         r"the records are kept in .*run.partial"):
        store.finalize()
    monkeypatch.setattr(store_module.shutil, "disk_usage", real)

    def enospc(*a, **k):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(store_module, "_copy_rows", enospc)
    with pytest.raises(ValueError, match=r"cannot finalise .*: No space left on device; the records are kept"):
        store.finalize()
    assert not list(tmp_path.glob(".run*.h5")) and not (tmp_path / "run.h5").exists()
    monkeypatch.undo()
    assert open_records(store.finalize())["frame"].tolist() == [0, 1, 2]


def test_reopening_resumes_the_same_run_and_refuses_another(tmp_path):
    path = tmp_path / "run"
    _open(path).put(0, _record(0))
    # the same run, scene comments edited: resumes and sees the stored record
    assert _open(path, scene="# edited comment\n[chamber]\nheight_mm = 10.0\n").done().tolist() == [0]

    other_shape = Schema(tuple(Field("voltages", (208,)) if f.name == "voltages" else f for f in SCHEMA.fields), "palpate")
    with pytest.raises(ValueError, match=r"different run \(schema.fields.voltages.shape: \[256\] in the store, \[208\] now\)"):
        _open(path, schema=other_shape)
    with pytest.raises(ValueError, match=r"different run \(scene.chamber.height_mm: 10.0 in the store, 12.0 now\)"):
        _open(path, scene="[chamber]\nheight_mm = 12.0\n")
    with pytest.raises(ValueError, match=r"seed: 7 in the store, 8 now"):
        _open(path, seed=8)
    with pytest.raises(ValueError, match=r"n_records: 6 in the store, 7 now"):
        _open(path, n=7)
    with pytest.raises(ValueError, match=r"params.mesh: absent in the store, 'test' now"):
        _open(path, params={"mesh": "test"})

    meta = path.with_suffix(".partial") / "meta.json"
    m = json.loads(meta.read_text())
    m["identity"]["versions"]["numpy"] = "0.0.1"
    meta.write_text(json.dumps(m))
    with pytest.raises(ValueError, match="numpy 0.0.1 in the store, .* here"):
        _open(path)
    with pytest.raises(ValueError, match="numpy 0.0.1 in the store"):
        attach(path)
    assert _open(path, allow_version_change=True).done().tolist() == [0]


def test_resuming_from_another_code_commit_warns_and_keeps_the_records(tmp_path, monkeypatch, capsys):
    import jointsim.io.store as store

    path = tmp_path / "run"
    monkeypatch.setattr(store, "git_commit", lambda: "a" * 40)
    _open(path).put(0, _record(0))
    _open(path)  # the same commit: silent
    assert "warning" not in capsys.readouterr().err
    monkeypatch.setattr(store, "git_commit", lambda: "b" * 40)
    assert _open(path).done().tolist() == [0]
    err = capsys.readouterr().err
    assert "b" * 40 in err and "earlier sessions ran " + "a" * 40 in err


def test_a_finished_run_is_not_reopened_and_a_damaged_file_is_detected(tmp_path):
    store = _open(tmp_path / "run", n=2)
    store.put(0, _record(0))
    store.put(1, _record(1))
    path = store.finalize()
    with pytest.raises(FileExistsError, match="already exists"):
        _open(tmp_path / "run", n=2)
    with h5py.File(path, "r+") as h5:
        h5["records/volume"][1] = 7.0
    with pytest.raises(ValueError, match="does not match its data_sha256"):
        open_records(path)
    assert open_records(path, verify=False)["volume"][1] == 7.0


def _finalised_once(path, n: int):
    store = _open(path, n=n)
    for i in range(n):
        store.put(i, _record(i))
    return open_records(store.finalize())


def test_duplicates_pass_when_equal_and_are_refused_when_not(tmp_path):
    store = _open(tmp_path / "run", n=3)
    a, b = attach(tmp_path / "run"), pickle.loads(pickle.dumps(store))  # a retried task, or a copy sent to a worker
    for i in range(3):
        a.put(i, _record(i))
    b.put(1, {**_record(1), "timings": [9.9, 9.9]})  # the same work, timed differently: volatile
    assert store.done().tolist() == [0, 1, 2]
    rec = open_records(store.finalize(keep_partial=True))
    assert rec["frame"].tolist() == [0, 1, 2]
    assert rec.data_sha256 == _finalised_once(tmp_path / "once", 3).data_sha256

    (tmp_path / "run.h5").unlink()
    b.put(2, _record(2, x=2.0))
    with pytest.raises(ValueError, match="record 2 was written twice with different data"):
        store.finalize()


def test_a_write_that_fails_midway_leaves_no_record_file(tmp_path, monkeypatch):
    store = _open(tmp_path / "run")

    def crash(f, **arrays):
        f.write(b"PK\x03\x04 half a record")
        raise OSError("No space left on device")

    monkeypatch.setattr(np, "savez", crash)
    with pytest.raises(OSError, match="No space left"):
        store.put(0, _record(0))
    assert store.done().size == 0
    assert [p for p in (tmp_path / "run.partial" / "records").rglob("*") if p.is_file()] == []
    monkeypatch.undo()
    store.flush()  # the record stayed pending and is written by the next flush
    assert store.done().tolist() == [0]


def test_batched_writes_hold_strided_records_and_flush_on_exit(tmp_path):
    with _open(tmp_path / "run", n=9, batch=3) as store:
        # files 0,2,4 (full) | 6,8 (closed by 1, which does not continue it) | 1,3 (buffered)
        for i in [0, 2, 4, 6, 8, 1, 3]:
            store.put(i, _record(i), checkpoint={"state": np.full(2, i)})
        assert store.done().tolist() == [0, 2, 4, 6, 8]  # buffered records are not done yet
    files = sorted(p.name.split(".")[0] for p in (tmp_path / "run.partial" / "records").rglob("r*.npz"))
    assert files == ["r000000000000_2x3", "r000000000001_2x2", "r000000000006_2x2"]
    assert store.checkpoint(8)["state"].tolist() == [8, 8]
    with store:
        for i in [5, 7]:
            store.put(i, _record(i))
    assert open_records(store.finalize())["frame"].tolist() == list(range(9))


@pytest.mark.parametrize("batch", [1, 4])
def test_a_killed_time_series_resumes_to_the_same_data(tmp_path, batch):
    n = 60
    ref = tmp_path / "ref"
    _finish(_writer(tmp_path, ref, "series", n, batch))
    expected = open_records(attach(ref).finalize())

    run = tmp_path / "run"
    partial = run.with_suffix(".partial")
    for kill in range(2):  # killed twice, at different points, then resumed to the end
        before = attach(run).done().size if partial.exists() else 0
        _kill_after(_writer(tmp_path, run, "series", n, batch, delay=0.01), 8)
        done = attach(run).done()
        assert before < done.size < n and done.tolist() == list(range(done.size))
        # what a kill during a write leaves: a hidden, truncated temporary file
        one = next(partial.rglob("r*.npz"))
        (one.parent / f".{one.stem}.k{kill}.npz").write_bytes(one.read_bytes()[:100])
    _finish(_writer(tmp_path, run, "series", n, batch))
    got = open_records(attach(run).finalize())

    assert got.data_sha256 == expected.data_sha256 and got.provenance == expected.provenance
    for name in SCHEMA.names:
        if name != "timings":
            np.testing.assert_array_equal(got[name], expected[name], err_msg=name)
    assert len(got.run["sessions"]) == 3 and len(expected.run["sessions"]) == 1
    # the frames follow the recurrence through both restarts (checkpoints restored the state)
    state, poses = np.zeros(4), []
    for i in range(n):
        state = 0.9 * state + np.random.default_rng([7, i]).standard_normal(4)
        poses.append(state[:3])
    np.testing.assert_array_equal(got["pose"], poses)


def test_two_concurrent_writers_lose_nothing(tmp_path):
    n = 50
    store = tmp_path / "run"
    procs = [_writer(tmp_path, store, "independent", n, batch=3, worker=w, n_workers=2, delay=0.002) for w in range(2)]
    for p in procs:
        _finish(p)
    got = open_records(attach(store).finalize())
    ref = tmp_path / "ref"
    _finish(_writer(tmp_path, ref, "independent", n))
    expected = open_records(attach(ref).finalize())

    np.testing.assert_array_equal(got["frame"], np.arange(n))
    assert got.data_sha256 == expected.data_sha256
    np.testing.assert_array_equal(got["image"], expected["image"])
    assert len(got.run["sessions"]) == 2


def test_a_second_driver_on_one_output_is_refused_at_its_start(tmp_path):
    """exclusive(): while one run holds an output, another is refused at once, naming the path and
    the holder; the lock goes with the holder (here its block; a killed process's goes with it)."""
    from jointsim.io.store import exclusive

    with exclusive(tmp_path / "run"):
        with pytest.raises(ValueError, match=r"run\.h5: another jointsim run is writing it \(pid \d+ on "):
            with exclusive(tmp_path / "run.h5"):
                pass
    with exclusive(tmp_path / "run"):  # released
        pass


def test_a_second_dataset_on_one_output_is_refused_before_any_work(tmp_path):
    from jointsim.dataset import generate_dataset
    from jointsim.io.store import exclusive
    from jointsim.scene import scene_from_dict

    with exclusive(tmp_path / "ds.h5"), pytest.raises(ValueError, match="another jointsim run is writing it"):
        generate_dataset(scene_from_dict({"mesh": {"preset": "test"}}), 3, tmp_path / "ds.h5", seed=0, workers=1)
    assert not (tmp_path / "ds.partial").exists()


def test_a_full_disk_names_the_folder_and_says_the_stored_records_are_kept(tmp_path, monkeypatch):
    store = _open(tmp_path / "run")

    def full(f, **arrays):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(np, "savez", full)
    with pytest.raises(OSError, match=r"No space left on device \(writing records 0-0; the records stored before are kept") as e:
        store.put(0, _record(0))
    assert e.value.errno == 28 and Path(e.value.filename).parent == tmp_path / "run.partial" / "records"


def test_a_damaged_record_file_is_set_aside_and_its_records_count_as_missing(tmp_path):
    store = _open(tmp_path / "run")
    for i in range(3):
        store.put(i, _record(i))
    files = sorted((tmp_path / "run.partial" / "records").rglob("r*.npz"))
    data = bytearray(files[1].read_bytes())
    data[len(data) // 2: len(data) // 2 + 4] = bytes(b ^ 0xFF for b in data[len(data) // 2: len(data) // 2 + 4])
    files[1].write_bytes(bytes(data))
    with pytest.raises(ValueError, match="unreadable record file"):
        store.get(1)  # read where it lies: refused, not a wrong array
    aside = store.set_aside_unreadable()
    assert aside == [files[1].with_name(files[1].name + ".damaged")] and aside[0].exists()  # kept, not deleted
    assert store.missing().tolist() == [1, 3, 4, 5]  # n = 6; 0 and 2 are still stored
    assert store.set_aside_unreadable() == []  # the sound files are left where they are
