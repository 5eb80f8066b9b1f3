"""Scene families of a sweep: each turns (family, scene index) into a raw scenario dict.

* ``canopy`` — the Franka Panda reaching a random fruit in a seeded canopy of branch capsules and
  leaf spheres (:func:`qpctl.bench.scenes.canopy_scene`);
* ``planar`` — the paper's 3-link arm reaching a random point past 2–4 random discs
  (:func:`qpctl.bench.scenes.planar_scene`);
* ``scenario`` — a packaged scenario by name (``paper``, ``panda_canopy``, …) or a TOML file.

A random scene is built in code from its seed, then written as the scenario dict that TOML would
give (robot, path, obstacles, controller gains, sim), so that every run goes through the same
validation, ``--set``-style overrides and :func:`qpctl.run.simulate` as ``qpctl simulate``.
"""

from __future__ import annotations

import copy
import sys
from pathlib import Path
from typing import Any

from qpctl.errors import ConfigError

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

FAMILY_KINDS = ("canopy", "planar", "scenario")


def _obstacle_dict(o: Any) -> dict[str, Any]:
    out: dict[str, Any] = {"name": o.name, "shape": o.shape, "position": [float(x) for x in o.position]}
    if o.radius:
        out["radius"] = float(o.radius)
    if o.length:
        out["length"] = float(o.length)
    if o.size is not None:
        out["size"] = [float(x) for x in o.size]
    if o.shape in ("capsule", "cylinder", "box"):
        out["axis"] = [float(x) for x in o.axis]
    return out


def _scene_dict(scene: Any, robot_kind: str) -> dict[str, Any]:
    """A benchmark scene (:class:`qpctl.bench.scenes.BenchScene`) as a raw scenario dict."""
    g = scene.gains
    path = scene.path
    controller: dict[str, Any] = {"kind": "paper", "kp": g.kp, "kv": g.kv, "kn": g.kn, "v_ref": g.v_ref,
                                  "d_influence": g.d_influence, "d_safe": g.d_safe, "g_damping": g.g_damping,
                                  "pinv_eps": g.pinv_eps, "jdot_en": g.jdot_en}
    controller.update(scene.controller_cfg)
    return {
        "name": scene.name,
        "description": f"{scene.family} scene, seed {scene.seed}",
        "robot": {"kind": robot_kind},
        "path": {"start": [float(x) for x in path.points[0]],
                 "waypoints": [[float(x) for x in p] for p in path.points[1:]],
                 "durations": [float(d) for d in path.durations]},
        "obstacles": [_obstacle_dict(o) for o in scene.obstacles],
        "controller": controller,
        "sim": {"dt": float(scene.dt), "duration": float(scene.duration)},
    }


def scene_dict(kind: str, *, seed: int, obstacles: int = 10, duration: float | None = None,
               scenario: str = "") -> tuple[str, dict[str, Any], Path | None]:
    """(scene name, raw scenario dict, base folder for relative paths) of one scene of a family."""
    if kind == "canopy":
        from qpctl.bench.scenes import canopy_scene

        scene = canopy_scene(seed, obstacles=obstacles, **({} if duration is None else {"duration": duration}))
        return scene.name, _scene_dict(scene, "panda"), None
    if kind == "planar":
        from qpctl.bench.scenes import planar_scene

        scene = planar_scene(seed, **({} if duration is None else {"duration": duration}))
        return scene.name, _scene_dict(scene, "planar3"), None
    if kind == "scenario":
        from importlib import resources

        path = Path(scenario)
        if path.suffix == ".toml" or path.exists():
            if not path.is_file():
                raise ConfigError(f"scenario file not found: {path}", key="families.scenario")
            text, base = path.read_text(), path.resolve().parent
        else:
            res = resources.files("qpctl") / "scenarios" / f"{scenario}.toml"
            if not res.is_file():
                from qpctl.scenario import packaged_scenarios

                raise ConfigError(f"no scenario named {scenario!r}; packaged: {', '.join(packaged_scenarios())}",
                                  key="families.scenario")
            text, base = res.read_text(), None
        raw = tomllib.loads(text)
        if duration is not None:
            raw = copy.deepcopy(raw)
            raw.setdefault("sim", {})["duration"] = float(duration)
        return str(raw.get("name", path.stem)), raw, base
    raise ConfigError(f"unknown family kind {kind!r}; one of {', '.join(FAMILY_KINDS)}", key="families.kind")
