"""The stiffness-identifiability study's arithmetic on presses with known power laws (no
simulation): sensitivities, the slave-side grouping and the first-order modulus error."""

import math

import numpy as np
import pytest

from jointsim.studies.stiffness_sensitivity import MEMBRANE_STEP, PressCurve, StudyResult, joint_modulus_error, modulus_error


def _curve(E, scale, slave, depths, a=0.1, b=0.8):
    # F = c · E^a · μ^b, with a jump of c between the contact sides (their discretisation
    # differs): a difference taken across the jump would not return a
    e = 1e9 if math.isinf(E) else E
    F = depths * e**a * scale**b * (1.3 if slave == "membrane" else 1.0)
    return PressCurve(E, scale, slave, depths, F, 2 * F, 3 * F)


def _study(slaves, moduli):
    d = np.array([1e-3, 2e-3])
    moduli = np.asarray(moduli, float)
    return StudyResult(7.5e-3, moduli, [_curve(E, 1.0, s, d) for E, s in zip(moduli, slaves)],
                       [_curve(E, MEMBRANE_STEP, s, d) for E, s in zip(moduli, slaves)])


def test_sensitivities_recover_the_power_law_exponents():
    r = _study(["target", "target", "membrane", "membrane", "rigid"], [1e4, 1e5, 1e6, 3e6, math.inf])
    s_e, s_mu = r.target_sensitivity(), r.membrane_sensitivity()
    # ln F is linear in ln E within each side: central/one-sided differences are exact
    assert np.allclose(s_e[:4], 0.1, rtol=1e-12)
    assert np.all(s_e[4] == 0.0)
    assert np.allclose(s_mu, 0.8, rtol=1e-12)


def test_a_modulus_alone_on_its_contact_side_has_no_sensitivity():
    r = _study(["target", "target", "membrane", "rigid"], [1e4, 1e5, 1e6, math.inf])
    s = r.target_sensitivity()
    assert np.all(np.isnan(s[2])) and np.allclose(s[:2], 0.1)


def test_modulus_error_first_order_formula():
    # S_E 0.1, S_μ 0.8, ε_F 1 %, ε_μ 5 %: δ ln E = √(1e-4 + 16e-4) / 0.1
    assert modulus_error(0.1, 0.8, 0.01, 0.05) == pytest.approx(math.expm1(math.sqrt(1e-4 + 0.04**2) / 0.1))
    assert modulus_error(0.5, 0.5, 0.0, 0.0) == 0.0
    assert math.isinf(modulus_error(0.0, 0.8, 0.01, 0.0))
    with pytest.raises(ValueError, match="force_precision"):
        modulus_error(0.1, 0.8, -0.01, 0.0)


def test_joint_error_inverts_the_two_by_two_sensitivities():
    # F ∝ E^0.1 μ^0.8, V ∝ E^0.2 μ^-0.3: d ln E = (−0.3 d ln F − 0.8 d ln V) / det, det = −0.19
    expected = math.expm1(0.01 * math.hypot(0.3, 0.8) / 0.19)
    assert joint_modulus_error((0.1, 0.8), (0.2, -0.3), 0.01, 0.01) == pytest.approx(expected)
    # a Monte Carlo of the linearised model agrees
    rng = np.random.default_rng(0)
    J = np.array([[0.1, 0.8], [0.2, -0.3]])
    noise = 0.01 * rng.standard_normal((200_000, 2))
    est = np.linalg.solve(J, noise.T)[0]
    assert math.expm1(est.std()) == pytest.approx(expected, rel=0.01)
    # proportional sensitivities cannot separate E from μ
    assert math.isinf(joint_modulus_error((0.1, 0.8), (0.2, 1.6), 0.01, 0.01))
