"""Run any qpctl controller in Drake (``pip install 'qpctl[drake]'``), or put it in your own Drake diagram.

**The plant** (:func:`add_robot`) is parsed from the robot's own URDF (the Panda's from
example-robot-data, any ``robot.kind = "urdf"``), the user's (``sim.model``), or one written from the
Pinocchio model (the planar arm; :func:`qpctl.adapters.urdf.robot_urdf`). What a naive parse gets wrong,
and what is done instead:

* **Collision meshes.** Drake's parser refuses STL collision meshes ("MakeConvexHull only applies to
  .obj, .vtk, and .gltf"): every ``<collision>`` is dropped and qpctl's link capsules
  (``robot.capsules``, the shapes the controller keeps clear) are registered instead, for collision
  and illustration. They never touch each other (filtered within the robot); in a diagram of
  your own they may touch your plant's other geometry.
* **Visuals** stay where their meshes are on this machine: a ``package://NAME/`` URL resolves through
  ``ROS_PACKAGE_PATH`` or a folder NAME above the URDF (example-robot-data's layout); anything else is
  dropped with a note. Drake's remote ``drake_models`` package is removed from the parser's package map:
  nothing is ever fetched at run time.
* **Actuators.** A URDF without ``<transmission>`` elements gets none: each controller joint without
  one gets a ``JointActuator`` (no effort limit) before ``Finalize``. A transmission's actuator is kept
  with its effort limit — Drake clamps the actuation to it, and the ticks where that happened are
  counted (``effort_clamped_ticks``) — and any rotor inertia shows in the dynamics check.
* **The root** link is welded to the world (otherwise Drake adds 6 free DoF); joints the controller
  does not drive (the Panda's fingers) are made fixed, as Pinocchio's reduced model locks them; the
  controller's joints lose their position limits and the URDF's ``<dynamics>`` (damping), which the
  controller's model does not have (a note lists the damping removed); gravity is the robot's.
* **Joint order.** Drake orders positions and velocities by its own tree (on branched robots not
  Pinocchio's): joints are matched by name, each one's ``position_start``/``velocity_start`` and its
  actuator's slot against Pinocchio's ``idx_q``/``idx_v`` order (:class:`DrakeJoints`).

**Obstacles** (:func:`add_obstacles`) are Drake geometry of a source of their own (``qpctl_obstacles``):
static ones anchored, moving ones on frames whose poses :class:`ObstaclePoses` computes from the
context's time, with proximity and illustration roles — a Meshcat visualiser shows them — and their
contact filtered out (Drake never pushes the arm, as no other simulator here does). In a second
context where the capsule–obstacle pairs are allowed, Drake's own signed distance (SceneGraph's query)
measures the run's clearance again beside qpctl's.

**The simulation** (:class:`DrakeSimulator`, ``--sim drake``) steps a continuous ``MultibodyPlant``
with Drake's ``SemiExplicitEulerIntegrator`` in fixed-step mode, one step of ``dt`` per control tick
(v ← v + dt·v̇, q ← q + dt·v: the built-in ``integrator = "euler"``), or a discrete plant
(``discrete=True``, ``time_step = dt``: Drake's SAP model, which without contact is the same scheme).
Drake has no classical RK4; ``sim.integrator = "rk4"`` gets a note. The controller runs in qpctl's
recording loop, its torque fixed on the plant's actuation input for the step (zero-order hold).

**Your own diagram** (:class:`QpctlController`): a ``LeafSystem`` with an ``estimated_state`` input
(the plant's state output of the arm's model instance) and an ``actuation`` output (to the plant's
actuation input of that instance) that calls the controller once per control period.
"""

from __future__ import annotations

import contextlib
import logging
import math
import re
import xml.etree.ElementTree as ET
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from qpctl.adapters.joint_map import JointMap
from qpctl.adapters.model_check import DynamicsCheck, check_simulator
from qpctl.adapters.urdf import prepare_urdf, robot_urdf, urdf_joints
from qpctl.controllers.base import Controller
from qpctl.errors import ConfigError, SimulationError
from qpctl.geometry.obstacles import Obstacle, rotation_z_to
from qpctl.robot.model import RobotModel
from qpctl.simulation.loop import SimulatorBase
from qpctl.simulation.trajectory import Trajectory

try:
    from pydrake.common.value import AbstractValue
    from pydrake.geometry import (
        Box,
        Capsule,
        CollisionFilterDeclaration,
        Cylinder,
        FramePoseVector,
        GeometryFrame,
        GeometryId,
        GeometryInstance,
        GeometrySet,
        MakePhongIllustrationProperties,
        ProximityProperties,
        Role,
        SceneGraph,
        Shape,
        Sphere,
    )
    from pydrake.math import RigidTransform, RotationMatrix
    from pydrake.multibody.parsing import Parser
    from pydrake.multibody.plant import AddMultibodyPlantSceneGraph, CoulombFriction, MultibodyPlant
    from pydrake.multibody.tree import ModelInstanceIndex
    from pydrake.systems.analysis import ResetIntegratorFromFlags, Simulator
    from pydrake.systems.framework import Context, DiagramBuilder, EventStatus, LeafSystem
except ImportError as exc:  # pragma: no cover - exercised only without the extra
    raise ImportError("the Drake adapter needs Drake: pip install 'qpctl[drake]' (or pip install drake)") from exc

CAPSULE_RGBA = np.array([0.9, 0.55, 0.1, 0.5])
OBSTACLE_RGBA = np.array([0.45, 0.6, 0.3, 0.6])


# -- the plant ------------------------------------------------------------------------------------
@contextlib.contextmanager
def _drake_messages(into: list[str]) -> Iterator[None]:
    """Collect what Drake logs (the parser's warnings) into ``into`` instead of printing it."""

    class _Collect(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            into.append(" ".join(record.getMessage().split()))

    logger = logging.getLogger("drake")
    handler, propagate = _Collect(logging.WARNING), logger.propagate
    logger.addHandler(handler)
    logger.propagate = False
    try:
        yield
    finally:
        logger.removeHandler(handler)
        logger.propagate = propagate


def _resolve_visual_meshes(root: ET.Element, parser: Parser, source: Path | None) -> list[str]:
    """Make each visual's mesh a file Drake can open without a network: relative paths made absolute,
    ``package://NAME`` registered when NAME is a folder above the URDF; visuals whose mesh is not on
    this machine are removed. Returns what was removed, one phrase each."""
    packages = parser.package_map()
    if packages.Contains("drake_models"):
        packages.Remove("drake_models")  # a remote package: resolving it downloads
    with _drake_messages([]):  # (it warns of each missing folder of ROS_PACKAGE_PATH)
        packages.PopulateFromRosPackagePath()
    dropped: list[str] = []
    for link in root.iter("link"):
        for visual in list(link.findall("visual")):
            for mesh in visual.iter("mesh"):
                url = mesh.get("filename", "")
                path: Path | None = None
                if url.startswith("package://"):
                    name = url[len("package://"):].split("/", 1)[0]
                    if not packages.Contains(name) and source is not None:
                        above = next((p for p in source.resolve().parents if p.name == name), None)
                        if above is not None:
                            packages.Add(name, str(above))
                    if packages.Contains(name):
                        path = Path(packages.GetPath(name)) / url[len("package://") + len(name) + 1:]
                elif url.startswith("file://"):
                    path = Path(url[len("file://"):])
                elif url:
                    path = Path(url) if Path(url).is_absolute() or source is None else source.parent / url
                    mesh.set("filename", str(path.resolve()))
                if path is None or not path.is_file():
                    link.remove(visual)
                    dropped.append(f"{link.get('name')}'s {url}")
                    break
    return dropped


def _root_link(root: ET.Element) -> str:
    children = {c.get("link") for j in root.iter("joint") for c in j.findall("child")}
    roots = [str(link.get("name")) for link in root.findall("link") if link.get("name") not in children]
    if len(roots) != 1:
        raise ConfigError(f"a URDF needs one root link, found {len(roots)} ({', '.join(roots)})", key="sim.model")
    return roots[0]


def _capsule_shape(p0: np.ndarray, p1: np.ndarray, radius: float) -> tuple[Shape, RigidTransform]:
    """Drake's capsule (or sphere, for a zero-length segment) on p0–p1 [m], and its pose in the frame."""
    axis = np.asarray(p1, float) - np.asarray(p0, float)
    length = float(np.linalg.norm(axis))
    centre = (np.asarray(p0, float) + np.asarray(p1, float)) / 2
    if length <= 1e-9:
        return Sphere(radius), RigidTransform(centre)
    return Capsule(radius, length), RigidTransform(RotationMatrix(rotation_z_to(axis / length)), centre)


def obstacle_shape(obstacle: Obstacle) -> tuple[Shape, RotationMatrix]:
    """Drake's shape for an obstacle (from its MuJoCo geom: sphere, box, capsule, cylinder, all along z)
    and its orientation; :class:`ConfigError` for a shape Drake has no primitive for here."""
    geom = obstacle.kind.mujoco_geom(obstacle)
    size = geom.size
    makers = {"sphere": lambda: Sphere(size[0]), "box": lambda: Box(*(2 * np.asarray(size, float))),
              "capsule": lambda: Capsule(size[0], 2 * size[1]), "cylinder": lambda: Cylinder(size[0], 2 * size[1])}
    if geom.type not in makers:
        raise ConfigError(f"shape {obstacle.shape!r} (MuJoCo geom {geom.type!r}) has no Drake shape here "
                          f"({', '.join(makers)})", key="obstacles.shape")
    rotation = RotationMatrix() if geom.rotation is None else RotationMatrix(np.asarray(geom.rotation, float))
    return makers[geom.type](), rotation


@dataclass
class DrakeRobot:
    """What :func:`add_robot` put into a plant.

    Attributes:
        instance: the robot's model instance.
        joint_names: the plant's names of the controller's joints, in the controller's order.
        by_order: the joints were matched by order (a user's URDF without the controller's names).
        capsule_ids: the link capsules' geometry ids (collision role), as ``robot.capsules``.
        notes: what was changed in the URDF to make it Drake's (one sentence each).
    """

    instance: ModelInstanceIndex
    joint_names: tuple[str, ...]
    by_order: bool
    capsule_ids: list[GeometryId]
    notes: list[str] = field(default_factory=list)


def add_robot(plant: MultibodyPlant, scene_graph: SceneGraph, robot: RobotModel, *,
              model: str | Path | None = None, joint_names: Sequence[str] | None = None) -> DrakeRobot:
    """Add ``robot`` to an unfinalised ``plant`` (module docstring: the URDF's collision meshes replaced
    by ``robot.capsules``, actuators added, the root welded, undriven joints fixed, damping removed,
    gravity set to the robot's). Call ``plant.Finalize()`` afterwards.

    Args:
        plant, scene_graph: from ``AddMultibodyPlantSceneGraph`` (yours, or :class:`DrakeSimulator`'s).
        robot: the controller's robot (``controller.robot``).
        model: a URDF file of your own instead of the robot's.
        joint_names: the URDF's names of the controller's joints, in the controller's order (default
            ``robot.joint_names``; a URDF of your own with none of them: its movable joints in order).

    Raises:
        ConfigError (``sim.model``): a file that is not a URDF or that Drake cannot parse.
    """
    own = model is not None
    source: Path | None
    if model is not None:
        source = Path(model)
        if not source.is_file() or source.suffix.lower() != ".urdf":
            raise ConfigError(f"the Drake adapter needs a URDF file, got {source}"
                              + ("" if source.is_file() else " (not found)"), key="sim.model")
        text = source.read_text()
    elif robot.urdf is not None:
        source, text = robot.urdf, robot.urdf.read_text()
    else:
        source, text = None, robot_urdf(robot)
    joints = urdf_joints(text, robot, joint_names, own=own, source=source)
    notes = [joints.order_note(robot)] if joints.by_order else []
    collisions = re.findall(r"<collision\b", text)
    stl = len(re.findall(r"<collision\b(?:(?!</collision>).)*?\.stl", text, flags=re.DOTALL | re.IGNORECASE))
    root = ET.fromstring(prepare_urdf(text, joints.names, visuals=True))
    for joint in root.iter("joint"):  # ROS's safety controller, and the damping the controller's model lacks
        for extra in joint.findall("safety_controller") + (joint.findall("dynamics") if joint.get("name") in
                                                           joints.names else []):
            joint.remove(extra)
    if joints.damping:
        notes.append(joints.damping_note())
    if collisions:
        notes.append(f"the URDF's {len(collisions)} collision elements" + (f" ({stl} STL meshes, which Drake "
                     "cannot take)" if stl else "") + f" replaced by qpctl's {len(robot.capsules)} link capsules")
    parser = Parser(plant)
    parser.SetAutoRenaming(True)
    dropped = _resolve_visual_meshes(root, parser, source)
    if dropped:
        notes.append(f"{len(dropped)} visual meshes not on this machine left out (nothing is fetched): "
                     + ", ".join(dropped[:3]) + (", …" if len(dropped) > 3 else ""))
    base = _root_link(root)
    messages: list[str] = []
    try:
        with _drake_messages(messages):
            instances = parser.AddModelsFromString(ET.tostring(root, encoding="unicode"), "urdf")
    except RuntimeError as exc:
        raise ConfigError(f"Drake could not parse {source or 'the generated URDF'}: {' '.join(str(exc).split())}",
                          key="sim.model") from None
    if messages:
        notes.append(f"Drake's URDF parser: {'; '.join(messages[:3])}" + (" …" if len(messages) > 3 else ""))
    (instance,) = instances
    if base != "world":
        plant.WeldFrames(plant.world_frame(), plant.GetFrameByName(base, instance))
    for name in joints.names:
        if not plant.HasJointNamed(name, instance):
            raise ConfigError(f"no joint {name!r} in {source or 'the generated URDF'}", key="sim.joint_names")
    # the transmissions' actuators (GetJointActuatorIndices(instance) is empty before Finalize: all, filtered)
    actuated = {plant.get_joint_actuator(a).joint().name() for a in plant.GetJointActuatorIndices()
                if plant.get_joint_actuator(a).model_instance() == instance}
    for name in joints.names:
        if name not in actuated:
            plant.AddJointActuator(name, plant.GetJointByName(name, instance), math.inf)
    ids = []
    for k, cap in enumerate(robot.capsules):  # on the child body of the capsule's joint (its frame is the joint's)
        body = plant.world_body() if cap.joint_id == 0 else plant.GetJointByName(
            joints.names[robot.model.joints[cap.joint_id].idx_v], instance).child_body()
        shape, pose = _capsule_shape(cap.p0, cap.p1, cap.radius)
        ids.append(plant.RegisterCollisionGeometry(body, pose, shape, f"qpctl_capsule{k}_{cap.name}",
                                                   CoulombFriction(0.5, 0.5)))
        plant.RegisterVisualGeometry(body, pose, shape, f"qpctl_capsule{k}_{cap.name}", CAPSULE_RGBA)
    if ids:  # the capsules overlap at the joints: never a contact between the robot's own links
        scene_graph.collision_filter_manager().Apply(CollisionFilterDeclaration().ExcludeWithin(GeometrySet(ids)))
    plant.mutable_gravity_field().set_gravity_vector(np.asarray(robot.model.gravity.linear, float))
    return DrakeRobot(instance, joints.names, joints.by_order, ids, notes)


class ObstaclePoses(LeafSystem):
    """The poses of the moving obstacles' frames at the context's time (``geometry_pose``, a
    ``FramePoseVector`` for ``scene_graph.get_source_pose_port(source_id)``)."""

    def __init__(self, frames: Sequence[tuple[Any, Obstacle, RotationMatrix]]) -> None:
        super().__init__()
        self._frames = list(frames)
        self.DeclareAbstractOutputPort("geometry_pose", lambda: AbstractValue.Make(FramePoseVector()), self._calc)

    def _calc(self, context: Context, output: Any) -> None:
        poses = output.get_mutable_value()
        poses.clear()
        t = context.get_time()
        for frame_id, obs, rotation in self._frames:
            poses.set_value(frame_id, RigidTransform(rotation, obs.position_at(t)))


@dataclass
class DrakeObstacles:
    """What :func:`add_obstacles` registered: the source, one geometry id per obstacle, and the pose
    system of the moving ones (None if all are static)."""

    source_id: Any
    ids: list[GeometryId]
    poses: ObstaclePoses | None


def add_obstacles(builder: DiagramBuilder, scene_graph: SceneGraph, obstacles: Sequence[Obstacle]) -> DrakeObstacles:
    """Register ``obstacles`` in ``scene_graph`` under the source ``qpctl_obstacles``: anchored geometry
    for the static ones, frames posed by an :class:`ObstaclePoses` system (added and connected here)
    for the moving ones; proximity and illustration roles. They are ghosts — shown, measurable, never
    in contact: a ``MultibodyPlant`` refuses contact with geometry it does not own, so their contact
    with every proximity geometry registered so far is filtered out. Call it after :func:`add_robot`
    (and your other models)."""
    source = scene_graph.RegisterSource("qpctl_obstacles")
    ids, frames, names = [], [], set()
    for i, obs in enumerate(obstacles):
        name = obs.name or f"obstacle{i}"
        name = name if name not in names else f"{name}_{i}"  # SceneGraph wants unique names
        names.add(name)
        shape, rotation = obstacle_shape(obs)
        if obs.moving:
            frame = scene_graph.RegisterFrame(source, GeometryFrame(name))
            instance = GeometryInstance(RigidTransform(), shape, name)
            frames.append((frame, obs, rotation))
        else:
            instance = GeometryInstance(RigidTransform(rotation, np.asarray(obs.position, float)), shape, name)
        instance.set_proximity_properties(ProximityProperties())
        instance.set_illustration_properties(MakePhongIllustrationProperties(OBSTACLE_RGBA))
        ids.append(scene_graph.RegisterGeometry(source, frame, instance) if obs.moving
                   else scene_graph.RegisterAnchoredGeometry(source, instance))
    if ids:  # ghosts: a MultibodyPlant refuses contact with geometry it does not own
        others = [g for g in scene_graph.model_inspector().GetAllGeometryIds(Role.kProximity) if g not in ids]
        scene_graph.collision_filter_manager().Apply(
            CollisionFilterDeclaration().ExcludeWithin(GeometrySet(ids)).ExcludeBetween(GeometrySet(ids),
                                                                                          GeometrySet(others)))
    poses = None
    if frames:
        poses = builder.AddSystem(ObstaclePoses(frames))
        poses.set_name("qpctl_obstacle_poses")
        builder.Connect(poses.get_output_port(), scene_graph.get_source_pose_port(source))
    return DrakeObstacles(source, ids, poses)


# -- the joints -------------------------------------------------------------------------------------
class DrakeJoints:
    """Where the controller's joints live in a finalised plant, matched by name (:class:`JointMap`).

    Attributes:
        q, v: (n,) the joints' ``position_start``/``velocity_start`` in the plant's q and v.
        q_local, v_local, u_local: (n,) their slots in the model instance's state (the state output
            port: positions, then velocities) and actuation (the actuation input port) vectors.
        nq, nv, nu: the instance's positions, velocities and actuators.
        effort_limit: (n,) the joints' actuators' effort limits [N·m] (inf: none; Drake clamps to them).

    Raises:
        ConfigError: a controller joint missing from the instance (the message lists both sets), one
            that is not a 1-DoF joint, or one without an actuator; extra DoF in the instance unless
            ``allow_extra`` (they are then left alone: read never, driven with 0).
    """

    def __init__(self, plant: MultibodyPlant, instance: ModelInstanceIndex, names: Sequence[str], *,
                 allow_extra: bool = False) -> None:
        joints = [plant.get_joint(i) for i in plant.GetJointIndices(instance)]
        moving = [j for j in joints if j.num_velocities() > 0]
        self.map = JointMap.from_names([j.name() for j in moving], names, allow_extra=allow_extra)
        mine = [moving[i] for i in self.map.sim_index]
        bad = [j.name() for j in mine if j.num_positions() != 1 or j.num_velocities() != 1]
        if bad:
            raise ConfigError(f"Drake joints {', '.join(bad)} are not 1-DoF (revolute or prismatic) joints",
                              key="joint_map")
        self.q = np.array([j.position_start() for j in mine], int)
        self.v = np.array([j.velocity_start() for j in mine], int)
        q_of = plant.GetPositionsFromArray(instance, np.arange(plant.num_positions(), dtype=float)).astype(int)
        v_of = plant.GetVelocitiesFromArray(instance, np.arange(plant.num_velocities(), dtype=float)).astype(int)
        u_of = plant.GetActuationFromArray(instance, np.arange(plant.num_actuated_dofs(), dtype=float)).astype(int)
        self.nq, self.nv, self.nu = len(q_of), len(v_of), len(u_of)
        self.q_local = np.array([int(np.flatnonzero(q_of == i)[0]) for i in self.q], int)
        self.v_local = np.array([int(np.flatnonzero(v_of == i)[0]) for i in self.v], int)
        actuators = {plant.get_joint_actuator(a).joint().index(): plant.get_joint_actuator(a)
                     for a in plant.GetJointActuatorIndices(instance)}
        missing = [j.name() for j in mine if j.index() not in actuators]
        if missing:
            raise ConfigError(f"Drake joints {', '.join(missing)} have no actuator (add a JointActuator, or a "
                              "<transmission> in the URDF)", key="joint_map")
        acts = [actuators[j.index()] for j in mine]
        self.u_local = np.array([int(np.flatnonzero(u_of == a.input_start())[0]) for a in acts], int)
        self.effort_limit = np.array([a.effort_limit() for a in acts], float)
        if not allow_extra and (self.nq != len(mine) or self.nu != len(mine)):
            raise ConfigError(f"the Drake model has {self.nq} positions and {self.nu} actuators, the controller "
                              f"{len(mine)} joints", key="joint_map")

    def actuation(self, tau: np.ndarray) -> np.ndarray:
        """The instance's actuation vector (nu,) for the controller's torques (n,) [N·m] (others 0)."""
        u = np.zeros(self.nu)
        u[self.u_local] = tau
        return u


def _find_instance(plant: MultibodyPlant, names: Sequence[str]) -> ModelInstanceIndex:
    """The one model instance that has every joint in ``names``."""
    found = [ModelInstanceIndex(i) for i in range(plant.num_model_instances())
             if all(plant.HasJointNamed(n, ModelInstanceIndex(i)) for n in names)]
    if len(found) != 1:
        raise ConfigError(f"{len(found)} model instances have the joints {', '.join(names)}; pass instance= "
                          "(the arm's model instance) or joint_names=", key="joint_map")
    return found[0]


# -- the controller as a Drake system ------------------------------------------------------------------
class QpctlController(LeafSystem):
    """A qpctl controller as a Drake ``LeafSystem``: ``estimated_state`` in, ``actuation`` out.

    Connect ``plant.get_state_output_port(instance)`` to its input and its output to
    ``plant.get_actuation_input_port(instance)``; joints are matched by name, so the plant may order
    them as it likes and have others (driven with 0, e.g. a hand). The system calls
    ``controller.step(q, v, t)`` once per control period with the state at that instant (t: the
    context's time, on the path's clock) and holds the torque:

    * ``period`` [s] given: a periodic discrete update (offset ``period``; the first sample at
      initialisation) holds the torque in the system's discrete state — a zero-order hold, what a
      continuous plant needs (or a controller slower than a discrete plant). At instants a discrete
      plant's step shares with it, Drake's event order decides what the controller samples: in Drake
      1.51 the plant steps first (an unrestricted update), so the controller reads the next state with
      the current time — measured on the paper arm, 7.8e-5 rad off the adapter's run after 0.2 s.
    * ``period=None``, a discrete plant: the output is computed from the state when the plant's step
      asks for it — one controller call per plant step, no delay (a repeated evaluation at the same time
      and state returns the same torque without a call).

    The controller's own state (warm starts, the previous torque) lives in the controller, not in the
    Drake context: ``Simulator.Initialize()`` resets it (an initialisation event), and one system serves
    one simulation at a time. ``controller.warmup()`` runs here, so no tick compiles.

    Args:
        controller: any qpctl :class:`~qpctl.controllers.base.Controller`.
        plant: the finalised ``MultibodyPlant`` the arm is in.
        instance: the arm's model instance (default: the one with ``controller.robot.joint_names``).
        period: the control period [s], or None (the two ways above).
        joint_names: the plant's names of the controller's joints, in the controller's order.

    Raises:
        ConfigError: a continuous plant without ``period``, a non-positive period, joints that do not
            match (:class:`DrakeJoints`).
    """

    def __init__(self, controller: Controller, plant: MultibodyPlant, instance: ModelInstanceIndex | None = None,
                 *, period: float | None = None, joint_names: Sequence[str] | None = None) -> None:
        super().__init__()
        names = list(joint_names) if joint_names is not None else list(controller.robot.joint_names)
        if instance is None:
            instance = _find_instance(plant, names)
        if period is None and not plant.time_step() > 0:
            raise ConfigError("a continuous plant needs the control period: QpctlController(..., period=dt)",
                              key="sim.dt")
        if period is not None and not (np.isfinite(period) and period > 0):
            raise ConfigError(f"must be a positive number of seconds, got {period}", key="sim.dt")
        self.controller = controller
        self.joints = DrakeJoints(plant, instance, names, allow_extra=True)
        self.period = period
        j = self.joints
        self._state = self.DeclareVectorInputPort("estimated_state", j.nq + j.nv)
        if period is not None:
            held = self.DeclareDiscreteState(j.nu)
            self.DeclareStateOutputPort("actuation", held)
            self.DeclareInitializationDiscreteUpdateEvent(self._start)
            self.DeclarePeriodicDiscreteUpdateEvent(period, period, self._sample)
        else:
            self.DeclareVectorOutputPort("actuation", j.nu, self._output)
            self.DeclareInitializationUnrestrictedUpdateEvent(self._reset)
        self._memo: tuple[float, bytes, np.ndarray] | None = None
        if not controller.warm:
            controller.warmup()

    def _torque(self, context: Context) -> np.ndarray:
        x = self._state.Eval(context)
        q, v = x[self.joints.q_local], x[self.joints.nq + self.joints.v_local]
        robot = self.controller.robot
        if robot.lie:  # Drake's revolute angles → Pinocchio's configuration (continuous joints)
            q = robot.configuration(q)
        t = float(context.get_time())
        out = self.controller.step(q, v, t)
        if not np.all(np.isfinite(out.tau)):
            raise SimulationError(f"controller {self.controller.kind} returned non-finite torque at t = {t:.4f} s")
        return self.joints.actuation(out.tau)

    def _start(self, context: Context, discrete_state: Any) -> EventStatus:
        self.controller.reset()
        return self._sample(context, discrete_state)

    def _sample(self, context: Context, discrete_state: Any) -> EventStatus:
        discrete_state.set_value(0, self._torque(context))
        return EventStatus.Succeeded()

    def _reset(self, context: Context, state: Any) -> EventStatus:
        self.controller.reset()
        self._memo = None
        return EventStatus.Succeeded()

    def _output(self, context: Context, output: Any) -> None:
        t, x = float(context.get_time()), np.asarray(self._state.Eval(context), float).tobytes()
        if self._memo is None or self._memo[0] != t or self._memo[1] != x:
            self._memo = (t, x, self._torque(context))
        output.SetFromVector(self._memo[2])


# -- qpctl's simulator on Drake ------------------------------------------------------------------------
class DrakeSimulator(SimulatorBase):
    """Runs a controller on a Drake ``MultibodyPlant`` and records the same trajectory as the built-in
    simulator (module docstring).

    Args:
        controller: any :class:`~qpctl.controllers.base.Controller`.
        dt: the integrator's (or the discrete plant's) step and the control period [s].
        duration: simulated time [s].
        progress: show a tqdm progress bar.
        model: a URDF of your own instead of the robot's (``sim.model``, relative to the scenario's
            folder); ``joint_names``: its names of the controller's joints (:func:`add_robot`).
        integrator: the scenario's ``sim.integrator``: Drake steps with semi-explicit Euler whatever it
            says (a note says so when it is not ``"euler"``).
        discrete: a discrete plant (``time_step = dt``, Drake's SAP model) instead of the continuous plant
            and the fixed-step ``SemiExplicitEulerIntegrator``.
        measure_clearance: after the run, measure the clearance again with Drake's own signed distance
            (``drake_clearance``; its extremes go into ``notes``).

    Attributes:
        diagram, plant, scene_graph, simulator: the Drake objects.
        robot_in_plant: :class:`DrakeRobot`; joints: :class:`DrakeJoints`; obstacle_geometry: :class:`DrakeObstacles`.
        dynamics: M(q) and the bias forces against Pinocchio's (:class:`DynamicsCheck`).
        forward_rel: Drake's q̈ (one step from 5 random states, τ = 0) against ABA's, relative.
        drake_clearance: (T,) Drake's least capsule–obstacle distance at each recorded state [m].
    """

    name = "drake"

    def __init__(self, controller: Controller, *, dt: float = 1e-3, duration: float = 5.0, progress: bool = False,
                 model: str | Path | None = None, joint_names: Sequence[str] | None = None,
                 integrator: str = "euler", discrete: bool = False, measure_clearance: bool = True) -> None:
        super().__init__(controller, dt=dt, duration=duration, progress=progress)
        self.robot.check_scalar_joints("Drake")
        if integrator != "euler":
            self.notes.append(f"Drake steps with semi-explicit Euler (sim.integrator = {integrator!r} is the "
                              "built-in simulator's; Drake has no classical RK4)")
        self.discrete = discrete
        self.measure_clearance = measure_clearance
        builder = DiagramBuilder()
        plant, scene_graph = AddMultibodyPlantSceneGraph(builder, time_step=self.dt if discrete else 0.0)
        self.plant, self.scene_graph = plant, scene_graph
        self.robot_in_plant = add_robot(plant, scene_graph, self.robot, model=model, joint_names=joint_names)
        self.notes.extend(self.robot_in_plant.notes)
        plant.Finalize()
        self.obstacle_geometry = add_obstacles(builder, scene_graph, self.obstacles)
        self.diagram = builder.Build()
        instance = self.robot_in_plant.instance
        self.joints = DrakeJoints(plant, instance, self.robot_in_plant.joint_names)
        self.simulator = Simulator(self.diagram)
        if not discrete:
            # a hair above dt, so that a target t + dt a few ulps farther than dt is still one step
            ResetIntegratorFromFlags(self.simulator, "semi_explicit_euler", self.dt * (1 + 1e-9))
            self.simulator.get_mutable_integrator().set_fixed_step_mode(True)
        self._context = self.simulator.get_mutable_context()
        self._plant_context = plant.GetMyMutableContextFromRoot(self._context)
        self._actuation = plant.get_actuation_input_port(instance).FixValue(self._plant_context,
                                                                            np.zeros(self.joints.nu))
        # a second context for measuring, where the capsule–obstacle pairs are allowed (only there)
        self._measure = self.diagram.CreateDefaultContext()
        scene_graph.collision_filter_manager(scene_graph.GetMyMutableContextFromRoot(self._measure)).Apply(
            CollisionFilterDeclaration().AllowBetween(GeometrySet(self.robot_in_plant.capsule_ids),
                                                      GeometrySet(self.obstacle_geometry.ids)))
        self._measure_plant = plant.GetMyMutableContextFromRoot(self._measure)
        self._robot_id_set = set(self.robot_in_plant.capsule_ids)
        self._v_in_x = plant.num_positions() + self.joints.v  # the velocities' slots in [q; v]
        self._limited = bool(np.isfinite(self.joints.effort_limit).any())
        self.effort_clamped_ticks = 0
        self.drake_clearance = np.zeros(0)
        self._check_model(self.robot_in_plant.by_order)

    @classmethod
    def from_scenario(cls, controller: Controller, scenario: Any, *, progress: bool = False) -> DrakeSimulator:
        """Drake for the scenario's ``[sim]``: ``dt``, ``duration``, ``integrator`` (noted), the user's
        ``model`` (a URDF, relative to the scenario file's folder) and ``joint_names``."""
        sim = scenario.data["sim"]
        model = scenario.resolve(sim["model"]) if sim["model"] else None
        return cls(controller, dt=sim["dt"], duration=sim["duration"], progress=progress, model=model,
                   joint_names=sim["joint_names"], integrator=sim["integrator"])

    # -- checks --------------------------------------------------------------------------------------
    def terms(self, q: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Drake's M(q) [kg·m²] (``CalcMassMatrix``) and bias forces C(q, v)v − τ_g(q) [N·m]
        (``CalcBiasTerm`` less ``CalcGravityGeneralizedForces``), in the controller's joint order."""
        plant, ctx, j = self.plant, self._measure_plant, self.joints
        qs, vs = np.zeros(plant.num_positions()), np.zeros(plant.num_velocities())
        qs[j.q], vs[j.v] = self.robot.angles(q), v
        plant.SetPositions(ctx, qs)
        plant.SetVelocities(ctx, vs)
        M = plant.CalcMassMatrix(ctx)
        bias = plant.CalcBiasTerm(ctx) - plant.CalcGravityGeneralizedForces(ctx)
        return M[np.ix_(j.v, j.v)], bias[j.v]

    def _check_model(self, by_order: bool) -> None:
        self.dynamics: DynamicsCheck
        self.dynamics, self.forward_rel = check_simulator(self, self.terms, "the Drake model", by_order=by_order)
        limits = [f"{n} {e:g}" for n, e in zip(self.robot.joint_names, self.joints.effort_limit) if np.isfinite(e)]
        if limits:
            self.notes.append("the URDF's transmissions give effort limits [N·m or N], to which Drake clamps the "
                              "actuation: " + ", ".join(limits))

    def drake_distance(self, q: np.ndarray, t: float) -> float:
        """Drake's least signed distance [m] between the link capsules and the obstacles at (q, t)
        (SceneGraph's ``ComputeSignedDistancePairwiseClosestPoints``; inf without obstacles)."""
        if not self.obstacle_geometry.ids:
            return math.inf
        qs = np.zeros(self.plant.num_positions())
        qs[self.joints.q] = self.robot.angles(q)
        self.plant.SetPositions(self._measure_plant, qs)
        self._measure.SetTime(float(t))
        query = self.scene_graph.get_query_output_port().Eval(self.scene_graph.GetMyContextFromRoot(self._measure))
        pairs = query.ComputeSignedDistancePairwiseClosestPoints(math.inf)
        return min((p.distance for p in pairs if (p.id_A in self._robot_id_set) != (p.id_B in self._robot_id_set)),
                   default=math.inf)

    # -- the five methods ----------------------------------------------------------------------------
    def reset(self, q0: np.ndarray, v0: np.ndarray | None = None) -> None:
        """Put the plant at (q0 [rad], v0 [rad/s], default rest) at t = 0, zero actuation, and initialise."""
        q0 = np.asarray(q0, float)
        if q0.shape != (self.robot.nq,):
            raise ConfigError(f"q0 needs {self.robot.nq} joint values, got {q0.size}", key="robot.q0")
        v0 = np.zeros(self.robot.nv) if v0 is None else np.asarray(v0, float)
        qs, vs = np.zeros(self.plant.num_positions()), np.zeros(self.plant.num_velocities())
        qs[self.joints.q], vs[self.joints.v] = self.robot.angles(q0), v0
        self._context.SetTime(0.0)
        self.plant.SetPositions(self._plant_context, qs)
        self.plant.SetVelocities(self._plant_context, vs)
        self._actuation.GetMutableData().get_mutable_value().SetFromVector(np.zeros(self.joints.nu))
        self.simulator.Initialize()
        self.simulator.ResetStatistics()
        self._t = 0.0
        self.effort_clamped_ticks = 0

    def read(self) -> tuple[np.ndarray, np.ndarray]:
        x = self.plant.GetPositionsAndVelocities(self._plant_context)
        if not np.isfinite(x).all():
            raise SimulationError("Drake state diverged (non-finite joint state)")
        q = x[self.joints.q]
        return (self.robot.configuration(q) if self.robot.lie else q), x[self._v_in_x]

    def apply(self, tau: np.ndarray) -> None:
        tau = np.asarray(tau, float)
        if self._limited and np.any(np.abs(tau) > self.joints.effort_limit):
            self.effort_clamped_ticks += 1
        self._actuation.GetMutableData().get_mutable_value().SetFromVector(self.joints.actuation(tau))

    def step(self, t: float) -> None:
        k = round(t / self.dt)  # the target as Drake's periodic events compute it: no step lost to round-off
        try:
            self.simulator.AdvanceTo((k + 1) * self.dt)
        except RuntimeError as exc:
            raise SimulationError(f"Drake failed at t = {t:.4f} s: {' '.join(str(exc).split())}") from None
        self._t = (k + 1) * self.dt

    def obstacle_positions(self) -> np.ndarray:
        """Where Drake holds the obstacles [m]: their geometries' poses in SceneGraph now."""
        query = self.scene_graph.get_query_output_port().Eval(self.scene_graph.GetMyContextFromRoot(self._context))
        return np.array([query.GetPoseInWorld(g).translation() for g in self.obstacle_geometry.ids],
                        float).reshape(-1, 3)

    def steps_taken(self) -> int:
        """Drake's steps since :meth:`reset`: the integrator's, or the discrete plant's updates."""
        if self.discrete:  # (the plant's step is an unrestricted update in Drake 1.51, a discrete one before)
            return int(self.simulator.get_num_discrete_updates() + self.simulator.get_num_unrestricted_updates())
        return int(self.simulator.get_integrator().get_num_steps_taken())

    def run(self, q0: np.ndarray, v0: np.ndarray | None = None) -> Trajectory:
        traj = super().run(q0, v0)
        steps = self.steps_taken()
        if steps != len(traj.t) - 1:
            raise SimulationError(f"Drake took {steps} steps for {len(traj.t) - 1} control periods")
        if np.isfinite(self.joints.effort_limit).any():
            self.counts["effort_clamped_ticks"] = self.effort_clamped_ticks
            if self.effort_clamped_ticks:
                self.notes.append(f"Drake clamped the torque to the effort limits on {self.effort_clamped_ticks} "
                                  "ticks: tau records the command")
        if self.measure_clearance and self.obstacle_geometry.ids:
            self.drake_clearance = np.array([self.drake_distance(q, t) for q, t in zip(traj.q, traj.t)])
            gap = float(np.max(np.abs(self.drake_clearance - traj.clearance)))
            self.notes.append(f"Drake's own signed distance (SceneGraph) between the capsules and the obstacles: "
                              f"min {self.drake_clearance.min():.4f} m over the run, within {gap:.2g} m of qpctl's "
                              "clearance at every tick")
        return traj


__all__ = ["DrakeJoints", "DrakeObstacles", "DrakeRobot", "DrakeSimulator", "ObstaclePoses", "QpctlController",
           "add_obstacles", "add_robot", "obstacle_shape"]
