"""Link–obstacle distances with witness points and normals, from python-fcl.

For each (link capsule, obstacle) pair closer than a cutoff the engine returns the signed distance
d [m] (negative when penetrating), the witness points on the link and on the obstacle, and the
unit normal n pointing from the obstacle to the link, so that moving the link point along n
increases d (∂d/∂p_link = nᵀ).

With many obstacles a broad phase prunes the far pairs first: the link capsules, inflated by the
cutoff, are collided against python-fcl's dynamic AABB tree of obstacles, and only the pairs that
touch get an exact distance query — so obstacles farther than the cutoff cost (almost) nothing.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import fcl
import numpy as np

from qpctl.geometry.obstacles import Obstacle, rotation_z_to

_UNSIGNED = fcl.DistanceRequest(enable_nearest_points=True, enable_signed_distance=False)
_SIGNED = fcl.DistanceRequest(enable_nearest_points=True, enable_signed_distance=True)


def signed_distance(o1: fcl.CollisionObject, o2: fcl.CollisionObject) -> tuple[float, fcl.DistanceResult]:
    """Signed distance [m] and python-fcl's result (nearest points on o1, o2).

    Separated shapes use fcl's plain distance query, which is closed-form for sphere and capsule
    pairs (exact to rounding); fcl's signed query runs GJK/EPA for every pair and is off by up to
    ~1e-4 m in distance and ~1e-3 m in witness points. Only penetrating pairs pay for it.
    """
    res = fcl.DistanceResult()
    d = fcl.distance(o1, o2, _UNSIGNED, res)
    if d > 0.0:
        return d, res
    res = fcl.DistanceResult()
    return fcl.distance(o1, o2, _SIGNED, res), res


@dataclass(frozen=True)
class PairSet:
    """The link–obstacle pairs within the cutoff at one instant (k pairs; arrays in world frame, [m])."""

    link: np.ndarray  # (k,) int, index into the robot's capsules
    obstacle: np.ndarray  # (k,) int, index into the obstacle list
    distance: np.ndarray  # (k,) signed distance d
    normal: np.ndarray  # (k, 3) unit normal, obstacle → link
    p_link: np.ndarray  # (k, 3) witness point on the link
    p_obstacle: np.ndarray  # (k, 3) witness point on the obstacle
    v_obstacle: np.ndarray  # (k, 3) obstacle velocity [m/s]
    a_obstacle: np.ndarray  # (k, 3) obstacle acceleration [m/s²]

    def __len__(self) -> int:
        return int(self.link.shape[0])

    @staticmethod
    def empty() -> "PairSet":
        z = np.zeros((0, 3))
        return PairSet(np.zeros(0, int), np.zeros(0, int), np.zeros(0), z, z, z, z, z)


def closest_point_on_segment(a: np.ndarray, b: np.ndarray, p: np.ndarray) -> np.ndarray:
    ab = b - a
    denom = float(ab @ ab)
    s = 0.0 if denom == 0 else float(np.clip((p - a) @ ab / denom, 0.0, 1.0))
    return a + s * ab


class DistanceEngine:
    """Distances between a robot's link capsules and a set of obstacles.

    Args:
        radii: capsule radius of each link [m].
        obstacles: the scene.
        broadphase: prune far pairs with python-fcl's dynamic AABB tree; ``None`` turns it on for
            more than 16 obstacles.
    """

    def __init__(self, radii: Sequence[float], obstacles: Sequence[Obstacle], broadphase: bool | None = None):
        self.radii = np.asarray(radii, float)
        self.obstacles = list(obstacles)
        self.broadphase = len(self.obstacles) > 16 if broadphase is None else bool(broadphase)
        self._obs_objs = [fcl.CollisionObject(o.geometry(), o.transform(0.0)) for o in self.obstacles]
        self._moving = [i for i, o in enumerate(self.obstacles) if o.moving]
        self._link_objs = [fcl.CollisionObject(fcl.Capsule(r, 1e-9)) for r in self.radii]
        self._link_len = np.full(len(self.radii), np.nan)
        self._inflated: list[fcl.CollisionObject] = []
        self._inflate = np.nan
        self._t = 0.0
        self._by_position: dict[tuple[float, ...], list[int]] | None = None
        if self.broadphase:
            self._manager = fcl.DynamicAABBTreeCollisionManager()
            self._manager.registerObjects(self._obs_objs)
            self._manager.setup()

    # -- pose updates -------------------------------------------------------------------------
    def _capsule_pose(self, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        axis = b - a
        length = float(np.linalg.norm(axis))
        rot = rotation_z_to(axis) if length > 1e-12 else np.eye(3)
        return rot, (a + b) / 2, length

    def update(self, segments: np.ndarray, t: float) -> None:
        """Set the link segments ((L, 2, 3) world endpoints [m]) and the obstacles' poses at time t [s]."""
        self._segments = segments
        for i, (a, b) in enumerate(segments):
            rot, mid, length = self._capsule_pose(a, b)
            if not abs(length - self._link_len[i]) <= 1e-12:  # first call (NaN) or a new length: rebuild
                self._link_objs[i] = fcl.CollisionObject(fcl.Capsule(self.radii[i], max(length, 1e-9)))
                self._link_len[i] = length
            self._link_objs[i].setTransform(fcl.Transform(rot, mid))
        if t != self._t or not self._moving:
            for j in self._moving:
                self._obs_objs[j].setTransform(self.obstacles[j].transform(t))
            if self.broadphase and self._moving:
                self._manager.update()
                self._by_position = None
        self._t = t

    # -- queries ------------------------------------------------------------------------------
    def _candidates(self, cutoff: float) -> list[tuple[int, int]]:
        nl, no = len(self._link_objs), len(self._obs_objs)
        if not self.broadphase or not np.isfinite(cutoff):
            return [(i, j) for i in range(nl) for j in range(no)]
        if self._inflate != cutoff or len(self._inflated) != nl:
            self._inflated = [fcl.CollisionObject(fcl.Capsule(r + cutoff, max(L, 1e-9)))
                              for r, L in zip(self.radii, self._link_len)]
            self._inflate = cutoff
        # python-fcl hands the callback new wrappers of the registered objects (their ids differ),
        # so obstacles are recognised by their exact current translation; a shared translation
        # only adds candidates, which the exact distance query then filters.
        if self._by_position is None:
            self._by_position = {}
            for j, o in enumerate(self._obs_objs):
                self._by_position.setdefault(tuple(o.getTranslation()), []).append(j)
        lookup = self._by_position
        found: list[tuple[int, int]] = []
        for i, (obj, infl) in enumerate(zip(self._link_objs, self._inflated)):
            infl.setTransform(obj.getTransform())
            hits: list[int] = []

            def callback(o1: fcl.CollisionObject, o2: fcl.CollisionObject, _data: object,
                         hits: list[int] = hits) -> bool:
                if fcl.collide(o1, o2, fcl.CollisionRequest(), fcl.CollisionResult()):
                    for o in (o1, o2):
                        hits.extend(lookup.get(tuple(o.getTranslation()), ()))
                return False

            self._manager.collide(infl, None, callback)
            found.extend((i, j) for j in sorted(set(hits)))
        return found

    def pair(self, i: int, j: int) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
        """Signed distance d [m], unit normal n (obstacle → link), witness points on link and obstacle."""
        d, res = signed_distance(self._link_objs[i], self._obs_objs[j])
        return (d, *self._witness(i, j, d, res))

    def _witness(self, i: int, j: int, d: float, res: fcl.DistanceResult
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        p_link, p_obs = np.asarray(res.nearest_points[0]), np.asarray(res.nearest_points[1])
        diff = p_link - p_obs
        nd = float(np.linalg.norm(diff))
        if d > 1e-6:
            # GJK's witness point on a capsule can be off by ~1e-4 m along the axis (the flat
            # direction); the exact one is the axis point closest to the obstacle's witness,
            # pushed out by the radius. It matters for the barrier's drift (ḣ to ~1e-6 m/s).
            a, b = self._segments[i]
            w = closest_point_on_segment(a, b, p_obs) - p_obs
            wn = float(np.linalg.norm(w))
            n = w / wn if wn > 1e-9 else diff / max(nd, 1e-12)
            p_link = p_obs + n * (wn - self.radii[i]) if wn > 1e-9 else p_link
        elif nd > 1e-6 and abs(d) > 1e-9:
            n = np.sign(d) * diff / nd
        else:  # touching (witness points < 1 µm apart, their direction is rounding noise):
            # fall back on the direction from the obstacle's centre to the link's axis
            c = self.obstacles[j].position_at(self._t)
            a, b = self._segments[i]
            w = closest_point_on_segment(a, b, c) - c
            n = w / max(float(np.linalg.norm(w)), 1e-12)
        return n, p_link, p_obs

    def pairs(self, cutoff: float = np.inf) -> PairSet:
        """All pairs with signed distance below ``cutoff`` [m]."""
        rows = []
        for i, j in self._candidates(cutoff):
            d, res = signed_distance(self._link_objs[i], self._obs_objs[j])
            if d >= cutoff:
                continue
            n, p_link, p_obs = self._witness(i, j, d, res)
            rows.append((i, j, d, n, p_link, p_obs))
        if not rows:
            return PairSet.empty()
        link = np.array([r[0] for r in rows], int)
        obs = np.array([r[1] for r in rows], int)
        v = np.array([self.obstacles[j].velocity_at(self._t) for j in obs])
        a = np.array([self.obstacles[j].acceleration_at(self._t) for j in obs])
        return PairSet(link, obs, np.array([r[2] for r in rows], float), np.array([r[3] for r in rows]),
                       np.array([r[4] for r in rows]), np.array([r[5] for r in rows]), v, a)

    def min_distance(self) -> float:
        """Least signed distance [m] between any link and any obstacle (inf with no obstacles)."""
        if not self._obs_objs:
            return float("inf")
        best = float("inf")
        for lo in self._link_objs:
            for oo in self._obs_objs:
                best = min(best, signed_distance(lo, oo)[0])
        return best
