"""Every exported name resolves; the controller interface is the same for every law."""

from __future__ import annotations

import importlib

import numpy as np
import pytest

PACKAGES = ["qpctl", "baselines", "qpctl.robot", "qpctl.geometry", "qpctl.simulation", "qpctl.controllers",
            "qpctl.adapters", "qpctl.solvers", "qpctl.tasks", "qpctl.constraints", "qpctl.sweep",
            "qpctl.scenes"]


@pytest.mark.parametrize("package", PACKAGES)
def test_all_names_resolve(package):
    mod = importlib.import_module(package)
    names = mod.__all__
    assert len(names) == len(set(names)), "duplicate names in __all__"
    for name in names:
        assert getattr(mod, name, None) is not None, f"{package}.{name} does not resolve"


def test_star_import_works():
    ns: dict = {}
    exec("from qpctl import *", ns)  # noqa: S102
    exec("from baselines import *", ns)  # noqa: S102
    import baselines
    import qpctl

    for name in qpctl.__all__ + baselines.__all__:
        assert name in ns


def test_errors_share_one_base():
    import qpctl

    for name in ("ConfigError", "InvalidStateError", "UnknownFrameError", "UnknownSolverError", "SolverError",
                 "InfeasibleError", "SimulationError"):
        assert issubclass(getattr(qpctl, name), qpctl.QpctlError)


def test_baselines_share_the_controller_interface(planar):
    import baselines
    import qpctl

    path = qpctl.WaypointPath([[-1.0, -2.0], [-0.5, -1.5]], duration=1.0)
    for name in baselines.__all__:
        cls = getattr(baselines, name)
        assert issubclass(cls, qpctl.Controller)
        ctrl = cls(planar, path)
        tau = ctrl.torque(planar.q_home, np.zeros(3), 0.0)
        assert tau.shape == (3,) and np.all(np.isfinite(tau))
        with pytest.raises(qpctl.InvalidStateError):
            ctrl.torque(np.full(3, np.nan), np.zeros(3), 0.0)


def test_the_front_door_holds_what_a_user_needs_and_no_internals():
    """``from qpctl import …`` gives the controllers and their configs, tasks, constraints, Scenario,
    simulate and the solver listing (issue 15); the tick's internals stay in their modules."""
    import qpctl

    front = set(qpctl.__all__)
    assert {"QPController", "QPConfig", "PaperController", "HsuController", "LawGains", "EndEffectorTask",
            "PostureTask", "ObstacleBarrier", "TorqueLimit", "Scenario", "simulate", "available_solvers"} <= front
    assert not front & {"Dynamics", "TickState", "PairSet", "DistanceEngine", "LawTerms", "law_terms",
                        "PseudoInverse", "weighted_pinv", "compute_metrics", "Workspace"}
    assert len(front) <= 45
    import baselines

    assert baselines.PaperController is qpctl.PaperController and baselines.HsuController is qpctl.HsuController


def test_the_library_does_not_import_its_applications():
    """qpctl/ imports none of its applications — the baselines package (the laws live in
    qpctl.controllers.closed_form), the benchmarks (``qpctl bench`` and the scene families are
    qpctl.bench) and the paper reproduction: read from the source, every import statement."""
    import ast
    from pathlib import Path

    import qpctl

    root = Path(qpctl.__file__).parent
    offenders = []
    for path in root.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else (
                [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
            offenders += [f"{path.relative_to(root)}: {n}" for n in names if n.split(".")[0] in ("baselines", "benchmarks", "reproduction")]
    assert not offenders, offenders
