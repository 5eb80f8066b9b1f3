"""Seeded canopies: a fruiting wall a depth camera sees and an arm reaches into.

A scenario names a canopy by its seed (``[canopy] seed = 7``, :class:`CanopyConfig`) instead of listing
its shapes; :func:`generate_canopy` grows it, the same for the same keys:

* the **row**: a trunk (a vertical capsule) in the plane x = ``row_x`` and ``wires`` trellis wires
  (horizontal capsules of 1.5 mm radius along y, just in front of it) — rigid, known to the
  controller as primitives;
* **fruits** (spheres of ``fruit_radius``) in the ``depth`` in front of the row: shapes only a camera
  sees (scenery: the gripper takes them, no clearance is kept to them). Each is checked: within the
  arm's reach, reached by a joint configuration within the limits (damped least squares from the
  start configuration and a few seeded ones), and with that configuration clear of the row by d_safe.
  The reachable ones, in nearest-first order from the start, become the path's waypoints; the others
  are reported with the reason (:attr:`Fruit.reason`);
* ``branches`` (rigid capsules of 8–20 mm radius, 0.2–0.45 m long) from the trunk and the wires
  towards the arm — perceived: the controller knows them only through the depth map;
* ``leaves`` (soft spheres of ``leaf_radius``), perceived: ``occluding_leaves`` in front of each fruit
  as seen from the viewpoint (the scenario's world camera, else the task point at the start), each
  hiding part of it, and the rest in clusters along the branches, the trunk and the wires.

Every branch keeps the hand's capsule + d_safe + 3 cm off the reference path (straight legs from the
start through the reachable fruits) and 2 cm + d_safe off the arm at each fruit's configuration;
leaves other than the occluding ones keep off the hand's capsule along the path; nothing comes within
3 cm of the arm at the start. So a collision with a branch is the controller's doing, and the hand
meets leaves only at the fruits it reaches for. Leaves are spheres rather than discs: the true
clearance and the soft-contact metrics over a few hundred of them then stay closed-form at 1 kHz
(python-fcl would take ~10 µs a disc–link pair). A draw that does not fit (after 200 tries for each
shape) is left out, and the canopy's counts say so.

:func:`qpctl.scenario.depth_canopies` gives the packaged ``panda_canopy_depth`` scenario under 20 seeds.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
import pinocchio as pin

from qpctl.config import check_fields, setting
from qpctl.errors import ConfigError
from qpctl.geometry.obstacles import Obstacle
from qpctl.kernels.geometry import capsule_pair
from qpctl.robot.model import RobotModel, arm_reach

WIRE_RADIUS = 0.0015  # [m] a 3 mm trellis wire
TRIES = 200  # draws per shape before it is left out
START_MARGIN = 0.03  # [m] every shape off the arm at the start
PATH_MARGIN = 0.03  # [m] branches off the hand along the path, beyond the hand's radius + d_safe
POSE_MARGIN = 0.02  # [m] branches off the arm at each fruit, beyond d_safe
IK_TOL = 1e-3  # [m] a configuration reaches a fruit when its task point is this close (iterated to 1e-5)
IK_STARTS = 6  # configurations tried per fruit: the start and seeded draws about it


@dataclass(frozen=True, kw_only=True)
class CanopyConfig:
    """The ``[canopy]`` keys of a scenario (each declared here once; :func:`qpctl.config.schema_of`).

    seed: names the canopy (None: no canopy). leaves, branches, fruits, wires: how many.
    row_x [m]: the row's plane (trunk, wires) at x = row_x; depth [m]: how far the canopy reaches
    towards the arm; width [m]: its extent along y about y = 0; z_range [m]: its heights.
    leaf_radius [m]: the leaves' radii (least, largest); fruit_radius [m]; occluding_leaves: leaves
    set in front of each fruit.
    """

    seed: int | None = None
    leaves: int = setting(300, valid="nonnegative")
    branches: int = setting(12, valid="nonnegative")
    fruits: int = setting(3, valid="positive")
    wires: int = setting(3, valid="nonnegative")
    row_x: float = setting(0.8, valid="positive", unit="m")
    depth: float = setting(0.45, valid="positive", unit="m")
    width: float = setting(1.2, valid="positive", unit="m")
    z_range: list[float] = dataclasses.field(default_factory=lambda: [0.15, 1.0])
    leaf_radius: list[float] = dataclasses.field(default_factory=lambda: [0.02, 0.04])
    fruit_radius: float = setting(0.035, valid="positive", unit="m")
    occluding_leaves: int = setting(2, valid="nonnegative")

    def __post_init__(self) -> None:
        check_fields(self, "canopy")
        if self.seed is not None and self.seed < 0:
            raise ConfigError(f"must be an integer >= 0, got {self.seed}", key="canopy.seed")
        for name in ("z_range", "leaf_radius"):
            lo_hi = getattr(self, name)
            if len(lo_hi) != 2 or not all(math.isfinite(v) for v in lo_hi) or not 0 <= lo_hi[0] <= lo_hi[1]:
                raise ConfigError(f"needs two numbers 0 <= least <= largest [m], got {lo_hi}", key=f"canopy.{name}")
        if self.leaf_radius[0] <= 0:
            raise ConfigError(f"needs positive radii, got {self.leaf_radius}", key="canopy.leaf_radius")
        if self.z_range[1] - self.z_range[0] < 0.2:
            raise ConfigError(f"must span at least 0.2 m, got {self.z_range}", key="canopy.z_range")
        if self.depth >= self.row_x:
            raise ConfigError(f"depth {self.depth} m must be less than row_x {self.row_x} m (the canopy stays in "
                              "front of the arm's base)", key="canopy.depth")

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> CanopyConfig:
        """From the validated ``[canopy]`` table."""
        return cls(**{f.name: d[f.name] for f in dataclasses.fields(cls) if f.name in d})

    @property
    def enabled(self) -> bool:
        return self.seed is not None


class Fruit(NamedTuple):
    """A fruit of the canopy: where [m], how big [m], whether the arm can reach it and, if not, why;
    ``q``: a configuration whose task point is at it — clear of the row if reachable, else the
    clearest tried, the one the reason describes (None: no configuration reaches it)."""

    name: str
    position: np.ndarray
    radius: float
    reachable: bool
    reason: str
    q: np.ndarray | None


@dataclass(frozen=True)
class Canopy:
    """A generated canopy (module docstring): its obstacles (row, branches, leaves), its fruits, and the
    reachable fruits' positions in path order (``waypoints``, (k, 3) [m])."""

    config: CanopyConfig
    obstacles: list[Obstacle]
    fruits: list[Fruit]
    waypoints: np.ndarray

    def count(self, prefix: str) -> int:
        """How many obstacles are named ``prefix…`` ("leaf", "branch", "wire", "trunk")."""
        return sum(o.name.startswith(prefix) for o in self.obstacles)

    def scenery(self) -> list[Obstacle]:
        """The fruits as spheres, for a camera (no clearance is kept to them)."""
        return [Obstacle("sphere", f.position, radius=f.radius, name=f.name) for f in self.fruits]

    def summary(self) -> dict[str, Any]:
        """What was grown and which fruits can be reached, for a run's metrics."""
        return {"seed": self.config.seed, "leaves": self.count("leaf"), "branches": self.count("branch"),
                "wires": self.count("wire"),
                "fruits": [{"name": f.name, "position": [round(float(x), 4) for x in f.position],
                            "reachable": f.reachable, **({"reason": f.reason} if f.reason else {})}
                           for f in self.fruits]}


# -- geometry -----------------------------------------------------------------------------------------
Capsule = tuple[np.ndarray, np.ndarray, float]  # axis ends [m], radius [m]


def _axis(obs: Obstacle) -> Capsule:
    """A sphere's or capsule's axis segment and radius."""
    if obs.shape == "sphere":
        return obs.position, obs.position, obs.radius
    half = 0.5 * obs.length * obs.axis / np.linalg.norm(obs.axis)
    return obs.position - half, obs.position + half, obs.radius


_SCRATCH = (np.zeros(3), np.zeros(3), np.zeros(3))


def _gap(a: Capsule, b: Capsule) -> float:
    """Signed distance [m] between two capsules (a sphere: a zero-length axis)."""
    return float(capsule_pair(a[0], a[1], a[2], b[0], b[1], b[2], *_SCRATCH))


def _clear(shape: Capsule, others: Sequence[Capsule], margin: float) -> bool:
    return all(_gap(shape, o) >= margin for o in others)


def link_capsules(robot: RobotModel, q: np.ndarray) -> list[Capsule]:
    """The robot's link capsules at q, in the world."""
    data = robot.model.createData()
    pin.forwardKinematics(robot.model, data, q)
    return [(data.oMi[c.joint_id].act(c.p0), data.oMi[c.joint_id].act(c.p1), c.radius) for c in robot.capsules]


def task_point(robot: RobotModel, q: np.ndarray) -> np.ndarray:
    data = robot.model.createData()
    pin.framesForwardKinematics(robot.model, data, q)
    return np.array(data.oMf[robot.ee_frame_id].translation)


def reach(robot: RobotModel, target: np.ndarray, q_start: np.ndarray, iterations: int = 300) -> tuple[np.ndarray, float]:
    """A configuration within the joint limits whose task point is at ``target`` [m], by damped least
    squares from q_start with a pull towards it in the null space; (q, the remaining error [m])."""
    model, data, fid = robot.model, robot.model.createData(), robot.ee_frame_id
    lo = np.where(np.isfinite(robot.q_min), robot.q_min, -np.pi)
    hi = np.where(np.isfinite(robot.q_max), robot.q_max, np.pi)
    q = robot.configuration(np.clip(robot.angles(q_start), lo, hi))
    err = math.inf
    for _ in range(iterations):
        pin.framesForwardKinematics(model, data, q)
        e = target - data.oMf[fid].translation
        err = float(np.linalg.norm(e))
        if err < 1e-5:
            break
        J = pin.computeFrameJacobian(model, data, q, fid, pin.LOCAL_WORLD_ALIGNED)[:3]
        JJt = J @ J.T + 1e-4 * np.eye(3)
        step = J.T @ np.linalg.solve(JJt, e)
        pull = 0.1 * robot.difference(q, q_start)
        step += pull - J.T @ np.linalg.solve(JJt, J @ pull)
        q = robot.configuration(np.clip(robot.angles(robot.integrate(q, np.clip(step, -0.3, 0.3))), lo, hi))
    return q, err


def _fruit_reach(robot: RobotModel, fruit: np.ndarray, q0: np.ndarray, row: list[tuple[str, Capsule]], d_safe: float,
                 rng: np.random.Generator) -> tuple[np.ndarray | None, str]:
    """(a configuration reaching the fruit clear of the row, "") or (None or the best one, the reason not)."""
    bound = arm_reach(robot)
    if bound is not None:
        centre, radius = bound
        far = float(np.linalg.norm(fruit - centre))
        if far > radius:
            return None, f"beyond the arm's reach: {far:.3f} m from its first joint, which reaches {radius:.3f} m"
    starts = [q0] + [robot.integrate(q0, rng.uniform(-0.6, 0.6, robot.nv)) for _ in range(IK_STARTS - 1)]
    best: tuple[float, np.ndarray, str] | None = None
    closest = math.inf
    for start in starts:
        q, err = reach(robot, fruit, start)
        closest = min(closest, err)
        if err >= IK_TOL:
            continue
        arm = link_capsules(robot, q)
        gaps = [(min(_gap(link, cap) for link in arm), name) for name, cap in row]
        gap, name = min(gaps) if gaps else (math.inf, "")
        if best is None or gap > best[0]:
            best = (gap, q, name)
        if gap >= d_safe:
            return q, ""
    if best is None:
        return None, f"no configuration within the joint limits reaches it (closest {1e3 * closest:.1f} mm)"
    gap, q, name = best
    where = f"cuts {-gap:.3f} m into {name}" if gap < 0 else f"comes within {gap:.3f} m of {name}"
    return q, f"the arm reaching it {where} (d_safe {d_safe} m) in every configuration tried"


def _greedy_order(start: np.ndarray, points: list[np.ndarray]) -> list[int]:
    order, left, at = [], list(range(len(points))), start
    while left:
        k = min(left, key=lambda i: float(np.linalg.norm(points[i] - at)))
        order.append(k)
        left.remove(k)
        at = points[k]
    return order


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def generate_canopy(config: CanopyConfig, robot: RobotModel, q0: np.ndarray, *, d_safe: float = 0.03,
                    viewpoint: np.ndarray | None = None) -> Canopy:
    """Grow the canopy of ``config`` (its seed must be set) in front of ``robot`` starting at ``q0``
    (module docstring); ``d_safe`` [m] is the clearance the reachability check and the branches keep,
    ``viewpoint`` [m] where the occluding leaves hide the fruits from (default: the task point at q0)."""
    if config.seed is None:
        raise ConfigError("a canopy needs its seed", key="canopy.seed")
    if tuple(robot.task_axes) != (0, 1, 2):
        raise ConfigError(f"needs a spatial arm (task axes x, y, z); {robot.name}'s are {list(robot.task_axes)}",
                          key="canopy.seed")
    rng = np.random.default_rng(config.seed)
    cfg = config
    z_lo, z_hi = cfg.z_range
    start = task_point(robot, q0)
    eye = start if viewpoint is None else np.asarray(viewpoint, float)
    start_arm = link_capsules(robot, q0)
    hand = max(c.radius for c in robot.capsules)

    # the row: trunk and wires (rigid, known)
    trunk_r = float(rng.uniform(0.05, 0.07))
    top = z_hi + 0.15
    trunk = Obstacle("capsule", np.array([cfg.row_x, float(rng.uniform(-0.1, 0.1)) * cfg.width, 0.5 * top]),
                     radius=trunk_r, length=top, name="trunk")
    row = [trunk]
    for k in range(cfg.wires):
        z = z_lo + (k + 1) * (z_hi - z_lo) / (cfg.wires + 1) + float(rng.uniform(-0.03, 0.03))
        row.append(Obstacle("capsule", np.array([cfg.row_x - trunk_r - WIRE_RADIUS, 0.0, z]), radius=WIRE_RADIUS,
                            length=cfg.width + 0.6, axis=np.array([0.0, 1.0, 0.0]), name=f"wire{k}"))
    row_caps = [(o.name, _axis(o)) for o in row]
    if not all(_clear(c, start_arm, START_MARGIN) for _, c in row_caps):
        raise ConfigError("the trunk or a wire touches the arm at its start; move canopy.row_x away", key="canopy.row_x")

    # fruits, each checked
    fruits: list[Fruit] = []
    spots: list[np.ndarray] = []
    for k in range(cfg.fruits):
        for _ in range(TRIES):
            p = rng.uniform([cfg.row_x - cfg.depth, -0.4 * cfg.width, z_lo + 0.05],
                            [cfg.row_x - trunk_r - cfg.fruit_radius, 0.4 * cfg.width, z_hi - 0.05])
            me = (p, p, cfg.fruit_radius)
            if (_clear(me, [c for _, c in row_caps], 0.005) and _clear(me, start_arm, START_MARGIN)
                    and all(np.linalg.norm(p - s) > 0.15 for s in spots)):
                break
        else:
            continue
        spots.append(p)
        q, reason = _fruit_reach(robot, p, q0, row_caps, d_safe, rng)
        fruits.append(Fruit(f"fruit{k}", p, cfg.fruit_radius, not reason, reason, q))
    reachable = [f for f in fruits if f.reachable]
    if not reachable:
        why = "; ".join(f"{f.name}: {f.reason}" for f in fruits) or "no fruit fits the canopy"
        raise ConfigError(f"seed {cfg.seed} grows no fruit the arm can reach ({why})", key="canopy.seed")
    order = _greedy_order(start, [f.position for f in reachable])
    waypoints = np.array([reachable[i].position for i in order])
    legs = list(zip(np.vstack([start, waypoints[:-1]]), waypoints, strict=True))
    corridor = [(a, b, hand + d_safe + PATH_MARGIN) for a, b in legs]  # the hand along the path, inflated
    poses = [c for f in reachable for c in link_capsules(robot, f.q)]  # type: ignore[arg-type]

    def keeps_off(shape: Capsule, margin_start: float) -> bool:
        return (_clear(shape, start_arm, margin_start)
                and all(_gap(shape, (a, b, 0.0)) >= r for a, b, r in corridor))

    # branches (rigid, perceived) from the trunk and the wires towards the arm
    branches: list[Obstacle] = []
    for k in range(cfg.branches):
        for _ in range(TRIES):
            length, radius = float(rng.uniform(0.2, 0.45)), float(rng.uniform(0.008, 0.02))
            if cfg.wires and rng.random() < 0.5:
                wire = row[1 + int(rng.integers(cfg.wires))]
                base = np.array([wire.position[0], rng.uniform(-0.5, 0.5) * cfg.width, wire.position[2]])
                yaw = float(rng.uniform(-1.3, 1.3))
            else:
                base = np.array([trunk.position[0], trunk.position[1], rng.uniform(z_lo, z_hi)])
                yaw = float(rng.uniform(-1.2, 1.2))
            pitch = float(rng.uniform(-0.4, 0.6))
            direction = np.array([-math.cos(pitch) * math.cos(yaw), math.cos(pitch) * math.sin(yaw), math.sin(pitch)])
            tip = base + length * direction
            me = (base, tip, radius)
            if keeps_off(me, START_MARGIN) and _clear(me, poses, d_safe + POSE_MARGIN) and tip[2] > 0.05:
                branches.append(Obstacle("capsule", 0.5 * (base + tip), radius=radius, length=length, axis=direction,
                                         name=f"branch{k}", perceived=True))
                break

    # leaves (soft, perceived): in front of each fruit, then in clusters along the branches and the row
    leaves: list[Obstacle] = []
    fruit_caps = [(f.position, f.position, f.radius) for f in fruits]

    def add_leaf(centre: np.ndarray, radius: float, along_path: bool) -> bool:
        me = (centre, centre, radius)
        if not _clear(me, fruit_caps, 0.002) or not _clear(me, start_arm, START_MARGIN) or centre[2] < radius:
            return False
        if not along_path and not all(_gap(me, (a, b, 0.0)) >= hand for a, b, _ in corridor):
            return False
        leaves.append(Obstacle("sphere", centre, radius=radius, name=f"leaf{len(leaves)}", material="soft",
                               perceived=True))
        return True

    r_lo, r_hi = cfg.leaf_radius
    for f in fruits:
        view = _unit(eye - f.position)
        side = _unit(np.cross(view, rng.normal(size=3)))
        for _ in range(cfg.occluding_leaves):
            for _ in range(TRIES):
                r = float(rng.uniform(r_lo, r_hi))
                turn = rng.uniform(0.0, 2.0 * math.pi)
                lateral = math.cos(turn) * side + math.sin(turn) * np.cross(view, side)
                centre = f.position + (f.radius + r + 0.004) * view + rng.uniform(0.4, 1.0) * f.radius * lateral
                if add_leaf(centre, r, along_path=True):
                    break
    holders = [_axis(o) for o in branches] + [c for _, c in row_caps]
    weights = np.array([3.0] * len(branches) + [1.0] * len(row_caps))
    while len(leaves) < cfg.leaves:
        for _ in range(TRIES):
            a, b, r_h = holders[int(rng.choice(len(holders), p=weights / weights.sum()))]
            s = float(rng.uniform(0.3, 1.0)) if len(holders) > len(row_caps) else float(rng.uniform())
            r = float(rng.uniform(r_lo, r_hi))
            centre = a + s * (b - a) + rng.uniform(r_h + 0.3 * r, 0.12) * _unit(rng.normal(size=3))
            if abs(centre[1]) <= 0.5 * cfg.width + 0.1 and add_leaf(centre, r, along_path=False):
                break
        else:
            break
    return Canopy(config, row + branches + leaves, fruits, waypoints)

