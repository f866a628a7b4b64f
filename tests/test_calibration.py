"""Calibration maps (jointsim.calibration, `jointsim calibrate`, `jointsim palpate --calibration`)
on synthetic dataset stores whose measurements are known functions of the labels
(jointsim.calibration.synthetic): the fits must recover those functions on held-out presses,
the split must keep presses whole, and a map must reload bit for bit in a new process and
refuse a sensor it was not built for. ~30 s on 2 cores."""

import json
import subprocess
import sys
import tomllib
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from jointsim.calibration import (SceneMismatchError, Settings, calibrate, load_map, load_samples, save_map,
                                  scene_from_provenance, sensor_fingerprint, split_groups)
from jointsim.calibration.curves import Monotone, fit_level_curves, value_at
from jointsim.calibration.regression import fit_regressor
from jointsim.calibration.synthetic import DATASET_SCHEMA, synthetic_com, write_synthetic_dataset
from jointsim.cli.main import main
from jointsim.io.store import Field, Records, Schema, open_store
from jointsim.scene import load_scene, scene_from_dict

ROOT = Path(__file__).resolve().parents[1]
SCENE = ROOT / "scenes" / "paper_sensor.toml"


@pytest.fixture(scope="module")
def stores(tmp_path_factory):
    d = tmp_path_factory.mktemp("calibration")
    text = SCENE.read_text()
    return {
        "soft": write_synthetic_dataset(d / "soft.h5", text, n_groups=90, seed=1, soft_fraction=0.5),
        "rigid": write_synthetic_dataset(d / "rigid.h5", text, n_groups=40, seed=2),
        "dir": d,
    }


@pytest.fixture(scope="module")
def built(stores):
    # the ridge regression: the MLP is tested on its own (test_direct_regression_learns_and_evaluates_as_sklearn_does)
    return calibrate(load_samples(stores["soft"]), Settings(seed=0, regressor="ridge"), progress=lambda s: None)


# -- pieces with exact answers -----------------------------------------------------------------


def test_value_at_interpolates_along_each_press():
    g = np.array([0, 0, 0, 1, 1, 2])
    depth = np.array([1.0, 2.0, 3.0, 2.0, 1.0, 0.5])  # group 1 out of order; group 2 never reaches 1.5
    v = 10 * depth + g
    ids, out = value_at(g, depth, v, 1.5)
    np.testing.assert_array_equal(ids, [0, 1])
    np.testing.assert_allclose(out, [15.0, 16.0])


def test_monotone_inverse_recovers_a_known_curve():
    size = np.linspace(8e-3, 30e-3, 40)
    metric = -30 * (size / 10e-3) ** 1.5  # decreasing in size: the inverse must find that itself
    inv = Monotone.fit(metric, size)
    q = np.linspace(metric.min(), metric.max(), 17)
    exact = 10e-3 * (-q / 30) ** (1 / 1.5)
    assert np.abs(inv(q) - exact).max() < 0.1e-3
    assert np.isnan(inv(np.array([np.nan]))).all()


def test_level_curves_blend_between_levels_and_refuse_outside():
    n = 30
    g = np.repeat(np.arange(n), 4)
    depth = np.tile([1.0, 2.0, 3.0, 4.0], n) * 1e-3
    size = np.repeat(np.linspace(8e-3, 30e-3, n), 4)
    metric = size * depth * 1e3  # linear in depth: blending the two levels' curves is exact
    lc = fit_level_curves("depth", "m", np.array([1e-3, 3e-3]), g, depth, metric, size)
    at = np.array([1e-3, 2e-3, 3e-3, 3.5e-3])
    s = np.array([12e-3, 20e-3, 25e-3, 20e-3])
    p = lc.predict(s * at * 1e3, at)
    np.testing.assert_allclose(p[:3], s[:3], rtol=0.01)
    assert np.isnan(p[3])  # 3.5 mm lies past the last level


# -- the split ---------------------------------------------------------------------------------


def test_split_keeps_presses_whole_and_is_deterministic():
    rng = np.random.default_rng(0)
    g = np.repeat(np.arange(50), 7)
    tr, te = split_groups(g, 0.2, seed=3)
    assert not np.intersect1d(g[tr], g[te]).size and (tr ^ te).all()
    assert len(np.unique(g[te])) == 10
    tr2, te2 = split_groups(g, 0.2, seed=3)
    np.testing.assert_array_equal(te, te2)
    # the order of the samples does not change which presses are held out
    perm = rng.permutation(len(g))
    _, te3 = split_groups(g[perm], 0.2, seed=3)
    np.testing.assert_array_equal(np.unique(g[perm][te3]), np.unique(g[te]))
    _, te4 = split_groups(g, 0.2, seed=4)
    assert not np.array_equal(te, te4)


def test_split_needs_enough_presses():
    with pytest.raises(ValueError, match="4 press group.*at least 5"):
        split_groups(np.repeat(np.arange(4), 5))


# -- the fitted calibration recovers the known transforms on held-out presses -----------------


def test_calibration_recovers_the_known_transforms(built):
    ev = built.evaluation
    assert ev["split"]["overlapping_presses"] == 0
    # the CoM map undoes the warp: uncalibrated CoM is ~1 mm off, calibrated ≪ the 0.05 mm noise × warp
    assert ev["com"]["raw_xy_r15"]["median"] > 0.8
    assert ev["com"]["xy_r15"]["median"] < 0.2 and ev["com"]["xy_r15"]["p95"] < 0.5
    assert ev["com"]["depth_all"]["median"] < 0.2
    # the map is the inverse of synthetic_com on clean points inside the data
    pos = np.array([[2e-3, -3e-3, 2e-3], [-8e-3, 5e-3, 3e-3], [0.0, 10e-3, 1.5e-3]])
    np.testing.assert_allclose(built.map.com(synthetic_com(pos)), pos, atol=0.3e-3)
    # size: the chosen per-frame route within 1.5 mm median over 8–30 mm diameters
    route = ev["size_route"]
    assert ev["size_per_frame"][route]["all"]["median"] < 1.5
    # stiffness from force and image at fixed depths: the synthetic Hertz law in series
    assert ev["stiffness"]["estimable"] and ev["stiffness"]["relative"]["median"] < 0.2
    # per decade of the true modulus, the held-out presses all counted once
    dec = ev["stiffness"]["by_decade"]
    assert sum(b["n"] for b in dec) == ev["stiffness"]["relative"]["n"]
    assert all(b["to_pa"] == pytest.approx(10 * b["from_pa"]) for b in dec)
    # the synthetic force is Hertz with target and membrane (E 66 kPa) in series: a decade of
    # soft targets below the membrane presses with less force than one well above it
    sens = ev["stiffness"]["force_sensitivity"]["by_decade"]
    assert len(sens) >= 3 and sens[0]["mean_percent"] < sens[-1]["mean_percent"] - 10
    # the goals table says, for every goal, a value and whether it is met
    assert {g["goal"] for g in ev["goals"]} >= {"depth", "modulus (relative)"}
    assert all(isinstance(g["met"], bool) for g in ev["goals"])
    # met, not met, or undetermined where too few held-out samples (or no value) judge it
    from jointsim.calibration.build import MIN_JUDGED

    for g in ev["goals"]:
        q = "modulus" if g["goal"].startswith("modulus") else ""
        few = g["n"] < MIN_JUDGED.get(q, 20) or not np.isfinite(g["value"])
        assert g["verdict"] == ("undetermined" if few else "met" if g["value"] <= g["limit"] else "not met")
        assert g["met"] == (g["verdict"] == "met")
    # a map that makes the position worse than the raw image CoM says so
    from jointsim.calibration.build import worse_than_uncalibrated

    assert worse_than_uncalibrated({"xy_r15": {"median": 1.2, "p95": 2.0}, "raw_xy_r15": {"median": 0.8, "p95": 2.5}}) == [
        "the CoM map makes the in-plane position worse than the uncalibrated image CoM on held-out presses (median 1.2 mm "
        "against 0.8 mm within r <= 15 mm): use the raw CoM, or the direct regression, for position"]
    assert worse_than_uncalibrated({"xy_r15": {"median": 0.5, "p95": 1.0}, "raw_xy_r15": {"median": 0.8, "p95": 2.5}}) == []
    assert isinstance(ev["warnings"], list)


def test_direct_regression_learns_and_evaluates_as_sklearn_does(stores):
    s = load_samples(stores["rigid"])
    from jointsim.calibration.data import voltage_features
    from jointsim.calibration.regression import regression_targets

    X = voltage_features(s.voltages, s.dv)
    T = regression_targets(s.position, s.size, s.force_mag)
    tr, te = split_groups(s.group, 0.25, seed=0)
    for kind in ("ridge", "mlp"):
        reg = fit_regressor(X[tr], T[tr], s.group[tr], kind=kind, seed=0)
        err = np.abs(reg(X[te]) - T[te])
        base = np.abs(T[te] - T[tr].mean(axis=0))
        # better than predicting the training mean for depth (the strongest voltage signal)
        assert np.median(err[:, 2]) < 0.7 * np.median(base[:, 2]), kind
    # the NumPy forward pass is scikit-learn's own prediction (refit-free evaluation)
    from sklearn.neural_network import MLPRegressor

    reg = fit_regressor(X[tr], T[tr], s.group[tr], kind="mlp", seed=0)
    Z = reg.whiten(X[te])
    m = MLPRegressor(hidden_layer_sizes=tuple(w.shape[1] for w in reg.weights[:-1]))
    m.fit(Z[:5], np.zeros((5, T.shape[1])))  # shapes only; then the fitted weights
    m.coefs_, m.intercepts_ = list(reg.weights), list(reg.biases)
    np.testing.assert_allclose(m.predict(Z) * reg.y_scale + reg.y_mean, reg(X[te]), rtol=1e-12, atol=1e-15)


def test_noisy_features_draw_the_datasets_noise():
    """Fresh draws of one clean sample: δV/V has the clean value as its mean and, per channel,
    the standard deviation σ·√(1 + 1/n_ref)/|V_ref| of the sample's noise plus the averaged
    reference's (σ from the SNR re the mean standing |V|). 4000 draws: the standard
    deviation is estimated to ~1.1 % (1/√(2N)) per channel, so 6 % bounds all 256 channels."""
    from jointsim.calibration.data import voltage_features
    from jointsim.calibration.regression import noisy_features

    rng = np.random.default_rng(5)
    ref = 0.02 * (1.0 + 0.5 * rng.uniform(size=(1, 256)))
    clean = ref * (1.0 - 1e-3 * rng.uniform(size=(1, 256)))
    X = noisy_features(clean, ref, (60.0, 60.0), 50, 4000, np.random.default_rng(0))
    assert X.shape == (4000, 256)
    sigma = np.abs(ref).mean() / 10 ** (60.0 / 20)
    want = sigma * np.sqrt(1 + 1 / 50) / ref[0]
    np.testing.assert_allclose(X.std(axis=0), want, rtol=0.06)
    np.testing.assert_allclose(X.mean(axis=0), voltage_features(clean, clean - ref)[0], atol=5 * want.max() / np.sqrt(4000))
    # a reference of one frame is as noisy as the sample: √2
    X1 = noisy_features(clean, ref, (60.0, 60.0), 1, 4000, np.random.default_rng(2))
    np.testing.assert_allclose(X1.std(axis=0), sigma * np.sqrt(2) / ref[0], rtol=0.06)
    # SNRs drawn over the range: more spread than at its quiet end alone
    Y = noisy_features(clean, ref, (40.0, 60.0), 50, 200, np.random.default_rng(1))
    assert np.all(Y.std(axis=0) > 2 * want)
    assert noisy_features(clean, ref, (60.0, 60.0), 50, 0, rng).shape == (0, 256)


def test_the_direct_regression_trains_on_fresh_noise_draws(stores):
    """A store with clean voltages: the regression's training rows are the stored samples plus
    ``noise_copies`` draws of each, over the training samples' SNR range; 0 copies trains on the
    stored samples alone; the setting is validated."""
    s = load_samples(stores["rigid"])
    assert s.has_clean and s.reference_frames == 50
    for copies in (0, 3):
        # (the emulator, whose routes are judged below, fitted once)
        cal = calibrate(s, Settings(regressor="ridge", noise_copies=copies, emulator=copies > 0), progress=lambda x: None)
        t = cal.evaluation["regression"]["training"]
        assert t["noise_copies"] == copies and t["rows"] == (copies + 1) * t["samples"]
    lo, hi = t["snr_db"]
    # asked to, a simulated store's noise draws are moved about the ring by the 32 symmetries of its
    # 16 electrodes and skip protocol (as its fingerprint records them)
    simulated = replace(s, source={**s.source, "synthetic": False})
    t = calibrate(simulated, Settings(regressor="ridge", noise_copies=3, symmetry=True, emulator=False),
                  progress=lambda x: None).evaluation["regression"]["training"]
    assert t["symmetries"] == 32 and t["rows"] == 4 * t["samples"]
    t = calibrate(simulated, Settings(regressor="ridge", noise_copies=3, emulator=False), progress=lambda x: None).evaluation["regression"]["training"]
    assert t["symmetries"] == 0  # off by default
    t = calibrate(s, Settings(regressor="ridge", noise_copies=3, symmetry=True, emulator=False), progress=lambda x: None)
    assert t.evaluation["regression"]["training"]["symmetries"] == 0  # a synthetic store's voltages are no chamber's
    train = s.subset(~np.isin(s.group, cal.tables["regression"]["group"]))
    assert (lo, hi) == (train.snr_db.min(), train.snr_db.max())
    # each goal on position, depth and size is judged for both routes
    routes = {g["route"] for g in cal.evaluation["goals"] if g["goal"] == "depth"}
    assert routes == {"image", "direct (ridge)", "emulator (per frame)", "emulator (press)"}  # the store has clean voltages
    for bad in (-1, 1001, 2.5):
        with pytest.raises(ValueError, match="noise_copies"):
            Settings(noise_copies=bad)


def test_binned_errors_tell_a_flat_prediction_from_a_noisy_one():
    """The report's by-size table: a regressor that returns the training mean shows a flat
    predicted median and an error growing away from it; one that follows the truth with
    noise shows the truth's medians and the noise's median |error| (0.6745 σ)."""
    from jointsim.calibration.build import SIZE_BINS, _binned

    rng = np.random.default_rng(0)
    size = rng.uniform(8e-3, 30e-3, 20000)
    flat = _binned(size, np.full_like(size, 19e-3), SIZE_BINS)
    assert [r["predicted_median"] for r in flat] == [19e-3] * 5
    assert flat[0]["error_median"] == pytest.approx(19e-3 - 10e-3, abs=2e-4)  # bin 8-12 mm
    assert sum(r["n"] for r in flat) == len(size)
    noisy = _binned(size, size + rng.normal(0, 1e-3, len(size)), SIZE_BINS)
    for r, lo, hi in zip(noisy, SIZE_BINS[:-1], SIZE_BINS[1:]):
        assert r["predicted_median"] == pytest.approx((lo + hi) / 2, abs=3e-4)
        assert r["error_median"] == pytest.approx(0.6745e-3, rel=0.1)
    force = _binned(np.array([0.5e-3, 2.5e-3]), np.array([0.02, 0.06]), (0.0, 1e-3, 2e-3, 3e-3), truth=np.array([0.01, 0.05]))
    assert [r["n"] for r in force] == [1, 0, 1] and force[2]["relative_median"] == pytest.approx(0.2)


def test_stiffness_of_rigid_targets_is_said_to_be_not_estimable(stores):
    cal = calibrate(load_samples(stores["rigid"]), Settings(regressor="ridge"), progress=lambda s: None)
    st = cal.evaluation["stiffness"]
    assert not st["estimable"] and "rigid" in st["reason"] and "not estimable" in st["reason"]
    goal = next(g for g in cal.evaluation["goals"] if g["goal"].startswith("modulus"))
    assert goal["met"] is False and "not estimable" in goal["note"]
    assert np.isnan(cal.map.stiffness.predict_features(np.zeros((2, 9)))).all()


# -- the map file ------------------------------------------------------------------------------


def _frames(s):
    return {"com": s.com, "voltages": s.voltages, "dv": s.dv, "force": s.force, "sum_sigma": s.sum_sigma,
            "diameter": s.diameter, "group": s.group, "depth": s.depth}


def test_map_loads_in_a_new_process_with_identical_predictions(built, stores):
    path = save_map(built.map, stores["dir"] / "map.h5")
    s = load_samples(stores["soft"])
    here = built.map.apply(_frames(s))
    assert np.isfinite(here["modulus"]).any() and np.isfinite(here["cal_diameter"]).any()
    assert built.map.emulator is not None and np.isfinite(here["model_x"]).all() and np.isfinite(here["press_x"]).any()
    out = stores["dir"] / "applied.npz"
    code = (
        "import numpy as np, sys\n"
        "from jointsim.calibration import load_map, load_samples\n"
        f"m = load_map({str(path)!r}); s = load_samples({str(stores['soft'])!r})\n"
        "f = dict(com=s.com, voltages=s.voltages, dv=s.dv, force=s.force, sum_sigma=s.sum_sigma, diameter=s.diameter,"
        " group=s.group, depth=s.depth)\n"
        f"np.savez({str(out)!r}, **m.apply(f))\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT)
    with np.load(out) as z:
        for k, v in here.items():
            if k == "outside":  # the flags: equal as strings
                assert z[k].tolist() == v.tolist()
                continue
            # the same parameters give the same numbers up to the summation order of BLAS, which
            # depends on the process's threading state (bitwise equal alone; 1.7e-12 relative,
            # 1e-16 absolute, after the mechanics tests had run in this process); a parameter
            # lost or rounded in the file would show at 1e-7 (float32) or worse
            v = np.asarray(v, float)
            scale = np.nanmax(np.abs(v)) if np.isfinite(v).any() else 1.0
            # the emulator's fits are iterations stopped at 1 nm steps: they agree to that
            tol = dict(rtol=1e-6, atol=1e-9) if k.startswith(("model_", "press_")) else dict(rtol=1e-10, atol=1e-12 * scale)
            np.testing.assert_allclose(z[k], v, err_msg=k, **tol)


def test_map_refuses_another_sensor_and_accepts_its_own(built):
    scene = load_scene(SCENE)
    built.map.check_scene(scene)
    data = tomllib.loads(SCENE.read_text())
    data["electrodes"]["ring_radius_mm"] = 14.0
    other = scene_from_dict(data)
    with pytest.raises(SceneMismatchError, match=r"electrodes\.ring_radius: 0\.015 in the map, 0\.014 in the scene"):
        built.map.check_scene(other)
    with pytest.raises(SceneMismatchError, match=r"mesh\.preset.*give --mesh dataset_p2\)\.$"):
        built.map.check_scene(scene.with_mesh_preset("test"))
    # P1 voltages are not the P2 voltages the map learnt
    with pytest.raises(SceneMismatchError, match=r"mesh\.element_order: 2 in the map, 'absent' in the scene"):
        built.map.check_scene(replace(scene, mesh=replace(scene.mesh, element_order=1)))
    # values a dataset randomises (saline, noise) do not make another sensor
    built.map.check_scene(replace(scene, noise=replace(scene.noise, snr_db=60.0)))


def test_fingerprint_from_a_datasets_recorded_scene_matches_the_scene():
    scene = load_scene(SCENE)
    d = json.loads(json.dumps(scene.to_dict()))  # as a store's JSON provenance holds it
    from jointsim.calibration.fingerprint import check_fingerprint, provenance_fingerprint

    assert provenance_fingerprint({"params": {"scene": d}, "scene_toml": ""}) == sensor_fingerprint(scene)
    p1 = json.loads(json.dumps(scene.with_mesh_preset("dataset").to_dict()))
    del p1["mesh"]["element_order"]  # recorded before the element order existed: P1
    assert provenance_fingerprint({"params": {"scene": p1}, "scene_toml": ""}) == sensor_fingerprint(scene.with_mesh_preset("dataset"))
    assert provenance_fingerprint({"params": {"scene": p1}, "scene_toml": ""}) != sensor_fingerprint(scene)
    prov = {"scene_toml": SCENE.read_text(), "params": {"mesh_preset": "test"}}
    assert scene_from_provenance(prov).mesh.preset == "test"
    # recorded before [reconstruction]: the image settings sat in [palpation], and maps built
    # then hold them under that name; both still match the scene
    legacy = json.loads(json.dumps(scene.to_dict()))
    legacy["palpation"].update(legacy.pop("reconstruction"))
    assert provenance_fingerprint({"params": {"scene": legacy}, "scene_toml": ""}) == sensor_fingerprint(scene)
    stored = {k.replace("reconstruction.", "palpation."): v for k, v in sensor_fingerprint(scene).items()}
    assert "palpation.cells" in stored
    check_fingerprint(stored, sensor_fingerprint(scene))
    other = replace(scene, reconstruction=replace(scene.reconstruction, cells=3000))
    with pytest.raises(SceneMismatchError, match=r"reconstruction\.cells: 7000 in the map, 3000 in the scene"):
        check_fingerprint(stored, sensor_fingerprint(other))
    # λ's press defines the sensor only where it is not the default it had before it existed
    assert "reconstruction.lambda_depth" not in sensor_fingerprint(scene)
    deeper = replace(scene, reconstruction=replace(scene.reconstruction, lambda_depth=2e-3))
    assert sensor_fingerprint(deeper)["reconstruction.lambda_depth"] == 2e-3


def test_load_map_refuses_other_files(tmp_path, stores):
    with pytest.raises(ValueError, match="no such file"):
        load_map(tmp_path / "nope.h5")
    with pytest.raises(ValueError, match="not a jointsim calibration map"):
        load_map(stores["soft"])
    (tmp_path / "text.h5").write_text("not hdf5")
    with pytest.raises(ValueError, match="not an HDF5 file"):
        load_map(tmp_path / "text.h5")


def _noisy_com_samples(n: int, seed: int):
    """Contacts over r ≤ 15 mm, depth 0.5–3 mm, whose CoM is the contact plus noise of SD
    2 mm at 40 dB falling 10x per 20 dB (to 0.02 mm at 80 dB); the CoM's z tracks the depth."""
    rng = np.random.default_rng(seed)
    r, t = 15e-3 * np.sqrt(rng.uniform(0, 1, n)), rng.uniform(0, 2 * np.pi, n)
    pos = np.column_stack([r * np.cos(t), r * np.sin(t), rng.uniform(0.5e-3, 3e-3, n)])
    snr = rng.uniform(40, 80, n)
    sd = 2e-3 * 10 ** ((40 - snr) / 20)
    com = np.column_stack([pos[:, :2], 5e-3 - 0.5 * pos[:, 2]]) + sd[:, None] * rng.standard_normal((n, 3))
    return pos, com, snr, np.arange(n) // 3


def test_com_map_weights_noisy_frames_less():
    from jointsim.calibration.com import fit_com_map

    pos, com, snr, group = _noisy_com_samples(600, 3)
    weighted, _ = fit_com_map(com, pos, group, snr)
    plain, _ = fit_com_map(com, pos, group)
    clean_pos, _, _, _ = _noisy_com_samples(300, 4)
    clean_com = np.column_stack([clean_pos[:, :2], 5e-3 - 0.5 * clean_pos[:, 2]])
    err = {k: np.median(np.linalg.norm(m(clean_com) - clean_pos, axis=1)) for k, m in (("weighted", weighted), ("plain", plain))}
    # the exact map is the identity in x, y and linear in z, and a third of the points lie
    # within 0.2 mm of it (SNR ≥ 67 dB): weighted by their noise, the map must follow them
    # (unweighted it measured 0.50 mm, weighted 0.04 mm)
    assert err["weighted"] < 0.1e-3 and err["weighted"] < 0.5 * err["plain"], err


def test_a_version_1_map_still_loads(built, tmp_path):
    """A format-1 map stored the position itself (no CoM correction) and one smoothing."""
    import h5py

    path = save_map(built.map, tmp_path / "v1.h5")
    com = built.map.com
    with h5py.File(path, "r+") as h5:
        h5.attrs["format_version"] = 1
        c = h5["com"]
        values = com.values.copy()
        values[:, :2] += com.points[:, :2]  # the v1 map fitted the position (mm) itself
        c["values"][...] = values
        del c["smoothing"]
        c.attrs["smoothing"] = 1e-3
    old = load_map(path).com
    assert not old.residual and float(old.smoothing) == 1e-3
    probe = np.array([[1e-3, -2e-3, 4e-3], [5e-3, 3e-3, 3.5e-3]])
    assert np.all(np.isfinite(old(probe)))
    with h5py.File(path, "r+") as h5:
        h5.attrs["format_version"] = 3
    with pytest.raises(ValueError, match="format version 3"):
        load_map(path)


# -- bad datasets ------------------------------------------------------------------------------


def _store(path, schema, records):
    st = open_store(path, schema, scene_toml=SCENE.read_text(), seed=0, n_records=len(records), fsync=False)
    for i, r in enumerate(records):
        st.put(i, r)
    return st.finalize()


def test_a_version_1_dataset_takes_the_target_centre_as_position(tmp_path, stores):
    from jointsim.io.store import open_records

    v2 = load_samples(stores["rigid"])
    assert v2.contact_known
    np.testing.assert_array_equal(v2.position[:, :2], v2.contact_xy)
    keep = tuple(f for f in DATASET_SCHEMA.fields if f.name != "contact_centre")
    rec = open_records(stores["rigid"])
    rows = [{f.name: rec[f.name][i] for f in keep} for i in range(len(rec))]
    v1 = load_samples(_store(tmp_path / "v1.h5", Schema(keep, name="dataset", version=1), rows))
    assert not v1.contact_known and np.isnan(v1.contact_xy).all()
    np.testing.assert_array_equal(v1.position[:, :2], v1.xy)


def test_bad_datasets_get_clear_errors(tmp_path, stores):
    with pytest.raises(ValueError, match="no such file"):
        load_samples(tmp_path / "missing.h5")
    # a store of another schema (e.g. a palpation run)
    other = _store(tmp_path / "pal.h5", Schema((Field("x"),), name="palpation"), [{"x": 1.0}])
    with pytest.raises(ValueError, match="'palpation' store.*'dataset' stores"):
        load_samples(other)
    # a dataset store without the image metrics
    keep = tuple(f for f in DATASET_SCHEMA.fields if f.name not in ("com", "sum_sigma"))
    lean = Schema(keep, name="dataset", version=1)
    rec = {f.name: np.zeros(f.shape, f.dtype) for f in keep}
    path = _store(tmp_path / "lean.h5", lean, [rec])
    with pytest.raises(ValueError, match=r"missing field\(s\) \['com', 'sum_sigma'\]"):
        load_samples(path)
    # too few presses for a held-out split
    small = write_synthetic_dataset(tmp_path / "small.h5", SCENE.read_text(), n_groups=4, seed=0)
    with pytest.raises(ValueError, match="4 press group"):
        calibrate(load_samples(small), progress=lambda s: None)


# -- command line ------------------------------------------------------------------------------


def test_calibrate_command_writes_the_map_and_report(stores, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["calibrate", str(stores["rigid"]), "--out", str(out), "--regressor", "ridge", "--depths-mm", "1,2,3"]) == 0
    for name in ("calibration_map.h5", "report.md", "com_error_map.png", "com_error_map.csv", "size_curves_depth.png",
                 "size_curves_force.png", "regression_comparison.csv", "goals.csv", "evaluation.json"):
        assert (out / name).is_file(), name
    md = (out / "report.md").read_text()
    assert "Not estimable" in md and "held out by press" in md
    m = load_map(out / "calibration_map.h5")
    np.testing.assert_allclose(m.size["depth/sum_sigma"].levels, [1e-3, 2e-3, 3e-3])
    assert ("## Model-based estimation" in md and "within 1σ" in md) == (m.emulator is not None)
    # bad input: one line and exit 2, nothing written
    assert main(["calibrate", str(tmp_path / "none.h5"), "--out", str(tmp_path / "x")]) == 2
    assert main(["calibrate", str(stores["rigid"]), "--out", str(tmp_path / "y"), "--depths-mm", "2,1"]) == 2
    err = capsys.readouterr().err
    assert "no such file" in err and "--depths-mm" in err and not (tmp_path / "x").exists()


def test_palpate_refuses_a_map_of_another_sensor_before_any_work(built, stores, tmp_path, capsys):
    path = save_map(built.map, stores["dir"] / "map_cli.h5")
    data = SCENE.read_text().replace("ring_radius_mm = 15.0", "ring_radius_mm = 14.0")
    scene = tmp_path / "other.toml"
    scene.write_text(data)
    assert main(["palpate", str(scene), "--calibration", str(path), "--out", str(tmp_path / "p")]) == 2
    assert "electrodes.ring_radius" in capsys.readouterr().err and not (tmp_path / "p").exists()


def test_calibrated_frames_of_a_palpation_run(built):
    """The per-frame table `palpate --calibration` writes, on palpation-shaped records."""
    from jointsim.calibration.apply import calibrate_frames, summarise_calibrated

    rng = np.random.default_rng(0)
    n = 12
    target = np.repeat([0, 1], 6)
    depth = np.tile([0, 1, 2, 3, 2, 1], 2) * 1e-3
    xy = np.array([[3e-3, 2e-3], [-5e-3, 4e-3]])[target]
    pos = np.column_stack([xy, depth])
    samples = load_samples_like(built, rng, n)
    fields = {"target": target, "frame": np.tile(np.arange(6), 2), "target_radius": np.full(n, 7.5e-3),
              "position": pos, "depth": depth, "com": synthetic_com(pos), **samples}
    rec = Records(fields, DATASET_SCHEMA, {}, {}, "")
    table = calibrate_frames(built.map, rec)
    ok = depth > 0
    np.testing.assert_allclose(table["cal_x"][ok], xy[ok, 0], atol=0.3e-3)
    np.testing.assert_allclose(table["cal_depth"][ok], depth[ok], atol=0.3e-3)
    rows = summarise_calibrated(table)
    assert [r["frame"] for r in rows] == [3, 3] and abs(rows[0]["cal_x_mm"] - 3.0) < 0.3


def test_a_map_knows_the_region_it_was_trained_on(built, stores):
    """The map records what its training samples span (read back from its file) and flags
    estimates outside it by name; a map without a recorded region flags nothing."""
    from jointsim.calibration.maps import outside_region

    r = built.map.region
    assert 0 < r["r_max_m"] and r["depth_m"][0] < r["depth_m"][1] and r["diameter_m"][0] < r["diameter_m"][1]
    assert load_map(save_map(built.map, stores["dir"] / "map_region.h5")).region == r
    inside = np.array([r["depth_m"][0], r["diameter_m"][0]]) * 1.01
    xy = np.array([[0.0, 0.0], [r["r_max_m"] * 1.01, 0.0], [0.0, 0.0]])
    flags = outside_region(r, xy, np.array([inside[0], inside[0], r["depth_m"][1] * 2]),
                           np.array([inside[1], r["diameter_m"][1] * 2, inside[1]]))
    assert flags.tolist() == ["", "position+diameter", "depth"]
    assert outside_region({}, xy, np.ones(3), np.ones(3)).tolist() == ["", "", ""]
    assert built.evaluation["region"]["test_samples"] > 0


def load_samples_like(built, rng, n):
    """Voltages and metrics of the right shapes (values only feed the regression and size routes)."""
    v = 0.2 + 1e-3 * rng.standard_normal((n, 256))
    return {"voltages": v, "dv": 1e-5 * rng.standard_normal((n, 256)), "force": np.tile([0.0, 0.0, 0.1], (n, 1)),
            "sum_sigma": np.full(n, -50.0), "diameter": np.full(n, 8e-3)}


def test_a_nan_estimate_comes_with_its_reason(built):
    """A diameter off the size curves' levels and a modulus of a press that missed the stiffness
    levels are NaN with a sentence saying why; finite values carry none."""
    from jointsim.calibration.apply import why_nan

    lc = built.map.size[built.map.size_route]
    far = 10 * float(lc.levels[-1])
    table = {"cal_diameter": np.array([np.nan, 0.01]), "cal_depth": np.array([far, 1e-3]), "force": np.array([far, 0.01]),
             "modulus": np.array([np.nan, 1e5])}
    why = why_nan(built.map, table, 0)
    assert "outside the size curves' levels" in why["diameter"]
    assert "stiffness" in why["modulus"] or built.map.stiffness.reason in why["modulus"]
    assert why_nan(built.map, table, 1) == {}
