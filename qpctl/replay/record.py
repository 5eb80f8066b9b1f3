"""What a replay is made of, gathered from a finished run (:func:`from_result`) or from a run's folder
(:func:`from_run_dir`): the robot, the world's obstacles, the recorded arrays, and the distances that
scale the links' colours. Nothing is recomputed from the physics: the page shows the run's own
arrays.

A run folder needs ``trajectory.npz`` and the ``scenario.toml`` that ``qpctl simulate`` writes beside
it (the scenario as it ran: every default filled in, the law and simulator it used); a folder written
before that file existed gets a :class:`~qpctl.errors.ReplayError`. An optional depth map's points
are read from ``trajectory.npz`` when it holds them (:data:`MAP_KEYS`).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from qpctl.errors import ConfigError, ReplayError
from qpctl.geometry.obstacles import Obstacle
from qpctl.robot.model import RobotModel
from qpctl.simulation.trajectory import Trajectory

SCENARIO_FILE = "scenario.toml"  # beside a run's outputs: its scenario as it ran (qpctl.run.scenario_as_run)

if TYPE_CHECKING:
    from qpctl.scenario import Scenario

#: Optional arrays of ``trajectory.npz`` the page draws as the depth map's points: ``map_points``
#: (K, 3) [m] in the world frame and, optionally, ``map_stamps`` (K,) [s], the time from which each
#: point is part of the map (points sharing a stamp form one snapshot; a snapshot is shown from its
#: stamp until the next one's). Written by whatever builds the map (qpctl.perception); none: no map.
MAP_KEYS = ("map_points", "map_stamps")


@dataclass(frozen=True)
class ReplayInput:
    """Everything the page draws.

    Attributes:
        robot: the robot the run controlled (its model, capsules and, from a URDF, its meshes).
        obstacles: the world's obstacles as they moved in the simulation (with ``[faults]``, the truth,
            not the controller's map).
        trajectory: the recorded arrays (DESIGN.md §4).
        d_safe: the distance the run is judged by [m] (``controller.d_safe``).
        d_influence: where the controller starts to act on an obstacle [m].
        title: "<scenario> — <law> (<solver>, <simulator>)".
        tau_max: the joint torque limits [N·m] (inf: none), for the torque panel.
        map_points: (K, 3) depth-map points [m] or None; ``map_stamps`` (K,) their stamps [s] or None.
    """

    robot: RobotModel
    obstacles: list[Obstacle]
    trajectory: Trajectory
    d_safe: float
    d_influence: float
    title: str
    tau_max: np.ndarray
    map_points: np.ndarray | None = None
    map_stamps: np.ndarray | None = None


def world_obstacles(scenario: Scenario, robot: RobotModel) -> list[Obstacle]:
    """The obstacles as the built-in simulator moves them: the scenario's, with ``[faults]``'s unknown
    drift (:meth:`Faults.world <qpctl.simulation.faults.Faults.world>`)."""
    truth = scenario.build_obstacles()
    faults = scenario.faults()
    return faults.world(truth, robot.task_axes) if faults.active else truth


def _title(scenario: Scenario, metrics: dict[str, Any]) -> str:
    law = metrics.get("controller", scenario.data["controller"]["kind"])
    extra = [str(v) for v in (metrics.get("solver"), metrics.get("simulator")) if v and v != "closed-form"]
    return f"{scenario.name} — {law}" + (f" ({', '.join(extra)})" if extra else "")


def _map(arrays: Any) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The depth map's points and stamps from an npz file or an object's attributes, checked."""
    get = arrays.get if isinstance(arrays, dict) else (lambda k: getattr(arrays, k, None))
    points, stamps = get("map_points"), get("map_stamps")
    if points is None:
        return None, None
    points = np.asarray(points, float).reshape(-1, 3) if np.size(points) % 3 == 0 else None
    if points is None:
        raise ReplayError("map_points must be (K, 3) points [m]")
    if stamps is not None:
        stamps = np.asarray(stamps, float).reshape(-1)
        if stamps.shape != (len(points),):
            raise ReplayError(f"map_stamps needs one stamp per map point ({len(points)}), got {stamps.size}")
    return points, stamps


def _make(scenario: Scenario, robot: RobotModel, traj: Trajectory, metrics: dict[str, Any],
          maps: tuple[np.ndarray | None, np.ndarray | None]) -> ReplayInput:
    return ReplayInput(robot, world_obstacles(scenario, robot), traj, float(scenario.data["controller"]["d_safe"]),
                       float(scenario.gains(robot).d_influence), _title(scenario, metrics),
                       np.asarray(robot.tau_max, float), *maps)


class RunLike(Protocol):
    """What :func:`from_result` reads of a :class:`qpctl.run.RunResult` (the run layer is above this one)."""

    scenario: Scenario
    controller: Any
    trajectory: Trajectory
    metrics: dict[str, Any]


def from_result(result: RunLike) -> ReplayInput:
    """The replay of a run just simulated (:func:`qpctl.run.simulate`)."""
    robot = result.controller.robot
    return _make(result.scenario, robot, result.trajectory, result.metrics, _map(result.trajectory))


def from_run_dir(run_dir: str | Path) -> ReplayInput:
    """The replay of the run written into ``run_dir`` (``trajectory.npz``, ``scenario.toml``, and
    ``metrics.json`` for the title); :class:`ReplayError` naming what is missing."""
    from qpctl.scenario import Scenario

    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise ReplayError(f"{run_dir} is not a folder (give the output folder of a run)")
    npz, toml = run_dir / "trajectory.npz", run_dir / SCENARIO_FILE
    if not npz.is_file():
        raise ReplayError(f"{run_dir} has no trajectory.npz: not the output folder of a run")
    if not toml.is_file():
        raise ReplayError(f"{run_dir} has no {SCENARIO_FILE} (the scenario as it ran, written by qpctl simulate "
                          "since the replay page): simulate the run again to replay it")
    try:
        scenario = Scenario.load(toml)
    except ConfigError as exc:
        raise ReplayError(f"{toml} cannot be read back: {exc}") from None
    traj = Trajectory.load(npz)
    with np.load(npz) as data:
        maps = _map({k: data[k] for k in MAP_KEYS if k in data.files})
    metrics_file = run_dir / "metrics.json"
    metrics = json.loads(metrics_file.read_text()) if metrics_file.is_file() else {}
    robot = scenario.build_robot()
    if traj.q.ndim != 2 or traj.q.shape[1] != robot.nq:
        raise ReplayError(f"{npz} holds {traj.q.shape[-1]}-joint states but {toml} describes a {robot.nv}-joint "
                          f"robot ({robot.name})")
    return _make(scenario, robot, traj, metrics, maps)
