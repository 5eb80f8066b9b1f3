"""Scenario files: TOML, validated on load, overridable by ``--set key.path=value``.

A scenario names the robot, the reference path, the obstacles, the controller and the simulation
(DESIGN.md §3–4; every key is documented in the README). Unknown keys, wrong types and missing
values raise :class:`~qpctl.errors.ConfigError` naming the file and the dotted key.
"""

from __future__ import annotations

import copy
import dataclasses
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from qpctl.barrier_design import BarrierDesign, auto_approach_speed, design_for
from qpctl.config import (
    REQUIRED,
    Checker,
    schema_of,
    string,
)
from qpctl.controllers.config import ControllerConfig, controller_schema
from qpctl.errors import ConfigError
from qpctl.geometry.obstacles import Obstacle
from qpctl.law import LawGains
from qpctl.paths import PathConfig, PosePath, TaskConfig, WaypointPath
from qpctl.perception.config import PerceptionConfig
from qpctl.robot.config import RobotConfig
from qpctl.robot.model import RobotModel, arm_reach, load_robot
from qpctl.scenario_orientation import path_rotations, with_task_orientations
from qpctl.scenes.canopy import Canopy, CanopyConfig, generate_canopy
from qpctl.simulation.camera import CameraConfig
from qpctl.simulation.faults import Faults, with_payload
from qpctl.simulation.loop import SimConfig

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

# Schema: each leaf is a (checker, default) pair; a checker returns the value or raises TypeError.
# Every table is generated from the fields of the dataclass that declares its keys (qpctl.config).
# [[obstacles]]: Obstacle's fields, and the label the paper reproduction groups them by
OBSTACLE_SCHEMA: dict[str, tuple[Checker, Any]] = {**schema_of(Obstacle), "area": (string, "")}
# [[tasks]]: several task frames, each with its own waypoints (qpctl.paths.TaskConfig)
TASK_SCHEMA: dict[str, tuple[Checker, Any]] = schema_of(TaskConfig)
ARRAYS = {"obstacles": OBSTACLE_SCHEMA, "tasks": TASK_SCHEMA}  # the arrays of tables

SCHEMA: dict[str, Any] = {
    "name": (string, "scenario"),
    "description": (string, ""),
    # [robot], [path], [controller], [faults], [sim]: their dataclasses' fields (qpctl.config.schema_of)
    "robot": schema_of(RobotConfig),
    "path": schema_of(PathConfig),
    "obstacles": OBSTACLE_SCHEMA,  # array of tables
    "tasks": TASK_SCHEMA,  # array of tables (none: the one task of robot.ee_frame and [path])
    # LawGains', QPConfig's and ControllerConfig's fields (qpctl.controllers.config)
    "controller": controller_schema(),
    # every fault off (qpctl.simulation.faults)
    "faults": schema_of(Faults),
    "sim": schema_of(SimConfig),
    "camera": schema_of(CameraConfig),  # a simulated depth camera (qpctl.simulation.camera); mount "": none
    "canopy": schema_of(CanopyConfig),  # a seeded canopy (qpctl.scenes.canopy); seed unset: none
    "perception": schema_of(PerceptionConfig),  # the depth map the QP reads with a [camera] (qpctl.perception)
}

# Tables that exist only when a key names them: a [camera] is its mount, a [canopy] its seed.
NAMED_BY = {"camera": "mount", "canopy": "seed"}


def _validate_table(raw: Any, schema: dict[str, Any], source: str, prefix: str) -> dict[str, Any]:
    if not isinstance(raw, dict):
        raise ConfigError("must be a table", source=source, key=prefix or "<top level>")
    out: dict[str, Any] = {}
    for key in raw:
        if key not in schema:
            where = f"{prefix}.{key}" if prefix else key
            known = ", ".join(sorted(schema))
            raise ConfigError(f"unknown key (known here: {known})", source=source, key=where)
    for key, spec in schema.items():
        where = f"{prefix}.{key}" if prefix else key
        if key in ARRAYS and not prefix:
            items = raw.get(key, [])
            if not isinstance(items, list):
                raise ConfigError(f"must be an array of tables ([[{key}]])", source=source, key=where)
            out[key] = [_validate_table(item, ARRAYS[key], source, f"{where}[{i}]")
                        for i, item in enumerate(items)]
        elif isinstance(spec, dict):
            out[key] = _validate_table(raw.get(key, {}), spec, source, where)
        else:
            checker, default = spec
            if key not in raw:
                if default is REQUIRED:
                    raise ConfigError("missing value", source=source, key=where)
                out[key] = copy.deepcopy(default)
                continue
            if raw[key] is None and default is None:  # an unset optional key (a validated dict re-read)
                out[key] = None
                continue
            try:
                out[key] = checker(raw[key])
            except TypeError as exc:
                raise ConfigError(f"must be {exc}, got {raw[key]!r}", source=source, key=where) from None
    return out


def parse_override(item: str) -> tuple[list[str], Any]:
    """``"controller.v_ref=0.4"`` → (["controller", "v_ref"], 0.4); values are read as TOML, else text."""
    if "=" not in item:
        raise ConfigError(f"expected KEY=VALUE, got {item!r}", source="--set")
    key, _, text = item.partition("=")
    key = key.strip()
    if not key:
        raise ConfigError(f"empty key in {item!r}", source="--set")
    try:
        value = tomllib.loads(f"v = {text.strip()}")["v"]
    except tomllib.TOMLDecodeError:
        value = text.strip()
    return key.split("."), value


def apply_overrides(raw: dict[str, Any], overrides: Sequence[str]) -> dict[str, Any]:
    """Set each dotted key in the raw scenario; the key must exist in the schema."""
    raw = copy.deepcopy(raw)
    for item in overrides:
        path, value = parse_override(item)
        dotted = ".".join(path)
        schema: Any = SCHEMA
        node = raw
        for i, part in enumerate(path):
            last = i == len(path) - 1
            table = part.split("[")[0]
            if table in ARRAYS and (part != table or not last):
                raise ConfigError(f"{table} cannot be overridden with --set; edit the file", source="--set",
                                  key=dotted)
            if not isinstance(schema, dict) or part not in schema:
                raise ConfigError("unknown key", source="--set", key=dotted)
            schema = schema[part]
            if last:
                if isinstance(schema, dict) and part != "solver_settings":
                    raise ConfigError("is a table; set one of its keys", source="--set", key=dotted)
                node[part] = value
            else:
                if part == "controller" and path[i + 1] == "solver_settings" and i + 2 < len(path):
                    node = node.setdefault(part, {}).setdefault("solver_settings", {})
                    node[".".join(path[i + 2:])] = value
                    break
                node = node.setdefault(part, {})
                if not isinstance(node, dict):
                    raise ConfigError("is not a table", source="--set", key=".".join(path[: i + 1]))
    return raw


def packaged_scenarios() -> list[str]:
    """Names of the scenarios shipped with qpctl."""
    folder = resources.files("qpctl") / "scenarios"
    return sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".toml"))


def depth_canopies(count: int = 20, first_seed: int = 1) -> list[Scenario]:
    """The packaged ``panda_canopy_depth`` with ``canopy.seed`` = first_seed, first_seed + 1, … (``count``
    of them, each validated: each grows at least one reachable fruit; :mod:`qpctl.scenes.canopy`)."""
    return [Scenario.load("panda_canopy_depth", overrides=[f"canopy.seed={s}"])
            for s in range(first_seed, first_seed + count)]


@dataclass
class Scenario:
    """A validated scenario; ``data`` mirrors the TOML with every default filled in."""

    data: dict[str, Any]
    source: str
    base_dir: Path | None = None  # where relative paths in it (robot.urdf) are resolved: the file's folder
    _canopy: Canopy | None = dataclasses.field(default=None, init=False, repr=False, compare=False)

    @classmethod
    def load(cls, spec: str | Path, overrides: Sequence[str] = ()) -> Scenario:
        """Load a TOML file, or a packaged scenario by name, and apply ``--set`` overrides."""
        path = Path(spec)
        if path.suffix == ".toml" or path.exists():
            if not path.is_file():
                raise ConfigError(f"scenario file not found: {path}")
            source, text, base = str(path), path.read_text(), path.resolve().parent
        else:
            res = resources.files("qpctl") / "scenarios" / f"{spec}.toml"
            if not res.is_file():
                raise ConfigError(f"no scenario named {str(spec)!r}; packaged: {', '.join(packaged_scenarios())}"
                                  " (or give a path to a .toml file)")
            source, text, base = f"{spec} (packaged)", res.read_text(), None
        try:
            raw = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(f"not valid TOML: {exc}", source=source) from None
        return cls.from_dict(raw, source=source, overrides=overrides, base_dir=base)

    @classmethod
    def from_dict(cls, raw: dict[str, Any], *, source: str = "<dict>", overrides: Sequence[str] = (),
                  base_dir: str | Path | None = None) -> Scenario:
        """A scenario from a dict as TOML would give it; relative paths in it (``robot.urdf``) are
        resolved from ``base_dir`` (default: the working folder)."""
        raw = apply_overrides(raw, overrides) if overrides else raw
        data = _validate_table(raw, SCHEMA, source, "")
        for table, key in NAMED_BY.items():  # a table set without the key that makes it exist (a table of
            given = raw.get(table)  # defaults only, as a validated scenario written back to TOML gives, is fine)
            if (isinstance(given, dict) and key not in given
                    and any(v != SCHEMA[table][k][1] for k, v in given.items() if k in SCHEMA[table])):
                raise ConfigError(f"missing value (the [{table}] table is written but its {key} is not given)",
                                  source=source, key=f"{table}.{key}")
        from qpctl.controllers.factory import CONTROLLERS, unknown_kind

        if data["controller"]["kind"] not in CONTROLLERS:
            raise unknown_kind(data["controller"]["kind"], source)
        scen = cls(data, source, Path(base_dir) if base_dir is not None else None)
        scen._check_values()
        return scen

    def _err(self, key: str, message: str) -> ConfigError:
        return ConfigError(message, source=self.source, key=key)

    def _check_tasks(self) -> None:
        """The ``[[tasks]]``: each names a frame once and gives as many waypoints as the others; they
        replace path.waypoints and path.start, and their first frame is robot.ee_frame."""
        tasks, path, r = self.data["tasks"], self.data["path"], self.data["robot"]
        if not tasks:
            return
        for key in ("waypoints", "start"):
            if path[key] is not None:
                raise self._err(f"path.{key}", "the [[tasks]] give each task frame's points: set them there")
        if self.data["canopy"]["seed"] is not None:
            raise self._err("tasks", "a [canopy]'s fruits are the waypoints of one task frame: drop the [[tasks]]")
        if r["ee_frame"] and r["ee_frame"] != tasks[0]["frame"]:
            raise self._err("robot.ee_frame", f"is {r['ee_frame']!r} but the first task's frame is "
                            f"{tasks[0]['frame']!r}: leave it out (the first task's frame is the task frame)")
        count = None
        for i, t in enumerate(tasks):
            if not t["frame"]:
                raise self._err(f"tasks[{i}].frame", "missing value (the task frame)")
            if t["frame"] in (u["frame"] for u in tasks[:i]):
                raise self._err(f"tasks[{i}].frame", f"two tasks on frame {t['frame']!r}: give each frame once")
            if not t["waypoints"]:
                raise self._err(f"tasks[{i}].waypoints", "missing value (the task's points after its start)")
            if count is not None and len(t["waypoints"]) != count:
                raise self._err(f"tasks[{i}].waypoints", f"has {len(t['waypoints'])} points, tasks[0] {count}: every "
                                "task moves through as many points, on [path]'s timing")
            count = len(t["waypoints"])
            w = t["weights"]
            ws = [w] if isinstance(w, float) else (w or [])
            if any(not (np.isfinite(x) and x > 0) for x in ws):
                raise self._err(f"tasks[{i}].weights", f"must be positive numbers, got {w}")

    def task_weights(self, robot: RobotModel) -> list[float] | None:
        """The QP's task-row weights: controller.task_weights, with the [[tasks]]' weights on their
        position rows (None: all 1)."""
        given = self.data["controller"]["task_weights"]
        tasks = self.data["tasks"]
        if not any(t["weights"] is not None for t in tasks):
            return given
        per = len(robot.task_axes)
        out = list(given) if given is not None else [1.0] * robot.m
        for i, t in enumerate(tasks):
            w = t["weights"]
            if w is None:
                continue
            vals = [float(w)] * per if isinstance(w, float) else list(w)
            if len(vals) != per:
                raise self._err(f"tasks[{i}].weights", f"needs one value or {per} (one per position row), got {len(vals)}")
            out[i * per:(i + 1) * per] = vals
        return out

    def _check_values(self) -> None:
        sim = self.data["sim"]
        try:  # the rules of the [sim] and [controller] keys' fields (dt and duration > 0, integrator, task...)
            SimConfig(**sim)
            c = self.data["controller"]
            ControllerConfig(**{f.name: c[f.name] for f in dataclasses.fields(ControllerConfig)})
        except ConfigError as exc:
            raise self._err(exc.key or "sim", exc.message) from None
        if sim["dt"] > sim["duration"]:
            raise self._err("sim.dt", f"step {sim['dt']} s exceeds the duration {sim['duration']} s")
        from qpctl.simulation.simulator import check_ticks

        try:
            check_ticks(sim["duration"], sim["dt"])
        except ConfigError as exc:
            raise self._err("sim.duration", str(exc).split(": ", 1)[-1]) from None
        path = self.data["path"]
        if path["duration"] is None and path["durations"] is None:
            raise self._err("path.duration", "missing value (give duration or durations)")
        self._check_tasks()
        if path["waypoints"] is None and self.data["canopy"]["seed"] is None and not self.data["tasks"]:
            raise self._err("path.waypoints", "missing value (or name a [canopy], whose reachable fruits are the "
                                              "waypoints)")
        from qpctl.adapters import SIMULATORS

        if sim["simulator"] not in SIMULATORS:
            raise self._err("sim.simulator", f"must be one of {', '.join(SIMULATORS)}, got {sim['simulator']!r}")
        if sim["model"] and not self.resolve(sim["model"]).is_file():
            raise self._err("sim.model", f"file not found: {self.resolve(sim['model'])}")
        if sim["joint_names"] is not None and not sim["model"]:
            raise self._err("sim.joint_names", "names the joints of sim.model, which is not set")
        faults = self.faults()
        try:
            CanopyConfig.from_dict(self.data["canopy"])
        except ConfigError as exc:
            raise self._err(exc.key or "canopy", exc.message) from None
        try:
            self.gains()
        except ConfigError as exc:
            raise ConfigError(exc.message, source=self.source, key=exc.key) from None
        self._check_controller()
        # Validated on load (DESIGN.md §4), not when the run starts: obstacles, robot, q0, path.
        obstacles = self.build_obstacles()
        robot = self.build_robot()
        w = self.task_weights(robot)
        if w is not None and (len(w) != robot.m or not all(np.isfinite(x) and x > 0 for x in w)):
            raise self._err("controller.task_weights", f"needs {robot.m} positive numbers (one per task row: "
                            f"{robot.m_position} position, {robot.m_orientation} orientation), got {w}")
        names = sim["joint_names"]
        if names is not None and (len(names) != robot.nv or len(set(names)) != len(names)):
            raise self._err("sim.joint_names", f"needs {robot.nv} distinct names (the simulator's names of "
                            f"{', '.join(robot.joint_names)}, in that order), got {names}")
        q0 = self.q0(robot)
        self._check_camera(robot)
        self.perception_config()
        if not self.camera_config().enabled and any(o.get("perceived") for o in self.data["obstacles"]):
            raise self._err("camera.mount", "perceived obstacles are known to the controller only through a depth "
                            "camera: give the [camera] a mount, or set perceived = false")
        self._check_reach(robot, self.build_path(robot, q0))
        self._check_start_clear(robot, obstacles, q0)
        self._check_start_apart(robot, q0)
        sat = faults.torque_saturation
        if sat is not None and np.size(sat) not in (1, robot.nv):
            raise self._err("faults.torque_saturation", f"needs one value or {robot.nv} (one per joint), got "
                            f"{np.size(sat)}")
        if faults.active and sim["simulator"] != "builtin":
            raise self._err("faults", f"the {sim['simulator']} simulator does not apply faults ({', '.join(faults.kinds())}"
                            "); use sim.simulator = \"builtin\"")

    def _check_controller(self) -> None:
        """The QP's keys, whichever controller the file names (``--controller qp`` may pick it later)."""
        from qpctl.controllers.qp import QPConfig
        from qpctl.errors import UnknownSolverError
        from qpctl.fallbacks import FALLBACKS
        from qpctl.solvers import make_solver

        c = self.data["controller"]
        try:  # every QPConfig key's type and rule (qpctl.config.check_fields)
            QPConfig.from_dict(c)
        except ConfigError as exc:
            raise ConfigError(exc.message, source=self.source, key=exc.key) from None
        for name in c["fallback"]:
            if name not in FALLBACKS:  # the strategies registered now (qpctl.fallbacks.register_fallback)
                try:
                    make_solver(name)
                except UnknownSolverError as exc:
                    raise self._err("controller.fallback", f"{exc} (or {', '.join(FALLBACKS)})") from None
        r = self.data["robot"]
        if r["gravity"] is not None and (len(r["gravity"]) != 3 or not np.all(np.isfinite(r["gravity"]))):
            raise self._err("robot.gravity", f"needs 3 finite numbers [m/s²] (x, y, z), got {r['gravity']}")
        for key in ("tau_max", "v_max", "tau_rate_max", "qdd_max"):
            if r[key] is not None and not np.all(np.asarray(r[key], float) > 0):  # inf allowed, NaN not
                raise self._err(f"robot.{key}", f"must be positive (inf: no limit), got {r[key]}")

    def _check_camera(self, robot: RobotModel) -> None:
        """The ``[camera]`` keys (CameraConfig's rules) and its mount frame on this robot."""
        try:
            cfg = self.camera_config()
            if cfg.mount not in ("", "world"):
                from qpctl.simulation.camera import DepthCamera

                DepthCamera(cfg, robot)
        except ConfigError as exc:
            raise self._err(exc.key or "camera", exc.message) from None

    def perception_config(self) -> PerceptionConfig:
        """The scenario's ``[perception]`` (the depth map's settings; used where a ``[camera]`` is)."""
        try:
            return PerceptionConfig(**self.data["perception"])
        except ConfigError as exc:
            raise self._err(exc.key or "perception", exc.message) from None

    def camera_config(self) -> CameraConfig:
        """The scenario's ``[camera]`` (``mount`` "": none; :mod:`qpctl.simulation.camera`)."""
        return CameraConfig.from_dict(self.data["camera"])

    def scenery(self) -> list[Obstacle]:
        """Shapes only a camera sees (a canopy's fruits): in its images, in no clearance."""
        canopy = self.canopy()
        return canopy.scenery() if canopy is not None else []

    def canopy(self) -> Canopy | None:
        """The scenario's seeded canopy (``[canopy]``, :mod:`qpctl.scenes.canopy`; None without a seed),
        grown once in front of its robot at q0, its fruits hidden from the world camera if there is one."""
        cfg = CanopyConfig.from_dict(self.data["canopy"])
        if not cfg.enabled:
            return None
        if self._canopy is None:
            robot = self.build_robot()
            camera = self.camera_config()
            eye = camera.mount_pose()[:3, 3] if camera.mount == "world" else None
            try:
                self._canopy = generate_canopy(cfg, robot, self.q0(robot), d_safe=self.data["controller"]["d_safe"],
                                               viewpoint=eye)
            except ConfigError as exc:
                raise self._err(exc.key or "canopy", exc.message) from None
        return self._canopy

    def _check_reach(self, robot: RobotModel, path: WaypointPath) -> None:
        """Every waypoint within the arm's reach (a sphere about its first joint; revolute arms with one
        task frame only)."""
        reach = arm_reach(robot) if not robot.task_frames else None
        if reach is None:
            return
        centre, radius = reach
        axes = list(robot.task_axes)
        for i, w in enumerate(path.points[1:]):
            d = float(np.linalg.norm(w - centre[axes]))
            if d > radius * (1 + 1e-9) + 1e-9:
                raise self._err("path.waypoints", f"waypoint {i} {w.tolist()} is out of reach: {d:.3f} m from the "
                                f"arm's base {centre[axes].tolist()}, which reaches at most {radius:.3f} m")

    def _check_start_clear(self, robot: RobotModel, obstacles: list[Obstacle], q0: np.ndarray) -> None:
        """No obstacle penetrates a link at the start (q0, t = 0): no controller could recover from that."""
        if not obstacles:
            return
        import pinocchio as pin

        from qpctl.geometry.distance import DistanceEngine

        data = robot.model.createData()
        pin.forwardKinematics(robot.model, data, q0)
        segments = np.array([[data.oMi[c.joint_id].act(c.p0), data.oMi[c.joint_id].act(c.p1)]
                             for c in robot.capsules])
        engine = DistanceEngine([c.radius for c in robot.capsules], obstacles, broadphase=False)
        engine.update(segments, 0.0)
        for j, obs in enumerate(obstacles):
            for i, cap in enumerate(robot.capsules):
                d = engine.pair(i, j)[0]
                if d < 0:
                    raise self._err(f"obstacles[{j}]", f"obstacle {obs.name!r} penetrates link {cap.name!r} by "
                                    f"{-d:.4f} m at the start configuration (robot.q0, t = 0)")

    def _check_start_apart(self, robot: RobotModel, q0: np.ndarray) -> None:
        """No two of the links the self-collision barrier keeps apart are within ``self_d_safe`` at the
        start (issue 22, item 5): the barrier's rows would be violated from the first tick, every tick
        infeasible. The pairs are the QP's (named, or :func:`self_collision_pairs`), the distances
        python-fcl's."""
        c = self.data["controller"]
        if not c["self_collision"] or not robot.capsules:
            return
        from qpctl.geometry.self_collision import fcl_self_distances, named_pairs, self_collision_pairs

        try:
            pairs = (named_pairs(robot, c["self_collision_pairs"]) if c["self_collision_pairs"] is not None
                     else self_collision_pairs(robot, c["self_d_safe"])).pairs
        except ConfigError as exc:
            raise self._err(exc.key or "controller.self_collision_pairs", exc.message) from None
        if not pairs:
            return
        gaps = fcl_self_distances(robot, q0, pairs)
        k = int(np.argmin(gaps))
        if gaps[k] < c["self_d_safe"]:
            a, b = (robot.capsules[i].name for i in pairs[k])
            how = f"overlap by {-gaps[k]:.4f} m" if gaps[k] < 0 else f"are {gaps[k]:.4f} m apart"
            raise self._err("robot.q0", f"links {a!r} and {b!r} {how} at the start configuration "
                            f"{np.round(robot.angles(q0), 4).tolist()}, within controller.self_d_safe = {c['self_d_safe']} m "
                            "(the self-collision rows would be violated from the first tick)")

    @property
    def name(self) -> str:
        return str(self.data["name"])

    def resolve(self, path: str) -> Path:
        """A path of the scenario's, relative ones from the scenario file's folder (or the working folder);
        ``package://example-robot-data/robots/<file>`` is that installed package's file."""
        if path.startswith("package://"):
            from qpctl.robot.files import resolve_package_uri

            return resolve_package_uri(path)
        p = Path(path).expanduser()
        return p if p.is_absolute() or self.base_dir is None else self.base_dir / p

    # -- builders -------------------------------------------------------------------------------
    def build_robot(self) -> RobotModel:
        r = self.data["robot"]
        try:
            if r["kind"].startswith("planar"):
                kwargs: dict[str, Any] = {"length": r["length"], "mass": r["mass"], "radius": r["radius"]}
                if r["gravity"] is not None:
                    kwargs["gravity"] = r["gravity"]
                robot = load_robot(f"planar{r['links']}" if r["kind"] == "planar" else r["kind"], **kwargs)
            elif r["kind"] == "urdf":
                r = {**r, "ee_frame": r["ee_frame"] or (self.data["tasks"][0]["frame"] if self.data["tasks"] else "")}
                for key in ("urdf", "ee_frame"):
                    if not r[key]:
                        raise self._err(f"robot.{key}", 'is required with robot.kind = "urdf" (the URDF file and '
                                                         "the frame whose origin is the task point)")
                kw: dict[str, Any] = {"capsule_radius": r["radius"], "locked_joints": r["locked_joints"] or ()}
                if r["gravity"] is not None:
                    kw["gravity"] = r["gravity"]
                robot = RobotModel.from_urdf(self.resolve(r["urdf"]), r["ee_frame"], **kw)
            elif r["kind"] == "mjcf":
                from qpctl.robot.mjcf import from_mjcf

                r = {**r, "ee_frame": r["ee_frame"] or (self.data["tasks"][0]["frame"] if self.data["tasks"] else "")}
                for key in ("mjcf", "ee_frame"):
                    if not r[key]:
                        raise self._err(f"robot.{key}", 'is required with robot.kind = "mjcf" (the MJCF file and '
                                                         "the frame whose origin is the task point)")
                robot = from_mjcf(self.resolve(r["mjcf"]), r["ee_frame"], gravity=r["gravity"])
            else:
                kw = {"gravity": r["gravity"]} if r["gravity"] is not None else {}
                robot = load_robot(r["kind"], **kw)
            robot = robot.with_robot_files(capsules=self.resolve(r["capsules"]) if r["capsules"] else None,
                                           srdf=self.resolve(r["srdf"]) if r["srdf"] not in ("", "none") else r["srdf"] or None)
            robot = self._with_task(robot)
            robot = self._with_task_frames(robot)
            limits = {k: r[k] for k in ("tau_max", "v_max", "tau_rate_max", "qdd_max") if r[k] is not None}
            if limits:
                robot = robot.with_limits(**limits)
            if not (np.isfinite(r["payload_mass"]) and r["payload_mass"] >= 0):
                raise ConfigError(f"must be a finite number >= 0 [kg], got {r['payload_mass']}", key="robot.payload_mass")
            if not (np.isfinite(r["payload_radius"]) and r["payload_radius"] > 0):
                raise ConfigError(f"must be a positive number [m], got {r['payload_radius']}", key="robot.payload_radius")
            if r["payload_mass"]:  # known to the controller, and carried by the simulated robot too
                robot = with_payload(robot, r["payload_mass"], r["payload_radius"])
        except ConfigError as exc:
            raise ConfigError(str(exc).split(": ", 1)[-1], source=self.source, key=exc.key or "robot") from None
        return robot

    def _with_task_frames(self, robot: RobotModel) -> RobotModel:
        """The [[tasks]]' frames (none: the robot's own task frame); an unknown frame names its key."""
        from qpctl.errors import UnknownFrameError

        frames = [t["frame"] for t in self.data["tasks"]]
        if not frames:
            return robot
        for i, name in enumerate(frames):
            try:
                robot.frame_id(name)
            except UnknownFrameError as exc:
                raise ConfigError(str(exc), key=f"tasks[{i}].frame") from None
        return with_task_orientations(self.data, robot.with_task_frames(frames))

    def _with_task(self, robot: RobotModel) -> RobotModel:
        """The robot's task rows: robot.task_axes, and controller.task's orientation rows."""
        r, c = self.data["robot"], self.data["controller"]
        task, mask = c["task"], c["task_mask"]
        if mask is not None:
            if task != "pose":
                raise ConfigError('applies to controller.task = "pose" only', key="controller.task_mask")
            if r["task_axes"] is not None:
                raise ConfigError("replaces robot.task_axes in a pose task: give one of them", key="controller.task_mask")
            if len(mask) != 6 or any(v not in (0.0, 1.0) for v in mask):
                raise ConfigError(f"needs 6 entries of 0 or 1 (x, y, z, rx, ry, rz), got {mask}", key="controller.task_mask")
            if not any(mask[:3]):
                raise ConfigError("must keep at least one position axis (x, y or z)", key="controller.task_mask")
        if r["task_axes"] is not None:
            robot = robot.with_task_axes(r["task_axes"])
        elif mask is not None:
            robot = robot.with_task_axes([i for i in range(3) if mask[i]])
        else:
            robot.check_task_axes()
        p = self.data["path"]
        for key, kinds in (("orientations", ("pose",)), ("approach", ("approach",)),
                           ("start_orientation", ("pose", "approach"))):
            if p[key] is not None and task not in kinds:
                raise ConfigError(f"applies to controller.task = {' or '.join(kinds)} only", key=f"path.{key}")
        if task == "position":
            return robot
        axes = [i for i in range(3) if mask is None or mask[3 + i]]
        return robot.with_orientation(task, axes=axes, approach_axis=c["approach_axis"])

    def q0(self, robot: RobotModel) -> np.ndarray:
        q0 = self.data["robot"]["q0"]
        if q0 is None:
            return robot.q_home.copy()
        if len(q0) != robot.nv:
            raise self._err("robot.q0", f"needs {robot.nv} joint values, got {len(q0)}")
        q = np.array(q0, float)
        if not np.all(np.isfinite(q)):
            raise self._err("robot.q0", f"must be finite numbers, got {q0}")
        outside = np.flatnonzero((q < robot.q_min) | (q > robot.q_max))
        if outside.size:
            i = int(outside[0])
            raise self._err("robot.q0", f"joint {robot.dof_names[i]} = {q[i]} is outside its limits "
                            f"[{robot.q_min[i]}, {robot.q_max[i]}]")
        return robot.configuration(q)  # one angle per continuous joint, x, y, θ per planar one → Pinocchio's q

    def build_path(self, robot: RobotModel, q0: np.ndarray) -> WaypointPath:
        p = self.data["path"]
        if self.data["tasks"]:
            return self._task_path(robot, q0)
        if p["start"] is not None:
            start = np.array(p["start"], float)
        else:
            import pinocchio as pin

            data = robot.model.createData()
            pin.framesForwardKinematics(robot.model, data, q0)
            start = data.oMf[robot.ee_frame_id].translation[list(robot.task_axes)].copy()
        waypoints = p["waypoints"]
        if waypoints is None:  # a canopy's reachable fruits (_check_values made sure there is one)
            canopy = self.canopy()
            assert canopy is not None
            waypoints = canopy.waypoints.tolist()
        pts = [list(start)] + waypoints
        if any(len(w) != robot.m_position for w in pts):
            raise self._err("path.waypoints", f"each point needs {robot.m_position} coordinates for robot {robot.name}")
        return self._timed_path(robot, q0, pts)

    def _timed_path(self, robot: RobotModel, q0: np.ndarray, pts: Any) -> WaypointPath:
        """The path through ``pts`` on [path]'s timing (a pose path where the robot has orientation rows)."""
        p = self.data["path"]
        timing = {"duration": p["duration"], "durations": p["durations"], "start_time": p["start_time"],
                  "dwell": p["dwell"]}
        try:
            if robot.m_orientation:
                return PosePath(pts, path_rotations(self.data, robot, q0, len(pts)), **timing)
            return WaypointPath(pts, **timing)
        except ConfigError as exc:
            raise ConfigError(exc.message, source=self.source, key=exc.key) from None

    def _task_path(self, robot: RobotModel, q0: np.ndarray) -> WaypointPath:
        """The [[tasks]]' paths as one: each point the task frames' points stacked (their position
        rows' order), on [path]'s timing."""
        import pinocchio as pin

        tasks = self.data["tasks"]
        data = robot.model.createData()
        pin.framesForwardKinematics(robot.model, data, q0)
        at_q0 = robot.task_positions(data).reshape(len(tasks), -1)
        per = robot.m_position // len(tasks)
        rows = []
        for i, t in enumerate(tasks):
            pts = ([t["start"]] if t["start"] is not None else [at_q0[i].tolist()]) + t["waypoints"]
            if any(len(w) != per for w in pts):
                raise self._err(f"tasks[{i}].waypoints", f"each point needs {per} coordinates (robot.task_axes)")
            rows.append(np.array(pts, float))
        pts = np.concatenate(rows, axis=1)
        return self._timed_path(robot, q0, pts)

    def build_obstacles(self) -> list[Obstacle]:
        """The ``[[obstacles]]``, then a ``[canopy]``'s trunk, wires, branches and leaves."""
        out = []
        for i, o in enumerate(self.data["obstacles"]):
            kwargs = {k: v for k, v in o.items() if k != "area"}
            kwargs["name"] = o["name"] or f"obstacle{i}"
            try:
                out.append(Obstacle(**kwargs))
            except ConfigError as exc:
                raise ConfigError(str(exc).split(": ", 1)[-1], source=self.source,
                                  key=f"obstacles[{i}].{(exc.key or '').rsplit('.', 1)[-1]}") from None
        canopy = self.canopy()
        return out + (copy.deepcopy(canopy.obstacles) if canopy is not None else [])  # fresh, as the others

    def faults(self) -> Faults:
        """The run's faults (``[faults]``, all off by default; :mod:`qpctl.simulation.faults`)."""
        try:
            return Faults.from_dict(self.data["faults"])
        except ConfigError as exc:
            raise ConfigError(str(exc).split(": ", 1)[-1], source=self.source, key=exc.key) from None

    def d_safe_margin(self, robot: RobotModel | None = None) -> float:
        """The margin [m] the controllers add to d_safe (``controller.d_safe_margin``; ``"auto"``: the one
        :meth:`Faults.margin` derives from ``[faults]``'s noise levels, 0 without faults)."""
        margin = self.data["controller"]["d_safe_margin"]  # ≥ 0 or "auto" (ControllerConfig's rule)
        if margin != "auto":
            return float(margin)
        faults = self.faults()
        return faults.margin(robot if robot is not None else self.build_robot()) if faults.active else 0.0

    def barrier_design(self, robot: RobotModel | None = None, *, margin: float | None = None) -> BarrierDesign | None:
        """The barrier gains and influence distance derived from the robot's drives
        (``controller.barrier_design = "drives"``, :mod:`qpctl.barrier_design`), or None ("manual": the
        scenario's ``barrier_k0``, ``barrier_k1`` and ``d_influence`` as written). ``margin``: the
        d_safe margin when the caller has it (:meth:`d_safe_margin`)."""
        c = self.data["controller"]  # barrier_design and approach_speed checked by ControllerConfig
        if c["barrier_design"] == "manual":
            return None
        robot = robot if robot is not None else self.build_robot()
        q0 = self.q0(robot)
        v = c["approach_speed"]
        if v == "auto":
            v = auto_approach_speed(self.build_path(robot, q0), self.build_obstacles())
        margin = self.d_safe_margin(robot) if margin is None else margin
        try:
            return design_for(robot, q0, float(v), c["d_safe"] + margin, self.data["sim"]["dt"])
        except ConfigError as exc:
            raise self._err(exc.key or "controller.barrier_design", exc.message) from None

    def gains(self, robot: RobotModel | None = None) -> LawGains:
        """The laws' gains, with d_safe raised by :meth:`d_safe_margin` (``controller.d_safe`` stays the
        distance the run is judged by; ``d_influence`` the design's under ``barrier_design = "drives"``)."""
        margin = self.d_safe_margin(robot)
        return self._gains(margin, self.barrier_design(robot, margin=margin))

    def _gains(self, margin: float, designed: BarrierDesign | None) -> LawGains:
        c = dict(self.data["controller"])
        if designed is not None:
            c["d_influence"] = designed.d_influence
        if margin > 0 and not c["d_safe"] + margin < c["d_influence"]:
            raise self._err("controller.d_safe_margin", f"d_safe {c['d_safe']} m + margin {margin:.4g} m must stay "
                            f"below d_influence {c['d_influence']} m")
        c["d_safe"] += margin
        return LawGains(**{f.name: c[f.name] for f in dataclasses.fields(LawGains) if f.name in c})

    def build_controller(self, kind: str | None = None, solver: str | None = None,
                         robot: RobotModel | None = None, obstacles: list[Obstacle] | None = None) -> Any:
        """The scenario's controller (``kind``/``solver`` override the file; ``obstacles`` replaces the
        scenario's in the controller's map, e.g. :meth:`Faults.perceived`)."""
        from qpctl.controllers.factory import controller_class, make_controller

        robot = robot or self.build_robot()
        q0 = self.q0(robot)
        c = dict(self.data["controller"])
        c["task_weights"] = self.task_weights(robot)  # with the [[tasks]]' own
        margin = self.d_safe_margin(robot)
        designed = self.barrier_design(robot, margin=margin)  # once: the gains below take it too
        if designed is not None:
            c["barrier_k0"], c["barrier_k1"], c["d_influence"] = designed.k0, designed.k1, designed.d_influence
        if c.get("braking_period") == 0:  # the braking-aware rows' period: the simulator's
            c["braking_period"] = self.data["sim"]["dt"]
        if kind is not None:
            c["kind"] = kind
        if solver is not None:
            c["solver"] = solver
        controller_class(c["kind"], self.source)  # a ConfigError naming the registered kinds
        bp = {"auto": None, "on": True, "off": False}[c["broadphase"]]  # ControllerConfig's choices
        scene = self.build_obstacles() if obstacles is None else obstacles
        ctrl = make_controller(c, robot, self.build_path(robot, q0), scene, self._gains(margin, designed),
                               broadphase=bp, source=self.source)  # type: ignore[arg-type]
        if not c["backup"]:
            return ctrl
        from qpctl.safety import BackupGuard

        return BackupGuard(ctrl, self.data["sim"]["dt"], check_distance=c["backup_check_distance"],
                           margin=c["backup_margin"], check_steps=c["backup_check_steps"],
                           check_evaluations=c["backup_check_evaluations"],
                           tries_on_brake=c["backup_tries_on_brake"], retreats=c["backup_retreats"],
                           hold=c["backup_hold"], unverified=c["backup_unverified"],
                           retreat_proposals=c["backup_retreat_proposals"], settle=c["backup_settle"],
                           carry=c["backup_carry"])

    def to_toml(self, **changes: dict[str, Any]) -> str:
        """The validated scenario as a TOML file that :meth:`load` reads back to the same ``data``:
        every default filled in, relative paths (``robot.urdf``, ``.mjcf``, ``.capsules``, ``.srdf``,
        ``sim.model``) made absolute, unset
        optional keys left out. ``changes`` replaces keys of a table, e.g. ``controller={"kind": "qp"}``
        for the law a run used (what ``qpctl simulate`` writes beside a run as ``scenario.toml``)."""
        import tomli_w

        data = copy.deepcopy(self.data)
        for table, values in changes.items():
            data[table].update(values)
        for table, key in (("robot", "urdf"), ("robot", "mjcf"), ("robot", "capsules"), ("robot", "srdf"),
                           ("sim", "model")):
            if data[table].get(key) and data[table][key] != "none":  # robot.srdf = "none": no SRDF
                data[table][key] = str(self.resolve(data[table][key]).resolve())
        return tomli_w.dumps(_toml_value(data))


def _toml_value(value: Any) -> Any:
    """``value`` with numpy scalars and arrays as plain numbers and lists, tuples as lists, and the
    None of unset optional keys dropped (TOML has no null)."""
    if isinstance(value, dict):
        return {k: _toml_value(v) for k, v in value.items() if v is not None}
    if isinstance(value, (list, tuple, np.ndarray)):
        return [_toml_value(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    return value
