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

import copy
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin

from qpctl.adapters.joint_map import JointMap
from qpctl.adapters.model_check import DynamicsCheck, check_dynamics
from qpctl.controllers.base import Controller
from qpctl.errors import ConfigError, SimulationError
from qpctl.geometry.obstacles import Obstacle
from qpctl.robot.model import RobotModel
from qpctl.simulation.loop import SimulatorBase
from qpctl.simulation.trajectory import Trajectory

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
    if kind.startswith("JointModelRUB") and kind[-1] in _AXES:  # continuous: an unlimited hinge
        return "hinge", np.array(_AXES[kind[-1]])
    if kind in ("JointModelRevoluteUnaligned", "JointModelRevoluteUnboundedUnaligned"):
        return "hinge", np.asarray(joint.extract().axis, float)
    if kind == "JointModelPrismaticUnaligned":
        return "slide", np.asarray(joint.extract().axis, float)
    raise ConfigError(f"joint type {kind} has no MuJoCo counterpart here (revolute, continuous and prismatic "
                      "only; write a planar base as two slides and a hinge)", key="robot")


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
    geom = obstacle.kind.mujoco_geom(obstacle)  # the shape's own (qpctl.geometry.shapes)
    attrs.update(type=geom.type, size=_fmt(geom.size))
    if geom.rotation is not None:
        attrs["quat"] = _fmt(_quat(geom.rotation))
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


def scene_caster(camera: Any) -> Any:
    """A depth camera's (:class:`~qpctl.simulation.camera.DepthCamera`) ``mj_multiRay`` caster on a
    MuJoCo model of its own scene (:func:`build_model`: the robot, the obstacles and the scenery)."""
    from qpctl.adapters.mujoco_camera import MujocoCaster

    model = build_model(camera.robot, [*camera.obstacles, *camera.scenery])
    return MujocoCaster(model, MujocoJoints.for_robot(model, camera.robot), camera)


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

    Built from joint names (:class:`JointMap`): ``joint_names`` are the MuJoCo model's names of the
    controller's joints, in the controller's order (``robot.joint_names`` when the MJCF uses the same
    names), so the MJCF may order or name its joints as it likes; only hinge and slide joints can
    stand for the model's revolute/prismatic joints.
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
        self.jnt_ids = np.asarray(ids, int)
        self.names = tuple(str(n) for n in joint_names)
        self.qpos_adr = np.asarray(mj_model.jnt_qposadr[ids], int)
        self.dof_adr = np.asarray(mj_model.jnt_dofadr[ids], int)
        # the controller's robot where its configuration is not its hinges' angles (continuous joints:
        # Pinocchio's cos θ, sin θ); read and write_state convert (set by for_robot)
        self.robot: RobotModel | None = None

    @classmethod
    def for_robot(cls, mj_model: mujoco.MjModel, robot: RobotModel, *,
                  allow_extra: bool = False) -> MujocoJoints:
        return cls(mj_model, robot.joint_names, allow_extra=allow_extra).on(robot)

    def on(self, robot: RobotModel) -> MujocoJoints:
        """These joints with ``robot``'s configurations (converted to and from the hinges' angles
        where nq ≠ nv); itself."""
        self.robot = robot if robot.lie else None
        return self

    @classmethod
    def by_order(cls, mj_model: mujoco.MjModel, n: int) -> MujocoJoints:
        """The model's hinge and slide joints in their MJCF order, which must be exactly ``n``."""
        scalar = (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE))
        names = [mj_model.joint(i).name for i in range(mj_model.njnt) if int(mj_model.jnt_type[i]) in scalar]
        if len(names) != n or mj_model.njnt != n:
            raise ConfigError(f"cannot match joints by order: the MuJoCo model has {mj_model.njnt} joints "
                              f"({len(names)} hinge/slide: {', '.join(names)}), the robot {n}; name them "
                              "with sim.joint_names", key="sim.joint_names")
        return cls(mj_model, names)

    def read(self, data: mujoco.MjData) -> tuple[np.ndarray, np.ndarray]:
        """(q (the robot's configuration), v [rad/s]) in the model's joint order."""
        q = data.qpos[self.qpos_adr].copy()
        return (q if self.robot is None else self.robot.configuration(q)), data.qvel[self.dof_adr].copy()

    def write_state(self, data: mujoco.MjData, q: np.ndarray, v: np.ndarray) -> None:
        data.qpos[self.qpos_adr] = q if self.robot is None else self.robot.angles(q)
        data.qvel[self.dof_adr] = v

    def apply(self, data: mujoco.MjData, tau: np.ndarray) -> None:
        """Set the generalised force ``qfrc_applied`` [N·m] of the model's joints (held until changed)."""
        data.qfrc_applied[self.dof_adr] = tau

    def select(self, matrix: np.ndarray) -> np.ndarray:
        """Rows and columns of a (nv, nv) MuJoCo matrix in the model's joint order (e.g. M(q))."""
        return matrix[np.ix_(self.dof_adr, self.dof_adr)]


_KIND = {  # (gain type, bias type) → what the actuator is, as MJCF's shortcuts make it
    ("FIXED", "NONE"): "motor",
    ("FIXED", "AFFINE"): "servo",  # position (bias −kp q − kv q̇), velocity (−kv q̇), intvelocity
}


class MujocoActuation:
    """How the controller's torque reaches the joints of a MuJoCo model.

    * A joint driven by a **motor** actuator (gain type fixed, no bias, no activation dynamics,
      ``<motor>`` in MJCF) gets its torque through ``ctrl``: ctrl = τ / (gain · gear), clamped to
      ``ctrlrange`` (and the force to ``forcerange``) as MuJoCo would; the ticks at which that
      changed the torque are counted (``ctrl_clamped_ticks``), never hidden.
    * Any other actuator on one of the controller's joints (position/velocity servos, filters,
      muscles) would fight the controller: its gains and bias are set to zero in this copy of the
      model, and a note says so.
    * Joints without a motor get their torque through ``qfrc_applied``.

    Actuators on joints the controller does not drive (a gripper's) are left as they are.
    """

    def __init__(self, model: mujoco.MjModel, joints: MujocoJoints) -> None:
        self.notes: list[str] = []
        n = len(joints.dof_adr)
        by_joint = {int(j): i for i, j in enumerate(joints.jnt_ids)}
        motor_idx, motor_ids, scale = [], [], []
        for a in range(model.nu):
            name = model.actuator(a).name or f"actuator{a}"
            trn = int(model.actuator_trntype[a])
            if trn not in (int(mujoco.mjtTrn.mjTRN_JOINT), int(mujoco.mjtTrn.mjTRN_JOINTINPARENT)):
                self.notes.append(f"actuator {name} (transmission {mujoco.mjtTrn(trn).name}) left as it is")
                continue
            jid = int(model.actuator_trnid[a, 0])
            if jid not in by_joint:
                continue  # not one of the controller's joints: left alone
            i = by_joint[jid]
            gain = mujoco.mjtGain(int(model.actuator_gaintype[a])).name.removeprefix("mjGAIN_")
            bias = mujoco.mjtBias(int(model.actuator_biastype[a])).name.removeprefix("mjBIAS_")
            dyn = int(model.actuator_dyntype[a])
            kind = _KIND.get((gain, bias), "other") if dyn == int(mujoco.mjtDyn.mjDYN_NONE) else "other"
            gear = float(model.actuator_gear[a, 0])
            if kind == "motor" and i not in motor_idx and gear * model.actuator_gainprm[a, 0] != 0:
                motor_idx.append(i)
                motor_ids.append(a)
                scale.append(gear * float(model.actuator_gainprm[a, 0]))
                continue
            what = {"servo": f"a servo: kp = {-model.actuator_biasprm[a, 1]:.4g}, kv = "
                             f"{-model.actuator_biasprm[a, 2]:.4g}",
                    "motor": "a second motor on the joint"}.get(kind, f"gain {gain}, bias {bias}, dynamics "
                                                                    f"{mujoco.mjtDyn(dyn).name}")
            model.actuator_gainprm[a, :] = 0.0
            model.actuator_biasprm[a, :] = 0.0
            self.notes.append(f"actuator {name} on joint {joints.names[i]} switched off ({what}): it would "
                              "fight the torque controller")
        self.motor_idx = np.asarray(motor_idx, int)
        self.motor_ids = np.asarray(motor_ids, int)
        self.scale = np.asarray(scale, float)
        self.ctrl_lo = np.where(model.actuator_ctrllimited[self.motor_ids] > 0,
                                model.actuator_ctrlrange[self.motor_ids, 0], -np.inf)
        self.ctrl_hi = np.where(model.actuator_ctrllimited[self.motor_ids] > 0,
                                model.actuator_ctrlrange[self.motor_ids, 1], np.inf)
        gain = model.actuator_gainprm[self.motor_ids, 0]
        f_lo = np.where(model.actuator_forcelimited[self.motor_ids] > 0,
                        model.actuator_forcerange[self.motor_ids, 0], -np.inf)
        f_hi = np.where(model.actuator_forcelimited[self.motor_ids] > 0,
                        model.actuator_forcerange[self.motor_ids, 1], np.inf)
        # the force range as a range of ctrl (force = gain · ctrl)
        with np.errstate(divide="ignore", invalid="ignore"):
            a_lo, a_hi = f_lo / gain, f_hi / gain
        self.ctrl_lo = np.maximum(self.ctrl_lo, np.where(gain > 0, a_lo, a_hi))
        self.ctrl_hi = np.minimum(self.ctrl_hi, np.where(gain > 0, a_hi, a_lo))
        self.free_idx = np.setdiff1d(np.arange(n), self.motor_idx)
        self.free_dofs = joints.dof_adr[self.free_idx]
        self.clamped_ticks = 0
        self.clamped_joints: set[str] = set()
        self._names = joints.names
        if len(self.motor_ids):
            self.notes.append("torque through the motor actuators' ctrl (gear and gain: "
                              + ", ".join(f"{joints.names[i]} × {s:.4g}" for i, s in zip(self.motor_idx, self.scale))
                              + ")")

    def apply(self, data: mujoco.MjData, tau: np.ndarray) -> None:
        """Hold ``tau`` [N·m] (controller's order): motors' ``ctrl``, the other joints' ``qfrc_applied``."""
        if len(self.motor_ids):
            ctrl = tau[self.motor_idx] / self.scale
            held = np.clip(ctrl, self.ctrl_lo, self.ctrl_hi)
            if np.any(held != ctrl):
                self.clamped_ticks += 1
                self.clamped_joints.update(self._names[i] for i in self.motor_idx[held != ctrl])
            data.ctrl[self.motor_ids] = held
        data.qfrc_applied[self.free_dofs] = tau[self.free_idx]

    def reset(self) -> None:
        self.clamped_ticks = 0
        self.clamped_joints = set()


def _geom_type(name: str, shape: str) -> Any:
    """MuJoCo's geom type called ``name`` ("sphere", "box", ...); ConfigError for one it lacks."""
    kind = getattr(mujoco.mjtGeom, f"mjGEOM_{name.upper()}", None)
    if kind is None:
        raise ConfigError(f"shape {shape!r} gives MuJoCo geom type {name!r}, which MuJoCo does not have",
                          key="obstacles.shape")
    return kind


def _add_obstacles(spec: Any, obstacles: Sequence[Obstacle], prefix: str) -> None:
    """Contact-free geoms for ``obstacles`` in a user's model (MjSpec); moving ones on mocap bodies."""
    for i, obs in enumerate(obstacles):
        name = f"{prefix}{obs.name or f'obstacle{i}'}"
        if obs.moving:
            parent = spec.worldbody.add_body(name=name, mocap=True, pos=np.asarray(obs.position, float))
            pos = np.zeros(3)
        else:
            parent, pos = spec.worldbody, np.asarray(obs.position, float)
        geom = obs.kind.mujoco_geom(obs)  # the shape's own (qpctl.geometry.shapes)
        size = [*geom.size, *[0.0] * (3 - len(geom.size))]
        quat = list(_quat(geom.rotation)) if geom.rotation is not None else [1.0, 0.0, 0.0, 0.0]
        parent.add_geom(name=f"{name}_geom" if obs.moving else name, type=_geom_type(geom.type, obs.shape),
                        size=size, pos=pos, quat=quat, contype=0, conaffinity=0, group=1, rgba=[0.45, 0.6, 0.3, 0.6])


def servos_to_motors(spec: Any, joints: Sequence[str]) -> str | None:
    """Turn the position and velocity servos (and other affine-bias actuators) on ``joints`` into
    motors (``actuator.set_to_motor()``): torque = gear × ctrl, still clamped by ``forcerange``; their
    ``ctrlrange`` — a position or a speed — no longer limits it. Returns the one-line note, or None."""
    names = set(joints)
    changed = []
    for act in spec.actuators:
        if act.trntype not in (mujoco.mjtTrn.mjTRN_JOINT, mujoco.mjtTrn.mjTRN_JOINTINPARENT) or act.target not in names:
            continue
        if act.biastype == mujoco.mjtBias.mjBIAS_AFFINE and act.dyntype in (mujoco.mjtDyn.mjDYN_NONE,
                                                                             mujoco.mjtDyn.mjDYN_INTEGRATOR):
            kp, kv = -act.biasprm[1], -act.biasprm[2]
            changed.append(f"{act.name or act.target} (kp {kp:.4g}, kv {kv:.4g})")
            act.set_to_motor()
            act.dyntype = mujoco.mjtDyn.mjDYN_NONE
            act.ctrllimited = mujoco.mjtLimited.mjLIMITED_FALSE
    if not changed:
        return None
    return (f"{len(changed)} servo{'s' if len(changed) > 1 else ''} turned into motors (MjSpec set_to_motor; "
            f"forcerange kept, ctrlrange dropped): {', '.join(changed)}")


def load_user_model(path: str | Path, obstacles: Sequence[Obstacle] = (), *, motor_joints: Sequence[str] = (),
                    notes: list[str] | None = None, key: str = "sim.model") -> mujoco.MjModel:
    """Compile the user's MJCF (or URDF) at ``path`` with ``obstacles`` added as contact-free geoms
    (bodies and geoms named ``qpctl_<obstacle name>``), servos on ``motor_joints`` turned into motors
    (:func:`servos_to_motors`, its note appended to ``notes``)."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"MuJoCo model not found: {path}", key=key)
    try:
        spec = mujoco.MjSpec.from_file(str(path))
        _add_obstacles(spec, obstacles, "qpctl_")
        note = servos_to_motors(spec, motor_joints)
        if note is not None and notes is not None:
            notes.append(note)
        return spec.compile()
    except ValueError as exc:
        raise ConfigError(f"MuJoCo rejected {path}: {' '.join(str(exc).split())}", key=key) from None


class MujocoSimulator(SimulatorBase):
    """Runs a controller in MuJoCo and records the same :class:`Trajectory` as the built-in simulator.

    Args:
        controller: any :class:`~qpctl.controllers.base.Controller`.
        dt: MuJoCo's step and the control period [s] (one controller call per ``mj_step``).
        duration: simulated time [s].
        integrator: ``"rk4"`` (default, as the built-in simulator), ``"euler"`` (semi-implicit),
            ``"implicit"`` or ``"implicitfast"``.
        progress: show a tqdm progress bar.
        joint_limits: enforce joint limits as MuJoCo limit constraints (the generated model gets
            ``robot.q_min``/``q_max``; a user's model keeps its own ranges); off, as in the built-in
            simulator, by default.
        model: your own model instead of the generated one: a path to an MJCF (or URDF) file — the
            scene's obstacles are added to it as contact-free geoms — or a compiled ``mujoco.MjModel``
            (copied; obstacles not added). Its timestep and integrator are replaced by ``dt`` and
            ``integrator``, contacts are switched off, its actuators handled by
            :class:`MujocoActuation`, its dynamics checked against the controller's
            (:func:`~qpctl.adapters.model_check.check_dynamics`; see ``notes``).
        joint_names: with ``model``, the model's names of the controller's joints, in the
            controller's order (default: ``robot.joint_names``; if the model has none of those names,
            its joints are taken in order, which must then pass the dynamics check).
        allow_extra_joints: with ``model``, leave joints the robot does not have undriven.
        obstacles: the true obstacles, where they differ from the controller's map (perceived ones).
        scenery: shapes only a camera sees (a canopy's fruits): geoms in the model, in no clearance.
    """

    name = "mujoco"

    def __init__(self, controller: Controller, *, dt: float = 1e-3, duration: float = 5.0,
                 integrator: str = "rk4", progress: bool = False, joint_limits: bool = False,
                 model: mujoco.MjModel | str | Path | None = None, joint_names: Sequence[str] | None = None,
                 allow_extra_joints: bool = False, obstacles: Sequence[Obstacle] | None = None,
                 scenery: Sequence[Obstacle] = ()) -> None:
        super().__init__(controller, dt=dt, duration=duration, progress=progress, obstacles=obstacles)
        self.robot.check_scalar_joints("MuJoCo")
        if integrator not in INTEGRATORS:
            raise ConfigError(f"unknown MuJoCo integrator {integrator!r}; one of {', '.join(INTEGRATORS)}",
                              key="sim.integrator")
        own = model is not None
        prefix = ""
        mj: mujoco.MjModel
        shown = [*self.obstacles, *scenery]  # scenery after the obstacles: geoms a camera sees
        if model is None:
            mj = build_model(self.robot, shown, timestep=self.dt, integrator=integrator, joint_limits=joint_limits)
        else:
            if isinstance(model, (str, Path)):
                mj = load_user_model(model, shown, motor_joints=joint_names or self.robot.joint_names,
                                     notes=self.notes)
                prefix = "qpctl_"
            else:
                mj = copy.copy(model)
            mj.opt.timestep = self.dt
            mj.opt.integrator = getattr(mujoco.mjtIntegrator, f"mjINT_{INTEGRATORS[integrator].upper()}")
            mj.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONTACT)
            if not joint_limits:
                mj.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_LIMIT)
        self.model: mujoco.MjModel = mj
        self.geom_prefix = prefix  # of the obstacles' geom and body names (a user's model: "qpctl_")
        model = mj
        self.data = mujoco.MjData(model)
        self.joints = (self._match_joints(model, joint_names, allow_extra_joints) if own else
                       MujocoJoints.for_robot(model, self.robot)).on(self.robot)
        self.actuation = MujocoActuation(model, self.joints)
        self.notes.extend(self.actuation.notes)
        self.dynamics: DynamicsCheck | None = None
        if own:
            self._check_model(by_order=joint_names is None and self.joints.names != tuple(self.robot.joint_names))
        self._mocap = []
        for i, obs in enumerate(self.obstacles):
            if obs.moving:
                bid = mujoco.mj_name2id(mj, mujoco.mjtObj.mjOBJ_BODY, prefix + (obs.name or f"obstacle{i}"))
                if bid >= 0 and mj.body_mocapid[bid] >= 0:
                    self._mocap.append((i, int(mj.body_mocapid[bid]), obs))

    @classmethod
    def from_scenario(cls, controller: Controller, scenario: Any, *, progress: bool = False) -> MujocoSimulator:
        """MuJoCo for the scenario's ``[sim]``: ``dt``, ``duration``, ``integrator``, and the user's
        ``model`` (relative to the scenario file's folder) with its ``joint_names`` — by default, for an
        MJCF robot (``robot.kind = "mjcf"``), the robot's own file; the scenario's obstacles (perceived ones
        too) and scenery (a canopy's fruits) in the model."""
        sim = scenario.data["sim"]
        model = scenario.resolve(sim["model"]) if sim["model"] else controller.robot.mjcf  # an MJCF robot's own file
        return cls(controller, dt=sim["dt"], duration=sim["duration"], integrator=sim["integrator"],
                   progress=progress, model=model, joint_names=sim["joint_names"],
                   obstacles=scenario.build_obstacles(), scenery=scenario.scenery())

    def ray_caster(self, camera: Any) -> Any:
        """A depth camera's caster in this simulator's live model (``mujoco.mj_multiRay``;
        :class:`qpctl.adapters.mujoco_camera.MujocoCaster`)."""
        from qpctl.adapters.mujoco_camera import MujocoCaster

        return MujocoCaster(self.model, self.joints, camera, prefix=self.geom_prefix)

    def _match_joints(self, model: mujoco.MjModel, joint_names: Sequence[str] | None,
                      allow_extra: bool) -> MujocoJoints:
        n = self.robot.nv
        if joint_names is not None:
            if len(joint_names) != n:
                raise ConfigError(f"needs {n} names (the model's names of {', '.join(self.robot.joint_names)}), "
                                  f"got {len(joint_names)}", key="sim.joint_names")
            return MujocoJoints(model, joint_names, allow_extra=allow_extra)
        names = {model.joint(i).name for i in range(model.njnt)}
        if any(name in names for name in self.robot.joint_names) or allow_extra:
            return MujocoJoints.for_robot(model, self.robot, allow_extra=allow_extra)
        joints = MujocoJoints.by_order(model, n)
        self.notes.append("joints matched by order: " + ", ".join(
            f"{a} → {b}" for a, b in zip(self.robot.joint_names, joints.names)))
        return joints

    def _check_model(self, by_order: bool) -> None:
        """M(q) and bias forces against the controller's model; passive forces and gravity noted."""
        model, joints = self.model, self.joints
        data = mujoco.MjData(model)

        def terms(q: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            mujoco.mj_resetData(model, data)
            joints.write_state(data, q, v)
            mujoco.mj_forward(model, data)
            return joints.select(full_inertia(model, data)), data.qfrc_bias[joints.dof_adr].copy()

        self.dynamics = check_dynamics(self.robot, terms)
        if by_order and not self.dynamics.same:
            raise ConfigError("joints matched by order, but " + self.dynamics.sentence("the MuJoCo model")
                              + "; name the joints with sim.joint_names (or fix the model)",
                              key="sim.joint_names")
        self.notes.append(self.dynamics.sentence("the MuJoCo model"))
        dofs = joints.dof_adr
        passive = {"damping": model.dof_damping[dofs], "frictionloss": model.dof_frictionloss[dofs],
                   "stiffness": model.jnt_stiffness[joints.jnt_ids]}
        for key, values in passive.items():
            if np.any(values != 0):
                self.notes.append(f"the MuJoCo model's joints have {key} {np.round(values, 6).tolist()}, which "
                                  "the controller's model does not (MuJoCo applies it)")

    def _move_obstacles(self, t: float) -> None:
        for _, mocap_id, obs in self._mocap:
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
        if q0.shape != (self.robot.nq,):
            raise ConfigError(f"q0 needs {self.robot.nq} joint values, got {q0.size}", key="robot.q0")
        v0 = np.zeros(self.robot.nv) if v0 is None else np.asarray(v0, float)
        self.joints.write_state(self.data, q0, v0)
        self._move_obstacles(0.0)
        self.actuation.reset()
        mujoco.mj_forward(self.model, self.data)

    def read(self) -> tuple[np.ndarray, np.ndarray]:
        return self.joints.read(self.data)

    def apply(self, tau: np.ndarray) -> None:
        self.actuation.apply(self.data, tau)  # zero-order hold: ctrl / qfrc_applied stay for all RK4 stages

    def step(self, t: float) -> None:
        self.data.time = t
        mujoco.mj_step(self.model, self.data)
        self._move_obstacles(t + self.dt)
        if self._diverged():
            raise SimulationError(f"MuJoCo state diverged at t = {t + self.dt:.4f} s")

    def obstacle_positions(self) -> np.ndarray:
        """Where MuJoCo holds the obstacles [m]: the mocap bodies' positions for the moving ones."""
        out = np.array([o.position for o in self.obstacles], float).reshape(-1, 3)
        for i, mocap_id, _ in self._mocap:
            out[i] = self.data.mocap_pos[mocap_id]
        return out

    def run(self, q0: np.ndarray, v0: np.ndarray | None = None) -> Trajectory:
        traj = super().run(q0, v0)
        act = self.actuation
        if len(act.motor_ids):
            self.counts["ctrl_clamped_ticks"] = act.clamped_ticks
            if act.clamped_ticks:
                self.notes.append(f"ctrlrange/forcerange clamped the torque on {act.clamped_ticks} ticks "
                                  f"(joints {', '.join(sorted(act.clamped_joints))}): tau records the command")
        return traj
