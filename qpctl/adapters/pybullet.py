"""Run any qpctl controller in PyBullet (``pip install 'qpctl[pybullet]'``).

**The model.** PyBullet loads a URDF: the robot's own when qpctl read it from one (the Panda from
example-robot-data, any ``robot.kind = "urdf"``), the user's (``sim.model``), or one written from
the Pinocchio model by :func:`robot_urdf` (the planar arm, or any model without a file). Before
loading, the URDF's ``<visual>``/``<collision>`` elements are dropped (no meshes to resolve, and
PyBullet must never push the arm: clearance is qpctl's own, as in the other simulators), joints the
controller does not drive (the Panda's fingers) are made fixed — Pinocchio's reduced model locks them
the same way — and, unless ``joint_limits``, the controller's revolute joints become continuous
(the built-in simulator has no joint stops). It is loaded with ``URDF_USE_INERTIA_FROM_FILE`` (else
PyBullet recomputes inertias from the collision shapes) and a fixed base; the dynamics are then
checked against Pinocchio's (M(q) from ``calculateMassMatrix``, the bias forces from
``calculateInverseDynamics`` at zero acceleration) and any mismatch is reported in ``notes``.

**What PyBullet does by default and qpctl undoes.** Each joint's velocity motor (it would hold the
joint still) is switched off with ``VELOCITY_CONTROL`` at force 0; the links' linear and angular
damping (0.04 by default) and the joint damping a URDF declares (``<dynamics damping>``: 0.003
N·m·s/rad on the Panda's joints; Pinocchio does not read it, so the controller's model has none) are
set to 0 — in a ``changeDynamics`` call of their own: PyBullet 3.2.7 leaves the joint damping in place
when ``maxJointVelocity`` is set in the same call — and the joint speed cap (100 rad/s) is raised.

**The loop.** DIRECT mode, ``setTimeStep(dt)``: one ``stepSimulation`` per control tick, the torque
applied with ``TORQUE_CONTROL`` before each step (PyBullet clears applied forces after a step, so it
is held over exactly one step). Obstacles are bodies without a collision shape (visual only), moving
ones moved with ``resetBasePositionAndOrientation`` after each step.

**The integrator** is PyBullet's own: Featherstone's articulated-body algorithm with a semi-implicit
Euler step (v ← v + dt·q̈, q ← q + dt·v), the scheme of the built-in ``integrator = "euler"``. So
against the built-in RK4 it differs by the method's O(dt) error, against the built-in Euler by
round-off; ``sim.integrator`` is not PyBullet's to choose (a note says so when it is not ``euler``).
At start-up one step from each of 5 random states (τ = 0) is compared with Pinocchio's ABA, and a
difference above 1e-9 relative is reported (it found the joint damping above).
"""

from __future__ import annotations

import contextlib
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin

from qpctl.adapters.joint_map import JointMap
from qpctl.adapters.model_check import DynamicsCheck, check_simulator
from qpctl.adapters.urdf import prepare_urdf, robot_urdf, urdf_joints
from qpctl.controllers.base import Controller
from qpctl.errors import ConfigError, SimulationError
from qpctl.simulation.loop import SimulatorBase

__all__ = ["PybulletSimulator", "prepare_urdf", "robot_urdf"]  # the URDF writers live in qpctl.adapters.urdf


def _import_quietly() -> Any:
    """PyBullet, without the "pybullet build time: …" line its C module prints to stdout on import
    (it would land in ``qpctl simulate``'s output and in a user's logs)."""
    import os
    import sys

    sys.stdout.flush()
    saved = os.dup(1)
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 1)
            import pybullet as module
    finally:
        os.dup2(saved, 1)
        os.close(saved)
    return module


try:
    pybullet = _import_quietly()
except ImportError as exc:  # pragma: no cover - exercised only without the extra
    raise ImportError("the PyBullet adapter needs PyBullet: pip install 'qpctl[pybullet]' (or pip install "
                      "pybullet)") from exc

class PybulletSimulator(SimulatorBase):
    """Runs a controller in PyBullet and records the same trajectory as the built-in simulator.

    Args:
        controller: any :class:`~qpctl.controllers.base.Controller`.
        dt: PyBullet's time step and the control period [s] (one controller call per ``stepSimulation``).
        duration: simulated time [s].
        progress: show a tqdm progress bar.
        model: a URDF file of your own instead of the robot's (relative paths: from the working folder;
            ``sim.model`` in a scenario is relative to its file).
        joint_names: the URDF's names of the controller's joints, in the controller's order (default:
            ``robot.joint_names``; if the URDF has none of those names, its movable joints in order,
            which must then pass the dynamics check).
        joint_limits: keep the URDF's joint limits (PyBullet's stops); off by default, as in the
            built-in simulator.
        integrator: the scenario's ``sim.integrator``, for the record only: PyBullet integrates with
            semi-implicit Euler whatever it says (a note says so when it is not ``"euler"``).
    """

    name = "pybullet"

    def __init__(self, controller: Controller, *, dt: float = 1e-3, duration: float = 5.0,
                 progress: bool = False, model: str | Path | None = None, joint_names: Sequence[str] | None = None,
                 joint_limits: bool = False, integrator: str = "euler") -> None:
        super().__init__(controller, dt=dt, duration=duration, progress=progress)
        robot = self.robot
        robot.check_scalar_joints("PyBullet")
        if integrator != "euler":
            self.notes.append(f"PyBullet integrates with semi-implicit Euler (sim.integrator = {integrator!r} "
                              "is the built-in simulator's)")
        own = model is not None
        if own:
            path = Path(model)  # type: ignore[arg-type]
            if not path.is_file() or path.suffix.lower() != ".urdf":
                raise ConfigError(f"PyBullet needs a URDF file, got {path}" + ("" if path.is_file() else
                                                                                " (not found)"), key="sim.model")
            text, source = path.read_text(), path
        elif robot.urdf is not None:
            text, source = robot.urdf.read_text(), robot.urdf
        else:
            text, source = robot_urdf(robot), None
        joints = urdf_joints(text, robot, joint_names, own=own, source=source)
        names, by_order = list(joints.names), joints.by_order
        if by_order:
            self.notes.append(joints.order_note(robot))
        self.joint_names = joints.names
        self._joints = joints
        self.client = pybullet.connect(pybullet.DIRECT)
        try:
            self._load(prepare_urdf(text, names, joint_limits=joint_limits), source)
            self._place_obstacles()
            self._check_model(by_order)
        except BaseException:
            pybullet.disconnect(self.client)
            raise

    def _load(self, urdf: str, source: Path | None) -> None:
        c = self.client
        pybullet.setTimeStep(self.dt, physicsClientId=c)
        pybullet.setPhysicsEngineParameter(numSubSteps=0, physicsClientId=c)
        pybullet.setGravity(*self.robot.model.gravity.linear, physicsClientId=c)
        with tempfile.TemporaryDirectory(prefix="qpctl-pybullet-") as tmp:
            path = Path(tmp) / "robot.urdf"
            path.write_text(urdf)
            body = pybullet.loadURDF(str(path), useFixedBase=True, flags=pybullet.URDF_USE_INERTIA_FROM_FILE,
                                     physicsClientId=c)
        if body < 0:
            raise ConfigError(f"PyBullet could not load the URDF ({source or 'generated'})", key="sim.model")
        self.body = body
        count = pybullet.getNumJoints(body, physicsClientId=c)
        infos = [pybullet.getJointInfo(body, i, physicsClientId=c) for i in range(count)]
        sim_names = [info[1].decode() for info in infos]
        movable = [i for i, info in enumerate(infos) if info[2] != pybullet.JOINT_FIXED]
        self.map = JointMap.from_names([sim_names[i] for i in movable], self.joint_names)
        self.joint_ids = [movable[i] for i in self.map.sim_index]
        self._dof_order = list(self.map.sim_index)  # model joint i ↔ PyBullet's movable joint (its DoF order)
        self._n_dof = len(movable)
        for link in range(-1, count):  # PyBullet's defaults and the URDF's <dynamics damping>, undone
            # (two calls: PyBullet 3.2.7 drops jointDamping when maxJointVelocity is in the same call —
            # measured: the Panda URDF's damping of 0.003 N·m·s/rad then stays, 1.8e-2 relative in q̈)
            pybullet.changeDynamics(body, link, linearDamping=0.0, angularDamping=0.0, jointDamping=0.0,
                                    physicsClientId=c)
            pybullet.changeDynamics(body, link, maxJointVelocity=1e6, physicsClientId=c)
        if self._joints.damping:
            self.notes.append(self._joints.damping_note())
        pybullet.setJointMotorControlArray(body, movable, pybullet.VELOCITY_CONTROL, forces=[0.0] * len(movable),
                                           physicsClientId=c)

    def _terms(self, q: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """PyBullet's M(q) [kg·m²] and bias forces [N·m] in the controller's joint order."""
        c, n = self.client, self._n_dof
        qs, vs = np.zeros(n), np.zeros(n)
        qs[self._dof_order], vs[self._dof_order] = self.robot.angles(q), v
        M = np.asarray(pybullet.calculateMassMatrix(self.body, qs.tolist(), physicsClientId=c))
        b = np.asarray(pybullet.calculateInverseDynamics(self.body, qs.tolist(), vs.tolist(), [0.0] * n,
                                                         physicsClientId=c))
        idx = self._dof_order
        return M[np.ix_(idx, idx)], b[idx]

    def _check_model(self, by_order: bool) -> None:
        self.dynamics: DynamicsCheck
        self.dynamics, self.forward_rel = check_simulator(self, self._terms, "the PyBullet model", by_order=by_order)

    def _place_obstacles(self) -> None:
        c = self.client
        self._obstacle_bodies = []
        for obs in self.obstacles:
            rgba = [0.45, 0.6, 0.3, 0.6]
            geom = obs.kind.mujoco_geom(obs)  # the shape's MuJoCo geom, drawn with PyBullet's same primitive
            if geom.type == "sphere":
                vs = pybullet.createVisualShape(pybullet.GEOM_SPHERE, radius=geom.size[0], rgbaColor=rgba,
                                                physicsClientId=c)
            elif geom.type == "box":
                vs = pybullet.createVisualShape(pybullet.GEOM_BOX, halfExtents=list(geom.size), rgbaColor=rgba,
                                                physicsClientId=c)
            elif geom.type in ("capsule", "cylinder"):
                shape = pybullet.GEOM_CAPSULE if geom.type == "capsule" else pybullet.GEOM_CYLINDER
                vs = pybullet.createVisualShape(shape, radius=geom.size[0], length=2 * geom.size[1], rgbaColor=rgba,
                                                physicsClientId=c)
            else:
                raise ConfigError(f"shape {obs.shape!r} (MuJoCo geom {geom.type!r}) has no PyBullet visual here "
                                  "(sphere, box, capsule, cylinder)", key="obstacles.shape")
            quat = np.array([0.0, 0.0, 0.0, 1.0]) if geom.rotation is None \
                else pin.Quaternion(geom.rotation).coeffs()  # (x, y, z, w), PyBullet's order
            body = pybullet.createMultiBody(baseMass=0.0, baseCollisionShapeIndex=-1, baseVisualShapeIndex=vs,
                                            basePosition=list(obs.position), baseOrientation=list(quat),
                                            physicsClientId=c)
            self._obstacle_bodies.append((body, list(quat)))

    def _move_obstacles(self, t: float) -> None:
        for obs, (body, quat) in zip(self.obstacles, self._obstacle_bodies):
            if obs.moving:
                pybullet.resetBasePositionAndOrientation(body, list(obs.position_at(t)), quat,
                                                         physicsClientId=self.client)

    @classmethod
    def from_scenario(cls, controller: Controller, scenario: Any, *, progress: bool = False) -> PybulletSimulator:
        """PyBullet for the scenario's ``[sim]``: ``dt``, ``duration``, the user's ``model`` (a URDF,
        relative to the scenario file's folder) and ``joint_names``."""
        sim = scenario.data["sim"]
        model = scenario.resolve(sim["model"]) if sim["model"] else None
        return cls(controller, dt=sim["dt"], duration=sim["duration"], progress=progress, model=model,
                   joint_names=sim["joint_names"], integrator=sim["integrator"])

    def reset(self, q0: np.ndarray, v0: np.ndarray | None = None) -> None:
        v0 = np.zeros(self.robot.nv) if v0 is None else np.asarray(v0, float)
        for j, qj, vj in zip(self.joint_ids, self.robot.angles(np.asarray(q0, float)), v0):  # continuous: angles
            pybullet.resetJointState(self.body, j, float(qj), float(vj), physicsClientId=self.client)
        self._move_obstacles(0.0)

    def read(self) -> tuple[np.ndarray, np.ndarray]:
        states = pybullet.getJointStates(self.body, self.joint_ids, physicsClientId=self.client)
        q, v = np.array([s[0] for s in states]), np.array([s[1] for s in states])
        if not (np.all(np.isfinite(q)) and np.all(np.isfinite(v))):
            raise SimulationError("PyBullet state diverged (non-finite joint state)")
        return (self.robot.configuration(q) if self.robot.lie else q), v

    def apply(self, tau: np.ndarray) -> None:
        pybullet.setJointMotorControlArray(self.body, self.joint_ids, pybullet.TORQUE_CONTROL,
                                           forces=np.asarray(tau, float).tolist(), physicsClientId=self.client)

    def step(self, t: float) -> None:
        pybullet.stepSimulation(physicsClientId=self.client)
        self._move_obstacles(t + self.dt)  # (a diverged state is caught by the next read)

    def obstacle_positions(self) -> np.ndarray:
        """Where PyBullet holds the obstacles [m] (their bodies' base positions)."""
        return np.array([pybullet.getBasePositionAndOrientation(b, physicsClientId=self.client)[0]
                         for b, _ in self._obstacle_bodies], float).reshape(-1, 3)

    def close(self) -> None:
        """Disconnect from PyBullet (also done when the simulator is garbage-collected)."""
        if getattr(self, "client", None) is not None and pybullet.isConnected(self.client):
            pybullet.disconnect(self.client)
        self.client = None  # type: ignore[assignment]

    def __del__(self) -> None:
        with contextlib.suppress(Exception):  # at interpreter shutdown pybullet may be gone first
            self.close()
