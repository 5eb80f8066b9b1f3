"""URDF text for the simulators that load one (PyBullet, Drake), without importing either.

* :func:`robot_urdf` writes a URDF from the Pinocchio model (the planar arm, any model without a file);
* :func:`prepare_urdf` makes a robot's or a user's URDF fit for a torque-controlled run: the joints the
  controller does not drive fixed (as Pinocchio's reduced model locks them), the others without stops,
  collision geometry (and, for PyBullet, the visuals) dropped;
* :func:`urdf_joints` reads which of the URDF's joints stand for the controller's — by name, or by
  order when none of the names is there — and the joint damping it declares (Pinocchio does not read
  ``<dynamics>``, so the controller's model has none).
"""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import pinocchio as pin

from qpctl.errors import ConfigError
from qpctl.robot.model import RobotModel

MOVABLE = ("revolute", "continuous", "prismatic")
_AXES = {"X": (1.0, 0.0, 0.0), "Y": (0.0, 1.0, 0.0), "Z": (0.0, 0.0, 1.0)}


def _fmt(values: Sequence[float] | np.ndarray) -> str:
    return " ".join(f"{float(v):.17g}" for v in np.asarray(values, float).reshape(-1))


def _joint_type_axis(joint: Any) -> tuple[str, np.ndarray]:
    kind = joint.shortname()
    for k, axis in _AXES.items():
        if kind in (f"JointModelR{k}", f"JointModelRUB{k}"):  # revolute, continuous
            return "continuous", np.array(axis)
        if kind == f"JointModelP{k}":
            return "prismatic", np.array(axis)
    if kind in ("JointModelRevoluteUnaligned", "JointModelRevoluteUnboundedUnaligned"):
        return "continuous", np.asarray(joint.extract().axis, float)
    if kind == "JointModelPrismaticUnaligned":
        return "prismatic", np.asarray(joint.extract().axis, float)
    raise ConfigError(f"joint type {kind} has no URDF counterpart here (revolute, continuous and prismatic only)",
                      key="robot")


def robot_urdf(robot: RobotModel) -> str:
    """URDF text of ``robot``'s Pinocchio model: one link per joint with Pinocchio's placement, mass,
    centre of mass and rotational inertia; joints named ``robot.joint_names``, continuous (revolute
    without stops) or prismatic without limits; the root link ``qpctl_base``; no visuals, collisions,
    transmissions, damping or friction."""
    model = robot.model
    root = ET.Element("robot", {"name": robot.name})
    base = ET.SubElement(ET.SubElement(root, "link", {"name": "qpctl_base"}), "inertial")
    ET.SubElement(base, "mass", {"value": "0"})  # a fixed base: its mass plays no part
    ET.SubElement(base, "inertia", {"ixx": "0", "ixy": "0", "ixz": "0", "iyy": "0", "iyz": "0", "izz": "0"})
    link_names = {0: "qpctl_base"}
    for j in range(1, model.njoints):
        name = f"qpctl_link{j}"
        link_names[j] = name
        link = ET.SubElement(root, "link", {"name": name})
        inertia = model.inertias[j]
        if not inertia.mass > 0:
            raise ConfigError(f"joint {model.names[j]} moves a body without mass; a simulator cannot simulate it",
                              key="robot")
        inertial = ET.SubElement(link, "inertial")
        ET.SubElement(inertial, "origin", {"xyz": _fmt(inertia.lever), "rpy": "0 0 0"})
        ET.SubElement(inertial, "mass", {"value": f"{inertia.mass:.17g}"})
        ic = inertia.inertia
        ET.SubElement(inertial, "inertia", {k: f"{ic[a, b]:.17g}" for k, (a, b) in {
            "ixx": (0, 0), "ixy": (0, 1), "ixz": (0, 2), "iyy": (1, 1), "iyz": (1, 2), "izz": (2, 2)}.items()})
        jtype, axis = _joint_type_axis(model.joints[j])
        joint = ET.SubElement(root, "joint", {"name": robot.joint_names[j - 1], "type": jtype})
        placement = model.jointPlacements[j]
        ET.SubElement(joint, "origin", {"xyz": _fmt(placement.translation),
                                        "rpy": _fmt(pin.rpy.matrixToRpy(placement.rotation))})
        ET.SubElement(joint, "parent", {"link": link_names[int(model.parents[j])]})
        ET.SubElement(joint, "child", {"link": name})
        ET.SubElement(joint, "axis", {"xyz": _fmt(axis)})
        if jtype == "prismatic":
            ET.SubElement(joint, "limit", {"lower": "-1e9", "upper": "1e9", "effort": "0", "velocity": "0"})
    ET.indent(root)
    return ET.tostring(root, encoding="unicode")


def prepare_urdf(text: str, joint_names: Sequence[str], *, joint_limits: bool = False,
                 visuals: bool = False) -> str:
    """A URDF made fit for a torque-controlled run: no ``<collision>`` (nor its meshes), no ``<visual>``
    unless ``visuals``, no ``<mimic>``; movable joints not in ``joint_names`` fixed; ``joint_names``'
    revolute joints continuous, without position limits, unless ``joint_limits``."""
    kinds = "visual|collision" if not visuals else "collision"
    text = re.sub(rf"<({kinds})\b.*?</\1>", "", text, flags=re.DOTALL)
    text = re.sub(rf"<({kinds})\b[^>]*/>", "", text)
    text = re.sub(r"<mimic\b[^>]*/>", "", text)
    root = ET.fromstring(text)
    keep = set(joint_names)
    for joint in root.iter("joint"):
        kind, name = joint.get("type"), joint.get("name")
        if kind in MOVABLE and name not in keep:
            joint.set("type", "fixed")
        elif kind == "revolute" and not joint_limits:
            joint.set("type", "continuous")
            for limit in joint.iter("limit"):
                limit.attrib.pop("lower", None)
                limit.attrib.pop("upper", None)
    return ET.tostring(root, encoding="unicode")


class UrdfJoints(NamedTuple):
    """Which joints of a URDF stand for the controller's (:func:`urdf_joints`).

    Attributes:
        names: the URDF's names of the controller's joints, in the controller's order.
        by_order: matched by order (none of the controller's names is in the file): the simulator must
            then find the same dynamics, or refuse.
        damping: joint name → its declared ``<dynamics damping>`` [N·m·s/rad], where not zero.
    """

    names: tuple[str, ...]
    by_order: bool
    damping: dict[str, float]

    def order_note(self, robot: RobotModel) -> str:
        """The sentence for the simulator's notes when ``by_order``."""
        return "joints matched by order: " + ", ".join(f"{a} → {b}" for a, b in zip(robot.joint_names, self.names))

    def damping_note(self) -> str:
        """The sentence for the simulator's notes when it removed ``damping``."""
        return ("the URDF's joint damping set to 0, as in the controller's model (Pinocchio does not read it): "
                + ", ".join(f"{k} {v:g}" for k, v in self.damping.items()) + " N·m·s/rad")


def urdf_joints(text: str, robot: RobotModel, joint_names: Sequence[str] | None = None, *, own: bool = False,
                source: Path | None = None) -> UrdfJoints:
    """The controller's joints in the URDF ``text``: ``joint_names`` if given (``sim.joint_names``), else
    ``robot.joint_names`` — or, in a user's own file (``own``) that has none of them, its movable joints
    in order, which must be as many as the robot's.

    Raises:
        ConfigError: ``sim.model`` if the text is not XML; ``sim.joint_names`` for a wrong count.
    """
    names = list(joint_names) if joint_names is not None else None
    if names is not None and len(names) != robot.nv:
        raise ConfigError(f"needs {robot.nv} names (the URDF's names of {', '.join(robot.joint_names)}), "
                          f"got {len(names)}", key="sim.joint_names")
    try:
        joints = list(ET.fromstring(text).iter("joint"))
    except ET.ParseError as exc:
        raise ConfigError(f"not a readable URDF ({source or 'generated'}): {exc}", key="sim.model") from None
    by_order = False
    if names is None:
        movable = [str(j.get("name")) for j in joints if j.get("type") in MOVABLE]
        if own and not any(n in movable for n in robot.joint_names):
            if len(movable) != robot.nv:
                raise ConfigError(f"cannot match joints by order: the URDF has {len(movable)} movable joints "
                                  f"({', '.join(movable)}), the robot {robot.nv}; name them with sim.joint_names",
                                  key="sim.joint_names")
            names, by_order = movable, True
        else:
            names = list(robot.joint_names)
    damping = {}
    for j in joints:
        dyn = j.find("dynamics")
        value = float(dyn.get("damping", 0) or 0) if dyn is not None else 0.0
        if j.get("name") in names and value != 0:
            damping[str(j.get("name"))] = value
    return UrdfJoints(tuple(names), by_order, damping)
