"""Which of a robot's link capsules are kept apart, and python-fcl's distances between them.

Pairs are left out, as Pink and mink leave them out (their SRDF-style "disabled collisions"):

* **adjacent** — the capsules of one joint, or of a joint and its parent: they touch at the joint by
  construction;
* **always close** — nearer than ``d_safe`` at the robot's home configuration, or in more than half
  of ``samples`` seeded random configurations within the joint limits: a barrier on such a pair
  would hold the arm near its start or be infeasible from it (for the Panda: its wrist's links 5–7).

A robot with an SRDF (``robot.srdf``; :mod:`qpctl.robot.srdf`) whose capsules name their links
(fitted ones do) leaves out instead the pairs the SRDF disables (every pair of the two capsules'
links disabled), the capsules of one rigid body (one joint) and of a joint and its parent, and those
nearer than ``d_safe`` at home; no sampling.

:func:`self_collision_pairs` returns what is kept and why the rest is not; a scenario may name its
own pairs instead (``controller.self_collision_pairs``). The distances the tick computes in closed
form (:func:`qpctl.kernels.self_pairs.self_pairs`) are held against :func:`fcl_self_distances` in the tests.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import fcl
import numpy as np
import pinocchio as pin

from qpctl.errors import ConfigError
from qpctl.robot.model import RobotModel

ALWAYS_CLOSE_FRACTION = 0.5


@dataclass(frozen=True)
class SelfPairs:
    """Capsule index pairs (i < j) kept apart, and those left out with the reason."""

    pairs: tuple[tuple[int, int], ...]
    excluded: dict[tuple[int, int], str]

    def names(self, robot: RobotModel) -> list[tuple[str, str]]:
        return [(robot.capsules[i].name, robot.capsules[j].name) for i, j in self.pairs]


def _segments(robot: RobotModel, data: pin.Data, q: np.ndarray) -> np.ndarray:
    pin.forwardKinematics(robot.model, data, q)
    return np.array([[data.oMi[c.joint_id].act(c.p0), data.oMi[c.joint_id].act(c.p1)] for c in robot.capsules])


def segment_distance(a0: np.ndarray, a1: np.ndarray, b0: np.ndarray, b1: np.ndarray) -> float:
    """Least distance between two segments [m] (by a fine sampling refined with a projection: an
    independent check of the closed form, used only off the tick)."""
    s = np.linspace(0.0, 1.0, 201)
    pa = a0 + s[:, None] * (a1 - a0)
    d = b1 - b0
    dd = float(d @ d)
    t = np.clip(((pa - b0) @ d) / dd, 0.0, 1.0) if dd > 0 else np.zeros_like(s)
    pb = b0 + t[:, None] * d
    return float(np.min(np.linalg.norm(pa - pb, axis=1)))


def adjacent(robot: RobotModel, i: int, j: int) -> bool:
    """Capsules i and j on one joint, or on a joint and its parent."""
    a, b = robot.capsules[i].joint_id, robot.capsules[j].joint_id
    parents = robot.model.parents
    return a == b or parents[a] == b or parents[b] == a


_CACHE: dict[tuple[object, ...], SelfPairs] = {}


def self_collision_pairs(robot: RobotModel, d_safe: float, *, samples: int = 200, seed: int = 0) -> SelfPairs:
    """The capsule pairs a self-collision barrier keeps ``d_safe`` [m] apart (module docstring);
    remembered per robot geometry (a controller or simulator built again does not sample again)."""
    srdf = robot.disabled_pairs if robot.disabled_pairs is not None and any(c.links for c in robot.capsules) else None
    key = (robot.name, robot.model.nq, tuple((c.joint_id, *c.p0, *c.p1, c.radius, c.links) for c in robot.capsules),
           tuple(robot.q_min), tuple(robot.q_max), tuple(robot.q_home), tuple(robot.model.parents),
           float(d_safe), samples, seed, srdf)
    if key not in _CACHE:
        _CACHE[key] = _select(robot, d_safe, samples, seed) if srdf is None else _select_srdf(robot, d_safe, srdf)
    return _CACHE[key]


def _select_srdf(robot: RobotModel, d_safe: float, disabled: frozenset[frozenset[str]]) -> SelfPairs:
    """The pairs an SRDF leaves (module docstring)."""
    data = robot.model.createData()
    home = _segments(robot, data, robot.q_home)
    caps = robot.capsules
    keep, excluded = [], {}
    for i in range(len(caps)):
        for j in range(i + 1, len(caps)):
            a, b = caps[i], caps[j]
            if a.joint_id == b.joint_id:
                excluded[(i, j)] = "one rigid body"
            elif adjacent(robot, i, j):
                excluded[(i, j)] = "adjacent"
            elif a.links and b.links and all(la == lb or frozenset((la, lb)) in disabled
                                               for la in a.links for lb in b.links):
                excluded[(i, j)] = "disabled by the SRDF"
            elif segment_distance(*home[i], *home[j]) < a.radius + b.radius + d_safe:
                excluded[(i, j)] = "within d_safe at home"
            else:
                keep.append((i, j))
    return SelfPairs(tuple(keep), excluded)


def _select(robot: RobotModel, d_safe: float, samples: int, seed: int) -> SelfPairs:
    L = len(robot.capsules)
    data = robot.model.createData()
    rng = np.random.default_rng(seed)
    lo = np.where(np.isfinite(robot.q_min), robot.q_min, -np.pi)
    hi = np.where(np.isfinite(robot.q_max), robot.q_max, np.pi)
    radius = np.array([c.radius for c in robot.capsules])
    home = _segments(robot, data, robot.q_home)
    close = np.zeros((L, L), int)
    segs = [_segments(robot, data, robot.random_configuration(rng, lo, hi)) for _ in range(samples)]
    keep, excluded = [], {}
    for i in range(L):
        for j in range(i + 1, L):
            if adjacent(robot, i, j):
                excluded[(i, j)] = "adjacent"
                continue
            gap = radius[i] + radius[j] + d_safe
            if segment_distance(*home[i], *home[j]) < gap:
                excluded[(i, j)] = "within d_safe at home"
                continue
            close[i, j] = sum(segment_distance(*s[i], *s[j]) < gap for s in segs)
            if close[i, j] > ALWAYS_CLOSE_FRACTION * samples:
                excluded[(i, j)] = f"within d_safe in {close[i, j]} of {samples} random configurations"
                continue
            keep.append((i, j))
    return SelfPairs(tuple(keep), excluded)


def named_pairs(robot: RobotModel, names: Sequence[Sequence[str]]) -> SelfPairs:
    """Pairs given by the capsules' names (``controller.self_collision_pairs``)."""
    index = {c.name: k for k, c in enumerate(robot.capsules)}
    out = []
    for pair in names:
        if len(pair) != 2 or any(n not in index for n in pair) or pair[0] == pair[1]:
            raise ConfigError(f"each entry needs two different link names among {list(index)}, got {list(pair)}",
                              key="controller.self_collision_pairs")
        i, j = sorted((index[pair[0]], index[pair[1]]))
        out.append((i, j))
    return SelfPairs(tuple(dict.fromkeys(out)), {})


def capsule_object(a: np.ndarray, b: np.ndarray, radius: float) -> fcl.CollisionObject:
    """The capsule of axis a–b [m] and ``radius`` [m] as a python-fcl object (a point's: a sphere)."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    axis = b - a
    length = float(np.linalg.norm(axis))
    z = axis / length if length > 1e-12 else np.array([0.0, 0.0, 1.0])
    R = pin.Quaternion.FromTwoVectors(np.array([0.0, 0.0, 1.0]), z).matrix()
    return fcl.CollisionObject(fcl.Capsule(float(radius), length), fcl.Transform(R, 0.5 * (a + b)))


def fcl_self_distances(robot: RobotModel, q: np.ndarray, pairs: Sequence[tuple[int, int]]) -> np.ndarray:
    """Signed-free distances [m] between the pairs' capsules by python-fcl (0 where they overlap)."""
    data = robot.model.createData()
    seg = _segments(robot, data, np.asarray(q, float))
    objects = [capsule_object(seg[k][0], seg[k][1], c.radius) for k, c in enumerate(robot.capsules)]
    out = np.empty(len(pairs))
    for k, (i, j) in enumerate(pairs):
        res = fcl.DistanceResult()
        out[k] = fcl.distance(objects[i], objects[j], fcl.DistanceRequest(), res)
    return out
