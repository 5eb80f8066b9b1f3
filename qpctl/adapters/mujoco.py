"""Run any qpctl controller in MuJoCo.

**The model.** :func:`robot_mjcf` writes an MJCF of a :class:`~qpctl.robot.model.RobotModel`
straight from its Pinocchio model: one body per joint, placed by Pinocchio's joint placement, with
Pinocchio's mass, centre of mass and rotational inertia (``fullinertia``), the same joint axes and
the model's gravity; no damping, armature or friction. For the planar arm that is the paper's arm;
for the Panda it is the URDF as Pinocchio reads it, fingers locked exactly as
:func:`qpctl.robot.panda` locks them (their inertia lumped into link 7 by Pinocchio's reduced model).
We generate from Pinocchio rather than compile the URDF with MuJoCo because (i) one code path then
serves every robot qpctl can load, planar arms included, (ii) what MuJoCo integrates is by
construction the model the controller believes in — no imported URDF damping or friction, no
different lumping of fixed links — so any disagreement is the integrator's, and (iii) the test
suite still checks it independently: M(q) and the bias forces from MuJoCo (``mj_fullM``,
``qfrc_bias``) against Pinocchio's on random states, and for the Panda also against MuJoCo's own
compilation of the mesh-stripped URDF.

Obstacles become geoms (moving ones on mocap bodies, moved every step) and the links carry their
collision capsules as geoms, all with ``contype = conaffinity = 0`` and contacts disabled: MuJoCo
never pushes the arm; clearance and distances are qpctl's own, as in the built-in simulator.
Joint limits are off by default, as in the built-in simulator (the closed-form laws do not know
them); ``joint_limits=True`` turns them into MuJoCo's hard limit constraints.

**The loop.** :class:`MujocoSimulator` reads ``qpos``/``qvel`` through a :class:`MujocoJoints`
map (joint names matched by :class:`~qpctl.adapters.joint_map.JointMap`), calls
``controller.step(q, v, t)``, writes the torque into ``qfrc_applied`` and calls ``mj_step``.
``qfrc_applied`` rather than actuators: it is the generalised force itself — no gain, bias, gear or
``ctrlrange`` clamping in between — so any MJCF can be driven by a torque controller without
editing its actuators (MuJoCo Menagerie's Panda, for one, has position servos), and it persists
until overwritten, so the torque is held over the whole step.

**Integrators.** With ``integrator="rk4"`` (``mjINT_RK4``) MuJoCo runs the same classical
four-stage Runge–Kutta as :func:`qpctl.simulation.simulator.rk4_step`, and, like ours, holds the
applied force constant over all four stages (zero-order hold over the control period). What
differs is bookkeeping: stage 1 reuses the accelerations of the ``mj_forward`` that ``mj_step``
runs at the start state, stages 2–4 call ``mj_forwardSkip``; accelerations come from MuJoCo's
composite-rigid-body M and its LDLᵀ factorisation instead of Pinocchio's ABA; positions are
integrated by ``mj_integratePos`` (identical for hinges). So the two simulators differ by
round-off — amplified by the closed loop — not by a method error (see ``tests/test_mujoco.py``).
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from collections.abc import Sequence
from typing import Any

import numpy as np
import pinocchio as pin

from qpctl.adapters.joint_map import JointMap
from qpctl.controllers.base import Controller
from qpctl.errors import ConfigError, SimulationError
from qpctl.geometry.obstacles import Obstacle, rotation_z_to
from qpctl.robot.model import RobotModel
from qpctl.simulation.simulator import Trajectory, check_ticks, finish_trajectory, measured_self_pairs
from qpctl.tick import WorldClearance

try:
    import mujoco
except ImportError as exc:  # pragma: no cover - exercised only without the extra
    raise ImportError("the MuJoCo adapter needs MuJoCo: pip install 'qpctl[mujoco]' (or pip install mujoco)"
                      ) from exc

INTEGRATORS = {
    "rk4": "RK4",
    "euler": "Euler",
    "implicit": "implicit",
    "implicitfast": "implicitfast",
}

_AXES = {"X": (1.0, 0.0, 0.0), "Y": (0.0, 1.0, 0.0), "Z": (0.0, 0.0, 1.0)}
_REVOLUTE = {f"JointModelR{k}": axis for k, axis in _AXES.items()}
_PRISMATIC = {f"JointModelP{k}": axis for k, axis in _AXES.items()}


def _fmt(values: Sequence[float] | np.ndarray) -> str:
    return " ".join(f"{float(v):.17g}" for v in np.asarray(values, float).reshape(-1))


def _quat(rotation: np.ndarray) -> np.ndarray:
    """(w, x, y, z) of a rotation matrix."""
    q = np.zeros(4)
    mujoco.mju_mat2Quat(q, np.asarray(rotation, float).reshape(9))
    return q


def _joint_type_axis(joint: Any) -> tuple[str, np.ndarray]:
    kind = joint.shortname()
    if kind in _REVOLUTE:
        return "hinge", np.array(_REVOLUTE[kind])
    if kind in _PRISMATIC:
        return "slide", np.array(_PRISMATIC[kind])
    if kind == "JointModelRevoluteUnaligned":
        return "hinge", np.asarray(joint.extract().axis, float)
    if kind == "JointModelPrismaticUnaligned":
        return "slide", np.asarray(joint.extract().axis, float)
    raise ConfigError(f"joint type {kind} has no MuJoCo counterpart here (revolute and prismatic only)",
                      key="robot")


def _body_name(model: pin.Model, joint_id: int) -> str:
    for f in model.frames:
        if f.parentJoint == joint_id and f.type == pin.FrameType.BODY and f.placement.isIdentity():
            return str(f.name)
    return f"{model.names[joint_id]}_body"


def _obstacle_geom(parent: ET.Element, obstacle: Obstacle, name: str, at_origin: bool) -> None:
    """A geom for ``obstacle``; at the parent's origin (mocap body) or at its initial position."""
    attrs = {"name": name, "contype": "0", "conaffinity": "0", "group": "1", "rgba": "0.45 0.6 0.3 0.6"}
    if not at_origin:
        attrs["pos"] = _fmt(obstacle.position)
    if obstacle.shape == "sphere":
        attrs.update(type="sphere", size=_fmt([obstacle.radius]))
    elif obstacle.shape == "box":
        assert obstacle.size is not None
        attrs.update(type="box", size=_fmt(np.asarray(obstacle.size) / 2))
    else:  # capsule / cylinder: axis along the obstacle's axis, size = (radius, half-length)
        attrs.update(type=obstacle.shape, size=_fmt([obstacle.radius, obstacle.length / 2]),
                     quat=_fmt(_quat(rotation_z_to(obstacle.axis))))
    ET.SubElement(parent, "geom", attrs)


def robot_mjcf(robot: RobotModel, obstacles: Sequence[Obstacle] = (), *, timestep: float = 1e-3,
               integrator: str = "rk4", joint_limits: bool = False) -> str:
    """MJCF text of ``robot`` (from its Pinocchio model) in a scene of ``obstacles``.

    Joints are named ``robot.joint_names``; the task point is a site named after ``robot.ee_frame``;
    link capsules and obstacles are contact-free geoms (see the module docstring).

    Args:
        robot: the robot model.
        obstacles: the scene; moving obstacles go on mocap bodies named after them.
        timestep: MuJoCo's step [s].
        integrator: ``"rk4"`` (default), ``"euler"``, ``"implicit"`` or ``"implicitfast"``.
        joint_limits: give the joints their ``robot.q_min``/``q_max`` ranges as hard limits.
    """
    if integrator not in INTEGRATORS:
        raise ConfigError(f"unknown MuJoCo integrator {integrator!r}; one of {', '.join(INTEGRATORS)}",
                          key="sim.integrator")
    if not (np.isfinite(timestep) and timestep > 0):
        raise ConfigError(f"must be a positive number of seconds, got {timestep}", key="sim.dt")
    model = robot.model
    root = ET.Element("mujoco", {"model": robot.name})
    ET.SubElement(root, "compiler", {"angle": "radian", "inertiafromgeom": "false", "autolimits": "true"})
    option = ET.SubElement(root, "option", {"timestep": f"{timestep:.17g}",
                                            "integrator": INTEGRATORS[integrator],
                                            "gravity": _fmt(model.gravity.linear)})
    flags = {"contact": "disable"}
    if not joint_limits:
        flags["constraint"] = "disable"
    ET.SubElement(option, "flag", flags)
    world = ET.SubElement(root, "worldbody")
    ET.SubElement(world, "light", {"pos": "0 0 3", "dir": "0 0 -1", "directional": "true"})

    bodies: dict[int, ET.Element] = {0: world}
    for j in range(1, model.njoints):
        placement = model.jointPlacements[j]
        body = ET.SubElement(bodies[model.parents[j]], "body", {
            "name": _body_name(model, j), "pos": _fmt(placement.translation),
            "quat": _fmt(_quat(placement.rotation))})
        bodies[j] = body
        inertia = model.inertias[j]
        if not inertia.mass > 0:
            raise ConfigError(f"joint {model.names[j]} moves a body without mass; MuJoCo cannot simulate it",
                              key="robot")
        ic = inertia.inertia  # rotational inertia about the COM, body axes [kg·m²]
        full = [ic[0, 0], ic[1, 1], ic[2, 2], ic[0, 1], ic[0, 2], ic[1, 2]]  # MJCF's order
        ET.SubElement(body, "inertial", {"pos": _fmt(inertia.lever), "mass": f"{inertia.mass:.17g}",
                                         "fullinertia": _fmt(full)})
        jtype, axis = _joint_type_axis(model.joints[j])
        jattrs = {"name": robot.joint_names[j - 1], "type": jtype, "axis": _fmt(axis)}
        i = model.joints[j].idx_v
        if joint_limits and np.isfinite(robot.q_min[i]) and np.isfinite(robot.q_max[i]):
            jattrs["range"] = _fmt([robot.q_min[i], robot.q_max[i]])
        ET.SubElement(body, "joint", jattrs)
    for k, cap in enumerate(robot.capsules):
        attrs = {"name": f"capsule{k}_{cap.name}", "contype": "0", "conaffinity": "0", "group": "2",
                 "rgba": "0.9 0.55 0.1 0.5", "size": f"{cap.radius:.17g}"}
        if np.linalg.norm(np.asarray(cap.p1) - np.asarray(cap.p0)) > 1e-9:
            attrs.update(type="capsule", fromto=_fmt(np.concatenate([cap.p0, cap.p1])))
        else:
            attrs.update(type="sphere", pos=_fmt(cap.p0))
        ET.SubElement(bodies[cap.joint_id], "geom", attrs)
    ee = model.frames[robot.ee_frame_id]
    ET.SubElement(bodies[ee.parentJoint], "site", {"name": robot.ee_frame, "size": "0.01", "rgba": "1 0 0 1",
                                                    "pos": _fmt(ee.placement.translation)})
    for i, obs in enumerate(obstacles):
        name = obs.name or f"obstacle{i}"
        if obs.moving:
            mocap = ET.SubElement(world, "body", {"name": name, "mocap": "true", "pos": _fmt(obs.position)})
            _obstacle_geom(mocap, obs, f"{name}_geom", at_origin=True)
        else:
            _obstacle_geom(world, obs, name, at_origin=False)
    ET.indent(root)
    return ET.tostring(root, encoding="unicode")


def build_model(robot: RobotModel, obstacles: Sequence[Obstacle] = (), **kwargs: Any) -> mujoco.MjModel:
    """Compile :func:`robot_mjcf` (same arguments) into a ``mujoco.MjModel``."""
    xml = robot_mjcf(robot, obstacles, **kwargs)
    try:
        return mujoco.MjModel.from_xml_string(xml)
    except ValueError as exc:
        raise ConfigError(f"MuJoCo rejected the generated model of {robot.name}: {exc}", key="robot") from exc


def full_inertia(model: mujoco.MjModel, data: mujoco.MjData) -> np.ndarray:
    """Dense joint-space inertia M(q) (nv, nv) [kg·m²] of the last ``mj_forward``/``mj_step``."""
    M = np.zeros((model.nv, model.nv))
    try:
        mujoco.mj_fullM(model, data, M)  # MuJoCo ≥ 4
    except TypeError:
        mujoco.mj_fullM(model, M, data.qM)  # MuJoCo 3
    return M


class MujocoJoints:
    """Where the model's joints live in a MuJoCo model: ``qpos``/``qvel``/``qfrc`` addresses.

    Built from joint names (:class:`JointMap`), so the MJCF may order or name its other joints as it
    likes; only hinge and slide joints can stand for the model's revolute/prismatic joints.
    """

    def __init__(self, mj_model: mujoco.MjModel, joint_names: Sequence[str], *, allow_extra: bool = False):
        sim_names = [mj_model.joint(i).name for i in range(mj_model.njnt)]
        self.map = JointMap.from_names(sim_names, joint_names, allow_extra=allow_extra)
        ids = self.map.sim_index
        scalar = (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE))
        bad = [sim_names[i] for i in ids if int(mj_model.jnt_type[i]) not in scalar]
        if bad:
            raise ConfigError(f"MuJoCo joints {', '.join(bad)} are not hinge or slide joints",
                              key="joint_map")
        self.qpos_adr = np.asarray(mj_model.jnt_qposadr[ids], int)
        self.dof_adr = np.asarray(mj_model.jnt_dofadr[ids], int)

    @classmethod
    def for_robot(cls, mj_model: mujoco.MjModel, robot: RobotModel, *,
                  allow_extra: bool = False) -> MujocoJoints:
        return cls(mj_model, robot.joint_names, allow_extra=allow_extra)

    def read(self, data: mujoco.MjData) -> tuple[np.ndarray, np.ndarray]:
        """(q [rad], v [rad/s]) in the model's joint order."""
        return data.qpos[self.qpos_adr].copy(), data.qvel[self.dof_adr].copy()

    def write_state(self, data: mujoco.MjData, q: np.ndarray, v: np.ndarray) -> None:
        data.qpos[self.qpos_adr] = q
        data.qvel[self.dof_adr] = v

    def apply(self, data: mujoco.MjData, tau: np.ndarray) -> None:
        """Set the generalised force ``qfrc_applied`` [N·m] of the model's joints (held until changed)."""
        data.qfrc_applied[self.dof_adr] = tau

    def select(self, matrix: np.ndarray) -> np.ndarray:
        """Rows and columns of a (nv, nv) MuJoCo matrix in the model's joint order (e.g. M(q))."""
        return matrix[np.ix_(self.dof_adr, self.dof_adr)]


class MujocoSimulator:
    """Runs a controller in MuJoCo and records the same :class:`Trajectory` as the built-in simulator.

    Args:
        controller: any :class:`~qpctl.controllers.base.Controller`.
        dt: MuJoCo's step and the control period [s] (one controller call per ``mj_step``).
        duration: simulated time [s].
        integrator: ``"rk4"`` (default, as the built-in simulator), ``"euler"`` (semi-implicit),
            ``"implicit"`` or ``"implicitfast"``.
        progress: show a tqdm progress bar.
        joint_limits: enforce ``robot.q_min``/``q_max`` as MuJoCo limit constraints (generated model only).
        model: your own ``mujoco.MjModel`` instead of the generated one; its joints are matched to
            ``robot.joint_names`` by name, and its timestep and integrator are replaced by ``dt`` and
            ``integrator``.
        allow_extra_joints: with ``model``, leave joints the robot does not have undriven.
    """

    def __init__(self, controller: Controller, *, dt: float = 1e-3, duration: float = 5.0,
                 integrator: str = "rk4", progress: bool = False, joint_limits: bool = False,
                 model: mujoco.MjModel | None = None, allow_extra_joints: bool = False) -> None:
        if not (np.isfinite(duration) and duration > 0):
            raise ConfigError(f"must be a positive number of seconds, got {duration}", key="sim.duration")
        check_ticks(duration, dt)
        self.controller = controller
        self.robot = controller.robot
        self.dt = float(dt)
        self.duration = float(duration)
        self.progress = progress
        if model is None:
            model = build_model(self.robot, controller.obstacles, timestep=self.dt, integrator=integrator,
                                joint_limits=joint_limits)
        else:
            if integrator not in INTEGRATORS:
                raise ConfigError(f"unknown MuJoCo integrator {integrator!r}; one of "
                                  f"{', '.join(INTEGRATORS)}", key="sim.integrator")
            if not (np.isfinite(dt) and dt > 0):
                raise ConfigError(f"must be a positive number of seconds, got {dt}", key="sim.dt")
            model.opt.timestep = self.dt
            model.opt.integrator = getattr(mujoco.mjtIntegrator, f"mjINT_{INTEGRATORS[integrator].upper()}")
        self.model = model
        self.data = mujoco.MjData(model)
        self.joints = MujocoJoints.for_robot(model, self.robot, allow_extra=allow_extra_joints)
        self._mocap = []
        for i, obs in enumerate(controller.obstacles):
            if obs.moving:
                bid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, obs.name or f"obstacle{i}")
                if bid >= 0 and model.body_mocapid[bid] >= 0:
                    self._mocap.append((int(model.body_mocapid[bid]), obs))
        self._world = WorldClearance(self.robot, controller.obstacles, measured_self_pairs(controller))

    def clearance(self, q: np.ndarray, t: float) -> float:
        """Exact least link–obstacle distance [m] at (q, t), as the built-in simulator measures it."""
        return self._world(q, t)

    def _move_obstacles(self, t: float) -> None:
        for mocap_id, obs in self._mocap:
            self.data.mocap_pos[mocap_id] = obs.position_at(t)

    def _diverged(self) -> bool:
        # MuJoCo resets a diverged state silently (with a warning count) instead of returning NaN.
        w = mujoco.mjtWarning
        bad = (w.mjWARN_BADQACC, w.mjWARN_BADQPOS, w.mjWARN_BADQVEL)
        return any(self.data.warning[w].number > 0 for w in bad) or not (
            np.all(np.isfinite(self.data.qpos)) and np.all(np.isfinite(self.data.qvel)))

    def reset(self, q0: np.ndarray, v0: np.ndarray | None = None) -> None:
        """Put MuJoCo at (q0, v0) at t = 0, zero applied force, and run ``mj_forward``."""
        mujoco.mj_resetData(self.model, self.data)
        q0 = np.asarray(q0, float)
        if q0.shape != (self.robot.nv,):
            raise ConfigError(f"q0 needs {self.robot.nv} joint values, got {q0.size}", key="robot.q0")
        v0 = np.zeros(self.robot.nv) if v0 is None else np.asarray(v0, float)
        self.joints.write_state(self.data, q0, v0)
        self._move_obstacles(0.0)
        mujoco.mj_forward(self.model, self.data)

    def run(self, q0: np.ndarray, v0: np.ndarray | None = None) -> Trajectory:
        """Simulate from (q0 [rad], v0 [rad/s]) at t = 0 for ``duration``; one controller tick per step."""
        self.reset(q0, v0)
        n, m = self.robot.nv, self.robot.m
        steps = round(self.duration / self.dt) + 1
        rec = {k: np.zeros((steps, n)) for k in ("q", "v", "tau", "e_null")}
        rec.update({k: np.zeros((steps, m)) for k in ("x", "x_ref", "xd_ref", "xdd_ref")})
        t_arr, clear, tick_us = np.zeros(steps), np.zeros(steps), np.zeros(steps)
        self_clear = np.full(steps, np.inf)
        singular = np.zeros(steps, bool)
        infos: list[dict[str, Any]] = []
        ctrl, data = self.controller, self.data
        if ctrl.warm:  # kernels loaded, workspace built, solver set up: not in the first tick
            ctrl.reset()
        else:
            ctrl.warmup()  # (ends in reset())
        iterator: Any = range(steps)
        if self.progress:
            from tqdm import tqdm

            iterator = tqdm(iterator, desc=f"mujoco {ctrl.kind}", unit="tick", leave=False)
        for k in iterator:
            t = k * self.dt
            q, v = self.joints.read(data)
            out = ctrl.step(q, v, t)
            tau = out.tau
            if not np.all(np.isfinite(tau)):
                raise SimulationError(f"controller {ctrl.kind} returned non-finite torque at t = {t:.4f} s")
            t_arr[k] = t
            rec["q"][k], rec["v"][k], rec["tau"][k], rec["e_null"][k] = q, v, tau, out.e_null
            rec["x"][k], rec["x_ref"][k] = out.x, out.ref.x
            rec["xd_ref"][k], rec["xdd_ref"][k] = out.ref.xd, out.ref.xdd
            clear[k] = self.clearance(q, t)
            self_clear[k] = self._world.self_clearance
            tick_us[k] = out.compute_us
            singular[k] = out.singular
            infos.append(out.info)
            if k + 1 < steps:
                self.joints.apply(data, tau)  # zero-order hold: qfrc_applied stays for all RK4 stages
                data.time = t
                mujoco.mj_step(self.model, data)
                self._move_obstacles(t + self.dt)
                if self._diverged():
                    raise SimulationError(f"MuJoCo state diverged at t = {t + self.dt:.4f} s")
        traj = Trajectory(t_arr, rec["q"], rec["v"], rec["tau"], rec["x"], rec["x_ref"], rec["xd_ref"],
                          rec["xdd_ref"], clear, rec["e_null"], tick_us, singular, infos)
        if len(self._world.ws.sc_pairs):
            traj.self_clearance = self_clear
        return finish_trajectory(traj, ctrl)
