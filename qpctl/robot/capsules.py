"""Link capsules fitted to a robot's own meshes, and the TOML file that keeps them (``qpctl fit-capsules``).

**Where the geometry comes from.** Pinocchio's own parsers read the robot file
(``pin.buildGeomFromUrdf`` / ``pin.buildGeomFromMJCF``, package:// paths resolved, mesh scales
applied): each geometry object names its link (a URDF link, an MJCF body: its ``parentFrame``) and
its placement. A link's collision geometry is used, else its visual geometry. Meshes are read with
trimesh (vertices and faces, scaled as the file says); primitives become polytopes that contain
them (a box's corners; a cylinder's, sphere's or capsule's circumscribed polygon or polyhedron), so
that a capsule holding the points holds the primitive. Everything is expressed in the link's frame.

**The fit** (:func:`fit_capsule`). The least-volume capsule — segment a–b [m], radius r [m] —
holding the vertices of the convex hull of a link's points (trimesh): minimise
π r² ‖b − a‖ + 4/3 π r³ subject to dist(v_i, [a, b]) ≤ r for every hull vertex v_i, with scipy's
SLSQP from the hull's two principal axes; the radius is then recomputed exactly as the largest
vertex-to-segment distance, so every vertex is inside whatever the solver did.

**Two capsules** (:func:`fit_link`). Where one capsule exceeds ``try_split`` × the hull's volume
(on links of at least :data:`SPLIT_MIN_VOLUME`), the link's mesh is cut by planes normal to the
hull's principal axes, to the capsule's axis and to :data:`SPLIT_NORMALS` (at the
:data:`SPLIT_OFFSETS` quantiles); each side's points, with the points where the mesh's edges cross
the plane, get their own capsule — so every point of every triangle lies in one of the two. The
splits are ranked by the union volume of capsules fitted to 48 well-spread hull vertices of each
side; the best is fitted to every point and kept when it saves ``min_gain`` of the single capsule's
volume, or when the single capsule exceeds ``max_ratio`` × the hull. **Three** where two still
exceed ``max_ratio`` × the hull: the larger capsule's side (its convex hull as the mesh, which holds
the side's part of the link's) is split again the same way.

**Volumes.** A link's capsule volume is the volume of their union: exact for one capsule, a
Monte Carlo estimate for two (2¹⁶ fixed-seed points in the union's bounding box, ≲ 1 % error). The report compares it with the convex hull's volume (trimesh) and gives the largest
distance [m] of a mesh vertex outside every capsule of its link (0 by construction, up to the
file's rounding, which rounds each radius up).

**The file** (:func:`write_capsules`, :func:`read_capsules`): one ``[[capsule]]`` table per capsule,
``link``, ``a``, ``b`` [m] in the link's frame and ``radius`` [m], with the fit in a comment; a
scenario reads it with ``robot.capsules = "capsules.toml"``.
"""

from __future__ import annotations

import functools
import math
import sys
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import pinocchio as pin

from qpctl.errors import ConfigError
from qpctl.robot.files import example_robot_data_path, package_dirs, read_model, resolve_package_uri

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

TRY_SPLIT = 1.5  # try two capsules where one exceeds this × the hull's volume
MIN_GAIN = 0.10  # keep two when their union saves this fraction of the single capsule's volume
MAX_RATIO = 2.0  # ... or when the single capsule exceeds this × the hull's volume (and two do better)
SPLIT_MIN_VOLUME = 1e-5  # [m³] links smaller than this keep one capsule
SPLIT_OFFSETS = np.linspace(0.1, 0.9, 9)  # the split planes' offsets, as quantiles of the vertices along the normal
# the split planes' normals beside the hull's principal axes and the capsule's axis: the cube's 3 face,
# 6 edge and 4 corner directions
SPLIT_NORMALS = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0], [1, -1, 0], [1, 0, 1], [1, 0, -1], [0, 1, 1],
                          [0, 1, -1], [1, 1, 1], [1, 1, -1], [1, -1, 1], [-1, 1, 1]], float)
SPLIT_NORMALS /= np.linalg.norm(SPLIT_NORMALS, axis=1)[:, None]
_SECTIONS = 48  # sides of the polygon that circumscribes a cylinder's or a sphere's circle
DECIMALS = 5  # the file's precision [m]: 10 µm


class Capsule(NamedTuple):
    """A capsule: the segment a–b [m] swept by ``radius`` [m] (in some frame, the caller's)."""

    a: np.ndarray
    b: np.ndarray
    radius: float

    @property
    def volume(self) -> float:
        """[m³]"""
        return float(math.pi * self.radius**2 * np.linalg.norm(self.b - self.a) + 4.0 / 3.0 * math.pi * self.radius**3)

    def distance(self, points: np.ndarray) -> np.ndarray:
        """Signed distance [m] of each point (k, 3) to the capsule's surface (negative inside)."""
        return segment_distances(points, self.a, self.b) - self.radius


@dataclass(frozen=True)
class LinkGeometry:
    """A link's geometry in the link's frame: a triangle mesh (vertices [m], faces) and where it came from."""

    link: str
    vertices: np.ndarray  # (k, 3) [m]
    faces: np.ndarray  # (f, 3) int; primitives' polytopes have none (their hull is theirs)
    source: str  # "collision" or "visual"
    parts: int  # geometry objects merged
    exact: Capsule | None = None  # the link's one geometry object is a capsule or a sphere: itself


@dataclass(frozen=True)
class LinkFit:
    """The capsules fitted to one link and how well they fit."""

    link: str
    capsules: tuple[Capsule, ...]
    hull_volume: float  # [m³] of the convex hull of the link's points
    volume: float  # [m³] of the capsules' union
    max_outside: float  # [m] largest distance of a vertex outside every capsule (≤ 0: all inside)
    vertices: int
    source: str

    @property
    def ratio(self) -> float:
        """Capsule volume over convex-hull volume."""
        return self.volume / self.hull_volume if self.hull_volume > 0 else math.inf

    def line(self) -> str:
        caps = len(self.capsules)
        return (f"{self.link}: {caps} capsule{'s' if caps > 1 else ''} from {self.vertices} {self.source} vertices, "
                f"volume {self.volume:.3e} m³ = {self.ratio:.2f} × the convex hull's {self.hull_volume:.3e} m³, "
                f"largest vertex outside {max(self.max_outside, 0.0) * 1e3:.3f} mm")


# -- the fit ----------------------------------------------------------------------------------------
def segment_distances(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance [m] of each point (k, 3) to the segment a–b."""
    ab = np.asarray(b, float) - np.asarray(a, float)
    ll = float(ab @ ab)
    s = np.clip((points - a) @ ab / ll, 0.0, 1.0) if ll > 0 else np.zeros(len(points))
    return np.asarray(np.linalg.norm(points - (a + s[:, None] * ab), axis=1))


def _hull_vertices(points: np.ndarray) -> np.ndarray:
    import trimesh

    pts = np.unique(np.asarray(points, float).reshape(-1, 3), axis=0)
    if len(pts) < 5:
        return pts
    try:
        with np.errstate(invalid="ignore", divide="ignore"):  # a flat hull's centre of mass: 0 / 0
            return np.asarray(trimesh.convex.convex_hull(pts).vertices)
    except Exception:  # noqa: BLE001 - degenerate (flat) point sets: qhull refuses them; all points then
        return pts


def hull_volume(points: np.ndarray) -> float:
    """Volume [m³] of the convex hull of ``points`` (trimesh; 0 for flat sets)."""
    import trimesh

    pts = np.unique(np.asarray(points, float).reshape(-1, 3), axis=0)
    try:
        with np.errstate(invalid="ignore", divide="ignore"):
            return float(trimesh.convex.convex_hull(pts).volume) if len(pts) >= 4 else 0.0
    except Exception:  # noqa: BLE001 - flat: no volume
        return 0.0


def _slsqp(points: np.ndarray, a0: np.ndarray, b0: np.ndarray, r0: float) -> Capsule:
    """SLSQP from (a0, b0, r0): min π r²‖b − a‖ + 4/3 π r³ s.t. r² ≥ dist²(p_i, [a, b]), in scaled units."""
    from scipy.optimize import minimize

    centre = points.mean(axis=0)
    scale = float(np.ptp(points, axis=0).max()) or 1.0
    q = (points - centre) / scale

    def split(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        return x[:3], x[3:6], float(x[6])

    def volume(x: np.ndarray) -> float:
        a, b, r = split(x)
        return float(math.pi * r * r * np.linalg.norm(b - a) + 4.0 / 3.0 * math.pi * r**3)

    def volume_grad(x: np.ndarray) -> np.ndarray:
        a, b, r = split(x)
        length = float(np.linalg.norm(b - a))
        u = (b - a) / length if length > 1e-12 else np.zeros(3)
        return np.concatenate([-math.pi * r * r * u, math.pi * r * r * u, [2 * math.pi * r * length + 4 * math.pi * r * r]])

    def gap(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        a, b, _ = split(x)
        ab = b - a
        s = np.clip((q - a) @ ab / (ab @ ab + 1e-18), 0.0, 1.0)
        return q - (a + s[:, None] * ab), s

    def inside(x: np.ndarray) -> np.ndarray:
        w, _ = gap(x)
        return np.asarray(x[6] ** 2 - np.einsum("ij,ij->i", w, w))

    def inside_jac(x: np.ndarray) -> np.ndarray:
        w, s = gap(x)  # the closest point's parameter s is optimal: its own derivative drops out
        jac = np.empty((len(q), 7))
        jac[:, 0:3] = 2.0 * w * (1.0 - s)[:, None]
        jac[:, 3:6] = 2.0 * w * s[:, None]
        jac[:, 6] = 2.0 * x[6]
        return jac

    x0 = np.concatenate([(a0 - centre) / scale, (b0 - centre) / scale, [r0 / scale]])
    bounds = [(-2.0, 2.0)] * 6 + [(0.0, 2.0)]  # scaled: the points lie within ±1
    res = minimize(volume, x0, jac=volume_grad, method="SLSQP", bounds=bounds,
                   constraints=[{"type": "ineq", "fun": inside, "jac": inside_jac}],
                   options={"maxiter": 100, "ftol": 1e-9})
    x = res.x if np.all(np.isfinite(res.x)) else x0
    a, b = x[:3] * scale + centre, x[3:6] * scale + centre
    return Capsule(a, b, float(segment_distances(points, a, b).max()))


def fit_capsule(points: np.ndarray, *, starts: int = 2) -> Capsule:
    """The least-volume capsule holding every point (k, 3) [m] (module docstring): exact containment.
    ``starts``: how many of the hull's principal axes SLSQP starts from (1–3)."""
    pts = np.asarray(points, float).reshape(-1, 3)
    if len(pts) == 0:
        raise ValueError("no points to fit a capsule to")
    hull = _hull_vertices(pts)
    centre = hull.mean(axis=0)
    if len(hull) < 2 or np.ptp(hull, axis=0).max() < 1e-12:
        return Capsule(centre.copy(), centre.copy(), float(np.linalg.norm(pts - centre, axis=1).max()))
    _, _, vt = np.linalg.svd(hull - centre, full_matrices=False)
    best: Capsule | None = None
    for d in vt[:starts]:
        t = (hull - centre) @ d
        rho = float(np.linalg.norm((hull - centre) - np.outer(t, d), axis=1).max())
        cap = _slsqp(hull, centre + 0.5 * t.min() * d, centre + 0.5 * t.max() * d, max(rho, 1e-9))
        if best is None or cap.volume < best.volume:
            best = cap
    assert best is not None
    # the segment may collapse to a point: then a sphere about its mean
    if np.linalg.norm(best.b - best.a) < 1e-9:
        c = 0.5 * (best.a + best.b)
        best = Capsule(c, c.copy(), float(np.linalg.norm(pts - c, axis=1).max()))
    return Capsule(best.a, best.b, float(segment_distances(pts, best.a, best.b).max()))


@functools.lru_cache(maxsize=4)
def _unit_samples(samples: int) -> np.ndarray:
    return np.random.default_rng(0).random((samples, 3))


def _thin(points: np.ndarray, count: int = 48) -> np.ndarray:
    """At most ``count`` of the hull's vertices, spread out (farthest-point order): enough to rank
    the split planes; the split kept is fitted to every point."""
    hull = _hull_vertices(points)
    if len(hull) <= count:
        return hull
    chosen = [int(np.argmax(np.linalg.norm(hull - hull.mean(axis=0), axis=1)))]
    gap = np.linalg.norm(hull - hull[chosen[0]], axis=1)
    for _ in range(count - 1):
        chosen.append(int(np.argmax(gap)))
        gap = np.minimum(gap, np.linalg.norm(hull - hull[chosen[-1]], axis=1))
    return hull[chosen]


def union_volume(capsules: Sequence[Capsule], samples: int = 2**16) -> float:
    """Volume [m³] of the union of ``capsules``: exact for one, else the fraction of ``samples``
    fixed-seed uniform points of the union's bounding box inside one (deterministic; standard error
    ≲ 0.5 % of the box at the default count)."""
    if len(capsules) == 1:
        return capsules[0].volume
    lo = np.min([np.minimum(c.a, c.b) - c.radius for c in capsules], axis=0)
    hi = np.max([np.maximum(c.a, c.b) + c.radius for c in capsules], axis=0)
    x = lo + _unit_samples(samples) * (hi - lo)
    inside = np.zeros(samples, bool)
    for c in capsules:
        inside |= c.distance(x) <= 0.0
    return float(inside.mean() * np.prod(hi - lo))


def _sides(vertices: np.ndarray, faces: np.ndarray, normal: np.ndarray, offset: float
           ) -> tuple[np.ndarray, np.ndarray]:
    """The points on each side of the plane n·x = offset: the vertices there and where edges cross it."""
    h = vertices @ normal - offset
    if len(faces):
        edges = np.unique(np.sort(np.vstack([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1), axis=0)
    else:  # a polytope without faces: every pair of its (few) points
        i, j = np.triu_indices(len(vertices), 1)
        edges = np.column_stack([i, j])
    ha, hb = h[edges[:, 0]], h[edges[:, 1]]
    cross = (ha > 0) != (hb > 0)
    w = ha[cross] / (ha[cross] - hb[cross])
    va, vb = vertices[edges[cross, 0]], vertices[edges[cross, 1]]
    cut = va + w[:, None] * (vb - va)
    return np.vstack([vertices[h > 0], cut]), np.vstack([vertices[h <= 0], cut])


def _best_split(verts: np.ndarray, tris: np.ndarray, one: Capsule) -> tuple[np.ndarray, np.ndarray] | None:
    """The two sides (points: vertices and edge crossings) of the plane whose sides' capsules, fitted
    to 48 well-spread hull vertices each, have the least union volume (None: no plane splits it)."""
    hull = _hull_vertices(verts)
    centre = hull.mean(axis=0)
    _, _, vt = np.linalg.svd(hull - centre, full_matrices=False)
    normals = [*vt, *SPLIT_NORMALS]
    axis = one.b - one.a
    if np.linalg.norm(axis) > 1e-9:
        normals.append(axis / np.linalg.norm(axis))
    best: tuple[float, tuple[np.ndarray, np.ndarray]] | None = None
    for n in normals:
        proj = verts @ n
        for q in SPLIT_OFFSETS:
            left, right = _sides(verts, tris, n, float(np.quantile(proj, q)))
            if len(left) < 2 or len(right) < 2:
                continue
            v = union_volume((fit_capsule(_thin(left), starts=1), fit_capsule(_thin(right), starts=1)), samples=2**12)
            if best is None or v < best[0]:
                best = (v, (left, right))
    return None if best is None else best[1]


def _hull_mesh(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The convex hull of ``points`` as (vertices, faces): a mesh holding every point, to split again."""
    import trimesh

    with np.errstate(invalid="ignore", divide="ignore"):
        hull = trimesh.convex.convex_hull(np.unique(points, axis=0))
    return np.asarray(hull.vertices, float), np.asarray(hull.faces, int)


def fit_link(vertices: np.ndarray, faces: np.ndarray | None = None, *, try_split: float = TRY_SPLIT,
             min_gain: float = MIN_GAIN, max_ratio: float = MAX_RATIO, max_capsules: int = 3
             ) -> tuple[tuple[Capsule, ...], float, float]:
    """One capsule, two where one fits poorly, three where two still exceed ``max_ratio`` × the
    hull (module docstring): (capsules, union volume [m³], hull volume [m³])."""
    verts = np.asarray(vertices, float).reshape(-1, 3)
    tris = np.zeros((0, 3), int) if faces is None else np.asarray(faces, int).reshape(-1, 3)
    hull_v = hull_volume(verts)
    one = fit_capsule(verts)
    if max_capsules < 2 or hull_v < SPLIT_MIN_VOLUME or one.volume <= try_split * hull_v:
        return (one,), one.volume, hull_v
    sides = _best_split(verts, tris, one)
    if sides is None:
        return (one,), one.volume, hull_v
    two = tuple(fit_capsule(side) for side in sides)  # the best split, fitted from every start
    v_two = union_volume(two)
    if not (v_two <= (1.0 - min_gain) * one.volume or (one.volume > max_ratio * hull_v and v_two < one.volume)):
        return (one,), one.volume, hull_v
    if max_capsules < 3 or v_two <= max_ratio * hull_v:
        return two, v_two, hull_v
    # a third: the larger capsule's side split again (its convex hull as the mesh: it holds the side)
    k = int(np.argmax([c.volume for c in two]))
    sub, _, _ = fit_link(*_hull_mesh(sides[k]), try_split=0.0, min_gain=0.0, max_ratio=max_ratio, max_capsules=2)
    three = (two[1 - k], *sub)
    v_three = union_volume(three)
    return (three, v_three, hull_v) if len(sub) == 2 and v_three < v_two else (two, v_two, hull_v)


def fit_links(geometry: Iterable[LinkGeometry], **options: Any) -> list[LinkFit]:
    """:func:`fit_link` on each link's geometry (``options`` are its keywords)."""
    out = []
    for g in geometry:
        caps: tuple[Capsule, ...]
        if g.exact is not None:
            caps, volume, hull_v = (g.exact,), g.exact.volume, g.exact.volume
        else:
            caps, volume, hull_v = fit_link(g.vertices, g.faces, **options)
        caps = tuple(_rounded(c) for c in caps)
        # the polytope of an exact capsule circumscribes it: the capsule itself is the geometry
        outside = 0.0 if g.exact is not None else float(np.min([c.distance(g.vertices) for c in caps], axis=0).max())
        out.append(LinkFit(g.link, caps, hull_v, volume if len(caps) > 1 else caps[0].volume, outside,
                           len(g.vertices), g.source))
    return out


def _rounded(c: Capsule) -> Capsule:
    """The capsule as the file keeps it: endpoints to :data:`DECIMALS`, the radius rounded up so that
    it still holds what it held."""
    a, b = np.round(c.a, DECIMALS), np.round(c.b, DECIMALS)
    grow = float(max(np.abs(a - c.a).max(), np.abs(b - c.b).max()))
    step = 10.0**-DECIMALS
    return Capsule(a, b, math.ceil((c.radius + grow) / step - 1e-9) * step)


# -- the robot's geometry -----------------------------------------------------------------------------
def _polytope(geometry: Any) -> np.ndarray:
    """Points (k, 3) whose convex hull contains a coal primitive, in the primitive's frame."""
    import coal

    k = _SECTIONS
    ring = np.linspace(0.0, 2.0 * np.pi, k, endpoint=False)
    grow = 1.0 / math.cos(math.pi / k)  # the circumscribed polygon

    def disc(radius: float, z: float) -> np.ndarray:
        return np.column_stack([grow * radius * np.cos(ring), grow * radius * np.sin(ring), np.full(k, z)])

    def ball(radius: float, centre: np.ndarray) -> np.ndarray:
        import trimesh

        sphere = trimesh.creation.icosphere(subdivisions=2)
        inner = float(np.min(np.abs(np.einsum("ij,ij->i", sphere.face_normals, sphere.triangles[:, 0]))))
        return np.asarray(sphere.vertices) * (radius / inner) + centre

    if isinstance(geometry, coal.Box):
        half = np.asarray(geometry.halfSide, float)
        return np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float) * half
    if isinstance(geometry, coal.Cylinder):
        r, h = float(geometry.radius), float(geometry.halfLength)
        return np.vstack([disc(r, -h), disc(r, h)])
    if isinstance(geometry, coal.Capsule):
        r, h = float(geometry.radius), float(geometry.halfLength)
        return np.vstack([ball(r, np.array([0.0, 0.0, -h])), ball(r, np.array([0.0, 0.0, h]))])
    if isinstance(geometry, coal.Sphere):
        return ball(float(geometry.radius), np.zeros(3))
    if isinstance(geometry, coal.Ellipsoid):
        return ball(1.0, np.zeros(3)) * np.asarray(geometry.radii, float)
    if isinstance(geometry, coal.Cone):
        r, h = float(geometry.radius), float(geometry.halfLength)
        return np.vstack([disc(r, -h), [[0.0, 0.0, h]]])
    if hasattr(geometry, "points"):  # coal.Convex
        return np.asarray(geometry.points(), float).reshape(-1, 3)
    raise ConfigError(f"geometry type {type(geometry).__name__} has no capsule fit here", key="robot")


def _mesh(obj: Any, key: str) -> tuple[np.ndarray, np.ndarray]:
    """The mesh file of a geometry object, read with trimesh and scaled: (vertices [m], faces)."""
    import trimesh

    try:
        mesh: Any = trimesh.load(obj.meshPath, force="mesh")
        verts = np.asarray(mesh.vertices, float) * np.asarray(obj.meshScale, float)
        faces = np.asarray(mesh.faces, int)
    except Exception as exc:  # noqa: BLE001 - any reader's failure: name the file
        raise ConfigError(f"cannot read mesh {obj.meshPath}: {' '.join(str(exc).split())}", key=key) from None
    if len(verts) == 0:
        raise ConfigError(f"mesh {obj.meshPath} has no vertices", key=key)
    return verts, faces


def link_geometry(model: pin.Model, collision: pin.GeometryModel, visual: pin.GeometryModel | None = None,
                  *, key: str = "robot") -> list[LinkGeometry]:
    """Each link's geometry in its own frame: its collision objects, else its visual ones (links that
    have neither are left out). ``model`` is the model the geometry models were built for."""
    import trimesh

    def by_link(gm: pin.GeometryModel | None) -> dict[str, list[Any]]:
        out: dict[str, list[Any]] = {}
        for obj in gm.geometryObjects if gm is not None else ():
            out.setdefault(model.frames[obj.parentFrame].name, []).append(obj)
        return out

    coll, vis = by_link(collision), by_link(visual)
    out: list[LinkGeometry] = []
    for f in model.frames:
        if f.type != pin.FrameType.BODY or f.name in {g.link for g in out}:
            continue
        objs, source = (coll[f.name], "collision") if f.name in coll else (vis.get(f.name, []), "visual")
        if not objs:
            continue
        verts, faces, base = [], [], 0
        for obj in objs:
            if obj.meshPath and obj.meshPath not in ("BOX", "CYLINDER", "SPHERE", "CAPSULE", "CONE") and \
                    type(obj.geometry).__name__.startswith("BVH"):
                v, tri = _mesh(obj, key)
            else:  # the polytope's hull: its faces give the edges a split plane cuts
                hull: Any = trimesh.convex.convex_hull(_polytope(obj.geometry))
                v, tri = np.asarray(hull.vertices, float), np.asarray(hull.faces, int)
            # object placement is in its joint's frame; the link frame is f.placement in that frame too
            local = f.placement.inverse() * obj.placement
            verts.append(v @ local.rotation.T + local.translation)
            faces.append(tri + base)
            base += len(v)
        out.append(LinkGeometry(f.name, np.vstack(verts), np.vstack(faces), source, len(objs),
                                _exact(objs[0], f.placement) if len(objs) == 1 else None))
    return out


def _exact(obj: Any, link: pin.SE3) -> Capsule | None:
    """A capsule or sphere geometry object as the capsule it is, in the link's frame; else None."""
    import coal

    geo = obj.geometry
    if not isinstance(geo, (coal.Capsule, coal.Sphere)):
        return None
    local = link.inverse() * obj.placement
    half = float(geo.halfLength) if isinstance(geo, coal.Capsule) else 0.0
    a, b = local.act(np.array([0.0, 0.0, -half])), local.act(np.array([0.0, 0.0, half]))
    return Capsule(a, b, float(geo.radius))


def _needs_visual(urdf: Path) -> bool:
    """Whether some link of the URDF has visual geometry but no collision geometry."""
    import xml.etree.ElementTree as ET

    try:
        root = ET.parse(urdf).getroot()
    except ET.ParseError:
        return False  # Pinocchio's parser has already read it, or will say why not
    return any(link.find("visual") is not None and link.find("collision") is None for link in root.iter("link"))


def file_geometry(path: str | Path, *, key: str = "robot") -> list[LinkGeometry]:
    """Each link's geometry (:func:`link_geometry`) of a URDF or MJCF file (``.xml``), read by
    Pinocchio's parsers; :class:`ConfigError` naming ``key`` if the file or a mesh does not load."""
    path = resolve_package_uri(path)
    mjcf = path.suffix.lower() in (".xml", ".mjcf")
    model = read_model(path, key=key)

    def geometry(kind: Any) -> pin.GeometryModel:
        try:
            if mjcf:
                return pin.buildGeomFromMJCF(model, str(path), kind)
            return pin.buildGeomFromUrdf(model, str(path), kind, package_dirs=package_dirs(path))
        except (ValueError, RuntimeError) as exc:  # a mesh Pinocchio cannot find or read
            raise ConfigError(f"{path.name}: {' '.join(str(exc).split())}", key=key) from None

    collision = geometry(pin.COLLISION)
    visual = geometry(pin.VISUAL) if mjcf or _needs_visual(path) else None
    return link_geometry(model, collision, visual, key=key)


def robot_file(robot: str | Path) -> Path:
    """The robot file ``qpctl fit-capsules ROBOT`` means: ``"panda"`` (example-robot-data's Panda
    URDF), ``package://example-robot-data/robots/<file>``, or a path to a URDF or MJCF (``.xml``) file."""
    if str(robot) == "panda":
        return example_robot_data_path("panda_description/urdf/panda.urdf")
    path = resolve_package_uri(robot)
    if path.suffix.lower() not in (".urdf", ".xml", ".mjcf"):
        raise ConfigError(f"expected panda, a .urdf or an MJCF .xml file, got {str(robot)!r}", key="ROBOT")
    if not path.is_file():
        raise ConfigError(f"robot file not found: {path}", key="ROBOT")
    return path


def fit_robot(robot: str | Path, *, skip: Sequence[str] = (), **options: Any) -> tuple[Path, list[LinkFit]]:
    """The robot file (:func:`robot_file`) and its links' fits (:func:`fit_links`), less ``skip``."""
    path = robot_file(robot)
    geometry = file_geometry(path, key="ROBOT")
    names = {g.link for g in geometry}
    for link in skip:
        if link not in names:
            raise ConfigError(f"no link {link!r} with geometry in {path.name}; those with: {', '.join(sorted(names))}",
                              key="--skip")
    return path, fit_links([g for g in geometry if g.link not in skip], **options)


# -- the file ---------------------------------------------------------------------------------------
def _num(x: float) -> str:
    """``x`` to :data:`DECIMALS` places, trailing zeros dropped, no negative zero."""
    text = f"{float(x) + 0.0:.{DECIMALS}f}".rstrip("0")
    text = text + "0" if text.endswith(".") else text
    return "0.0" if text == "-0.0" else text


def _fmt(v: np.ndarray) -> str:
    return "[" + ", ".join(_num(x) for x in v) + "]"


def write_capsules(fits: Sequence[LinkFit], path: str | Path, *, robot: str, source: str, command: str) -> Path:
    """Write the fitted capsules as TOML (module docstring); returns the path."""
    lines = [
        f"# Collision capsules of {robot}, fitted to its link meshes by `{command}`.",
        "# One [[capsule]] per capsule: the link (a URDF link, an MJCF body) it moves with, the segment",
        "# from a to b [m] in that link's frame, and the radius [m]. Edit freely: a scenario reads this",
        '# file with robot.capsules = "<this file>"; links left out get no capsule.',
        "# Each link's fit: its capsules' volume against the convex hull of its vertices, and the largest",
        "# distance of a vertex outside them (0: all inside).",
        f'robot = "{robot}"',
        f'source = "{source}"',
        "",
    ]
    for fit in fits:
        lines.append(f"# {fit.line()}")
        for cap in fit.capsules:
            lines += ["[[capsule]]", f'link = "{fit.link}"', f"a = {_fmt(cap.a)}", f"b = {_fmt(cap.b)}",
                      f"radius = {_num(cap.radius)}", ""]
    path = Path(path)
    path.write_text("\n".join(lines))
    return path


@dataclass(frozen=True)
class CapsuleEntry:
    """One ``[[capsule]]`` of a capsules file: in the frame of ``link``."""

    link: str
    capsule: Capsule


def read_capsules(path: str | Path, *, key: str = "robot.capsules") -> list[CapsuleEntry]:
    """The capsules of a file :func:`write_capsules` wrote (or a person edited); :class:`ConfigError`
    naming ``key`` (and the entry) for a missing file, bad TOML or a bad entry."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"capsules file not found: {path}", key=key)
    try:
        data = tomllib.loads(path.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path.name} is not valid TOML: {exc}", key=key) from None
    unknown = set(data) - {"robot", "source", "capsule"}
    if unknown:
        raise ConfigError(f"{path.name}: unknown key {min(unknown)!r} (known: robot, source, capsule)", key=key)
    items = data.get("capsule")
    if not isinstance(items, list) or not items:
        raise ConfigError(f"{path.name} has no [[capsule]] tables", key=key)
    out = []
    for i, item in enumerate(items):
        where = f"{path.name}: capsule[{i}]"
        if not isinstance(item, dict) or set(item) - {"link", "a", "b", "radius"}:
            raise ConfigError(f"{where}: the keys are link, a, b and radius", key=key)
        try:
            link = item["link"]
            a, b = (np.asarray(item[k], float) for k in ("a", "b"))
            radius = float(item["radius"])
        except (KeyError, TypeError, ValueError) as exc:
            raise ConfigError(f"{where}: needs link, a, b and radius ({exc})", key=key) from None
        if not isinstance(link, str) or a.shape != (3,) or b.shape != (3,) or not np.all(np.isfinite([*a, *b])):
            raise ConfigError(f"{where}: link must be a name, a and b 3 finite numbers [m]", key=key)
        if not (math.isfinite(radius) and radius > 0):
            raise ConfigError(f"{where}: radius must be a positive number [m], got {item['radius']}", key=key)
        out.append(CapsuleEntry(link, Capsule(a, b, radius)))
    return out
