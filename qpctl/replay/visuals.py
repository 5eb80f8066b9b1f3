"""What the replay draws, as triangle meshes: the robot's links and the obstacles, and the colour scale
of the links' clearance.

* A robot read from a URDF is drawn with its visual meshes, as Pinocchio reads them
  (``pinocchio.buildGeomFromUrdf(..., GeometryType.VISUAL)``: each mesh with its placement in its
  parent joint's frame, loaded by coal/assimp); the Panda's come from example-robot-data. A URDF
  primitive (box, cylinder, sphere, capsule) becomes a trimesh primitive of the same size.
* A robot without meshes (the paper's planar arm) is drawn with its collision capsules
  (:attr:`RobotModel.capsules`), which are also drawn, hidden until shown in the scene tree, over a
  robot that has meshes.
* An obstacle becomes the trimesh primitive of its MuJoCo geom (:meth:`Shape.mujoco_geom
  <qpctl.geometry.shapes.Shape.mujoco_geom>`: sphere, box, capsule, cylinder), so a registered shape
  is drawn as it is simulated; a geom type with no primitive here is drawn as its bounding sphere.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pinocchio as pin
import trimesh

from qpctl.geometry.obstacles import Obstacle
from qpctl.robot.model import RobotModel

Rgb = tuple[int, int, int]

NEUTRAL: Rgb = (214, 216, 220)  # a link beyond d_influence
NEAR: Rgb = (242, 201, 46)  # a link at d_influence
SAFE: Rgb = (214, 39, 40)  # a link at d_safe or closer
CONTACT: Rgb = (110, 0, 20)  # a link penetrating an obstacle (clearance < 0)
RIGID: Rgb = (133, 94, 66)  # branches, trunk, wires
SOFT: Rgb = (72, 158, 72)  # leaves
MARKER: Rgb = (255, 0, 255)  # the task point (end effector)
TRACE: Rgb = (255, 127, 14)  # the task point's trace
REFERENCE: Rgb = (44, 160, 44)  # the reference path
LEVELS = 8  # colours between d_influence and d_safe


@dataclass(frozen=True)
class Mesh:
    """Triangles in a local frame: ``vertices`` (V, 3) float32 [m], ``faces`` (F, 3) uint32."""

    vertices: np.ndarray
    faces: np.ndarray

    @staticmethod
    def of(mesh: trimesh.Trimesh) -> Mesh:
        return Mesh(np.ascontiguousarray(mesh.vertices, np.float32), np.ascontiguousarray(mesh.faces, np.uint32))


@dataclass(frozen=True)
class LinkVisual:
    """One mesh that moves with joint ``joint_id`` (0: the fixed base), placed by ``placement`` (in the
    joint's frame); ``link`` is the index of the robot capsule whose clearance colours it (-1: none)."""

    name: str
    joint_id: int
    placement: pin.SE3
    mesh: Mesh
    link: int


def clearance_colour(d: float, d_safe: float, d_influence: float) -> Rgb:
    """The colour of a link at clearance ``d`` [m]: neutral beyond ``d_influence``, from yellow at
    d_influence to red at ``d_safe`` in :data:`LEVELS` steps, red closer, dark red in contact (d < 0)."""
    if not d < d_influence:
        return NEUTRAL
    if d < 0.0:
        return CONTACT
    if d <= d_safe:
        return SAFE
    s = (d_influence - d) / max(d_influence - d_safe, 1e-12)  # 0 at d_influence, 1 at d_safe
    s = min(np.floor(s * LEVELS) / (LEVELS - 1), 1.0)
    return tuple(round(a + (b - a) * s) for a, b in zip(NEAR, SAFE))  # type: ignore[return-value]


def scale_stops(d_safe: float, d_influence: float) -> list[tuple[float, Rgb]]:
    """(clearance [m], colour) pairs along the scale, for the page's legend."""
    ds = np.linspace(d_influence, d_safe, LEVELS)
    return [(float(d), clearance_colour(float(d) - 1e-12, d_safe, d_influence)) for d in ds]


def capsule_mesh(p0: np.ndarray, p1: np.ndarray, radius: float, *, count: tuple[int, int] = (24, 12)) -> Mesh:
    """A capsule of ``radius`` [m] about the segment p0–p1 [m], in the segment's frame."""
    axis = np.asarray(p1, float) - np.asarray(p0, float)
    length = float(np.linalg.norm(axis))
    mesh = trimesh.creation.capsule(height=length, radius=radius, count=list(count))
    from qpctl.geometry.obstacles import rotation_z_to

    T = np.eye(4)
    if length > 1e-12:
        T[:3, :3] = rotation_z_to(axis / length)
    T[:3, 3] = 0.5 * (np.asarray(p0, float) + np.asarray(p1, float))
    mesh.apply_transform(T)
    return Mesh.of(mesh)


def capsule_visuals(robot: RobotModel) -> list[LinkVisual]:
    """The robot's collision capsules, one visual each, in their joints' frames."""
    return [LinkVisual(f"capsule_{i}_{c.name}", c.joint_id, pin.SE3.Identity(), capsule_mesh(c.p0, c.p1, c.radius), i)
            for i, c in enumerate(robot.capsules)]


def _coal_mesh(geometry: object, scale: np.ndarray) -> Mesh | None:
    """A coal geometry (what Pinocchio loaded) as triangles; None for a type this does not draw."""
    import coal

    if isinstance(geometry, coal.BVHModelBase):
        tris = geometry.tri_indices
        faces = np.array([[t[0], t[1], t[2]] for t in (tris(i) for i in range(geometry.num_tris))], np.uint32)
        return Mesh(np.ascontiguousarray(geometry.vertices(), np.float32), faces.reshape(-1, 3))
    if isinstance(geometry, coal.Box):
        return Mesh.of(trimesh.creation.box(extents=2 * np.asarray(geometry.halfSide) * scale))
    if isinstance(geometry, coal.Sphere):
        return Mesh.of(trimesh.creation.icosphere(subdivisions=2, radius=geometry.radius * float(scale[0])))
    if isinstance(geometry, coal.Capsule):
        return Mesh.of(trimesh.creation.capsule(height=2 * geometry.halfLength, radius=geometry.radius))
    if isinstance(geometry, coal.Cylinder):
        return Mesh.of(trimesh.creation.cylinder(radius=geometry.radius, height=2 * geometry.halfLength))
    return None


Part = tuple[str, int, pin.SE3, Mesh]  # (name, parent joint, placement in the joint's frame, mesh)
_VISUALS: dict[str, tuple[Part, ...]] = {}


def cache_dir() -> Path:
    """Where the replay keeps the robots' meshes as Pinocchio read them: ``$QPCTL_CACHE_DIR``, else
    ``$XDG_CACHE_HOME/qpctl`` (``~/.cache/qpctl``)."""
    if os.environ.get("QPCTL_CACHE_DIR"):
        return Path(os.environ["QPCTL_CACHE_DIR"])
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "qpctl"


def _key(urdf: Path, model: pin.Model) -> str:
    """The URDF's version (path, size, time) and the model's joints and frames, hashed."""
    import hashlib

    st = urdf.stat()
    text = repr((str(urdf.resolve()), st.st_size, st.st_mtime_ns, tuple(model.names), tuple(f.name for f in model.frames),
                 pin.__version__))
    return hashlib.sha1(text.encode()).hexdigest()[:20]


def _save(path: Path, parts: tuple[Part, ...], meshes: list[str]) -> None:
    arrays: dict[str, np.ndarray] = {
        "names": np.array([p[0] for p in parts]), "joints": np.array([p[1] for p in parts], int),
        "placements": np.array([p[2].homogeneous for p in parts]).reshape(-1, 4, 4),
        "files": np.array(meshes), "mtimes": np.array([Path(f).stat().st_mtime_ns for f in meshes], np.int64)}
    for i, p in enumerate(parts):
        arrays[f"v{i}"], arrays[f"f{i}"] = p[3].vertices, p[3].faces
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(f".{os.getpid()}.tmp.npz")
    np.savez(tmp, **arrays)  # type: ignore[arg-type]  # (numpy's stub: allow_pickle among the kwargs)
    tmp.replace(path)


def _load(path: Path) -> tuple[Part, ...] | None:
    """The cached parts, or None if there are none or a mesh file changed since."""
    try:
        with np.load(path) as d:
            if any(Path(f).stat().st_mtime_ns != m for f, m in zip(d["files"].tolist(), d["mtimes"].tolist())):
                return None
            return tuple((str(n), int(j), pin.SE3(M), Mesh(d[f"v{i}"], d[f"f{i}"]))
                         for i, (n, j, M) in enumerate(zip(d["names"], d["joints"], d["placements"])))
    except (OSError, KeyError, ValueError):
        return None


def _urdf_visuals(urdf: Path, model: pin.Model) -> tuple[Part, ...]:
    """(name, parent joint, placement, mesh) of each visual element of ``urdf`` on ``model``, as
    Pinocchio reads them (coal loads the meshes, ~1 s for the Panda's). Kept per process (a sweep or
    the reproduction writes many replays of one robot) and in :func:`cache_dir` (until the URDF or a
    mesh file changes), so that writing a replay does not load the meshes again."""
    key = _key(urdf, model)
    if key in _VISUALS:
        return _VISUALS[key]
    cached = cache_dir() / f"replay-visuals-{key}.npz"
    parts = _load(cached)
    if parts is None:
        dirs = [str(p) for p in urdf.parents]  # package://NAME/... resolves under any folder above the URDF
        geom = pin.buildGeomFromUrdf(model, str(urdf), pin.GeometryType.VISUAL, package_dirs=dirs)
        found = []
        for g in geom.geometryObjects:
            mesh = _coal_mesh(g.geometry, np.asarray(g.meshScale, float))
            if mesh is not None and len(mesh.faces):
                found.append((g.name, int(g.parentJoint), pin.SE3(g.placement), mesh))
        parts = tuple(found)
        files = sorted({g.meshPath for g in geom.geometryObjects if g.meshPath and Path(g.meshPath).is_file()})
        try:
            _save(cached, parts, files)
        except OSError:  # a read-only home: no cache, the meshes are loaded each time
            pass
    _VISUALS[key] = parts
    return parts


def robot_visuals(robot: RobotModel) -> tuple[list[LinkVisual], str]:
    """The robot's drawn parts and what they are (``"meshes"`` or ``"capsules"``): its URDF's visual
    meshes when it has them, else its capsules. Each mesh is coloured by the clearance of the first
    capsule on its joint."""
    if robot.urdf is not None:
        try:
            parts = _urdf_visuals(Path(robot.urdf), robot.model)
        except (RuntimeError, ValueError, OSError):  # a mesh Pinocchio cannot find or read: capsules
            parts = ()
        if parts:
            first: dict[int, int] = {}
            for i, c in enumerate(robot.capsules):
                first.setdefault(c.joint_id, i)
            return [LinkVisual(name, j, placement, mesh, first.get(j, -1)) for name, j, placement, mesh in parts], "meshes"
    return capsule_visuals(robot), "capsules"


def obstacle_mesh(obs: Obstacle) -> Mesh:
    """The obstacle's shape as triangles about its centre (its axis along ``obs.axis``)."""
    geom = obs.kind.mujoco_geom(obs)
    size = geom.size
    if geom.type == "sphere":
        mesh = trimesh.creation.icosphere(subdivisions=3, radius=size[0])
    elif geom.type == "box":
        mesh = trimesh.creation.box(extents=2 * np.asarray(size[:3], float))
    elif geom.type == "capsule":
        mesh = trimesh.creation.capsule(height=2 * size[1], radius=size[0], count=[32, 16])
    elif geom.type == "cylinder":
        mesh = trimesh.creation.cylinder(radius=size[0], height=2 * size[1], sections=48)
    else:  # a shape with no primitive here: its bounding sphere
        mesh = trimesh.creation.icosphere(subdivisions=2, radius=obs.bounding_radius())
    if geom.rotation is not None:
        T = np.eye(4)
        T[:3, :3] = geom.rotation
        mesh.apply_transform(T)
    return Mesh.of(mesh)


def obstacle_colour(obs: Obstacle) -> tuple[Rgb, float]:
    """(colour, opacity) of an obstacle: soft ones (leaves) green and translucent, rigid ones brown."""
    return (SOFT, 0.75) if obs.material == "soft" else (RIGID, 1.0)
