"""The benchmark scenes, built in code and seeded.

* :func:`paper_scene` — the paper's scenario (``Scenario.load("paper")``): the planar paper arm.
* :func:`spheres_scene` — the packaged ``panda_spheres`` scenario: the Panda picking three fruits
  in turn among 10 sphere obstacles (issue #10's reference scene).
* :func:`free_scene` — the same Panda task with no obstacles (what TSID's tick is compared with).
* :func:`planar_scene` — the paper's arm reaching a random point past 2–4 random discs.
* :func:`canopy_scene` — the Franka Panda reaching a fruit inside a canopy of branch capsules and
  leaf spheres (position-only task: 7 joints, 3 task coordinates, 4 degrees of redundancy).
* :func:`orchard_scene` — a canopy scene tiled along the hedge row to N obstacles at the same
  density: the obstacles near the arm are the canopy's, the rest are farther than the cutoff
  (the scaling suite: what the far obstacles cost with the broad phase on).

Every random scene keeps its path clear: no obstacle comes closer to the reference path than the
hand's capsule radius plus a margin, nor to the arm's starting pose — so a collision is the
controller's doing, not the scene's.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from functools import lru_cache
from typing import Any

import numpy as np
import pinocchio as pin

from qpctl.controllers.base import Controller
from qpctl.controllers.factory import make_controller
from qpctl.geometry.obstacles import Obstacle
from qpctl.law import LawGains
from qpctl.paths import WaypointPath
from qpctl.robot.model import RobotModel, panda, planar_arm
from qpctl.scenario import Scenario
from qpctl.scenes.canopy import link_capsules as _link_segments  # the link capsules' axes at q

#: Canopy block in front of the Panda (world frame, [m]): x depth, y width, z height.
CANOPY_LO = np.array([0.35, -0.35, 0.15])
CANOPY_HI = np.array([0.85, 0.35, 0.85])
#: Fruit targets are drawn here (inside the canopy, within the Panda's comfortable reach) [m].
FRUIT_LO = np.array([0.45, -0.25, 0.30])
FRUIT_HI = np.array([0.62, 0.25, 0.60])


@dataclass(frozen=True)
class BenchScene:
    """One benchmark scene: robot, start, reference path, obstacles, gains, run length.

    ``controller_cfg`` holds the ``[controller]`` keys (QP settings) shared by every controller.
    """

    name: str
    family: str  # "paper", "planar", "spheres", "free" or "canopy": the scene group it belongs to
    robot: RobotModel
    q0: np.ndarray
    path: WaypointPath
    obstacles: tuple[Obstacle, ...]
    gains: LawGains
    dt: float  # [s]
    duration: float  # [s]
    seed: int | None = None
    controller_cfg: dict[str, Any] = field(default_factory=dict)

    @property
    def target(self) -> np.ndarray:
        """The path's last point [m]."""
        return self.path.points[-1]

    def controller(self, kind: str, solver: str | None = None, *, broadphase: bool | None = None) -> Controller:
        """A fresh controller of ``kind`` (``paper``, ``hsu``, ``qp``) for this scene."""
        cfg = dict(self.controller_cfg, kind=kind)
        if solver is not None:
            cfg["solver"] = solver
        return make_controller(cfg, self.robot, self.path, list(self.obstacles), self.gains, broadphase=broadphase)


def scenario_scene(scenario: str, family: str, name: str | None = None) -> BenchScene:
    """A packaged scenario (by name) as a benchmark scene: its robot, start, path, obstacles, gains,
    dt and duration, and its ``[controller]`` keys (QP settings) for every controller."""
    scen = Scenario.load(scenario)
    robot = scen.build_robot()
    q0 = scen.q0(robot)
    cfg = {k: v for k, v in scen.data["controller"].items() if k not in ("kind", "broadphase")}
    return BenchScene(name or scen.name, family, robot, q0, scen.build_path(robot, q0), tuple(scen.build_obstacles()),
                      scen.gains(), scen.data["sim"]["dt"], scen.data["sim"]["duration"], None, cfg)


def paper_scene() -> BenchScene:
    """The packaged ``paper`` scenario as a benchmark scene."""
    return scenario_scene("paper", "paper")


#: The packaged scenario of the Panda + 10 spheres scene (issue #10's reference scene).
SPHERES_SCENARIO = "panda_spheres"


def spheres_scene() -> BenchScene:
    """The packaged ``panda_spheres`` scenario: the Panda from its home pose to three fruits in turn
    (straight quintic legs of 1.5 s, 0.5 s dwells; 6 s at 1 ms) among 10 sphere obstacles."""
    return scenario_scene(SPHERES_SCENARIO, "spheres", "panda-spheres")


def free_scene(spheres: BenchScene | None = None) -> BenchScene:
    """:func:`spheres_scene`'s task (robot, start, path, gains, QP settings) with no obstacles."""
    base = spheres if spheres is not None else spheres_scene()
    return replace(base, name="panda-free", family="free", obstacles=())


def _segment_distance(a: np.ndarray, b: np.ndarray, p: np.ndarray) -> float:
    ab = b - a
    s = float(np.clip((p - a) @ ab / max(float(ab @ ab), 1e-300), 0.0, 1.0))
    return float(np.linalg.norm(a + s * ab - p))


def _ee_position(robot: RobotModel, q: np.ndarray) -> np.ndarray:
    data = robot.model.createData()
    pin.framesForwardKinematics(robot.model, data, q)
    return data.oMf[robot.ee_frame_id].translation[list(robot.task_axes)].copy()


def _clear_of(centre: np.ndarray, reach: float, segments: Sequence[tuple[np.ndarray, np.ndarray, float]],
              margin: float) -> bool:
    """Whether a shape of bounding radius ``reach`` at ``centre`` keeps ``margin`` from every capsule."""
    return all(_segment_distance(a, b, centre) - r - reach >= margin for a, b, r in segments)


def planar_scene(seed: int, *, duration: float = 3.0) -> BenchScene:
    """The paper's 3-link arm from q₀ = (π, π/2, 0) to a random reachable point past 2–4 random discs."""
    rng = np.random.default_rng(seed)
    robot = planar_arm()
    q0 = robot.q_home.copy()
    start = _ee_position(robot, q0)
    gains = LawGains()
    while True:  # a target 0.8–2 m away whose straight path stays 1–2.7 m from the base
        target = rng.uniform(-2.6, 2.6, 2)
        s = np.linspace(0.0, 1.0, 50)[:, None]
        radii = np.linalg.norm(start + s * (target - start), axis=1)
        if 0.8 < np.linalg.norm(target - start) < 2.0 and radii.min() > 1.0 and radii.max() < 2.7:
            break
    path_seg = (np.append(start, 0.0), np.append(target, 0.0), robot.capsules[-1].radius)
    start_arm = _link_segments(robot, q0)
    obstacles: list[Obstacle] = []
    for _ in range(200):
        if len(obstacles) == int(rng.integers(2, 5)):
            break
        radius = float(rng.uniform(0.08, 0.18))
        along = rng.uniform(0.15, 0.85)
        normal = np.array([-(target - start)[1], (target - start)[0]]) / np.linalg.norm(target - start)
        offset = rng.choice([-1.0, 1.0]) * rng.uniform(0.2, 0.5)
        centre = np.append(start + along * (target - start) + offset * normal, 0.0)
        if _clear_of(centre, radius, [path_seg], 0.05) and _clear_of(centre, radius, start_arm, 0.1) \
                and all(np.linalg.norm(centre - o.position) > radius + o.radius for o in obstacles):
            obstacles.append(Obstacle("sphere", centre, radius=radius, name=f"disc{len(obstacles)}"))
    path = WaypointPath([start, target], duration=duration - 0.5)
    return BenchScene(f"planar-{seed}", "planar", robot, q0, path, tuple(obstacles), gains, 1e-3, duration, seed,
                      {"solver": "proxqp"})


def _canopy_obstacle(rng: np.random.Generator, lo: np.ndarray, hi: np.ndarray, name: str) -> Obstacle:
    """A branch (capsule, 2/5 of the time) or a leaf cluster (sphere) at a uniform place in the box."""
    centre = rng.uniform(lo, hi)
    if rng.random() < 0.4:
        axis = rng.normal(size=3)
        axis[2] = abs(axis[2]) + 0.5  # branches lean upwards
        return Obstacle("capsule", centre, radius=float(rng.uniform(0.01, 0.03)), length=float(rng.uniform(0.15, 0.4)),
                        axis=axis / np.linalg.norm(axis), name=f"branch{name}")
    return Obstacle("sphere", centre, radius=float(rng.uniform(0.02, 0.05)), name=f"leaf{name}")


def canopy_obstacles(rng: np.random.Generator, count: int, lo: np.ndarray, hi: np.ndarray,
                     keep_clear: Sequence[tuple[np.ndarray, np.ndarray, float]], margin: float) -> list[Obstacle]:
    """``count`` branches and leaves in the box [lo, hi], each ``margin`` [m] clear of the given capsules."""
    out: list[Obstacle] = []
    while len(out) < count:
        obs = _canopy_obstacle(rng, lo, hi, str(len(out)))
        if _clear_of(obs.position, obs.bounding_radius(), keep_clear, margin):
            out.append(obs)
    return out


@lru_cache(maxsize=1)
def _panda() -> RobotModel:
    """The Panda, loaded once (every canopy scene shares it; each controller has its own data)."""
    return panda()


def _canopy_config() -> dict[str, Any]:
    return {"solver": "proxqp", "torque_limits": True, "joint_limits": True}


def canopy_scene(seed: int, *, obstacles: int = 10, duration: float = 2.5) -> BenchScene:
    """The Panda from its home pose to a random fruit in a seeded canopy of ``obstacles`` shapes.

    The reference is a straight quintic path (2 s) to the fruit; the path (inflated by the hand's
    capsule radius + 0.06 m) and the starting arm (+ 0.05 m) are kept clear of obstacles.
    """
    rng = np.random.default_rng(seed)
    robot = _panda()
    q0 = robot.q_home.copy()
    start = _ee_position(robot, q0)
    fruit = rng.uniform(FRUIT_LO, FRUIT_HI)
    gains = LawGains(kp=100.0, kv=20.0, kn=10.0, v_ref=0.3, d_influence=0.15, d_safe=0.03)
    hand = robot.capsules[-1].radius
    keep_clear = [(start, fruit, hand + 0.06)] + _link_segments(robot, q0)
    obs = canopy_obstacles(rng, obstacles, CANOPY_LO, CANOPY_HI, keep_clear, 0.05)
    path = WaypointPath([start, fruit], duration=duration - 0.5)
    return BenchScene(f"canopy-{seed}", "canopy", robot, q0, path, tuple(obs), gains, 1e-3, duration, seed,
                      _canopy_config())


def orchard_scene(scene: BenchScene, total: int, *, seed: int = 0) -> BenchScene:
    """``scene``'s canopy plus blocks of the same size and density tiled along the hedge row (±y) up to
    ``total`` obstacles; the added blocks start one cutoff beyond the reach of the arm's workspace."""
    rng = np.random.default_rng(seed)
    extra = total - len(scene.obstacles)
    if extra < 0:
        raise ValueError(f"the scene already has {len(scene.obstacles)} obstacles, more than {total}")
    per_block = max(len(scene.obstacles), 1)
    width = CANOPY_HI[1] - CANOPY_LO[1]
    added: list[Obstacle] = []
    k = 0
    while len(added) < extra:
        k += 1
        for side in (1.0, -1.0):
            shift = np.array([0.0, side * (k * width + 0.6), 0.0])  # 0.6 m: beyond reach + cutoff
            n = min(per_block, extra - len(added))
            added += canopy_obstacles(rng, n, CANOPY_LO + shift, CANOPY_HI + shift, [], 0.0)
            if len(added) >= extra:
                break
    renamed = [replace(o, name=f"row{i}") for i, o in enumerate(added)]
    return replace(scene, name=f"{scene.name}-x{total}", obstacles=scene.obstacles + tuple(renamed))
