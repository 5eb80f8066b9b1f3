"""Every script in examples/ runs as a user would run it (a fresh interpreter), shortened by its
duration variable ``QPCTL_EXAMPLE_DURATION`` [s] so each takes a few seconds."""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import pytest

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"

# script, simulated seconds, what its output must contain, whether it needs the QP controller
CASES = [
    ("drive_mujoco_loop.py", 0.2, "tracking error", False),
    ("drive_pybullet_loop.py", 0.2, "tracking error", False),
    ("drive_my_mujoco_model.py", 0.3, "ctrl clamped on 0 ticks", False),
    ("drake_diagram.py", 0.2, "min clearance", True),
    ("swap_solver.py", 0.05, "swapped a live controller to osqp", True),
    ("posture_task.py", 0.1, "with PostureTask", True),
    ("moving_obstacle.py", 0.1, "min clearance", True),
    ("realsense_stream.py", 0.3, "maps built, min clearance", True),
]


def test_every_example_is_tested():
    assert sorted(p.name for p in EXAMPLES.glob("*.py")) == sorted(c[0] for c in CASES)


@pytest.mark.parametrize(("script", "duration", "expected", "needs_qp"), CASES, ids=[c[0] for c in CASES])
def test_example_runs(script, duration, expected, needs_qp):
    if script in ("drive_mujoco_loop.py", "drive_my_mujoco_model.py"):
        pytest.importorskip("mujoco")
    if script == "drive_pybullet_loop.py":
        pytest.importorskip("pybullet")
    if script == "drake_diagram.py":
        pytest.importorskip("pydrake")
    if needs_qp and importlib.util.find_spec("qpctl.controllers.qp") is None:
        pytest.skip("needs the QP controller")
    env = dict(os.environ, QPCTL_EXAMPLE_DURATION=str(duration), MPLBACKEND="Agg")
    proc = subprocess.run([sys.executable, str(EXAMPLES / script)], check=False, env=env, capture_output=True,
                          text=True, timeout=120, cwd=EXAMPLES.parent)
    assert proc.returncode == 0, proc.stderr
    assert expected in proc.stdout, proc.stdout
