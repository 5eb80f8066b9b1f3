"""A simulated depth camera: what a RealSense-class sensor would deliver, on the CPU without OpenGL.

:class:`DepthCamera` renders the world's obstacles at time t (moving ones moved, ``perceived = true``
ones included), the shapes only a camera sees (``scenery``: the fruits of a canopy) and the robot's
own link capsules at q, from a camera fixed in the world or on a robot frame (the wrist), and hands
back a :class:`~qpctl.perception.frames.DepthFrame` — :meth:`DepthCamera.capture` ``(q, t)``. Two
casters do the geometry, held to each other and to a python-fcl reference in the tests:
:class:`NumbaCaster` (:mod:`qpctl.kernels.raycast`, the scene's primitives) and
:class:`~qpctl.adapters.mujoco_camera.MujocoCaster` (``mujoco.mj_multiRay`` in a MuJoCo model: the
MuJoCo simulator's live one, whose user-supplied meshes it sees too; :meth:`DepthCamera.use_mujoco`).

**The noise model** (``noise = true``), on the true depth z of each pixel, in this order:

1. *flying pixels*: where a 4-neighbour's depth differs by more than :data:`EDGE_JUMP`, the pixel
   is, with probability ``flying_pixels``, a mixed return at z + u (z_n − z), u ~ U(0, 1) — a point on
   no surface, as stereo and time-of-flight sensors produce at depth edges;
2. *depth noise*: z + N(0, σ²), σ = ``sigma_0`` + ``sigma_z2`` z² (Intel's model of a stereo depth
   camera, RMS error = z² × subpixel error / (focal length × baseline): 0.08 px / (383 px × 0.05 m)
   = 0.0042 m⁻¹ for a D435 at 640×480);
3. *dropouts*: no return where the ray meets its surface at more than ``grazing_deg`` from the normal,
   and at random with probability ``dropout``;
4. the range: a return nearer than ``range_min`` or farther than ``range_max`` is none.

"No return" is depth 0, as a RealSense reports it; ``encoding = "uint16"`` delivers the image as
integers of ``depth_scale`` [m] (RealSense: 0.001), ``"metres"`` as float32. The noise of a frame is
drawn from the camera's ``seed`` and the frame's stamp: the same (q, t) gives the same frame
(:mod:`qpctl.kernels.sensor_noise` applies it in one compiled pass).

**Labels and the truth.** ``labels = true`` gives each pixel the class a segmenter would: the hit
obstacle's ``material`` (:data:`~qpctl.perception.frames.RIGID` or
:data:`~qpctl.perception.frames.SOFT`), :data:`~qpctl.perception.frames.UNLABELED` for the robot's
own links, the scenery (fruits) and pixels without a return. Every frame is a
:class:`SimulatedDepthFrame` whose ``truth`` (:class:`FrameTruth`) says what each pixel really saw:
the noise-free depth, which shape (``hit``, an index into ``names``), whether that is the robot
(``robot``: what a self-filter must remove), the scenery (``scenery``), a flying pixel (``flying``:
a phantom point) or a dropped return (``dropped``).

**Frames.** The optical frame is x right, y down, z forward (DESIGN §6; a pixel (u, v) at depth z is
((u − c_x) z / f_x, (v − c_y) z / f_y, z)); the frame's ``pose`` is the camera in the world (the
robot's base frame). A shape whose interior holds the camera is not seen: a camera looks out of the
link capsule it is mounted in.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, NamedTuple, Protocol

import numpy as np
import pinocchio as pin

from qpctl.config import check_fields, setting
from qpctl.errors import ConfigError, PerceptionError, UnknownFrameError
from qpctl.geometry.obstacles import Obstacle
from qpctl.kernels import raycast as K
from qpctl.kernels.sensor_noise import depth_frame
from qpctl.perception.frames import RIGID, SOFT, UNLABELED, DepthFrame, Intrinsics
from qpctl.robot.model import RobotModel

EDGE_JUMP = 0.05  # [m] a neighbour's depth differing by more than this makes a pixel a depth edge (flying pixels)

# What a shape of the camera is (DepthCamera.source)
NOTHING, OBSTACLE, SCENERY, ROBOT, OTHER = 0, 1, 2, 3, 4


def _vector(v: list[float] | None, n: int, key: str) -> np.ndarray | None:
    if v is None:
        return None
    a = np.asarray(v, float)
    if a.shape != (n,) or not np.all(np.isfinite(a)):
        raise ConfigError(f"needs {n} finite numbers, got {v}", key=key)
    return a


@dataclass(frozen=True, kw_only=True)
class CameraConfig:
    """The ``[camera]`` keys of a scenario (each declared here once; :func:`qpctl.config.schema_of`).

    mount: "" (no camera), "world" (fixed), or the name of a robot frame it rides on ("panda_hand").
    position [m], look_at [m], up, quaternion: the camera in the mount's frame — its optical centre,
    and either a point its optical axis passes through (with the direction ``up`` that is up in its
    image) or the optical frame's orientation as a quaternion (x, y, z, w); neither: the mount's own
    axes (a robot frame: looking along its z). A world camera needs ``position``.
    width, height [pixels], fov_y [deg]: the image and its vertical field of view (square pixels,
    centred); or fx, fy, cx, cy [pixels]: the pinhole intrinsics themselves (fy defaults to fx, cx
    and cy to the image's centre).
    rate [Hz]: frames per second. range_min, range_max [m]: the depths it returns.
    noise: the noise model on (module docstring) with sigma_0 [m], sigma_z2 [1/m], dropout
    (probability), grazing_deg [deg], flying_pixels (probability at a depth edge).
    encoding: "metres" (float32) or "uint16" (integers of depth_scale [m]).
    labels: per-pixel rigid/soft labels, as from a segmenter. caster: "auto" (MuJoCo's ray casting
    in the MuJoCo simulator, qpctl's kernel elsewhere), "numba" or "mujoco". seed: the noise's.
    """

    mount: str = ""
    position: list[float] | None = None
    look_at: list[float] | None = None
    up: list[float] = dataclasses.field(default_factory=lambda: [0.0, 0.0, 1.0])
    quaternion: list[float] | None = None
    width: int = 640
    height: int = 480
    fov_y: float = setting(58.0, unit="deg")
    fx: float | None = setting(None, unit="px")
    fy: float | None = setting(None, unit="px")
    cx: float | None = setting(None, unit="px")
    cy: float | None = setting(None, unit="px")
    rate: float = setting(30.0, valid="positive", unit="Hz")
    range_min: float = setting(0.1, valid="nonnegative", unit="m")
    range_max: float = setting(3.0, valid="positive", unit="m")
    noise: bool = True
    sigma_0: float = setting(0.0005, valid="nonnegative", unit="m")
    sigma_z2: float = setting(0.0042, valid="nonnegative", unit="1/m")
    dropout: float = setting(0.005, valid="nonnegative")
    grazing_deg: float = setting(80.0, valid="positive", unit="deg")
    flying_pixels: float = setting(0.5, valid="nonnegative")
    encoding: str = setting("metres", choices=("metres", "uint16"))
    depth_scale: float = setting(0.001, valid="positive", unit="m")
    labels: bool = True
    caster: str = setting("auto", choices=("auto", "numba", "mujoco"))
    seed: int = setting(0, valid="nonnegative")

    def __post_init__(self) -> None:
        check_fields(self, "camera")
        if self.mount == "world" and self.position is None:
            raise ConfigError('missing value: a camera with mount = "world" needs its position [m]', key="camera.position")
        if self.look_at is not None and self.quaternion is not None:
            raise ConfigError("give look_at or quaternion, not both", key="camera.quaternion")
        _vector(self.position, 3, "camera.position")
        _vector(self.look_at, 3, "camera.look_at")
        q = _vector(self.quaternion, 4, "camera.quaternion")
        if q is not None and np.linalg.norm(q) < 1e-9:
            raise ConfigError("must not be all zeros", key="camera.quaternion")
        up = _vector(self.up, 3, "camera.up")
        if up is None or np.linalg.norm(up) < 1e-9:
            raise ConfigError(f"must be a non-zero 3-vector, got {self.up}", key="camera.up")
        if self.look_at is not None:
            view = np.asarray(self.look_at, float) - np.asarray(self.position or [0.0, 0.0, 0.0], float)
            if np.linalg.norm(view) < 1e-9:
                raise ConfigError("must differ from the camera's position", key="camera.look_at")
            if np.linalg.norm(np.cross(view, up)) < 1e-9 * np.linalg.norm(view) * np.linalg.norm(up):
                raise ConfigError("is parallel to the viewing direction (position → look_at)", key="camera.up")
        for name in ("width", "height"):
            if getattr(self, name) <= 0:
                raise ConfigError(f"must be a positive number of pixels, got {getattr(self, name)}", key=f"camera.{name}")
        if not 0.0 < self.fov_y < 180.0:
            raise ConfigError(f"must be between 0 and 180 degrees, got {self.fov_y}", key="camera.fov_y")
        if self.fy is not None and self.fx is None:
            raise ConfigError("is given without fx", key="camera.fy")
        if self.range_min >= self.range_max:
            raise ConfigError(f"range_min {self.range_min} m must be below range_max {self.range_max} m",
                              key="camera.range_min")
        for name, hi in (("dropout", 1.0), ("flying_pixels", 1.0), ("grazing_deg", 90.0)):
            if getattr(self, name) > hi:
                raise ConfigError(f"must be at most {hi:g}, got {getattr(self, name)}", key=f"camera.{name}")
        if self.dropout == 1.0:
            raise ConfigError("must be below 1 (every return lost)", key="camera.dropout")
        try:
            self.intrinsics()
        except PerceptionError as exc:  # a non-positive focal length
            raise ConfigError(str(exc).split(": ", 1)[-1], key="camera.fx") from None

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> CameraConfig:
        """From the validated ``[camera]`` table."""
        return cls(**{f.name: d[f.name] for f in dataclasses.fields(cls) if f.name in d})

    @property
    def enabled(self) -> bool:
        return bool(self.mount)

    def intrinsics(self) -> Intrinsics:
        """The pinhole intrinsics (fx etc. if given, else from fov_y)."""
        if self.fx is None:
            return Intrinsics.from_fov(self.width, self.height, self.fov_y)
        return Intrinsics(float(self.fx), float(self.fy if self.fy is not None else self.fx),
                          float(self.cx if self.cx is not None else (self.width - 1) / 2.0),
                          float(self.cy if self.cy is not None else (self.height - 1) / 2.0), self.width, self.height)

    def mount_pose(self) -> np.ndarray:
        """The optical frame in the mount's frame (4×4)."""
        T = np.eye(4)
        p = np.asarray(self.position if self.position is not None else [0.0, 0.0, 0.0], float)
        T[:3, 3] = p
        if self.quaternion is not None:
            x, y, z, w = self.quaternion
            T[:3, :3] = pin.Quaternion(w, x, y, z).normalized().matrix()
        elif self.look_at is not None:
            T[:3, :3] = look_at_rotation(p, np.asarray(self.look_at, float), np.asarray(self.up, float))
        return T


def look_at_rotation(position: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """The optical frame's rotation (columns x right, y down, z forward) of a camera at ``position``
    looking at ``target`` with ``up`` up in its image."""
    z = target - position
    z = z / np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(z, x), z])


class Hits(NamedTuple):
    """A noise-free rendering: ``depth`` (H, W) [m] (inf: nothing within range_max), ``hit`` (H, W) the
    index of the shape seen (into :attr:`DepthCamera.names`; −1: none) and ``cos_incidence`` (H, W), the
    |cosine| between the ray and the surface's normal."""

    depth: np.ndarray
    hit: np.ndarray
    cos_incidence: np.ndarray


@dataclass(frozen=True)
class FrameTruth:
    """What each pixel of a simulated frame really saw (H, W arrays; module docstring)."""

    depth: np.ndarray  # [m] the noise-free depth of the surface seen (NaN: none within range_max)
    hit: np.ndarray  # int32: the shape seen, an index into names (−1: none)
    names: tuple[str, ...]  # the camera's shapes: obstacles, scenery, link capsules (then "robot", "other")
    robot: np.ndarray  # bool: the surface seen is the robot's own
    scenery: np.ndarray  # bool: ... is a shape only the camera knows (a fruit)
    flying: np.ndarray  # bool: the return is a flying pixel (a point on no surface)
    dropped: np.ndarray  # bool: a surface within range, but no return (dropout, grazing, range_min)


@dataclass(frozen=True)
class SimulatedDepthFrame(DepthFrame):
    """A :class:`DepthFrame` from the simulated camera, with the ``truth`` of every pixel."""

    truth: FrameTruth | None = field(default=None, compare=False)


class Caster(Protocol):
    """Renders the camera's scene (:meth:`DepthCamera.render`)."""

    def cast(self, camera: DepthCamera, pose: np.ndarray, q: np.ndarray, t: float) -> Hits: ...


class NumbaCaster:
    """qpctl's compiled ray caster (:func:`qpctl.kernels.raycast.cast_image`) on the camera's primitives."""

    def cast(self, camera: DepthCamera, pose: np.ndarray, q: np.ndarray, t: float) -> Hits:
        H, W = camera.intrinsics.height, camera.intrinsics.width
        depth, hit, cos = np.empty((H, W)), np.empty((H, W), np.int32), np.empty((H, W))
        k = camera.intrinsics
        scene = camera.scene
        K.cast_image(np.ascontiguousarray(pose[:3, 3]), np.ascontiguousarray(pose[:3, :3]), k.fx, k.fy, k.cx, k.cy,
                     scene.kind, scene.centre, scene.axes, scene.size, camera.visible, camera.config.range_max,
                     depth, hit, cos)
        return Hits(depth, hit, cos)


class DepthCamera:
    """A simulated depth camera (module docstring).

    Args:
        config: its keys (:class:`CameraConfig`; ``mount`` must not be "").
        robot: the robot whose link capsules it sees, and whose frame a ``mount`` may name.
        obstacles: the world's obstacles (the true ones: a simulator's, ``perceived`` included).
        scenery: shapes only the camera sees (a canopy's fruits): in the image, in no clearance.
        caster: what renders (:class:`NumbaCaster` by default; a simulator's own, :meth:`use_mujoco`).

    Attributes:
        intrinsics: the pinhole intrinsics of its images.
        names: its shapes, obstacles then scenery then link capsules (``FrameTruth.hit`` indexes them;
            two more at the end, "robot" and "other", for a MuJoCo model's unmatched geoms).
        visible: (P,) bool, the shapes it sees (clear one to hide it, e.g. in a test).
    """

    def __init__(self, config: CameraConfig, robot: RobotModel, obstacles: Sequence[Obstacle] = (), *,
                 scenery: Sequence[Obstacle] = (), caster: Caster | None = None) -> None:
        if not config.enabled:
            raise ConfigError('a camera needs its mount ("world" or a robot frame)', key="camera.mount")
        self.config = config
        self.robot = robot
        self.obstacles = list(obstacles)
        self.scenery = list(scenery)
        self.intrinsics = config.intrinsics()
        self.frame_id: int | None = None
        if config.mount != "world":
            try:
                self.frame_id = robot.frame_id(config.mount)
            except UnknownFrameError as exc:
                raise ConfigError(f'must be "world" or a frame of {robot.name}: {exc}', key="camera.mount") from None
        self.mount_pose = config.mount_pose()
        self._data = robot.model.createData()
        shapes = [*self.obstacles, *self.scenery]
        self.names: tuple[str, ...] = tuple([o.name or f"obstacle{i}" for i, o in enumerate(self.obstacles)]
                                            + [o.name or f"scenery{i}" for i, o in enumerate(self.scenery)]
                                            + [c.name for c in robot.capsules] + ["robot", "other"])
        n_shapes, n_links = len(shapes), len(robot.capsules)
        self.id_robot, self.id_other = n_shapes + n_links, n_shapes + n_links + 1
        self.source = np.array([OBSTACLE] * len(self.obstacles) + [SCENERY] * len(self.scenery)
                               + [ROBOT] * (n_links + 1) + [OTHER], np.uint8)
        self.label = np.array([SOFT if o.material == "soft" else RIGID for o in self.obstacles]
                              + [UNLABELED] * (len(self.scenery) + n_links + 2), np.uint8)
        self.scene = K.Primitives.empty(n_shapes + n_links)
        for i, obs in enumerate(shapes):
            K.obstacle_primitive(obs, 0.0, self.scene, i)
        self._moving = [(i, o) for i, o in enumerate(shapes) if o.moving]
        self._link_radius = np.array([c.radius for c in robot.capsules], float)
        self.visible = np.ones(n_shapes + n_links, np.bool_)
        k = self.intrinsics
        u, v = np.meshgrid(np.arange(k.width, dtype=float), np.arange(k.height, dtype=float))
        self.rays = np.column_stack([((u - k.cx) / k.fx).ravel(), ((v - k.cy) / k.fy).ravel(),
                                     np.ones(k.width * k.height)])  # optical frame, z = 1
        self.caster: Caster = caster if caster is not None else NumbaCaster()

    def use_mujoco(self, simulator: Any) -> DepthCamera:
        """Cast with ``mujoco.mj_multiRay`` in the MuJoCo simulator's live model (its ``ray_caster``,
        :class:`~qpctl.adapters.mujoco_camera.MujocoCaster`); returns the camera."""
        self.caster = simulator.ray_caster(self)
        return self

    # -- geometry ---------------------------------------------------------------------------------
    def _kinematics(self, q: np.ndarray) -> None:
        model, data = self.robot.model, self._data
        pin.forwardKinematics(model, data, np.asarray(q, float))
        if self.frame_id is not None:
            pin.updateFramePlacement(model, data, self.frame_id)

    def _pose(self) -> np.ndarray:
        if self.frame_id is None:
            return self.mount_pose.copy()
        return np.asarray(self._data.oMf[self.frame_id].homogeneous) @ self.mount_pose

    def pose(self, q: np.ndarray) -> np.ndarray:
        """The camera's optical frame in the world (the robot's base frame) at q, 4×4."""
        self._kinematics(q)
        return self._pose()

    def update_scene(self, q: np.ndarray, t: float) -> np.ndarray:
        """Place the moving shapes at t and the link capsules at q in :attr:`scene`; the camera's pose."""
        self._kinematics(q)
        for i, obs in self._moving:
            self.scene.centre[i] = obs.position_at(t)
        data = self._data
        caps = self.robot.capsules
        if caps:
            a = np.array([data.oMi[c.joint_id].act(c.p0) for c in caps])
            b = np.array([data.oMi[c.joint_id].act(c.p1) for c in caps])
            K.capsule_rows(a, b, self._link_radius, self.scene, len(self.obstacles) + len(self.scenery))
        return self._pose()

    def render(self, q: np.ndarray, t: float) -> tuple[np.ndarray, Hits]:
        """(pose, the noise-free :class:`Hits`) at (q [rad], t [s])."""
        pose = self.update_scene(q, t)
        return pose, self.caster.cast(self, pose, np.asarray(q, float), float(t))

    # -- frames -----------------------------------------------------------------------------------
    def due(self, t: float, dt: float) -> bool:
        """Whether a frame falls in the tick [t, t + dt) [s] (frames at k / rate)."""
        rate = self.config.rate
        k = math.ceil(t * rate - 1e-9)
        return k / rate < t + dt - 1e-12

    def frame_seed(self, t: float) -> np.uint64:
        """The seed of the noise of the frame stamped t [s]: from the camera's seed and the stamp [µs]."""
        ss = np.random.SeedSequence([self.config.seed, round(t * 1e6) % (1 << 63)])
        return np.uint64(ss.generate_state(1, np.uint64)[0])

    def capture(self, q: np.ndarray, t: float) -> SimulatedDepthFrame:
        """The depth frame at (q [rad], t [s]): rendered, with the noise model, encoded, labelled,
        stamped t, with its :class:`FrameTruth`."""
        cfg = self.config
        pose, hits = self.render(q, t)
        H, W = hits.depth.shape
        uint16 = cfg.encoding == "uint16"
        depth_m = np.zeros((0, 0) if uint16 else (H, W), np.float32)
        depth_u = np.zeros((H, W) if uint16 else (0, 0), np.uint16)
        labels = np.empty((H, W), np.uint8)
        truth_depth = np.empty((H, W))
        source = np.empty((H, W), np.uint8)
        flying, dropped = np.empty((H, W), np.bool_), np.empty((H, W), np.bool_)
        depth_frame(hits.depth, hits.cos_incidence, hits.hit, self.label, self.source, cfg.noise, self.frame_seed(t),
                    cfg.flying_pixels, EDGE_JUMP, cfg.sigma_0, cfg.sigma_z2, math.cos(math.radians(cfg.grazing_deg)),
                    cfg.dropout, cfg.range_min, cfg.range_max, cfg.depth_scale if uint16 else 0.0, depth_m, depth_u,
                    labels, truth_depth, source, flying, dropped)
        truth = FrameTruth(truth_depth, hits.hit, self.names, source == ROBOT, source == SCENERY, flying, dropped)
        meta = {"sigma_0": cfg.sigma_0 if cfg.noise else 0.0, "sigma_z2": cfg.sigma_z2 if cfg.noise else 0.0,
                "range_min": cfg.range_min, "range_max": cfg.range_max, "rate": cfg.rate}
        return SimulatedDepthFrame(depth_u if uint16 else depth_m, self.intrinsics, pose, float(t),
                                   labels if cfg.labels else None, cfg.depth_scale if uint16 else 1.0, meta, truth)

    @classmethod
    def from_scenario(cls, scenario: Any, robot: RobotModel | None = None, *, simulator: Any = None) -> DepthCamera:
        """The scenario's ``[camera]`` looking at its world: the true obstacles (every one, perceived
        ones included) and its canopy's fruits; in ``simulator`` (its obstacles, and with ``caster``
        "auto" or "mujoco" a MuJoCo simulator's live model) when given."""
        cfg = CameraConfig.from_dict(scenario.data["camera"])
        robot = robot if robot is not None else scenario.build_robot()
        obstacles = simulator.obstacles if simulator is not None else scenario.build_obstacles()
        camera = cls(cfg, robot, obstacles, scenery=scenario.scenery())
        casts = simulator is not None and hasattr(simulator, "ray_caster")  # a MuJoCo simulator
        if cfg.caster == "mujoco" and not casts:
            raise ConfigError('"mujoco" casts in the MuJoCo simulator\'s model: run it there (sim.simulator = '
                              '"mujoco", or --sim mujoco), or use "auto" or "numba"', source=scenario.source,
                              key="camera.caster")
        if casts and cfg.caster != "numba":
            camera.use_mujoco(simulator)
        return camera

