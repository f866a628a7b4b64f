"""The palpation test bench in MuJoCo, coupled frame by frame to the FEM contact force.

This module owns the rig: the linear stage that carries the target, its controller, the
commanded trajectories, and the explicit staggered coupling at the instrument's frame rate.
It does not own the sensor's mechanics: MuJoCo never computes the target–sensor contact (the
rig's geoms do not collide); the caller evaluates the contact force (the FEM of
:mod:`jointsim.mechanics`, or the analytic surrogate :func:`hertz_contact_force` here) at the
pose the rig returns and hands it back for the next frame::

    rig = load_rig(target_radius=7.5e-3, controller=Controller.position(press_hold_retract(3e-3)))
    f = rig.current
    while not rig.done:
        force = contact_force_at(f.position)  # e.g. MembraneModel.press(...).force
        f = rig.frame(force)

The model is ``scenes/bench_rig.xml`` (the paper's bench, section III.C): a fixed plate with
the dome on it, a stage on x, y, z slides (x and y position the target over the dome, z is
driven), and the target sphere on the stage. Three controllers drive the z axis:

``position``
    a stiff PD servo follows the commanded stage height, with velocity feed-forward;
``force``
    a force actuator presses with the commanded force (the stage's weight compensated); the
    target settles where the contact force balances it;
``compliant``
    the stiff servo moves the stage and the target hangs from it on a spring-damper (a soft
    probe); the target settles where the spring force balances the contact force.

Coupling (one call of :meth:`Rig.frame` per frame): the contact force evaluated at the pose of
frame k is held constant, as ``data.xfrc_applied`` on the target body at its centre, while
MuJoCo advances 1/frame_rate s in 1 ms steps to frame k + 1 (zero-order hold). This is
explicit: a contact of stiffness k closes a sampled feedback loop around the target's axis,
which converges only if the rig's damping absorbs what one frame of held force injects. The
loop's per-frame contraction is computed exactly by :meth:`Rig.coupling_radius`; see it for
the reasoning and the numbers.

Units: SI throughout (m, s, N, kg). Heights are world z of the target centre; the sensor base
plane is z = 0.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path

import mujoco
import numpy as np
from scipy.linalg import expm

from ..scene import SCENES_DIR

__all__ = [
    "DEFAULT_RIG",
    "MODES",
    "Trajectory",
    "press_hold_retract",
    "Controller",
    "RigFrame",
    "Rig",
    "load_rig",
    "hertz_contact_force",
    "first_contact_height",
]

DEFAULT_RIG = SCENES_DIR / "bench_rig.xml"
MODES = ("position", "force", "compliant")
MAX_TARGET_RADIUS = 0.1  # m: the paper's targets are 8–30 mm (radius or diameter); 100 mm is far past any


def _check(name: str, value: float, ok: bool, allowed: str) -> None:
    if not ok:
        raise ValueError(f"{name} = {value!r}: must be {allowed}")


def _finite(x: float) -> bool:
    return isinstance(x, (int, float, np.floating, np.integer)) and math.isfinite(x)


# ---------------------------------------------------------------------------------------------
# Trajectories: plain data
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Trajectory:
    """A stage program sampled at the frame rate.

    ``depth`` (n,) m is the commanded indentation of frame k, measured from first contact
    (positive into the sensor; a negative value is a gap above the dome), ``t`` (n,) s the
    frame times (t[0] = 0), ``xy`` (2,) m where the target is lowered. The commanded stage
    (target-centre) height is ``stage_z(contact_z)`` = contact_z − depth: the initial distance
    between target and dome is compensated, as in the paper, by the rig supplying the
    first-contact height ``contact_z``."""

    t: np.ndarray
    depth: np.ndarray
    xy: tuple[float, float] = (0.0, 0.0)
    frame_rate: float = 50.0

    def __post_init__(self) -> None:
        t, depth = np.asarray(self.t, float), np.asarray(self.depth, float)
        _check("frame_rate", self.frame_rate, _finite(self.frame_rate) and self.frame_rate > 0, "> 0 Hz")
        _check("depth", depth.shape, depth.ndim == 1 and len(depth) >= 1, "a non-empty 1-D array")
        _check("t", t.shape, t.shape == depth.shape, f"of the shape of depth {depth.shape}")
        _check("depth", "non-finite values", bool(np.isfinite(depth).all()), "finite")
        _check("xy", self.xy, len(self.xy) == 2 and all(_finite(v) for v in self.xy), "two finite numbers (m)")
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "depth", depth)
        object.__setattr__(self, "xy", (float(self.xy[0]), float(self.xy[1])))

    def __len__(self) -> int:
        return len(self.depth)

    def stage_z(self, contact_z: float) -> np.ndarray:
        """Commanded target-centre height (n,) m for a target that touches the dome with its
        centre at height ``contact_z``."""
        return contact_z - self.depth


def press_hold_retract(
    depth: float,
    speed: float = 25e-3,
    hold_s: float = 0.5,
    frame_rate: float = 50.0,
    xy: tuple[float, float] = (0.0, 0.0),
    gap: float = 0.0,
) -> Trajectory:
    """The paper's palpation: from ``gap`` m above first contact, move down at ``speed`` m/s
    to ``depth`` m below first contact, hold for ``hold_s`` s, and retract at the same speed
    to the start. Sampled at ``frame_rate`` Hz from t = 0 to the end of the retraction (the
    last frame lands on the end); at 25 mm/s and 50 Hz a frame is 0.5 mm of travel."""
    _check("depth", depth, _finite(depth) and depth >= 0, ">= 0 m")
    _check("speed", speed, _finite(speed) and speed > 0, "> 0 m/s")
    _check("hold_s", hold_s, _finite(hold_s) and hold_s >= 0, ">= 0 s")
    _check("frame_rate", frame_rate, _finite(frame_rate) and frame_rate > 0, "> 0 Hz")
    _check("gap", gap, _finite(gap) and gap >= 0, ">= 0 m")
    travel = (gap + depth) / speed
    knots_t = np.array([0.0, travel, travel + hold_s, 2 * travel + hold_s])
    knots_d = np.array([-gap, depth, depth, -gap])
    n = int(math.ceil(knots_t[-1] * frame_rate - 1e-9)) + 1
    t = np.arange(n) / frame_rate
    return Trajectory(t=t, depth=np.interp(t, knots_t, knots_d), xy=xy, frame_rate=frame_rate)


# ---------------------------------------------------------------------------------------------
# Controller
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Controller:
    """What drives the stage's z axis; build it with :meth:`position`, :meth:`force` or
    :meth:`compliant`.

    ``trajectory`` (position and compliant modes) is the stage program; ``press_force`` (force
    mode) the pressing force, N, downward on the sensor (negative: the stage lifts the target
    away): a constant or one value per frame (n,), the last held after the end; ``xy`` and
    ``gap`` (force mode) where the target
    starts: ``gap`` m above first contact. ``spring_stiffness`` N/m and ``spring_damping``
    N s/m (compliant mode) override the probe spring of the MJCF; None keeps it."""

    mode: str = "position"
    trajectory: Trajectory | None = None
    press_force: float | np.ndarray | None = None
    xy: tuple[float, float] = (0.0, 0.0)
    gap: float = 0.0
    spring_stiffness: float | None = None
    spring_damping: float | None = None

    def __post_init__(self) -> None:
        _check("mode", self.mode, self.mode in MODES, f"one of {MODES}")
        if self.mode == "force":
            _check("press_force", self.press_force, self.press_force is not None, "given in force mode (N)")
            f = np.atleast_1d(np.asarray(self.press_force, float))
            _check("press_force", self.press_force, f.ndim == 1 and len(f) >= 1 and bool(np.isfinite(f).all()),
                   "finite N (a number or a 1-D array per frame; negative lifts)")
            _check("trajectory", self.trajectory, self.trajectory is None, "None in force mode (use press_force)")
            _check("gap", self.gap, _finite(self.gap) and self.gap >= 0, ">= 0 m")
            _check("xy", self.xy, len(self.xy) == 2 and all(_finite(v) for v in self.xy), "two finite numbers (m)")
        else:
            _check("trajectory", self.trajectory, isinstance(self.trajectory, Trajectory), f"a Trajectory in {self.mode} mode")
            _check("press_force", self.press_force, self.press_force is None, f"None in {self.mode} mode (it is for force mode)")
        for name in ("spring_stiffness", "spring_damping"):
            v = getattr(self, name)
            if v is not None:
                _check(name, v, self.mode == "compliant", "None outside compliant mode")
                _check(name, v, _finite(v) and v > 0, "> 0")

    @classmethod
    def position(cls, trajectory: Trajectory) -> "Controller":
        return cls("position", trajectory=trajectory)

    @classmethod
    def force(cls, press_force: float | np.ndarray, xy: tuple[float, float] = (0.0, 0.0), gap: float = 0.0) -> "Controller":
        return cls("force", press_force=press_force, xy=xy, gap=gap)

    @classmethod
    def compliant(cls, trajectory: Trajectory, stiffness: float | None = None, damping: float | None = None) -> "Controller":
        return cls("compliant", trajectory=trajectory, spring_stiffness=stiffness, spring_damping=damping)

    @property
    def start_xy(self) -> tuple[float, float]:
        return self.trajectory.xy if self.trajectory is not None else (float(self.xy[0]), float(self.xy[1]))


# ---------------------------------------------------------------------------------------------
# Frames
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class RigFrame:
    """The rig at the end of one frame.

    ``position`` (3,) m and ``velocity`` (3,) m/s of the target centre (world); ``time`` s;
    ``applied_force`` (3,) N: the external force on the target as MuJoCo's dynamics received
    it over the frame, read back from its generalized-force balance on the target's x, y and
    z joints (see :meth:`Rig._applied_force`); ``stage_z`` m the carriage height (differs from
    the target's in compliant mode); ``command_z`` m the commanded stage height (NaN in force
    mode); ``command_force`` N the commanded pressing force (NaN outside force mode);
    ``spring_force`` N the probe spring's upward force on the target beyond the one that
    carries its weight (compliant mode; NaN otherwise)."""

    index: int
    time: float
    position: np.ndarray
    velocity: np.ndarray
    applied_force: np.ndarray
    stage_z: float
    command_z: float
    command_force: float
    spring_force: float


# ---------------------------------------------------------------------------------------------
# The rig
# ---------------------------------------------------------------------------------------------


@dataclass
class Rig:
    """A compiled bench with its controller, ready to step: call :meth:`frame` once per frame.

    Built by :func:`load_rig`. ``contact_z`` is the target-centre height at first contact
    (trajectories are offset by it); ``dome_apex`` and ``base_radius`` (m) the sensor's
    visual dome as read from the model."""

    model: mujoco.MjModel
    data: mujoco.MjData
    controller: Controller
    target_radius: float
    frame_rate: float
    contact_z: float
    dome_apex: float
    base_radius: float
    index: int = 0
    _ids: dict[str, int] = field(default_factory=dict, repr=False)
    _recent: deque = field(default_factory=lambda: deque(maxlen=16), repr=False)

    # -- geometry and parameters read from the compiled model ------------------------------

    @property
    def mode(self) -> str:
        return self.controller.mode

    @property
    def substeps(self) -> int:
        return int(round(1.0 / (self.frame_rate * self.model.opt.timestep)))

    @property
    def gravity(self) -> float:
        return float(-self.model.opt.gravity[2])

    @property
    def moving_mass(self) -> float:
        """Mass carried by the z slide (stage + target holder), kg."""
        return float(self.model.body_subtreemass[self._ids["stage_body"]])

    @property
    def probe_mass(self) -> float:
        return float(self.model.body_mass[self._ids["target_body"]])

    @property
    def servo_gains(self) -> tuple[float, float]:
        """(kp N/m, kv N s/m) of the z position servo (position and compliant modes)."""
        if self.mode == "force":
            raise ValueError("servo_gains: force mode has no z position servo")
        return float(self.model.actuator_gainprm[self._ids["servo_z"], 0]), float(self.model.actuator_gainprm[self._ids["servo_zdot"], 0])

    @property
    def stage_damping(self) -> float:
        """Joint damping of the z slide, N s/m."""
        return float(self.model.dof_damping[self._ids["dof_z"]])

    @property
    def spring(self) -> tuple[float, float]:
        """(stiffness N/m, damping N s/m) of the probe spring (compliant mode)."""
        if self.mode != "compliant":
            raise ValueError(f"spring: only in compliant mode, not {self.mode!r}")
        j = self._ids["probe_joint"]
        return float(self.model.jnt_stiffness[j]), float(self.model.dof_damping[self._ids["dof_probe"]])

    @property
    def n_frames(self) -> int | None:
        """Length of the program (frames, including frame 0); None for a constant force."""
        c = self.controller
        if c.trajectory is not None:
            return len(c.trajectory)
        f = np.asarray(c.press_force, float)
        return len(f) if f.ndim == 1 else None

    @property
    def done(self) -> bool:
        """True once the program's last frame has been produced (never for a constant force)."""
        n = self.n_frames
        return n is not None and self.index >= n - 1

    # -- commands --------------------------------------------------------------------------

    def command_z(self, k: int) -> float:
        """Commanded stage height at frame ``k`` (the last one held past the end)."""
        tr = self.controller.trajectory
        return float(self.contact_z - tr.depth[min(k, len(tr) - 1)])

    def command_force(self, k: int) -> float:
        f = np.atleast_1d(np.asarray(self.controller.press_force, float))
        return float(f[min(k, len(f) - 1)])

    # -- the coupling ----------------------------------------------------------------------

    def frame(self, contact_force: np.ndarray) -> RigFrame:
        """Advance one frame (1/frame_rate s, in 1 ms steps) with ``contact_force`` (3,) N, the
        force of the sensor on the target evaluated at the current pose, held constant on the
        target's centre; return the rig at the end of the frame."""
        f = np.asarray(contact_force, float)
        _check("contact_force", f.shape, f.shape == (3,) and bool(np.isfinite(f).all()), "a finite (3,) array in N")
        m, d, ids = self.model, self.data, self._ids
        d.xfrc_applied[ids["target_body"]] = 0.0
        d.xfrc_applied[ids["target_body"], :3] = f
        n, k = self.substeps, self.index
        if self.mode == "force":
            # weight compensated: at rest the contact force balances the commanded force alone
            d.ctrl[ids["force_z"]] = self.moving_mass * self.gravity - self.command_force(k + 1)
            mujoco.mj_step(m, d, nstep=n)
        else:
            # the stage moves continuously (25 mm/s), not in 0.5 mm jumps: the reference is
            # interpolated linearly within the frame, each substep's value at the time of the
            # state it acts on, so that a steady ramp is followed with no lag
            z0, z1 = self.command_z(k), self.command_z(k + 1)
            d.ctrl[ids["servo_zdot"]] = (z1 - z0) * self.frame_rate
            for z in z0 + (z1 - z0) * np.arange(n) / n:
                d.ctrl[ids["servo_z"]] = z
                mujoco.mj_step(m, d)
        # the stepping leaves positions one integration ahead of the derived quantities:
        # recompute them (and the force balance read back below) at the frame's end state
        mujoco.mj_forward(m, d)
        self.index = k + 1
        self._recent.append(float(d.xpos[ids["target_body"], 2]))
        return self.current

    @property
    def current(self) -> RigFrame:
        """The rig now, without stepping (frame 0 right after loading)."""
        d, ids, k = self.data, self._ids, self.index
        vel = np.zeros(6)
        mujoco.mj_objectVelocity(self.model, d, mujoco.mjtObj.mjOBJ_BODY, ids["target_body"], vel, 0)
        pos = d.xpos[ids["target_body"]].copy()
        spring = math.nan
        if self.mode == "compliant":
            # the spring is preloaded by the probe's weight (springref): beyond it, k·q
            spring = self.spring[0] * float(d.qpos[ids["qpos_probe"]])
        return RigFrame(
            index=k,
            time=float(d.time),
            position=pos,
            velocity=vel[3:].copy(),
            applied_force=self._applied_force(),
            stage_z=float(d.qpos[ids["qpos_z"]]),
            command_z=math.nan if self.mode == "force" else self.command_z(k),
            command_force=self.command_force(k) if self.mode == "force" else math.nan,
            spring_force=spring,
        )

    def _applied_force(self) -> np.ndarray:
        """The external force on the target as MuJoCo used it: qfrc_smooth, the sum of every
        non-constraint generalized force in the last forward pass, less those that are not
        xfrc_applied (passive, bias, actuator, qfrc_applied), leaves Jᵀ·xfrc_applied; on the
        target's x, y and z joints (all along world axes) those are the force's components."""
        d, ids = self.data, self._ids
        q = d.qfrc_smooth - d.qfrc_passive + d.qfrc_bias - d.qfrc_actuator - d.qfrc_applied
        return q[[ids["dof_x"], ids["dof_y"], ids["dof_target_z"]]].copy()

    # -- stability and settling ------------------------------------------------------------

    def coupling_radius(self, contact_stiffness: float) -> float:
        """Spectral radius of the staggered 50 Hz loop for a contact of ``contact_stiffness``
        N/m (the slope −dF_z/dz at the operating point): the factor by which a disturbance
        shrinks per frame; the loop is stable below 1.

        Reasoning: along z the target is a mass m with damping c and (mode) stiffness k_r
        (position: the servo, c + kv and kp; force: the stage's damping alone, k_r = 0;
        compliant: the probe's mass on its spring, the stiff stage taken as fixed). The contact
        force −k·z_k is evaluated at the frame's start and held for T = 1/frame_rate, so the
        frame map is the exact zero-order-hold discretisation [x; v]_{k+1} = (Φ − Γ·[k, 0])·
        [x; v]_k with Φ = e^{A T}, Γ = ∫₀ᵀ e^{A s} ds·B. Roughly: over one frame the held force
        moves an overdamped target by k·T/c per metre of error, so the loop needs c ≳ k·T/2.
        The MJCF's defaults give, at 100 N/m: force mode (50 g, 3 N s/m) 0.70, and stability
        up to ~370 N/m; compliant mode (10 g, 100 N/m, 2 N s/m) 0.42, up to ~290 N/m. A soft
        contact settles slowly in force mode (1 − k·T/c per frame: 0.84 at 20 N/m) — the price
        of the damping that a stiff one needs."""
        _check("contact_stiffness", contact_stiffness, _finite(contact_stiffness) and contact_stiffness >= 0, ">= 0 N/m")
        if self.mode == "force":
            mass, c, k_r = self.moving_mass, self.stage_damping, 0.0
        elif self.mode == "compliant":
            mass, (k_r, c) = self.probe_mass, self.spring
        else:
            kp, kv = self.servo_gains
            mass, c, k_r = self.moving_mass, self.stage_damping + kv, kp
        T = 1.0 / self.frame_rate
        # [A B; 0 0]·T exponentiated gives Φ and Γ together (Van Loan)
        M = np.zeros((3, 3))
        M[:2, :2] = np.array([[0.0, 1.0], [-k_r / mass, -c / mass]]) * T
        M[1, 2] = T / mass
        E = expm(M)
        Ad = E[:2, :2] - np.outer(E[:2, 2], [contact_stiffness, 0.0])
        return float(np.abs(np.linalg.eigvals(Ad)).max())

    def settled(self, tol: float = 1e-6, window: int = 3) -> bool:
        """True when the target's height moved less than ``tol`` m in each of the last
        ``window`` frames. With the loop contracting by ρ = :meth:`coupling_radius` per frame,
        the distance still to go is about tol·ρ/(1 − ρ), i.e. a force residual of about
        k·tol·ρ/(1 − ρ) for a contact of stiffness k (0.1 mN at 20 N/m, where ρ = 0.84 in force
        mode, with tol = 1 µm: 0.3 % of a 30 mN press)."""
        _check("tol", tol, _finite(tol) and tol > 0, "> 0 m")
        _check("window", window, isinstance(window, int) and 1 <= window < self._recent.maxlen, f"an int in [1, {self._recent.maxlen - 1}]")
        z = np.array(self._recent)
        return len(z) > window and bool((np.abs(np.diff(z[-window - 1 :])) < tol).all())


# ---------------------------------------------------------------------------------------------
# Loading
# ---------------------------------------------------------------------------------------------


def _named(root: ET.Element, tag: str, name: str) -> tuple[ET.Element, ET.Element]:
    """(parent, element) of the ``tag`` element called ``name`` in the MJCF tree."""
    for parent in root.iter():
        for child in parent:
            if child.tag == tag and child.get("name") == name:
                return parent, child
    raise ValueError(f"rig model: no <{tag} name=\"{name}\"> (is this scenes/bench_rig.xml or a copy of it?)")


def first_contact_height(xy: tuple[float, float], radius: float, dome_apex: float = 10e-3, base_radius: float = 20e-3) -> float:
    """Centre height of a sphere of ``radius`` m lowered at ``xy`` when it first touches the
    undeformed spherical-cap dome (apex ``dome_apex``, base radius ``base_radius``, on z = 0):
    on the cap, or on its rim circle when the sphere comes down beside the cap's edge."""
    R = (base_radius**2 + dome_apex**2) / (2 * dome_apex)
    zc = dome_apex - R  # the cap's sphere centre
    rho = float(np.hypot(*xy))
    heights = []
    if rho < R + radius:  # touching the cap's sphere: valid if the touch point is on the cap
        h = zc + math.sqrt((R + radius) ** 2 - rho**2)
        if zc + R * (h - zc) / (R + radius) >= 0:
            heights.append(h)
    if abs(rho - base_radius) < radius:  # touching the rim circle
        heights.append(math.sqrt(radius**2 - (rho - base_radius) ** 2))
    if not heights:
        raise ValueError(f"xy = ({xy[0]:.4g}, {xy[1]:.4g}) m: a target of radius {radius:.4g} m there misses the dome; "
                         f"must be within {base_radius + radius:.4g} m of the axis")
    return max(heights)


def load_rig(
    path: str | Path | None = None,
    target_radius: float = 7.5e-3,
    controller: Controller | None = None,
    frame_rate: float = 50.0,
    contact_z: float | None = None,
) -> Rig:
    """Compile the bench at ``path`` (default ``scenes/bench_rig.xml``) for a spherical target
    of ``target_radius`` m driven by ``controller`` (default: position mode at first contact,
    no motion), stepping ``frame_rate`` Hz frames; the rig is placed at its program's frame 0,
    at rest.

    ``contact_z`` is the target-centre height at first contact, from which the trajectory's
    depths are measured; by default it is that of the undeformed visual dome
    (:func:`first_contact_height`). When coupling to the FEM, pass the membrane's own, e.g.
    ``MembraneModel.first_contact_height(xy)`` (its outer surface lies a membrane thickness
    above the dome the rig draws)."""
    _check("target_radius", target_radius, _finite(target_radius) and 0 < target_radius <= MAX_TARGET_RADIUS, f"in (0, {MAX_TARGET_RADIUS}] m")
    _check("frame_rate", frame_rate, _finite(frame_rate) and frame_rate > 0, "> 0 Hz")
    controller = controller if controller is not None else Controller.position(press_hold_retract(0.0, hold_s=0.0))
    _check("controller", type(controller).__name__, isinstance(controller, Controller), "a Controller")
    if controller.trajectory is not None and controller.trajectory.frame_rate != frame_rate:
        raise ValueError(f"frame_rate = {frame_rate}: must equal the trajectory's frame_rate {controller.trajectory.frame_rate} Hz")
    path = Path(path) if path is not None else DEFAULT_RIG
    if not path.is_file():
        raise ValueError(f"path = {str(path)!r}: no such rig model file")
    root = ET.parse(path).getroot()

    _named(root, "geom", "target")[1].set("size", repr(float(target_radius)))
    rod = _named(root, "geom", "rod")[1]
    top = [float(v) for v in rod.get("fromto").split()][3:]
    rod.set("fromto", " ".join(map(repr, [0.0, 0.0, float(target_radius), *top])))
    if controller.mode != "compliant":  # the target rigid on the stage
        parent, joint = _named(root, "joint", "probe_z")
        parent.remove(joint)
    unused = ("servo_z", "servo_zdot") if controller.mode == "force" else ("force_z",)
    for name in unused:
        parent, act = _named(root, "motor" if name == "force_z" else "general", name)
        parent.remove(act)
    model = mujoco.MjModel.from_xml_string(ET.tostring(root, encoding="unicode"))

    steps = 1.0 / (frame_rate * model.opt.timestep)
    if abs(steps - round(steps)) > 1e-9 or round(steps) < 1:
        raise ValueError(f"frame_rate = {frame_rate}: must divide 1/timestep = {1 / model.opt.timestep:g} Hz into whole steps")

    ids = _index(model, controller.mode)
    dome = ids.pop("dome_geom")
    R, zc = float(model.geom_size[dome, 0]), float(model.geom_pos[dome, 2])
    dome_apex, base_radius = zc + R, math.sqrt(max(R * R - zc * zc, 0.0))
    xy = controller.start_xy
    if contact_z is None:
        contact_z = first_contact_height(xy, target_radius, dome_apex, base_radius)
    _check("contact_z", contact_z, _finite(contact_z) and contact_z >= target_radius, f">= target_radius = {target_radius:.4g} m (the target above the base)")
    if controller.trajectory is not None:
        lowest = contact_z - float(controller.trajectory.depth.max()) - target_radius
        _check("depth", float(controller.trajectory.depth.max()), lowest >= 0,
               f"<= {contact_z - target_radius:.4g} m: deeper would push the target through the base plane z = 0")

    rig = Rig(model, mujoco.MjData(model), controller, float(target_radius), float(frame_rate), float(contact_z), dome_apex, base_radius, _ids=ids)
    if controller.mode == "compliant":
        c = controller
        j, dof = ids["probe_joint"], ids["dof_probe"]
        if c.spring_stiffness is not None:
            model.jnt_stiffness[j] = c.spring_stiffness
        if c.spring_damping is not None:
            model.dof_damping[dof] = c.spring_damping
        # preload: the free-hanging probe sits at q = 0, so the spring's k·q is the contact force
        model.qpos_spring[ids["qpos_probe"]] = rig.probe_mass * rig.gravity / model.jnt_stiffness[j]
    _place(rig, xy)
    return rig


def _index(model: mujoco.MjModel, mode: str) -> dict[str, int]:
    """Ids and addresses the rig uses, by role."""
    jnt = lambda name: model.joint(name).id  # noqa: E731
    ids = {
        "stage_body": model.body("stage").id,
        "target_body": model.body("probe").id,
        "dome_geom": model.geom("dome").id,
        "dof_x": int(model.jnt_dofadr[jnt("stage_x")]),
        "dof_y": int(model.jnt_dofadr[jnt("stage_y")]),
        "dof_z": int(model.jnt_dofadr[jnt("stage_z")]),
        "qpos_x": int(model.jnt_qposadr[jnt("stage_x")]),
        "qpos_y": int(model.jnt_qposadr[jnt("stage_y")]),
        "qpos_z": int(model.jnt_qposadr[jnt("stage_z")]),
        "servo_x": model.actuator("servo_x").id,
        "servo_y": model.actuator("servo_y").id,
    }
    ids["dof_target_z"] = ids["dof_z"]
    if mode == "compliant":
        j = jnt("probe_z")
        ids.update(probe_joint=j, dof_probe=int(model.jnt_dofadr[j]), qpos_probe=int(model.jnt_qposadr[j]))
        ids["dof_target_z"] = ids["dof_probe"]  # the outermost joint carrying the target along z
    if mode == "force":
        ids["force_z"] = model.actuator("force_z").id
    else:
        ids.update(servo_z=model.actuator("servo_z").id, servo_zdot=model.actuator("servo_zdot").id)
    return ids


def _place(rig: Rig, xy: tuple[float, float]) -> None:
    """Put the rig at frame 0 in static equilibrium (no contact force): servos at their
    commands, each sagging by the weight it carries over its stiffness."""
    m, d, ids = rig.model, rig.data, rig._ids
    d.qpos[ids["qpos_x"]], d.qpos[ids["qpos_y"]] = xy
    d.ctrl[ids["servo_x"]], d.ctrl[ids["servo_y"]] = xy
    if rig.mode == "force":
        d.qpos[ids["qpos_z"]] = rig.contact_z + rig.controller.gap
        d.ctrl[ids["force_z"]] = rig.moving_mass * rig.gravity - rig.command_force(0)
    else:
        z0 = rig.command_z(0)
        kp = rig.servo_gains[0]
        d.qpos[ids["qpos_z"]] = z0 - rig.moving_mass * rig.gravity / kp
        d.ctrl[ids["servo_z"]], d.ctrl[ids["servo_zdot"]] = z0, 0.0
    mujoco.mj_forward(m, d)
    rig._recent.clear()
    rig._recent.append(float(d.xpos[ids["target_body"], 2]))


# ---------------------------------------------------------------------------------------------
# The analytic contact surrogate
# ---------------------------------------------------------------------------------------------


def hertz_contact_force(
    centre: np.ndarray,
    radius: float,
    dome_apex: float = 10e-3,
    base_radius: float = 20e-3,
    modulus: float = 7e3,
) -> np.ndarray:
    """SURROGATE contact law, for tests and demos, NOT the FEM: the force (..., 3) N of the
    dome on a rigid sphere of ``radius`` m centred at ``centre`` (..., 3) m, by Hertz between
    two spheres (the dome's cap sphere of radius R = (a² + h²)/(2h) as a solid),

        F = 4/3 · E* · √R* · δ^{3/2} along the line of centres,  R* = r·R/(r + R),

    δ the overlap, zero without contact. ``modulus`` is the effective modulus E* (Pa).
    A saline-filled membrane dome is far softer than a solid of Ecoflex (E* ≈ 90 kPa): the
    default 7 kPa matches the FEM dome's force at 1 mm (0.023 N for a 7.5 mm target,
    results/indentation); the FEM's curve is nearly linear in depth, not δ^{3/2}, so away from
    1 mm the surrogate is off by tens of percent. Its stiffness is dF/dδ = 2·E*·√(R*·δ)."""
    _check("radius", radius, _finite(radius) and radius > 0, "> 0 m")
    _check("modulus", modulus, _finite(modulus) and modulus > 0, "> 0 Pa")
    _check("dome_apex", dome_apex, _finite(dome_apex) and dome_apex > 0, "> 0 m")
    _check("base_radius", base_radius, _finite(base_radius) and base_radius > 0, "> 0 m")
    c = np.asarray(centre, float)
    _check("centre", c.shape, c.shape[-1:] == (3,), "an array of shape (..., 3) in m")
    R = (base_radius**2 + dome_apex**2) / (2 * dome_apex)
    d = c - np.array([0.0, 0.0, dome_apex - R])
    dist = np.linalg.norm(d, axis=-1)
    overlap = np.clip(radius + R - dist, 0.0, None)
    r_eff = radius * R / (radius + R)
    magnitude = 4.0 / 3.0 * modulus * math.sqrt(r_eff) * overlap**1.5
    return magnitude[..., None] * d / np.maximum(dist, 1e-300)[..., None]
