"""The README is the front door and docs/ holds the rest: the quick start and the example scenarios run,
docs/scenarios.md documents every scenario key, docs/sweeps.md every sweep spec key, and every relative
link in README.md and docs/*.md resolves (file and heading anchor)."""

from __future__ import annotations

import re
import sys
from pathlib import Path

import numpy as np

from qpctl.scenario import ARRAYS, SCHEMA, Scenario

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()
DOC_FILES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
ALL_DOCS = "\n".join(p.read_text() for p in DOC_FILES)
SCENARIO_REFERENCE = (ROOT / "docs" / "scenarios.md").read_text()
SWEEPS = (ROOT / "docs" / "sweeps.md").read_text()


def toml_blocks() -> list[str]:
    return re.findall(r"```toml\n(.*?)```", ALL_DOCS, flags=re.DOTALL)


def test_quick_start_runs():
    """The README's Python quick start, as printed, with short runs."""
    block = re.search(r"## Quick start\n+```python\n(.*?)```", README, flags=re.DOTALL)
    assert block is not None
    code = block.group(1)
    assert len(code.splitlines()) <= 20 and code.count("duration=5.0") == 2
    exec(compile(code.replace("duration=5.0", "duration=0.05"), "README quick start", "exec"), {})  # noqa: S102


def _anchor(heading: str) -> str:
    """GitHub's rule: lowercase, punctuation other than '-' and '_' dropped, spaces to '-'."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def _anchors(path: Path) -> set[str]:
    text = re.sub(r"```.*?```", "", path.read_text(), flags=re.DOTALL)
    return {_anchor(h) for h in re.findall(r"^#{1,6} (.+)$", text, flags=re.MULTILINE)}


def test_every_relative_link_resolves():
    bad = []
    for doc in DOC_FILES:
        text = re.sub(r"```.*?```", "", doc.read_text(), flags=re.DOTALL)
        for target in re.findall(r"\]\(([^)\s]+)\)", text):
            if re.match(r"[a-z]+:", target):
                continue
            file, _, frag = target.partition("#")
            dest = (doc.parent / file).resolve() if file else doc
            if not dest.exists():
                bad.append(f"{doc.name}: {target} (no file)")
            elif frag and (dest.suffix != ".md" or frag not in _anchors(dest)):
                bad.append(f"{doc.name}: {target} (no heading)")
    assert not bad, bad


def test_complete_qp_example_scenario_builds_and_steps():
    block = next(b for b in toml_blocks() if 'name = "paper-qp"' in b)
    scen = Scenario.from_dict(tomllib.loads(block), source="README")
    ctrl = scen.build_controller()
    assert ctrl.kind == "qp" and ctrl.solver == "proxqp"
    out = ctrl.step(scen.q0(ctrl.robot), np.zeros(3), 0.0)
    assert out.info["status"] == "solved" and np.all(np.abs(out.tau) <= 400.0 + 1e-9)


def test_every_scenario_key_is_documented():
    text = SCENARIO_REFERENCE
    missing = []
    for section, spec in SCHEMA.items():
        if isinstance(spec, dict) and section not in ARRAYS:
            for key in spec:
                if f"{section}.{key}" not in text and f"`.{key}`" not in text:
                    missing.append(f"{section}.{key}")
        elif section in ARRAYS:  # [[obstacles]], [[tasks]]
            for key in ARRAYS[section]:
                if f"{section}[].{key}" not in text and f"`.{key}`" not in text:
                    missing.append(f"{section}[].{key}")
        elif f"`{section}`" not in text:
            missing.append(section)
    assert not missing, missing


def test_every_sweep_spec_key_is_documented():
    from qpctl.sweep.spec import FAMILY_KEYS, TOP_KEYS

    section = SWEEPS.split("## Sweeps", 1)[1]
    missing = [k for k in TOP_KEYS if f"`{k}`" not in section and f"`[{k}]`" not in section
               and f"`[[{k}]]`" not in section]
    missing += [f"families[].{k}" for k in FAMILY_KEYS if f"`families[].{k}`" not in section]
    assert not missing, missing
