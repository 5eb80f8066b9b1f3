"""Link–obstacle distances with witness points and normals, from python-fcl.

For each (link capsule, obstacle) pair closer than a cutoff the engine returns the signed distance
d [m] (negative when penetrating), the witness points on the link and on the obstacle, and the
unit normal n pointing from the obstacle to the link, so that moving the link point along n
increases d (∂d/∂p_link = nᵀ).

With many obstacles a broad phase prunes the far pairs first: the link capsules, inflated by the
cutoff, are collided against python-fcl's dynamic AABB tree of obstacles, and only the pairs that
touch get an exact distance query — so obstacles farther than the cutoff cost (almost) nothing.

Sphere obstacles never reach python-fcl's distance query: a capsule–sphere distance is closed-form
(the sphere's centre to the link's axis segment, less both radii), and python-fcl 0.7's signed query
(libccd GJK/EPA) never returns when a sphere's centre lies on (within ~0.1 mm of) the end of a
penetrating capsule's axis — a stalled control loop. Boxes, capsules and cylinders go to python-fcl.
Before any exact query, a vectorised bound drops the pairs whose bounding spheres are farther apart
than the cutoff (segment-to-centre distance less the capsule and bounding radii): a lower bound on
the distance, so the pairs it drops are exactly those the exact query would have dropped.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import fcl
import numpy as np

from qpctl.geometry.frames import quaternion_z_to
from qpctl.geometry.obstacles import Obstacle

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
    def empty() -> PairSet:
        z = np.zeros((0, 3))
        return PairSet(np.zeros(0, int), np.zeros(0, int), np.zeros(0), z, z, z, z, z)


def _closest_on_segment(a: Sequence[float], b: Sequence[float], p: Sequence[float]) -> tuple[float, float, float]:
    (ax, ay, az), (bx, by, bz), (px, py, pz) = a, b, p
    dx, dy, dz = bx - ax, by - ay, bz - az
    denom = dx * dx + dy * dy + dz * dz
    s = 0.0 if denom == 0 else min(max(((px - ax) * dx + (py - ay) * dy + (pz - az) * dz) / denom, 0.0), 1.0)
    return (ax + s * dx, ay + s * dy, az + s * dz)


def _perpendicular(x: float, y: float, z: float) -> tuple[float, float, float]:
    """A unit vector perpendicular to (x, y, z) and to the world axis least aligned with it (e_x for a
    zero vector)."""
    ax, ay, az = abs(x), abs(y), abs(z)
    e = (0.0, 0.0, 1.0) if az <= ax and az <= ay else ((0.0, 1.0, 0.0) if ay <= ax else (1.0, 0.0, 0.0))
    px, py, pz = y * e[2] - z * e[1], z * e[0] - x * e[2], x * e[1] - y * e[0]
    pn = math.hypot(px, py, pz)
    return (px / pn, py / pn, pz / pn) if pn > 0.0 else (1.0, 0.0, 0.0)


def closest_point_on_segment(a: np.ndarray, b: np.ndarray, p: np.ndarray) -> np.ndarray:
    """The point of segment [a, b] closest to p (3-vectors [m]; plain floats inside, it runs per pair)."""
    return np.array(_closest_on_segment(a.tolist(), b.tolist(), p.tolist()))


class DistanceEngine:
    """Distances between a robot's link capsules and a set of obstacles.

    Args:
        radii: capsule radius of each link [m].
        obstacles: the scene.
        broadphase: prune far pairs with python-fcl's dynamic AABB tree; ``None`` turns it on for
            more than 16 obstacles.
    """

    def __init__(self, radii: Sequence[float] | np.ndarray, obstacles: Sequence[Obstacle],
                 broadphase: bool | None = None):
        self.radii = np.asarray(radii, float)
        self.obstacles = list(obstacles)
        self.broadphase = len(self.obstacles) > 16 if broadphase is None else bool(broadphase)
        self._obs_objs = [fcl.CollisionObject(o.geometry(), o.transform(0.0)) for o in self.obstacles]
        self._moving = [i for i, o in enumerate(self.obstacles) if o.moving]
        self._link_objs = [fcl.CollisionObject(fcl.Capsule(r, 1e-9)) for r in self.radii]
        # sphere obstacles' distances are closed-form (module docstring)
        self._is_sphere = [o.shape == "sphere" for o in self.obstacles]
        self._link_len = np.full(len(self.radii), np.nan)
        self._inflated: list[fcl.CollisionObject] = []
        self._inflate = np.nan
        self._link_quat = [(1.0, 0.0, 0.0, 0.0)] * len(self.radii)
        self._t = 0.0
        # obstacle centres, bounding radii, velocities and accelerations (rows per obstacle) for the
        # vectorised bound and the PairSet; every (link, obstacle) index pair, link-major
        self._centres = np.array([o.position_at(0.0) for o in self.obstacles]).reshape(-1, 3)
        self._bound = np.array([o.bounding_radius() for o in self.obstacles])
        self._vel = np.array([o.velocity_at(0.0) for o in self.obstacles]).reshape(-1, 3)
        self._acc = np.array([o.acceleration_at(0.0) for o in self.obstacles]).reshape(-1, 3)
        self._all_links = np.repeat(np.arange(len(self.radii)), len(self.obstacles))
        self._all_obstacles = np.tile(np.arange(len(self.obstacles)), len(self.radii))
        self._by_position: dict[tuple[float, ...], list[int]] | None = None
        if self.broadphase:
            self._manager = fcl.DynamicAABBTreeCollisionManager()
            self._manager.registerObjects(self._obs_objs)
            self._manager.setup()

    # -- pose updates -------------------------------------------------------------------------
    def update(self, segments: np.ndarray, t: float, links: Sequence[int] | None = None) -> None:
        """Set the link segments ((L, 2, 3) world endpoints [m]) and the obstacles' poses at time t [s].

        ``links``: move only these links' python-fcl capsules (then query only pairs of these links).
        """
        self._segments = segments
        self._mids = 0.5 * (segments[:, 0] + segments[:, 1])
        ends = segments.tolist()
        for i in range(len(ends)) if links is None else links:
            (ax, ay, az), (bx, by, bz) = ends[i]
            dx, dy, dz = bx - ax, by - ay, bz - az
            length = math.sqrt(dx * dx + dy * dy + dz * dz)
            if not abs(length - self._link_len[i]) <= 1e-12:  # first call (NaN) or a new length: rebuild
                self._link_objs[i] = fcl.CollisionObject(fcl.Capsule(self.radii[i], max(length, 1e-9)))
                self._link_len[i] = length
                self._inflate = np.nan  # the broad phase's inflated capsules too
            # the capsule's axis is its local z: a quaternion and a translation, no matrices
            self._link_quat[i] = quaternion_z_to(dx, dy, dz) if length > 1e-12 else (1.0, 0.0, 0.0, 0.0)
            self._link_objs[i].setQuatRotation(self._link_quat[i])
            self._link_objs[i].setTranslation(self._mids[i])
        if t != self._t or not self._moving:
            for j in self._moving:
                o = self.obstacles[j]
                self._obs_objs[j].setTransform(o.transform(t))
                self._centres[j], self._vel[j], self._acc[j] = o.position_at(t), o.velocity_at(t), o.acceleration_at(t)
            if self.broadphase and self._moving:
                self._manager.update()
                self._by_position = None
        self._t = t

    # -- queries ------------------------------------------------------------------------------
    def obstacle_positions(self) -> np.ndarray:
        """(O, 3) obstacle centres [m] at the time of the last update (a view: do not modify)."""
        return self._centres

    def obstacle_velocities(self, obstacles: np.ndarray) -> np.ndarray:
        """(k, 3) velocities [m/s] of the given obstacles (indices) at the time of the last update."""
        return self._vel[obstacles]

    def _candidates(self, cutoff: float) -> tuple[np.ndarray, np.ndarray]:
        """(link, obstacle) index arrays of the pairs that may lie within ``cutoff`` [m], link-major."""
        if not np.isfinite(cutoff):
            return self._all_links, self._all_obstacles
        links, obstacles = self._tree_candidates(cutoff) if self.broadphase else (self._all_links,
                                                                                   self._all_obstacles)
        keep = self._sphere_bound(links, obstacles) < cutoff
        return links[keep], obstacles[keep]

    def _sphere_bound(self, links: np.ndarray, obstacles: np.ndarray) -> np.ndarray:
        """A lower bound [m] on each pair's distance: the link axis to the obstacle's centre, less the
        capsule radius and the obstacle's bounding radius (less 1e-9 m for rounding)."""
        a = self._segments[links, 0]
        ab = self._segments[links, 1] - a
        p = self._centres[obstacles] - a
        s = np.clip((p * ab).sum(axis=1) / np.maximum((ab * ab).sum(axis=1), 1e-300), 0.0, 1.0)
        gap = p - s[:, None] * ab
        return np.sqrt((gap * gap).sum(axis=1)) - self.radii[links] - self._bound[obstacles] - 1e-9

    def _tree_candidates(self, cutoff: float) -> tuple[np.ndarray, np.ndarray]:
        """The pairs whose inflated link capsule's AABB overlaps the obstacle's, from fcl's AABB tree."""
        nl = len(self._link_objs)
        if self._inflate != cutoff or len(self._inflated) != nl:
            self._inflated = [fcl.CollisionObject(fcl.Capsule(r + cutoff, max(L, 1e-9)))
                              for r, L in zip(self.radii, self._link_len)]
            self._inflate = cutoff
        # python-fcl hands the callback new wrappers of the registered objects (their ids differ),
        # so obstacles are recognised by their exact current translation (the callback's first
        # object is the tree's); a shared translation only adds candidates, which the bound and the
        # exact distance query then filter.
        if self._by_position is None:
            self._by_position = {}
            for j, o in enumerate(self._obs_objs):
                self._by_position.setdefault(tuple(o.getTranslation()), []).append(j)
        lookup = self._by_position
        links: list[int] = []
        obstacles: list[int] = []
        for i, infl in enumerate(self._inflated):
            infl.setQuatRotation(self._link_quat[i])
            infl.setTranslation(self._mids[i])
            hits: set[int] = set()

            def callback(o1: fcl.CollisionObject, _o2: fcl.CollisionObject, _data: object,
                         hits: set[int] = hits) -> bool:
                hits.update(lookup.get(tuple(o1.getTranslation()), ()))
                return False

            self._manager.collide(infl, None, callback)
            links += [i] * len(hits)
            obstacles += sorted(hits)
        return np.array(links, dtype=int), np.array(obstacles, dtype=int)

    def pair(self, i: int, j: int) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
        """Signed distance d [m], unit normal n (obstacle → link), witness points on link and obstacle."""
        out = self._query(i, j)
        assert out is not None
        return out

    def _query(self, i: int, j: int, cutoff: float = np.inf
               ) -> tuple[float, np.ndarray, np.ndarray, np.ndarray] | None:
        """(d, n, p_link, p_obs) of one pair, or None when d ≥ ``cutoff`` (then no witness points are
        computed): spheres in closed form, every other shape by python-fcl."""
        if self._is_sphere[j]:
            out = self._sphere_pair(i, j)
            return out if out[0] < cutoff else None
        d, res = signed_distance(self._link_objs[i], self._obs_objs[j])
        return (d, *self._witness(i, j, d, res)) if d < cutoff else None

    def _distance(self, i: int, j: int) -> float:
        """Signed distance [m] of one pair, without witness points."""
        if self._is_sphere[j]:
            return self._sphere_pair(i, j)[0]
        return signed_distance(self._link_objs[i], self._obs_objs[j])[0]

    def _sphere_pair(self, i: int, j: int) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
        """Closed-form capsule–sphere pair: d = |axis point − centre| − r_link − r_sphere, n along it.

        A centre on the link's axis leaves n free: it is taken perpendicular to the axis and to the
        world axis least aligned with it (in the plane of a planar arm, the in-plane normal)."""
        a, b = self._segments[i].tolist()
        c = self._centres[j].tolist()
        sx, sy, sz = _closest_on_segment(a, b, c)
        wx, wy, wz = sx - c[0], sy - c[1], sz - c[2]
        wn = math.hypot(wx, wy, wz)
        if wn > 1e-12:
            n = (wx / wn, wy / wn, wz / wn)
        else:
            n = _perpendicular(b[0] - a[0], b[1] - a[1], b[2] - a[2])
        rl, rs = float(self.radii[i]), self.obstacles[j].radius
        p_link = np.array((sx - rl * n[0], sy - rl * n[1], sz - rl * n[2]))
        p_obs = np.array((c[0] + rs * n[0], c[1] + rs * n[1], c[2] + rs * n[2]))
        return wn - rl - rs, np.array(n), p_link, p_obs

    def _witness(self, i: int, j: int, d: float, res: fcl.DistanceResult
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        p_obs = np.asarray(res.nearest_points[1])
        if d > 1e-6:
            # GJK's witness point on a capsule can be off by ~1e-4 m along the axis (the flat
            # direction); the exact one is the axis point closest to the obstacle's witness,
            # pushed out by the radius. It matters for the barrier's drift (ḣ to ~1e-6 m/s).
            # (In plain floats: the common case, every pair at every tick.)
            ox, oy, oz = po = p_obs.tolist()
            a, b = self._segments[i].tolist()
            cx, cy, cz = _closest_on_segment(a, b, po)
            wx, wy, wz = cx - ox, cy - oy, cz - oz
            wn = math.hypot(wx, wy, wz)
            if wn > 1e-9:
                nx, ny, nz = wx / wn, wy / wn, wz / wn
                out = wn - float(self.radii[i])
                return np.array((nx, ny, nz)), np.array((ox + nx * out, oy + ny * out, oz + nz * out)), p_obs
        p_link = np.asarray(res.nearest_points[0])
        diff = p_link - p_obs
        nd = math.hypot(*diff.tolist())
        if d > 1e-6:  # the obstacle's witness lies on the link's axis: keep GJK's direction
            n = diff / max(nd, 1e-12)
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
        links, obstacles = self._candidates(cutoff)
        for i, j in zip(links.tolist(), obstacles.tolist()):
            out = self._query(i, j, cutoff)
            if out is not None:
                rows.append((i, j, *out))
        if not rows:
            return PairSet.empty()
        link = np.array([r[0] for r in rows], int)
        obs = np.array([r[1] for r in rows], int)
        v = self._vel[obs]
        a = self._acc[obs]
        return PairSet(link, obs, np.array([r[2] for r in rows], float), np.array([r[3] for r in rows]),
                       np.array([r[4] for r in rows]), np.array([r[5] for r in rows]), v, a)

    def min_distance(self) -> float:
        """Least signed distance [m] between any link and any obstacle (inf with no obstacles)."""
        if not self._obs_objs:
            return float("inf")
        links, obstacles = self._all_links, self._all_obstacles
        if getattr(self, "_segments", None) is None:  # no pose set yet: nothing to bound with
            bound = np.full(links.size, -np.inf)
        else:
            bound = self._sphere_bound(links, obstacles)
        best = float("inf")
        for k in np.argsort(bound, kind="stable").tolist():  # nearest bounds first; stop once none can win
            if bound[k] >= best:
                break
            best = min(best, self._distance(int(links[k]), int(obstacles[k])))
        return best
