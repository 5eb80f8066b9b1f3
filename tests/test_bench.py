"""The benchmark harness (``qpctl bench``) on a tiny configuration, and its parts.

The four target scenes of issue #10 (Panda + 10 spheres, the same task with no obstacles, one
Panda canopy, the planar paper arm), 50 ticks each, every installed solver, a two-point scaling
curve: the harness must write ``results.json`` (machine, load, seeds, the floor and every ratio to
it, the stages, issue #10's targets), ``results.md`` and the plots, and ``performance_section`` the
README's section. Timings are measurements, never asserted: the tests check the structure and that
every derived number (ratios, met flags) is what the reported medians give.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from qpctl.bench import report
from qpctl.bench.harness import BenchConfig, run
from qpctl.bench.scenes import canopy_scene, free_scene, orchard_scene, spheres_scene
from qpctl.bench.timing import (
    BREAKDOWN,
    FLOOR,
    STAGES,
    PinocchioFloor,
    StateSequence,
    TickTimes,
    breakdown,
    time_on_states,
)
from qpctl.solvers import available_solvers

TINY = BenchConfig(quick=True, planar_scenes=0, canopy_scenes=1, max_ticks=50, scaling_counts=(10, 20),
                   progress=False)
TARGET_KEYS = {"spheres_qp_median", "spheres_qp_p99", "spheres_paper_median", "free_qp_median",
               "canopy_over_spheres", "paper_arm_qp_median", "scaling", "qp_over_floor", "paper_over_floor",
               "harvest_over_position"}


@pytest.fixture(scope="module")
def tiny(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict, dict, Path]:
    out = tmp_path_factory.mktemp("bench")
    res = run(TINY, out, command="pytest smoke")
    return res, json.loads((out / "results.json").read_text()), out


def test_results_json_machine_scenes_and_floor(tiny: tuple[dict, dict, Path]) -> None:
    _, data, _ = tiny
    m = data["machine"]
    assert m["cpu"] and m["cores"] >= 1 and m["python"]
    for pkg in ("numpy", "numba", "pin", "python-fcl", "qpsolvers", "proxsuite", "osqp", "daqp", "quadprog"):
        assert pkg in m["packages"]
    assert set(data["load_average"]) == {"start", "end"} and data["duration_s"] > 0
    assert data["config"]["canopy_seeds"] == TINY.canopy_seeds and data["config"]["covers"]
    labels = [FLOOR, "paper", "hsu"] + [f"qp-{s}" for s in available_solvers()]
    assert list(data["scene_groups"]) == ["spheres", "free", "canopy", "paper"]
    assert data["scenes"]["panda-spheres"]["obstacles"] == 10 and data["scenes"]["panda-free"]["obstacles"] == 0
    blocks = list(data["scene_groups"].values()) + list(data["same_ticks"].values())
    assert set(data["same_ticks"]) == {"panda", "planar3"}
    for block in blocks:
        ctrl = block["controllers"]
        assert list(ctrl) == labels
        floor = ctrl[FLOOR]["wall"]["median"]
        assert floor > 0
        for c in ctrl.values():
            assert math.isfinite(c["wall"]["median"]) and math.isfinite(c["cpu"]["p99"])
            # ÷ floor is the ratio of the medians the block reports
            assert c["ratio_to_floor"] == pytest.approx(c["wall"]["median"] / floor, rel=1e-12)
            assert c["ratio_to_paper"] == pytest.approx(c["wall"]["median"] / ctrl["paper"]["wall"]["median"],
                                                        rel=1e-12)
        assert ctrl[FLOOR]["ratio_to_floor"] == 1.0
    for group in data["scene_groups"].values():
        assert group["ticks"] == 50
    assert [r["controller"] for r in data["quality"]["runs"]] == labels[1:] * 4
    assert set(data["scaling"]["counts"]) == {"10", "20"}


def test_stages_are_the_compiled_ticks(tiny: tuple[dict, dict, Path]) -> None:
    """Every controller reports Pinocchio, the state kernel and the law (+ rows); only the QP a solve;
    the floor none; no separate distance stage any more."""
    _, data, _ = tiny
    for block in data["scene_groups"].values():
        for label, c in block["controllers"].items():
            assert set(c["stages_median"]) == set(STAGES)
            assert set(c["breakdown_median"]) == {key for key, _ in BREAKDOWN}
            bd = c["breakdown_median"]
            if label == FLOOR:
                assert all(v is None for v in bd.values())
                continue
            for key in ("pinocchio_us", "state_kernel_us", "law_rows_us", "other_us"):
                assert bd[key] is not None and bd[key] > 0, (label, key)
            assert (bd["solve_us"] is not None) == label.startswith("qp-")
            st = c["stages_median"]
            assert st["state_us"] > st["rigid_us"] > 0


def test_targets_rows_follow_from_the_numbers(tiny: tuple[dict, dict, Path]) -> None:
    res, data, _ = tiny
    rows = {r["key"]: r for r in data["targets"]}
    assert set(rows) == TARGET_KEYS and res["targets"] == data["targets"]
    for r in rows.values():
        assert r["limit"] == report.TARGETS[_limit_key(r["key"])]
        assert r["value"] is not None and r["met"] is (r["value"] <= r["limit"]), r
    groups = data["scene_groups"]
    qp = "qp-daqp"
    assert rows["spheres_qp_median"]["value"] == groups["spheres"]["controllers"][qp]["wall"]["median"]
    assert rows["spheres_qp_p99"]["value"] == groups["spheres"]["controllers"][qp]["wall"]["p99"]
    assert rows["spheres_paper_median"]["value"] == groups["spheres"]["controllers"]["paper"]["wall"]["median"]
    assert rows["free_qp_median"]["value"] == groups["free"]["controllers"][qp]["wall"]["median"]
    assert rows["paper_arm_qp_median"]["value"] == groups["paper"]["controllers"][qp]["wall"]["median"]
    assert rows["canopy_over_spheres"]["value"] == pytest.approx(
        groups["canopy"]["controllers"][qp]["wall"]["median"] / groups["spheres"]["controllers"][qp]["wall"]["median"])
    assert rows["qp_over_floor"]["value"] == groups["spheres"]["controllers"][qp]["ratio_to_floor"]
    assert rows["paper_over_floor"]["value"] == groups["spheres"]["controllers"]["paper"]["ratio_to_floor"]
    sc = data["scaling"]["counts"]
    assert rows["scaling"]["value"] == pytest.approx(
        sc["20"]["controllers"][qp]["wall"]["median"] / sc["10"]["controllers"][qp]["wall"]["median"])
    # the quoted TSID figure travels with its provenance (the script that measured it)
    assert data["tsid_reference"]["tick_us"] == report.TSID_US and "tsid_tick.py" in data["tsid_reference"]["credit"]
    hv = data["harvest"]  # panda_harvest cut to 50 ticks (51 states, t = 0 … 50 dt), timed on every other one
    assert hv["ticks"] == 26 and rows["harvest_over_position"]["value"] == pytest.approx(
        hv["approach_us"] / hv["position_us"])


def _limit_key(key: str) -> str:
    return {"spheres_qp_median": "spheres_qp_median_us", "spheres_qp_p99": "spheres_qp_p99_us",
            "spheres_paper_median": "spheres_paper_median_us", "free_qp_median": "free_qp_median_us",
            "paper_arm_qp_median": "paper_arm_qp_median_us", "scaling": "scaling_over_first"}.get(key, key)


def test_markdown_performance_section_and_plots(tiny: tuple[dict, dict, Path]) -> None:
    _, data, out = tiny
    md = (out / "results.md").read_text()
    for text in ("## Targets (issue #10)", "| Panda + 10 spheres | floor |", "| Panda, no obstacles | qp-daqp |",
                 "| Panda canopy | paper |", "| planar paper arm | hsu |", "÷ floor", "state kernel µs",
                 "law + rows µs", "## Scaling", "TSID"):
        assert text in md, text
    assert "distance µs" not in md and "distance_us" not in json.dumps(data)
    perf = report.performance_section(data, demo_wall_s=95.0)
    for text in ("pytest smoke", "load average", "| target (issue #10) |", "| scene | controller |",
                 "Pinocchio µs", "| 20 |", "tick_times.png", "stages.png", "scaling.png", "`make demo`: 95 s"):
        assert text in perf, text
    for png in ("tick_times.png", "stages.png", "scaling.png"):
        assert (out / png).stat().st_size > 0


def test_scenes_are_seeded_and_orchard_keeps_the_canopy() -> None:
    a, b = canopy_scene(3), canopy_scene(3)
    assert np.array_equal(a.target, b.target)
    assert [o.position.tolist() for o in a.obstacles] == [o.position.tolist() for o in b.obstacles]
    big = orchard_scene(a, 40)
    assert len(big.obstacles) == 40 and all(x is y for x, y in zip(big.obstacles, a.obstacles))


def test_spheres_scene_is_the_packaged_scenario_and_free_drops_its_obstacles() -> None:
    from qpctl.scenario import Scenario

    scen = Scenario.load("panda_spheres")
    s = spheres_scene()
    assert s.robot.name == "panda" and s.family == "spheres"
    assert [o.name for o in s.obstacles] == [o["name"] for o in scen.data["obstacles"]]
    assert len(s.obstacles) == 10 and all(o.shape == "sphere" for o in s.obstacles)
    f = free_scene(s)
    assert f.obstacles == () and f.family == "free" and f.path is s.path and np.array_equal(f.q0, s.q0)


def test_breakdown_is_the_reported_stages() -> None:
    nan = np.nan
    t = TickTimes(np.array([30.0, 15.0, 4.0]), np.array([31.0, 16.0, 5.0]),
                  {"rigid_us": np.array([4.0, 4.0, nan]), "state_us": np.array([9.0, 9.0, nan]),
                   "build_us": np.array([6.0, 4.0, nan]), "solve_us": np.array([12.0, nan, nan])})
    bd = breakdown(t)
    assert bd["pinocchio_us"][:2].tolist() == [4.0, 4.0] and bd["state_kernel_us"][:2].tolist() == [5.0, 5.0]
    assert bd["law_rows_us"][:2].tolist() == [6.0, 4.0]
    assert bd["other_us"][:2].tolist() == [3.0, 2.0]  # 30 − 9 − 6 − 12, 15 − 9 − 4 (no solve)
    assert all(np.isnan(bd[k][2]) for k in bd)  # a tick that reported no stages (the floor)


def test_same_ticks_run_in_rotating_blocks_in_order() -> None:
    """Every controller (and the floor) warms up, then steps through every state once, in order, in
    blocks of consecutive ticks; each block after the first opens with an untimed replay of the
    controller's previous state; the controller that opens a block rotates from block to block."""
    scene = canopy_scene(100)
    calls: list[tuple[str, float]] = []
    ctrls = {}
    for label in ("floor", "paper", "qp"):
        ctrl = PinocchioFloor(scene.robot) if label == "floor" else scene.controller(label, "daqp" if label == "qp"
                                                                                     else None)
        inner = ctrl.step

        def step(q, v, t, inner=inner, label=label):
            calls.append((label, t))
            return inner(q, v, t)

        ctrl.step = step  # type: ignore[method-assign]
        ctrls[label] = ctrl
    T, block = 23, 5
    ts = np.arange(T) * scene.dt
    states = StateSequence(ts, np.tile(scene.q0, (T, 1)), np.zeros((T, scene.robot.nv)))
    res = time_on_states(ctrls, states, block=block)
    warm = [lb for lb, _ in calls[:4]]
    assert warm == ["paper", "paper", "qp", "qp"]  # warmup(): two ticks each (the floor has none)
    timed = calls[4:]
    for label in ctrls:
        expected: list[float] = []
        for k0 in range(0, T, block):
            expected += ([ts[k0 - 1]] if k0 else []) + ts[k0 : k0 + block].tolist()
        assert [t for lb, t in timed if lb == label] == expected
        assert np.all(res[label].wall > 0) and res[label].wall.size == T
        assert np.isnan(res[label].cold[0]) and np.all(res[label].cold[1:] > 0)
    openers = [timed[i][0] for i in range(len(timed)) if i == 0 or timed[i][0] != timed[i - 1][0]]
    assert openers[:6] == ["floor", "paper", "qp", "paper", "qp", "floor"]
    assert np.all(np.isnan(res["floor"].stages["state_us"])) and np.all(res["qp"].stages["solve_us"] > 0)


def test_profile_reports_every_part_of_a_tick() -> None:
    """``python -m benchmarks.profile``: every part timed, a whole QP tick costing more than its state
    stage alone, and cProfile's report naming the controller's step."""
    from benchmarks.profile import parts, profile

    solver = "daqp" if "daqp" in available_solvers() else "proxqp"
    res = parts(solver, 100, duration=0.05)
    assert len(res) == 9 and all(np.isfinite(v) and v > 0 for v in res.values())
    assert res["QP: whole tick"] > res["state kernel: rigid terms, pairs, distances, barrier drift (both)"]
    assert res["QP: whole tick"] > res["Pinocchio crba + nonLinearEffects (both)"]
    assert "qpctl/controllers/qp.py" in profile(solver, 100, top=10, duration=0.05)


def test_a_speed_change_in_the_floor_is_flagged(tiny: tuple[dict, dict, Path]) -> None:
    """The floor's 25-tick block medians: one speed gives a spread of 1 and no flag; a floor that steps
    from 4 µs to 5.5 µs a third of the way through (block medians 4 and 5.5: 10th and 90th percentiles
    by numpy on the same blocks) is flagged, and the report's scene line says so for that group only."""
    from qpctl.bench.harness import SPEED_CHANGE, floor_spread

    rng = np.random.default_rng(3)
    steady = 4.0 + 0.01 * rng.standard_normal(3000)
    fb = floor_spread(steady)
    assert not fb["speed_change"] and fb["ratio"] < 1.02
    stepped = np.concatenate([np.full(1000, 4.0), np.full(2000, 5.5)]) + 0.01 * rng.standard_normal(3000)
    fb = floor_spread(stepped)
    meds = np.median(stepped.reshape(-1, 25), axis=1)
    lo, hi = np.percentile(meds, [10, 90])
    assert fb["speed_change"] and math.isclose(fb["p10_us"], lo) and math.isclose(fb["p90_us"], hi)
    assert hi / lo > SPEED_CHANGE and 3.9 < lo < 4.1 and 5.4 < hi < 5.6
    _, data, _ = tiny
    assert "floor_blocks" in data["scene_groups"]["spheres"]
    for g in data["scene_groups"].values():
        g["floor_blocks"] = {"p10_us": 4.0, "p90_us": 4.0, "ratio": 1.0, "speed_change": False}
    assert "changed speed" not in report.scene_groups_line(data)
    data["scene_groups"]["spheres"]["floor_blocks"] = floor_spread(stepped)
    line = report.scene_groups_line(data)
    title = data["scene_groups"]["spheres"]["title"]
    assert f"changed speed during {title} (the floor's 25-tick blocks 4.0–5.5 µs" in line
