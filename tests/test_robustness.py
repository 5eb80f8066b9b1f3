"""The robustness study (``make robust``, benchmarks/robustness.py): one real run through its harness,
its fault levels, and its report's arithmetic on records whose answers are known."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

from benchmarks import robustness as rb
from qpctl import Faults, Simulator
from qpctl.controllers.factory import make_controller
from qpctl.tick import WorldClearance


def test_a_run_records_the_true_clearance_tracking_and_gravity():
    rec = rb.run_one(rb.Run("planar-1", "qp"))
    scene = rb.get_scene("planar-1")
    # the same run by hand: the same controller settings, the built-in simulator, no faults
    ctrl = make_controller(dict(scene.controller_cfg, kind="qp", solver="daqp"), scene.robot, scene.path,
                           list(scene.obstacles), scene.gains)
    traj = Simulator(ctrl, dt=scene.dt, duration=scene.duration).run(scene.q0)
    world = WorldClearance(scene.robot, list(scene.obstacles))
    assert rec["min_clearance"] == pytest.approx(min(world(q, t) for q, t in zip(traj.q, traj.t, strict=True)),
                                                 abs=1e-12)
    assert rec["max_tracking_error"] == pytest.approx(np.max(np.linalg.norm(traj.x_ref - traj.x, axis=1)), abs=1e-12)
    assert rec["torque_limit_ticks"] == 0  # the planar arm has no torque limits
    data = scene.robot.model.createData()
    gravity = np.max([np.abs(pin.computeGeneralizedGravity(scene.robot.model, data, q)) for q in traj.q[::5]], axis=0)
    np.testing.assert_allclose(rec["peak_gravity"], gravity, rtol=1e-12)
    assert rb.keeps(rec)


def test_fault_levels_and_seeds():
    peaks = {"planar-1": {"peak_torque": [300.0, 150.0, 20.0], "peak_gravity": [250.0, 160.0, 10.0]}}
    sat = dict(rb.fault_fields(next(k for k in rb.KINDS if k.name == "torque_saturation"), 1, "planar-1", 4, peaks))
    # G + f (peak − G), no headroom where gravity already exceeds the peak
    assert sat["torque_saturation"] == pytest.approx((275.0, 160.0, 15.0)) and sat["seed"] == rb.FAULT_SEED + 4
    moderate = dict(rb.fault_fields(None, 0, "planar-1", 0, peaks))
    assert Faults(**moderate).kinds() == ["q_noise", "v_noise", "delay_ticks", "mass_error", "payload_mass",
                                          "obstacle_noise"]
    assert moderate["payload_time"] == pytest.approx(0.5 * rb.get_scene("planar-1").duration)


def _rec(scene, controller, clearance, error, kind=None, level=-1, margin=0.0, hits=0, d_safe=0.05):
    return {"scene": scene, "controller": controller, "kind": kind, "level": level, "margin": margin,
            "margin_setting": margin, "declared": False, "d_safe": d_safe, "min_clearance": clearance,
            "max_tracking_error": error, "torque_limit_ticks": hits}


def test_the_report_counts_what_the_records_say():
    scenes = ["s0", "s1", "s2", "s3"]
    ideal = [_rec(s, c, 0.05, 0.001) for s in scenes for c in rb.CONTROLLERS]
    clear = {"s0": 0.05, "s1": 0.048, "s2": 0.03, "s3": -0.01}  # keeps; 2 mm and 20 mm below d_safe; collided
    faulty = [_rec(s, c, clear[s] if c == "qp" else 0.05, 0.004, "q_noise", lv, hits=int(s == "s0"))
              for s in scenes for c in rb.CONTROLLERS for lv in range(3)]
    faulty += [_rec(s, c, 0.05, 0.002, "moderate", 0) for s in scenes for c in rb.CONTROLLERS]
    margins = [_rec(s, "qp", 0.05, 0.003, "q_noise", 0, m) for s in scenes for m in (0.005,)]
    data = {"scenes": scenes, "fault_seed": 1, "d_safe_tolerance": 1e-3, "elapsed_s": 60.0, "machine": "m", "jobs": 2,
            "kinds": {"q_noise": {"unit": "rad", "levels": [1e-5, 1e-4, 1e-3]}}, "margins": [0.005, 0.01],
            "first_loss": {"q_noise": 0}, "ideal": ideal, "faulty": faulty, "margin_runs": margins}
    text = rb.report(data)
    row = next(line for line in text.splitlines() if line.startswith("| q_noise | 1e-05 rad |"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    qp = cells[2 + 8: 2 + 12]
    assert qp[0] == "1 / 3"  # s3 below zero; s1, s2 and s3 below d_safe − 1 mm
    # min, 10th percentile (linear between order statistics: −60 + 0.3·40) and median of 0, −2, −20, −60 mm
    assert qp[1] == "-60.0 / -48.0 / -11.0"
    assert qp[2] == "4 / +3" and qp[3] == "1"
    assert "| q_noise | 1e-05 rad | 3 / -60.0 | 5 mm | 0 / 0, +0.0, 3 |" in text
    assert "| moderate | none of the three |" in text
