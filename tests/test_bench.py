"""Smoke test of the benchmark harness (``qpctl bench``) on a tiny configuration.

One Panda canopy scene, 50 ticks, every installed solver, a two-point scaling curve: the harness
must write ``results.json`` (with the machine block and the seeds), ``results.md`` (the tables) and
the plots. Timings are measurements, never asserted.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from benchmarks.harness import BenchConfig, run
from benchmarks.scenes import canopy_scene, orchard_scene
from qpctl.solvers import available_solvers

TINY = BenchConfig(quick=True, paper=False, planar_scenes=0, canopy_scenes=1, max_ticks=50,
                   scaling_counts=(10, 20), progress=False)


def test_quick_harness_writes_results_and_tables(tmp_path: Path) -> None:
    res = run(TINY, tmp_path, command="pytest smoke")
    data = json.loads((tmp_path / "results.json").read_text())
    m = data["machine"]
    assert m["cpu"] and m["cores"] >= 1 and m["python"]
    for pkg in ("numpy", "pin", "python-fcl", "qpsolvers", "proxsuite", "osqp", "daqp", "quadprog"):
        assert pkg in m["packages"]
    assert data["config"]["canopy_seeds"] == TINY.canopy_seeds
    labels = ["paper", "hsu"] + [f"qp-{s}" for s in available_solvers()]
    panda = data["same_ticks"]["panda"]
    assert list(panda["controllers"]) == labels
    for label in labels:
        block = panda["controllers"][label]
        assert np.isfinite(block["wall"]["median"]) and np.isfinite(block["cpu"]["p99"])
    assert panda["ticks"] == 50
    assert [r["controller"] for r in data["quality"]["runs"]] == labels
    assert set(data["scaling"]["counts"]) == {"10", "20"}
    assert res["targets"]  # evaluated, met or not
    md = (tmp_path / "results.md").read_text()
    assert "## Same ticks" in md and "| panda | qp-proxqp |" in md and "## Scaling" in md
    for png in ("tick_times.png", "stages.png", "scaling.png"):
        assert (tmp_path / png).stat().st_size > 0


def test_scenes_are_seeded_and_orchard_keeps_the_canopy() -> None:
    a, b = canopy_scene(3), canopy_scene(3)
    assert np.array_equal(a.target, b.target)
    assert [o.position.tolist() for o in a.obstacles] == [o.position.tolist() for o in b.obstacles]
    big = orchard_scene(a, 40)
    assert len(big.obstacles) == 40 and all(x is y for x, y in zip(big.obstacles, a.obstacles))


def test_same_ticks_run_in_rotating_blocks_in_order() -> None:
    """Every controller steps through every state once, in order, in blocks of consecutive ticks; the
    controller that opens a block rotates from block to block."""
    from benchmarks.timing import StateSequence, time_on_states

    scene = canopy_scene(100)
    calls: list[tuple[str, float]] = []
    ctrls = {}
    for label in ("paper", "hsu", "qp"):
        ctrl = scene.controller(label, "daqp" if label == "qp" else None)
        inner = ctrl.step

        def step(q, v, t, inner=inner, label=label):
            calls.append((label, t))
            return inner(q, v, t)

        ctrl.step = step  # type: ignore[method-assign]
        ctrls[label] = ctrl
    T = 23
    ts = np.arange(T) * scene.dt
    states = StateSequence(ts, np.tile(scene.q0, (T, 1)), np.zeros((T, scene.robot.nv)))
    res = time_on_states(ctrls, states, block=5)
    for label in ctrls:
        assert [t for lb, t in calls if lb == label] == ts.tolist()
        assert np.all(res[label].wall > 0)
    openers = [calls[i][0] for i in range(len(calls)) if i == 0 or calls[i][0] != calls[i - 1][0]]
    assert openers[:6] == ["paper", "hsu", "qp", "hsu", "qp", "paper"]


def test_profile_reports_every_part_of_a_tick() -> None:
    """``python -m benchmarks.profile``: every part timed, a whole QP tick costing more than its state
    stage alone, and cProfile's report naming the controller's step."""
    from benchmarks.profile import parts, profile

    solver = "daqp" if "daqp" in available_solvers() else "proxqp"
    res = parts(solver, 100, duration=0.05)
    assert len(res) == 9 and all(np.isfinite(v) and v > 0 for v in res.values())
    assert res["QP: whole tick"] > res["state kernel: rigid terms, pairs, distances, barrier drift (both)"]
    assert res["QP: whole tick"] > res["Pinocchio computeAllTerms (both)"]
    assert "qpctl/controllers/qp.py" in profile(solver, 100, top=10, duration=0.05)
