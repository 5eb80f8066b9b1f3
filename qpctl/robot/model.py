"""Robot models: a Pinocchio model, the task frame, link collision capsules and limits.

Every rigid-body quantity in qpctl comes from Pinocchio; this module only builds the models.

* :func:`planar_arm` — the paper's arm: ``n`` revolute joints about z, uniform thin rods of length
  ``l`` [m] and mass ``m`` [kg] (centre of mass at mid-link, I_c = m l²/12 about the axes normal to
  the rod), in the vertical x–y plane with gravity along −y.
* :func:`panda` — the Franka Emika Panda from the URDF shipped by the ``example-robot-data``
  package (found on disk through the installed package's file list, never fetched), fingers
  locked, with a capsule approximation of each link and the URDF's torque, velocity and joint
  limits.
* :meth:`RobotModel.from_urdf` — any URDF.
"""

from __future__ import annotations

import importlib.metadata
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import pinocchio as pin

from qpctl.errors import ConfigError, UnknownFrameError
from qpctl.robot.config import RobotConfig

# Where a URDF names a link and a joint alike (example-robot-data's Z1: "gripperStator"), Pinocchio
# has several frames of that name; the task point is then the first of these kinds.
_FRAME_PREFERENCE = (pin.FrameType.OP_FRAME, pin.FrameType.BODY, pin.FrameType.FIXED_JOINT, pin.FrameType.JOINT)


def frame_index(model: pin.Model, name: str) -> int:
    """Pinocchio id of frame ``name`` (an operational frame, else the link's, else a joint's, where
    several share the name); :class:`UnknownFrameError` lists the frames that exist."""
    ids = [i for i, f in enumerate(model.frames) if f.name == name]
    if not ids:
        raise UnknownFrameError(name, [f.name for f in model.frames])
    rank = {t: k for k, t in enumerate(_FRAME_PREFERENCE)}
    return min(ids, key=lambda i: (rank.get(model.frames[i].type, len(rank)), i))


@dataclass(frozen=True)
class LinkCapsule:
    """A capsule attached to a joint's frame: the segment p0–p1 [m] (in that frame) swept by ``radius`` [m]."""

    name: str
    joint_id: int
    p0: np.ndarray
    p1: np.ndarray
    radius: float

    def __post_init__(self) -> None:
        if not (np.isfinite(self.radius) and self.radius > 0):
            raise ConfigError(f"capsule radius must be positive, got {self.radius}", key=self.name)


@dataclass
class RobotModel:
    """A Pinocchio model with what the controllers need on top of it.

    Attributes:
        name: short name ("planar3", "panda", or the URDF's).
        model: the Pinocchio model (``nq == nv``: revolute/prismatic joints only).
        ee_frame: name of the frame whose origin is the task point.
        task_axes: which world axes form the task (``(0, 1)`` planar x–y, ``(0, 1, 2)`` spatial).
        capsules: link collision shapes for python-fcl, one per link that can collide.
        q_min, q_max: joint position limits [rad or m] (±inf where unlimited).
        v_max: joint speed limits [rad/s] (inf where unlimited).
        tau_max: joint torque limits [N·m] (inf where unlimited); symmetric, ``|τ| ≤ tau_max``.
        q_home: a default configuration.
        tau_rate_max: the drives' torque-rate limits [N·m/s] (inf where unlimited): between two
            commands dt apart, ``|τ_k − τ_{k−1}| ≤ tau_rate_max · dt``.
        qdd_max: joint acceleration limits [rad/s² or m/s²] (inf where unlimited), ``|q̈| ≤ qdd_max``.
        orientation: the task frame's orientation rows after the position rows: ``"none"``;
            ``"pose"`` — its rotation about the world axes ``orientation_axes`` (the log map of
            R_d Rᵀ); ``"approach"`` — the direction of ``approach_axis`` (a unit vector in the task
            frame) only, 2 rows, the roll about it left free (see :mod:`qpctl.orientation`).
    """

    name: str
    model: pin.Model
    ee_frame: str
    task_axes: tuple[int, ...]
    capsules: list[LinkCapsule]
    q_min: np.ndarray
    q_max: np.ndarray
    v_max: np.ndarray
    tau_max: np.ndarray
    q_home: np.ndarray
    joint_names: list[str] = field(default_factory=list)
    tau_rate_max: np.ndarray | None = None
    qdd_max: np.ndarray | None = None
    orientation: str = "none"
    orientation_axes: tuple[int, ...] = ()
    approach_axis: np.ndarray | None = None
    urdf: Path | None = None  # the URDF it was read from (simulators that load URDFs use it), if any

    def __post_init__(self) -> None:
        if self.model.nq != self.model.nv:
            raise ConfigError("only models with nq == nv (revolute/prismatic joints) are supported",
                              key="robot")
        self.ee_frame_id = self.frame_id(self.ee_frame)
        if not self.joint_names:
            self.joint_names = [self.model.names[i] for i in range(1, self.model.njoints)]
        for name in ("tau_rate_max", "qdd_max"):
            if getattr(self, name) is None:
                setattr(self, name, np.full(self.nv, np.inf))
        if self.approach_axis is None:
            self.approach_axis = np.array([0.0, 0.0, 1.0])
        for name in ("q_min", "q_max", "v_max", "tau_max", "q_home", "tau_rate_max", "qdd_max"):
            arr = np.asarray(getattr(self, name), dtype=float).reshape(-1)
            if arr.shape != (self.nv,):
                raise ConfigError(f"{name} must have {self.nv} entries, got {arr.shape[0]}", key=name)
            setattr(self, name, arr)

    @property
    def nv(self) -> int:
        """Number of joints (degrees of freedom)."""
        return int(self.model.nv)

    @property
    def m(self) -> int:
        """Task rows: the position's (2 planar, 3 spatial), then the orientation's (0, 2 or 3)."""
        return len(self.task_axes) + self.m_orientation

    @property
    def m_position(self) -> int:
        """The task's position rows (the coordinates of a path's points)."""
        return len(self.task_axes)

    @property
    def m_orientation(self) -> int:
        """The task's orientation rows: 0, ``len(orientation_axes)`` (pose) or 2 (approach)."""
        return {"none": 0, "pose": len(self.orientation_axes), "approach": 2}[self.orientation]

    @property
    def ee_rotation(self) -> np.ndarray:
        """The task frame's rotation in its parent joint's frame (3, 3)."""
        return np.array(self.model.frames[self.ee_frame_id].placement.rotation, float)

    def approach_basis(self) -> np.ndarray:
        """(2, 3) two unit vectors of the task frame orthogonal to ``approach_axis`` and to each other:
        the directions, rotating with the gripper, of the approach task's two rows."""
        a = np.asarray(self.approach_axis, float)
        seed = np.eye(3)[int(np.argmin(np.abs(a)))]
        b1 = np.cross(a, seed)
        b1 /= np.linalg.norm(b1)
        return np.array([b1, np.cross(a, b1)])

    def with_orientation(self, kind: str, *, axes: Sequence[int] = (0, 1, 2),
                         approach_axis: Sequence[float] = (0.0, 0.0, 1.0)) -> RobotModel:
        """A copy whose task adds the task frame's orientation (``kind`` "pose", "approach" or "none";
        ``axes``: the world rotation axes a pose task holds; ``approach_axis``: the gripper's approach
        direction in the task frame)."""
        if kind not in ("none", "pose", "approach"):
            raise ConfigError(f"must be position, pose or approach, got {kind!r}", key="controller.task")
        axes = tuple(int(a) for a in axes)
        axis = np.asarray(approach_axis, float).reshape(-1)
        if axis.shape != (3,) or not np.all(np.isfinite(axis)) or np.linalg.norm(axis) < 1e-9:
            raise ConfigError(f"must be a non-zero 3-vector, got {list(approach_axis)}", key="controller.approach_axis")
        if kind == "pose" and (len(set(axes)) != len(axes) or any(not 0 <= a <= 2 for a in axes)):
            raise ConfigError(f"pose axes must be distinct among 0, 1, 2, got {list(axes)}", key="controller.task_mask")
        return replace(self, orientation=kind, orientation_axes=axes if kind == "pose" else (),
                       approach_axis=axis / np.linalg.norm(axis), capsules=list(self.capsules),
                       joint_names=list(self.joint_names))

    def frame_id(self, name: str) -> int:
        """Pinocchio id of frame ``name``; :class:`UnknownFrameError` lists the frames that exist."""
        return frame_index(self.model, name)

    def with_task_axes(self, axes: Sequence[str | int]) -> RobotModel:
        """A copy whose task is the task point's position along ``axes`` ("x", "y", "z" or 0, 1, 2, in
        that order), checked with :meth:`check_task_axes`."""
        names = {"x": 0, "y": 1, "z": 2}
        try:
            idx = tuple(names[a.lower()] if isinstance(a, str) else int(a) for a in axes)
        except (KeyError, AttributeError, ValueError):
            raise ConfigError(f"must be world axes among x, y, z, got {list(axes)}", key="robot.task_axes") from None
        if not idx or len(set(idx)) != len(idx) or any(not 0 <= i <= 2 for i in idx) or list(idx) != sorted(idx):
            raise ConfigError(f"must be distinct world axes in the order x, y, z, got {list(axes)}",
                              key="robot.task_axes")
        out = replace(self, task_axes=idx, capsules=list(self.capsules), joint_names=list(self.joint_names))
        out.check_task_axes()
        return out

    def immobile_axes(self, samples: int = 8, seed: int = 0) -> list[int]:
        """World axes along which the task point cannot move at all: its Jacobian's row is zero at
        ``samples`` random configurations within the joint limits (a planar arm's normal, say)."""
        rng = np.random.default_rng(seed)
        lo = np.where(np.isfinite(self.q_min), self.q_min, -np.pi)
        hi = np.where(np.isfinite(self.q_max), self.q_max, np.pi)
        data = self.model.createData()
        reach = np.zeros(3)
        for _ in range(samples):
            q = rng.uniform(lo, hi)
            J = pin.computeFrameJacobian(self.model, data, q, self.ee_frame_id, pin.LOCAL_WORLD_ALIGNED)[:3]
            reach = np.maximum(reach, np.abs(J).max(axis=1))
        return [i for i in range(3) if reach[i] <= 1e-9 * max(1.0, float(reach.max()))]

    def check_task_axes(self) -> None:
        """:class:`ConfigError` if the task asks for motion along an axis the task point cannot move
        along: that row of the task Jacobian is zero everywhere, so every tick would be singular."""
        stuck = [i for i in self.immobile_axes() if i in self.task_axes]
        if stuck:
            keep = [a for a in self.task_axes if a not in stuck]
            names = "xyz"
            raise ConfigError(
                f"the task point ({self.ee_frame}) cannot move along {', '.join(names[i] for i in stuck)} "
                f"(a planar arm?): set robot.task_axes = {[names[i] for i in keep]}".replace("'", '"'),
                key="robot.task_axes")

    def with_limits(self, *, tau_max: Sequence[float] | float | None = None,
                    v_max: Sequence[float] | float | None = None,
                    tau_rate_max: Sequence[float] | float | None = None,
                    qdd_max: Sequence[float] | float | None = None) -> RobotModel:
        """Return a copy with torque, speed, torque-rate and/or acceleration limits replaced (a scalar
        applies to every joint; inf: no limit)."""
        out = replace(self, capsules=list(self.capsules), q_min=self.q_min.copy(), q_max=self.q_max.copy(),
                      v_max=self.v_max.copy(), tau_max=self.tau_max.copy(), q_home=self.q_home.copy(),
                      joint_names=list(self.joint_names), tau_rate_max=self.tau_rate_max.copy(),  # type: ignore[union-attr]
                      qdd_max=self.qdd_max.copy())  # type: ignore[union-attr]
        for name, val in (("tau_max", tau_max), ("v_max", v_max), ("tau_rate_max", tau_rate_max), ("qdd_max", qdd_max)):
            if val is not None:
                arr = np.asarray(val, float)
                if arr.ndim > 1 or arr.size not in (1, self.nv):
                    raise ConfigError(f"needs one value or {self.nv} (one per joint), got {arr.size}", key=f"robot.{name}")
                setattr(out, name, np.broadcast_to(arr.reshape(-1) if arr.ndim else arr, (self.nv,)).copy())
        return out

    @classmethod
    def from_urdf(cls, path: str | Path, ee_frame: str, *, capsules: list[LinkCapsule] | None = None,
                  locked_joints: Sequence[str] = (), capsule_radius: float = 0.05,
                  gravity: Sequence[float] = (0.0, 0.0, -9.81), q_home: Sequence[float] | None = None,
                  ee_offset: Sequence[float] | None = None, name: str | None = None) -> RobotModel:
        """Load a URDF. Without ``capsules``, each link gets a capsule from its joint to the next joint.

        ``ee_offset`` [m] adds a frame ``<ee_frame>_tcp`` at that offset in ``ee_frame`` and uses it.
        """
        path = Path(path)
        if not path.is_file():
            raise ConfigError(f"URDF not found: {path}", key="robot.urdf")
        full = pin.buildModelFromUrdf(str(path))
        if locked_joints:
            ids = []
            for jn in locked_joints:
                if not full.existJointName(jn):
                    raise ConfigError(f"no joint {jn!r} in {path.name}", key="robot.locked_joints")
                ids.append(full.getJointId(jn))
            model = pin.buildReducedModel(full, ids, pin.neutral(full))
        else:
            model = full
        model.gravity.linear = np.asarray(gravity, float)
        ee_id = frame_index(model, ee_frame)
        if ee_offset is not None:
            parent = model.frames[ee_id]
            placement = parent.placement * pin.SE3(np.eye(3), np.asarray(ee_offset, float))
            tcp = f"{ee_frame}_tcp"
            while model.existFrame(tcp):  # the URDF may already name a frame so (example-robot-data ≥ 4.2)
                tcp = f"{tcp}_offset"
            model.addFrame(pin.Frame(tcp, parent.parentJoint, ee_id, placement, pin.FrameType.OP_FRAME))
            ee_frame = tcp
            ee_id = frame_index(model, tcp)
        if capsules is None:
            capsules = default_capsules(model, capsule_radius)
        nv = model.nv
        return cls(
            name=name or path.stem, model=model, ee_frame=ee_frame, task_axes=(0, 1, 2), capsules=capsules,
            q_min=np.where(np.isfinite(model.lowerPositionLimit), model.lowerPositionLimit, -np.inf)[:nv],
            q_max=np.where(np.isfinite(model.upperPositionLimit), model.upperPositionLimit, np.inf)[:nv],
            v_max=np.where(model.velocityLimit > 0, model.velocityLimit, np.inf)[:nv],
            tau_max=np.where(model.effortLimit > 0, model.effortLimit, np.inf)[:nv],
            q_home=np.asarray(q_home, float) if q_home is not None else pin.neutral(model),
            urdf=path.resolve(),
        )


def default_capsules(model: pin.Model, radius: float) -> list[LinkCapsule]:
    """One capsule per joint's body, from the joint to its first child joint — or, on a link with no
    child joint (the last), to the farthest frame the URDF attaches to it (the task frame, a tool or
    tip link), so that every link with a length is covered. A link with neither is a sphere at its
    joint."""
    capsules = []
    for j in range(1, model.njoints):
        children = [c for c in range(j + 1, model.njoints) if model.parents[c] == j]
        if children:
            p1 = model.jointPlacements[children[0]].translation.copy()
        else:
            ends = [f.placement.translation for f in model.frames if f.parentJoint == j]
            p1 = max(ends, key=lambda p: float(np.linalg.norm(p)), default=np.zeros(3)).copy()
        capsules.append(LinkCapsule(model.names[j], j, np.zeros(3), p1, radius))
    return capsules


def planar_arm(n: int = RobotConfig.links, *, length: float = RobotConfig.length, mass: float = RobotConfig.mass,
               radius: float = RobotConfig.radius,
               gravity: float | Sequence[float] = 9.81,
               tau_max: float | Sequence[float] = np.inf) -> RobotModel:
    """The paper's planar arm: ``n`` uniform thin rods in the vertical x–y plane, gravity along −y.

    Joint i rotates about z at the tip of link i−1; link i points along its joint frame's x axis.
    The task point is the tip of the last link (frame ``"ee"``); the task is its (x, y) position.
    ``gravity`` is a magnitude [m/s²] along −y, or a 3-vector.
    """
    if n < 2:
        raise ConfigError("a planar arm needs at least 2 links", key="robot.links")
    for key, val in (("robot.length", length), ("robot.mass", mass), ("robot.radius", radius)):
        if not (np.isfinite(val) and val > 0):
            raise ConfigError(f"must be a positive number, got {val}", key=key)
    model = pin.Model()
    model.name = f"planar{n}"
    g = np.asarray(gravity, float)
    model.gravity.linear = np.array([0.0, -float(g), 0.0]) if g.ndim == 0 else g.reshape(3)
    izz = mass * length**2 / 12.0
    parent, placement = 0, pin.SE3.Identity()
    capsules = []
    for i in range(n):
        jid = model.addJoint(parent, pin.JointModelRZ(), placement, f"joint{i + 1}")
        # Thin rod along x: no inertia about its own axis (a tiny value keeps the tensor valid).
        inertia = pin.Inertia(mass, np.array([length / 2, 0.0, 0.0]), np.diag([1e-12 * izz, izz, izz]))
        model.appendBodyToJoint(jid, inertia, pin.SE3.Identity())
        model.addFrame(pin.Frame(f"link{i + 1}", jid, 0, pin.SE3.Identity(), pin.FrameType.BODY))
        capsules.append(LinkCapsule(f"link{i + 1}", jid, np.zeros(3), np.array([length, 0, 0]), radius))
        parent, placement = jid, pin.SE3(np.eye(3), np.array([length, 0.0, 0.0]))
    model.addFrame(pin.Frame("ee", parent, 0, placement, pin.FrameType.OP_FRAME))
    inf = np.full(n, np.inf)
    return RobotModel(
        name=f"planar{n}", model=model, ee_frame="ee", task_axes=(0, 1), capsules=capsules,
        q_min=-inf, q_max=inf, v_max=inf.copy(),
        tau_max=np.broadcast_to(np.asarray(tau_max, float), (n,)).copy(),
        q_home=np.array([np.pi, np.pi / 2] + [0.0] * (n - 2)),
    )


def example_robot_data_path(relative: str) -> Path:
    """Absolute path of a file shipped by the installed ``example-robot-data`` package.

    ``relative`` is below the package's ``robots/`` folder, e.g. ``panda_description/urdf/panda.urdf``.
    """
    try:
        files = importlib.metadata.files("example-robot-data") or []
    except importlib.metadata.PackageNotFoundError as exc:
        raise ConfigError("the example-robot-data package is not installed (pip install example-robot-data)",
                          key="robot") from exc
    suffix = "example-robot-data/robots/" + relative
    for f in files:
        if str(f).replace("\\", "/").endswith(suffix):
            return Path(f.locate()).resolve()
    raise ConfigError(f"example-robot-data has no file {relative}", key="robot")


# Capsules approximating the Panda's links, in each joint's frame [m], one per link. Measured against
# the collision meshes of example-robot-data's panda_description (meshes/collision/link{1..7}.stl,
# read as binary STL; each is a union of r = 0.055 m cylinders): for each link a minimax fit — the
# segment minimising (largest vertex-to-segment distance + 0.05 × segment length), scipy Nelder–Mead
# from 40 random starts — rounded to 5 mm, then the radius rounded up to 5 mm so that every vertex
# lies inside. Link 7's capsule also covers the hand (hand.stl, in the link-7 frame at z = 0.107 m
# turned −45° about z) and the locked, closed fingers (finger.stl at z = 0.0584 m in the hand frame),
# since the reduced model rigidly attaches them to joint 7. Result: 100 % of the vertices inside on
# every link; largest vertex distance / radius [m]: 0.078/0.08, 0.077/0.08, 0.071/0.075,
# 0.071/0.075, 0.069/0.07, 0.076/0.08, 0.088/0.09 (link 7 + hand). The previous table held only
# 11–57 % of each mesh's vertices (up to 0.11 m outside). tests/test_panda_capsules.py repeats the
# measurement. A tighter fit needs two capsules on the L-shaped links and a separate hand capsule.
_PANDA_CAPSULES: list[tuple[str, tuple[float, float, float], tuple[float, float, float], float]] = [
    ("panda_joint1", (0.0, -0.005, -0.145), (0.0, -0.055, 0.0), 0.08),
    ("panda_joint2", (0.0, -0.165, 0.015), (0.0, 0.005, 0.055), 0.08),
    ("panda_joint3", (0.095, 0.05, 0.015), (0.0, 0.0, -0.08), 0.075),
    ("panda_joint4", (0.0, 0.0, 0.045), (-0.08, 0.085, 0.0), 0.075),
    ("panda_joint5", (0.0, 0.01, -0.245), (0.0, 0.065, 0.0), 0.07),
    ("panda_joint6", (0.09, 0.01, 0.0), (0.015, 0.015, 0.01), 0.08),
    ("panda_joint7", (-0.03, -0.03, 0.15), (0.03, 0.03, 0.105), 0.09),
]


# Franka's published limits for the Panda's joints (Franka Control Interface documentation, "Robot
# and interface specifications", limits in the joint space): torque rate τ̇_max 1000 N·m/s and
# acceleration q̈_max per joint — what the FCI accepts in a command (libfranka's kMaxTorqueRate,
# kMaxJointAcceleration).
PANDA_TAU_RATE_MAX = 1000.0  # [N·m/s]
PANDA_QDD_MAX = (15.0, 7.5, 10.0, 12.5, 15.0, 20.0, 20.0)  # [rad/s²]


def panda(*, gravity: Sequence[float] = (0.0, 0.0, -9.81)) -> RobotModel:
    """The Franka Panda (7 DoF, fingers locked) from example-robot-data, task point between the
    fingertips; the URDF's torque, speed and position limits, and Franka's published torque-rate
    and acceleration limits (:data:`PANDA_TAU_RATE_MAX`, :data:`PANDA_QDD_MAX`)."""
    urdf = example_robot_data_path("panda_description/urdf/panda.urdf")
    locked = ["panda_finger_joint1", "panda_finger_joint2"]
    robot = RobotModel.from_urdf(urdf, "panda_hand", locked_joints=locked, gravity=gravity,
                                 ee_offset=(0.0, 0.0, 0.1034), name="panda",
                                 q_home=[0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785], capsules=[])
    model = robot.model
    robot.capsules = [LinkCapsule(jn, int(model.getJointId(jn)), np.array(a), np.array(b), r)
                      for jn, a, b, r in _PANDA_CAPSULES]
    robot.tau_rate_max = np.full(robot.nv, PANDA_TAU_RATE_MAX)
    robot.qdd_max = np.array(PANDA_QDD_MAX, float)
    return robot


def load_robot(kind: str, **kwargs: object) -> RobotModel:
    """Build a robot by name: ``"planar3"`` (or ``"planarN"``), ``"panda"``, or a path to a URDF."""
    if kind.lower().endswith(".urdf"):  # before the names: a file may be called planar4.urdf
        ee = kwargs.pop("ee_frame", None)
        if not isinstance(ee, str):
            raise ConfigError("a URDF robot needs robot.ee_frame", key="robot.ee_frame")
        return RobotModel.from_urdf(kind, ee, **kwargs)  # type: ignore[arg-type]
    if kind.startswith("planar"):
        suffix = kind[len("planar"):]
        if suffix and not suffix.isdigit():
            raise ConfigError(f"unknown robot {kind!r}; use planar3, panda or a URDF path", key="robot.kind")
        return planar_arm(int(suffix or 3), **kwargs)  # type: ignore[arg-type]
    if kind == "panda":
        return panda(**kwargs)  # type: ignore[arg-type]
    raise ConfigError(f"unknown robot {kind!r}; use planar3, panda or a path to a .urdf file", key="robot.kind")


def arm_reach(robot: RobotModel) -> tuple[np.ndarray, float] | None:
    """(centre [m], radius [m]) of a sphere that holds every position of the task point, or None.

    For a chain of revolute joints the first joint's origin stays put and each further joint origin
    (and the task frame) sits at a fixed distance from the previous one, so the task point is never
    farther from the first joint's origin than the sum of those distances. Prismatic or other joints
    give no such bound (None).
    """
    model = robot.model
    frame = model.frames[robot.ee_frame_id]
    radius = float(np.linalg.norm(frame.placement.translation))
    j = int(frame.parentJoint)
    if j == 0:
        return None
    while True:
        if not model.joints[j].shortname().startswith("JointModelR"):
            return None
        parent = int(model.parents[j])
        if parent == 0:
            return np.asarray(model.jointPlacements[j].translation, float).copy(), radius
        radius += float(np.linalg.norm(model.jointPlacements[j].translation))
        j = parent
