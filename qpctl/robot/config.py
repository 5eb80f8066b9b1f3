"""The ``[robot]`` keys of a scenario, each declared here once (:func:`qpctl.config.schema_of`).

The planar arm's defaults (:func:`qpctl.robot.model.planar_arm`) and the payload's radius
(:data:`qpctl.simulation.faults.PAYLOAD_RADIUS`) read theirs from here.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True, kw_only=True)
class RobotConfig:
    """The ``[robot]`` table (units in brackets; None: the robot's own).

    kind: "planar3" / "planarN" (the paper's arm with N links), "panda", "urdf", "mjcf". links, length [m],
    mass [kg]: the planar arm's links (uniform thin rods); radius [m]: the link capsules' radius (planar
    arm; URDF links). gravity [m/s²]: a 3-vector. urdf (kind = "urdf") or mjcf (kind = "mjcf"): the
    robot file (relative to the scenario's folder, or package://example-robot-data/robots/...) and
    ee_frame: the task frame. locked_joints: joints of the URDF held at their neutral position (a
    Baxter's head and grippers: Pinocchio's reduced model). capsules: a capsules file (``qpctl fit-capsules``) replacing the link
    capsules. srdf: the SRDF whose disabled pairs the self-collision pairs leave out ("": the one beside
    the URDF, if any, when the capsules name their links; "none": no SRDF). task_axes: the
    world axes the task point tracks. q0 [rad]: the start. tau_max [N·m], v_max [rad/s], tau_rate_max
    [N·m/s], qdd_max [rad/s²]: limits, one value or one per joint. payload_mass [kg],
    payload_radius [m]: a payload the controller knows, a solid sphere on the task frame.
    """

    kind: str = "planar3"
    links: int = 3
    length: float = 1.0
    mass: float = 10.0
    radius: float = 0.05
    gravity: list[float] | None = None
    urdf: str = ""
    mjcf: str = ""
    ee_frame: str = ""
    locked_joints: list[str] | None = None
    capsules: str = ""
    srdf: str = ""
    task_axes: list[str] | None = None
    q0: list[float] | None = None
    tau_max: float | list[float] | None = None
    v_max: float | list[float] | None = None
    tau_rate_max: float | list[float] | None = None
    qdd_max: float | list[float] | None = None
    payload_mass: float = 0.0
    payload_radius: float = 0.04
