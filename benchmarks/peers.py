"""Peers on qpctl's scene: qpctl's QP, Pink and mink on the Panda canopy, in one process, interleaved
(issue 23, item 6; docs/performance.md, "Peers"). ``make peers`` installs the ``[peers]`` extra
(pin-pink, mink) and runs this; ``python -m benchmarks.peers [--duration S]`` alone needs it installed.

The scene is the packaged ``panda_canopy`` scenario: the Franka Panda, its path through three fruits
(quintic legs), the branches (capsules) and leaves (spheres), d_influence and d_safe from the
scenario. Each controller runs its own closed loop at the scenario's dt, the three loops interleaved
in blocks of 25 ticks (rotating the order) so that machine drift falls on all alike:

* **qpctl** — the torque QP (``controller.kind = "qp"``, DAQP; obstacle barrier rows for every link
  and obstacle within d_influence), the arm integrated by RK4 on Pinocchio's forward dynamics;
* **Pink** (stephane-caron/pink) — velocity-level IK on Pinocchio: a position-only FrameTask on the
  task frame (target x_d(t)), a light PostureTask, and a SelfCollisionBarrier over every
  link-capsule–obstacle pair of a Pinocchio GeometryModel (coal shapes: the same capsules and
  obstacles), d_min = d_safe; solved by DAQP through qpsolvers, q integrated with the velocity;
* **mink** (kevinzakka/mink) — the same IK on MuJoCo (the MJCF of :func:`qpctl.adapters.mujoco.robot_mjcf`:
  the same capsules and obstacles as geoms): FrameTask on the task site, PostureTask, and a
  CollisionAvoidanceLimit over every link–obstacle geom pair (minimum distance d_safe, detection
  distance d_influence); DAQP through qpsolvers.

A tick's time is the controller's own: qpctl's ``compute_us`` (Pinocchio's terms, distances, the QP,
τ); Pink's and mink's wall time of their configuration update (kinematics, Jacobians, distances)
and ``solve_ik`` (stacking and the QP). The peers command velocities, not torques: they track
kinematically, without dynamics, torque or joint limits, which qpctl's QP also holds. Clearance is
the true least distance between the link capsules and the obstacles (:class:`qpctl.tick.WorldClearance`)
along each run, tracking the task point's distance to x_d(t).

TSID is not run here (its pip wheel crashes against pin 4.1 unless rebuilt from its sdist): its
figure is quoted (:data:`TSID_QUOTE`) from ``benchmarks/tsid_tick.py``, which runs it beside qpctl in
one process in a scratch environment with TSID built from source.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Sequence
from typing import Any

import numpy as np
import pinocchio as pin

from qpctl.errors import ConfigError
from qpctl.robot.model import RobotModel
from qpctl.scenario import Scenario
from qpctl.simulation.simulator import rk4_step
from qpctl.tick import WorldClearance

BLOCK = 25  # ticks a controller runs before the next one takes over
SCENARIO = "panda_canopy"
#: TSID's figure, with its provenance (``benchmarks/tsid_tick.py``; docs/performance.md).
TSID_QUOTE = ("TSID 1.10's C++ torque QP (eiquadprog-fast, the end-effector position task with posture, "
              "actuation and joint bounds, no obstacle avoidance): 9.8 µs median per tick on the panda_spheres "
              "states, side by side in one process with qpctl's QP at 15.7–16.1 µs with its 10 spheres "
              "(benchmarks/tsid_tick.py, TSID built from its sdists against pin 4.1, 2026-12-03; issue 23 "
              "quoted 23 against 29 µs on the canopy path, another machine)")


class Loop:
    """One controller's closed loop: its state, and per tick its time [µs], tracking error [m] and
    clearance [m]."""

    name = ""

    def __init__(self, robot: RobotModel, path: Any, world: WorldClearance, q0: np.ndarray, dt: float,
                 ticks: int) -> None:
        self.robot, self.path, self.world, self.dt = robot, path, world, dt
        self.q, self.v = q0.copy(), np.zeros(robot.nv)
        self.tick_us, self.error, self.clearance = np.zeros(ticks), np.zeros(ticks), np.zeros(ticks)
        self._data = robot.model.createData()

    def run(self, k0: int, k1: int) -> None:
        for k in range(k0, k1):
            t = k * self.dt
            self.tick_us[k] = self.tick(t)
            pin.framesForwardKinematics(self.robot.model, self._data, self.q)
            x = self._data.oMf[self.robot.ee_frame_id].translation[list(self.robot.task_axes)]
            self.error[k] = float(np.linalg.norm(x - self.path(t).x[: x.size]))
            self.clearance[k] = self.world(self.q, t)

    def tick(self, t: float) -> float:
        """One tick at time t [s] (the state moves on by dt); its time [µs]."""
        raise NotImplementedError


class QpctlLoop(Loop):
    name = "qpctl (QP, daqp)"

    def __init__(self, scen: Scenario, *args: Any) -> None:
        super().__init__(*args)
        self.ctrl = scen.build_controller("qp")
        self.ctrl.warmup()
        self._fd = self.robot.model.createData()

    def tick(self, t: float) -> float:
        out = self.ctrl.step(self.q, self.v, t)
        tau, model, data = out.tau.copy(), self.robot.model, self._fd
        self.q, self.v = rk4_step(lambda q, v: pin.aba(model, data, q, v, tau), self.q, self.v, self.dt)
        return out.compute_us


def _capsule_placement(p0: np.ndarray, p1: np.ndarray) -> pin.SE3:
    """The placement of a coal capsule (axis z, centred) whose axis runs from p0 to p1 [m]."""
    axis = p1 - p0
    z = axis / np.linalg.norm(axis)
    rot = pin.Quaternion.FromTwoVectors(np.array([0.0, 0.0, 1.0]), z).matrix()
    return pin.SE3(rot, 0.5 * (p0 + p1))


class PinkLoop(Loop):
    name = "Pink (IK, daqp)"

    def __init__(self, scen: Scenario, obstacles: Sequence[Any], gains: Any, *args: Any) -> None:
        super().__init__(*args)
        import coal
        import pink
        from pink.barriers import SelfCollisionBarrier
        from pink.tasks import FrameTask, PostureTask

        model = self.robot.model
        geom = pin.GeometryModel()
        links = []
        for k, cap in enumerate(self.robot.capsules):
            length = float(np.linalg.norm(cap.p1 - cap.p0))
            links.append(geom.addGeometryObject(pin.GeometryObject(
                f"capsule{k}", cap.joint_id, _capsule_placement(cap.p0, cap.p1), coal.Capsule(cap.radius, length))))
        obs = []
        for j, o in enumerate(obstacles):
            if o.shape == "sphere":
                shape, place = coal.Sphere(o.radius), pin.SE3(np.eye(3), o.position)
            elif o.shape == "capsule":
                half = 0.5 * o.length * o.axis / np.linalg.norm(o.axis)
                shape, place = coal.Capsule(o.radius, o.length), _capsule_placement(o.position - half, o.position + half)
            else:
                raise ConfigError(f"peers: shape {o.shape!r} is not in this benchmark's Pink scene", key="obstacles")
            obs.append(geom.addGeometryObject(pin.GeometryObject(f"obstacle{j}", 0, place, shape)))
        for i in links:
            for j in obs:
                geom.addCollisionPair(pin.CollisionPair(i, j))
        self.pairs = len(links) * len(obs)
        data = model.createData()
        self.config = pink.Configuration(model, data, self.q.copy(), collision_model=geom,
                                         collision_data=pin.GeometryData(geom))
        self.task = FrameTask(self.robot.ee_frame, position_cost=1.0, orientation_cost=0.0)
        posture = PostureTask(cost=1e-3)
        posture.set_target(self.q.copy())
        self.tasks = [self.task, posture]
        self.barriers = [SelfCollisionBarrier(n_collision_pairs=self.pairs, gain=1.0, d_min=gains.d_safe)]
        self._solve_ik = pink.solve_ik

    def tick(self, t: float) -> float:
        start = time.perf_counter()
        self.task.set_target(pin.SE3(np.eye(3), self.path(t).x))
        vel = self._solve_ik(self.config, self.tasks, self.dt, solver="daqp", barriers=self.barriers,
                             safety_break=False)
        self.config.integrate_inplace(vel, self.dt)
        end = time.perf_counter()
        self.q, self.v = self.config.q.copy(), vel
        return (end - start) * 1e6


class MinkLoop(Loop):
    name = "mink (IK, daqp)"

    def __init__(self, scen: Scenario, obstacles: Sequence[Any], gains: Any, *args: Any) -> None:
        super().__init__(*args)
        import mink
        import mujoco

        from qpctl.adapters.mujoco import robot_mjcf

        if any(o.moving for o in obstacles):
            raise ConfigError("peers: the mink scene has static obstacles only", key="obstacles")
        model = mujoco.MjModel.from_xml_string(robot_mjcf(self.robot, obstacles, timestep=self.dt))
        model.geom_contype[:] = 1  # mink pairs only geoms that may collide; MuJoCo's contacts stay off
        model.geom_conaffinity[:] = 1
        links = [g for g in range(model.ngeom) if model.geom_bodyid[g] != 0]
        world = [g for g in range(model.ngeom) if model.geom_bodyid[g] == 0]
        self.pairs = len(links) * len(world)
        self.config = mink.Configuration(model, self.q.copy())
        self.task = mink.FrameTask(self.robot.ee_frame, "site", position_cost=1.0, orientation_cost=0.0)
        posture = mink.PostureTask(model, cost=1e-3)
        posture.set_target(self.q.copy())
        self.tasks = [self.task, posture]
        self.limits = [mink.CollisionAvoidanceLimit(model, [(links, world)],
                                                    minimum_distance_from_collisions=gains.d_safe,
                                                    collision_detection_distance=gains.d_influence)]
        self._mink = mink

    def tick(self, t: float) -> float:
        mink = self._mink
        start = time.perf_counter()
        self.task.set_target(mink.SE3.from_translation(self.path(t).x))
        vel = mink.solve_ik(self.config, self.tasks, self.dt, "daqp", limits=self.limits)
        self.config.integrate_inplace(vel, self.dt)
        end = time.perf_counter()
        self.q, self.v = self.config.q.copy(), vel
        return (end - start) * 1e6


def run(duration: float | None = None) -> dict[str, Loop]:
    """The three loops on the scenario, interleaved; ``duration`` [s] (default: the scenario's)."""
    scen = Scenario.load(SCENARIO)
    robot = scen.build_robot()
    q0 = scen.q0(robot)
    path = scen.build_path(robot, q0)
    obstacles = scen.build_obstacles()
    gains = scen.gains()
    dt = float(scen.data["sim"]["dt"])
    ticks = round((duration if duration is not None else float(scen.data["sim"]["duration"])) / dt) + 1
    world = WorldClearance(robot, obstacles)
    common = (robot, path, world, q0, dt, ticks)
    loops: list[Loop] = [QpctlLoop(scen, *common), PinkLoop(scen, obstacles, gains, *common),
                         MinkLoop(scen, obstacles, gains, *common)]
    for k0 in range(0, ticks, BLOCK):
        shift = (k0 // BLOCK) % len(loops)
        for loop in loops[shift:] + loops[:shift]:
            loop.run(k0, min(k0 + BLOCK, ticks))
    return {loop.name: loop for loop in loops}


def table(loops: dict[str, Loop]) -> str:
    """The Markdown table: tick time (median, p90), qpctl's ratio, tracking and clearance."""
    base = float(np.median(next(iter(loops.values())).tick_us))
    head = ("| controller | pairs | tick median [µs] | tick p90 [µs] | × qpctl | rms tracking [m] | "
            "max tracking [m] | min clearance [m] |")
    rows = [head, "|---|---|---|---|---|---|---|---|"]
    for name, lp in loops.items():
        med = float(np.median(lp.tick_us))
        pairs = getattr(lp, "pairs", "within d_influence")
        rows.append(f"| {name} | {pairs} | {med:.1f} | {np.percentile(lp.tick_us, 90):.1f} | {med / base:.2f} | "
                    f"{np.sqrt(np.mean(lp.error ** 2)):.4f} | {lp.error.max():.4f} | {lp.clearance.min():.4f} |")
    return "\n".join(rows)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="qpctl, Pink and mink on the Panda canopy, interleaved")
    parser.add_argument("--duration", type=float, default=None, help="seconds of the path (default: all of it)")
    args = parser.parse_args(argv)
    loops = run(args.duration)
    ticks = len(next(iter(loops.values())).tick_us)
    print(f"{SCENARIO}: {ticks} ticks each, interleaved in blocks of {BLOCK}")
    print(table(loops))
    names = list(loops)
    base = float(np.median(loops[names[0]].tick_us))
    for name in names[1:]:
        print(f"qpctl's tick is {float(np.median(loops[name].tick_us)) / base:.1f}x faster than {name}'s")
    print(f"TSID (quoted, not run): {TSID_QUOTE}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
