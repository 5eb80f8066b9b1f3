"""Run a scenario end to end and write its outputs (``trajectory.npz``, ``metrics.json``, figures,
``scenario.toml`` — the scenario as it ran — and the replay page ``replay.html``).

Outputs are written to a temporary folder beside ``out`` and moved into place only when the run
has finished, so a failed run leaves nothing half-written.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from qpctl.controllers.base import Controller
from qpctl.replay.record import SCENARIO_FILE
from qpctl.scenario import Scenario
from qpctl.simulation.loop import SimulatorBase
from qpctl.simulation.metrics import compute_metrics
from qpctl.simulation.simulator import Simulator, Trajectory
from qpctl.simulation.trajectory import link_segments


@dataclass
class RunResult:
    scenario: Scenario
    controller: Controller
    trajectory: Trajectory
    metrics: dict[str, Any]
    perception: Any = None  # the depth map's loop (qpctl.perception.closed_loop.MapLoop), with a [camera]


def simulate(scenario: Scenario, *, kind: str | None = None, solver: str | None = None,
             simulator: str | None = None, progress: bool = False) -> RunResult:
    """Build the scenario's controller and run it in the chosen simulator (built-in RK4 by default).

    ``simulator`` (or ``sim.simulator``) is a name in :data:`qpctl.adapters.SIMULATORS`: ``builtin``,
    ``mujoco``, ``pybullet``, ``drake``. With ``[faults]`` on, the controller is built on its (perturbed)
    map of the obstacles and the built-in simulator applies the faults (:mod:`qpctl.simulation.faults`); the
    other simulators refuse them. What an adapter changed in or found about the user's model
    (``sim.model``) is in ``metrics["simulator_notes"]``."""
    faults = scenario.faults()
    sim_cfg = scenario.data["sim"]
    which = simulator or sim_cfg["simulator"]
    if faults.active and which != "builtin":
        from qpctl.errors import ConfigError

        raise ConfigError(f"the {which} simulator does not apply faults ({', '.join(faults.kinds())}); "
                          "use the built-in one", source=scenario.source, key="faults")
    robot = scenario.build_robot()
    truth = scenario.build_obstacles()
    sees = scenario.camera_config().enabled  # a depth camera: the perceived obstacles reach the QP by its map
    known = [o for o in truth if not o.perceived]
    seen = faults.perceived(known, robot.task_axes) if faults.active else (known if len(known) < len(truth) else None)
    controller = scenario.build_controller(kind, solver, robot=robot, obstacles=seen)
    judged = [o for o in truth if o.material != "soft"]  # min_clearance: to the true rigid geometry
    q0 = scenario.q0(controller.robot)
    from qpctl.adapters import simulator_class
    from qpctl.errors import ConfigError

    sim: SimulatorBase
    try:
        cls = simulator_class(which)
        if which == "builtin":
            sim = Simulator.from_scenario(controller, scenario, progress=progress,
                                          faults=faults if faults.active else None,
                                          obstacles=judged if (faults.active or seen is not None
                                                               or len(judged) < len(truth)) else None)
        else:
            sim = cls.from_scenario(controller, scenario, progress=progress)
    except ConfigError as exc:  # name the scenario file beside the key
        if exc.source is not None:
            raise
        raise ConfigError(str(exc).split(": ", 1)[-1] if exc.key else str(exc), source=scenario.source,
                          key=exc.key) from None
    loop = _perceive(scenario, controller, sim, truth) if sees else None
    traj = sim.run(q0)
    metrics: dict[str, Any] = {
        "scenario": scenario.name,
        "controller": controller.kind,
        "solver": getattr(controller, "solver", "closed-form"),
        "simulator": which,
        "gravity": controller.robot.model.gravity.linear.tolist(),
    }
    d_safe = float(scenario.data["controller"]["d_safe"])  # the run is judged by the scenario's d_safe
    metrics.update(compute_metrics(traj, d_safe=d_safe, frames=len(controller.robot.frames)))
    margin = scenario.d_safe_margin(controller.robot)
    if margin:
        metrics["d_safe_margin"] = margin
    if faults.active:
        metrics["faults"] = {k: getattr(faults, k) for k in faults.kinds()} | {"seed": faults.seed}
        metrics.update(getattr(sim, "fault_counts", {}))
    metrics.update(sim.counts)
    if loop is not None:
        traj.map_points, traj.map_stamps = loop.map_points()  # the replay draws the map the rows read
        metrics.update(loop.metrics())
        path = loop.path.path if loop.path is not None else controller.path
        metrics["fruit_errors_mm"] = [float(np.min(np.linalg.norm(traj.x[:, :3] - p, axis=1)) * 1e3)
                                      for p in path.points[1:]]
        metrics["fruit_misses"] = loop.explain_misses(traj, path.points[1:])
    canopy = scenario.canopy()
    if canopy is not None:  # what was grown, and each fruit's reachability (with the reason where not)
        metrics["canopy"] = canopy.summary()
    if sim.notes:
        metrics["simulator_notes"] = list(sim.notes)
    return RunResult(scenario, controller, traj, metrics, loop)


def _perceive(scenario: Scenario, controller: Controller, sim: SimulatorBase, truth: list[Any]) -> Any:
    """The scenario's depth camera and map on the QP's rows (:func:`qpctl.perception.closed_loop.attach`);
    a closed-form law reads no map: a note says it sees the known primitives only."""
    if controller.kind != "qp":
        sim.notes.append(f"the {controller.kind} law does not read the depth map: it sees only the known "
                         "(not perceived) obstacles")
        return None
    from qpctl.perception.closed_loop import attach
    from qpctl.simulation.camera import DepthCamera

    camera = DepthCamera.from_scenario(scenario, controller.robot)  # the whole world: the leaves too
    if sim.name == "mujoco" and camera.config.caster in ("auto", "mujoco"):
        camera.use_mujoco(sim)
    path = controller.path
    targets = (np.asarray(path.points[1:], float), np.asarray(path.starts, float)) if hasattr(path, "starts") else None
    return attach(controller, sim, scenario.perception_config(), camera=camera, world=truth, targets=targets)


def scenario_as_run(result: RunResult) -> str:
    """The run's scenario as TOML (:meth:`Scenario.to_toml`), with the law, solver and simulator it
    ran with (``qpctl simulate RUN_DIR/scenario.toml`` runs it again; ``qpctl replay`` reads it)."""
    controller = {"kind": result.controller.kind}
    solver = result.metrics.get("solver")
    if solver and solver != "closed-form":
        controller["solver"] = solver
    return result.scenario.to_toml(controller=controller, sim={"simulator": result.metrics["simulator"]})


def write_outputs(result: RunResult, out: Path, *, figures: bool = True, replay: bool = True) -> list[Path]:
    """Write trajectory.npz, metrics.json, scenario.toml, the figures and (``replay``) the replay page
    replay.html (:mod:`qpctl.replay`) into ``out`` atomically (folder-wise)."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        result.trajectory.save(tmp / "trajectory.npz")
        (tmp / "metrics.json").write_text(json.dumps(result.metrics, indent=2) + "\n")
        (tmp / SCENARIO_FILE).write_text(scenario_as_run(result))
        if figures:
            from qpctl.plots import write_figures

            segs = link_segments(result.controller, result.trajectory.q)
            label = f"{result.scenario.name}, {result.controller.kind}"
            write_figures(tmp, result.trajectory, segs, result.controller.obstacles, label,
                          tau_rate_max=result.controller.robot.tau_rate_max)
            if result.perception is not None:  # the depth map's: a frame, a field slice, true vs believed
                result.perception.write_figures(tmp, result.trajectory.t, result.trajectory.clearance,
                                                float(result.scenario.data["controller"]["d_safe"]))
        if replay:
            from qpctl.replay import REPLAY_FILE, from_result, write_replay

            write_replay(from_result(result), tmp / REPLAY_FILE)
        names = sorted(f.name for f in tmp.iterdir())
        if not out.exists():  # the usual case: one rename, so the folder appears complete or not at all
            mask = os.umask(0)
            os.umask(mask)
            tmp.chmod(0o777 & ~mask)  # mkdtemp made it private; give it a new folder's usual mode
            tmp.rename(out)
            return [out / name for name in names]
        written = []
        for f in sorted(tmp.iterdir()):  # an existing folder: each file replaced by a rename
            dest = out / f.name
            shutil.move(str(f), dest)
            written.append(dest)
        return written
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
