"""The README is the front door: its example scenario runs, and it documents every scenario key."""

from __future__ import annotations

import re
import sys
from pathlib import Path

import numpy as np

from qpctl.scenario import OBSTACLE_SCHEMA, SCHEMA, Scenario

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

README = (Path(__file__).resolve().parents[1] / "README.md").read_text()


def toml_blocks() -> list[str]:
    return re.findall(r"```toml\n(.*?)```", README, flags=re.DOTALL)


def test_complete_qp_example_scenario_builds_and_steps():
    block = next(b for b in toml_blocks() if 'name = "paper-qp"' in b)
    scen = Scenario.from_dict(tomllib.loads(block), source="README")
    ctrl = scen.build_controller()
    assert ctrl.kind == "qp" and ctrl.solver == "proxqp"
    out = ctrl.step(scen.q0(ctrl.robot), np.zeros(3), 0.0)
    assert out.info["status"] == "solved" and np.all(np.abs(out.tau) <= 400.0 + 1e-9)


def test_every_scenario_key_is_documented():
    text = README
    missing = []
    for section, spec in SCHEMA.items():
        if isinstance(spec, dict) and section != "obstacles":
            for key in spec:
                if f"{section}.{key}" not in text and f"`.{key}`" not in text:
                    missing.append(f"{section}.{key}")
        elif section == "obstacles":
            for key in OBSTACLE_SCHEMA:
                if f"obstacles[].{key}" not in text and f"`.{key}`" not in text:
                    missing.append(f"obstacles[].{key}")
        elif f"`{section}`" not in text:
            missing.append(section)
    assert not missing, missing


def test_every_sweep_spec_key_is_documented():
    from qpctl.sweep.spec import FAMILY_KEYS, TOP_KEYS

    section = README.split("## Sweeps", 1)[1]
    missing = [k for k in TOP_KEYS if f"`{k}`" not in section and f"`[{k}]`" not in section
               and f"`[[{k}]]`" not in section]
    missing += [f"families[].{k}" for k in FAMILY_KEYS if f"`families[].{k}`" not in section]
    assert not missing, missing
