"""The simulated depth camera in MuJoCo: ``mujoco.mj_multiRay`` as a :class:`~qpctl.simulation.camera.DepthCamera`'s caster.

In the MuJoCo simulator the camera casts in the live model (``camera.use_mujoco(simulator)``, or
``caster = "auto"`` in a scenario run there), so a user's own model is seen as MuJoCo holds it, its
meshes included; :func:`qpctl.adapters.mujoco.scene_caster` builds a MuJoCo model of a camera's own scene instead (the
tests hold it to qpctl's kernel pixel for pixel).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from qpctl.kernels import raycast as K
from qpctl.simulation.camera import DepthCamera, Hits

try:
    import mujoco
except ImportError as exc:  # pragma: no cover - exercised only without the extra
    raise ImportError("MuJoCo's ray casting needs MuJoCo: pip install 'qpctl[mujoco]'") from exc


class MujocoCaster:
    """``mujoco.mj_multiRay`` in a MuJoCo model holding the camera's shapes: the MuJoCo simulator's
    live model (:meth:`qpctl.adapters.mujoco.MujocoSimulator.ray_caster`), or one built from the
    camera's scene (:func:`qpctl.adapters.mujoco.scene_caster`).

    It keeps its own ``MjData``: the joints are set to q, the moving obstacles' mocap bodies to their
    place at t, and ``mj_kinematics`` places the geoms. Geoms are matched to the camera's shapes by
    name (the obstacles' and scenery's as :func:`qpctl.adapters.mujoco.robot_mjcf` and
    :func:`~qpctl.adapters.mujoco.load_user_model` name them, the link capsules ``capsule{k}_…``); a
    geom on a body the robot's joints move that is none of those (a user model's meshes) is "robot",
    any other "other" (a table, a floor). ``joints``: the model's
    :class:`~qpctl.adapters.mujoco.MujocoJoints` of the robot. The camera's shapes that hold its origin are excluded (moved
    to geom group 5 for the call, so a user's own group-5 geoms are not seen either).
    """

    def __init__(self, model: mujoco.MjModel, joints: Any, camera: DepthCamera, *, prefix: str = "") -> None:
        self.model = model
        self.data = mujoco.MjData(model)
        self.joints = joints
        names = [model.geom(g).name for g in range(model.ngeom)]
        index = {n: g for g, n in enumerate(names)}
        robot_bodies = self._robot_bodies(model, joints)
        self.geom_to_shape = np.full(model.ngeom, camera.id_other, np.int32)
        for g in range(model.ngeom):
            if int(model.geom_bodyid[g]) in robot_bodies:
                self.geom_to_shape[g] = camera.id_robot
        self.shape_geom = np.full(len(camera.visible), -1, np.int64)  # the camera's shape → its geom
        for i, obs in enumerate([*camera.obstacles, *camera.scenery]):
            base = prefix + (obs.name or f"obstacle{i}")
            g = index.get(f"{base}_geom" if obs.moving else base, -1)
            if g >= 0:
                self.geom_to_shape[g] = i
                self.shape_geom[i] = g
        n_before = len(camera.obstacles) + len(camera.scenery)
        for k, cap in enumerate(camera.robot.capsules):
            g = index.get(f"capsule{k}_{cap.name}", -1)
            if g >= 0:
                self.geom_to_shape[g] = n_before + k
                self.shape_geom[n_before + k] = g
        self.mocap = []
        for i, obs in enumerate(camera.obstacles):
            if obs.moving:
                bid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, prefix + (obs.name or f"obstacle{i}"))
                if bid >= 0 and model.body_mocapid[bid] >= 0:
                    self.mocap.append((int(model.body_mocapid[bid]), obs))
        H, W = camera.intrinsics.height, camera.intrinsics.width
        self._geomid = np.zeros(H * W, np.int32)
        self._dist = np.zeros(H * W)
        self._normal = np.zeros(3 * H * W)
        self._dirs = np.zeros((H * W, 3))

    @staticmethod
    def _robot_bodies(model: Any, joints: Any) -> set[int]:
        """The bodies the robot's joints move (their subtrees)."""
        moved = {int(model.jnt_bodyid[j]) for j in joints.jnt_ids}
        out = set()
        for b in range(model.nbody):
            a = b
            while a > 0:
                if a in moved:
                    out.add(b)
                    break
                a = int(model.body_parentid[a])
        return out

    def cast(self, camera: DepthCamera, pose: np.ndarray, q: np.ndarray, t: float) -> Hits:
        model, data = self.model, self.data
        self.joints.write_state(data, q, np.zeros(len(self.joints.dof_adr)))
        for mocap_id, obs in self.mocap:
            data.mocap_pos[mocap_id] = obs.position_at(t)
        mujoco.mj_kinematics(model, data)
        origin = np.ascontiguousarray(pose[:3, 3])
        dirs = self._dirs
        K.rotate_rays(camera.rays, np.ascontiguousarray(pose[:3, :3]), dirs)  # world directions, optical z = 1
        inside = np.zeros(len(camera.visible), np.bool_)
        scene = camera.scene
        K.contains_point(scene.kind, scene.centre, scene.axes, scene.size, origin, inside)
        hidden = self.shape_geom[(inside | ~camera.visible) & (self.shape_geom >= 0)]
        groups = model.geom_group[hidden].copy()
        model.geom_group[hidden] = 5
        try:
            N = len(dirs)
            far = camera.config.range_max * float(np.sqrt((dirs * dirs).sum(axis=1).max()))
            mujoco.mj_multiRay(model, data, origin, dirs.reshape(-1), np.array([1, 1, 1, 1, 1, 0], np.uint8), 1, -1,
                               self._geomid, self._dist, self._normal, N, far)
        finally:
            model.geom_group[hidden] = groups
        H, W = camera.intrinsics.height, camera.intrinsics.width
        found = (self._geomid >= 0) & (self._dist >= 0) & (self._dist <= camera.config.range_max)
        depth = np.where(found, self._dist, np.inf).reshape(H, W)
        hit = np.where(found, self.geom_to_shape[np.maximum(self._geomid, 0)], -1).astype(np.int32).reshape(H, W)
        normal = self._normal.reshape(-1, 3)
        cos = np.abs((normal * dirs).sum(axis=1)) / np.sqrt((dirs * dirs).sum(axis=1))
        return Hits(depth, hit, np.where(found, cos, 0.0).reshape(H, W))

