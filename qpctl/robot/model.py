"""Robot models: a Pinocchio model, the task frame, link collision capsules and limits.

Every rigid-body quantity in qpctl comes from Pinocchio; this module only builds the models (reading
their files through :mod:`qpctl.robot.files`).

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

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin

from qpctl.errors import ConfigError, UnknownFrameError
from qpctl.robot.config import RobotConfig
from qpctl.robot.files import example_robot_data_path, read_model, resolve_package_uri
from qpctl.robot.frame_orientation import FrameOrientation

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
    """A capsule attached to a joint's frame: the segment p0–p1 [m] (in that frame) swept by ``radius`` [m].

    ``links``: the robot's links (URDF links, MJCF bodies) it covers, which an SRDF's pairs name;
    empty where unknown (then no SRDF applies to it).
    """

    name: str
    joint_id: int
    p0: np.ndarray
    p1: np.ndarray
    radius: float
    links: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if not (np.isfinite(self.radius) and self.radius > 0):
            raise ConfigError(f"capsule radius must be positive, got {self.radius}", key=self.name)


@dataclass
class RobotModel:
    """A Pinocchio model with what the controllers need on top of it.

    Attributes:
        name: short name ("planar3", "panda", or the URDF's).
        model: the Pinocchio model: revolute and prismatic joints, continuous (unbounded revolute)
            joints and planar joints (x, y, θ; a mobile base). A configuration q has ``nq`` entries
            (Pinocchio's: cos θ, sin θ for a continuous joint), a velocity ``nv``; :meth:`angles` and
            :meth:`configuration` convert to and from one number per degree of freedom.
        ee_frame: name of the frame whose origin is the task point.
        task_axes: which world axes form the task (``(0, 1)`` planar x–y, ``(0, 1, 2)`` spatial).
        capsules: link collision shapes for python-fcl, one per link that can collide.
        q_min, q_max: joint position limits [rad or m], one per degree of freedom, in :meth:`angles`'
            coordinates (±inf where unlimited: always on continuous and planar joints).
        v_max: joint speed limits [rad/s] (inf where unlimited).
        tau_max: joint torque limits [N·m] (inf where unlimited); symmetric, ``|τ| ≤ tau_max``.
        q_home: a default configuration (Pinocchio's, ``nq``; given as ``nv`` angles it is converted).
        tau_rate_max: the drives' torque-rate limits [N·m/s] (inf where unlimited): between two
            commands dt apart, ``|τ_k − τ_{k−1}| ≤ tau_rate_max · dt``.
        qdd_max: joint acceleration limits [rad/s² or m/s²] (inf where unlimited), ``|q̈| ≤ qdd_max``.
        orientation: the task frame's orientation rows after the position rows: ``"none"``;
            ``"pose"`` — its rotation about the world axes ``orientation_axes`` (the log map of
            R_d Rᵀ); ``"approach"`` — the direction of ``approach_axis`` (a unit vector in the task
            frame) only, 2 rows, the roll about it left free (see :mod:`qpctl.orientation`).
        task_orientations: the orientation tasks of ``task_frames`` (one each; missing ones none).
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
    mjcf: Path | None = None  # the MJCF it was read from (MuJoCo runs it), if any
    srdf: Path | None = None  # the SRDF whose disabled pairs the self-collision pairs leave out, if any
    disabled_pairs: frozenset[frozenset[str]] | None = None  # its <disable_collisions> link pairs
    # more task frames after ee_frame (several arms on one torso): each adds its position rows along
    # task_axes, stacked in this order after ee_frame's; then each oriented frame's orientation rows
    task_frames: tuple[str, ...] = ()
    task_orientations: tuple[FrameOrientation, ...] = ()

    def __post_init__(self) -> None:
        self._joint_maps()
        self.ee_frame_id = self.frame_id(self.ee_frame)
        self.task_frames = tuple(self.task_frames)
        seen = {self.ee_frame}
        for name in self.task_frames:
            if name in seen:
                raise ConfigError(f"two tasks on frame {name!r}: give each task frame once", key="tasks")
            seen.add(name)
        self.task_frame_ids = [self.ee_frame_id] + [self.frame_id(f) for f in self.task_frames]
        self.task_orientations = tuple(self.task_orientations)
        if len(self.task_orientations) > len(self.task_frames):
            raise ConfigError(f"{len(self.task_orientations)} orientation tasks for {len(self.task_frames)} more "
                              "task frames", key="tasks")
        if not self.joint_names:
            self.joint_names = [self.model.names[i] for i in range(1, self.model.njoints)]
        for name in ("tau_rate_max", "qdd_max"):
            if getattr(self, name) is None:
                setattr(self, name, np.full(self.nv, np.inf))
        if self.approach_axis is None:
            self.approach_axis = np.array([0.0, 0.0, 1.0])
        home = np.asarray(self.q_home, dtype=float).reshape(-1)
        if self.lie and home.shape == (self.nv,):
            home = self.configuration(home)
        if home.shape != (self.nq,):
            raise ConfigError(f"q_home must have {self.nq} entries (or {self.nv} angles), got {home.shape[0]}",
                              key="q_home")
        self.q_home = home
        for name in ("q_min", "q_max", "v_max", "tau_max", "tau_rate_max", "qdd_max"):
            arr = np.asarray(getattr(self, name), dtype=float).reshape(-1)
            if arr.shape != (self.nv,):
                raise ConfigError(f"{name} must have {self.nv} entries, got {arr.shape[0]}", key=name)
            setattr(self, name, arr)
        if self.lie:  # no position limit on a continuous or planar joint's coordinates
            self.q_min = np.where(self.bounded, self.q_min, -np.inf)
            self.q_max = np.where(self.bounded, self.q_max, np.inf)

    def _joint_maps(self) -> None:
        """Index maps between a configuration (nq) and one number per degree of freedom (nv):
        ``_plain`` (q index, v index) of the coordinates that are the same in both (revolute,
        prismatic, a planar joint's x, y); ``_rot`` (index of cos θ, v index) of the angles stored as
        (cos θ, sin θ). A free-flyer or spherical joint is a :class:`ConfigError`."""
        plain_q: list[int] = []
        plain_v: list[int] = []
        rot_q: list[int] = []
        rot_v: list[int] = []
        bounded = np.ones(self.model.nv, dtype=bool)
        for j in range(1, self.model.njoints):
            jm = self.model.joints[j]
            kind, iq, iv = jm.shortname(), jm.idx_q, jm.idx_v
            if jm.nq == jm.nv:
                plain_q += range(iq, iq + jm.nq)
                plain_v += range(iv, iv + jm.nv)
            elif kind.startswith(("JointModelRUB", "JointModelRevoluteUnbounded")):
                rot_q.append(iq)
                rot_v.append(iv)
                bounded[iv] = False
            elif kind == "JointModelPlanar":
                plain_q += [iq, iq + 1]
                plain_v += [iv, iv + 1]
                rot_q.append(iq + 2)
                rot_v.append(iv + 2)
                bounded[iv:iv + 3] = False
            elif kind == "JointModelFreeFlyer":
                raise ConfigError(f"joint {self.model.names[j]!r} is a free-flyer (a floating base): it needs contact "
                                  "constraints, which qpctl does not model; fix the base or give it a planar joint",
                                  key="robot")
            else:
                raise ConfigError(f"joint {self.model.names[j]!r} is a {kind} (nq {jm.nq} ≠ nv {jm.nv}); qpctl takes "
                                  "revolute, prismatic, continuous and planar joints", key="robot")
        self._plain_q, self._plain_v = np.array(plain_q, np.int64), np.array(plain_v, np.int64)
        self._rot_q, self._rot_v = np.array(rot_q, np.int64), np.array(rot_v, np.int64)
        self.bounded = bounded

    @property
    def dof_names(self) -> list[str]:
        """One name per degree of freedom: the joint's, ``<joint>.x``, ``.y``, ``.theta`` on a planar joint."""
        names: list[str] = []
        for j in range(1, self.model.njoints):
            jm, name = self.model.joints[j], self.model.names[j]
            names += [name] if jm.nv == 1 else [f"{name}.{c}" for c in ("x", "y", "theta")[:jm.nv]]
        return names

    def check_scalar_joints(self, simulator: str) -> None:
        """:class:`ConfigError` if a joint is planar: ``simulator`` has one coordinate per joint axis
        (slides and hinges), whose velocities are not a planar joint's (Pinocchio's, in the base's frame)."""
        planar = [self.model.names[j] for j in range(1, self.model.njoints)
                  if self.model.joints[j].shortname() == "JointModelPlanar"]
        if planar:
            raise ConfigError(f"the {simulator} simulator takes hinges and slides; joint {planar[0]!r} is planar: "
                              "use the built-in simulator, or write the base as two prismatic joints and a "
                              "revolute one", key="sim.simulator")

    @property
    def nq(self) -> int:
        """Entries of a configuration (Pinocchio's ``nq``: 2 per continuous joint, 4 per planar one)."""
        return int(self.model.nq)

    @property
    def lie(self) -> bool:
        """True when a configuration is not one number per degree of freedom (nq ≠ nv)."""
        return self.model.nq != self.model.nv

    def angles(self, q: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """One number per degree of freedom [rad or m] of configuration(s) ``q`` (nq, or T × nq): a
        continuous joint's angle atan2(sin θ, cos θ) in (−π, π], a planar joint's x, y, θ; ``q`` itself
        where nq == nv (no copy). ``out``: an (nv,) array to write into."""
        q = np.asarray(q, float)
        if not self.lie:
            return q
        if out is None:
            out = np.empty(q.shape[:-1] + (self.nv,))
        out[..., self._plain_v] = q[..., self._plain_q]
        out[..., self._rot_v] = np.arctan2(q[..., self._rot_q + 1], q[..., self._rot_q])
        return out

    def configuration(self, angles: np.ndarray | Sequence[float]) -> np.ndarray:
        """The configuration (nq, or T × nq) of one number per degree of freedom (nv, or T × nv): the
        inverse of :meth:`angles`; a copy."""
        a = np.array(angles, float)
        if not self.lie:
            return a
        if a.shape[-1:] != (self.nv,):
            raise ConfigError(f"needs {self.nv} joint values, got {a.shape[-1] if a.ndim else 1}", key="robot.q0")
        q = np.empty(a.shape[:-1] + (self.nq,))
        q[..., self._plain_q] = a[..., self._plain_v]
        q[..., self._rot_q] = np.cos(a[..., self._rot_v])
        q[..., self._rot_q + 1] = np.sin(a[..., self._rot_v])
        return q

    def integrate(self, q: np.ndarray, dv: np.ndarray) -> np.ndarray:
        """q ⊕ dv: the configuration reached from ``q`` along the velocity ``dv`` for a unit time
        (``pin.integrate``; q + dv where nq == nv)."""
        return pin.integrate(self.model, q, dv) if self.lie else q + dv

    def difference(self, q0: np.ndarray, q1: np.ndarray) -> np.ndarray:
        """q1 ⊖ q0 (nv): the velocity that takes ``q0`` to ``q1`` in a unit time (``pin.difference``;
        q1 − q0 where nq == nv)."""
        return pin.difference(self.model, q0, q1) if self.lie else q1 - q0

    def interpolate(self, q0: np.ndarray, q1: np.ndarray, w: float) -> np.ndarray:
        """The configuration a fraction ``w`` of the way from ``q0`` to ``q1`` (``pin.interpolate``)."""
        return pin.interpolate(self.model, q0, q1, w) if self.lie else (1 - w) * q0 + w * q1

    def random_configuration(self, rng: np.random.Generator, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """A configuration of angles drawn uniformly in [lo, hi] (nv each)."""
        return self.configuration(rng.uniform(lo, hi))

    @property
    def nv(self) -> int:
        """Number of joints (degrees of freedom)."""
        return int(self.model.nv)

    @property
    def m(self) -> int:
        """Task rows: the position's (2 planar, 3 spatial, per task frame), then the orientation's (0, 2 or 3)."""
        return self.m_position + self.m_orientation

    @property
    def m_position(self) -> int:
        """The task's position rows (the coordinates of a path's points): ``task_axes`` per task frame."""
        return len(self.task_axes) * (1 + len(self.task_frames))

    @property
    def frames(self) -> tuple[str, ...]:
        """The task frames: ``ee_frame``, then ``task_frames``."""
        return (self.ee_frame, *self.task_frames)

    def task_positions(self, data: pin.Data) -> np.ndarray:
        """(m_position,) the task frames' positions along ``task_axes`` [m], stacked, from ``data``
        after ``framesForwardKinematics``."""
        axes = list(self.task_axes)
        return np.concatenate([data.oMf[f].translation[axes] for f in self.task_frame_ids])

    def with_task_frames(self, frames: Sequence[str]) -> RobotModel:
        """A copy whose tasks are on ``frames`` (the first becomes ``ee_frame``); an unknown frame is an
        :class:`UnknownFrameError`, a frame given twice a :class:`ConfigError` naming ``tasks``."""
        if not frames:
            raise ConfigError("needs at least one task", key="tasks")
        return replace(self, ee_frame=frames[0], task_frames=tuple(frames[1:]), task_orientations=(),
                       capsules=list(self.capsules), joint_names=list(self.joint_names))

    @property
    def m_orientation(self) -> int:
        """The task's orientation rows: each task frame's (0, ``len(axes)`` for a pose, 2 for an approach)."""
        return sum(self.frame_orientation(i).rows for i in range(len(self.task_frame_ids)))

    def frame_orientation(self, i: int = 0) -> FrameOrientation:
        """Task frame ``i``'s orientation task (0: ``ee_frame``'s, ``orientation`` and its keys)."""
        if i == 0:
            axis = np.asarray(self.approach_axis, float)
            return FrameOrientation(self.orientation, tuple(self.orientation_axes),
                                    (float(axis[0]), float(axis[1]), float(axis[2])))
        return self.task_orientations[i - 1] if i - 1 < len(self.task_orientations) else FrameOrientation()

    @property
    def oriented_frames(self) -> tuple[int, ...]:
        """The task frames (indices into :attr:`frames`) with orientation rows, in the rows' order."""
        return tuple(i for i in range(len(self.task_frame_ids)) if self.frame_orientation(i).rows)

    @property
    def ee_rotation(self) -> np.ndarray:
        """The task frame's rotation in its parent joint's frame (3, 3)."""
        return self.frame_rotation(0)

    def frame_rotation(self, i: int) -> np.ndarray:
        """Task frame ``i``'s rotation in its parent joint's frame (3, 3)."""
        return np.array(self.model.frames[self.task_frame_ids[i]].placement.rotation, float)

    def approach_basis(self) -> np.ndarray:
        """(2, 3) two unit vectors of the task frame orthogonal to ``approach_axis`` and to each other:
        the directions, rotating with the gripper, of the approach task's two rows."""
        return self.frame_orientation(0).basis()

    def with_orientation(self, kind: str, *, axes: Sequence[int] = (0, 1, 2),
                         approach_axis: Sequence[float] = (0.0, 0.0, 1.0)) -> RobotModel:
        """A copy whose task adds the task frame's orientation (``kind`` "pose", "approach" or "none";
        ``axes``: the world rotation axes a pose task holds; ``approach_axis``: the gripper's approach
        direction in the task frame)."""
        o = FrameOrientation.make(kind, axes, approach_axis)
        return replace(self, orientation=o.kind, orientation_axes=o.axes, approach_axis=np.array(o.approach_axis),
                       capsules=list(self.capsules), joint_names=list(self.joint_names))

    def with_frame_orientation(self, i: int, orientation: FrameOrientation) -> RobotModel:
        """A copy whose task frame ``i`` (an index into :attr:`frames`) has ``orientation``."""
        if i == 0:
            return self.with_orientation(orientation.kind, axes=orientation.axes,
                                         approach_axis=orientation.approach_axis)
        extra = list(self.task_orientations) + [FrameOrientation()] * (len(self.task_frames) - len(self.task_orientations))
        extra[i - 1] = orientation
        return replace(self, task_orientations=tuple(extra), capsules=list(self.capsules),
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
            q = self.random_configuration(rng, lo, hi)
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

    def link_names(self) -> list[str]:
        """The robot's links (URDF links, MJCF bodies): its Pinocchio model's body frames."""
        return list(dict.fromkeys(f.name for f in self.model.frames if f.type == pin.FrameType.BODY))

    def with_capsules(self, path: str | Path, *, key: str = "robot.capsules") -> RobotModel:
        """A copy whose capsules are a capsules file's (:func:`qpctl.robot.capsules.read_capsules`),
        each moved from its link's frame to its joint's; a link the model lacks is a
        :class:`ConfigError` naming ``key`` and listing the links."""
        from qpctl.robot.capsules import read_capsules

        return self.with_link_capsules(read_capsules(path, key=key), Path(path).name, key=key)

    def with_link_capsules(self, entries: Sequence[Any], source: str, *, key: str = "robot.capsules") -> RobotModel:
        """A copy whose capsules are ``entries`` (:class:`qpctl.robot.capsules.CapsuleEntry`: a link and
        a capsule in its frame), named after their links (``link:k`` where a link has several)."""
        links = self.link_names()
        counts: dict[str, int] = {}
        for e in entries:
            counts[e.link] = counts.get(e.link, 0) + 1
        capsules, seen = [], dict.fromkeys(counts, 0)
        for e in entries:
            if e.link not in links:
                raise ConfigError(f"{source} names link {e.link!r}, which {self.name} lacks; its links: "
                                  f"{', '.join(links)}", key=key)
            frame = self.model.frames[self.frame_id(e.link)]
            name = e.link if counts[e.link] == 1 else f"{e.link}:{seen[e.link]}"
            seen[e.link] += 1
            capsules.append(LinkCapsule(name, int(frame.parentJoint), frame.placement.act(e.capsule.a),
                                        frame.placement.act(e.capsule.b), e.capsule.radius, (e.link,)))
        return replace(self, capsules=capsules, joint_names=list(self.joint_names))

    def with_robot_files(self, *, capsules: str | Path | None = None, srdf: str | Path | None = None) -> RobotModel:
        """The scenario's ``robot.capsules`` and ``robot.srdf``: a capsules file replacing the
        capsules; the SRDF given, or (``srdf`` None) the one beside the robot's URDF when the capsules
        name their links, or none (``srdf = "none"``)."""
        from qpctl.robot.srdf import find_srdf

        out = self.with_capsules(capsules) if capsules else self
        named = any(c.links for c in out.capsules)
        if srdf == "none":
            return out
        if srdf:
            if not named:
                raise ConfigError(f"the capsules of {self.name} do not name their links, so no SRDF pair applies to "
                                  "them: set robot.capsules (qpctl fit-capsules)", key="robot.srdf")
            return out.with_srdf(srdf)
        found = find_srdf(self.urdf) if self.urdf is not None and named else None
        return out.with_srdf(found) if found is not None else out

    def with_srdf(self, path: str | Path, *, key: str = "robot.srdf") -> RobotModel:
        """A copy whose self-collision pairs leave out the SRDF's disabled link pairs
        (:func:`qpctl.robot.srdf.disabled_pairs`; a link the model lacks is a :class:`ConfigError`)."""
        from qpctl.robot.srdf import disabled_pairs

        pairs = disabled_pairs(path, self.link_names(), key=key)
        return replace(self, srdf=Path(path).resolve(), disabled_pairs=pairs, capsules=list(self.capsules),
                       joint_names=list(self.joint_names))

    @classmethod
    def from_urdf(cls, path: str | Path, ee_frame: str, *, capsules: list[LinkCapsule] | None = None,
                  locked_joints: Sequence[str] = (), capsule_radius: float = 0.05,
                  gravity: Sequence[float] = (0.0, 0.0, -9.81), q_home: Sequence[float] | None = None,
                  ee_offset: Sequence[float] | None = None, name: str | None = None) -> RobotModel:
        """Load a URDF. Without ``capsules``, each link gets a capsule from its joint to the next joint.

        ``ee_offset`` [m] adds a frame ``<ee_frame>_tcp`` at that offset in ``ee_frame`` and uses it.
        """
        path = resolve_package_uri(path)
        full = read_model(path, key="robot.urdf")
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
            capsules = default_capsules(model, capsule_radius, _links_with_geometry(path))
        q_min, q_max = position_limits(model)
        return cls(
            name=name or path.stem, model=model, ee_frame=ee_frame, task_axes=(0, 1, 2), capsules=capsules,
            q_min=q_min, q_max=q_max,
            v_max=np.where(model.velocityLimit > 0, model.velocityLimit, np.inf)[:model.nv],
            tau_max=np.where(model.effortLimit > 0, model.effortLimit, np.inf)[:model.nv],
            q_home=np.asarray(q_home, float) if q_home is not None else pin.neutral(model),
            urdf=path.resolve(),
        )


def position_limits(model: pin.Model) -> tuple[np.ndarray, np.ndarray]:
    """(q_min, q_max) [rad or m], one per degree of freedom: the model's position limits on joints whose
    configuration is their coordinate (nq == nv), ±inf elsewhere (continuous, planar) and where the
    file gives none (Pinocchio's ±DBL_MAX)."""
    lo, hi = np.full(model.nv, -np.inf), np.full(model.nv, np.inf)
    for j in range(1, model.njoints):
        jm = model.joints[j]
        if jm.nq == jm.nv:
            lo[jm.idx_v:jm.idx_v + jm.nv] = model.lowerPositionLimit[jm.idx_q:jm.idx_q + jm.nq]
            hi[jm.idx_v:jm.idx_v + jm.nv] = model.upperPositionLimit[jm.idx_q:jm.idx_q + jm.nq]
    big = 0.5 * np.finfo(float).max
    return np.where(lo > -big, lo, -np.inf), np.where(hi < big, hi, np.inf)


def _links_with_geometry(urdf: Path) -> set[str] | None:
    """The URDF's links that have a collision (or visual) element, or None if it cannot be read here."""
    import xml.etree.ElementTree as ET

    try:
        root = ET.parse(urdf).getroot()
    except ET.ParseError:
        return None
    return {str(link.get("name")) for link in root.iter("link")
            if link.find("collision") is not None or link.find("visual") is not None}


def default_capsules(model: pin.Model, radius: float, shaped: set[str] | None = None) -> list[LinkCapsule]:
    """One capsule per joint's body, from the joint to its first child joint — or, on a link with no
    child joint (the last), to the farthest frame the URDF attaches to it (the task frame, a tool or
    tip link), so that every link with a length is covered. A link with neither is a sphere at its
    joint. Each covers the links (body frames) its joint carries — those with geometry, when
    ``shaped`` names them."""
    capsules = []
    for j in range(1, model.njoints):
        links = tuple(f.name for f in model.frames if f.parentJoint == j and f.type == pin.FrameType.BODY)
        if shaped is not None and any(name in shaped for name in links):
            links = tuple(name for name in links if name in shaped)
        children = [c for c in range(j + 1, model.njoints) if model.parents[c] == j]
        if children:
            p1 = model.jointPlacements[children[0]].translation.copy()
        else:
            ends = [f.placement.translation for f in model.frames if f.parentJoint == j]
            p1 = max(ends, key=lambda p: float(np.linalg.norm(p)), default=np.zeros(3)).copy()
        capsules.append(LinkCapsule(model.names[j], j, np.zeros(3), p1, radius, links))
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
