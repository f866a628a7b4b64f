"""The MuJoCo bench rig (jointsim.palpation.rig): model, trajectories, the three controllers, the force
read-back, the coupling loop's stability, and input validation. Each test runs in well under a
second: the rig is a 4-dof model and the contact is the analytic Hertz surrogate."""

import math

import mujoco
import numpy as np
import pytest

from jointsim.palpation.rig import (
    DEFAULT_RIG,
    Controller,
    Trajectory,
    first_contact_height,
    hertz_contact_force,
    load_rig,
    press_hold_retract,
)

R_TARGET = 7.5e-3


def contact(rig, position, modulus=7e3):
    return hertz_contact_force(position, rig.target_radius, rig.dome_apex, rig.base_radius, modulus)


def run(rig, n, modulus=7e3, until_settled=False):
    """Couple the rig to the Hertz surrogate for ``n`` frames; return the frames and the force
    fed into each."""
    f, frames, forces = rig.current, [], []
    for _ in range(n):
        force = contact(rig, f.position, modulus)
        f = rig.frame(force)
        frames.append(f)
        forces.append(force)
        if until_settled and rig.settled():
            break
    return frames, np.array(forces)


# ---------------------------------------------------------------------------------------------
# model and trajectories
# ---------------------------------------------------------------------------------------------


def test_mjcf_loads_as_specified():
    raw = mujoco.MjModel.from_xml_path(str(DEFAULT_RIG))
    assert raw.opt.timestep == 1e-3
    np.testing.assert_allclose(raw.opt.gravity, [0, 0, -9.81])
    assert raw.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_CONTACT
    assert not raw.geom_contype.any() and not raw.geom_conaffinity.any()  # MuJoCo never touches the sensor

    for mode, ctrl, nv in [
        ("position", Controller.position(press_hold_retract(1e-3)), 3),
        ("force", Controller.force(0.02), 3),
        ("compliant", Controller.compliant(press_hold_retract(1e-3)), 4),
    ]:
        rig = load_rig(target_radius=12e-3, controller=ctrl)
        assert rig.mode == mode and rig.model.nv == nv
        assert rig.model.geom("target").size[0] == 12e-3
        assert rig.moving_mass == pytest.approx(0.05)
        assert rig.substeps == 20
        assert rig.dome_apex == pytest.approx(10e-3) and rig.base_radius == pytest.approx(20e-3)
        # on the axis, first contact is at apex + radius
        assert rig.contact_z == pytest.approx(10e-3 + 12e-3)
        # frame 0: at rest, at the commanded height less the servo's static sag under the weight
        f0 = rig.current
        assert f0.index == 0 and f0.time == 0.0
        np.testing.assert_array_equal(f0.applied_force, 0.0)
        if mode != "force":
            sag = rig.moving_mass * rig.gravity / rig.servo_gains[0]
            assert f0.position[2] == pytest.approx(rig.contact_z - sag, abs=1e-15)


def test_press_hold_retract_samples_the_paper_profile():
    tr = press_hold_retract(3e-3, hold_s=0.4, gap=1e-3, xy=(2e-3, -1e-3))
    step = np.diff(tr.depth)
    # 25 mm/s at 50 Hz: 0.5 mm per frame on the ramps, zero on the hold
    assert np.abs(step).max() == pytest.approx(0.5e-3)
    assert tr.depth[0] == -1e-3 and tr.depth[-1] == pytest.approx(-1e-3) and tr.depth.max() == 3e-3
    assert (tr.depth == 3e-3).sum() == 0.4 * 50 + 1  # hold frames, both ends included
    np.testing.assert_allclose(tr.t, np.arange(len(tr)) / 50.0)
    assert len(tr) == 1 + round((2 * 4e-3 / 25e-3 + 0.4) * 50)
    np.testing.assert_allclose(tr.stage_z(0.02), 0.02 - tr.depth)


def test_first_contact_and_surrogate():
    # on the cap (sphere of radius 25 mm centred at z = -15 mm): apex + r on the axis, and
    # still on the cap near its edge; beyond, the sphere rests on the rim circle (r = 20 mm)
    assert first_contact_height((0.0, 0.0), R_TARGET) == pytest.approx(17.5e-3)
    assert first_contact_height((25e-3, 0.0), R_TARGET) == pytest.approx(-15e-3 + math.sqrt(32.5e-3**2 - 25e-3**2))
    assert first_contact_height((0.0, 27e-3), R_TARGET) == pytest.approx(math.sqrt(R_TARGET**2 - 7e-3**2))
    with pytest.raises(ValueError, match="xy"):
        first_contact_height((30e-3, 0.0), R_TARGET)
    # the surrogate: zero at first contact, pointing up on the axis, 3/2 power law
    z0 = first_contact_height((0.0, 0.0), R_TARGET)
    np.testing.assert_array_equal(hertz_contact_force([0, 0, z0 + 1e-6], R_TARGET), 0.0)
    f1, f2 = hertz_contact_force(np.array([[0, 0, z0 - 1e-3], [0, 0, z0 - 2e-3]]), R_TARGET)
    assert f1[:2] == pytest.approx([0, 0]) and f1[2] > 0
    assert f2[2] / f1[2] == pytest.approx(2**1.5)
    # the default modulus is fitted to the FEM dome's 0.023 N at 1 mm (results/indentation)
    assert f1[2] == pytest.approx(0.023, rel=0.05)


# ---------------------------------------------------------------------------------------------
# coupling: read-back of the applied force
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("ctrl", [
    Controller.position(press_hold_retract(2e-3)),
    Controller.force(0.02),
    Controller.compliant(press_hold_retract(2e-3)),
], ids=["position", "force", "compliant"])
def test_applied_force_read_back_from_mujoco(ctrl):
    """The force MuJoCo's dynamics received (qfrc_smooth less every other contribution, on the
    target's joints) equals the contact force given. 1e-12 relative: the read-back subtracts
    terms of up to ~1 N (servo, weight) from a sum, so its rounding is ~1e-16 N per term, i.e.
    ~1e-14 relative on the ≥ 5 mN components used here; a force applied at the wrong point,
    on the wrong body, or scaled, would be off by orders of magnitude more."""
    rig = load_rig(target_radius=R_TARGET, controller=ctrl)
    rng = np.random.default_rng(0)
    for _ in range(5):
        force = rng.uniform(5e-3, 5e-2, 3) * rng.choice([-1, 1], 3)
        f = rig.frame(force)
        np.testing.assert_allclose(f.applied_force, force, rtol=1e-12, atol=0)
        # and MuJoCo holds it where the coupling put it: on the target body, at its centre
        np.testing.assert_array_equal(rig.data.xfrc_applied[rig.model.body("probe").id], [*force, 0, 0, 0])
    # zero force in, zero read back (the read-back is not a constant offset)
    f = rig.frame(np.zeros(3))
    assert np.abs(f.applied_force).max() < 1e-15


# ---------------------------------------------------------------------------------------------
# position mode
# ---------------------------------------------------------------------------------------------


def test_position_mode_follows_the_trajectory():
    """Tolerance from the servo gains. With force = kp (z_ref − z) + kv (v_ref − ż), joint
    damping c and moving mass M, the tracking error e = z_ref − z obeys
    M ë + (kv + c) ė + kp e = c v_ref + M g − F_z: at rest on a ramp or a hold it is exactly
    e* = (c v_ref + M g − F_z)/kp. The reference is piecewise linear between frames, so v_ref
    and F_z change only at frame starts; the deviation from e* then starts from at most
    |Δv| in rate and |Δe*| in value and decays with the servo's poles s₁ (slow), s₂ (fast):
    after one frame T it is ≤ (|Δv| + |s₂||Δe*|)·e^{−|s₁|T}/(|s₂| − |s₁|). We allow 10× that
    for the 1 ms integration of a ~2 ms time constant (ω·dt = 0.63). It comes to ~0.1 µm; a
    servo without the velocity feed-forward would lag by kv·v/kp = 79 µm."""
    tr = press_hold_retract(3e-3, hold_s=0.4, gap=1e-3, xy=(3e-3, -2e-3))
    rig = load_rig(target_radius=R_TARGET, controller=Controller.position(tr))
    frames, forces = run(rig, len(tr) - 1)
    assert rig.done and forces[:, 2].max() > 0.02  # it did press the dome

    kp, kv = rig.servo_gains
    M, c, g, T = rig.moving_mass, rig.stage_damping, rig.gravity, 1 / rig.frame_rate
    poles = np.sort(np.abs(np.roots([M, kv + c, kp])))
    assert np.isreal(poles).all()  # overdamped
    z_cmd = np.array([f.command_z for f in frames])
    np.testing.assert_allclose(z_cmd, rig.contact_z - tr.depth[1:])
    v_ref = np.diff(np.r_[rig.contact_z - tr.depth[0], z_cmd]) / T
    Fz = np.array([f.applied_force[2] for f in frames])
    e_star = (c * v_ref + M * g - Fz) / kp
    dv = np.abs(np.diff(np.r_[0.0, v_ref])).max()
    de = np.abs(np.diff(np.r_[M * g / kp, e_star])).max()
    tol = 10 * (dv + poles[1] * de) * math.exp(-poles[0] * T) / (poles[1] - poles[0])
    assert 1e-9 < tol < 1e-6

    z = np.array([f.position[2] for f in frames])
    np.testing.assert_allclose(z, z_cmd - e_star, rtol=0, atol=tol)
    # x and y stay put (to the lateral force over the servo stiffness)
    xy = np.array([f.position[:2] for f in frames])
    assert np.abs(xy - tr.xy).max() <= np.abs(forces[:, :2]).max() / kp + tol

    # the hold plateau is flat: after its first frame, nothing changes (the contact force
    # is constant at a constant depth), so the heights agree to the transient bound
    hold = np.flatnonzero(tr.depth[1:] == tr.depth.max())[1:]
    assert len(hold) == 20
    assert np.ptp(z[hold]) <= tol
    assert z[hold].mean() == pytest.approx(rig.contact_z - 3e-3 - e_star[hold].mean(), abs=tol)


# ---------------------------------------------------------------------------------------------
# force mode and the coupling loop's stability
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("modulus, press", [(7e3, 0.03), (24e3, 0.05)], ids=["soft-37N/m", "stiff-100N/m"])
def test_force_mode_settles_at_the_commanded_force(modulus, press):
    """The surrogate's stiffness at the balance point, dF/dδ = 3/2·F/δ, is ~37 N/m for the
    FEM-fitted modulus and ~100 N/m (the stiffness the loop must take) for the stiffer one.
    1 %: the settle criterion (1 µm per frame, three frames) leaves a residual of
    k·1 µm·ρ/(1 − ρ) ≲ 0.2 mN, under 1 % of either press."""
    rig = load_rig(target_radius=R_TARGET, controller=Controller.force(press, xy=(1e-3, 1e-3)))
    K = 4 / 3 * modulus * math.sqrt(R_TARGET * 25e-3 / (R_TARGET + 25e-3))
    delta = (press / K) ** (2 / 3)
    k = 1.5 * press / delta
    assert rig.coupling_radius(k) < 0.9
    frames, forces = run(rig, 400, modulus, until_settled=True)
    assert rig.settled() and len(frames) < 400
    f = frames[-1]
    assert f.command_force == press and math.isnan(f.command_z)
    balance = np.linalg.norm(contact(rig, f.position, modulus))
    assert balance == pytest.approx(press, rel=0.01)
    # it got there without overshooting into a bounce off the dome (contact never lost)
    assert (forces[1:, 2] > 0).all()


@pytest.mark.parametrize("k", [20.0, 100.0, 450.0])
def test_coupling_radius_predicts_the_simulated_loop(k):
    """A linear contact F_z = P − k (z − z_eq) in force mode: the disturbance shrinks (or grows)
    per frame by the predicted spectral radius. 5 %: the prediction is the continuous-time
    zero-order-hold map, MuJoCo integrates it in 1 ms steps (measured: ≤ 3 % apart)."""
    press = 0.03
    rig = load_rig(target_radius=R_TARGET, controller=Controller.force(press))
    z_eq = rig.contact_z - 1e-3
    f, err = rig.current, []
    for _ in range(60):
        f = rig.frame(np.array([0.0, 0.0, press - k * (f.position[2] - z_eq)]))
        err.append(abs(f.position[2] - z_eq))
    err = np.array(err)
    measured = (err[40:60].max() / err[20:40].max()) ** (1 / 20)  # envelope ratio per frame
    predicted = rig.coupling_radius(k)
    assert measured == pytest.approx(predicted, rel=0.05)
    if k == 100.0:  # the stiffness the loop must take: stable and contracting fast
        assert predicted < 0.75
    assert (err[-1] > err[0]) == (predicted > 1)


# ---------------------------------------------------------------------------------------------
# compliant mode
# ---------------------------------------------------------------------------------------------


def test_compliant_mode_settles_where_spring_balances_contact():
    """1 %: as for force mode, the settle criterion leaves ≲ k·1 µm·ρ/(1 − ρ), here ≪ 1 mN
    (ρ ≈ 0.3) against a ~70 mN contact force."""
    tr = press_hold_retract(3e-3, hold_s=2.0)
    rig = load_rig(target_radius=R_TARGET, controller=Controller.compliant(tr, stiffness=80.0, damping=2.0))
    assert rig.spring == (80.0, 2.0)
    frames, _ = run(rig, len(tr) - 1, until_settled=True)
    f = frames[-1]
    assert tr.depth[f.index] == 3e-3  # settled during the hold
    fc = contact(rig, f.position)[2]
    assert f.spring_force == pytest.approx(fc, rel=0.01)
    # the soft probe gave way: the target rides above the stage by spring force / stiffness
    assert f.position[2] - f.stage_z == pytest.approx(f.spring_force / 80.0, rel=1e-9)
    assert f.position[2] - f.stage_z > 0.5e-3
    # the stage itself still follows its command (stiff servo carrying the target's push)
    assert f.stage_z == pytest.approx(f.command_z, abs=1e-4)


# ---------------------------------------------------------------------------------------------
# bad input
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("call, name", [
    (lambda: load_rig(target_radius=-1e-3), "target_radius"),
    (lambda: load_rig(target_radius=0.0), "target_radius"),
    (lambda: press_hold_retract(-1e-3), "depth"),
    (lambda: press_hold_retract(1e-3, speed=0.0), "speed"),
    (lambda: press_hold_retract(1e-3, speed=-25e-3), "speed"),
    (lambda: press_hold_retract(1e-3, gap=-1e-3), "gap"),
    (lambda: press_hold_retract(1e-3, hold_s=-1.0), "hold_s"),
    (lambda: Controller(mode="velocity", trajectory=press_hold_retract(1e-3)), "mode"),
    (lambda: Controller.force(float("nan")), "press_force"),
    (lambda: Controller("position"), "trajectory"),
    (lambda: Controller.compliant(press_hold_retract(1e-3), stiffness=-5.0), "spring_stiffness"),
    (lambda: load_rig(controller=Controller.position(press_hold_retract(20e-3))), "depth"),
    (lambda: load_rig(controller=Controller.force(0.1, xy=(40e-3, 0.0))), "xy"),
    (lambda: load_rig(frame_rate=30.0, controller=Controller.force(0.1)), "frame_rate"),
    (lambda: load_rig(frame_rate=40.0), "frame_rate"),  # trajectory sampled at 50 Hz
    (lambda: load_rig(path="no/such/rig.xml"), "path"),
    (lambda: load_rig().frame(np.zeros(2)), "contact_force"),
    (lambda: Trajectory(t=np.zeros(3), depth=np.zeros(2)), "t"),
])
def test_bad_input_names_the_parameter(call, name):
    with pytest.raises(ValueError, match=rf"^{name} = "):
        call()
