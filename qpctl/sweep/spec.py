"""Sweep specs: TOML files (or packaged names) that expand into a list of runs.

A spec names scene families, controllers, QP solvers, grids and random ranges of scenario keys
(dotted, as ``--set`` takes them), repetitions and a seed. :meth:`SweepSpec.runs` expands it into
:class:`RunParams`, one per run: every run is a pure function of its parameters (seed included), and
its id is a hash of them (:attr:`RunParams.run_id`), so a run can be re-run alone and a sweep knows
which of its runs are already done. The README ("Sweeps") documents every key.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import math
import sys
from dataclasses import asdict, dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from qpctl.controllers.factory import controller_kinds
from qpctl.errors import ConfigError
from qpctl.scenario import apply_overrides
from qpctl.sweep.families import FAMILY_KINDS

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

CLOSED_FORM = "closed-form"  # the solver column of the closed-form laws

TOP_KEYS = ("name", "description", "seed", "repetitions", "controllers", "solvers", "set", "grid", "random",
            "families")
FAMILY_KEYS = ("kind", "name", "count", "seed", "obstacles", "duration", "scenario")


def packaged_specs() -> list[str]:
    """Names of the sweep specs shipped with qpctl."""
    folder = resources.files("qpctl") / "sweep" / "specs"
    return sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".toml"))


def toml_value(v: Any) -> str:
    """``v`` as TOML text (the right-hand side of a ``--set`` override)."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    raise TypeError(f"not a TOML value: {v!r}")


def _flatten(table: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """``{"controller": {"kp": [1, 2]}}`` and ``{"controller.kp": [1, 2]}`` alike → ``{"controller.kp": [1, 2]}``."""
    out: dict[str, Any] = {}
    for k, v in table.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict) and not key.endswith("solver_settings"):
            out.update(_flatten(v, key + "."))
        else:
            out[key] = v
    return out


@dataclass(frozen=True)
class Family:
    """A scene family: ``count`` scenes of ``kind`` (seeds ``seed`` … ``seed + count − 1`` for the random
    kinds), each ``duration`` seconds long (None: the family's own)."""

    kind: str
    name: str
    count: int = 1
    seed: int = 0
    obstacles: int = 10
    duration: float | None = None
    scenario: str = ""


@dataclass(frozen=True)
class RunParams:
    """Everything one run depends on. ``overrides`` are dotted scenario keys (sorted) and their values:
    the spec's ``set``, the run's grid point and its random draws (``sim.seed`` = ``seed``)."""

    family: str
    kind: str
    scene_seed: int | None
    obstacles: int
    duration: float | None
    scenario: str
    controller: str
    solver: str
    repetition: int
    seed: int
    overrides: tuple[tuple[str, Any], ...] = ()

    def to_json(self) -> str:
        return json.dumps(asdict(self), sort_keys=True, separators=(",", ":"))

    @classmethod
    def from_json(cls, text: str) -> RunParams:
        d = json.loads(text)
        d["overrides"] = tuple((k, tuple(v) if isinstance(v, list) else v) for k, v in d["overrides"])
        return cls(**d)

    @property
    def run_id(self) -> str:
        """A stable id: the first 16 hex digits of the SHA-256 of the parameters' canonical JSON."""
        return hashlib.sha256(self.to_json().encode()).hexdigest()[:16]

    def override_strings(self) -> list[str]:
        return [f"{k}={toml_value(v)}" for k, v in self.overrides]


def _seed_of(*parts: Any) -> int:
    text = json.dumps(parts, sort_keys=True, separators=(",", ":"))
    return int.from_bytes(hashlib.sha256(text.encode()).digest()[:4], "little") & 0x7FFFFFFF


@dataclass(frozen=True)
class SweepSpec:
    """A validated sweep spec (see the module docstring and the README)."""

    name: str
    source: str
    text: str  # the spec as written (a sweep's folder keeps a copy: a different spec is refused there)
    description: str = ""
    seed: int = 0
    repetitions: int = 1
    controllers: tuple[str, ...] = ("paper", "hsu", "qp")
    solvers: tuple[str, ...] = ("daqp",)
    fixed: tuple[tuple[str, Any], ...] = ()
    grid: tuple[tuple[str, tuple[Any, ...]], ...] = ()
    random: tuple[tuple[str, tuple[float, float]], ...] = ()
    families: tuple[Family, ...] = field(default_factory=tuple)

    @property
    def swept_keys(self) -> list[str]:
        """The keys that vary from run to run (grid and random), in spec order."""
        return [k for k, _ in self.grid] + [k for k, _ in self.random]

    @classmethod
    def load(cls, spec: str | Path) -> SweepSpec:
        """Load a spec file, or a packaged spec by name (``canopy_small``)."""
        path = Path(spec)
        if path.suffix == ".toml" or path.exists():
            if not path.is_file():
                raise ConfigError(f"sweep spec not found: {path}")
            source, text = str(path), path.read_text()
        else:
            res = resources.files("qpctl") / "sweep" / "specs" / f"{spec}.toml"
            if not res.is_file():
                raise ConfigError(f"no sweep spec named {str(spec)!r}; packaged: {', '.join(packaged_specs())}"
                                  " (or give a path to a .toml file)")
            source, text = f"{spec} (packaged)", res.read_text()
        try:
            raw = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(f"not valid TOML: {exc}", source=source) from None
        return cls.from_dict(raw, source=source, text=text, default_name=path.stem)

    @classmethod
    def from_dict(cls, raw: dict[str, Any], *, source: str = "<dict>", text: str = "",
                  default_name: str = "sweep") -> SweepSpec:
        def err(key: str, msg: str) -> ConfigError:
            return ConfigError(msg, source=source, key=key)

        for k in raw:
            if k not in TOP_KEYS:
                raise err(k, f"unknown key; one of {', '.join(TOP_KEYS)}")

        def get(key: str, typ: type | tuple[type, ...], default: Any) -> Any:
            v = raw.get(key, default)
            if isinstance(v, bool) and typ is not bool or not isinstance(v, typ):
                raise err(key, f"must be {getattr(typ, '__name__', typ)}, got {v!r}")
            return v

        name = get("name", str, default_name)
        seed = get("seed", int, 0)
        reps = get("repetitions", int, 1)
        if reps < 1:
            raise err("repetitions", f"must be >= 1, got {reps}")
        controllers = get("controllers", list, ["paper", "hsu", "qp"])
        for c in controllers:
            if c not in controller_kinds():  # the registered kinds (qpctl.controllers.factory)
                raise err("controllers", f"unknown controller {c!r}; one of {', '.join(controller_kinds())}")
        if not controllers:
            raise err("controllers", "needs at least one controller")
        solvers = get("solvers", list, ["daqp"])
        if "qp" in controllers:
            from qpctl.solvers import available_solvers

            avail = available_solvers()
            for s in solvers:
                if not isinstance(s, str) or s not in avail:
                    raise err("solvers", f"unknown or unavailable solver {s!r}; available: {', '.join(avail)}")
            if not solvers:
                raise err("solvers", "needs at least one solver when controllers has qp")
        fixed = _flatten(get("set", dict, {}))
        grid = _flatten(get("grid", dict, {}))
        rnd = _flatten(get("random", dict, {}))
        for key, values in grid.items():
            if not isinstance(values, list) or not values:
                raise err(f"grid.{key}", f"must be a non-empty list of values, got {values!r}")
        for key, rng in rnd.items():
            if (not isinstance(rng, list) or len(rng) != 2 or any(isinstance(x, bool) or not isinstance(x, (int, float))
                                                                  for x in rng) or not rng[0] <= rng[1]):
                raise err(f"random.{key}", f"must be [low, high] with low <= high, got {rng!r}")
        seen: dict[str, str] = {}
        for table, keys in (("set", fixed), ("grid", grid), ("random", rnd)):
            for key in keys:
                if key in seen:
                    raise err(f"{table}.{key}", f"also given in [{seen[key]}]")
                seen[key] = table
                try:  # the key exists in the scenario schema (and may be set): as --set would check it
                    value = keys[key][0] if table != "set" else keys[key]
                    apply_overrides({}, [f"{key}={toml_value(value)}"])
                except ConfigError as exc:
                    raise err(f"{table}.{key}", str(exc).rsplit(": ", 1)[-1]) from None
                except TypeError as exc:
                    raise err(f"{table}.{key}", str(exc)) from None
                if key in ("controller.kind", "controller.solver"):
                    raise err(f"{table}.{key}", "use the spec's controllers and solvers lists")
        fams = get("families", list, None)
        if not fams:
            raise err("families", "needs at least one [[families]] table")
        families = []
        names: set[str] = set()
        for i, f in enumerate(fams):
            key = f"families[{i}]"
            if not isinstance(f, dict):
                raise err(key, "must be a table")
            for k in f:
                if k not in FAMILY_KEYS:
                    raise err(f"{key}.{k}", f"unknown key; one of {', '.join(FAMILY_KEYS)}")
            kind = f.get("kind")
            if kind not in FAMILY_KINDS:
                raise err(f"{key}.kind", f"must be one of {', '.join(FAMILY_KINDS)}, got {kind!r}")
            scenario = f.get("scenario", "")
            if kind == "scenario" and (not isinstance(scenario, str) or not scenario):
                raise err(f"{key}.scenario", "a scenario family needs the name or path of a scenario")
            if kind != "scenario" and scenario:
                raise err(f"{key}.scenario", f"only for kind = \"scenario\" (this family is {kind})")
            count = f.get("count", 1)
            if isinstance(count, bool) or not isinstance(count, int) or count < 1:
                raise err(f"{key}.count", f"must be an integer >= 1, got {count!r}")
            fseed = f.get("seed", 0)
            if isinstance(fseed, bool) or not isinstance(fseed, int):
                raise err(f"{key}.seed", f"must be an integer, got {fseed!r}")
            obstacles = f.get("obstacles", 10)
            if isinstance(obstacles, bool) or not isinstance(obstacles, int) or obstacles < 0:
                raise err(f"{key}.obstacles", f"must be an integer >= 0, got {obstacles!r}")
            if "obstacles" in f and kind != "canopy":
                raise err(f"{key}.obstacles", "only for kind = \"canopy\"")
            duration = f.get("duration")
            if duration is not None and (isinstance(duration, bool) or not isinstance(duration, (int, float))
                                         or not (math.isfinite(duration) and duration > 0)):
                raise err(f"{key}.duration", f"must be a positive number of seconds, got {duration!r}")
            if duration is not None and kind != "scenario" and duration <= 0.5:
                raise err(f"{key}.duration", f"must exceed 0.5 s (the reach takes duration − 0.5 s), got {duration!r}")
            fname = f.get("name", scenario if kind == "scenario" else kind)
            if not isinstance(fname, str) or fname in names:
                raise err(f"{key}.name", f"must be a unique text, got {fname!r}")
            names.add(fname)
            families.append(Family(kind, fname, count, fseed, obstacles,
                                   None if duration is None else float(duration), scenario))
        description = get("description", str, "")
        text = text or json.dumps(raw, sort_keys=True, indent=1, default=str)  # a spec built in code
        spec = cls(name, source, text, description, seed, reps, tuple(controllers), tuple(solvers),
                   tuple(sorted(fixed.items())), tuple((k, tuple(v)) for k, v in grid.items()),
                   tuple((k, (float(v[0]), float(v[1]))) for k, v in rnd.items()), tuple(families))
        return spec

    def runs(self) -> list[RunParams]:
        """Every run of the sweep, in a stable order: family, scene, grid point, repetition, controller,
        solver. A run's seed depends on its scene, grid point and repetition, not on its controller or
        solver: every controller meets the same random draws."""
        out: list[RunParams] = []
        grid_keys = [k for k, _ in self.grid]
        points = list(itertools.product(*[v for _, v in self.grid])) if self.grid else [()]
        laws = [(c, s) for c in self.controllers for s in (self.solvers if c == "qp" else (CLOSED_FORM,))]
        for fam in self.families:
            for i in range(fam.count):
                scene_seed = fam.seed + i if fam.kind != "scenario" else None
                for point in points:
                    for rep in range(self.repetitions):
                        seed = _seed_of(self.seed, fam.name, scene_seed, list(zip(grid_keys, point)), rep)
                        rng = np.random.default_rng(seed)
                        draws = [(k, float(lo + (hi - lo) * rng.random())) for k, (lo, hi) in self.random]
                        overrides = dict(self.fixed) | dict(zip(grid_keys, point)) | dict(draws)
                        overrides["sim.seed"] = seed
                        ov = tuple(sorted((k, tuple(v) if isinstance(v, list) else v) for k, v in overrides.items()))
                        for controller, solver in laws:
                            out.append(RunParams(fam.name, fam.kind, scene_seed, fam.obstacles, fam.duration,
                                                 fam.scenario, controller, solver, rep, seed, ov))
        return out
