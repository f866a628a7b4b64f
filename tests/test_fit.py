"""Fitting the sensor's electrical nuisance parameters to a reference frame
(jointsim.eit.fit): on the test chamber, a pseudo-measured sensor (saline 3 % off, every
contact impedance drawn over ×0.5–2, every ring electrode moved up to 0.1 mm) is recovered
from the scene's nominal values, noise-free and at the instrument's noise."""

import numpy as np
import pytest

from jointsim.eit.fit import fit_reference
from jointsim.eit.forward import ForwardModel
from jointsim.eit.protocol import scene_protocol
from jointsim.mesh.electrodes import disc_patches


@pytest.fixture(scope="module")
def truth(test_chamber):
    scene, ch = test_chamber
    rng = np.random.default_rng(4)
    lay = ch.layout
    n = len(lay.radii)
    z = 1e-3 * np.exp(rng.uniform(np.log(0.5), np.log(2.0), n))
    c = lay.centres.copy()
    ring = [l for l in range(n) if l != ch.ground]
    r, a = 0.1e-3 * np.sqrt(rng.uniform(size=len(ring))), rng.uniform(0, 2 * np.pi, len(ring))
    c[ring, 0] += r * np.cos(a)
    c[ring, 1] += r * np.sin(a)
    protocol = scene_protocol(scene)
    model = ForwardModel(ch.mesh, disc_patches(ch.mesh, c, lay.radii), ch.ground, z)
    v = model.solve(0.36).voltages(protocol)
    return scene, ch, protocol, v, z, c, ring


def test_a_reference_frame_gives_back_the_sensor_it_was_measured_on(truth):
    """Noise-free, the same model: the conductivity to 1e-6, every ring electrode's contact
    impedance to 0.1 % and centre to 1 µm (from 100 µm off), the residual from 15 % to < 1e-7
    of the frame. The central ground's too: it carries no net current (every injection is
    between ring electrodes) but shunts the field through its 4 mm disc, so its contact shows."""
    scene, ch, protocol, v, z, c, ring = truth
    z0 = np.append(np.asarray(scene.electrodes.contact_impedance), scene.electrodes.ground_contact_impedance)
    fit = fit_reference(ch.mesh, ch.layout.centres, ch.layout.radii, ch.ground, protocol, v, 0.37, z0, noise_std=1e-9)
    assert fit.before > 1e-2 and fit.after < 1e-7
    assert fit.conductivity == pytest.approx(0.36, rel=1e-6)
    np.testing.assert_allclose(fit.contact_impedance, z, rtol=1e-3)
    assert np.abs(fit.centres[ring, :2] - c[ring, :2]).max() < 1e-6


def test_at_the_instruments_noise_the_fit_is_as_good_as_the_noise_allows(truth):
    """One noisy frame at 74.2 dB (5 µV per channel): the residual ends at the noise (its RMS
    within 20 % of the noise's), the conductivity within 0.5 % and the centres within 20 µm."""
    scene, ch, protocol, v, z, c, ring = truth
    z0 = np.append(np.asarray(scene.electrodes.contact_impedance), scene.electrodes.ground_contact_impedance)
    std = np.abs(v).mean() * 10 ** (-74.2 / 20)
    noisy = v + np.random.default_rng(0).normal(0, std, len(v))
    fit = fit_reference(ch.mesh, ch.layout.centres, ch.layout.radii, ch.ground, protocol, noisy, 0.37, z0, noise_std=std)
    rms = fit.after * np.linalg.norm(noisy) / np.sqrt(len(v))
    assert rms == pytest.approx(std, rel=0.2)
    assert fit.conductivity == pytest.approx(0.36, rel=5e-3)
    assert np.abs(fit.centres[ring, :2] - c[ring, :2]).max() < 20e-6
